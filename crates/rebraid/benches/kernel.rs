//! Throughput of the core kernel: mesh BVH builds (Mtris/s) and closest-hit
//! and occlusion traversal (Mrays/s) of coherent camera rays and incoherent
//! random rays, on one thread and on all threads.
//!
//! Scenes: a generated one of about a million triangles (a terrain and many
//! spheres), and the real `openarena_oa_thor.obj` and
//! `samurai_monastery.obj` from `$REBRAID_SCENES` (default
//! `../shared/scenes`), skipped with a message when missing.
//!
//! Run: `cargo bench -p rebraid --bench kernel`.

#[path = "../tests/common/mod.rs"]
mod common;
mod support;

use divan::counter::ItemsCount;
use divan::{Bencher, black_box};
use rebraid::{BuildParams, Hit, MeshBvh, Ray, TriangleMesh};

fn main() {
    // Load and build every scene up front, so that their summaries (and skip
    // messages) print before divan's table instead of inside it.
    for scene in SCENES {
        prepared(scene);
    }
    divan::main();
}

const SCENES: [&str; 3] = ["generated_1m", "openarena_oa_thor", "samurai_monastery"];
/// Rays per traversal sample: a 256 x 256 image, or as many random rays.
const RAYS: usize = 256 * 256;

/// A scene ready to trace: mesh, BVH and the two ray sets.
struct Prepared {
    mesh: TriangleMesh,
    bvh: MeshBvh,
    coherent: Vec<Ray>,
    incoherent: Vec<Ray>,
}

/// Scenes are built once per process and shared by the traversal benches.
fn prepared(name: &'static str) -> Option<&'static Prepared> {
    static CACHE: support::SceneCache<Prepared> = support::SceneCache::new();
    support::cached(&CACHE, name, || {
        let mesh = support::load(name)?;
        let bvh = MeshBvh::build(&mesh, &BuildParams::default()).unwrap();
        let b = mesh.bounds();
        let (coherent, incoherent) = (
            support::camera_rays(&b, RAYS),
            support::random_rays(&b, RAYS),
        );
        let hits = coherent
            .iter()
            .filter(|r| bvh.intersect(r).is_some())
            .count();
        eprintln!(
            "{name}: {} triangles, {} nodes, SAH {:.1}, camera hits {:.0}%",
            mesh.len(),
            bvh.bvh.nodes.len(),
            bvh.stats().sah_cost,
            100.0 * hits as f64 / RAYS as f64
        );
        Some(Prepared {
            mesh,
            bvh,
            coherent,
            incoherent,
        })
    })
}

/// A one-thread rayon pool: "single thread" builds and batches run in it.
fn single_thread_pool() -> &'static rayon::ThreadPool {
    static POOL: std::sync::OnceLock<rayon::ThreadPool> = std::sync::OnceLock::new();
    POOL.get_or_init(|| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
    })
}

mod build {
    use super::*;

    fn build(bencher: Bencher, scene: &'static str, single: bool) {
        let Some(p) = prepared(scene) else { return };
        let params = BuildParams::default();
        bencher.counter(ItemsCount::new(p.mesh.len())).bench(|| {
            if single {
                single_thread_pool()
                    .install(|| MeshBvh::build(black_box(&p.mesh), &params).unwrap())
            } else {
                MeshBvh::build(black_box(&p.mesh), &params).unwrap()
            }
        });
    }

    /// Triangles per second of `MeshBvh::build` in a one-thread pool.
    #[divan::bench(args = SCENES, sample_count = 5, sample_size = 1)]
    fn one_thread(bencher: Bencher, scene: &'static str) {
        build(bencher, scene, true);
    }

    /// Triangles per second of `MeshBvh::build` on the global pool.
    #[divan::bench(args = SCENES, sample_count = 5, sample_size = 1)]
    fn all_threads(bencher: Bencher, scene: &'static str) {
        build(bencher, scene, false);
    }
}

mod traverse {
    use super::*;

    #[derive(Clone, Copy)]
    enum Query {
        Closest,
        Occluded,
    }

    fn trace(bencher: Bencher, scene: &'static str, coherent: bool, query: Query, single: bool) {
        let Some(p) = prepared(scene) else { return };
        let rays = if coherent { &p.coherent } else { &p.incoherent };
        let mut hits: Vec<Option<Hit>> = vec![None; rays.len()];
        let mut occluded = vec![false; rays.len()];
        bencher
            .counter(ItemsCount::new(rays.len()))
            .bench_local(|| {
                let mut run = || match query {
                    Query::Closest => p.bvh.intersect_batch(black_box(rays), &mut hits),
                    Query::Occluded => p.bvh.occluded_batch(black_box(rays), &mut occluded),
                };
                if single {
                    single_thread_pool().install(run)
                } else {
                    run()
                }
            });
    }

    #[divan::bench(args = SCENES, sample_count = 10)]
    fn closest_coherent_one_thread(b: Bencher, s: &'static str) {
        trace(b, s, true, Query::Closest, true);
    }
    #[divan::bench(args = SCENES, sample_count = 10)]
    fn closest_coherent_all_threads(b: Bencher, s: &'static str) {
        trace(b, s, true, Query::Closest, false);
    }
    #[divan::bench(args = SCENES, sample_count = 10)]
    fn closest_incoherent_one_thread(b: Bencher, s: &'static str) {
        trace(b, s, false, Query::Closest, true);
    }
    #[divan::bench(args = SCENES, sample_count = 10)]
    fn closest_incoherent_all_threads(b: Bencher, s: &'static str) {
        trace(b, s, false, Query::Closest, false);
    }
    #[divan::bench(args = SCENES, sample_count = 10)]
    fn occluded_coherent_one_thread(b: Bencher, s: &'static str) {
        trace(b, s, true, Query::Occluded, true);
    }
    #[divan::bench(args = SCENES, sample_count = 10)]
    fn occluded_coherent_all_threads(b: Bencher, s: &'static str) {
        trace(b, s, true, Query::Occluded, false);
    }
    #[divan::bench(args = SCENES, sample_count = 10)]
    fn occluded_incoherent_one_thread(b: Bencher, s: &'static str) {
        trace(b, s, false, Query::Occluded, true);
    }
    #[divan::bench(args = SCENES, sample_count = 10)]
    fn occluded_incoherent_all_threads(b: Bencher, s: &'static str) {
        trace(b, s, false, Query::Occluded, false);
    }
}
