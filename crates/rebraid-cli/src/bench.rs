//! `rebraid bench`: build and trace every scene in every mode, with the same
//! rays, and report build times, memory, SAH cost and Mrays/s.
//!
//! Measurement protocol (the machine is shared and noisy): every figure is
//! the median of `reps` repetitions, and the repetitions alternate between
//! modes (mode A, mode B, mode C, A, B, C, ...) so that drifts of the machine
//! hit every mode alike; ratios between modes of one run are what to quote.
//! Each thread count runs inside its own rayon pool. Beside Embree
//! (`--embree`) every (mode, threads) row, ours and Embree's, runs in a
//! fresh worker process that builds once untimed and then times, so that
//! neither side's builds run in a process the other's did not. The memory
//! the answers go into is made before the clock starts.

use std::time::Instant;

use anyhow::Context;
use rebraid::glam::Vec3;
use rebraid::{AccelMode, CommitReport, Hit, Ray, Scene, SceneDesc, SceneParams};
use serde::Serialize;

use crate::camera::Camera;
use crate::raysets::RaySets;

/// Results of one ray set.
#[derive(Clone, Debug, Default, Serialize, serde::Deserialize, PartialEq)]
pub struct RaySetResult {
    pub rays: usize,
    pub hits: usize,
    /// Sum of closest-hit distances (0 for shadow rays, which are any-hit).
    pub t_sum: f64,
    pub mrays_per_s: f64,
}

/// One row: a (scene, mode, threads) triple.
#[derive(Clone, Debug, Default, Serialize, serde::Deserialize, PartialEq)]
pub struct BenchRow {
    pub scene: String,
    pub mode: String,
    pub threads: usize,
    pub triangles: usize,
    pub objects: usize,
    pub instances: usize,
    pub build_ms_objects: f64,
    /// Top-level build; for `flat`, the build of its single BVH.
    pub build_ms_top: f64,
    pub build_ms_total: f64,
    pub mtris_per_s: f64,
    pub sah_cost: f64,
    pub bytes: usize,
    pub refs_opened: usize,
    pub primary: RaySetResult,
    pub shadow: RaySetResult,
    pub diffuse: RaySetResult,
    pub camera: String,
    /// The fastest of the row's repetitions (and, over cycles, of its
    /// cycles): see [`Best`].
    #[serde(default)]
    pub best: Best,
    /// The top level's build by phase (medians over the repetitions; zero
    /// for Embree's rows and the flat mode).
    #[serde(default)]
    pub top_phases_ms: TopPhases,
    /// The CPU the row was measured on ([`machine_description`]), written
    /// into `bench --json` files.
    #[serde(default)]
    pub machine: String,
}

/// The CPU's model name (from `/proc/cpuinfo` where there is one), its
/// logical CPUs and the widest vector extension it has, e.g. `Intel(R)
/// Xeon(R) Processor, 2 logical CPUs, AVX-512F`: Embree picks its kernels
/// by the last (our kernels stop at AVX2).
pub fn machine_description() -> String {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|info| {
            info.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, m)| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".to_string());
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    let widest = widest_vector_extension();
    format!("{model}, {cpus} logical CPUs, {widest}")
}

#[cfg(target_arch = "x86_64")]
fn widest_vector_extension() -> &'static str {
    if std::arch::is_x86_feature_detected!("avx512f") {
        "AVX-512F"
    } else if std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
    {
        "AVX2+FMA"
    } else if std::arch::is_x86_feature_detected!("sse4.1") {
        "SSE4.1"
    } else {
        "SSE2"
    }
}

#[cfg(not(target_arch = "x86_64"))]
fn widest_vector_extension() -> &'static str {
    "no x86 vector extension"
}

/// Where a top level's build went, in milliseconds: the binned build with
/// its opening, the reinsertion, and the layout pass by phase (see
/// [`rebraid::toplevel::LayoutTimes`]). The parts of
/// [`BenchRow::build_ms_top`] that the scene's own commit report does not
/// split: what decides how small a share of the whole build the re-braided
/// top level takes.
#[derive(Clone, Copy, Debug, Default, Serialize, serde::Deserialize, PartialEq)]
pub struct TopPhases {
    pub build: f64,
    pub reinsert: f64,
    pub collapse: f64,
    pub entries: f64,
    pub grafts: f64,
    pub order: f64,
    pub copies: f64,
}

impl TopPhases {
    /// The phases of one commit's top level (zero without one).
    pub fn of(top: Option<&rebraid::toplevel::TopLevelBuildStats>) -> Self {
        let Some(t) = top else {
            return Self::default();
        };
        let l = &t.layout;
        Self {
            build: t.build_ms - t.reinsert_ms,
            reinsert: t.reinsert_ms,
            collapse: l.collapse_ms,
            entries: l.entries_ms,
            grafts: l.graft_ms,
            order: l.order_ms,
            copies: l.copy_ms,
        }
    }

