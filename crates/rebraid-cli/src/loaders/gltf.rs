//! glTF 2.0 (`.gltf` with embedded or external buffers, `.glb`) through the
//! `gltf` crate: meshes become objects, nodes that place them become
//! instances carrying their world transforms.
//!
//! - One object per mesh (primitives merged), or one per primitive with
//!   [`Split::Material`] (glTF has one primitive per material). Objects are
//!   `placed: false`: they are seen only through instances.
//! - Every node reachable from any scene's root nodes (or, in a file without
//!   scenes, every node that is no other node's child) that has a mesh gives
//!   one instance per object of that mesh, with the composed transform of the
//!   whole node chain (non-uniform scale allowed).
//! - [`LoadOptions::flatten_instances`] bakes each placement instead into a
//!   `placed: true` object of world-space triangles.
//! - Triangle strips and fans are converted to triangles; points and lines
//!   are skipped and counted in the warnings, and so are placements with a
//!   singular (zero-scale) transform, which show nothing.
//!
//! Accessors are read by hand, not with `gltf`'s reader: the reader trusts
//! counts, strides and offsets (it subtracts 1 from the count and
//! debug-asserts on strides), so a malformed file could panic; here every
//! range is checked and reported as a [`LoadError`] naming the mesh and
//! primitive. Images are never decoded.

use std::path::Path;

use ::gltf::accessor::{DataType, Dimensions};
use ::gltf::mesh::Mode;
use glam::{Affine3A, Mat4, Vec3};
use rebraid::{InstanceDesc, ObjectDesc, SceneDesc, TriangleMesh};

use super::{LoadError, LoadOptions, Loaded, Location, Split, mesh_error};

