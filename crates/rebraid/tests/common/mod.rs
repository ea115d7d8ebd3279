//! Shared helpers of the kernel tests: seeded mesh and ray generators and the
//! comparison of BVH queries against the brute-force reference.
//!
//! Each test binary uses a different subset of these helpers.
#![allow(dead_code)]

pub mod obj;

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;
use rebraid::glam::Vec3;
use rebraid::mesh::{brute_force_intersect, brute_force_occluded};
use rebraid::triangle::{WatertightRay, intersect_triangle};
use rebraid::{Aabb, BuildParams, Hit, MeshBvh, Ray, TriangleMesh};

/// A seeded generator, so that every failure reproduces.
pub fn rng(seed: u64) -> Pcg64 {
    Pcg64::seed_from_u64(seed)
}

/// A point uniformly inside `bounds`.
pub fn point_in(rng: &mut impl Rng, bounds: &Aabb) -> Vec3 {
    let f = Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen());
    bounds.min + f * (bounds.max - bounds.min)
}

/// A direction uniformly on the unit sphere (rejection sampling).
pub fn unit_dir(rng: &mut impl Rng) -> Vec3 {
    loop {
        let d = Vec3::new(
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
        );
        let l = d.length_squared();
        if l > 1e-4 && l <= 1.0 {
            return d / l.sqrt();
        }
    }
}

/// `n` independent triangles with centres uniform in a cube of side `spread`
/// and vertices within `size` of their centre: small `size / spread` gives a
/// sparse soup, large gives many big overlapping triangles.
pub fn random_soup(rng: &mut impl Rng, n: usize, spread: f32, size: f32) -> TriangleMesh {
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|_| {
            let c = Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) * spread;
            let mut v = || c + (Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) - 0.5) * size;
            [v(), v(), v()]
        })
        .collect();
    TriangleMesh::from_triangles(&tris).unwrap()
}

/// A regular grid of `nx * ny` quads (two triangles each) in the `z = 0`
/// plane over `[0, nx] x [0, ny]`: shared edges on exact integer coordinates,
/// which are also the planes of many node boxes.
pub fn grid(nx: u32, ny: u32) -> TriangleMesh {
    let mut positions = Vec::new();
    for y in 0..=ny {
        for x in 0..=nx {
            positions.push(Vec3::new(x as f32, y as f32, 0.0));
        }
    }
    let id = |x: u32, y: u32| y * (nx + 1) + x;
    let mut indices = Vec::new();
    for y in 0..ny {
        for x in 0..nx {
            indices.push([id(x, y), id(x + 1, y), id(x + 1, y + 1)]);
            indices.push([id(x, y), id(x + 1, y + 1), id(x, y + 1)]);
        }
    }
    TriangleMesh::new(positions, indices).unwrap()
}

/// A closed UV sphere: single pole vertices and a seam that reuses the first
/// column of vertices, so every edge is shared by exactly two triangles.
pub fn uv_sphere(stacks: u32, slices: u32, radius: f32, center: Vec3) -> TriangleMesh {
    assert!(stacks >= 2 && slices >= 3);
    let mut positions = vec![center + Vec3::new(0.0, 0.0, radius)];
    for i in 1..stacks {
        let theta = std::f32::consts::PI * i as f32 / stacks as f32;
        for j in 0..slices {
            let phi = std::f32::consts::TAU * j as f32 / slices as f32;
            let d = Vec3::new(
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos(),
            );
            positions.push(center + d * radius);
        }
    }
    let south = positions.len() as u32;
    positions.push(center - Vec3::new(0.0, 0.0, radius));
    let ring = |i: u32, j: u32| 1 + (i - 1) * slices + j % slices;
    let mut indices = Vec::new();
    for j in 0..slices {
        indices.push([0, ring(1, j), ring(1, j + 1)]);
        indices.push([south, ring(stacks - 1, j + 1), ring(stacks - 1, j)]);
    }
    for i in 1..stacks - 1 {
        for j in 0..slices {
            indices.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
            indices.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
        }
    }
    TriangleMesh::new(positions, indices).unwrap()
}

