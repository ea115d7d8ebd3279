//! Edge cases of the mesh BVH: empty and tiny inputs, pathological
//! distributions (identical, collinear, exponentially spaced), axis-parallel
//! rays, ray intervals, invalid input and degenerate triangles.
mod common;

use common::*;
use rand::Rng;
use rebraid::bvh::binning::MAX_BINS;
use rebraid::bvh::{MAX_DEPTH, build_bvh};
use rebraid::glam::Vec3;
use rebraid::mesh::{brute_force_intersect, brute_force_occluded};
use rebraid::{Aabb, BuildParams, Error, MeshBvh, Ray, TriangleMesh};

/// The closed unit cube `[0, 1]^3`, 12 triangles over 8 shared vertices.
fn unit_cube() -> TriangleMesh {
    let positions = (0..8)
        .map(|i| Vec3::new((i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32))
        .collect();
    let quads = [
        [0, 2, 3, 1], // z = 0
        [4, 5, 7, 6], // z = 1
        [0, 1, 5, 4], // y = 0
        [2, 6, 7, 3], // y = 1
        [0, 4, 6, 2], // x = 0
        [1, 3, 7, 5], // x = 1
    ];
    let indices = quads
        .iter()
        .flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]])
        .collect();
    TriangleMesh::new(positions, indices).unwrap()
}

/// The depth of the tree, checked against the bound traversal stacks are sized by.
fn assert_depth_bounded(bvh: &MeshBvh) -> u32 {
    let depth = bvh.stats().max_depth;
    assert!(depth <= MAX_DEPTH, "depth {depth} > MAX_DEPTH {MAX_DEPTH}");
    depth
}

#[test]
fn empty_mesh_builds_and_hits_nothing() {
    let mesh = TriangleMesh::new(vec![], vec![]).unwrap();
    let bvh = build(&mesh);
    assert!(bvh.is_empty() && bvh.bvh.nodes.is_empty());
    assert_eq!(bvh.stats().nodes, 0);
    let ray = Ray::infinite(Vec3::ZERO, Vec3::X);
    assert_eq!(bvh.intersect(&ray), None);
    assert!(!bvh.occluded(&ray));
    let mut out = [Some(rebraid::Hit::NONE)];
    bvh.intersect_batch(&[ray], &mut out);
    assert_eq!(out, [None]);
    // Vertices without triangles are an empty mesh too.
    let bvh = build(&TriangleMesh::new(vec![Vec3::ONE; 5], vec![]).unwrap());
    assert_eq!(bvh.intersect(&ray), None);
}

#[test]
fn single_triangle() {
    let mesh = TriangleMesh::from_triangles(&[[Vec3::ZERO, Vec3::X, Vec3::Y]]).unwrap();
    let bvh = build(&mesh);
    assert_eq!(bvh.bvh.nodes.len(), 1);
    let h = hit(&bvh, Vec3::new(0.2, 0.3, 2.0), -Vec3::Z, 0.0, f32::INFINITY).unwrap();
    assert_eq!((h.prim_id, h.t, h.u, h.v), (0, 2.0, 0.2, 0.3));
    assert_eq!(h.normal, Vec3::Z);
    assert!(hit(&bvh, Vec3::new(0.6, 0.6, 2.0), -Vec3::Z, 0.0, f32::INFINITY).is_none());
    let mut r = rng(20);
    check_rays(
        "one triangle",
        &mesh,
        &bvh,
        &random_rays(&mut r, 5_000, &mesh.bounds()),
    );
}

