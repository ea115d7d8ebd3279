//! PLY (ASCII, binary little and big endian) through `ply-rs-bw`: the
//! `vertex` element's `x`, `y`, `z` and the `face` element's
//! `vertex_indices` (or `vertex_index`) list, polygons fan-triangulated, all
//! in one object.
//!
//! The header is parsed by ply-rs-bw; the payload is read one element at a
//! time (`read_ascii_element` / `read_*_endian_element`) rather than with
//! `read_payload`, so that (a) every error can name the ASCII line or the
//! binary element index, and (b) elements go straight into compact arrays
//! instead of one hash map per element. Any scalar type is accepted for the
//! coordinates (float and double usually) and any integer list type for the
//! indices. Other elements and properties (normals, colours, edges...) are
//! read and dropped. A file without a single triangle (a point cloud) is
//! rejected as unsupported.

use std::io::{BufRead, Cursor};
use std::path::Path;

use glam::Vec3;
use ply_rs_bw::parser::{ParseError, Parser};
use ply_rs_bw::ply::{
    ElementDef, Encoding, Property, PropertyAccess, PropertyAccessResult, PropertyType,
};
use rebraid::{ObjectDesc, SceneDesc, TriangleMesh};

use super::{LoadError, LoadOptions, Location, mesh_error};

