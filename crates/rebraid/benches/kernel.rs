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

use std::collections::HashMap;
use std::sync::{Mutex, OnceLock};

use divan::counter::ItemsCount;
use divan::{Bencher, black_box};
use rand::Rng;
use rebraid::glam::Vec3;
use rebraid::{Aabb, BuildParams, Hit, MeshBvh, Ray, TriangleMesh};

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

/// About a million triangles: a 500 x 500 height-field terrain (500k) and
/// 400 icospheres of 1,280 triangles scattered over it (512k).
fn generated_scene() -> TriangleMesh {
    let mut r = common::rng(7);
    let n = 500u32;
    let mut positions = Vec::new();
    for y in 0..=n {
        for x in 0..=n {
            let (fx, fy) = (x as f32, y as f32);
            let h = 8.0 * (fx * 0.05).sin() * (fy * 0.037).cos() + r.gen_range(0.0..0.3);
            positions.push(Vec3::new(fx, fy, h));
        }
    }
    let id = |x: u32, y: u32| y * (n + 1) + x;
    let mut indices = Vec::new();
    for y in 0..n {
        for x in 0..n {
            indices.push([id(x, y), id(x + 1, y), id(x + 1, y + 1)]);
            indices.push([id(x, y), id(x + 1, y + 1), id(x, y + 1)]);
        }
    }
    for _ in 0..400 {
        let c = Vec3::new(
            r.gen_range(0.0..500.0),
            r.gen_range(0.0..500.0),
            r.gen_range(5.0..40.0),
        );
        let s = common::icosphere(3, r.gen_range(1.0..12.0), c);
        let base = positions.len() as u32;
        positions.extend(&s.positions);
        indices.extend(s.indices.iter().map(|t| t.map(|i| i + base)));
    }
    TriangleMesh::new(positions, indices).unwrap()
}

/// The mesh of a scene, or `None` (after a message) for a missing real scene.
fn load(name: &str) -> Option<TriangleMesh> {
    if name == "generated_1m" {
        return Some(generated_scene());
    }
    let path = common::obj::scene_path_or_skip(&format!("{name}.obj"))?;
    Some(common::obj::load_obj(&path))
}

/// Pinhole camera rays from the middle of the scene towards a fixed, slightly
/// downward direction (every scene has content around its centre).
fn camera_rays(bounds: &Aabb) -> Vec<Ray> {
    let eye = bounds.center();
    let forward = Vec3::new(1.0, 0.35, -0.25).normalize();
    let right = forward.cross(Vec3::Z).normalize();
    let up = right.cross(forward);
    let side = (RAYS as f64).sqrt() as usize;
    (0..RAYS)
        .map(|i| {
            let (x, y) = (i % side, i / side);
            let sx = (x as f32 + 0.5) / side as f32 * 2.0 - 1.0;
            let sy = (y as f32 + 0.5) / side as f32 * 2.0 - 1.0;
            Ray::infinite(eye, forward + right * sx + up * sy)
        })
        .collect()
}

/// Random origins in the scene box and random directions.
fn random_rays(bounds: &Aabb) -> Vec<Ray> {
    let mut r = common::rng(8);
    (0..RAYS)
        .map(|_| Ray::infinite(common::point_in(&mut r, bounds), common::unit_dir(&mut r)))
        .collect()
}

/// Scenes are built once per process and shared by the traversal benches.
fn prepared(name: &'static str) -> Option<&'static Prepared> {
    static CACHE: OnceLock<Mutex<HashMap<&'static str, Option<&'static Prepared>>>> =
        OnceLock::new();
    let cache = CACHE.get_or_init(Default::default);
    let mut cache = cache.lock().unwrap();
    *cache.entry(name).or_insert_with(|| {
        let mesh = load(name)?;
        let bvh = MeshBvh::build(&mesh, &BuildParams::default()).unwrap();
        let b = mesh.bounds();
        let (coherent, incoherent) = (camera_rays(&b), random_rays(&b));
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
        Some(&*Box::leak(Box::new(Prepared {
            mesh,
            bvh,
            coherent,
            incoherent,
        })))
    })
}

/// A one-thread rayon pool: "single thread" builds and batches run in it.
fn single_thread_pool() -> &'static rayon::ThreadPool {
    static POOL: OnceLock<rayon::ThreadPool> = OnceLock::new();
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
