//! The `rebraid` tool: render scenes, benchmark every acceleration mode, and
//! report scene statistics. Run with no arguments to render the built-in
//! `library` scene.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use rebraid::bvh::{Collapse, ReinsertParams};
use rebraid::{AccelMode, RefBudget, Scene, SceneParams};
use rebraid_cli::animate;
use rebraid_cli::bench::{
    self, BenchConfig, BenchRow, CycleStat, EmbreeApi, EmbreeFlags, EmbreeIsa,
};
use rebraid_cli::camera::{Camera, UpAxis};
use rebraid_cli::loaders::{LoadOptions, Split};
use rebraid_cli::render::{self, RenderSettings};
use rebraid_cli::scene_input::SceneInput;

#[derive(Parser, Debug)]
#[command(
    name = "rebraid",
    version,
    about = "Two-level BVHs with partial re-braiding: render and benchmark scenes"
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Path-trace a scene to a PNG (and optionally a traversal heat map).
    Render(RenderArgs),
    /// Build and trace scenes in every mode with the same rays; print a table.
    Bench(BenchArgs),
    /// Scene statistics: objects, triangles, overlap, and per mode the tree statistics.
    Stats(StatsArgs),
    /// Move a built-in animated object through a scene; per-frame update and trace times per mode.
    Animate(AnimateArgs),
    /// Internal: trace stored rays through Embree in its own process.
    #[command(hide = true)]
    EmbreeWorker(EmbreeWorkerArgs),
    /// Internal: build and trace stored rays in one of our modes in its own
    /// process (`bench --embree`, so that ours run as Embree's do).
    #[command(hide = true)]
    BenchWorker(BenchWorkerArgs),
}

/// Options every command shares: how to read scenes and place the camera.
#[derive(Args, Debug, Clone)]
struct SceneOpts {
    /// Size of the built-in `library` scene (1.0 is about a million triangles).
    #[arg(long, default_value_t = 0.25, allow_negative_numbers = true)]
    scale: f32,
    /// Seed of the built-in scenes.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// What becomes one object of an OBJ (or glTF with `material`).
    #[arg(long, value_enum, default_value_t = SplitArg::Object)]
    split: SplitArg,
    /// Bake glTF instances into plain objects.
    #[arg(long)]
    flatten_instances: bool,
    /// Keep OBJ objects that share vertex positions apart (by default they
    /// are joined into one object).
    #[arg(long)]
    keep_touching_apart: bool,
    /// Camera as eye_x,eye_y,eye_z,target_x,target_y,target_z,fov (default: inside the scene box at centre - 0.3 x extent, looking at the centre).
    #[arg(long, allow_hyphen_values = true)]
    camera: Option<String>,
    /// Up axis of the scene (auto: its shortest axis).
    #[arg(long, value_enum, default_value_t = UpAxis::Auto)]
    up: UpAxis,
    /// Re-braiding: open refs longer than this fraction of their list's extent.
    #[arg(long)]
    threshold: Option<f32>,
    /// Re-braiding budget: ref slots per initial ref (Embree: 2).
    #[arg(long)]
    budget_per_ref: Option<f32>,
    /// Re-braiding budget: ref slots per primitive of the distinct objects
    /// (instanced objects count once; Embree: 0.001).
    #[arg(long)]
    budget_per_prim: Option<f32>,
    /// Re-braiding budget: at least this many ref slots (Embree: 1000).
    #[arg(long)]
    budget_min: Option<usize>,
    /// Re-braiding budget: the per-primitive term grows by the placements'
    /// overlap over this when above 1 (default 15; 0: off, as Embree).
    #[arg(long)]
    budget_overlap_unit: Option<f32>,
    /// Do not open object BVHs through instance transforms (Embree's behaviour).
    #[arg(long)]
    no_open_instances: bool,
    /// Re-braiding: open only refs that overlap a ref of another object or instance.
    #[arg(long)]
    open_only_overlapping: bool,
    /// Re-braiding: opening rounds per build step (the paper: 1).
    #[arg(long)]
    open_rounds: Option<usize>,
    /// Two-level modes: keep objects that one instance places as instances
    /// (by default they are traced from world-space BVHs while the instance
    /// does not move).
    #[arg(long)]
    no_bake_instances: bool,
    /// Re-braiding: keep the object leaves that top-level leaves enter
    /// through an instance as entries (by default they are copied into the
    /// top level in world space).
    #[arg(long)]
    no_inline_instanced_leaves: bool,
    /// Re-braiding: graft object subtrees of at most this many triangles
    /// that top-level leaves enter into the top level (0: none).
    #[arg(long)]
    graft_max_prims: Option<u32>,
    /// Re-braiding: primitives the grafts may copy, per primitive of the
    /// distinct objects.
    #[arg(long)]
    graft_budget: Option<f32>,
    /// Re-braiding: graft past the budget the entries whose slot covers at
    /// least this share of the scene box's area per primitive (0: off).
    #[arg(long)]
    graft_share_per_prim: Option<f32>,
    /// Largest leaf of object (and flat) BVHs.
    #[arg(long)]
    max_leaf: Option<u32>,
    /// Flat mode and `--merge-placed`: keep the large leaves of several
    /// blocks the SAH prefers (see `LargeLeafSplit`; for comparing).
    #[arg(long)]
    no_large_leaf_split: bool,
    /// Let nodes whose box holds a quarter of the scene's volume stay leaves
    /// of more than two triangles, as the SAH prefers (see
    /// `SceneVolumeLeafLimit`; for comparing).
    #[arg(long)]
    no_scene_volume_leaf_limit: bool,
    /// Re-braiding: reinsertion over the top level after its build, as
    /// RATIO,PASSES[,MAX] (the share of its nodes searched per pass, the
    /// passes, at most MAX nodes per pass; default 0.3,3,4096; "off": none).
    #[arg(long)]
    reinsert: Option<String>,
    /// Reinsertion over every object (and flat) BVH after its build, as
    /// RATIO,PASSES[,MAX] (default off).
    #[arg(long)]
    reinsert_objects: Option<String>,
    /// Two-level modes: trace the objects placed directly (not instanced,
    /// without instances, not refitted) from one BVH over all their
    /// triangles, as a static scene; an object's first edit takes it out
    /// (one rebuild of the merged BVH), later edits rebuild only its own.
    #[arg(long)]
    merge_placed: bool,
    /// Re-braiding: graft a merged BVH (`--merge-placed`) of at most this
    /// many triangles whole into the top level (0: never; larger ones stay
    /// behind entries like any object). A merged BVH that is the whole
    /// scene is walked alone, without a top level, whatever this says.
    #[arg(long)]
    graft_merged_max_prims: Option<u32>,
    /// Re-braiding: commits a moved placement is traced from a second top
    /// level, built at every commit, while the top level over the others
    /// is kept (0: one top level over everything, rebuilt at every commit).
    #[arg(long)]
    moving_hold_commits: Option<u32>,
    /// Re-braiding: split moving placements off only while their world
    /// triangles are at most this share of the others'.
    #[arg(long)]
    moving_split_max_share: Option<f32>,
    /// How every binary BVH (objects, flat, the top level) becomes the
    /// 8-wide one traversal walks: the SAH-optimal choice of wide nodes, or
    /// Embree's greedy rule (the largest child opened first).
    #[arg(long, value_enum, default_value_t = CollapseArg::Optimal)]
    collapse: CollapseArg,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum CollapseArg {
    Optimal,
    Greedy,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug)]