/// Parse a glTF or GLB file from memory. External buffer files are resolved
/// against `base_dir` (usually the file's directory); with `None`, only GLB
/// binary chunks and `data:` URIs work.
pub fn parse_gltf(
    bytes: &[u8],
    file: &Path,
    base_dir: Option<&Path>,
    opts: &LoadOptions,
) -> Result<Loaded, LoadError> {
    let whole = |detail: String| LoadError::Syntax {
        file: file.to_path_buf(),
        at: Location::File,
        detail,
    };
    // `gltf` computes `length - 12` on the GLB header without checking it.
    if bytes.starts_with(b"glTF") {
        let len = bytes
            .get(8..12)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
        match len {
            Some(l) if l < 12 => return Err(whole(format!("GLB header declares {l} bytes"))),
            Some(l) if l <= bytes.len() => {}
            _ => {
                return Err(LoadError::Truncated {
                    file: file.to_path_buf(),
                    at: Location::File,
                    detail: format!(
                        "GLB header declares {len:?} bytes, file has {}",
                        bytes.len()
                    ),
                });
            }
        }
    }
    // Parsed unchecked, then checked by `Document::from_json` once the
    // indices its validation trusts are known to be in range (see
    // `check_position_accessors`).
    let unchecked = ::gltf::Gltf::from_slice_without_validation(bytes)
        .map_err(|e| whole(format!("not valid glTF: {e}")))?;
    let blob = unchecked.blob;
    let root = unchecked.document.into_json();
    check_position_accessors(&root, file)?;
    let doc =
        ::gltf::Document::from_json(root).map_err(|e| whole(format!("not valid glTF: {e}")))?;
    let buffers = ::gltf::import_buffers(&doc, base_dir, blob).map_err(|e| match e {
        ::gltf::Error::BufferLength { .. } => LoadError::Truncated {
            file: file.to_path_buf(),
            at: Location::File,
            detail: e.to_string(),
        },
        _ => LoadError::Unsupported {
            file: file.to_path_buf(),
            at: Location::File,
            detail: format!("cannot load buffers: {e}"),
        },
    })?;
    let mut warnings = Vec::new();

    // Objects: one per mesh or per primitive; `mesh_objects[m]` lists the
    // object ids of mesh m (empty primitives and meshes give none).
    let mut objects: Vec<ObjectDesc> = Vec::new();
    let mut mesh_objects: Vec<Vec<u32>> = Vec::new();
    for mesh in doc.meshes() {
        let mesh_name = mesh
            .name()
            .map_or_else(|| format!("mesh {}", mesh.index()), str::to_owned);
        let mut ids = Vec::new();
        let mut merged = TriangleMesh::default();
        for prim in mesh.primitives() {
            let at = || {
                Location::Element(format!(
                    "mesh {} ({mesh_name:?}) primitive {}",
                    mesh.index(),
                    prim.index()
                ))
            };
            let Some(part) = read_primitive(&prim, &buffers)
                .map_err(|(kind, detail)| kind.make(file, at(), detail))?
            else {
                warnings.push(format!(
                    "mesh {} ({mesh_name:?}) primitive {}: {:?} primitive skipped (not triangles)",
                    mesh.index(),
                    prim.index(),
                    prim.mode()
                ));
                continue;
            };
            if part.is_empty() {
                continue;
            }
            if opts.split == Split::Material {
                let mat = prim.material();
                let mat_name = mat
                    .name()
                    .map(str::to_owned)
                    .or_else(|| mat.index().map(|i| format!("material {i}")))
                    .unwrap_or_else(|| "default".into());
                ids.push(objects.len() as u32);
                objects.push(ObjectDesc {
                    name: format!("{mesh_name}/{mat_name}"),
                    mesh: part,
                    placed: false,
                });
            } else {
                let base = merged.positions.len() as u32;
                merged.positions.extend_from_slice(&part.positions);
                merged
                    .indices
                    .extend(part.indices.iter().map(|t| t.map(|v| v + base)));
            }
        }
        if !merged.is_empty() {
            ids.push(objects.len() as u32);
            objects.push(ObjectDesc {
                name: mesh_name,
                mesh: merged,
                placed: false,
            });
        }
        mesh_objects.push(ids);
    }

    let placements = placements(&doc, file)?;
    let mut instances = Vec::new();
    let mut flat = Vec::new();
    for (node, world) in placements {
        let Some(mesh) = node.mesh() else { continue };
        let node_name = node
            .name()
            .map_or_else(|| format!("node {}", node.index()), str::to_owned);
        let at = || Location::Element(format!("node {} ({node_name:?})", node.index()));
        if !world.is_finite() {
            return Err(LoadError::NonFinite {
                file: file.to_path_buf(),
                at: at(),
                detail: "world transform has a non-finite entry".into(),
            });
        }
        if rebraid::transform::check_transform(&world).is_err() {
            warnings.push(format!(
                "node {} ({node_name:?}): singular world transform, placement skipped",
                node.index()
            ));
            continue;
        }
        for &obj in mesh_objects
            .get(mesh.index())
            .map_or(&[][..], |v| v.as_slice())
        {
            if opts.flatten_instances {
                let src = &objects[obj as usize];
                let positions = src
                    .mesh
                    .positions
                    .iter()
                    .map(|&p| world.transform_point3(p))
                    .collect();
                let mesh = TriangleMesh::new(positions, src.mesh.indices.clone())
                    .map_err(|e| mesh_error(file, at(), e))?;
                flat.push(ObjectDesc {
                    name: format!("{node_name}/{}", src.name),
                    mesh,
                    placed: true,
                });
            } else {
                instances.push(InstanceDesc {
                    name: node_name.clone(),
                    object: obj,
                    transform: world,
                });
            }
        }
    }
    let scene = if opts.flatten_instances {
        SceneDesc {
            objects: flat,
            instances: Vec::new(),
        }
    } else {
        SceneDesc { objects, instances }
    };
    Ok(Loaded { scene, warnings })
}

/// Every primitive's `POSITION` accessor index is in range. `gltf-json`
/// 1.4's validation reads that accessor (for its `min` and `max`) by
/// indexing before it checks the index, so a file naming an accessor past
/// the array would panic there instead of failing (found by the fuzz smoke
/// test, `tests/loader_fuzz.rs`); every other index it checks itself.
fn check_position_accessors(root: &::gltf::json::Root, file: &Path) -> Result<(), LoadError> {
    use ::gltf::json::mesh::Semantic;
    use ::gltf::json::validation::Checked;
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            let Some(a) = prim.attributes.get(&Checked::Valid(Semantic::Positions)) else {
                continue;
            };
            if a.value() >= root.accessors.len() {
                return Err(LoadError::BadIndex {
                    file: file.to_path_buf(),
                    at: Location::Element(format!("mesh {m} primitive {p}")),
                    detail: format!(
                        "POSITION names accessor {} of {}",
                        a.value(),
                        root.accessors.len()
                    ),
                });
            }
        }
    }
    Ok(())
}

