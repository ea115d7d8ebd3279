//! The BVH kernels against the brute-force reference, ray by ray: random
//! soups of several sizes and densities, structured meshes, and the batch
//! entry points.
mod common;

use common::*;
use rand::Rng;
use rebraid::bvh::binning::MAX_BINS;
use rebraid::glam::Vec3;
use rebraid::{Aabb, BuildParams, Ray};

/// Soups from one triangle to thousands, sparse to heavily overlapping; ray
/// counts shrink as meshes grow so that the brute force stays cheap.
#[test]
fn random_soups_match_brute_force() {
    let mut r = rng(1);
    let mut total = Tally::default();
    // (triangles, spread, triangle size, rays)
    let cases = [
        (1, 1.0, 1.0, 200_000),
        (2, 1.0, 1.0, 200_000),
        (9, 1.0, 0.5, 300_000),
        (64, 4.0, 1.0, 300_000),
        (300, 10.0, 0.6, 80_000),
        (300, 1.0, 3.0, 50_000), // big triangles, every box overlapping every other
        (2_000, 20.0, 0.8, 8_000),
        (2_000, 2.0, 2.0, 6_000),
        (6_000, 30.0, 0.5, 3_000),
    ];
    for (n, spread, size, nrays) in cases {
        let mesh = random_soup(&mut r, n, spread, size);
        let bvh = build(&mesh);
        let mut rays = random_rays(&mut r, nrays / 2, &mesh.bounds());
        rays.extend(aimed_rays(&mut r, nrays / 2, &mesh.bounds()));
        let tally = check_rays(
            &format!("soup n={n} spread={spread} size={size}"),
            &mesh,
            &bvh,
            &rays,
        );
        assert!(tally.hits > 0, "soup n={n}: no ray hit anything");
        assert!(tally.hits < tally.rays, "soup n={n}: every ray hit");
        total = total + tally;
    }
    println!("random soups: {total:?}");
}

/// Leaf sizes and bin counts change the tree, never the answers.
#[test]
fn build_parameters_do_not_change_answers() {
    let mut r = rng(2);
    let mesh = random_soup(&mut r, 400, 4.0, 1.0);
    let rays = aimed_rays(&mut r, 10_000, &mesh.bounds());
    for (bins, max_leaf_size) in [(2, 1), (4, 2), (16, 4), (MAX_BINS, 8), (3, 16), (8, 1000)] {
        let params = BuildParams {
            bins,
            max_leaf_size,
            ..BuildParams::default()
        };
        let bvh = build_with(&mesh, &params);
        let tally = check_rays(
            &format!("bins={bins} leaf={max_leaf_size}"),
            &mesh,
            &bvh,
            &rays,
        );
        assert!(tally.hits > 1_000, "{tally:?}");
    }
}

/// A grid in the `z = 0` plane: rays from above, including rays exactly
/// through shared edges and vertices (integer coordinates), which are also
/// the planes of node boxes.
#[test]
fn grid_matches_brute_force() {
    let mesh = grid(24, 24);
    let bvh = build(&mesh);
    let mut r = rng(3);
    let mut rays = random_rays(&mut r, 40_000, &mesh.bounds());
    rays.extend(aimed_rays(&mut r, 40_000, &mesh.bounds()));
    // Slanted and vertical rays through grid vertices and edge points.
    for y in 0..=24 {
        for x in 0..=24 {
            let p = Vec3::new(x as f32, y as f32, 0.0);
            for target in [
                p,
                p + Vec3::new(0.5, 0.0, 0.0),
                p + Vec3::new(0.0, 0.5, 0.0),
                p + Vec3::new(0.5, 0.5, 0.0),
            ] {
                let origin =
                    target + Vec3::new(r.gen_range(-2.0..2.0), r.gen_range(-2.0..2.0), 3.0);
                rays.push(Ray::new(origin, target - origin, 0.0, f32::INFINITY).unwrap());
                rays.push(Ray::new(target + Vec3::Z * 2.0, -Vec3::Z, 0.0, f32::INFINITY).unwrap());
            }
        }
    }
    let tally = check_rays("grid", &mesh, &bvh, &rays);
    assert!(tally.hits > 10_000);
    println!("grid: {tally:?}");
}