/// A closed icosphere: the icosahedron with each face split `subdivisions`
/// times into four, midpoints shared between neighbours.
pub fn icosphere(subdivisions: u32, radius: f32, center: Vec3) -> TriangleMesh {
    let t = (1.0 + 5.0f32.sqrt()) / 2.0;
    let mut unit: Vec<Vec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|&p| Vec3::from_array(p).normalize())
    .collect();
    let mut faces: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut midpoints = std::collections::HashMap::new();
        let mut mid = |a: u32, b: u32, unit: &mut Vec<Vec3>| {
            *midpoints.entry((a.min(b), a.max(b))).or_insert_with(|| {
                unit.push(((unit[a as usize] + unit[b as usize]) * 0.5).normalize());
                unit.len() as u32 - 1
            })
        };
        faces = faces
            .iter()
            .flat_map(|&[a, b, c]| {
                let ab = mid(a, b, &mut unit);
                let bc = mid(b, c, &mut unit);
                let ca = mid(c, a, &mut unit);
                [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
            })
            .collect();
    }
    let positions = unit.iter().map(|&p| center + p * radius).collect();
    TriangleMesh::new(positions, faces).unwrap()
}

/// `n` long, thin triangles (length `len`, width around `len / 500`) in random
/// orientations: boxes far larger than the triangles, the hard case for SAH.
pub fn thin_triangles(rng: &mut impl Rng, n: usize, spread: f32, len: f32) -> TriangleMesh {
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|_| {
            let a = Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) * spread;
            let d = unit_dir(rng) * len;
            let w = unit_dir(rng) * (len / 500.0);
            [a, a + d, a + d * 0.5 + w]
        })
        .collect();
    TriangleMesh::from_triangles(&tris).unwrap()
}

/// Rays with origins in `bounds` grown by half its size on each side, random
/// directions of random length, and a mix of intervals: `[0, inf)` for most,
/// and random `t_min` / `t_max` cuts for the rest so that hits get clipped.
pub fn random_rays(rng: &mut impl Rng, n: usize, bounds: &Aabb) -> Vec<Ray> {
    let e = bounds.extent().max(Vec3::splat(1e-3));
    let grown = Aabb::new(bounds.min - e * 0.5, bounds.max + e * 0.5);
    let scale = e.max_element();
    (0..n)
        .map(|_| {
            let origin = point_in(rng, &grown);
            let dir = unit_dir(rng) * rng.gen_range(0.25..4.0);
            let (t_min, t_max) = match rng.gen_range(0..4) {
                0 | 1 => (0.0, f32::INFINITY),
                2 => (0.0, rng.gen_range(0.0..scale)),
                _ => {
                    let a = rng.gen_range(0.0..scale);
                    (a, a + rng.gen_range(0.0..scale))
                }
            };
            Ray::new(origin, dir, t_min, t_max).unwrap()
        })
        .collect()
}

/// Rays from outside `bounds` aimed at random points inside it: nearly all
/// of them enter the geometry, unlike [`random_rays`] in a sparse scene.
pub fn aimed_rays(rng: &mut impl Rng, n: usize, bounds: &Aabb) -> Vec<Ray> {
    let r = bounds.extent().length().max(1e-3);
    (0..n)
        .map(|_| {
            let target = point_in(rng, bounds);
            let origin = bounds.center() + unit_dir(rng) * r;
            Ray::new(origin, target - origin, 0.0, f32::INFINITY).unwrap()
        })
        .collect()
}

/// What a comparison saw, so that tests can check they exercised hits and
/// misses (a suite where every ray misses would prove nothing).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Tally {
    pub rays: usize,
    pub hits: usize,
    pub ties: usize,
    pub occluded: usize,
}

impl std::ops::Add for Tally {
    type Output = Tally;
    fn add(self, o: Tally) -> Tally {
        Tally {
            rays: self.rays + o.rays,
            hits: self.hits + o.hits,
            ties: self.ties + o.ties,
            occluded: self.occluded + o.occluded,
        }
    }
}