    /// The phases summed: the whole top-level build.
    pub fn total(&self) -> f64 {
        self.build
            + self.reinsert
            + self.collapse
            + self.entries
            + self.grafts
            + self.order
            + self.copies
    }

    /// Each phase's median over `all`.
    pub fn median_of(all: &[TopPhases]) -> Self {
        let m = |f: fn(&TopPhases) -> f64| {
            if all.is_empty() {
                0.0
            } else {
                median(all.iter().map(f).collect())
            }
        };
        Self {
            build: m(|p| p.build),
            reinsert: m(|p| p.reinsert),
            collapse: m(|p| p.collapse),
            entries: m(|p| p.entries),
            grafts: m(|p| p.grafts),
            order: m(|p| p.order),
            copies: m(|p| p.copies),
        }
    }
}

/// The fastest measurement of a row: the shortest build (ms) and the
/// highest Mrays/s per ray set.
///
/// Why beside the medians: on a shared machine, interference (other
/// tenants' memory traffic) only ever slows a run down, so the fastest of
/// several repetitions is the least disturbed one. Measured on this
/// project's machine (session 9, `docs/performance.md`): the same binary
/// against itself, 8 alternations, 42 (scene, mode, ray set) cells: the
/// median of paired ratios strayed from 1.0 by 6.4% (root mean square of
/// its logarithm; worst 0.81), the ratio of the fastest runs by 1.6%
/// (worst 0.96).
#[derive(Clone, Copy, Debug, Default, Serialize, serde::Deserialize, PartialEq)]
pub struct Best {
    pub build_ms_total: f64,
    pub primary: f64,
    pub shadow: f64,
    pub diffuse: f64,
}

impl Best {
    /// From a row's repetitions: build times (ms) and the trace times (s)
    /// of each ray set of `sets` (primary, shadow, diffuse).
    pub fn of_sets(build_ms: &[f64], sets: &RaySets, times: &[Vec<f64>; 3]) -> Self {
        Self::of(
            build_ms,
            [
                (sets.primary.len(), &times[0]),
                (sets.shadow.len(), &times[1]),
                (sets.diffuse.len(), &times[2]),
            ],
        )
    }

    /// From a row's repetitions: build times (ms) and, per ray set, the ray
    /// count and the trace times (s).
    pub fn of(build_ms: &[f64], sets: [(usize, &[f64]); 3]) -> Self {
        let fastest = |(rays, times): (usize, &[f64])| {
            let t = times.iter().copied().fold(f64::INFINITY, f64::min);
            if t.is_finite() {
                rays as f64 / t.max(1e-12) / 1e6
            } else {
                0.0
            }
        };
        let build = build_ms.iter().copied().fold(f64::INFINITY, f64::min);
        Self {
            build_ms_total: if build.is_finite() { build } else { 0.0 },
            primary: fastest(sets[0]),
            shadow: fastest(sets[1]),
            diffuse: fastest(sets[2]),
        }
    }

    /// The faster of two.
    fn max(self, o: Self) -> Self {
        let min_pos = |a: f64, b: f64| match (a > 0.0, b > 0.0) {
            (true, true) => a.min(b),
            (true, false) => a,
            _ => b,
        };
        Self {
            build_ms_total: min_pos(self.build_ms_total, o.build_ms_total),
            primary: self.primary.max(o.primary),
            shadow: self.shadow.max(o.shadow),
            diffuse: self.diffuse.max(o.diffuse),
        }
    }
}

/// Which figure of a row's cycles a ratio compares (see [`format_ratios`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CycleStat {
    /// The median over the cycles of the ratio within a cycle.
    Median,
    /// The ratio of the fastest cycles (see [`Best`]).
    Best,
}

/// What to run.
#[derive(Clone, Debug)]
pub struct BenchConfig {
    pub modes: Vec<AccelMode>,
    pub threads: Vec<usize>,
    pub reps: usize,
    pub width: u32,
    pub height: u32,
    pub params: SceneParams,
    /// Build each mode once, untimed, before its timed builds: what a
    /// worker process does (see `rebraid bench --embree`), whose first
    /// build would otherwise pay for the process's fresh memory.
    pub warmup: bool,
}

/// The median of a non-empty list.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n == 0 {
        return 0.0;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Hits and distance sum of closest-hit results.
pub fn summarize_hits(hits: &[Option<Hit>]) -> (usize, f64) {
    hits.iter()
        .flatten()
        .fold((0, 0.0), |(n, s), h| (n + 1, s + h.t as f64))
}

fn pool(threads: usize) -> anyhow::Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .context("building a thread pool")
}