enum SplitArg {
    Object,
    Group,
    Material,
    None,
}

impl SceneOpts {
    fn load_options(&self) -> LoadOptions {
        LoadOptions {
            split: match self.split {
                SplitArg::Object => Split::Object,
                SplitArg::Group => Split::Group,
                SplitArg::Material => Split::Material,
                SplitArg::None => Split::None,
            },
            flatten_instances: self.flatten_instances,
            keep_touching_apart: self.keep_touching_apart,
        }
    }

    fn scene_params(&self, mode: AccelMode) -> anyhow::Result<SceneParams> {
        let mut p = SceneParams {
            mode,
            ..Default::default()
        };
        let r = &mut p.rebraid;
        if let Some(t) = self.threshold {
            r.threshold = t;
        }
        if let RefBudget::Scaled {
            min,
            per_initial_ref,
            per_primitive,
            overlap_unit,
        } = &mut r.budget
        {
            if let Some(v) = self.budget_min {
                *min = v;
            }
            if let Some(v) = self.budget_per_ref {
                *per_initial_ref = v;
            }
            if let Some(v) = self.budget_per_prim {
                *per_primitive = v;
            }
            if let Some(v) = self.budget_overlap_unit {
                *overlap_unit = v;
            }
        }
        r.open_instances = !self.no_open_instances;
        r.bake_single_instances = !self.no_bake_instances;
        r.inline_instanced_leaves = !self.no_inline_instanced_leaves;
        if let Some(g) = self.graft_max_prims {
            r.graft_max_prims = g;
        }
        if let Some(g) = self.graft_budget {
            r.graft_budget = g;
        }
        if let Some(g) = self.graft_share_per_prim {
            r.graft_share_per_prim = g;
        }
        r.open_only_overlapping = self.open_only_overlapping;
        if let Some(k) = self.open_rounds {
            r.open_rounds = k;
        }
        if let Some(m) = self.max_leaf {
            p.object_build.max_leaf_size = m;
        }
        if self.no_large_leaf_split {
            p.object_build.large_leaf_split = None;
        }
        if self.no_scene_volume_leaf_limit {
            p.object_build.scene_volume_leaf_limit = None;
        }
        if let Some(v) = &self.reinsert {
            r.reinsert = parse_reinsert("--reinsert", v)?;
        }
        if let Some(v) = &self.reinsert_objects {
            p.object_build.reinsert = parse_reinsert("--reinsert-objects", v)?;
        }
        p.merge_placed = self.merge_placed;
        if let Some(g) = self.graft_merged_max_prims {
            r.graft_merged_max_prims = g;
        }
        if let Some(h) = self.moving_hold_commits {
            r.moving_hold_commits = h;
        }
        if let Some(s) = self.moving_split_max_share {
            r.moving_split_max_share = s;
        }
        let collapse = match self.collapse {
            CollapseArg::Optimal => Collapse::SahOptimal,
            CollapseArg::Greedy => Collapse::Greedy,
        };
        p.object_build.collapse = collapse;
        r.collapse = collapse;
        p.object_build.check()?;
        r.check()?;
        Ok(p)
    }

