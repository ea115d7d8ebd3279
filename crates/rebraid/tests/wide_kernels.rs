//! The wide BVH layouts (W = 4 and 8) and every SIMD kernel this CPU runs,
//! against the scalar binary `MeshBvh` and the brute force: the same closest
//! `t` bit for bit, the same primitive but for exact ties, the same
//! barycentrics and normal, the same occlusion. Every wide tree is validated.
mod common;

use common::obj::{load_obj, scene_path_or_skip};
use common::*;
use rand::Rng;
use rayon::prelude::*;
use rebraid::bvh::{Kernel, WideMeshBvh};
use rebraid::glam::Vec3;
use rebraid::mesh::{brute_force_intersect, brute_force_occluded};
use rebraid::{Aabb, Hit, MeshBvh, Ray, TriangleMesh};

/// Compare one answer against a reference answer (see the module docs).
fn same_hit(
    mesh: &TriangleMesh,
    ray: &Ray,
    got: Option<Hit>,
    want: Option<Hit>,
    what: &str,
) -> Result<bool, String> {
    match (got, want) {
        (None, None) => Ok(false),
        (Some(g), Some(w)) => {
            if g.t != w.t {
                return Err(format!("{what}: t differs: {g:?} vs {w:?}, ray {ray:?}"));
            }
            if g.prim_id != w.prim_id {
                if triangle_t(mesh, g.prim_id, ray) != Some(w.t) {
                    return Err(format!("{what}: not a tie: {g:?} vs {w:?}, ray {ray:?}"));
                }
            } else if g != w {
                return Err(format!(
                    "{what}: same prim, other hit: {g:?} vs {w:?}, ray {ray:?}"
                ));
            }
            Ok(true)
        }
        (g, w) => Err(format!(
            "{what}: hit/miss differs: {g:?} vs {w:?}, ray {ray:?}"
        )),
    }
}

/// Check every wide width and available kernel on `rays`; `brute` also
/// compares against the brute force (costly on big meshes). Returns the
/// number of rays that hit.
fn check_all(label: &str, mesh: &TriangleMesh, bvh: &MeshBvh, rays: &[Ray], brute: bool) -> usize {
    let w4 = WideMeshBvh::<4>::from_mesh(bvh).expect("collapse to 4");
    let w8 = WideMeshBvh::<8>::from_mesh(bvh).expect("collapse to 8");
    w4.validate()
        .unwrap_or_else(|e| panic!("{label}: W=4 invalid: {e}"));
    w8.validate()
        .unwrap_or_else(|e| panic!("{label}: W=8 invalid: {e}"));
    let kernels = Kernel::available();
    let results: Vec<Result<bool, String>> = rays
        .par_iter()
        .map(|ray| {
            let bin = bvh.intersect(ray);
            let bin_occ = bvh.occluded(ray);
            if brute {
                same_hit(
                    mesh,
                    ray,
                    bin,
                    brute_force_intersect(mesh, ray),
                    "binary vs brute",
                )?;
                if bin_occ != brute_force_occluded(mesh, ray) {
                    return Err(format!("binary occlusion vs brute force, ray {ray:?}"));
                }
            }
            for &k in &kernels {
                let g4 = w4.intersect_with(k, ray);
                let g8 = w8.intersect_with(k, ray);
                same_hit(mesh, ray, g4, bin, &format!("W=4 {k:?} vs binary"))?;
                same_hit(mesh, ray, g8, bin, &format!("W=8 {k:?} vs binary"))?;
                if w4.occluded_with(k, ray) != bin_occ || w8.occluded_with(k, ray) != bin_occ {
                    return Err(format!(
                        "{k:?}: occlusion differs from binary ({bin_occ}), ray {ray:?}"
                    ));
                }
            }
            Ok(bin.is_some())
        })
        .collect();
    let failures: Vec<&String> = results.iter().filter_map(|r| r.as_ref().err()).collect();
    assert!(
        failures.is_empty(),
        "{label}: {} of {} rays disagree; first ones:\n{}",
        failures.len(),
        rays.len(),
        failures
            .iter()
            .take(5)
            .map(|s| s.as_str())
            .collect::<Vec<_>>()
            .join("\n")
    );
    // The batch entry points use the best kernel and must agree too.
    let mut hits = vec![None; rays.len()];
    let mut occ = vec![false; rays.len()];
    w8.intersect_batch(rays, &mut hits);
    w4.occluded_batch(rays, &mut occ);
    for (i, r) in rays.iter().enumerate() {
        assert_eq!(
            hits[i].map(|h| h.t),
            bvh.intersect(r).map(|h| h.t),
            "{label}: batch"
        );
        assert_eq!(occ[i], bvh.occluded(r), "{label}: batch occlusion");
    }
    results.into_iter().filter(|r| *r == Ok(true)).count()
}

#[test]
fn kernels_are_detected() {
    let k = Kernel::available();
    println!("available kernels: {k:?}, best {:?}", Kernel::best());
    assert!(k.contains(&Kernel::Scalar));
    assert!(k.contains(&Kernel::best()));
    let mut w = WideMeshBvh::<8>::from_mesh(&build(&grid(2, 2))).unwrap();
    for kernel in Kernel::ALL {
        assert_eq!(w.set_kernel(kernel).is_ok(), kernel.is_available());
    }
}

