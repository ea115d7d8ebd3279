//! `rebraid animate`: a static scene plus a built-in animated object moving
//! through it, committed and traced frame after frame in each mode.
//!
//! Per mode, the static scene and the object (posed at t = 0) are built once
//! (the "initial build", not a frame); then every frame poses the object at
//! its time (interpolation), commits (the moved object's BVH is rebuilt or
//! refitted by `--policy`, the top level rebuilt; flat rebuilds everything),
//! and traces: a fixed set of primary rays (one per pixel centre), and
//! shadow and diffuse rays made from the frame's primary hits (as `bench`
//! makes them, `crate::raysets`) for Mrays/s per ray set, and with `-o` a
//! path-traced PNG per frame. The summary gives the medians over the
//! frames.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use rebraid::glam::{Affine3A, Quat, Vec3};
use rebraid::procedural_dynamic::{DynamicKind, DynamicObject, DynamicParams};
use rebraid::{AccelMode, Ray, Scene, SceneParams, UpdatePolicy};
use serde::Serialize;

use crate::bench::median;
use crate::camera::{Camera, UpAxis};
use crate::loaders::LoadOptions;
use crate::raysets::RaySets;
use crate::render::{self, RenderSettings};
use crate::scene_input::SceneInput;

/// The built-in animated objects.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum DynamicArg {
    /// An articulated robot walking through the scene (one mesh, vertices posed per frame).
    LibraryRobot,
    /// A wobbling torus gliding through the scene (key-framed mesh and transform).
    Deforming,
    /// Sixty-four instances of one torus (the triangles shared out among
    /// them) flying rigidly through the scene: instance transforms set per
    /// frame, no vertex moves.
    Swarm,
}

/// Instances of [`DynamicArg::Swarm`].
pub const SWARM_INSTANCES: usize = 64;

impl DynamicArg {
    pub fn kind(self) -> DynamicKind {
        match self {
            DynamicArg::LibraryRobot => DynamicKind::Robot,
            DynamicArg::Deforming | DynamicArg::Swarm => DynamicKind::Deforming,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            DynamicArg::LibraryRobot => "library-robot",
            DynamicArg::Deforming => "deforming",
            DynamicArg::Swarm => "swarm",
        }
    }
}

/// Object-to-world transform of swarm instance `k` at time `t`: spread
/// over eight lanes beside the path and eight heights, each a phase of
/// the path ahead of the last, turning about the up axis as it goes.
fn swarm_transform(p: &DynamicParams, k: usize, t: f32) -> Affine3A {
    let lane = (k % 8) as f32 - 3.5;
    let level = (k / 8) as f32;
    let along = (t + k as f32 / SWARM_INSTANCES as f32).fract();
    let dir = p.end - p.start;
    let side = p.up.cross(dir).normalize_or_zero();
    let at = p.start
        + dir * along
        + side * (lane * 0.15 * p.height)
        + p.up * (p.height * (0.2 + 0.1 * level));
    let turn = Quat::from_axis_angle(p.up, std::f32::consts::TAU * (t + 0.37 * k as f32));
    Affine3A::from_rotation_translation(turn, at)
}

/// How the animated object's BVH follows it (two-level modes).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum PolicyArg {
    Refit,
    Rebuild,
}

impl PolicyArg {
    pub fn policy(self) -> UpdatePolicy {
        match self {
            PolicyArg::Refit => UpdatePolicy::Refit,
            PolicyArg::Rebuild => UpdatePolicy::Rebuild,
        }
    }
}

/// What to run.
#[derive(Clone, Debug)]
pub struct AnimateConfig {
    pub input: SceneInput,
    pub load: LoadOptions,
    /// Scene parameters (the mode is set per run).
    pub params: SceneParams,
    pub modes: Vec<AccelMode>,
    pub dynamic: DynamicArg,
    pub dynamic_triangles: usize,
    pub policy: PolicyArg,
    /// Keep the top-level build buffers between commits (the default).
    pub reuse_buffers: bool,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub bounces: u32,
    /// Write `<dir>/<mode>/frame_NNNN.png`.
    pub out_dir: Option<PathBuf>,
    pub json: Option<PathBuf>,
    /// `--camera` (default: the fitted camera).
    pub camera: Option<String>,
    pub up: UpAxis,
}