    /// These options as arguments of a worker process, which must load,
    /// place the camera and build exactly as this process does.
    fn worker_args(&self) -> Vec<String> {
        let name = |v: Option<clap::builder::PossibleValue>| {
            v.expect("no skipped variants").get_name().to_string()
        };
        let mut v = vec![
            format!("--scale={}", self.scale),
            format!("--seed={}", self.seed),
            format!("--split={}", name(self.split.to_possible_value())),
            format!("--up={}", name(self.up.to_possible_value())),
            format!("--collapse={}", name(self.collapse.to_possible_value())),
        ];
        let flags = [
            ("--flatten-instances", self.flatten_instances),
            ("--keep-touching-apart", self.keep_touching_apart),
            ("--no-open-instances", self.no_open_instances),
            ("--open-only-overlapping", self.open_only_overlapping),
            ("--no-bake-instances", self.no_bake_instances),
            (
                "--no-inline-instanced-leaves",
                self.no_inline_instanced_leaves,
            ),
            ("--merge-placed", self.merge_placed),
            ("--no-large-leaf-split", self.no_large_leaf_split),
            (
                "--no-scene-volume-leaf-limit",
                self.no_scene_volume_leaf_limit,
            ),
        ];
        v.extend(flags.iter().filter(|f| f.1).map(|f| f.0.to_string()));
        let values = [
            ("camera", self.camera.clone()),
            ("threshold", self.threshold.map(|x| x.to_string())),
            ("budget-per-ref", self.budget_per_ref.map(|x| x.to_string())),
            (
                "budget-per-prim",
                self.budget_per_prim.map(|x| x.to_string()),
            ),
            ("budget-min", self.budget_min.map(|x| x.to_string())),
            (
                "graft-max-prims",
                self.graft_max_prims.map(|x| x.to_string()),
            ),
            ("graft-budget", self.graft_budget.map(|x| x.to_string())),
            (
                "graft-merged-max-prims",
                self.graft_merged_max_prims.map(|x| x.to_string()),
            ),
            (
                "graft-share-per-prim",
                self.graft_share_per_prim.map(|x| x.to_string()),
            ),
            (
                "moving-hold-commits",
                self.moving_hold_commits.map(|x| x.to_string()),
            ),
            (
                "moving-split-max-share",
                self.moving_split_max_share.map(|x| x.to_string()),
            ),
            (
                "budget-overlap-unit",
                self.budget_overlap_unit.map(|x| x.to_string()),
            ),
            ("open-rounds", self.open_rounds.map(|x| x.to_string())),
            ("max-leaf", self.max_leaf.map(|x| x.to_string())),
            ("reinsert", self.reinsert.clone()),
            ("reinsert-objects", self.reinsert_objects.clone()),
        ];
        v.extend(
            values
                .into_iter()
                .filter_map(|(k, x)| x.map(|x| format!("--{k}={x}"))),
        );
        v
    }

    fn input(&self, arg: &str) -> anyhow::Result<SceneInput> {
        SceneInput::parse(arg, self.scale, self.seed)
    }

    fn camera(&self, bounds: &rebraid::Aabb) -> anyhow::Result<(Camera, rebraid::glam::Vec3)> {
        let up = self.up.resolve(bounds);
        let cam = match &self.camera {
            Some(s) => Camera::parse(s, up)?,
            None => Camera::fit(bounds, up),
        };
        Ok((cam, up))
    }
}

/// `RATIO,PASSES[,MAX]` or `off`.
fn parse_reinsert(flag: &str, s: &str) -> anyhow::Result<ReinsertParams> {
    if s.trim() == "off" {
        return Ok(ReinsertParams::OFF);
    }
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let parsed = || {
        let (r, p, m) = match parts[..] {
            [r, p] => (r, p, "0"),
            [r, p, m] => (r, p, m),
            _ => return None,
        };
        Some(ReinsertParams {
            batch_ratio: r.parse().ok()?,
            passes: p.parse().ok()?,
            max_batch: m.parse().ok()?,
        })
    };
    let parsed = parsed();
    let Some(params) = parsed else {
        bail!("{flag}: '{s}' is not RATIO,PASSES[,MAX] (e.g. 0.3,3,4096) or off");
    };
    params.check().with_context(|| format!("{flag}: '{s}'"))?;
    Ok(params)
}

fn parse_threads(s: &str) -> anyhow::Result<Vec<usize>> {
    let all = std::thread::available_parallelism().map_or(1, |n| n.get());
    s.split(',')
        .map(|x| match x.trim() {
            "N" | "n" | "all" => Ok(all),
            v => {
                let n: usize = v
                    .parse()
                    .with_context(|| format!("--threads: '{v}' is not a number or N"))?;
                if n == 0 {
                    bail!("--threads: 0 threads");
                }
                Ok(n)
            }
        })
        .collect()
}

fn parse_modes(s: &str) -> anyhow::Result<Vec<AccelMode>> {
    s.split(',')
        .map(|m| Ok(m.trim().parse::<AccelMode>()?))
        .collect()
}

#[derive(Args, Debug)]
struct RenderArgs {
    /// A scene file (OBJ, glTF/GLB, PLY) or `library`.
    #[arg(default_value = "library")]
    scene: String,
    #[arg(long, default_value = "rebraided")]
    mode: String,
    #[arg(short, long, default_value = "render.png")]
    output: PathBuf,
    #[arg(long, default_value_t = 960)]
    width: u32,
    #[arg(long, default_value_t = 540)]
    height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 4)]
    spp: u32,
    /// Diffuse bounces after the primary hit.
    #[arg(long, default_value_t = 2)]
    bounces: u32,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Also write a heat map of nodes visited per primary ray.
    #[arg(long)]
    heatmap: Option<PathBuf>,
    /// Node count at the hot end of the heat map's colour scale.
    #[arg(long, default_value_t = 400)]
    heat_max: u32,
    #[command(flatten)]
    opts: SceneOpts,
}

#[derive(Args, Debug)]
struct BenchArgs {
    /// Scene files or `library` (default: library).
    scenes: Vec<String>,
    #[arg(long, default_value = "flat,two-level,rebraided")]
    modes: String,
    /// Thread counts, comma-separated; N = all cores.
    #[arg(long, default_value = "1,N")]
    threads: String,
    /// Repetitions per figure (the median is reported). With `--embree`,
    /// repetitions are cycles: each runs every mode and every Embree worker
    /// once, in turn, and a ratio is the median of the cycles' ratios, so
    /// that ours and Embree's figures alternate in time.
    #[arg(long, default_value_t = 3)]
    reps: usize,
    #[arg(long, default_value_t = 1280)]
    width: u32,
    #[arg(long, default_value_t = 720)]
    height: u32,
    /// Write one JSON object per (scene, mode, threads) to this file.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Add Embree 3 rows (embree-flat, embree-two-level). Every row, ours
    /// and Embree's, is then built and traced in its own worker process,
    /// which builds once untimed before it times.
    #[arg(long)]
    embree: bool,
    /// With `--embree`: the highest instruction set Embree may use,
    /// comma-separated for a pair of Embree rows each (`auto`: Embree's own
    /// choice, AVX-512 where the CPU has it; `avx2` and `sse4.2` rows are
    /// named `embree-flat-avx2` and so on).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "auto")]
    embree_isa: Vec<EmbreeIsa>,
    /// With `--embree`: Embree's entry point for a batch, comma-separated
    /// for a pair of Embree rows each (`single`: `rtcIntersect1` per ray;
    /// `stream`: `rtcIntersect1M` per run of rays, rows named
    /// `embree-flat-stream` and so on).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "single")]
    embree_api: Vec<EmbreeApi>,
    /// With `--embree`: Embree's scene flags, comma-separated for a pair of
    /// Embree rows each (`default`: none, Embree's fast kernels, which are
    /// not watertight; `robust`: `RTC_SCENE_FLAG_ROBUST`, watertight as
    /// ours always are, rows named `embree-flat-robust` and so on).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "default")]
    embree_flags: Vec<EmbreeFlags>,
    /// Ray sets to trace, comma-separated (the others are generated but
    /// not traced and report 0): for profiling one workload.
    #[arg(long, default_value = "primary,shadow,diffuse")]
    sets: String,
    #[command(flatten)]
    opts: SceneOpts,
}