/// Every node reachable from the roots, with its world transform, in
/// depth-first order. Roots: all scenes' root nodes (each once), or when the
/// file has no scene, every node that is no node's child.
fn placements<'a>(
    doc: &'a ::gltf::Document,
    file: &Path,
) -> Result<Vec<(::gltf::Node<'a>, Affine3A)>, LoadError> {
    let node_count = doc.nodes().len();
    let mut is_root = vec![false; node_count];
    let mut roots = Vec::new();
    if doc.scenes().len() > 0 {
        for scene in doc.scenes() {
            for n in scene.nodes() {
                if !std::mem::replace(&mut is_root[n.index()], true) {
                    roots.push(n);
                }
            }
        }
    } else {
        let mut is_child = vec![false; node_count];
        for n in doc.nodes() {
            for c in n.children() {
                is_child[c.index()] = true;
            }
        }
        roots.extend(doc.nodes().filter(|n| !is_child[n.index()]));
    }

    // A valid glTF node graph is a forest. Guard against cycles (a path
    // longer than the node count) and against a DAG exploding exponentially.
    const MAX_VISITS: usize = 1 << 24;
    let mut out = Vec::new();
    let mut stack: Vec<(::gltf::Node<'a>, Affine3A, usize)> = roots
        .into_iter()
        .rev()
        .map(|n| (n, Affine3A::IDENTITY, 1))
        .collect();
    while let Some((node, parent, depth)) = stack.pop() {
        let at = || Location::Element(format!("node {}", node.index()));
        if depth > node_count || out.len() >= MAX_VISITS {
            return Err(LoadError::Unsupported {
                file: file.to_path_buf(),
                at: at(),
                detail: "node hierarchy has a cycle or too many placements".into(),
            });
        }
        let local = Affine3A::from_mat4(Mat4::from_cols_array_2d(&node.transform().matrix()));
        let world = parent * local;
        let children: Vec<_> = node.children().collect();
        for c in children.into_iter().rev() {
            stack.push((c, world, depth + 1));
        }
        out.push((node, world));
    }
    Ok(out)
}

/// Error kinds of accessor reading, turned into a [`LoadError`] by the
/// caller, who knows the location.
#[derive(Clone, Copy, Debug)]
enum Kind {
    BadIndex,
    NonFinite,
    OutOfRange,
    Truncated,
    Unsupported,
}

impl Kind {
    fn make(self, file: &Path, at: Location, detail: String) -> LoadError {
        let file = file.to_path_buf();
        match self {
            Kind::BadIndex => LoadError::BadIndex { file, at, detail },
            Kind::NonFinite => LoadError::NonFinite { file, at, detail },
            Kind::OutOfRange => LoadError::OutOfRange { file, at, detail },
            Kind::Truncated => LoadError::Truncated { file, at, detail },
            Kind::Unsupported => LoadError::Unsupported { file, at, detail },
        }
    }
}

type AccResult<T> = Result<T, (Kind, String)>;

/// The triangles of one primitive, or `None` for a non-triangle mode.
fn read_primitive(
    prim: &::gltf::Primitive,
    buffers: &[::gltf::buffer::Data],
) -> AccResult<Option<TriangleMesh>> {
    if !matches!(
        prim.mode(),
        Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
    ) {
        return Ok(None);
    }
    let pos = prim.get(&::gltf::Semantic::Positions).ok_or((
        Kind::Unsupported,
        "primitive has no POSITION attribute".to_string(),
    ))?;
    if pos.data_type() != DataType::F32 || pos.dimensions() != Dimensions::Vec3 {
        return Err((
            Kind::Unsupported,
            format!(
                "POSITION is {:?} {:?}, only float VEC3 is supported",
                pos.data_type(),
                pos.dimensions()
            ),
        ));
    }
    let (data, stride, count) = accessor_bytes(&pos, buffers, 12)?;
    let mut positions = Vec::with_capacity(count);
    for i in 0..count {
        let b = &data[i * stride..i * stride + 12];
        let f = |k: usize| f32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]]);
        let p = Vec3::new(f(0), f(1), f(2));
        if !p.is_finite() {
            return Err((Kind::NonFinite, format!("POSITION {i} is not finite: {p}")));
        }
        if p.abs().max_element() > rebraid::mesh::MAX_COORDINATE {
            return Err((
                Kind::OutOfRange,
                format!(
                    "POSITION {i} ({p}) is beyond +-{}",
                    rebraid::mesh::MAX_COORDINATE
                ),
            ));
        }
        positions.push(p);
    }

    let order: Vec<u32> = match prim.indices() {
        None => (0..count as u32).collect(),
        Some(acc) => {
            if acc.dimensions() != Dimensions::Scalar {
                return Err((
                    Kind::Unsupported,
                    format!("indices are {:?}", acc.dimensions()),
                ));
            }
            let size = match acc.data_type() {
                DataType::U8 => 1,
                DataType::U16 => 2,
                DataType::U32 => 4,
                t => return Err((Kind::Unsupported, format!("indices of type {t:?}"))),
            };
            let (data, stride, n) = accessor_bytes(&acc, buffers, size)?;
            let mut out = Vec::with_capacity(n);
            for i in 0..n {
                let b = &data[i * stride..];
                let v = match size {
                    1 => u32::from(b[0]),
                    2 => u32::from(u16::from_le_bytes([b[0], b[1]])),
                    _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                };
                if v as usize >= count {
                    return Err((
                        Kind::BadIndex,
                        format!("index {i} is {v}, but there are {count} positions"),
                    ));
                }
                out.push(v);
            }
            out
        }
    };

    let n = order.len();
    let indices: Vec<[u32; 3]> = match prim.mode() {
        Mode::TriangleStrip => (0..n.saturating_sub(2))
            .map(|i| {
                if i % 2 == 0 {
                    [order[i], order[i + 1], order[i + 2]]
                } else {
                    [order[i + 1], order[i], order[i + 2]]
                }
            })
            .collect(),
        Mode::TriangleFan => (1..n.saturating_sub(1))
            .map(|i| [order[0], order[i], order[i + 1]])
            .collect(),
        _ => order.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
    };
    // Indices are checked above and positions are finite, so this holds.
    TriangleMesh::new(positions, indices)
        .map(Some)
        .map_err(|e| (Kind::Unsupported, e.to_string()))
}