/// 100k copies of one triangle: one box, one centroid, no SAH split at all.
#[test]
fn hundred_thousand_identical_triangles() {
    let tri = [
        Vec3::new(1.0, 2.0, 3.0),
        Vec3::new(2.0, 2.0, 3.0),
        Vec3::new(1.0, 3.0, 4.0),
    ];
    let mesh = TriangleMesh::from_triangles(&vec![tri; 100_000]).unwrap();
    let params = BuildParams::default();
    let bvh = build_with(&mesh, &params);
    assert_depth_bounded(&bvh);
    assert!(
        bvh.bvh
            .nodes
            .iter()
            .all(|n| n.count <= params.max_leaf_size)
    );
    let mut r = rng(21);
    // Rays through points inside the triangle, from both sides.
    let rays: Vec<Ray> = (0..40)
        .map(|_| {
            let (u, v) = (r.gen_range(0.0..0.5), r.gen_range(0.0..0.5));
            let target = tri[0] + (tri[1] - tri[0]) * u + (tri[2] - tri[0]) * v;
            let origin = target + unit_dir(&mut r) * 3.0;
            Ray::infinite(origin, target - origin)
        })
        .collect();
    let tally = check_rays("identical", &mesh, &bvh, &rays);
    assert_eq!(tally.hits, rays.len(), "{tally:?}");
}

/// A million triangles of different sizes sharing one centroid: the builder
/// falls back to index medians; depth stays bounded, traversal exact.
#[test]
fn million_triangles_with_one_centroid() {
    let n = 1_000_000;
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|i| {
            let s = 1.0 + (i % 1000) as f32 * 0.01;
            // Box [-s, s]^2 x [0, 0]: centre at the origin for every size.
            [
                Vec3::new(-s, -s, 0.0),
                Vec3::new(s, -s, 0.0),
                Vec3::new(0.0, s, 0.0),
            ]
        })
        .collect();
    let mesh = TriangleMesh::from_triangles(&tris).unwrap();
    let bvh = build(&mesh);
    let depth = assert_depth_bounded(&bvh);
    assert!(
        depth >= 17,
        "a million primitives need depth >= 17, got {depth}"
    );
    let mut r = rng(22);
    check_rays(
        "one centroid",
        &mesh,
        &bvh,
        &aimed_rays(&mut r, 12, &mesh.bounds()),
    );
}

/// A million triangles with centroids on one line (unequal spacing), plus
/// the same with every centroid duplicated.
#[test]
fn million_collinear_triangles() {
    let n = 1_000_000;
    let mut r = rng(23);
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|i| {
            let x = if i % 2 == 0 {
                i as f32 * 1e-3
            } else {
                r.gen_range(0.0..1000.0)
            };
            let c = Vec3::new(x, 2.0 * x, -x);
            [
                c + Vec3::new(-0.1, 0.0, 0.0),
                c + Vec3::new(0.1, 0.0, 0.0),
                c + Vec3::new(0.0, 0.1, 0.1),
            ]
        })
        .collect();
    let mesh = TriangleMesh::from_triangles(&tris).unwrap();
    let bvh = build(&mesh);
    assert_depth_bounded(&bvh);
    check_rays(
        "collinear",
        &mesh,
        &bvh,
        &aimed_rays(&mut r, 12, &mesh.bounds()),
    );
}

/// Centroids at `1.05^i` (and `-1.05^i`) up to the largest coordinate a
/// mesh may have (`MAX_COORDINATE`, 1.844e18): each SAH split peels off a
/// few primitives, the worst case for depth, and the SAH costs of the top
/// splits (areas near 1e37 times hundreds of primitives) overflow to
/// infinity. (Up to 1e36, as before the limit, the areas themselves
/// overflowed.)
#[test]
fn exponentially_spaced_centroids() {
    let mut tris = Vec::new();
    for i in 0..850 {
        let x = 1.05f32.powi(i);
        for sign in [1.0, -1.0] {
            let c = Vec3::new(sign * x, 0.0, 0.0);
            let s = 0.01 * x;
            tris.push([
                c - Vec3::splat(s),
                c + Vec3::new(s, -s, 0.0),
                c + Vec3::new(0.0, s, s),
            ]);
        }
    }
    assert!(tris.iter().flatten().all(|v| v.is_finite()));
    let mesh = TriangleMesh::from_triangles(&tris).unwrap();
    for max_leaf_size in [1, 4] {
        let bvh = build_with(
            &mesh,
            &BuildParams {
                max_leaf_size,
                ..BuildParams::default()
            },
        );
        let depth = assert_depth_bounded(&bvh);
        println!("exponential spacing, leaf {max_leaf_size}: depth {depth}");
        // Rays along the line of centroids and across it at every scale.
        let mut rays = vec![
            Ray::infinite(Vec3::new(-1e38, 0.0, 0.0), Vec3::X),
            Ray::infinite(Vec3::new(1e38, 0.0, 0.0), -Vec3::X),
            Ray::infinite(Vec3::ZERO, Vec3::X),
        ];
        for t in &tris[..400] {
            let c = (t[0] + t[1] + t[2]) / 3.0;
            rays.push(Ray::infinite(c + Vec3::new(0.0, 0.0, c.x.abs()), -Vec3::Z));
        }
        let tally = check_rays("exponential", &mesh, &bvh, &rays);
        assert!(tally.hits > 300, "{tally:?}");
    }
}