/// Generate the ray sets of a scene with its camera. The reference scene is
/// committed in `mode` on all threads.
pub fn make_ray_sets(
    desc: &SceneDesc,
    params: &SceneParams,
    camera: &Camera,
    up: Vec3,
    width: u32,
    height: u32,
) -> anyhow::Result<RaySets> {
    let mut scene = Scene::from_desc(desc, params.clone())?;
    scene.commit()?;
    let (_, bounds) = desc.world_boxes();
    Ok(RaySets::generate(
        camera,
        width,
        height,
        &bounds,
        up,
        |r, h| scene.intersect_batch(r, h),
    ))
}

/// Inner nodes, leaves and entries visited per ray (top level and objects
/// together; entries are the top-level leaves that entered an object BVH,
/// counted among the leaves too), for the primary, shadow and diffuse sets,
/// ray by ray through the scene's counted queries.
pub fn visits_per_ray(scene: &Scene, sets: &RaySets) -> [[f64; 3]; 3] {
    let mut out = [[0.0; 3]; 3];
    for (k, rays) in [&sets.primary, &sets.shadow, &sets.diffuse]
        .into_iter()
        .enumerate()
    {
        // Summed in `u64` ray by ray: the counters are `u32`.
        let mut sum = [0u64; 3];
        for ray in rays {
            let mut c = rebraid::bvh::TraversalCounters::default();
            if k == 1 {
                scene.occluded_counted(ray, &mut c);
            } else {
                scene.intersect_counted(ray, &mut c);
            }
            sum[0] += u64::from(c.inner_visited);
            sum[1] += u64::from(c.leaves_visited);
            sum[2] += u64::from(c.entries_visited);
        }
        let n = rays.len().max(1) as f64;
        out[k] = sum.map(|x| x as f64 / n);
    }
    out
}

/// Trace the three sets once; returns seconds per set and the answers.
fn trace_sets(
    scene: &Scene,
    sets: &RaySets,
    hits: &mut Vec<Option<Hit>>,
    occ: &mut Vec<bool>,
) -> [(f64, usize, f64); 3] {
    let mut out = [(0.0, 0, 0.0); 3];
    for (k, rays) in [&sets.primary, &sets.shadow, &sets.diffuse]
        .into_iter()
        .enumerate()
    {
        // The answers' memory is made (and faulted in) before the clock
        // starts: a worker process traces once, into fresh pages.
        if k == 1 {
            occ.clear();
            occ.resize(rays.len(), false);
            let t = Instant::now();
            scene.occluded_batch(rays, occ);
            out[k] = (
                t.elapsed().as_secs_f64(),
                occ.iter().filter(|&&o| o).count(),
                0.0,
            );
        } else {
            hits.clear();
            hits.resize(rays.len(), None);
            let t = Instant::now();
            scene.intersect_batch(rays, hits);
            let secs = t.elapsed().as_secs_f64();
            let (n, s) = summarize_hits(hits);
            out[k] = (secs, n, s);
        }
    }
    out
}