#[test]
fn random_soups() {
    for (seed, n, size) in [(1, 2_000, 0.05), (2, 3_000, 0.4), (3, 500, 2.0)] {
        let mut r = rng(seed);
        let mesh = random_soup(&mut r, n, 1.0, size);
        let bvh = build(&mesh);
        let b = mesh.bounds();
        let mut rays = random_rays(&mut r, 1_500, &b);
        rays.extend(aimed_rays(&mut r, 1_500, &b));
        let hits = check_all("soup", &mesh, &bvh, &rays, true);
        assert!(hits > 300, "soup {seed}: only {hits} hits");
    }
}

/// Axis-parallel rays through the grid's vertices and edges, origins on the
/// box planes (integer coordinates), and grazing rays in the grid's plane:
/// the NaN slabs of the box test.
#[test]
fn grids_with_axis_parallel_rays() {
    let mesh = grid(24, 17);
    let bvh = build(&mesh);
    let mut rays = Vec::new();
    for y in 0..=34 {
        for x in 0..=48 {
            let p = Vec3::new(x as f32 * 0.5, y as f32 * 0.5, 0.0);
            // Straight down and up through vertices, edge midpoints, centres.
            rays.push(Ray::infinite(p + Vec3::Z, -Vec3::Z));
            rays.push(Ray::infinite(p - Vec3::Z * 2.0, Vec3::Z));
            // Origins exactly on the plane z = 0 (a box plane of every node).
            rays.push(Ray::infinite(p, -Vec3::Z));
            // In the plane, along the grid lines (x = const, y = const).
            rays.push(Ray::infinite(Vec3::new(p.x, -1.0, 0.0), Vec3::Y));
            rays.push(Ray::infinite(Vec3::new(-1.0, p.y, 0.0), Vec3::X));
            rays.push(Ray::infinite(Vec3::new(30.0, p.y, 0.0), -Vec3::X));
            // Diagonals through vertices with a zero z component.
            rays.push(Ray::infinite(
                Vec3::new(p.x, p.y, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
            ));
            // Slanted rays through vertices, with t clipped at the hit.
            rays.push(
                Ray::new(
                    p + Vec3::new(0.3, 0.2, 1.0),
                    Vec3::new(-0.3, -0.2, -1.0),
                    0.0,
                    1.0,
                )
                .unwrap(),
            );
        }
    }
    // Negative-zero direction components pick the other near plane.
    for x in 0..24 {
        rays.push(Ray::infinite(
            Vec3::new(x as f32, 3.0, 1.0),
            Vec3::new(-0.0, 0.0, -1.0),
        ));
        rays.push(Ray::infinite(
            Vec3::new(x as f32 + 0.5, 3.0, 1.0),
            Vec3::new(-0.0, -0.0, -1.0),
        ));
    }
    let mut r = rng(11);
    rays.extend(random_rays(&mut r, 2_000, &mesh.bounds()));
    let hits = check_all("grid", &mesh, &bvh, &rays, true);
    assert!(hits > 3_000, "grid: only {hits} hits");

    // The same grid standing in the planes x = 0 and y = 0: rays along the
    // normal have two zero direction components, and origins on the box
    // planes of both, so the z slab (the last one the SIMD kernels fold in)
    // is NaN too and must be widened, not propagated.
    let rotations: [fn(Vec3) -> Vec3; 2] =
        [|p| Vec3::new(p.z, p.x, p.y), |p| Vec3::new(p.y, p.z, p.x)];
    for rot in rotations {
        let positions = mesh.positions.iter().map(|&p| rot(p)).collect();
        let stood = TriangleMesh::new(positions, mesh.indices.clone()).unwrap();
        let bvh = build(&stood);
        let normal = rot(Vec3::Z);
        let mut rays = Vec::new();
        for y in 0..=34 {
            for x in 0..=48 {
                let p = rot(Vec3::new(x as f32 * 0.5, y as f32 * 0.5, 0.0));
                rays.push(Ray::infinite(p - normal, normal));
                rays.push(Ray::infinite(p + normal * 3.0, -normal));
            }
        }
        let hits = check_all("standing grid", &stood, &bvh, &rays, true);
        assert!(hits > 3_000, "standing grid: only {hits} hits");
    }
}

#[test]
fn spheres() {
    let mut r = rng(12);
    for mesh in [
        uv_sphere(40, 64, 1.0, Vec3::new(0.5, -0.2, 0.1)),
        icosphere(4, 3.0, Vec3::ZERO),
    ] {
        let bvh = build(&mesh);
        let b = mesh.bounds();
        let mut rays = aimed_rays(&mut r, 2_000, &b);
        rays.extend(random_rays(&mut r, 1_000, &b));
        // From the centre outwards: every ray hits exactly once (closed mesh).
        let c = b.center();
        rays.extend((0..1_000).map(|_| Ray::infinite(c, unit_dir(&mut r))));
        let hits = check_all("sphere", &mesh, &bvh, &rays, true);
        assert!(hits >= 1_000, "sphere: only {hits} hits");
    }
}

#[test]
fn empty_and_single_triangle() {
    let empty = TriangleMesh::default();
    let bvh = build(&empty);
    let w = WideMeshBvh::<8>::from_mesh(&bvh).unwrap();
    w.validate().unwrap();
    assert!(w.is_empty() && w.wide.nodes.is_empty());
    let ray = Ray::infinite(Vec3::ZERO, Vec3::X);
    for k in Kernel::available() {
        assert_eq!(w.intersect_with(k, &ray), None);
        assert!(!w.occluded_with(k, &ray));
    }
    let one = TriangleMesh::from_triangles(&[[Vec3::ZERO, Vec3::X, Vec3::Y]]).unwrap();
    let bvh = build(&one);
    let rays = vec![
        Ray::infinite(Vec3::new(0.25, 0.25, 1.0), -Vec3::Z),
        Ray::infinite(Vec3::new(0.0, 0.0, 1.0), -Vec3::Z),
        Ray::infinite(Vec3::new(2.0, 2.0, 1.0), -Vec3::Z),
        Ray::new(Vec3::new(0.25, 0.25, 1.0), -Vec3::Z, 0.0, 0.5).unwrap(),
        Ray::infinite(Vec3::new(-1.0, 0.0, 0.0), Vec3::X),
    ];
    let hits = check_all("one triangle", &one, &bvh, &rays, true);
    assert_eq!(hits, 2);
    let w = WideMeshBvh::<4>::from_mesh(&bvh).unwrap();
    let s = w.stats();
    assert_eq!((s.nodes, s.leaves, s.empty_slots), (1, 1, 3));
}

/// A million triangles sharing one centroid: the deepest trees the builder
/// makes (index medians), which exercise the stack bound.
#[test]
fn million_triangles_with_one_centroid() {
    let n = 1_000_000;
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|i| {
            let s = 1.0 + (i % 1000) as f32 * 0.01;
            [
                Vec3::new(-s, -s, 0.0),
                Vec3::new(s, -s, 0.0),
                Vec3::new(0.0, s, 0.0),
            ]
        })
        .collect();
    let mesh = TriangleMesh::from_triangles(&tris).unwrap();
    let bvh = build(&mesh);
    let mut r = rng(22);
    let mut rays = aimed_rays(&mut r, 12, &mesh.bounds());
    // Also rays that hit nothing but enter every box (grazing the plane).
    rays.push(Ray::infinite(Vec3::new(-20.0, 0.0, 0.0), Vec3::X));
    let hits = check_all("one centroid", &mesh, &bvh, &rays, true);
    assert!(hits >= 1, "one centroid: no hits");
    let w = WideMeshBvh::<8>::from_mesh(&bvh).unwrap();
    println!("one centroid, W=8: {:?}", w.stats());
}