/// Two groups of triangles whose centroids differ on x by the smallest
/// subnormal: a binning scale of `bins / extent` overflows to infinity there
/// (and `0 * inf` is NaN), and x is the axis a tie picks. The builder must
/// still agree with itself on every split.
#[test]
fn centroids_a_subnormal_apart() {
    let tiny = f32::from_bits(1);
    let mut tris = Vec::new();
    for i in 0..64 {
        for (x, y0) in [(0.0, 0.0), (tiny, 10.0)] {
            let y = y0 + i as f32 / 64.0;
            tris.push([
                Vec3::new(x, y, 0.0),
                Vec3::new(x, y + 0.01, 0.0),
                Vec3::new(x, y, 0.01),
            ]);
        }
    }
    let mesh = TriangleMesh::from_triangles(&tris).unwrap();
    let bvh = build_with(&mesh, &BuildParams::default());
    assert_depth_bounded(&bvh);
    let rays: Vec<Ray> = tris
        .iter()
        .map(|t| Ray::infinite(Vec3::new(-1.0, t[0].y + 0.002, 0.002), Vec3::X))
        .collect();
    let tally = check_rays("subnormal apart", &mesh, &bvh, &rays);
    assert!(tally.hits >= 100, "{tally:?}");
}

/// Rays with zero direction components, signed zeros, origins exactly on the
/// cube's face planes and on its edges, and rays lying in a face's plane.
#[test]
fn axis_parallel_rays() {
    let mesh = unit_cube();
    let grid = grid(8, 8);
    for (label, mesh) in [("cube", &mesh), ("grid", &grid)] {
        for max_leaf_size in [1, 8] {
            let bvh = build_with(
                mesh,
                &BuildParams {
                    max_leaf_size,
                    ..BuildParams::default()
                },
            );
            let b = mesh.bounds();
            let mut rays = Vec::new();
            let coords = [-0.5, 0.0, 0.25, 0.5, 1.0, 2.0, 8.0];
            for &x in &coords {
                for &y in &coords {
                    for &z in &[-1.0, 0.0, 0.5, 1.0, 3.0] {
                        let o = Vec3::new(x, y, z);
                        for axis in 0..3 {
                            for s in [1.0f32, -1.0] {
                                let mut d = Vec3::splat(0.0) * s; // signed zeros
                                d[axis] = s;
                                rays.push(Ray::infinite(o, d));
                                rays.push(Ray::infinite(o, d * 3.5));
                            }
                        }
                        // Two zero components out of three, diagonal in the others.
                        rays.push(Ray::infinite(o, Vec3::new(1.0, 1.0, 0.0)));
                        rays.push(Ray::infinite(o, Vec3::new(0.0, -1.0, -1.0)));
                    }
                }
            }
            let tally = check_rays(&format!("{label} axis-parallel"), mesh, &bvh, &rays);
            assert!(tally.hits > rays.len() / 10, "{label}: {tally:?}");
            // Rays through the inside of the cube along each axis, from
            // outside and from inside, must hit.
            if label == "cube" {
                for axis in 0..3 {
                    let mut d = Vec3::ZERO;
                    d[axis] = -1.0;
                    for o in [
                        Vec3::splat(0.5) - d * 2.0,
                        Vec3::splat(0.5),
                        b.max,
                        b.min - d * 0.5,
                    ] {
                        assert!(
                            bvh.intersect(&Ray::infinite(o, d)).is_some(),
                            "missed along {d} from {o}"
                        );
                    }
                }
            }
        }
    }
}