/// The bytes an accessor covers, its stride and its count, after checking
/// that every element lies inside its buffer view and the view inside its
/// buffer. `elem` is the size of one element in bytes.
fn accessor_bytes<'b>(
    acc: &::gltf::Accessor,
    buffers: &'b [::gltf::buffer::Data],
    elem: usize,
) -> AccResult<(&'b [u8], usize, usize)> {
    let name = format!("accessor {}", acc.index());
    if acc.sparse().is_some() {
        return Err((Kind::Unsupported, format!("{name} is sparse")));
    }
    let count = acc.count();
    if count == 0 {
        return Ok((&[], elem, 0));
    }
    let view = acc
        .view()
        .ok_or((Kind::Unsupported, format!("{name} has no buffer view")))?;
    let stride = view.stride().unwrap_or(elem);
    if stride < elem {
        return Err((
            Kind::Unsupported,
            format!("{name}: stride {stride} < element size {elem}"),
        ));
    }
    let data = buffers
        .get(view.buffer().index())
        .map(|d| &d.0[..])
        .ok_or((Kind::Unsupported, format!("{name}: missing buffer")))?;
    let view_end = view.offset().checked_add(view.length());
    let view_bytes = view_end
        .and_then(|end| data.get(view.offset()..end))
        .ok_or((
            Kind::Truncated,
            format!("buffer view {} lies outside its buffer", view.index()),
        ))?;
    let end = (count - 1)
        .checked_mul(stride)
        .and_then(|x| x.checked_add(elem))
        .and_then(|x| x.checked_add(acc.offset()));
    let bytes = end
        .and_then(|end| view_bytes.get(acc.offset()..end))
        .ok_or((
            Kind::Truncated,
            format!("{name} reaches past its buffer view"),
        ))?;
    Ok((bytes, stride, count))
}
