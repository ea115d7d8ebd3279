//! Wide BVH kernels against the scalar binary traversal, one thread:
//! closest-hit and occlusion Mrays/s of coherent camera rays and incoherent
//! random rays for the binary `MeshBvh`, the W = 4 and W = 8 trees with the
//! scalar-lane reference kernel, W = 4 with SSE4.1 and W = 8 with SSE4.1
//! (two halves) and AVX2.
//!
//! Scenes: the generated ~1M-triangle scene of the `kernel` bench, and
//! `openarena_oa_thor.obj` and `samurai_monastery.obj` from
//! `$REBRAID_SCENES` (skipped with a message when missing). Before anything
//! is timed, every kernel's answers on the scene's rays are checked against
//! the binary kernel's (same `t`, same occlusion), as tinybvh's benchmarks
//! do, so a fast wrong kernel cannot report a figure.
//!
//! Run: `cargo bench -p rebraid --bench wide`.

#[path = "../tests/common/mod.rs"]
mod common;
mod support;

use divan::counter::ItemsCount;
use divan::{Bencher, black_box};
use rebraid::bvh::{Kernel, WideMeshBvh};
use rebraid::{BuildParams, MeshBvh, Ray};

fn main() {
    for scene in SCENES {
        prepared(scene);
    }
    divan::main();
}

const SCENES: [&str; 3] = ["generated_1m", "openarena_oa_thor", "samurai_monastery"];
/// Rays per sample: a 256 x 256 image, or as many random rays.
const RAYS: usize = 256 * 256;

/// The traversal variants, as `divan` arguments.
const VARIANTS: [&str; 6] = [
    "binary_scalar",
    "w4_scalar",
    "w4_sse",
    "w8_scalar",
    "w8_sse",
    "w8_avx2",
];

struct Prepared {
    bvh: MeshBvh,
    w4: WideMeshBvh<4>,
    w8: WideMeshBvh<8>,
    coherent: Vec<Ray>,
    incoherent: Vec<Ray>,
}

/// The kernel of a wide variant, or `None` for the binary one or one this
/// CPU cannot run.
fn kernel_of(variant: &str) -> Option<Kernel> {
    let k = match variant.split('_').nth(1)? {
        "scalar" if variant != "binary_scalar" => Kernel::Scalar,
        "sse" => Kernel::Sse,
        "avx2" => Kernel::Avx2,
        _ => return None,
    };
    k.is_available().then_some(k)
}

/// Closest-hit `t` (bits) and occlusion of one ray by one variant.
fn answer(p: &Prepared, variant: &str, r: &Ray) -> (Option<u32>, bool) {
    let t = |h: Option<rebraid::Hit>| h.map(|h| h.t.to_bits());
    match (variant.starts_with("w4"), kernel_of(variant)) {
        (true, Some(k)) => (t(p.w4.intersect_with(k, r)), p.w4.occluded_with(k, r)),
        (false, Some(k)) => (t(p.w8.intersect_with(k, r)), p.w8.occluded_with(k, r)),
        _ => (t(p.bvh.intersect(r)), p.bvh.occluded(r)),
    }
}

fn prepared(name: &'static str) -> Option<&'static Prepared> {
    static CACHE: support::SceneCache<Prepared> = support::SceneCache::new();
    support::cached(&CACHE, name, || {
        let mesh = support::load(name)?;
        let bvh = MeshBvh::build(&mesh, &BuildParams::default()).unwrap();
        let w4 = WideMeshBvh::<4>::from_mesh(&bvh).unwrap();
        let w8 = WideMeshBvh::<8>::from_mesh(&bvh).unwrap();
        w4.validate().unwrap();
        w8.validate().unwrap();
        let b = mesh.bounds();
        let p = Prepared {
            bvh,
            w4,
            w8,
            coherent: support::camera_rays(&b, RAYS),
            incoherent: support::random_rays(&b, RAYS),
        };
        // Validate every kernel against the binary scalar kernel first.
        for rays in [&p.coherent, &p.incoherent] {
            let want: Vec<_> = rays
                .iter()
                .map(|r| answer(&p, "binary_scalar", r))
                .collect();
            for v in VARIANTS.iter().filter(|v| kernel_of(v).is_some()) {
                let bad = rays
                    .iter()
                    .zip(&want)
                    .filter(|(r, w)| answer(&p, v, r) != **w)
                    .count();
                assert_eq!(
                    bad, 0,
                    "{name}: {v} disagrees with the binary kernel on {bad} rays"
                );
            }
        }
        let (s4, s8) = (p.w4.wide.stats(), p.w8.wide.stats());
        eprintln!(
            "{name}: {} triangles; binary {} nodes ({} KB); W=4 {} nodes ({} KB, depth {}); \
             W=8 {} nodes ({} KB, depth {}); all kernels agree with the binary one",
            mesh.len(),
            p.bvh.bvh.nodes.len(),
            p.bvh.bvh.nodes.len() * 32 / 1024,
            s4.nodes,
            s4.bytes / 1024,
            s4.max_depth,
            s8.nodes,
            s8.bytes / 1024,
            s8.max_depth,
        );
        Some(p)
    })
}

#[derive(Clone, Copy)]
enum Query {
    Closest,
    Occluded,
}

/// One thread, no pool: a plain loop over the rays.
fn trace(bencher: Bencher, case: &str, coherent: bool, query: Query) {
    let Some((p, variant)) = support::case(case, &SCENES, prepared) else {
        return;
    };
    let kernel = kernel_of(variant);
    if variant != "binary_scalar" && kernel.is_none() {
        eprintln!("SKIPPED: {variant} not supported by this CPU");
        return;
    }
    let rays = if coherent { &p.coherent } else { &p.incoherent };
    let w4 = variant.starts_with("w4");
    bencher
        .counter(ItemsCount::new(rays.len()))
        .bench_local(|| {
            let mut n = 0usize;
            for r in black_box(rays) {
                let hit = match (query, kernel) {
                    (Query::Closest, None) => p.bvh.intersect(r).is_some(),
                    (Query::Occluded, None) => p.bvh.occluded(r),
                    (Query::Closest, Some(k)) if w4 => p.w4.intersect_with(k, r).is_some(),
                    (Query::Occluded, Some(k)) if w4 => p.w4.occluded_with(k, r),
                    (Query::Closest, Some(k)) => p.w8.intersect_with(k, r).is_some(),
                    (Query::Occluded, Some(k)) => p.w8.occluded_with(k, r),
                };
                n += hit as usize;
            }
            n
        });
}

fn cases() -> Vec<&'static str> {
    support::cases(&SCENES, &VARIANTS)
}

#[divan::bench(args = cases(), sample_count = 8)]
fn closest_coherent(b: Bencher, case: &str) {
    trace(b, case, true, Query::Closest);
}
#[divan::bench(args = cases(), sample_count = 8)]
fn closest_incoherent(b: Bencher, case: &str) {
    trace(b, case, false, Query::Closest);
}
#[divan::bench(args = cases(), sample_count = 8)]
fn occluded_coherent(b: Bencher, case: &str) {
    trace(b, case, true, Query::Occluded);
}
#[divan::bench(args = cases(), sample_count = 8)]
fn occluded_incoherent(b: Bencher, case: &str) {
    trace(b, case, false, Query::Occluded);
}
