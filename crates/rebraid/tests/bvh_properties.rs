//! Property tests of the builder and the kernels: structural invariants of
//! `build_bvh` on arbitrary boxes, identical trees for any thread count, and
//! watertightness on closed meshes.
mod common;

use std::sync::OnceLock;

use common::*;
use proptest::prelude::*;
use rand::Rng;
use rebraid::bvh::binning::MAX_BINS;
use rebraid::bvh::{BinBox, MAX_DEPTH, build_bvh, build_bvh_aligned};
use rebraid::glam::{Quat, Vec3, Vec3A};
use rebraid::{Aabb, BuildParams, Bvh, MeshBvh, Ray, TriangleMesh};

/// The flavours of input the builder must survive.
#[derive(Clone, Copy, Debug)]
enum BoxKind {
    /// Independent boxes of random size.
    Random,
    /// Few distinct boxes, each repeated many times (same box, same centroid).
    Duplicates,
    /// Boxes flat along one or more axes (points, segments, axis planes).
    Flat,
    /// Random boxes whose centroids lie on one line.
    Collinear,
    /// Boxes on an integer lattice: many exact ties in the SAH sweep.
    Lattice,
}

const KINDS: [BoxKind; 5] = [
    BoxKind::Random,
    BoxKind::Duplicates,
    BoxKind::Flat,
    BoxKind::Collinear,
    BoxKind::Lattice,
];

