//! Loader tests: the real third-party scenes of `shared/scenes` (counts from
//! its README), small files written here into a temporary directory, and
//! malformed files, each error checked to name the file and the line or
//! element.

#[path = "../../rebraid/tests/support/scenes.rs"]
mod scenes;
mod support;

use std::path::{Path, PathBuf};
use std::time::Instant;

use rebraid::SceneDesc;
use rebraid_cli::loaders::{
    LoadError, LoadOptions, Location, Split, load_scene, load_scene_with_warnings,
};
use support::gltf::{QUAD, glb, glb_buffer, tiny_gltf_json};

/// The split alone: OBJ objects that touch are kept apart.
fn opts(split: Split, flatten_instances: bool) -> LoadOptions {
    LoadOptions {
        split,
        flatten_instances,
        keep_touching_apart: true,
    }
}

fn timed_load(path: &Path, o: &LoadOptions) -> SceneDesc {
    let t = Instant::now();
    let s = load_scene(path, o).unwrap_or_else(|e| panic!("{e}"));
    eprintln!(
        "{} ({:?}, flatten {}): {:.1} ms, {} objects, {} instances, {} world / {} unique triangles, overlap {:.2}",
        path.file_name().unwrap().to_string_lossy(),
        o.split,
        o.flatten_instances,
        t.elapsed().as_secs_f64() * 1e3,
        s.objects.len(),
        s.instances.len(),
        s.world_triangles(),
        s.unique_triangles(),
        s.overlap_ratio()
    );
    s.validate().unwrap();
    s
}

#[test]
fn real_obj_scenes_match_the_readme() {
    let Some(dir) = scenes::scenes_dir_or_skip() else {
        return;
    };
    // (file, `o` objects, objects once those that touch are joined,
    // triangles, overlap of the `o` objects)
    for (file, objects, joined, tris, overlap) in [
        ("samurai_monastery.obj", 81, 51, 124_789, 5.2),
        ("nexuiz_ons_reborn.obj", 114, 28, 125_101, 21.8),
        ("openarena_oa_thor.obj", 51, 11, 57_743, 9.6),
    ] {
        let default = timed_load(&dir.join(file), &LoadOptions::default());
        assert_eq!(default.objects.len(), joined, "{file}");
        assert_eq!(default.world_triangles(), tris, "{file}");
        let s = timed_load(&dir.join(file), &opts(Split::Object, false));
        assert_eq!(s.objects.len(), objects, "{file}");
        assert_eq!(s.world_triangles(), tris, "{file}");
        assert!(s.instances.is_empty());
        assert!(s.objects.iter().all(|o| o.placed));
        assert!(
            (s.overlap_ratio() - overlap).abs() < 0.1,
            "{file}: overlap {}",
            s.overlap_ratio()
        );
        // Same triangles whatever the split.
        let one = timed_load(&dir.join(file), &opts(Split::None, false));
        assert_eq!(one.objects.len(), 1);
        assert_eq!(one.world_triangles(), tris);
    }
}

