//! The Embree side of `rebraid bench --embree`: a worker process that loads
//! the same scene, reads the stored ray sets, and times Embree on them with
//! the same protocol (median of `reps`), printing one JSON row.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, bail};

use crate::bench::{
    BenchRow, Best, EmbreeApi, EmbreeFlags, EmbreeIsa, RaySetResult, median, read_rays,
};
use crate::embree::{EmbreeMode, EmbreeScene};
use crate::loaders::LoadOptions;
use crate::scene_input::SceneInput;

/// Build and trace in Embree inside a pool of `threads` threads, with
/// kernels up to `max_isa`, each batch through `api`, its scenes made with
/// `flags`.
pub fn run_worker(
    input: &SceneInput,
    opts: &LoadOptions,
    rays: &Path,
    mode: &str,
    threads: usize,
    reps: usize,
    (max_isa, api, flags): (EmbreeIsa, EmbreeApi, EmbreeFlags),
) -> anyhow::Result<BenchRow> {
    let emode = match mode {
        "embree-flat" => EmbreeMode::Flat,
        "embree-two-level" => EmbreeMode::TwoLevel,
        _ => bail!("unknown Embree mode '{mode}'"),
    };
    let stream = api == EmbreeApi::Stream;
    let (desc, _) = input.load(opts)?;
    let sets = read_rays(rays)?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .context("building a thread pool")?;
    pool.install(|| {
        // One untimed build first: a worker is a fresh process, and its
        // first build pays for fresh memory (page faults) and Embree's
        // start-up, which our builds, timed in a process that has built
        // before, do not (`bench --embree` runs one timed build per worker
        // when it measures in cycles).
        drop(EmbreeScene::build_with(&desc, emode, max_isa, flags)?);
        let mut build_ms = Vec::new();
        let mut scene = None;
        for _ in 0..reps {
            drop(scene.take());
            let (s, ms) = EmbreeScene::build_with(&desc, emode, max_isa, flags)?;
            build_ms.push(ms);
            scene = Some(s);
        }
        let scene = scene.expect("reps >= 1");
        let mut times: [Vec<f64>; 3] = Default::default();
        let mut answers = [(0usize, 0.0f64); 3];
        for _ in 0..reps {
            for (k, rays) in [&sets.primary, &sets.shadow, &sets.diffuse]
                .into_iter()
                .enumerate()
            {
                // The answers' memory is made (and faulted in) before the
                // clock starts, as for our modes (`resize` writes every
                // element; `vec![false; n]` would map zeroed pages that
                // fault during the trace).
                if k == 1 {
                    let mut occ = Vec::with_capacity(rays.len());
                    occ.resize(rays.len(), false);
                    let t = Instant::now();
                    scene.occluded_batch_with(rays, &mut occ, stream);
                    times[k].push(t.elapsed().as_secs_f64());
                    answers[k] = (occ.iter().filter(|&&o| o).count(), 0.0);
                } else {
                    let mut hits = Vec::with_capacity(rays.len());
                    hits.resize(rays.len(), None);
                    let t = Instant::now();
                    scene.intersect_batch_with(rays, &mut hits, stream);
                    times[k].push(t.elapsed().as_secs_f64());
                    answers[k] = hits
                        .iter()
                        .flatten()
                        .fold((0, 0.0), |(n, s), h| (n + 1, s + h.t as f64));
                }
            }
        }
        let best = Best::of_sets(&build_ms, &sets, &times);
        let total = median(build_ms);
        let tris = desc.world_triangles();
        let set = |k: usize, n: usize| RaySetResult {
            rays: n,
            hits: answers[k].0,
            t_sum: answers[k].1,
            mrays_per_s: n as f64 / median(times[k].clone()).max(1e-12) / 1e6,
        };
        Ok(BenchRow {
            scene: input.name(),
            mode: mode.to_string(),
            threads,
            triangles: tris,
            objects: desc.objects.len(),
            instances: desc.instances.len(),
            build_ms_objects: 0.0,
            build_ms_top: total,
            build_ms_total: total,
            mtris_per_s: tris as f64 / (total.max(1e-9) * 1e-3) / 1e6,
            sah_cost: 0.0,
            bytes: scene.bytes(),
            refs_opened: 0,
            primary: set(0, sets.primary.len()),
            shadow: set(1, sets.shadow.len()),
            diffuse: set(2, sets.diffuse.len()),
            camera: String::new(),
            best,
            top_phases_ms: Default::default(),
            machine: String::new(),
        })
    })
}