/// The real scene `openarena_oa_thor.obj` (57,743 triangles).
#[test]
fn openarena_thor() {
    let Some(path) = scene_path_or_skip("openarena_oa_thor.obj") else {
        return;
    };
    let mesh = load_obj(&path);
    let bvh = build(&mesh);
    let b = mesh.bounds();
    let mut r = rng(31);
    let mut rays = Vec::new();
    for _ in 0..4 {
        let eye = point_in(
            &mut r,
            &Aabb::new(b.min + b.extent() * 0.3, b.max - b.extent() * 0.3),
        );
        let forward = unit_dir(&mut r);
        let right = forward.cross(Vec3::Z).normalize_or(Vec3::X);
        let up = right.cross(forward);
        for y in 0..32 {
            for x in 0..32 {
                let (sx, sy) = (x as f32 / 15.5 - 1.0, y as f32 / 15.5 - 1.0);
                rays.push(Ray::infinite(eye, forward + right * sx + up * sy));
            }
        }
    }
    // Axis-parallel rays from inside the level.
    for _ in 0..300 {
        let p = point_in(&mut r, &b);
        for d in [Vec3::X, -Vec3::Y, Vec3::Z, -Vec3::Z] {
            rays.push(Ray::infinite(p, d));
        }
    }
    let brute_rays: Vec<Ray> = rays.iter().step_by(8).copied().collect();
    rays.extend(random_rays(&mut r, 2_000, &b));
    for _ in 0..500 {
        let (p, q) = (point_in(&mut r, &b), point_in(&mut r, &b));
        rays.push(Ray::new(p, q - p, r.gen_range(0.0..0.1), 1.0).unwrap());
    }
    let hits = check_all("thor", &mesh, &bvh, &rays, false);
    assert!(hits > rays.len() / 3, "thor: {hits} hits of {}", rays.len());
    check_all("thor (brute force)", &mesh, &bvh, &brute_rays, true);
    let w8 = WideMeshBvh::<8>::from_mesh(&bvh).unwrap();
    let w4 = WideMeshBvh::<4>::from_mesh(&bvh).unwrap();
    println!(
        "thor: binary {} nodes; W=4 {:?}; W=8 {:?}",
        bvh.bvh.nodes.len(),
        w4.stats(),
        w8.stats()
    );
}