#[test]
fn real_glb_scenes_match_the_readme() {
    let Some(dir) = scenes::scenes_dir_or_skip() else {
        return;
    };
    // (file, meshes, mesh nodes, (node, material) pairs, world tris, unique tris)
    for (file, meshes, nodes, pairs, world, unique) in [
        ("stk_cocoa_temple.glb", 59, 1_485, 2_482, 462_347, 110_015),
        (
            "stk_ravenbridge_mansion.glb",
            56,
            513,
            768,
            274_892,
            138_137,
        ),
        ("2CylinderEngine.glb", 29, 67, 0, 121_496, 0),
    ] {
        let path = dir.join(file);
        let s = timed_load(&path, &LoadOptions::default());
        assert_eq!(s.objects.len(), meshes, "{file}");
        assert_eq!(s.instances.len(), nodes, "{file}");
        assert_eq!(s.world_triangles(), world, "{file}");
        if unique > 0 {
            assert_eq!(s.unique_triangles(), unique, "{file}");
        }
        assert!(s.objects.iter().all(|o| !o.placed));

        let m = timed_load(&path, &opts(Split::Material, false));
        if pairs > 0 {
            assert_eq!(m.instances.len(), pairs, "{file}");
        }
        assert_eq!(m.world_triangles(), world, "{file}");

        let flat = timed_load(&path, &opts(Split::Object, true));
        assert_eq!(flat.objects.len(), nodes, "{file}");
        assert!(flat.instances.is_empty() && flat.objects.iter().all(|o| o.placed));
        assert_eq!(flat.world_triangles(), world, "{file}");
        // Baking the transforms must give the same world geometry: compare
        // the exact bounds of the transformed vertices.
        let exact = s.instances.iter().fold(rebraid::Aabb::EMPTY, |b, i| {
            let o = &s.objects[i.object as usize];
            o.mesh
                .positions
                .iter()
                .fold(b, |b, &p| b.grow(i.transform.transform_point3(p)))
        });
        let (_, flat_box) = flat.world_boxes();
        let tol = 1e-4 * exact.extent().max_element();
        assert!(
            (exact.min - flat_box.min).abs().max_element() < tol,
            "{file}"
        );
        assert!(
            (exact.max - flat_box.max).abs().max_element() < tol,
            "{file}"
        );
    }
}

// ---------------------------------------------------------------------------
// Small files written by the tests.

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

fn names(s: &SceneDesc) -> Vec<(&str, usize)> {
    s.objects
        .iter()
        .map(|o| (o.name.as_str(), o.mesh.len()))
        .collect()
}

#[test]
fn obj_quads_negative_indices_and_vertex_forms() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(
        dir.path(),
        "quads.obj",
        b"# a quad, a pentagon and relative indices\r\n\
          v 0 0 0\r\nv 1 0 0 1.0\r\nv 1 1 0\r\nv 0 1 0 0.5 0.5 0.5\r\nv 0.5 2 0\r\n\
          vt 0 0\nvn 0 0 1\n\
          f 1 2 3 4\n\
          f 1/1/1 2/1/1 3//1 5 4  # pentagon\n\
          f -5 -4 -3\n\
          s off\nl 1 2\n",
    );
    let s = load_scene(&p, &LoadOptions::default()).unwrap();
    assert_eq!(names(&s), vec![("quads", 2 + 3 + 1)]);
    let m = &s.objects[0].mesh;
    assert_eq!(m.positions.len(), 5);
    assert_eq!(m.indices[0], [0, 1, 2]);
    assert_eq!(m.indices[1], [0, 2, 3]);
    assert_eq!(m.triangle(5), m.triangle(0));
}

const SPLITS_OBJ: &[u8] = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n\
    o A\ng g1\nusemtl red\nf 1 2 3\nf 1 2 4\n\
    o B\ng g2\nusemtl blue\nf 1 3 4\n\
    usemtl red\nf 2 3 4\n\
    g g1\nf 1 2 3\n";

#[test]
fn obj_splits_by_object_group_material_or_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(dir.path(), "splits.obj", SPLITS_OBJ);
    let load = |split| load_scene(&p, &opts(split, false)).unwrap();
    assert_eq!(names(&load(Split::Object)), vec![("A", 2), ("B", 3)]);
    assert_eq!(names(&load(Split::Group)), vec![("g1", 3), ("g2", 2)]);
    assert_eq!(names(&load(Split::Material)), vec![("red", 4), ("blue", 1)]);
    assert_eq!(names(&load(Split::None)), vec![("splits", 5)]);
    // Indented statements name their objects as unindented ones do.
    let indented: Vec<u8> = SPLITS_OBJ
        .split(|&b| b == b'\n')
        .flat_map(|l| [b" \t".as_slice(), l, b"\n"].concat())
        .collect();
    let q = write(dir.path(), "indented.obj", &indented);
    let s = load_scene(&q, &opts(Split::Object, false)).unwrap();
    assert_eq!(names(&s), vec![("A", 2), ("B", 3)]);
    // Each object gets only the vertices it uses.
    let b = &load(Split::Object).objects[1];
    assert_eq!(b.mesh.positions.len(), 4);
    assert!(load(Split::Object).objects.iter().all(|o| o.placed));
}