/// Rays from inside a closed mesh hit it in every direction, at t >= 0.
#[test]
fn rays_starting_inside_the_scene() {
    let mut r = rng(24);
    let cube = unit_cube();
    let bvh = build(&cube);
    for _ in 0..2_000 {
        let o = point_in(&mut r, &Aabb::new(Vec3::splat(0.01), Vec3::splat(0.99)));
        let ray = Ray::infinite(o, unit_dir(&mut r));
        let h = bvh
            .intersect(&ray)
            .expect("a ray from inside the cube hits it");
        assert!(h.t >= 0.0);
        check_ray(&cube, &bvh, &ray).unwrap();
    }
    // Origins inside a dense soup.
    let soup = random_soup(&mut r, 2_000, 5.0, 1.0);
    let bvh = build(&soup);
    let rays: Vec<Ray> = (0..5_000)
        .map(|_| Ray::infinite(point_in(&mut r, &soup.bounds()), unit_dir(&mut r)))
        .collect();
    check_rays("inside soup", &soup, &bvh, &rays);
}

/// Two parallel quads at `z = 0` and `z = -1`, ray from `z = 1` downwards:
/// `t_max` cuts hits off (inclusive bound), `t_min` skips them (inclusive).
#[test]
fn ray_interval_clips_hits() {
    let mut mesh = grid(2, 2);
    let base = mesh.positions.len() as u32;
    mesh.positions
        .extend(grid(2, 2).positions.iter().map(|p| *p - Vec3::Z));
    mesh.indices
        .extend(grid(2, 2).indices.iter().map(|t| t.map(|i| i + base)));
    let bvh = build(&mesh);
    let o = Vec3::new(0.3, 0.6, 1.0);
    let t = |t_min: f32, t_max: f32| hit(&bvh, o, -Vec3::Z, t_min, t_max).map(|h| h.t);
    assert_eq!(t(0.0, f32::INFINITY), Some(1.0));
    assert_eq!(t(0.0, 0.999), None);
    assert_eq!(t(0.0, 1.0), Some(1.0));
    assert_eq!(t(1.0, 1.0), Some(1.0));
    assert_eq!(t(1.0001, f32::INFINITY), Some(2.0));
    assert_eq!(t(1.5, 1.9), None);
    assert_eq!(t(2.0, 5.0), Some(2.0));
    assert_eq!(t(2.0001, f32::INFINITY), None);
    for (t_min, t_max, occluded) in [
        (0.0, 0.999, false),
        (0.0, 1.0, true),
        (1.5, 1.9, false),
        (1.5, 2.0, true),
        (2.5, 9.0, false),
    ] {
        let ray = Ray::new(o, -Vec3::Z, t_min, t_max).unwrap();
        assert_eq!(bvh.occluded(&ray), occluded, "[{t_min}, {t_max}]");
        assert_eq!(brute_force_occluded(&mesh, &ray), occluded);
    }
}

#[test]
fn non_finite_vertices_are_rejected() {
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let positions = vec![Vec3::ZERO, Vec3::X, Vec3::new(0.0, bad, 0.0)];
        let err = TriangleMesh::new(positions.clone(), vec![[0, 1, 2]]).unwrap_err();
        assert!(
            matches!(err, Error::NonFiniteVertex { index: 2, .. }),
            "{err:?}"
        );
        // A mesh assembled without the check is caught by the build.
        let unchecked = TriangleMesh {
            positions,
            indices: vec![[0, 1, 2]],
        };
        let err = MeshBvh::build(&unchecked, &BuildParams::default()).unwrap_err();
        assert!(
            matches!(err, Error::NonFiniteVertex { index: 2, .. }),
            "{err:?}"
        );
    }
    // Even a vertex no triangle uses.
    let err = TriangleMesh::new(
        vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::NAN],
        vec![[0, 1, 2]],
    )
    .unwrap_err();
    assert!(
        matches!(err, Error::NonFiniteVertex { index: 3, .. }),
        "{err:?}"
    );
}