#[derive(Args, Debug)]
struct StatsArgs {
    /// Scene files or `library` (default: library).
    scenes: Vec<String>,
    #[arg(long, default_value = "flat,two-level,rebraided")]
    modes: String,
    #[arg(long)]
    json: Option<PathBuf>,
    /// Also trace `bench`'s primary, shadow and diffuse rays from a
    /// WIDTHxHEIGHT image (e.g. `480x270`) and report each mode's inner
    /// nodes and leaves visited per ray (top level and objects together),
    /// and of the leaves the entries into object BVHs: where a mode's
    /// traversal time goes, independent of the machine.
    #[arg(long, value_name = "WIDTHxHEIGHT")]
    visits: Option<String>,
    #[command(flatten)]
    opts: SceneOpts,
}

#[derive(Args, Debug)]
struct AnimateArgs {
    /// A scene file (OBJ, glTF/GLB, PLY) or `library`: the static scene.
    #[arg(default_value = "library")]
    scene: String,
    #[arg(long, default_value_t = 10)]
    frames: usize,
    /// The animated object.
    #[arg(long, value_enum, default_value_t = animate::DynamicArg::LibraryRobot)]
    dynamic: animate::DynamicArg,
    /// Triangles of the animated object.
    #[arg(long, default_value_t = 200_000)]
    dynamic_triangles: usize,
    /// Modes, comma-separated, run one after another.
    #[arg(long, default_value = "flat,two-level,rebraided")]
    mode: String,
    /// How the animated object's BVH follows it in the two-level modes.
    #[arg(long, value_enum, default_value_t = animate::PolicyArg::Refit)]
    policy: animate::PolicyArg,
    /// Allocate the top-level build's buffers anew every frame (for measurements).
    #[arg(long)]
    no_buffer_reuse: bool,
    /// Render every frame to <DIR>/<mode>/frame_NNNN.png.
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Write the per-frame rows and the summary as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
    #[arg(long, default_value_t = 960)]
    width: u32,
    #[arg(long, default_value_t = 540)]
    height: u32,
    #[arg(long, default_value_t = 1)]
    spp: u32,
    #[arg(long, default_value_t = 1)]
    bounces: u32,
    #[command(flatten)]
    opts: SceneOpts,
}

fn run_animate(a: AnimateArgs) -> anyhow::Result<()> {
    let cfg = animate::AnimateConfig {
        input: a.opts.input(&a.scene)?,
        load: a.opts.load_options(),
        params: a.opts.scene_params(AccelMode::Rebraided)?,
        modes: parse_modes(&a.mode)?,
        dynamic: a.dynamic,
        dynamic_triangles: a.dynamic_triangles,
        policy: a.policy,
        reuse_buffers: !a.no_buffer_reuse,
        frames: a.frames,
        width: a.width,
        height: a.height,
        spp: a.spp,
        bounces: a.bounces,
        out_dir: a.output,
        json: a.json,
        camera: a.opts.camera.clone(),
        up: a.opts.up,
    };
    animate::run(&cfg).map(|_| ())
}

/// What every worker process of `bench --embree` is given (see
/// `worker_command`): the scene, the stored rays, the row's mode, threads
/// and repetitions, and the scene options.
#[derive(Args, Debug)]
struct BenchWorkerArgs {
    scene: String,
    #[arg(long)]
    rays: PathBuf,
    #[arg(long)]
    mode: String,
    #[arg(long)]
    threads: usize,
    #[arg(long)]
    reps: usize,
    #[command(flatten)]
    opts: SceneOpts,
}

#[derive(Args, Debug)]
struct EmbreeWorkerArgs {
    #[command(flatten)]
    worker: BenchWorkerArgs,
    #[arg(long, value_enum, default_value = "auto")]
    max_isa: EmbreeIsa,
    #[arg(long, value_enum, default_value = "single")]
    api: EmbreeApi,
    #[arg(long, value_enum, default_value = "default")]
    flags: EmbreeFlags,
}