#[test]
fn obj_with_one_object_falls_back_to_materials() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(
        dir.path(),
        "one.obj",
        b"o only\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl a\nf 1 2 3\nusemtl b\nf 3 2 1\nf 1 3 2\n",
    );
    let s = load_scene(&p, &opts(Split::Object, false)).unwrap();
    assert_eq!(names(&s), vec![("a", 1), ("b", 2)]);
    let s = load_scene(&p, &opts(Split::Group, false)).unwrap();
    assert_eq!(names(&s), vec![("one", 3)]);
    // By default the two materials, which share vertices, are one object.
    let s = load_scene(&p, &LoadOptions::default()).unwrap();
    assert_eq!(names(&s), vec![("a", 3)]);
}

/// Objects A, B, C, D, E: B repeats one of A's positions under its own
/// vertex (as exporters write the two sides of a cut), D one of B's at
/// `-0.0` where B has `0.0`, C only comes near A (another position, no
/// shared one), and E shares A's vertex indices (the same `v` lines).
const TOUCHING_OBJ: &[u8] = b"o A\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n\
    o B\nv 1 0 0\nv 2 0 0\nv 2 1 0\nf 4 5 6\n\
    o C\nv 0 0 0.001\nv -1 0 0\nv 0 -1 0\nf 7 8 9\n\
    o D\nv 2 1 -0\nv 3 1 0\nv 3 2 0\nf 10 11 12\nf 12 11 10\n\
    o E\nf 1 3 2\n";

#[test]
fn obj_objects_that_touch_are_joined() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(dir.path(), "touching.obj", TOUCHING_OBJ);
    let apart = load_scene(&p, &opts(Split::Object, false)).unwrap();
    assert_eq!(
        names(&apart),
        vec![("A", 1), ("B", 1), ("C", 1), ("D", 2), ("E", 1)]
    );
    // A, B, D and E are one set (D through B), named after its first
    // object; C stays apart. The sets keep their first objects' order.
    let joined = load_scene(&p, &LoadOptions::default()).unwrap();
    assert_eq!(names(&joined), vec![("A", 5), ("C", 1)]);
    // The same triangles, in the members' order, with the members'
    // vertices (the duplicated positions stay separate vertices).
    let a = &joined.objects[0].mesh;
    let want: Vec<[rebraid::glam::Vec3; 3]> = [0, 1, 3, 4]
        .iter()
        .flat_map(|&o| {
            let m = &apart.objects[o].mesh;
            (0..m.len()).map(|t| m.triangle(t)).collect::<Vec<_>>()
        })
        .collect();
    assert_eq!(
        (0..a.len()).map(|t| a.triangle(t)).collect::<Vec<_>>(),
        want
    );
    assert_eq!(a.positions.len(), 3 + 3 + 3);
    assert!(joined.objects.iter().all(|o| o.placed));
    joined.validate().unwrap();
    // Every split joins the same way; without a split there is one object.
    let groups = load_scene(
        &p,
        &LoadOptions {
            split: Split::Group,
            ..LoadOptions::default()
        },
    )
    .unwrap();
    assert_eq!(names(&groups), vec![("touching", 6)]);
}

/// A unit cube as a PLY header (after the format line) and its elements.
const CUBE_VERTS: [[f64; 3]; 8] = [
    [0., 0., 0.],
    [1., 0., 0.],
    [1., 1., 0.],
    [0., 1., 0.],
    [0., 0., 1.],
    [1., 0., 1.],
    [1., 1., 1.],
    [0., 1., 1.],
];
const CUBE_QUADS: [[u32; 4]; 6] = [
    [0, 3, 2, 1],
    [4, 5, 6, 7],
    [0, 1, 5, 4],
    [1, 2, 6, 5],
    [2, 3, 7, 6],
    [3, 0, 4, 7],
];