#[test]
fn out_of_range_indices_are_rejected() {
    let err = TriangleMesh::new(
        vec![Vec3::ZERO, Vec3::X, Vec3::Y],
        vec![[0, 1, 2], [0, 3, 1]],
    )
    .unwrap_err();
    assert_eq!(
        err,
        Error::IndexOutOfRange {
            triangle: 1,
            vertex: 3,
            vertex_count: 3
        }
    );
    let unchecked = TriangleMesh {
        positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
        indices: vec![[0, 1, u32::MAX]],
    };
    let err = MeshBvh::build(&unchecked, &BuildParams::default()).unwrap_err();
    assert!(
        matches!(
            err,
            Error::IndexOutOfRange {
                triangle: 0,
                vertex: u32::MAX,
                ..
            }
        ),
        "{err:?}"
    );
}

/// `Ray::new` rejects what queries would never hit; the same rays built
/// without the check hit nothing, in the BVH and in the reference.
#[test]
fn invalid_rays_error_and_never_hit() {
    let mesh = unit_cube();
    let bvh = build(&mesh);
    let inside = Vec3::splat(0.5);
    let bad = [
        (inside, Vec3::ZERO, 0.0, f32::INFINITY),
        (inside, -Vec3::ZERO, 0.0, 1.0),
        (Vec3::NAN, Vec3::X, 0.0, 1.0),
        (Vec3::new(0.5, f32::INFINITY, 0.5), Vec3::X, 0.0, 1.0),
        (inside, Vec3::new(f32::NAN, 1.0, 0.0), 0.0, 1.0),
        (inside, Vec3::new(f32::INFINITY, 0.0, 0.0), 0.0, 1.0),
        (inside, Vec3::X, f32::NAN, 1.0),
        (inside, Vec3::X, 0.0, f32::NAN),
        (inside, Vec3::X, 2.0, 1.0),
    ];
    for (origin, dir, t_min, t_max) in bad {
        assert!(
            matches!(
                Ray::new(origin, dir, t_min, t_max),
                Err(Error::InvalidRay(_))
            ),
            "{origin} {dir} {t_min} {t_max}"
        );
        let ray = Ray {
            origin,
            dir,
            t_min,
            t_max,
        };
        assert_eq!(bvh.intersect(&ray), None, "{ray:?}");
        assert!(!bvh.occluded(&ray), "{ray:?}");
        assert_eq!(brute_force_intersect(&mesh, &ray), None);
        assert!(!brute_force_occluded(&mesh, &ray));
    }
    assert!(matches!(
        Ray::new(inside, Vec3::X, -1.0, 1.0),
        Err(Error::InvalidRay(_))
    ));
    // The same origin with a valid direction does hit.
    assert!(
        bvh.intersect(&Ray::new(inside, Vec3::X, 0.0, f32::INFINITY).unwrap())
            .is_some()
    );
}