/// Seeded boxes and centroids (box centres) of one kind.
fn boxes_of(kind: BoxKind, n: usize, seed: u64) -> (Vec<Aabb>, Vec<Vec3>) {
    let mut r = rng(seed);
    let distinct: Vec<Aabb> = (0..8)
        .map(|_| {
            let c = Vec3::new(r.r#gen(), r.r#gen(), r.r#gen()) * 10.0;
            Aabb::new(c, c + Vec3::new(r.r#gen(), r.r#gen(), r.r#gen()))
        })
        .collect();
    let boxes: Vec<Aabb> = (0..n)
        .map(|i| match kind {
            BoxKind::Random => {
                let c = Vec3::new(r.r#gen(), r.r#gen(), r.r#gen()) * 100.0;
                let e = Vec3::new(r.r#gen(), r.r#gen(), r.r#gen()) * r.gen_range(0.0..20.0);
                Aabb::new(c - e, c + e)
            }
            BoxKind::Duplicates => distinct[r.gen_range(0..distinct.len())],
            BoxKind::Flat => {
                let c = Vec3::new(r.r#gen(), r.r#gen(), r.r#gen()) * 10.0;
                let mut e = Vec3::new(r.r#gen(), r.r#gen(), r.r#gen());
                for axis in 0..3 {
                    if r.gen_bool(0.6) {
                        e[axis] = 0.0;
                    }
                }
                Aabb::new(c, c + e)
            }
            BoxKind::Collinear => {
                let c = Vec3::new(1.0, 2.0, 3.0) * r.gen_range(-10.0..10.0f32);
                let e = Vec3::new(r.r#gen(), r.r#gen(), r.r#gen());
                Aabb::new(c - e, c + e)
            }
            BoxKind::Lattice => {
                let c = Vec3::new((i % 7) as f32, (i % 5) as f32, (i % 3) as f32);
                Aabb::new(c, c + Vec3::ONE)
            }
        })
        .collect();
    let centroids = boxes.iter().map(Aabb::center).collect();
    (boxes, centroids)
}

/// Check everything a built tree promises about its own structure.
fn check_structure(bvh: &Bvh, boxes: &[Aabb], params: &BuildParams) -> Result<(), TestCaseError> {
    let n = boxes.len();
    bvh.validate(boxes).map_err(TestCaseError::fail)?;
    let stats = bvh.stats(Default::default());
    prop_assert_eq!(stats.primitives, n);
    prop_assert_eq!(stats.leaves + stats.inner_nodes, stats.nodes);
    prop_assert_eq!(stats.nodes, bvh.nodes.len());
    prop_assert_eq!(stats.nodes, 2 * stats.leaves - 1);
    prop_assert!(stats.max_depth <= MAX_DEPTH);
    let mut leaf_total = 0;
    for node in bvh.nodes.iter().filter(|n| n.is_leaf()) {
        prop_assert!(
            node.count <= params.max_leaf_size,
            "leaf of {} > {}",
            node.count,
            params.max_leaf_size
        );
        leaf_total += node.count as usize;
    }
    prop_assert_eq!(leaf_total, n);
    let mut ids = bvh.prim_indices.clone();
    ids.sort_unstable();
    prop_assert!(
        ids.iter().copied().eq(0..n as u32),
        "not every primitive exactly once"
    );
    // The root box is the union of the inputs, exactly.
    let all = boxes.iter().fold(Aabb::EMPTY, |a, b| a.union(*b));
    prop_assert_eq!(bvh.bounds(), all);
    Ok(())
}

/// Pools of 1, 2 and 4 threads, built once per test binary.
fn pools() -> &'static [rayon::ThreadPool] {
    static POOLS: OnceLock<Vec<rayon::ThreadPool>> = OnceLock::new();
    POOLS.get_or_init(|| {
        [1, 2, 4]
            .iter()
            .map(|&t| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .unwrap()
            })
            .collect()
    })
}

fn kind_strategy() -> impl Strategy<Value = BoxKind> {
    (0..KINDS.len()).prop_map(|k| KINDS[k])
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 160, ..ProptestConfig::default() })]

    /// Any finite, non-empty boxes give a valid tree with consistent stats.
    #[test]
    fn builder_invariants(
        kind in kind_strategy(),
        n in 1usize..600,
        seed in any::<u64>(),
        bins in 2usize..=MAX_BINS,
        max_leaf_size in 1u32..12,
        traversal_cost in 0.0f32..4.0,
    ) {
        let (boxes, centroids) = boxes_of(kind, n, seed);
        let params = BuildParams { bins, max_leaf_size, traversal_cost, ..BuildParams::default() };
        let bvh = build_bvh(&boxes, &centroids, &params).unwrap();
        check_structure(&bvh, &boxes, &params)?;
    }

    /// Centroids need not be box centres: any finite point per box will do.
    #[test]
    fn builder_accepts_arbitrary_centroids(n in 1usize..300, seed in any::<u64>()) {
        let (boxes, _) = boxes_of(BoxKind::Random, n, seed);
        let mut r = rng(seed ^ 0x5eed);
        let centroids: Vec<Vec3> = (0..n)
            .map(|_| if r.gen_bool(0.3) { Vec3::ZERO } else { Vec3::new(r.r#gen(), r.r#gen(), r.r#gen()) * 1e3 })
            .collect();
        let params = BuildParams::default();
        let bvh = build_bvh(&boxes, &centroids, &params).unwrap();
        check_structure(&bvh, &boxes, &params)?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 6, ..ProptestConfig::default() })]

    /// The same input gives the same tree in pools of 1, 2 and 4 threads,
    /// including inputs large enough (> 1 << 15 per range) for the chunked
    /// parallel binning and partitioning.
    #[test]
    fn tree_is_independent_of_thread_count(
        kind in kind_strategy(),
        large in any::<bool>(),
        seed in any::<u64>(),
        parallel_threshold in prop_oneof![Just(0usize), Just(4096), Just(100_000)],
    ) {
        let n = if large { 120_000 + (seed % 20_000) as usize } else { 1 + (seed % 5_000) as usize };
        let (boxes, centroids) = boxes_of(kind, n, seed);
        let params = BuildParams { parallel_threshold, ..BuildParams::default() };
        let trees: Vec<Bvh> = pools()
            .iter()
            .map(|pool| pool.install(|| build_bvh(&boxes, &centroids, &params).unwrap()))
            .collect();
        prop_assert!(trees[0] == trees[1], "1 and 2 threads differ");
        prop_assert!(trees[0] == trees[2], "1 and 4 threads differ");
        check_structure(&trees[0], &boxes, &params)?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, ..ProptestConfig::default() })]

    /// How the build is cut into tasks does not show in the result: every
    /// parallel threshold (each task's subtree laid out by the final pass)
    /// gives the same nodes in the same order, and the aligned entry point
    /// gives what `build_bvh` gives.
    #[test]
    fn tree_is_independent_of_task_size(
        kind in kind_strategy(),
        n in 1usize..6_000,
        seed in any::<u64>(),
    ) {
        let (boxes, centroids) = boxes_of(kind, n, seed);
        let build = |parallel_threshold| {
            let params = BuildParams { parallel_threshold, ..BuildParams::default() };
            build_bvh(&boxes, &centroids, &params).unwrap()
        };
        let one_task = build(usize::MAX);
        for threshold in [0, 7, 1024] {
            prop_assert!(build(threshold) == one_task, "threshold {threshold} differs");
        }
        let aligned_boxes: Vec<BinBox> = boxes.iter().map(BinBox::from_aabb).collect();
        let aligned_centroids: Vec<Vec3A> = centroids.iter().map(|&c| c.into()).collect();
        let aligned =
            build_bvh_aligned(&aligned_boxes, &aligned_centroids, &BuildParams::default()).unwrap();
        prop_assert!(aligned == build(BuildParams::default().parallel_threshold));
    }
}

/// A mesh BVH over a large soup (> 100k triangles, several chunks per range)
/// is the same in every pool, triangles included.
#[test]
fn mesh_bvh_is_independent_of_thread_count() {
    let mut r = rng(11);
    let mesh = random_soup(&mut r, 130_000, 50.0, 0.5);
    let builds: Vec<MeshBvh> = pools()
        .iter()
        .map(|pool| pool.install(|| MeshBvh::build(&mesh, &BuildParams::default()).unwrap()))
        .collect();
    for b in &builds[1..] {
        assert!(b.bvh == builds[0].bvh, "trees differ between thread counts");
        assert_eq!(b.triangles, builds[0].triangles);
    }
}

/// A closed mesh, randomly rotated, scaled and moved; when `bumpy`, each
/// vertex is also pushed in along its direction from the centre. Radial
/// pushes keep each triangle's projection onto the sphere around `center`, so
/// the mesh stays closed and star-shaped around `center`; unpushed, it is
/// convex. Returns the mesh, its centre and its radius.
fn closed_mesh(ico: bool, detail: u32, bumpy: bool, seed: u64) -> (TriangleMesh, Vec3, f32) {
    let mut r = rng(seed);
    let radius = r.gen_range(0.01..100.0f32);
    let center = Vec3::new(
        r.gen_range(-50.0..50.0),
        r.gen_range(-50.0..50.0),
        r.gen_range(-50.0..50.0),
    );
    let mut mesh = if ico {
        icosphere(detail.min(3), 1.0, Vec3::ZERO)
    } else {
        uv_sphere(2 + detail * 3, 3 + detail * 5, 1.0, Vec3::ZERO)
    };
    let rot = Quat::from_euler(
        rebraid::glam::EulerRot::XYZ,
        r.r#gen(),
        r.r#gen(),
        r.r#gen(),
    );
    for p in &mut mesh.positions {
        let push = if bumpy { r.gen_range(0.7..1.0) } else { 1.0 };
        *p = center + rot * (*p * push * radius);
    }
    (mesh, center, radius)
}

/// The distance from `center` to the nearest face plane: every point closer
/// than that to the centre of a convex mesh is inside it.
fn inradius(mesh: &TriangleMesh, center: Vec3) -> f32 {
    (0..mesh.len())
        .map(|i| {
            let [a, b, c] = mesh.triangle(i);
            let n = (b - a).cross(c - a).normalize();
            (a - center).dot(n).abs()
        })
        .fold(f32::INFINITY, f32::min)
}

/// Rays that must hit the closed mesh: from inside (on segments between the
/// centre and surface points) in every direction; and from outside through
/// each vertex and through points along each edge, aimed at the centre (and,
/// for a convex mesh, at points around the centre), so that each one enters
/// the inside at that vertex or edge instead of grazing it.
fn watertight_rays(
    mesh: &TriangleMesh,
    center: Vec3,
    radius: f32,
    convex: bool,
    seed: u64,
) -> Vec<Ray> {
    let mut r = rng(seed);
    let mut rays = Vec::new();
    for _ in 0..200 {
        let [a, b, c] = mesh.triangle(r.gen_range(0..mesh.len()));
        let (u, v) = (r.r#gen::<f32>(), r.r#gen::<f32>());
        let (u, v) = if u + v > 1.0 {
            (1.0 - u, 1.0 - v)
        } else {
            (u, v)
        };
        let on_surface = a + (b - a) * u + (c - a) * v;
        let origin = center + (on_surface - center) * r.gen_range(0.0..0.95);
        rays.push(Ray::new(origin, unit_dir(&mut r), 0.0, f32::INFINITY).unwrap());
    }
    let aim_radius = if convex {
        0.9 * inradius(mesh, center)
    } else {
        0.0
    };
    let mut through = |p: Vec3, r: &mut rand_pcg::Pcg64| {
        let target = center + unit_dir(r) * r.gen_range(0.0..=aim_radius);
        let origin = p + (p - target).normalize() * r.gen_range(0.5..3.0) * radius;
        rays.push(Ray::new(origin, target - origin, 0.0, f32::INFINITY).unwrap());
    };
    for &v in &mesh.positions {
        through(v, &mut r);
    }
    for tri in &mesh.indices {
        for k in 0..3 {
            let (a, b) = (
                mesh.positions[tri[k] as usize],
                mesh.positions[tri[(k + 1) % 3] as usize],
            );
            through(a + (b - a) * 0.5, &mut r);
            through(a + (b - a) * r.r#gen::<f32>(), &mut r);
        }
    }
    rays
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 32, ..ProptestConfig::default() })]

    /// No ray slips through a closed mesh: through vertices, through edges,
    /// and from the inside.
    #[test]
    fn closed_meshes_are_watertight(
        ico in any::<bool>(),
        detail in 0u32..4,
        bumpy in any::<bool>(),
        seed in any::<u64>(),
        max_leaf_size in 1u32..9,
    ) {
        let (mesh, center, radius) = closed_mesh(ico, detail, bumpy, seed);
        let bvh = build_with(&mesh, &BuildParams { max_leaf_size, ..BuildParams::default() });
        for ray in &watertight_rays(&mesh, center, radius, !bumpy, seed) {
            let tally = check_ray(&mesh, &bvh, ray).map_err(TestCaseError::fail)?;
            prop_assert_eq!(tally.hits, 1, "ray slipped through: {:?}", ray);
        }
    }
}

/// Axis-parallel rays through the vertices of an axis-aligned UV sphere that
/// lie on its axis planes (the poles and the ring vertices at longitude 0):
/// their coordinates are exactly the planes of the leaf boxes around them, so
/// the slab test sees `0 * inf`. Each ray enters the sphere at that vertex.
/// (Regression: such rays used to miss every box they lay on the plane of.)
#[test]
fn axis_parallel_rays_through_vertices_on_box_planes_hit() {
    for (stacks, slices, center) in [
        (8, 8, Vec3::ZERO),
        (9, 12, Vec3::new(0.5, -2.0, 3.0)),
        (4, 4, Vec3::splat(1e3)),
    ] {
        let mesh = uv_sphere(stacks, slices, 1.0, center);
        for max_leaf_size in [1, 4] {
            let bvh = build_with(
                &mesh,
                &BuildParams {
                    max_leaf_size,
                    ..BuildParams::default()
                },
            );
            let mut rays = vec![];
            for (k, &v) in mesh.positions.iter().enumerate() {
                let on_axis_plane =
                    k == 0 || k == mesh.positions.len() - 1 || (k - 1) % slices as usize == 0;
                if !on_axis_plane {
                    continue;
                }
                let out = v - center;
                for axis in [Vec3::X, Vec3::Y, Vec3::Z] {
                    for axis in [axis, -axis] {
                        // Only rays that enter the inside at `v`.
                        if out.dot(axis) > 0.1
                            && (out - axis * out.dot(axis)).dot(out - axis * out.dot(axis)) == 0.0
                            || (axis == Vec3::X && k != 0 && k != mesh.positions.len() - 1)
                        {
                            rays.push(Ray::new(v + axis * 3.0, -axis, 0.0, f32::INFINITY).unwrap());
                        }
                    }
                }
            }
            assert!(
                rays.len() >= stacks as usize,
                "too few rays: {}",
                rays.len()
            );
            for ray in &rays {
                let tally = check_ray(&mesh, &bvh, ray).unwrap();
                assert_eq!(tally.hits, 1, "axis-parallel ray slipped through: {ray:?}");
            }
        }
    }
}

/// Regression (found by `closed_meshes_are_watertight`): a ray through a
/// shared vertex hit one triangle at `t` and a neighbour in another leaf one
/// ulp earlier; that leaf's box entry, computed at the vertex, rounded above
/// the first `t`, so traversal culled it and returned the farther hit.
#[test]
fn closest_hit_through_shared_vertex_is_not_culled() {
    let seed = 765974645078318838;
    let (mesh, center, radius) = closed_mesh(false, 2, false, seed);
    let bvh = build_with(
        &mesh,
        &BuildParams {
            max_leaf_size: 1,
            ..BuildParams::default()
        },
    );
    let rays = watertight_rays(&mesh, center, radius, true, seed);
    let tally = check_rays("uv sphere through vertices", &mesh, &bvh, &rays);
    assert_eq!(tally.hits, tally.rays);
}