/// Run every mode and thread count on one scene.
pub fn bench_scene(
    name: &str,
    desc: &SceneDesc,
    sets: &RaySets,
    camera: &Camera,
    cfg: &BenchConfig,
    mut progress: impl FnMut(&str) + Send,
) -> anyhow::Result<Vec<BenchRow>> {
    let mut rows = Vec::new();
    let tris = desc.world_triangles();
    for &threads in &cfg.threads {
        let pool = pool(threads)?;
        let rows_t: anyhow::Result<Vec<BenchRow>> = pool.install(|| {
            let m = cfg.modes.len();
            let mut builds: Vec<Vec<(f64, f64, f64)>> = vec![Vec::new(); m];
            let mut phases: Vec<Vec<TopPhases>> = vec![Vec::new(); m];
            let mut scenes: Vec<Option<Scene>> = (0..m).map(|_| None).collect();
            // One build of `mode`'s scene (the timed ones and the warm-up).
            let build = |mode: AccelMode| -> anyhow::Result<(Scene, CommitReport)> {
                let mut params = cfg.params.clone();
                params.mode = mode;
                let mut scene = Scene::from_desc(desc, params)?;
                let report = scene.commit()?;
                Ok((scene, report))
            };
            if cfg.warmup {
                for &mode in &cfg.modes {
                    progress(&format!(
                        "{name}: warm-up build {} ({threads} thr)",
                        mode.name()
                    ));
                    build(mode)?;
                }
            }
            for rep in 0..cfg.reps {
                for (i, &mode) in cfg.modes.iter().enumerate() {
                    progress(&format!(
                        "{name}: build {} ({threads} thr, rep {})",
                        mode.name(),
                        rep + 1
                    ));
                    let (scene, r) = build(mode)?;
                    builds[i].push((r.object_build_ms, r.top_build_ms, r.total_ms));
                    phases[i].push(TopPhases::of(r.top.as_ref()));
                    scenes[i] = Some(scene);
                }
            }
            let mut times: Vec<[Vec<f64>; 3]> = vec![Default::default(); m];
            let mut answers = vec![[(0usize, 0.0f64); 3]; m];
            let mut hits = Vec::new();
            let mut occ = Vec::new();
            for rep in 0..cfg.reps {
                for (i, &mode) in cfg.modes.iter().enumerate() {
                    progress(&format!(
                        "{name}: trace {} ({threads} thr, rep {})",
                        mode.name(),
                        rep + 1
                    ));
                    let scene = scenes[i].as_ref().expect("built above");
                    let r = trace_sets(scene, sets, &mut hits, &mut occ);
                    for k in 0..3 {
                        times[i][k].push(r[k].0);
                        answers[i][k] = (r[k].1, r[k].2);
                    }
                }
            }
            let mut out = Vec::new();
            for (i, &mode) in cfg.modes.iter().enumerate() {
                let scene = scenes[i].as_ref().expect("built above");
                let st = scene.stats();
                let b = &builds[i];
                let total = median(b.iter().map(|x| x.2).collect());
                let set = |k: usize, rays: usize| RaySetResult {
                    rays,
                    hits: answers[i][k].0,
                    t_sum: answers[i][k].1,
                    mrays_per_s: rays as f64 / median(times[i][k].clone()).max(1e-12) / 1e6,
                };
                out.push(BenchRow {
                    scene: name.to_string(),
                    mode: mode.name().to_string(),
                    threads,
                    triangles: tris,
                    objects: st.objects,
                    instances: st.instances,
                    build_ms_objects: median(b.iter().map(|x| x.0).collect()),
                    build_ms_top: median(b.iter().map(|x| x.1).collect()),
                    build_ms_total: total,
                    mtris_per_s: tris as f64 / (total.max(1e-9) * 1e-3) / 1e6,
                    sah_cost: st.sah_cost,
                    bytes: st.bytes,
                    refs_opened: st.top.as_ref().map_or(0, |t| t.nodes_opened),
                    primary: set(0, sets.primary.len()),
                    shadow: set(1, sets.shadow.len()),
                    diffuse: set(2, sets.diffuse.len()),
                    camera: camera.to_arg(),
                    best: Best::of_sets(
                        &b.iter().map(|x| x.2).collect::<Vec<_>>(),
                        sets,
                        &times[i],
                    ),
                    top_phases_ms: TopPhases::median_of(&phases[i]),
                    machine: String::new(),
                });
            }
            Ok(out)
        });
        rows.extend(rows_t?);
    }
    Ok(rows)
}

/// The rows as a fixed-width table.
pub fn format_table(rows: &[BenchRow]) -> String {
    let mut s = String::new();
    s.push_str(&format!(
        "{:<24} {:<21} {:>3} {:>9} {:>9} {:>8} {:>9} {:>7} {:>8} {:>8} {:>7} {:>8} {:>8} {:>8}\n",
        "scene",
        "mode",
        "thr",
        "tris",
        "obj ms",
        "top ms",
        "total ms",
        "Mtri/s",
        "MB",
        "SAH",
        "opened",
        "primary",
        "shadow",
        "diffuse"
    ));
    for r in rows {
        s.push_str(&format!(
            "{:<24} {:<21} {:>3} {:>9} {:>9.1} {:>8.1} {:>9.1} {:>7.2} {:>8.1} {:>8.1} {:>7} {:>8.2} {:>8.2} {:>8.2}\n",
            r.scene,
            r.mode,
            r.threads,
            r.triangles,
            r.build_ms_objects,
            r.build_ms_top,
            r.build_ms_total,
            r.mtris_per_s,
            r.bytes as f64 / (1024.0 * 1024.0),
            r.sah_cost,
            r.refs_opened,
            r.primary.mrays_per_s,
            r.shadow.mrays_per_s,
            r.diffuse.mrays_per_s,
        ));
    }
    s
}

/// Hits and distance sums per ray set, to check that modes agree.
pub fn format_answers(rows: &[BenchRow]) -> String {
    let mut s = String::from("answers (hits / sum of t) per ray set:\n");
    for r in rows
        .iter()
        .filter(|r| r.threads == rows[0].threads || r.mode.starts_with("embree"))
    {
        s.push_str(&format!(
            "  {:<24} {:<21} primary {:>8} / {:<16.6e} shadow {:>8} occluded   diffuse {:>8} / {:<16.6e}\n",
            r.scene, r.mode, r.primary.hits, r.primary.t_sum, r.shadow.hits, r.diffuse.hits, r.diffuse.t_sum
        ));
    }
    s
}