/// Parse a PLY file from memory. `file` names the source in errors and
/// gives the object its name.
pub fn parse_ply(bytes: &[u8], file: &Path, _opts: &LoadOptions) -> Result<SceneDesc, LoadError> {
    let mut reader = ply_rs_bw::parser::Reader::new(Cursor::new(bytes));
    let parser = Parser::<Elem>::new();
    let header = parser
        .read_header(&mut reader)
        .map_err(|e| ply_error(file, e.line().map_or(Location::File, Location::Line), &e))?;

    let unsupported = |detail: String| LoadError::Unsupported {
        file: file.to_path_buf(),
        at: Location::File,
        detail,
    };
    let vertex_def = header
        .elements
        .get("vertex")
        .ok_or_else(|| unsupported("no `vertex` element".into()))?;
    for axis in ["x", "y", "z"] {
        match vertex_def.properties.get(axis).map(|p| &p.data_type) {
            Some(PropertyType::Scalar(_)) => {}
            Some(PropertyType::List(..)) => {
                return Err(unsupported(format!("vertex property `{axis}` is a list")));
            }
            None => {
                return Err(unsupported(format!(
                    "vertex element has no `{axis}` property"
                )));
            }
        }
    }
    let face_def = header
        .elements
        .get("face")
        .ok_or_else(|| unsupported("no `face` element (point clouds are not supported)".into()))?;
    let face_list = ["vertex_indices", "vertex_index"]
        .into_iter()
        .find(|n| {
            matches!(
                face_def.properties.get(*n).map(|p| &p.data_type),
                Some(PropertyType::List(..))
            )
        })
        .ok_or_else(|| unsupported("face element has no `vertex_indices` list".into()))?;
    let nv = vertex_def.count;
    if nv > u32::MAX as usize {
        return Err(unsupported(format!("{nv} vertices (at most 2^32 - 1)")));
    }

    // First payload line (ASCII): the line after `end_header`.
    let header_end = reader.get_ref().position() as usize;
    let mut line = bytes[..header_end.min(bytes.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count();

    // Reserve from the header's counts, but not blindly: a corrupt header
    // may claim billions of elements.
    let cap = |n: usize| n.min(1 << 20);
    let mut positions: Vec<Vec3> = Vec::with_capacity(cap(nv));
    let mut indices: Vec<[u32; 3]> = Vec::with_capacity(cap(face_def.count.saturating_mul(2)));
    let mut text = String::new();

    for (name, def) in &header.elements {
        // A binary element without properties occupies no bytes: skip it
        // rather than loop over a count that may be in the billions.
        if def.properties.is_empty() && header.encoding != Encoding::Ascii {
            continue;
        }
        for i in 0..def.count {
            line += 1;
            let at = || match header.encoding {
                Encoding::Ascii => Location::Line(line),
                _ => Location::Element(format!("element `{name}` {i}")),
            };
            let elem = match header.encoding {
                Encoding::Ascii => {
                    text.clear();
                    let n =
                        reader
                            .get_mut()
                            .read_line(&mut text)
                            .map_err(|e| LoadError::Syntax {
                                file: file.to_path_buf(),
                                at: at(),
                                detail: format!("not text: {e}"),
                            })?;
                    if n == 0 {
                        return Err(truncated(file, at(), name, i, def));
                    }
                    parser.read_ascii_element(&text, def)
                }
                Encoding::BinaryLittleEndian => {
                    parser.read_little_endian_element(reader.get_mut(), def)
                }
                Encoding::BinaryBigEndian => parser.read_big_endian_element(reader.get_mut(), def),
            };
            let elem = match elem {
                Ok(e) => e,
                Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => {
                    return Err(truncated(file, at(), name, i, def));
                }
                Err(e) => return Err(ply_error(file, at(), &e)),
            };
            if std::ptr::eq(def, vertex_def) {
                let p = Vec3::from_array(elem.xyz.map(|c| c as f32));
                if !p.is_finite() {
                    return Err(LoadError::NonFinite {
                        file: file.to_path_buf(),
                        at: at(),
                        detail: format!("vertex {i} is {:?}", elem.xyz),
                    });
                }
                if p.abs().max_element() > rebraid::mesh::MAX_COORDINATE {
                    return Err(LoadError::OutOfRange {
                        file: file.to_path_buf(),
                        at: at(),
                        detail: format!(
                            "vertex {i} ({:?}) is beyond +-{}",
                            elem.xyz,
                            rebraid::mesh::MAX_COORDINATE
                        ),
                    });
                }
                positions.push(p);
            } else if std::ptr::eq(def, face_def) {
                let list = elem.list.ok_or_else(|| LoadError::Unsupported {
                    file: file.to_path_buf(),
                    at: at(),
                    detail: format!("face `{face_list}` must be a list of integers"),
                })?;
                let bad = |detail: String| LoadError::BadIndex {
                    file: file.to_path_buf(),
                    at: at(),
                    detail,
                };
                if list.len() < 3 {
                    return Err(bad(format!(
                        "face {i} has {} vertices, needs at least 3",
                        list.len()
                    )));
                }
                if let Some(&v) = list.iter().find(|&&v| v < 0 || v as u64 >= nv as u64) {
                    return Err(bad(format!(
                        "face {i} references vertex {v}, but there are {nv} vertices"
                    )));
                }
                for w in 1..list.len() - 1 {
                    indices.push([list[0] as u32, list[w] as u32, list[w + 1] as u32]);
                }
            }
        }
    }

    if indices.is_empty() {
        return Err(unsupported("no triangle faces".into()));
    }
    let name = file
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mesh =
        TriangleMesh::new(positions, indices).map_err(|e| mesh_error(file, Location::File, e))?;
    Ok(SceneDesc {
        objects: vec![ObjectDesc {
            name,
            mesh,
            placed: true,
        }],
        instances: Vec::new(),
    })
}

fn truncated(file: &Path, at: Location, name: &str, i: usize, def: &ElementDef) -> LoadError {
    LoadError::Truncated {
        file: file.to_path_buf(),
        at,
        detail: format!("element `{name}` {i} of {} is missing", def.count),
    }
}

fn ply_error(file: &Path, at: Location, e: &ParseError) -> LoadError {
    // ply-rs-bw's messages embed the offending line after a newline and a
    // tab; keep them on one line.
    let detail = e
        .to_string()
        .split_whitespace()
        .collect::<Vec<_>>()
        .join(" ");
    let file = file.to_path_buf();
    if e.kind() == std::io::ErrorKind::UnexpectedEof {
        LoadError::Truncated { file, at, detail }
    } else {
        LoadError::Syntax { file, at, detail }
    }
}

/// One payload element, keeping only what a triangle mesh needs. The same
/// type serves every element kind (ply-rs-bw's parser has one element type):
/// the caller knows which fields are meaningful.
#[derive(Default)]
struct Elem {
    xyz: [f64; 3],
    /// `vertex_indices`; `None` when absent or not made of integers.
    list: Option<Vec<i64>>,
}

impl PropertyAccess for Elem {
    fn new() -> Self {
        Self::default()
    }

    fn set_property(&mut self, name: &str, p: Property) -> PropertyAccessResult {
        let axis = match name {
            "x" => Some(0),
            "y" => Some(1),
            "z" => Some(2),
            _ => None,
        };
        if let Some(a) = axis {
            self.xyz[a] = match p {
                Property::Char(v) => v.into(),
                Property::UChar(v) => v.into(),
                Property::Short(v) => v.into(),
                Property::UShort(v) => v.into(),
                Property::Int(v) => v.into(),
                Property::UInt(v) => v.into(),
                Property::Float(v) => v.into(),
                Property::Double(v) => v,
                _ => return PropertyAccessResult::Ignored,
            };
            return PropertyAccessResult::Set;
        }
        if name == "vertex_indices" || name == "vertex_index" {
            self.list = match p {
                Property::ListChar(v) => Some(v.into_iter().map(i64::from).collect()),
                Property::ListUChar(v) => Some(v.into_iter().map(i64::from).collect()),
                Property::ListShort(v) => Some(v.into_iter().map(i64::from).collect()),
                Property::ListUShort(v) => Some(v.into_iter().map(i64::from).collect()),
                Property::ListInt(v) => Some(v.into_iter().map(i64::from).collect()),
                Property::ListUInt(v) => Some(v.into_iter().map(i64::from).collect()),
                _ => None,
            };
            return PropertyAccessResult::Set;
        }
        PropertyAccessResult::Ignored
    }
}