fn cube_ascii_ply() -> String {
    let mut s = String::from(
        "ply\nformat ascii 1.0\ncomment a cube\nelement vertex 8\nproperty double x\nproperty double y\nproperty double z\n\
         property uchar red\nelement face 6\nproperty list uchar int vertex_indices\nend_header\n",
    );
    for v in CUBE_VERTS {
        s += &format!("{} {} {} 255\n", v[0], v[1], v[2]);
    }
    for f in CUBE_QUADS {
        s += &format!("4 {} {} {} {}\n", f[0], f[1], f[2], f[3]);
    }
    s
}

fn cube_binary_ply(big_endian: bool) -> Vec<u8> {
    let fmt = if big_endian {
        "binary_big_endian"
    } else {
        "binary_little_endian"
    };
    let mut b = format!(
        "ply\nformat {fmt} 1.0\nelement vertex 8\nproperty float x\nproperty float y\nproperty float z\n\
         element face 6\nproperty uchar flags\nproperty list ushort uint vertex_index\nend_header\n"
    )
    .into_bytes();
    let f32b = |v: f32| {
        if big_endian {
            v.to_be_bytes()
        } else {
            v.to_le_bytes()
        }
    };
    let u32b = |v: u32| {
        if big_endian {
            v.to_be_bytes()
        } else {
            v.to_le_bytes()
        }
    };
    let u16b = |v: u16| {
        if big_endian {
            v.to_be_bytes()
        } else {
            v.to_le_bytes()
        }
    };
    for v in CUBE_VERTS {
        for c in v {
            b.extend(f32b(c as f32));
        }
    }
    for f in CUBE_QUADS {
        b.push(7);
        b.extend(u16b(4));
        for i in f {
            b.extend(u32b(i));
        }
    }
    b
}