/// The highest instruction set Embree may use (`rebraid bench
/// --embree-isa`). Embree picks its widest kernels by itself; on a CPU with
/// AVX-512 that is its AVX-512 path, which is not always its fastest (see
/// `docs/performance.md`), so the bench can also time it capped at AVX2,
/// the instruction set rebraid's kernels use, or at SSE4.2.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum EmbreeIsa {
    /// Embree's own choice (the widest the CPU has).
    Auto,
    Avx2,
    #[value(name = "sse4.2")]
    Sse42,
}

impl EmbreeIsa {
    /// Appended to the Embree modes' names in the bench rows (`embree-flat`
    /// for `Auto`, `embree-flat-avx2`, `embree-flat-sse4.2`).
    pub fn mode_suffix(self) -> &'static str {
        match self {
            EmbreeIsa::Auto => "",
            EmbreeIsa::Avx2 => "-avx2",
            EmbreeIsa::Sse42 => "-sse4.2",
        }
    }

    /// The name `--embree-isa` and the worker's `--max-isa` take.
    pub fn arg(self) -> &'static str {
        match self {
            EmbreeIsa::Auto => "auto",
            EmbreeIsa::Avx2 => "avx2",
            EmbreeIsa::Sse42 => "sse4.2",
        }
    }
}

/// Which Embree entry point traces a batch (`rebraid bench --embree-api`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum EmbreeApi {
    /// One `rtcIntersect1` / `rtcOccluded1` per ray: single-ray
    /// traversal, as `shared/docs/anchors.md` measured Embree.
    Single,
    /// One `rtcIntersect1M` / `rtcOccluded1M` per run of rays (Embree's
    /// stream API): Embree regroups the rays into packets by direction
    /// octant and traces coherent ones together.
    Stream,
}

impl EmbreeApi {
    /// Appended to the Embree modes' names after the ISA's suffix
    /// (`embree-flat-stream`, `embree-flat-avx2-stream`).
    pub fn mode_suffix(self) -> &'static str {
        match self {
            EmbreeApi::Single => "",
            EmbreeApi::Stream => "-stream",
        }
    }

    /// The name `--embree-api` and the worker's `--api` take.
    pub fn arg(self) -> &'static str {
        match self {
            EmbreeApi::Single => "single",
            EmbreeApi::Stream => "stream",
        }
    }
}

/// Embree's scene flags for a pair of bench rows (`rebraid bench
/// --embree-flags`). Embree's default traversal and triangle test are not
/// watertight (a ray through the edge two triangles share can pass between
/// them); `RTC_SCENE_FLAG_ROBUST` makes them so, as rebraid's kernels
/// always are (Woop et al.'s watertight test, conservative box tests): the
/// `-robust` rows compare the two under the same guarantee.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum EmbreeFlags {
    /// No scene flags: Embree's fast, not watertight, kernels.
    Default,
    /// `RTC_SCENE_FLAG_ROBUST` on every scene (the instanced ones too).
    Robust,
}

impl EmbreeFlags {
    /// Appended to the Embree modes' names after the ISA's suffix and
    /// before the API's (`embree-flat-robust`, `embree-flat-robust-stream`).
    pub fn mode_suffix(self) -> &'static str {
        match self {
            EmbreeFlags::Default => "",
            EmbreeFlags::Robust => "-robust",
        }
    }

    /// The name `--embree-flags` and the worker's `--flags` take.
    pub fn arg(self) -> &'static str {
        match self {
            EmbreeFlags::Default => "default",
            EmbreeFlags::Robust => "robust",
        }
    }
}