/// One frame of one mode.
#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct FrameRow {
    pub mode: String,
    pub frame: usize,
    pub time: f32,
    /// Posing the object (interpolation) and handing the vertices over.
    pub interp_ms: f64,
    /// Object BVH rebuilds (two-level modes).
    pub rebuild_ms: f64,
    /// Object BVH refits (two-level modes).
    pub refit_ms: f64,
    /// Top-level build, or the whole flat build.
    pub top_ms: f64,
    /// The whole commit.
    pub commit_ms: f64,
    /// Interpolation plus commit.
    pub update_ms: f64,
    pub objects_rebuilt: usize,
    pub objects_refitted: usize,
    /// Refs of the top level (of a split scene, the top level over the
    /// placements that did not move).
    pub top_refs: usize,
    /// A split scene's top level over the placements that moved (see
    /// `RebraidParams::moving_hold_commits`): its refs, 0 when not split.
    pub moving_refs: usize,
    /// The top level over the placements that did not move was kept from
    /// an earlier frame.
    pub fixed_kept: bool,
    /// Path-traced frame (with `-o`).
    pub render_ms: Option<f64>,
    pub primary_rays: usize,
    pub primary_hits: usize,
    /// Primary rays.
    pub mrays_per_s: f64,
    /// Shadow rays (occlusion) towards the point light from the frame's
    /// primary hits.
    pub shadow_mrays_per_s: f64,
    /// Diffuse rays (closest hit) from the frame's primary hits.
    pub diffuse_mrays_per_s: f64,
}

/// Medians of one mode over its frames.
#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct ModeSummary {
    pub mode: String,
    pub initial_build_ms: f64,
    pub frames: usize,
    pub median_update_ms: f64,
    pub median_commit_ms: f64,
    pub median_object_ms: f64,
    pub median_top_ms: f64,
    pub median_mrays_per_s: f64,
    pub median_shadow_mrays_per_s: f64,
    pub median_diffuse_mrays_per_s: f64,
    pub median_render_ms: Option<f64>,
}

#[derive(Serialize)]
struct Report<'a> {
    scene: String,
    dynamic: &'a str,
    dynamic_triangles: usize,
    static_triangles: usize,
    policy: &'a str,
    reuse_buffers: bool,
    width: u32,
    height: u32,
    camera: String,
    frames: &'a [FrameRow],
    summary: &'a [ModeSummary],
}