/// Closed spheres (UV and icosahedral), alone and nested inside each other,
/// seen from outside and from inside.
#[test]
fn closed_spheres_match_brute_force() {
    let mut r = rng(4);
    let meshes = [
        uv_sphere(12, 24, 1.0, Vec3::ZERO),
        icosphere(2, 2.0, Vec3::new(0.5, -0.25, 1.0)),
        uv_sphere(7, 5, 3.0, Vec3::new(10.0, 0.0, 0.0)),
    ];
    for (k, mesh) in meshes.iter().enumerate() {
        let bvh = build(mesh);
        let b = mesh.bounds();
        let mut rays = aimed_rays(&mut r, 15_000, &b);
        // From the centre outwards: every one of these must hit.
        let inner: Vec<Ray> = (0..10_000)
            .map(|_| Ray::new(b.center(), unit_dir(&mut r), 0.0, f32::INFINITY).unwrap())
            .collect();
        let inner_tally = check_rays(&format!("sphere {k} from inside"), mesh, &bvh, &inner);
        assert_eq!(
            inner_tally.hits, inner_tally.rays,
            "sphere {k}: a ray escaped from inside"
        );
        rays.extend(random_rays(&mut r, 15_000, &b));
        check_rays(&format!("sphere {k}"), mesh, &bvh, &rays);
    }
    // Nested spheres in one mesh: closest hit must pick the inner one.
    let mut nested = uv_sphere(8, 16, 1.0, Vec3::ZERO);
    let outer = icosphere(1, 2.0, Vec3::ZERO);
    let base = nested.positions.len() as u32;
    nested.positions.extend(&outer.positions);
    nested
        .indices
        .extend(outer.indices.iter().map(|t| t.map(|i| i + base)));
    let bvh = build(&nested);
    let rays = aimed_rays(
        &mut r,
        20_000,
        &Aabb::new(Vec3::splat(-0.5), Vec3::splat(0.5)),
    );
    let tally = check_rays("nested spheres", &nested, &bvh, &rays);
    assert_eq!(tally.hits, tally.rays);
}

/// Long thin triangles in random orientations: boxes much larger than the
/// triangles they hold.
#[test]
fn thin_triangles_match_brute_force() {
    let mut r = rng(5);
    for (n, len, nrays) in [(300, 5.0, 40_000), (2_000, 20.0, 6_000)] {
        let mesh = thin_triangles(&mut r, n, 10.0, len);
        let bvh = build(&mesh);
        let mut rays = random_rays(&mut r, nrays / 2, &mesh.bounds());
        rays.extend(aimed_rays(&mut r, nrays / 2, &mesh.bounds()));
        let tally = check_rays(&format!("thin n={n}"), &mesh, &bvh, &rays);
        assert!(tally.hits > 20, "thin n={n}: {tally:?}");
    }
}

/// `intersect_batch` and `occluded_batch` give, slot by slot, what the
/// single-ray queries give (including invalid rays in the middle).
#[test]
fn batch_queries_equal_single_ray_queries() {
    let mut r = rng(6);
    let mesh = random_soup(&mut r, 4_000, 10.0, 1.0);
    let bvh = build(&mesh);
    let mut rays = random_rays(&mut r, 30_000, &mesh.bounds());
    rays.extend(aimed_rays(&mut r, 30_000, &mesh.bounds()));
    rays.insert(100, Ray::infinite(Vec3::ONE, Vec3::ZERO));
    rays.insert(5_000, Ray::infinite(Vec3::NAN, Vec3::X));
    let mut hits = vec![None; rays.len()];
    let mut occluded = vec![false; rays.len()];
    bvh.intersect_batch(&rays, &mut hits);
    bvh.occluded_batch(&rays, &mut occluded);
    let mut n_hits = 0;
    for (i, ray) in rays.iter().enumerate() {
        assert_eq!(hits[i], bvh.intersect(ray), "intersect_batch slot {i}");
        assert_eq!(occluded[i], bvh.occluded(ray), "occluded_batch slot {i}");
        n_hits += hits[i].is_some() as usize;
    }
    assert!(n_hits > 1_000 && n_hits < rays.len());
    // Empty batches are fine.
    bvh.intersect_batch(&[], &mut []);
    bvh.occluded_batch(&[], &mut []);
}

/// A batch with fewer outputs than rays is a caller error, reported loudly.
#[test]
#[should_panic(expected = "one output per ray")]
fn batch_with_wrong_output_length_panics() {
    let bvh = build(&grid(2, 2));
    let rays = [Ray::infinite(Vec3::Z, -Vec3::Z); 3];
    bvh.intersect_batch(&rays, &mut [None, None]);
}