/// Ratio tables of `mode` against each baseline mode: Mrays/s ours over
/// theirs per ray set, build time theirs over ours. `cycles` holds the rows
/// of each measurement cycle (see [`median_rows`]). With
/// [`CycleStat::Median`] each ratio is the median over the cycles of the
/// ratio within a cycle, so that it pairs figures measured close in time on
/// a machine whose speed drifts; with [`CycleStat::Best`] it is the ratio of
/// the two rows' fastest figures over all cycles (see [`Best`]).
pub fn format_ratios(
    cycles: &[Vec<BenchRow>],
    mode: &str,
    baselines: &[&str],
    stat: CycleStat,
) -> String {
    let mut s = String::new();
    let Some(first) = cycles.first() else {
        return s;
    };
    let q = |a: f64, b: f64| if b > 0.0 { a / b } else { f64::NAN };
    for base in baselines {
        let mut lines = Vec::new();
        for ours0 in first.iter().filter(|r| r.mode == mode) {
            let mut ratios: [Vec<f64>; 4] = Default::default();
            let (mut best_ours, mut best_theirs) = (None::<Best>, None::<Best>);
            for rows in cycles {
                let find = |m: &str| {
                    rows.iter().find(|r| {
                        r.mode == m && r.scene == ours0.scene && r.threads == ours0.threads
                    })
                };
                let (Some(ours), Some(theirs)) = (find(mode), find(base)) else {
                    continue;
                };
                ratios[0].push(q(ours.primary.mrays_per_s, theirs.primary.mrays_per_s));
                ratios[1].push(q(ours.shadow.mrays_per_s, theirs.shadow.mrays_per_s));
                ratios[2].push(q(ours.diffuse.mrays_per_s, theirs.diffuse.mrays_per_s));
                ratios[3].push(q(theirs.build_ms_total, ours.build_ms_total));
                best_ours = Some(best_ours.map_or(ours.best, |b| b.max(ours.best)));
                best_theirs = Some(best_theirs.map_or(theirs.best, |b| b.max(theirs.best)));
            }
            let (Some(bo), Some(bt)) = (best_ours, best_theirs) else {
                continue;
            };
            let [p, sh, d, b] = match stat {
                CycleStat::Median => ratios.map(median),
                CycleStat::Best => [
                    q(bo.primary, bt.primary),
                    q(bo.shadow, bt.shadow),
                    q(bo.diffuse, bt.diffuse),
                    q(bt.build_ms_total, bo.build_ms_total),
                ],
            };
            lines.push(format!(
                "  {:<24} {:>3} {:>8.2} {:>8.2} {:>8.2} {:>8.2}\n",
                ours0.scene, ours0.threads, p, sh, d, b,
            ));
        }
        if lines.is_empty() {
            continue;
        }
        s.push_str(&format!(
            "{mode} / {base} (above 1.0: {mode} ahead; build: their time over ours):\n  {:<24} {:>3} {:>8} {:>8} {:>8} {:>8}\n",
            "scene", "thr", "primary", "shadow", "diffuse", "build"
        ));
        for l in lines {
            s.push_str(&l);
        }
    }
    s
}

/// One row per (scene, mode, threads) of the first cycle, each figure the
/// median of that row's figures over the cycles (and [`BenchRow::best`] the
/// fastest over them). `rebraid bench --embree`
/// measures in cycles (every mode and every Embree worker once per cycle,
/// in turn), so that ours and Embree's figures alternate in time as the
/// modes' own do; the answers (hits, distance sums) are the first cycle's.
pub fn median_rows(cycles: &[Vec<BenchRow>]) -> Vec<BenchRow> {
    let Some(first) = cycles.first() else {
        return Vec::new();
    };
    first
        .iter()
        .map(|r0| {
            let same: Vec<&BenchRow> = cycles
                .iter()
                .filter_map(|rows| {
                    rows.iter().find(|r| {
                        r.scene == r0.scene && r.mode == r0.mode && r.threads == r0.threads
                    })
                })
                .collect();
            let med = |f: &dyn Fn(&BenchRow) -> f64| median(same.iter().map(|r| f(r)).collect());
            let mut row = r0.clone();
            row.build_ms_objects = med(&|r| r.build_ms_objects);
            row.build_ms_top = med(&|r| r.build_ms_top);
            row.build_ms_total = med(&|r| r.build_ms_total);
            row.mtris_per_s = row.triangles as f64 / (row.build_ms_total.max(1e-9) * 1e-3) / 1e6;
            row.primary.mrays_per_s = med(&|r| r.primary.mrays_per_s);
            row.shadow.mrays_per_s = med(&|r| r.shadow.mrays_per_s);
            row.diffuse.mrays_per_s = med(&|r| r.diffuse.mrays_per_s);
            row.best = same.iter().map(|r| r.best).fold(r0.best, Best::max);
            let phases: Vec<TopPhases> = same.iter().map(|r| r.top_phases_ms).collect();
            row.top_phases_ms = TopPhases::median_of(&phases);
            row
        })
        .collect()
}

/// Empty the ray sets not named in `names` (comma-separated `primary`,
/// `shadow`, `diffuse`), so that a run traces only the named ones.
pub fn keep_sets(sets: &mut RaySets, names: &str) -> anyhow::Result<()> {
    let names: Vec<&str> = names.split(',').map(str::trim).collect();
    if let Some(bad) = names
        .iter()
        .find(|n| !["primary", "shadow", "diffuse"].contains(n))
    {
        anyhow::bail!("unknown ray set `{bad}` (expected primary, shadow or diffuse)");
    }
    for (name, v) in [
        ("primary", &mut sets.primary),
        ("shadow", &mut sets.shadow),
        ("diffuse", &mut sets.diffuse),
    ] {
        if !names.contains(&name) {
            v.clear();
        }
    }
    Ok(())
}