/// The `t` at which `ray` hits triangle `prim` alone, with the same kernel
/// the BVH and the reference use (so ties can be told from errors).
pub fn triangle_t(mesh: &TriangleMesh, prim: u32, ray: &Ray) -> Option<f32> {
    let [a, b, c] = mesh.triangle(prim as usize);
    if rebraid::triangle::is_degenerate(a, b, c) {
        return None;
    }
    let wray = WatertightRay::new(ray.origin, ray.dir);
    intersect_triangle(&wray, a, b, c, ray.t_min, ray.t_max).map(|(t, _, _)| t)
}

/// Check one ray's BVH answers against the brute-force reference: the same
/// closest `t` (bit for bit but for the sign of zero: both run the same
/// triangle test on the same vertices), the same primitive unless the other one is hit at exactly that
/// `t` too (a tie), the same barycentrics and normal for the same primitive,
/// and the same occlusion answer. Returns the tally of this one ray.
pub fn check_ray(mesh: &TriangleMesh, bvh: &MeshBvh, ray: &Ray) -> Result<Tally, String> {
    let got = bvh.intersect(ray);
    let want = brute_force_intersect(mesh, ray);
    let mut tally = Tally {
        rays: 1,
        ..Tally::default()
    };
    match (got, want) {
        (None, None) => {}
        (Some(g), Some(w)) => {
            tally.hits = 1;
            if g.t != w.t {
                return Err(format!(
                    "closest t differs: bvh {g:?}, brute force {w:?}, ray {ray:?}"
                ));
            }
            if g.prim_id != w.prim_id {
                tally.ties = 1;
                if triangle_t(mesh, g.prim_id, ray) != Some(w.t) {
                    return Err(format!(
                        "bvh prim {} is not a tie: {g:?} vs {w:?}, ray {ray:?}",
                        g.prim_id
                    ));
                }
            } else if g != w {
                return Err(format!(
                    "same prim, different hit: bvh {g:?}, brute force {w:?}, ray {ray:?}"
                ));
            }
        }
        (g, w) => {
            return Err(format!(
                "hit/miss differs: bvh {g:?}, brute force {w:?}, ray {ray:?}"
            ));
        }
    }
    let occluded = bvh.occluded(ray);
    if occluded != brute_force_occluded(mesh, ray) {
        return Err(format!(
            "occlusion differs: bvh says {occluded}, ray {ray:?}"
        ));
    }
    if occluded != tally.hits.eq(&1) {
        return Err(format!(
            "occluded() = {occluded} disagrees with intersect(), ray {ray:?}"
        ));
    }
    tally.occluded = occluded as usize;
    Ok(tally)
}

/// [`check_ray`] over many rays in parallel; panics with the first few
/// failures (labelled) and returns the tally.
pub fn check_rays(label: &str, mesh: &TriangleMesh, bvh: &MeshBvh, rays: &[Ray]) -> Tally {
    let results: Vec<Result<Tally, String>> =
        rays.par_iter().map(|r| check_ray(mesh, bvh, r)).collect();
    let failures: Vec<&String> = results.iter().filter_map(|r| r.as_ref().err()).collect();
    assert!(
        failures.is_empty(),
        "{label}: {} of {} rays disagree with the brute force; first ones:\n{}",
        failures.len(),
        rays.len(),
        failures
            .iter()
            .take(5)
            .map(|s| s.as_str())
            .collect::<Vec<_>>()
            .join("\n")
    );
    results
        .into_iter()
        .map(Result::unwrap)
        .fold(Tally::default(), |a, b| a + b)
}

/// Build a mesh BVH with default parameters and check it against its own mesh.
pub fn build(mesh: &TriangleMesh) -> MeshBvh {
    build_with(mesh, &BuildParams::default())
}

/// Build with the given parameters and validate the tree.
pub fn build_with(mesh: &TriangleMesh, params: &BuildParams) -> MeshBvh {
    let bvh = MeshBvh::build(mesh, params).expect("build");
    bvh.validate().expect("valid BVH");
    bvh
}

/// The closest hit of a ray given by its parts, for the edge-case tests.
pub fn hit(bvh: &MeshBvh, origin: Vec3, dir: Vec3, t_min: f32, t_max: f32) -> Option<Hit> {
    bvh.intersect(&Ray::new(origin, dir, t_min, t_max).unwrap())
}
