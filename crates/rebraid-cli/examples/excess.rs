//! Where the re-braided walk visits more than the flat one: per diffuse ray,
//! the re-braided mode's visited nodes and leaves (both levels) minus the
//! flat mode's over the same triangles, summed by the object the ray starts
//! on (the primary hit it bounces from) and by the object it hits.
//!
//! Session 49 found with it that nexuiz's excess starts on its terrain:
//! rays leaving a terrain patch start inside the boxes of the patches and
//! the grass that meet it there.
//!
//! ```sh
//! cargo run --release -p rebraid-cli --example excess -- SCENE [--width W --height H]
//!     [--keep-touching-apart] [--top N]
//! ```

use anyhow::Context;
use rebraid::bvh::TraversalCounters;
use rebraid::{AccelMode, Scene, SceneParams};
use rebraid_cli::camera::{Camera, UpAxis};
use rebraid_cli::loaders::LoadOptions;
use rebraid_cli::raysets::RaySets;
use rebraid_cli::scene_input::SceneInput;

/// Rays, re-braided minus flat visits, and flat visits, summed.
#[derive(Clone, Copy, Default)]
struct Sum {
    rays: u64,
    excess: i64,
    flat: i64,
}

fn main() -> anyhow::Result<()> {
    let mut scene = None;
    let (mut width, mut height, mut top) = (480u32, 270u32, 12usize);
    let mut opts = LoadOptions::default();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--width" => width = args.next().context("--width N")?.parse()?,
            "--height" => height = args.next().context("--height N")?.parse()?,
            "--top" => top = args.next().context("--top N")?.parse()?,
            "--keep-touching-apart" => opts.keep_touching_apart = true,
            _ => scene = Some(a),
        }
    }
    let input = SceneInput::parse(&scene.context("usage: excess SCENE [options]")?, 0.25, 1)?;
    let (desc, _) = input.load(&opts)?;
    let (_, bounds) = desc.world_boxes();
    let up = UpAxis::Auto.resolve(&bounds);
    let camera = Camera::fit(&bounds, up);
    let build = |mode| -> anyhow::Result<Scene> {
        let mut s = Scene::from_desc(
            &desc,
            SceneParams {
                mode,
                ..Default::default()
            },
        )?;
        s.commit()?;
        Ok(s)
    };
    let flat = build(AccelMode::Flat)?;
    let rebraided = build(AccelMode::Rebraided)?;
    let sets = RaySets::generate(&camera, width, height, &bounds, up, |r, h| {
        flat.intersect_batch(r, h)
    });
    // The diffuse rays bounce from the primary hits in order, one per hit
    // with a usable normal (`RaySets::generate`).
    let mut hits = vec![None; sets.primary.len()];
    flat.intersect_batch(&sets.primary, &mut hits);
    let starts: Vec<u32> = hits
        .iter()
        .flatten()
        .filter(|h| h.normal != rebraid::glam::Vec3::ZERO)
        .map(|h| h.object_id)
        .collect();
    anyhow::ensure!(
        starts.len() == sets.diffuse.len(),
        "diffuse rays do not match the primary hits"
    );
    let n = desc.objects.len();
    let (mut by_start, mut by_hit) = (vec![Sum::default(); n], vec![Sum::default(); n + 1]);
    let mut total = Sum::default();
    for (ray, &start) in sets.diffuse.iter().zip(&starts) {
        let (mut cf, mut cr) = (TraversalCounters::default(), TraversalCounters::default());
        let hit = flat.intersect_counted(ray, &mut cf);
        rebraided.intersect_counted(ray, &mut cr);
        let f = i64::from(cf.inner_visited + cf.leaves_visited);
        let r = i64::from(cr.inner_visited + cr.leaves_visited);
        let ended = hit.map_or(n, |h| h.object_id as usize);
        for s in [
            &mut by_start[start as usize],
            &mut by_hit[ended],
            &mut total,
        ] {
            s.rays += 1;
            s.excess += r - f;
            s.flat += f;
        }
    }
    let per = |x: i64, s: &Sum| x as f64 / s.rays.max(1) as f64;
    println!(
        "{}: {} diffuse rays, visits per ray flat {:.2}, re-braided {:.2} ({} objects)",
        input.name(),
        total.rays,
        per(total.flat, &total),
        per(total.flat + total.excess, &total),
        n
    );
    let name = |i: usize| desc.objects.get(i).map_or("(missed)", |o| o.name.as_str());
    for (title, sums) in [("starting on", &by_start), ("hitting", &by_hit)] {
        println!(
            "{:<40} {:>8} {:>8} {:>8} {:>7}",
            title, "rays", "excess", "flat", "share"
        );
        let mut order: Vec<usize> = (0..sums.len()).filter(|&i| sums[i].rays > 0).collect();
        order.sort_by_key(|&i| (-sums[i].excess, i));
        for &i in order.iter().take(top) {
            let s = &sums[i];
            println!(
                "{:<40} {:>8} {:>8.2} {:>8.2} {:>7.3}",
                name(i),
                s.rays,
                per(s.excess, s),
                per(s.flat, s),
                s.excess as f64 / total.excess.max(1) as f64
            );
        }
    }
    Ok(())
}