/// Zero-area triangles (repeated vertices, collinear vertices) are accepted,
/// kept in the tree, and never hit, even by rays aimed straight at them.
#[test]
fn degenerate_triangles_are_accepted_and_never_hit() {
    let mut r = rng(25);
    let mut tris = Vec::new();
    let mut degenerate = Vec::new();
    for i in 0..3_000 {
        let a = Vec3::new(r.r#gen(), r.r#gen(), r.r#gen()) * 10.0;
        let b = a + unit_dir(&mut r);
        let tri = match i % 4 {
            0 => [a, a, a],
            1 => [a, a, b],
            2 => {
                // Collinear along an axis, so exactly collinear in f32 too.
                let step = Vec3::AXES[i % 3] * r.gen_range(0.1..1.0);
                [a, a + step, a + step * 3.0]
            }
            _ => [a, b, a + unit_dir(&mut r)],
        };
        if i % 4 != 3 {
            degenerate.push(i as u32);
        }
        tris.push(tri);
    }
    let mesh = TriangleMesh::from_triangles(&tris).unwrap();
    let bvh = build(&mesh);
    assert_eq!(bvh.len(), 3_000);
    let mut rays = random_rays(&mut r, 10_000, &mesh.bounds());
    for &i in &degenerate {
        let [a, b, _] = tris[i as usize];
        let target = (a + b) * 0.5;
        let origin = target + unit_dir(&mut r);
        rays.push(Ray::infinite(origin, target - origin));
        rays.push(Ray::infinite(a + Vec3::Z, -Vec3::Z));
    }
    check_rays("degenerate", &mesh, &bvh, &rays);
    for ray in &rays {
        if let Some(h) = bvh.intersect(ray) {
            assert_eq!(h.prim_id % 4, 3, "a degenerate triangle was hit: {h:?}");
        }
    }
    // A mesh of nothing but degenerate triangles.
    let flat: Vec<[Vec3; 3]> = tris.iter().step_by(4).copied().collect();
    let mesh = TriangleMesh::from_triangles(&flat).unwrap();
    let bvh = build(&mesh);
    assert!(
        rays.iter()
            .all(|ray| bvh.intersect(ray).is_none() && !bvh.occluded(ray))
    );
}

#[test]
fn invalid_build_params_are_rejected() {
    let mesh = unit_cube();
    let (boxes, centroids) = mesh.prim_boxes();
    let d = BuildParams::default();
    let bad = [
        BuildParams {
            bins: 0,
            ..d.clone()
        },
        BuildParams {
            bins: 1,
            ..d.clone()
        },
        BuildParams {
            bins: MAX_BINS + 1,
            ..d.clone()
        },
        BuildParams {
            max_leaf_size: 0,
            ..d.clone()
        },
        BuildParams {
            traversal_cost: -1.0,
            ..d.clone()
        },
        BuildParams {
            traversal_cost: f32::NAN,
            ..d.clone()
        },
        BuildParams {
            traversal_cost: f32::INFINITY,
            ..d.clone()
        },
        BuildParams {
            intersection_cost: 0.0,
            ..d.clone()
        },
        BuildParams {
            intersection_cost: f32::NAN,
            ..d.clone()
        },
        BuildParams {
            intersection_cost: f32::INFINITY,
            ..d.clone()
        },
    ];
    for p in &bad {
        assert!(
            matches!(p.check(), Err(Error::InvalidParameter(_))),
            "{p:?}"
        );
        assert!(
            matches!(MeshBvh::build(&mesh, p), Err(Error::InvalidParameter(_))),
            "{p:?}"
        );
        assert!(
            matches!(
                build_bvh(&boxes, &centroids, p),
                Err(Error::InvalidParameter(_))
            ),
            "{p:?}"
        );
        // Even with nothing to build.
        assert!(build_bvh(&[], &[], p).is_err(), "{p:?}");
    }
    // The extremes of the valid ranges are fine.
    for p in [
        BuildParams {
            bins: 2,
            ..d.clone()
        },
        BuildParams {
            bins: MAX_BINS,
            ..d.clone()
        },
        BuildParams {
            max_leaf_size: 1,
            traversal_cost: 0.0,
            ..d.clone()
        },
        BuildParams {
            max_leaf_size: u32::MAX,
            parallel_threshold: 0,
            ..d.clone()
        },
    ] {
        build_with(&mesh, &p);
    }
}

/// `build_bvh` checks its own inputs: matching lengths, finite non-empty boxes.
#[test]
fn invalid_boxes_are_rejected() {
    let d = BuildParams::default();
    let unit = Aabb::new(Vec3::ZERO, Vec3::ONE);
    let c = Vec3::splat(0.5);
    assert!(matches!(
        build_bvh(&[unit, unit], &[c], &d),
        Err(Error::InvalidParameter(_))
    ));
    let cases: [(Vec<Aabb>, Vec<Vec3>, usize); 4] = [
        (vec![unit, Aabb::EMPTY], vec![c, c], 1),
        (
            vec![
                unit,
                unit,
                Aabb::new(Vec3::ZERO, Vec3::splat(f32::INFINITY)),
            ],
            vec![c; 3],
            2,
        ),
        (vec![Aabb::new(Vec3::NAN, Vec3::ONE)], vec![c], 0),
        (vec![unit, unit], vec![c, Vec3::NAN], 1),
    ];
    for (boxes, centroids, index) in cases {
        assert_eq!(
            build_bvh(&boxes, &centroids, &d),
            Err(Error::InvalidBounds { index })
        );
    }
    // Long inputs take the chunked parallel pass: the first bad primitive
    // is named whichever chunk it is in, and an inverted box counts.
    let n = 100_000;
    let bad: [(usize, Aabb, Vec3); 4] = [
        (70_001, Aabb::new(Vec3::ONE, Vec3::ZERO), c),
        (40_000, unit, Vec3::new(0.5, f32::INFINITY, 0.5)),
        (
            99_999,
            Aabb::new(Vec3::ZERO, Vec3::new(1.0, f32::NAN, 1.0)),
            c,
        ),
        (3, Aabb::new(Vec3::splat(f32::NEG_INFINITY), Vec3::ONE), c),
    ];
    // Each alone, then all four (the first one wins).
    let sets: Vec<&[(usize, Aabb, Vec3)]> =
        vec![&bad[0..1], &bad[1..2], &bad[2..3], &bad[3..4], &bad];
    for set in sets {
        let (mut boxes, mut centroids) = (vec![unit; n], vec![c; n]);
        for &(i, b, cc) in set {
            boxes[i] = b;
            centroids[i] = cc;
        }
        let first = set.iter().map(|x| x.0).min().unwrap();
        assert_eq!(
            build_bvh(&boxes, &centroids, &d),
            Err(Error::InvalidBounds { index: first })
        );
    }
    assert!(build_bvh(&vec![unit; n], &vec![c; n], &d).is_ok());
}

/// Coordinates beyond `MAX_COORDINATE` (Embree's `FLT_LARGE`, 1.844e18)
/// are refused with their own error, in a mesh, in moved vertices and in a
/// key-framed mesh; a mesh just inside it builds and is hit.
#[test]
fn coordinates_beyond_the_limit_are_rejected() {
    use rebraid::mesh::MAX_COORDINATE;
    for big in [1e19, -3e38, f32::MAX] {
        let positions = vec![Vec3::ZERO, Vec3::X, Vec3::new(0.0, 0.0, big)];
        let err = TriangleMesh::new(positions.clone(), vec![[0, 1, 2]]).unwrap_err();
        assert!(
            matches!(err, Error::VertexOutOfRange { index: 2, .. }),
            "{err:?}"
        );
        assert!(err.to_string().contains("vertex 2"), "{err}");
        let mut scene = rebraid::Scene::new();
        let id = scene
            .add_object(
                TriangleMesh::new(vec![Vec3::ZERO, Vec3::X, Vec3::Y], vec![[0, 1, 2]]).unwrap(),
            )
            .unwrap();
        let err = scene.set_vertices(id, &positions).unwrap_err();
        assert!(
            matches!(err, Error::VertexOutOfRange { index: 2, .. }),
            "{err:?}"
        );
    }
    // NaN among large values is still named non-finite.
    let err = TriangleMesh::new(
        vec![Vec3::ZERO, Vec3::X, Vec3::new(f32::NAN, 0.0, 0.0)],
        vec![[0, 1, 2]],
    )
    .unwrap_err();
    assert!(
        matches!(err, Error::NonFiniteVertex { index: 2, .. }),
        "{err:?}"
    );
    // Just inside: built and hit.
    let m = MAX_COORDINATE * 0.5;
    let mesh = TriangleMesh::new(
        vec![
            Vec3::new(-m, -m, 1.0),
            Vec3::new(m, -m, 1.0),
            Vec3::new(0.0, m, 1.0),
        ],
        vec![[0, 1, 2]],
    )
    .unwrap();
    let bvh = MeshBvh::build(&mesh, &BuildParams::default()).unwrap();
    let hit = bvh.intersect(&Ray::infinite(Vec3::ZERO, Vec3::Z)).unwrap();
    assert_eq!(hit.t, 1.0);
}