/// Load a ray file written by [`write_rays`].
pub fn read_rays(path: &std::path::Path) -> anyhow::Result<RaySets> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let mut sets = RaySets::default();
    let mut rest = bytes.as_slice();
    for v in [&mut sets.primary, &mut sets.shadow, &mut sets.diffuse] {
        anyhow::ensure!(rest.len() >= 8, "truncated ray file {}", path.display());
        let n = u64::from_le_bytes(rest[..8].try_into()?) as usize;
        rest = &rest[8..];
        let len = n * std::mem::size_of::<Ray>();
        anyhow::ensure!(rest.len() >= len, "truncated ray file {}", path.display());
        *v = bytemuck::pod_collect_to_vec(&rest[..len]);
        rest = &rest[len..];
    }
    Ok(sets)
}

/// Store ray sets for a worker process (the Embree rows run in their own
/// process so that Embree's TBB threads never share a run with rayon's).
pub fn write_rays(path: &std::path::Path, sets: &RaySets) -> anyhow::Result<()> {
    let mut out = Vec::new();
    for v in [&sets.primary, &sets.shadow, &sets.diffuse] {
        out.extend_from_slice(&(v.len() as u64).to_le_bytes());
        out.extend_from_slice(bytemuck::cast_slice(v));
    }
    std::fs::write(path, out).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The columns of the ratio table's line for `scene`.
    fn columns_of<'a>(table: &'a str, scene: &str) -> Vec<&'a str> {
        table
            .lines()
            .find(|l| l.split_whitespace().next() == Some(scene))
            .unwrap_or_else(|| panic!("no line for {scene} in {table}"))
            .split_whitespace()
            .collect()
    }

    #[test]
    fn median_of_odd_and_even() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 2.0, 3.0]), 2.5);
    }

    #[test]
    fn ray_file_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("rays.bin");
        let r = Ray::infinite(Vec3::new(1.0, 2.0, 3.0), Vec3::X);
        let sets = RaySets {
            primary: vec![r; 3],
            shadow: vec![],
            diffuse: vec![r],
        };
        write_rays(&p, &sets).unwrap();
        let back = read_rays(&p).unwrap();
        assert_eq!(back.primary, sets.primary);
        assert_eq!(back.diffuse, sets.diffuse);
        assert!(back.shadow.is_empty());
    }

    #[test]
    fn top_phases_are_medians_per_phase() {
        assert_eq!(TopPhases::of(None), TopPhases::default());
        assert_eq!(TopPhases::median_of(&[]), TopPhases::default());
        let p = |x: f64| TopPhases {
            build: x,
            reinsert: 2.0 * x,
            collapse: 3.0 * x,
            entries: 4.0 * x,
            grafts: 5.0 * x,
            order: 6.0 * x,
            copies: 7.0 * x,
        };
        let m = TopPhases::median_of(&[p(3.0), p(1.0), p(2.0)]);
        assert_eq!(m, p(2.0));
        assert_eq!(m.total(), 28.0 * 2.0);
        let stats = rebraid::toplevel::TopLevelBuildStats {
            build_ms: 5.0,
            reinsert_ms: 2.0,
            layout: rebraid::toplevel::LayoutTimes {
                collapse_ms: 1.0,
                entries_ms: 0.5,
                graft_ms: 0.25,
                order_ms: 0.125,
                copy_ms: 0.0625,
            },
            ..Default::default()
        };
        let t = TopPhases::of(Some(&stats));
        assert_eq!((t.build, t.reinsert), (3.0, 2.0));
        assert_eq!(t.total(), 5.0 + stats.layout.total_ms());
    }

    #[test]
    fn ratios_pair_rows_of_the_same_scene_and_threads() {
        let row = |scene: &str, mode: &str, threads, p, sh, d, build| BenchRow {
            scene: scene.into(),
            mode: mode.into(),
            threads,
            build_ms_total: build,
            primary: RaySetResult {
                mrays_per_s: p,
                ..Default::default()
            },
            shadow: RaySetResult {
                mrays_per_s: sh,
                ..Default::default()
            },
            diffuse: RaySetResult {
                mrays_per_s: d,
                ..Default::default()
            },
            ..Default::default()
        };
        let rows = vec![
            row("a", "rebraided", 1, 10.0, 6.0, 3.0, 20.0),
            row("a", "rebraided", 2, 20.0, 12.0, 6.0, 10.0),
            row("a", "embree-two-level", 1, 5.0, 12.0, 3.0, 10.0),
            row("b", "rebraided", 1, 1.0, 1.0, 1.0, 1.0),
        ];
        let s = format_ratios(
            std::slice::from_ref(&rows),
            "rebraided",
            &["embree-two-level", "embree-flat"],
            CycleStat::Median,
        );
        assert!(s.contains("rebraided / embree-two-level"), "{s}");
        assert!(!s.contains("embree-flat"), "no flat rows: {s}");
        let cols = columns_of(&s, "a");
        assert_eq!(cols, ["a", "1", "2.00", "0.50", "1.00", "0.50"]);
        assert_eq!(s.lines().count(), 3, "{s}");
        assert!(
            format_ratios(
                std::slice::from_ref(&rows),
                "flat",
                &["embree-flat"],
                CycleStat::Median
            )
            .is_empty()
        );
    }

    #[test]
    fn ratios_and_rows_over_cycles_are_medians() {
        let row = |mode: &str, p: f64, build: f64| BenchRow {
            scene: "a".into(),
            mode: mode.into(),
            threads: 1,
            triangles: 1000,
            build_ms_total: build,
            primary: RaySetResult {
                mrays_per_s: p,
                ..Default::default()
            },
            ..Default::default()
        };
        // The machine runs at a third of its speed in cycle 2: a ratio of
        // medians (10 / 5 = 2) hides what every cycle says (3).
        let cycles = vec![
            vec![row("rebraided", 12.0, 10.0), row("embree-flat", 4.0, 20.0)],
            vec![row("rebraided", 3.0, 30.0), row("embree-flat", 1.0, 90.0)],
            vec![row("rebraided", 9.0, 20.0), row("embree-flat", 3.0, 40.0)],
        ];
        let s = format_ratios(&cycles, "rebraided", &["embree-flat"], CycleStat::Median);
        let cols = columns_of(&s, "a");
        assert_eq!(cols[..3], ["a", "1", "3.00"]);
        assert_eq!(cols[5], "2.00", "build: median of 2, 3, 2");
        let rows = median_rows(&cycles);
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].primary.mrays_per_s, 9.0);
        assert_eq!(rows[1].build_ms_total, 40.0);
        assert_eq!(rows[0].mtris_per_s, 1000.0 / 0.02 / 1e6);
    }

    #[test]
    fn best_figures_are_the_fastest_repetitions_and_cycles() {
        // Two repetitions: builds of 30 and 20 ms, primary rays traced in
        // 0.5 and 0.25 s (1 Mray), no shadow rays traced.
        let b = Best::of(
            &[30.0, 20.0],
            [(1_000_000, &[0.5, 0.25]), (0, &[]), (10, &[1e-5])],
        );
        assert_eq!(b.build_ms_total, 20.0);
        assert_eq!(b.primary, 4.0);
        assert_eq!(b.shadow, 0.0, "nothing traced");
        assert!((b.diffuse - 1.0).abs() < 1e-9);
        let row = |mode: &str, median_p: f64, best_p: f64, best_build: f64| BenchRow {
            scene: "a".into(),
            mode: mode.into(),
            threads: 1,
            build_ms_total: best_build * 2.0,
            primary: RaySetResult {
                mrays_per_s: median_p,
                ..Default::default()
            },
            best: Best {
                build_ms_total: best_build,
                primary: best_p,
                shadow: 0.0,
                diffuse: 0.0,
            },
            ..Default::default()
        };
        // Ours is fastest in cycle 1, theirs in cycle 2: the best ratio
        // compares 12 with 6 (build: their 15 ms over our 10 ms), whatever
        // the cycles' own ratios say.
        let cycles = vec![
            vec![
                row("rebraided", 10.0, 12.0, 10.0),
                row("embree-flat", 1.0, 2.0, 30.0),
            ],
            vec![
                row("rebraided", 5.0, 6.0, 20.0),
                row("embree-flat", 5.0, 6.0, 15.0),
            ],
        ];
        let s = format_ratios(&cycles, "rebraided", &["embree-flat"], CycleStat::Best);
        let cols = columns_of(&s, "a");
        assert_eq!(cols[2], "2.00", "{s}");
        assert_eq!(cols[5], "1.50", "{s}");
        // Ray sets without figures on either side: no ratio (NaN).
        assert_eq!(cols[3], "NaN", "{s}");
        let rows = median_rows(&cycles);
        assert_eq!(rows[0].best.primary, 12.0);
        assert_eq!(rows[0].best.build_ms_total, 10.0);
        assert_eq!(rows[1].best.build_ms_total, 15.0);
    }

    #[test]
    fn keep_sets_empties_the_others_and_rejects_unknown_names() {
        let r = Ray::infinite(Vec3::ZERO, Vec3::X);
        let mut sets = RaySets {
            primary: vec![r; 2],
            shadow: vec![r; 3],
            diffuse: vec![r; 4],
        };
        keep_sets(&mut sets, "shadow").unwrap();
        assert_eq!(
            (sets.primary.len(), sets.shadow.len(), sets.diffuse.len()),
            (0, 3, 0)
        );
        assert!(keep_sets(&mut sets, "shadow,bounce").is_err());
    }
}
