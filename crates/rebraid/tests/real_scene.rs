//! The kernels on a real third-party scene (read from the shared scenes
//! directory, never copied into the repository).
mod common;

use common::obj::{load_obj, parse_obj, scene_path_or_skip};
use common::*;
use rand::Rng;
use rebraid::glam::Vec3;
use rebraid::{Aabb, Ray};

/// The OBJ reader itself: fan triangulation, `v/vt/vn` tokens, negative
/// (relative) indices and ignored lines.
#[test]
fn obj_parser_reads_positions_and_faces() {
    let text = "# comment\no quad\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1/1/1 2/2/1 3/3/1 4/4/1\nf -4 -2 -1\n";
    let mesh = parse_obj(text).unwrap();
    assert_eq!(mesh.positions.len(), 4);
    assert_eq!(mesh.indices, vec![[0, 1, 2], [0, 2, 3], [0, 2, 3]]);
    assert!(parse_obj("v 0 0\n").is_err());
    assert!(parse_obj("v 0 0 0\nf 1 2 3\n").is_err());
}

/// `openarena_oa_thor.obj`: the whole level in one mesh BVH, checked against
/// the brute force with camera-like rays from inside the level and random
/// rays through it.
#[test]
fn openarena_thor_matches_brute_force() {
    let Some(path) = scene_path_or_skip("openarena_oa_thor.obj") else {
        return;
    };
    let mesh = load_obj(&path);
    assert_eq!(mesh.len(), 57_743, "the scene README says 57,743 triangles");
    let bvh = build(&mesh);
    let stats = bvh.stats();
    println!("oa_thor: {stats:?}");
    let b = mesh.bounds();
    let mut r = rng(30);
    // A pinhole camera at a few points inside the level, looking around.
    let mut rays = Vec::new();
    for _ in 0..4 {
        let eye = point_in(
            &mut r,
            &Aabb::new(b.min + b.extent() * 0.3, b.max - b.extent() * 0.3),
        );
        let forward = unit_dir(&mut r);
        let right = forward.cross(Vec3::Z).normalize_or(Vec3::X);
        let up = right.cross(forward);
        for y in 0..16 {
            for x in 0..16 {
                let (sx, sy) = (x as f32 / 7.5 - 1.0, y as f32 / 7.5 - 1.0);
                rays.push(Ray::infinite(eye, forward + right * sx + up * sy));
            }
        }
    }
    rays.extend(random_rays(&mut r, 1_000, &b));
    rays.extend(aimed_rays(&mut r, 400, &b));
    // Short shadow-like segments between points of the level.
    for _ in 0..200 {
        let (p, q) = (point_in(&mut r, &b), point_in(&mut r, &b));
        rays.push(Ray::new(p, q - p, r.gen_range(0.0..0.1), 1.0).unwrap());
    }
    let tally = check_rays("oa_thor", &mesh, &bvh, &rays);
    println!("oa_thor: {tally:?}");
    assert!(tally.hits > rays.len() / 2, "{tally:?}");
    assert!(tally.hits < rays.len(), "{tally:?}");
}