#[test]
fn ply_ascii_and_binary_cubes() {
    let dir = tempfile::tempdir().unwrap();
    let files = [
        write(dir.path(), "cube_ascii.ply", cube_ascii_ply().as_bytes()),
        write(dir.path(), "cube_le.ply", &cube_binary_ply(false)),
        write(dir.path(), "cube_be.PLY", &cube_binary_ply(true)),
    ];
    let mut meshes = Vec::new();
    for p in &files {
        let s = load_scene(p, &LoadOptions::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(s.objects.len(), 1);
        assert_eq!(s.world_triangles(), 12);
        assert_eq!(s.objects[0].mesh.positions.len(), 8);
        assert!((s.overlap_ratio() - 1.0).abs() < 1e-6);
        meshes.push(s.objects[0].mesh.clone());
    }
    assert_eq!(meshes[0], meshes[1]);
    assert_eq!(meshes[1], meshes[2]);
    assert_eq!(meshes[0].indices[0], [0, 3, 2]);
    assert_eq!(meshes[0].indices[1], [0, 2, 1]);
}

#[test]
fn glb_node_hierarchy_instances_and_flattening() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = glb(
        &tiny_gltf_json(3, "", "[0, 0, 0]"),
        &glb_buffer(&QUAD, [0, 1, 2]),
    );
    let p = write(dir.path(), "tiny.glb", &bytes);
    let loaded =
        load_scene_with_warnings(&p, &LoadOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    let s = &loaded.scene;
    assert_eq!(names(s), vec![("tri", 1), ("strip", 2)]);
    assert!(s.objects.iter().all(|o| !o.placed));
    assert_eq!(s.instances.len(), 2, "the orphan node is in no scene");
    assert_eq!(loaded.warnings.len(), 1, "{:?}", loaded.warnings);
    assert!(
        loaded.warnings[0].contains("primitive 1"),
        "{:?}",
        loaded.warnings
    );
    let i0 = &s.instances[0];
    assert_eq!((i0.name.as_str(), i0.object), ("stretched", 0));
    assert!(
        (i0.transform.transform_point3(glam::Vec3::X) - glam::Vec3::new(12.0, 0.0, 0.0)).length()
            < 1e-5
    );
    let i1 = &s.instances[1];
    assert_eq!((i1.name.as_str(), i1.object), ("lifted", 1));
    // root * turned * lifted: (0,0,0) -> (0,5,0) -> (-5,0,0) -> (5,0,0).
    assert!(
        (i1.transform.transform_point3(glam::Vec3::ZERO) - glam::Vec3::new(5.0, 0.0, 0.0)).length()
            < 1e-5
    );
    // Strip winding alternates: (0,1,2), (2,1,3).
    assert_eq!(s.objects[1].mesh.indices, vec![[0, 1, 2], [2, 1, 3]]);
    assert_eq!(s.world_triangles(), 3);

    let flat = load_scene(&p, &opts(Split::Object, true)).unwrap();
    assert_eq!(flat.objects.len(), 2);
    assert!(flat.instances.is_empty() && flat.objects.iter().all(|o| o.placed));
    assert!((flat.objects[1].mesh.positions[0] - glam::Vec3::new(5.0, 0.0, 0.0)).length() < 1e-5);

    let per_prim = load_scene(&p, &opts(Split::Material, false)).unwrap();
    assert_eq!(names(&per_prim), vec![("tri/steel", 1), ("strip/brass", 2)]);
}

// ---------------------------------------------------------------------------
// Malformed files: the right error kind, naming the file and the line or
// element.

/// Load `bytes` saved as `name` and expect an error whose message contains
/// the file name and every one of `needles`.
fn load_err(name: &str, bytes: &[u8], needles: &[&str]) -> LoadError {
    let dir = tempfile::tempdir().unwrap();
    let p = write(dir.path(), name, bytes);
    let e = load_scene(&p, &LoadOptions::default()).expect_err(name);
    let msg = e.to_string();
    assert!(msg.contains(name), "{msg:?} does not name {name}");
    for n in needles {
        assert!(msg.contains(n), "{msg:?} does not contain {n:?}");
    }
    assert_eq!(e.file(), p);
    e
}

#[test]
fn unknown_extension_and_missing_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(dir.path(), "scene.stl", b"solid");
    let e = load_scene(&p, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, LoadError::UnknownExtension { .. }), "{e}");
    assert!(e.to_string().contains("scene.stl") && e.to_string().contains("stl"));
    let e = load_scene(&dir.path().join("nowhere.obj"), &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, LoadError::Io { .. }), "{e}");
    assert!(e.to_string().contains("nowhere.obj"));
}