fn main() -> ExitCode {
    // A closed stdout (`rebraid stats ... | head -1`) ends the process
    // quietly, as it does any Unix filter: Rust ignores SIGPIPE, so every
    // `println!` after the reader left would panic with a backtrace.
    #[cfg(unix)]
    // SAFETY: called first thing, before any other thread exists; setting a
    // signal's disposition to its default action has no other effect.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    let result = match cli.command {
        None => run_render(RenderArgs::parse_from(["render"])),
        Some(Command::Render(a)) => run_render(a),
        Some(Command::Bench(a)) => run_bench(a),
        Some(Command::Stats(a)) => run_stats(a),
        Some(Command::Animate(a)) => run_animate(a),
        Some(Command::EmbreeWorker(a)) => run_embree_worker(a),
        Some(Command::BenchWorker(a)) => run_bench_worker(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

impl RenderArgs {
    fn parse_from<const N: usize>(args: [&str; N]) -> Self {
        #[derive(Parser)]
        struct Wrap {
            #[command(flatten)]
            a: RenderArgs,
        }
        Wrap::parse_from(args).a
    }
}

fn run_render(a: RenderArgs) -> anyhow::Result<()> {
    if a.width == 0 || a.height == 0 || a.spp == 0 {
        bail!("--width, --height and --spp must be at least 1");
    }
    if let Some(t) = a.threads {
        if t == 0 {
            bail!("--threads must be at least 1");
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build_global()
            .ok();
    }
    let mode: AccelMode = a.mode.parse()?;
    let input = a.opts.input(&a.scene)?;
    let (desc, load_ms) = input.load(&a.opts.load_options())?;
    let (_, bounds) = desc.world_boxes();
    let (camera, up) = a.opts.camera(&bounds)?;
    let mut scene = Scene::from_desc(&desc, a.opts.scene_params(mode)?)?;
    let report = scene.commit()?;
    let st = scene.stats();
    println!(
        "scene {}: {} objects, {} instances, {} triangles (loaded in {load_ms:.0} ms)",
        input.name(),
        st.objects,
        st.instances,
        st.world_triangles
    );
    println!(
        "mode {}: built in {:.1} ms (objects {:.1} ms, top {:.1} ms), SAH cost {:.1}, {:.1} MB",
        mode.name(),
        report.total_ms,
        report.object_build_ms,
        report.top_build_ms,
        st.sah_cost,
        st.bytes as f64 / 1048576.0
    );
    println!("camera {}", camera.to_arg());
    let settings = RenderSettings {
        width: a.width,
        height: a.height,
        spp: a.spp,
        bounces: a.bounces,
        camera,
        bounds,
        up,
        progress: true,
    };
    let t = std::time::Instant::now();
    let img = render::render(&scene, &settings);
    render::write_png(&a.output, &img)?;
    println!(
        "wrote {} ({}x{}, {} spp) in {:.2} s",
        a.output.display(),
        a.width,
        a.height,
        a.spp,
        t.elapsed().as_secs_f64()
    );
    if let Some(h) = &a.heatmap {
        let counts = render::heat_counts(&scene, &settings);
        render::write_heatmap(h, &counts, a.width, a.height, a.heat_max)?;
        let mean = counts.iter().map(|&c| c as f64).sum::<f64>() / counts.len().max(1) as f64;
        println!(
            "wrote {}: nodes visited per primary ray, colour bar 0 (black) .. {} (white) nodes; mean {mean:.1}, max {}",
            h.display(),
            a.heat_max,
            counts.iter().max().copied().unwrap_or(0)
        );
    }
    Ok(())
}

fn scene_list(scenes: &[String]) -> Vec<String> {
    if scenes.is_empty() {
        vec!["library".to_string()]
    } else {
        scenes.to_vec()
    }
}

fn run_bench(a: BenchArgs) -> anyhow::Result<()> {
    let modes = parse_modes(&a.modes)?;
    let threads = parse_threads(&a.threads)?;
    if a.reps == 0 || a.width == 0 || a.height == 0 {
        bail!("--reps, --width and --height must be at least 1");
    }
    if a.embree && !cfg!(feature = "embree") {
        bail!(
            "--embree needs the tool built with `--features embree` (and libembree-dev installed)"
        );
    }
    let inputs: Vec<SceneInput> = scene_list(&a.scenes)
        .iter()
        .map(|s| a.opts.input(s))
        .collect::<Result<_, _>>()?;
    // Without Embree, one cycle of `reps` repetitions (the modes alternate
    // inside it); with Embree, `reps` cycles of one repetition each.
    let (cycles, reps_per_cycle) = if a.embree { (a.reps, 1) } else { (1, a.reps) };
    // Which machine: the project's build machine has changed between
    // sessions (AMD with AVX2 only, Intel with AVX-512), and a figure is
    // read against the CPU it ran on.
    let machine = bench::machine_description();
    println!("machine: {machine}");
    let mut rows: Vec<BenchRow> = Vec::new();
    let mut all_cycles: Vec<Vec<BenchRow>> = vec![Vec::new(); cycles];
    for input in &inputs {
        let name = input.name();
        let (desc, load_ms) = input.load(&a.opts.load_options())?;
        let (_, bounds) = desc.world_boxes();
        let (camera, up) = a.opts.camera(&bounds)?;
        eprintln!(
            "{name}: {} objects, {} instances, {} triangles, overlap {:.1}, loaded in {load_ms:.0} ms; camera {}",
            desc.objects.len(),
            desc.instances.len(),
            desc.world_triangles(),
            desc.overlap_ratio(),
            camera.to_arg()
        );
        let params = a.opts.scene_params(modes[0])?;
        let mut sets = bench::make_ray_sets(&desc, &params, &camera, up, a.width, a.height)?;
        bench::keep_sets(&mut sets, &a.sets)?;
        let cfg = BenchConfig {
            modes: modes.clone(),
            threads: threads.clone(),
            reps: reps_per_cycle,
            width: a.width,
            height: a.height,
            params,
            warmup: false,
        };
        let ray_dir = a.embree.then(|| -> anyhow::Result<_> {
            let dir = tempfile_dir()?;
            bench::write_rays(&dir.join("rays.bin"), &sets)?;
            Ok(dir)
        });
        let ray_dir = ray_dir.transpose()?;
        let mut scene_cycles = Vec::with_capacity(cycles);
        for (c, cycle_all) in all_cycles.iter_mut().enumerate() {
            let tag = if cycles > 1 {
                format!(" [cycle {}/{cycles}]", c + 1)
            } else {
                String::new()
            };
            let mut cycle_rows = match &ray_dir {
                // Beside Embree, our modes run as its workers do: each in a
                // fresh process that builds once untimed, then is timed.
                Some(dir) => our_rows(input, &a, &dir.join("rays.bin"), &cfg, &tag)?,
                None => {
                    let rows = bench::bench_scene(&name, &desc, &sets, &camera, &cfg, |msg| {
                        eprint!("\r\x1b[2K{msg}{tag}")
                    })?;
                    eprint!("\r\x1b[2K");
                    rows
                }
            };
            if let Some(dir) = &ray_dir {
                cycle_rows.extend(embree_rows(
                    input,
                    &a,
                    &dir.join("rays.bin"),
                    &threads,
                    reps_per_cycle,
                    &tag,
                )?);
            }
            cycle_all.extend(cycle_rows.iter().cloned());
            scene_cycles.push(cycle_rows);
        }
        if let Some(dir) = &ray_dir {
            std::fs::remove_dir_all(dir).ok();
        }
        let scene_rows = bench::median_rows(&scene_cycles);
        print!("{}", bench::format_table(&scene_rows));
        rows.extend(scene_rows);
    }
    println!();
    print!("{}", bench::format_answers(&rows));
    let baselines: Vec<String> = embree_variants(&a)
        .flat_map(|v| ["embree-two-level", "embree-flat"].map(|m| embree_row_name(m, v)))
        .collect();
    let baselines: Vec<&str> = baselines.iter().map(String::as_str).collect();
    let mut ratios = bench::format_ratios(&all_cycles, "rebraided", &baselines, CycleStat::Median);
    // Where a gap to Embree's flat BVH lies: the re-braided structure
    // against our own flat BVH over the same triangles (same kernels), and
    // our flat BVH against Embree's (the same structure, both builders and
    // kernels). Within a cycle their product is rebraided / embree-flat.
    let flats: Vec<&str> = baselines
        .iter()
        .copied()
        .filter(|b| b.starts_with("embree-flat"))
        .collect();
    for (mode, base) in [("rebraided", &["flat"][..]), ("flat", &flats[..])] {
        ratios.push_str(&bench::format_ratios(
            &all_cycles,
            mode,
            base,
            CycleStat::Median,
        ));
    }
    if !ratios.is_empty() {
        println!();
        if cycles > 1 {
            println!("(each ratio: the median over {cycles} cycles of the ratio within a cycle)");
        }
        print!("{ratios}");
        if cycles > 1 {
            println!();
            println!(
                "(each ratio: of the fastest of {cycles} cycles of either row; interference only slows a run down)"
            );
            print!(
                "{}",
                bench::format_ratios(&all_cycles, "rebraided", &baselines, CycleStat::Best)
            );
        }
    }
    if let Some(p) = &a.json {
        let mut s = String::new();
        for r in &rows {
            let r = BenchRow {
                machine: machine.clone(),
                ..r.clone()
            };
            s.push_str(&serde_json::to_string(&r)?);
            s.push('\n');
        }
        std::fs::write(p, s).with_context(|| format!("writing {}", p.display()))?;
        println!("wrote {}", p.display());
    }
    Ok(())
}

/// One Embree configuration of `bench --embree`.
type EmbreeVariant = (EmbreeIsa, EmbreeApi, EmbreeFlags);

/// The Embree variants `bench --embree` times: every ISA with every set of
/// flags and every API.
fn embree_variants(a: &BenchArgs) -> impl Iterator<Item = EmbreeVariant> + '_ {
    a.embree_isa.iter().flat_map(move |&isa| {
        a.embree_flags
            .iter()
            .flat_map(move |&flags| a.embree_api.iter().map(move |&api| (isa, api, flags)))
    })
}

/// The bench row of Embree `mode` in `variant`: `embree-flat`,
/// `embree-flat-avx2-robust-stream` and so on.
fn embree_row_name(mode: &str, (isa, api, flags): EmbreeVariant) -> String {
    format!(
        "{mode}{}{}{}",
        isa.mode_suffix(),
        flags.mode_suffix(),
        api.mode_suffix()
    )
}

/// A fresh directory for the ray file the Embree workers read.
fn tempfile_dir() -> anyhow::Result<PathBuf> {
    let dir = std::env::temp_dir().join(format!("rebraid-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    Ok(dir)
}

/// Embree rows, each (mode, threads) traced by a worker process with
/// `reps` repetitions; `tag` names the cycle in the progress line.
fn embree_rows(
    input: &SceneInput,
    a: &BenchArgs,
    rays: &std::path::Path,
    threads: &[usize],
    reps: usize,
    tag: &str,
) -> anyhow::Result<Vec<BenchRow>> {
    let mut rows = Vec::new();
    for &t in threads {
        for (v, mode) in
            embree_variants(a).flat_map(|v| ["embree-flat", "embree-two-level"].map(|m| (v, m)))
        {
            let (isa, api, flags) = v;
            let name = embree_row_name(mode, v);
            eprint!(
                "\r\x1b[2K{}: {name} ({t} thr) in a worker process{tag}",
                input.name(),
            );
            let mut cmd = worker_command("embree-worker", input, rays, t, reps, a)?;
            cmd.args(["--mode", mode])
                .args(["--max-isa", isa.arg()])
                .args(["--api", api.arg()])
                .args(["--flags", flags.arg()]);
            let mut row = worker_row(cmd, "Embree worker")?;
            row.scene = input.name();
            row.mode = name;
            rows.push(row);
        }
    }
    eprint!("\r\x1b[2K");
    Ok(rows)
}

/// This program as a worker process (`embree-worker` or `bench-worker`)
/// over `input` and the stored `rays`, with `threads` threads, `reps`
/// repetitions, and the scene options of `a`.
fn worker_command(
    worker: &str,
    input: &SceneInput,
    rays: &std::path::Path,
    threads: usize,
    reps: usize,
    a: &BenchArgs,
) -> anyhow::Result<std::process::Command> {
    let scene_arg = match input {
        SceneInput::Library { .. } => "library".to_string(),
        SceneInput::Grid { .. } => "grid".to_string(),
        SceneInput::File(p) => p.display().to_string(),
    };
    let mut cmd = std::process::Command::new(std::env::current_exe()?);
    cmd.args([worker, &scene_arg])
        .arg("--rays")
        .arg(rays)
        .args([
            "--threads",
            &threads.to_string(),
            "--reps",
            &reps.to_string(),
        ])
        .args(a.opts.worker_args());
    Ok(cmd)
}

/// Run a worker process and read the row it prints.
fn worker_row(mut cmd: std::process::Command, what: &str) -> anyhow::Result<BenchRow> {
    let out = cmd
        .output()
        .with_context(|| format!("running the {what}"))?;
    if !out.status.success() {
        bail!(
            "{what} failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    // The row is the last line; anything before it is Embree's own log
    // (`REBRAID_EMBREE_VERBOSE`), passed on to our stderr.
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stdout = stdout.trim_end();
    let (log, row) = stdout.rsplit_once('\n').unwrap_or(("", stdout));
    if !log.is_empty() {
        eprintln!("{log}");
    }
    serde_json::from_str(row).with_context(|| format!("reading the {what}'s row"))
}

/// Our rows of one cycle beside Embree's, each (threads, mode) built and
/// traced by a worker process as Embree's are (see [`embree_rows`]): a
/// fresh process, one untimed build, then `cfg.reps` timed ones. Run in
/// this long-lived process instead, our builds were up to 1.3x slower than
/// alone (nexuiz, re-braided, one thread: 51.9 ms against 40.0-41.7 ms;
/// `docs/performance.md`, session 12) while Embree's ran fresh.
fn our_rows(
    input: &SceneInput,
    a: &BenchArgs,
    rays: &std::path::Path,
    cfg: &BenchConfig,
    tag: &str,
) -> anyhow::Result<Vec<BenchRow>> {
    let mut rows = Vec::new();
    for &t in &cfg.threads {
        for mode in &cfg.modes {
            eprint!(
                "\r\x1b[2K{}: {} ({t} thr) in a worker process{tag}",
                input.name(),
                mode.name()
            );
            let mut cmd = worker_command("bench-worker", input, rays, t, cfg.reps, a)?;
            cmd.args(["--mode", mode.name()]);
            let mut row = worker_row(cmd, "bench worker")?;
            row.scene = input.name();
            rows.push(row);
        }
    }
    eprint!("\r\x1b[2K");
    Ok(rows)
}

/// The `bench-worker` process: one mode of ours over the stored rays, as
/// `bench` measures it, with one untimed build first; prints the row.
fn run_bench_worker(a: BenchWorkerArgs) -> anyhow::Result<()> {
    let mode: AccelMode = a.mode.parse()?;
    let input = a.opts.input(&a.scene)?;
    let (desc, _) = input.load(&a.opts.load_options())?;
    let (_, bounds) = desc.world_boxes();
    let (camera, _) = a.opts.camera(&bounds)?;
    let sets = bench::read_rays(&a.rays)?;
    let cfg = BenchConfig {
        modes: vec![mode],
        threads: vec![a.threads],
        reps: a.reps,
        width: 0,
        height: 0,
        params: a.opts.scene_params(mode)?,
        warmup: true,
    };
    let rows = bench::bench_scene(&input.name(), &desc, &sets, &camera, &cfg, |_| {})?;
    let row = rows
        .into_iter()
        .next()
        .context("the bench worker made no row")?;
    println!("{}", serde_json::to_string(&row)?);
    Ok(())
}

#[cfg(feature = "embree")]
fn run_embree_worker(a: EmbreeWorkerArgs) -> anyhow::Result<()> {
    let w = &a.worker;
    let row = rebraid_cli::embree_bench::run_worker(
        &w.opts.input(&w.scene)?,
        &w.opts.load_options(),
        &w.rays,
        &w.mode,
        w.threads,
        w.reps,
        (a.max_isa, a.api, a.flags),
    )?;
    println!("{}", serde_json::to_string(&row)?);
    Ok(())
}

#[cfg(not(feature = "embree"))]
fn run_embree_worker(_: EmbreeWorkerArgs) -> anyhow::Result<()> {
    bail!("this build has no Embree support (build with --features embree)")
}

/// One row of `rebraid stats`' top-level phases: the binned build (its
/// reinsertion apart), the layout pass by phase, their total and its share
/// of the commit's `total_ms`.
fn top_phases_line(mode: &str, p: &bench::TopPhases, total_ms: f64) -> String {
    let sum = p.total();
    let share = if total_ms > 0.0 {
        100.0 * sum / total_ms
    } else {
        0.0
    };
    format!(
        "  {:<10} {:>7.2} {:>8.2} {:>9.2} {:>8.2} {:>8.2} {:>7.2} {:>7.2} {:>7.2} {:>5.1}%",
        mode, p.build, p.reinsert, p.collapse, p.entries, p.grafts, p.order, p.copies, sum, share
    )
}

fn run_stats(a: StatsArgs) -> anyhow::Result<()> {
    let modes = parse_modes(&a.modes)?;
    let inputs: Vec<SceneInput> = scene_list(&a.scenes)
        .iter()
        .map(|s| a.opts.input(s))
        .collect::<Result<_, _>>()?;
    let mut json = String::new();
    for input in &inputs {
        let (desc, load_ms) = input.load(&a.opts.load_options())?;
        let overlap = desc.overlap_ratio();
        println!(
            "{}: {} objects, {} instances, {} world triangles ({} unique), overlap {:.2}, loaded in {load_ms:.0} ms",
            input.name(),
            desc.objects.len(),
            desc.instances.len(),
            desc.world_triangles(),
            desc.unique_triangles(),
            overlap
        );
        println!(
            "  {:<10} {:>10} {:>10} {:>9} {:>10} {:>9} {:>10} {:>9} {:>9} {:>9}",
            "mode",
            "build ms",
            "SAH",
            "MB",
            "top nodes",
            "top depth",
            "refs",
            "opened",
            "capacity",
            "wide SAH"
        );
        let mut per_mode = Vec::new();
        let sets = match &a.visits {
            Some(size) => {
                let (width, height) = parse_image_size(size)?;
                let (_, bounds) = desc.world_boxes();
                let (camera, up) = a.opts.camera(&bounds)?;
                let params = a.opts.scene_params(modes[0])?;
                Some(bench::make_ray_sets(
                    &desc, &params, &camera, up, width, height,
                )?)
            }
            None => None,
        };
        let mut visit_lines = Vec::new();
        let mut phase_lines = Vec::new();
        for &mode in &modes {
            let mut scene = Scene::from_desc(&desc, a.opts.scene_params(mode)?)?;
            let rep = scene.commit()?;
            let st = scene.stats();
            let top = st.top.clone().unwrap_or_default();
            println!(
                "  {:<10} {:>10.1} {:>10.2} {:>9.1} {:>10} {:>9} {:>10} {:>9} {:>9} {:>9.3}",
                mode.name(),
                rep.total_ms,
                st.sah_cost,
                st.bytes as f64 / 1048576.0,
                st.top_nodes,
                st.top_depth,
                top.refs_final,
                top.nodes_opened,
                top.capacity,
                st.wide_sah_cost
            );
            let mut visits = serde_json::Value::Null;
            if let Some(sets) = &sets {
                let v = bench::visits_per_ray(&scene, sets);
                visits = serde_json::json!({
                    "primary": v[0],
                    "shadow": v[1],
                    "diffuse": v[2],
                });
                let mut line = format!("  {:<10}", mode.name());
                for [inner, leaves, entries] in v {
                    line += &format!(" {inner:>9.2} {leaves:>7.2} {entries:>7.2}");
                }
                visit_lines.push(line);
            }
            let phases = bench::TopPhases::of(st.top.as_ref());
            per_mode.push(serde_json::json!({
                "mode": mode.name(),
                "build_ms": rep.total_ms,
                "build_ms_objects": rep.object_build_ms,
                "build_ms_top": rep.top_build_ms,
                "sah_cost": st.sah_cost,
                "wide_sah_cost": st.wide_sah_cost,
                "bytes": st.bytes,
                "top_nodes": st.top_nodes,
                "top_depth": st.top_depth,
                "refs_initial": top.refs_initial,
                "refs_final": top.refs_final,
                "refs_opened": top.nodes_opened,
                "ref_capacity": top.capacity,
                "flat_depth": st.flat.as_ref().map(|f| f.max_depth),
                "visits_per_ray": visits,
                "top_phases_ms": phases,
            }));
            if st.top.is_some() {
                phase_lines.push(top_phases_line(mode.name(), &phases, rep.total_ms));
            }
        }
        if !phase_lines.is_empty() {
            println!(
                "  top level by phase, ms (one build; share: of the whole commit, objects included):"
            );
            println!(
                "  {:<10} {:>7} {:>8} {:>9} {:>8} {:>8} {:>7} {:>7} {:>7} {:>6}",
                "mode",
                "build",
                "reinsert",
                "collapse",
                "entries",
                "grafts",
                "order",
                "copies",
                "total",
                "share"
            );
            for l in &phase_lines {
                println!("{l}");
            }
        }
        if !visit_lines.is_empty() {
            println!(
                "  visits per ray (inner nodes, leaves, and of the leaves the entries into objects; top level and objects together):"
            );
            let mut header = format!("  {:<10}", "mode");
            for set in ["primary", "shadow", "diffuse"] {
                header += &format!(" {set:>9} {:>7} {:>7}", "leaves", "entries");
            }
            println!("{header}");
            for l in &visit_lines {
                println!("{l}");
            }
        }
        let v = serde_json::json!({
            "scene": input.name(),
            "objects": desc.objects.len(),
            "instances": desc.instances.len(),
            "triangles": desc.world_triangles(),
            "unique_triangles": desc.unique_triangles(),
            "overlap": overlap,
            "modes": per_mode,
        });
        json.push_str(&serde_json::to_string(&v)?);
        json.push('\n');
    }
    if let Some(p) = &a.json {
        std::fs::write(p, json).with_context(|| format!("writing {}", p.display()))?;
        println!("wrote {}", p.display());
    }
    Ok(())
}

/// `WIDTHxHEIGHT`, both at least 1.
fn parse_image_size(s: &str) -> anyhow::Result<(u32, u32)> {
    let parsed = s
        .split_once(['x', 'X'])
        .and_then(|(w, h)| Some((w.trim().parse::<u32>().ok()?, h.trim().parse::<u32>().ok()?)));
    match parsed {
        Some((w, h)) if w > 0 && h > 0 => Ok((w, h)),
        _ => bail!("expected an image size WIDTHxHEIGHT such as 480x270, got `{s}`"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Parser, Debug)]
    struct OptsOnly {
        #[command(flatten)]
        opts: SceneOpts,
    }

    fn parse(args: &[String]) -> SceneOpts {
        OptsOnly::parse_from(std::iter::once("t".to_string()).chain(args.iter().cloned())).opts
    }

    /// A worker process gets every scene option this process was given:
    /// the options parsed back from `worker_args` are the same, for the
    /// defaults and for every option set (a negative scale and a camera
    /// starting with `-` included).
    #[test]
    fn worker_args_carry_every_scene_option() {
        let given: Vec<String> = [
            "--scale=-0.5",
            "--seed=7",
            "--split=material",
            "--flatten-instances",
            "--camera=-1,2,3,0,0,0,45",
            "--up=z",
            "--threshold=0.2",
            "--budget-per-ref=3",
            "--budget-per-prim=0.05",
            "--budget-min=500",
            "--no-open-instances",
            "--open-only-overlapping",
            "--open-rounds=2",
            "--no-bake-instances",
            "--max-leaf=4",
            "--no-large-leaf-split",
        ]
        .map(String::from)
        .to_vec();
        for args in [Vec::new(), given] {
            let opts = parse(&args);
            let again = parse(&opts.worker_args());
            assert_eq!(format!("{again:?}"), format!("{opts:?}"));
        }
    }
}