/// Run every mode; print the per-frame table and the summary; write the
/// PNGs and JSON asked for. Returns the rows and summaries.
pub fn run(cfg: &AnimateConfig) -> anyhow::Result<(Vec<FrameRow>, Vec<ModeSummary>)> {
    if cfg.frames == 0 || cfg.width == 0 || cfg.height == 0 || cfg.spp == 0 {
        bail!("--frames, --width, --height and --spp must be at least 1");
    }
    if cfg.modes.is_empty() {
        bail!("no mode to run");
    }
    let (desc, load_ms) = cfg.input.load(&cfg.load)?;
    let (_, bounds) = desc.world_boxes();
    let up = cfg.up.resolve(&bounds);
    let camera = match &cfg.camera {
        Some(s) => Camera::parse(s, up)?,
        None => Camera::fit(&bounds, up),
    };
    let swarm = cfg.dynamic == DynamicArg::Swarm;
    let dyn_params = DynamicParams::in_box(&bounds, up, cfg.dynamic_triangles);
    let object = if swarm {
        // One small torus, a twelfth of the height, centred at the origin
        // as the instances' prototype.
        DynamicObject::new(
            cfg.dynamic.kind(),
            &DynamicParams {
                start: Vec3::ZERO,
                end: Vec3::ZERO,
                height: dyn_params.height / 12.0,
                triangles: (cfg.dynamic_triangles / SWARM_INSTANCES).max(1),
                ..dyn_params
            },
        )?
    } else {
        DynamicObject::new(cfg.dynamic.kind(), &dyn_params)?
    };
    println!(
        "scene {}: {} objects, {} instances, {} triangles (loaded in {load_ms:.0} ms); camera {}",
        cfg.input.name(),
        desc.objects.len(),
        desc.instances.len(),
        desc.world_triangles(),
        camera.to_arg()
    );
    println!(
        "dynamic {}: {}{} triangles, {} vertices, height {:.2}, path {:?} -> {:?}; policy {:?}, {} frames",
        cfg.dynamic.name(),
        if swarm {
            format!("{SWARM_INSTANCES} instances of ")
        } else {
            String::new()
        },
        object.triangle_count(),
        object.vertex_count(),
        dyn_params.height,
        dyn_params.start.to_array(),
        dyn_params.end.to_array(),
        cfg.policy,
        cfg.frames
    );
    let cam = camera.rays(cfg.width, cfg.height);
    let rays: Vec<Ray> = (0..cfg.height)
        .flat_map(|y| (0..cfg.width).map(move |x| (x, y)))
        .map(|(x, y)| cam.pixel_ray(x, y))
        .collect();
    let mut hits = vec![None; rays.len()];
    let settings = RenderSettings {
        width: cfg.width,
        height: cfg.height,
        spp: cfg.spp,
        bounces: cfg.bounces,
        camera,
        bounds,
        up,
        progress: false,
    };

    let mut rows = Vec::new();
    let mut summaries = Vec::new();
    let mut positions: Vec<Vec3> = Vec::with_capacity(object.vertex_count());
    for &mode in &cfg.modes {
        let dir = match &cfg.out_dir {
            Some(d) => {
                let d = d.join(mode.name());
                std::fs::create_dir_all(&d).with_context(|| format!("creating {}", d.display()))?;
                Some(d)
            }
            None => None,
        };
        let mut scene = Scene::from_desc(
            &desc,
            SceneParams {
                mode,
                ..cfg.params.clone()
            },
        )?;
        scene.set_reuse_top_level_buffers(cfg.reuse_buffers);
        let (id, swarm_ids) = if swarm {
            let proto = scene.add_prototype(object.mesh_at(0.0))?;
            let ids = (0..SWARM_INSTANCES)
                .map(|k| scene.add_instance(proto, swarm_transform(&dyn_params, k, 0.0)))
                .collect::<Result<Vec<_>, _>>()?;
            (proto, ids)
        } else {
            (scene.add_object(object.mesh_at(0.0))?, Vec::new())
        };
        scene.set_update_policy(id, cfg.policy.policy())?;
        let initial = scene.commit()?;
        println!(
            "\n{}: initial build {:.1} ms (objects {:.1} ms, top {:.1} ms)",
            mode.name(),
            initial.total_ms,
            initial.object_build_ms,
            initial.top_build_ms
        );
        println!(
            "  {:>5} {:>6} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>8} {:>8} {:>8} {:>10} {:>8} {:>7} {:>5}",
            "frame",
            "t",
            "interp",
            "rebuild",
            "refit",
            "top",
            "commit",
            "update",
            "primary",
            "shadow",
            "diffuse",
            "render ms",
            "refs",
            "moving",
            "kept"
        );
        let mut mode_rows: Vec<FrameRow> = Vec::with_capacity(cfg.frames);
        for f in 0..cfg.frames {
            let t = if cfg.frames > 1 {
                f as f32 / (cfg.frames - 1) as f32
            } else {
                0.0
            };
            let t0 = Instant::now();
            if swarm {
                for (k, &inst) in swarm_ids.iter().enumerate() {
                    scene.set_instance_transform(inst, swarm_transform(&dyn_params, k, t))?;
                }
            } else {
                object.positions_into(t, &mut positions);
                scene.set_vertices(id, &positions)?;
            }
            let interp_ms = t0.elapsed().as_secs_f64() * 1e3;
            let rep = scene.commit()?;

            let t1 = Instant::now();
            scene.intersect_batch(&rays, &mut hits);
            let trace_s = t1.elapsed().as_secs_f64();
            let sets = RaySets::generate(&camera, cfg.width, cfg.height, &bounds, up, |r, h| {
                scene.intersect_batch(r, h)
            });
            let mrays = |n: usize, s: f64| n as f64 / s.max(1e-9) / 1e6;
            let t2 = Instant::now();
            let mut occluded = vec![false; sets.shadow.len()];
            scene.occluded_batch(&sets.shadow, &mut occluded);
            let shadow_mrays = mrays(sets.shadow.len(), t2.elapsed().as_secs_f64());
            let t3 = Instant::now();
            let mut diffuse_hits = vec![None; sets.diffuse.len()];
            scene.intersect_batch(&sets.diffuse, &mut diffuse_hits);
            let diffuse_mrays = mrays(sets.diffuse.len(), t3.elapsed().as_secs_f64());
            let render_ms = match &dir {
                Some(d) => {
                    let t2 = Instant::now();
                    let img = render::render(&scene, &settings);
                    let ms = t2.elapsed().as_secs_f64() * 1e3;
                    render::write_png(&d.join(format!("frame_{f:04}.png")), &img)?;
                    Some(ms)
                }
                None => None,
            };
            let row = FrameRow {
                mode: mode.name().to_string(),
                frame: f,
                time: t,
                interp_ms,
                rebuild_ms: rep.object_build_ms,
                refit_ms: rep.refit_ms,
                top_ms: rep.top_build_ms,
                commit_ms: rep.total_ms,
                update_ms: interp_ms + rep.total_ms,
                objects_rebuilt: rep.objects_rebuilt.len(),
                objects_refitted: rep.objects_refitted.len(),
                top_refs: rep.top.as_ref().map_or(0, |s| s.refs_final),
                moving_refs: rep.top_moving.as_ref().map_or(0, |s| s.refs_final),
                fixed_kept: rep.fixed_top_reused,
                render_ms,
                primary_rays: rays.len(),
                primary_hits: hits.iter().flatten().count(),
                mrays_per_s: mrays(rays.len(), trace_s),
                shadow_mrays_per_s: shadow_mrays,
                diffuse_mrays_per_s: diffuse_mrays,
            };
            println!(
                "  {:>5} {:>6.3} {:>9.2} {:>9.2} {:>9.2} {:>9.2} {:>9.2} {:>9.2} {:>8.2} {:>8.2} {:>8.2} {:>10} {:>8} {:>7} {:>5}",
                row.frame,
                row.time,
                row.interp_ms,
                row.rebuild_ms,
                row.refit_ms,
                row.top_ms,
                row.commit_ms,
                row.update_ms,
                row.mrays_per_s,
                row.shadow_mrays_per_s,
                row.diffuse_mrays_per_s,
                row.render_ms.map_or("-".to_string(), |m| format!("{m:.0}")),
                row.top_refs,
                row.moving_refs,
                if row.fixed_kept { "yes" } else { "-" }
            );
            mode_rows.push(row);
        }
        let med = |f: &dyn Fn(&FrameRow) -> f64| median(mode_rows.iter().map(f).collect());
        summaries.push(ModeSummary {
            mode: mode.name().to_string(),
            initial_build_ms: initial.total_ms,
            frames: cfg.frames,
            median_update_ms: med(&|r| r.update_ms),
            median_commit_ms: med(&|r| r.commit_ms),
            median_object_ms: med(&|r| r.rebuild_ms + r.refit_ms),
            median_top_ms: med(&|r| r.top_ms),
            median_mrays_per_s: med(&|r| r.mrays_per_s),
            median_shadow_mrays_per_s: med(&|r| r.shadow_mrays_per_s),
            median_diffuse_mrays_per_s: med(&|r| r.diffuse_mrays_per_s),
            median_render_ms: dir.as_ref().map(|_| med(&|r| r.render_ms.unwrap_or(0.0))),
        });
        rows.extend(mode_rows);
    }

    println!(
        "\nsummary (medians over {} frames; update = interpolation + commit; Mrays/s per ray set)",
        cfg.frames
    );
    println!(
        "  {:<10} {:>12} {:>10} {:>10} {:>10} {:>10} {:>9} {:>9} {:>9}",
        "mode",
        "initial ms",
        "update ms",
        "commit ms",
        "object ms",
        "top ms",
        "primary",
        "shadow",
        "diffuse"
    );
    for s in &summaries {
        println!(
            "  {:<10} {:>12.1} {:>10.2} {:>10.2} {:>10.2} {:>10.2} {:>9.2} {:>9.2} {:>9.2}",
            s.mode,
            s.initial_build_ms,
            s.median_update_ms,
            s.median_commit_ms,
            s.median_object_ms,
            s.median_top_ms,
            s.median_mrays_per_s,
            s.median_shadow_mrays_per_s,
            s.median_diffuse_mrays_per_s
        );
    }
    if let Some(d) = &cfg.out_dir {
        println!(
            "wrote {} frames per mode to {}/<mode>/frame_NNNN.png",
            cfg.frames,
            d.display()
        );
    }
    if let Some(p) = &cfg.json {
        let report = Report {
            scene: cfg.input.name(),
            dynamic: cfg.dynamic.name(),
            dynamic_triangles: object.triangle_count() * if swarm { SWARM_INSTANCES } else { 1 },
            static_triangles: desc.world_triangles(),
            policy: match cfg.policy {
                PolicyArg::Refit => "refit",
                PolicyArg::Rebuild => "rebuild",
            },
            reuse_buffers: cfg.reuse_buffers,
            width: cfg.width,
            height: cfg.height,
            camera: camera.to_arg(),
            frames: &rows,
            summary: &summaries,
        };
        std::fs::write(p, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", p.display()))?;
        println!("wrote {}", p.display());
    }
    Ok((rows, summaries))
}