#[test]
fn obj_errors_name_the_line() {
    let v3 = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
    type Case = (String, fn(&LoadError) -> bool, &'static str);
    let cases: Vec<Case> = vec![
        (
            format!("{v3}f 1 2 9\n"),
            |e| matches!(e, LoadError::BadIndex { .. }),
            "line 4",
        ),
        (
            format!("{v3}f 1 2 0\n"),
            |e| matches!(e, LoadError::BadIndex { .. }),
            "line 4",
        ),
        (
            format!("{v3}\n\nf -1 -2 -4\n"),
            |e| matches!(e, LoadError::BadIndex { .. }),
            "line 6",
        ),
        (
            format!("{v3}f 1 2 x\n"),
            |e| matches!(e, LoadError::Syntax { .. }),
            "line 4",
        ),
        (
            format!("{v3}f 1 2\n"),
            |e| matches!(e, LoadError::Syntax { .. }),
            "line 4",
        ),
        (
            format!("v 0 0 0\nv nan 0 0\n{v3}f 1 2 3\n"),
            |e| matches!(e, LoadError::NonFinite { .. }),
            "line 2",
        ),
        (
            format!("# big\nv 1e39 0 0\n{v3}"),
            |e| matches!(e, LoadError::NonFinite { .. }),
            "line 2",
        ),
        (
            // Finite, but beyond `rebraid::mesh::MAX_COORDINATE`.
            format!("# far\nv 0 -3e38 0\n{v3}f 1 2 3\n"),
            |e| matches!(e, LoadError::OutOfRange { .. }),
            "line 2",
        ),
        (
            "v 1 2\nf 1 1 1\n".to_string(),
            |e| matches!(e, LoadError::Syntax { .. }),
            "line 1",
        ),
        (
            format!("{v3}f 1 2 3\nv 0 0"),
            |e| matches!(e, LoadError::Truncated { .. }),
            "line 5",
        ),
        (
            format!("{v3}cstype bspline\n"),
            |e| matches!(e, LoadError::Unsupported { .. }),
            "line 4",
        ),
        (
            format!("{v3}\u{1}\u{2}garbage\n"),
            |e| matches!(e, LoadError::Syntax { .. }),
            "line 4",
        ),
        (
            v3.to_string(),
            |e| matches!(e, LoadError::Unsupported { .. }),
            "no triangle",
        ),
    ];
    for (i, (text, kind, needle)) in cases.iter().enumerate() {
        let e = load_err(&format!("bad{i}.obj"), text.as_bytes(), &[needle]);
        assert!(kind(&e), "case {i}: wrong kind: {e}");
        if needle.starts_with("line") {
            let line: usize = needle[5..].parse().unwrap();
            assert_eq!(e.location(), Some(&Location::Line(line)), "case {i}");
        }
    }
}

#[test]
fn ply_errors_name_the_line_or_element() {
    let good = cube_ascii_ply();
    // Header is 11 lines, vertices on lines 12..=19, faces on 20..=25.
    let bad_index = good.replace("4 1 2 6 5\n", "4 1 2 6 8\n");
    let e = load_err("bad_index.ply", bad_index.as_bytes(), &["line 23"]);
    assert!(matches!(e, LoadError::BadIndex { .. }), "{e}");

    let truncated = &good[..good.rfind("4 3 0").unwrap()];
    let e = load_err("truncated.ply", truncated.as_bytes(), &["line 25"]);
    assert!(matches!(e, LoadError::Truncated { .. }), "{e}");

    // Finite as a double, infinite as the f32 the mesh stores.
    let nan = good.replacen("1 1 0 255", "1 1e39 0 255", 1);
    let e = load_err("nan.ply", nan.as_bytes(), &["line 14"]);
    assert!(matches!(e, LoadError::NonFinite { .. }), "{e}");

    let far = good.replacen("1 1 0 255", "1 2e19 0 255", 1);
    let e = load_err("far.ply", far.as_bytes(), &["line 14", "beyond"]);
    assert!(matches!(e, LoadError::OutOfRange { .. }), "{e}");

    let syntax = good.replacen("1 1 0 255", "1 one 0 255", 1);
    let e = load_err("syntax.ply", syntax.as_bytes(), &["line 14"]);
    assert!(matches!(e, LoadError::Syntax { .. }), "{e}");

    let header = good.replace("property double y\n", "property double\n");
    let e = load_err("header.ply", header.as_bytes(), &["line 6"]);
    assert!(matches!(e, LoadError::Syntax { .. }), "{e}");

    let points = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n";
    let e = load_err("points.ply", points.as_bytes(), &["face"]);
    assert!(matches!(e, LoadError::Unsupported { .. }), "{e}");

    let bin = cube_binary_ply(false);
    let e = load_err("cut.ply", &bin[..bin.len() - 10], &["element `face` 5"]);
    assert!(matches!(e, LoadError::Truncated { .. }), "{e}");

    let mut bin = cube_binary_ply(false);
    let at = bin.windows(10).position(|w| w == b"end_header").unwrap() + 11;
    bin[at + 12 * 3..at + 12 * 3 + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let e = load_err("nan_le.ply", &bin, &["element `vertex` 3"]);
    assert!(matches!(e, LoadError::NonFinite { .. }), "{e}");

    let mut bin = cube_binary_ply(true);
    let n = bin.len();
    bin[n - 4..].copy_from_slice(&100u32.to_be_bytes());
    let e = load_err(
        "bad_index_be.ply",
        &bin,
        &["element `face` 5", "vertex 100"],
    );
    assert!(matches!(e, LoadError::BadIndex { .. }), "{e}");
}

#[test]
fn gltf_errors_name_the_element() {
    let buf = glb_buffer(&QUAD, [0, 1, 2]);
    // An index past the positions.
    let e = load_err(
        "bad_index.glb",
        &glb(
            &tiny_gltf_json(3, "", "[0, 0, 0]"),
            &glb_buffer(&QUAD, [0, 1, 7]),
        ),
        &["mesh 0", "primitive 0"],
    );
    assert!(matches!(e, LoadError::BadIndex { .. }), "{e}");
    // An accessor reaching past its buffer view.
    let e = load_err(
        "overrun.glb",
        &glb(&tiny_gltf_json(4, "", "[0, 0, 0]"), &buf),
        &["mesh 0", "primitive 0"],
    );
    assert!(matches!(e, LoadError::Truncated { .. }), "{e}");
    // A non-finite position.
    let mut nan = QUAD;
    nan[1][1] = f32::NAN;
    let e = load_err(
        "nan.glb",
        &glb(
            &tiny_gltf_json(3, "", "[0, 0, 0]"),
            &glb_buffer(&nan, [0, 1, 2]),
        ),
        &["mesh 0"],
    );
    assert!(matches!(e, LoadError::NonFinite { .. }), "{e}");
    // A position beyond `rebraid::mesh::MAX_COORDINATE`.
    let mut far = QUAD;
    far[2][0] = 3e38;
    let e = load_err(
        "far.glb",
        &glb(
            &tiny_gltf_json(3, "", "[0, 0, 0]"),
            &glb_buffer(&far, [0, 1, 2]),
        ),
        &["mesh 0", "beyond"],
    );
    assert!(matches!(e, LoadError::OutOfRange { .. }), "{e}");
    // Transforms that overflow once composed.
    let huge = glb(
        &tiny_gltf_json(3, r#", "scale": [1e30, 1e30, 1e30]"#, "[0, 0, 0]")
            .replace(r#""scale": [2, 1, 1]"#, r#""scale": [1e30, 1, 1]"#),
        &buf,
    );
    let e = load_err("huge.glb", &huge, &["node 1", "stretched"]);
    assert!(matches!(e, LoadError::NonFinite { .. }), "{e}");
    // A POSITION accessor past the accessors (a panic inside `gltf-json`'s
    // validation before the loader checked it; found by the fuzz smoke test).
    let json = tiny_gltf_json(3, "", "[0, 0, 0]");
    let past = r#"[{"attributes": {"POSITION": 5}, "mode": 5"#;
    let bad = json.replace(r#"[{"attributes": {"POSITION": 0}, "mode": 5"#, past);
    assert_ne!(bad, json);
    let e = load_err(
        "position_accessor.glb",
        &glb(&bad, &buf),
        &["mesh 1 primitive 0", "POSITION", "accessor 5 of 2"],
    );
    assert!(matches!(e, LoadError::BadIndex { .. }), "{e}");
    // A cut file.
    let whole = glb(&tiny_gltf_json(3, "", "[0, 0, 0]"), &buf);
    let e = load_err("cut.glb", &whole[..whole.len() - 20], &[]);
    assert!(matches!(e, LoadError::Truncated { .. }), "{e}");
    // Not glTF at all.
    let e = load_err("junk.gltf", b"{ not json", &[]);
    assert!(matches!(e, LoadError::Syntax { .. }), "{e}");
    // A zero scale is no error: the placement is skipped with a warning.
    let dir = tempfile::tempdir().unwrap();
    let flat = tiny_gltf_json(3, "", "[0, 0, 0]")
        .replace(r#""scale": [2, 1, 1]"#, r#""scale": [0, 1, 1]"#);
    let p = write(dir.path(), "zero.glb", &glb(&flat, &buf));
    let l = load_scene_with_warnings(&p, &LoadOptions::default()).unwrap();
    assert_eq!(l.scene.instances.len(), 1);
    assert!(
        l.warnings.iter().any(|w| w.contains("singular")),
        "{:?}",
        l.warnings
    );
}
