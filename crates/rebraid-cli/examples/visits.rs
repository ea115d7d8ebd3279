//! Wide nodes and leaves visited per ray, by acceleration mode and ray set
//! (shadow rays: occlusion queries, which stop at the first hit):
//! how much of a mode's speed difference is tree shape (visits) and how much
//! is cost per visit. In the two-level modes a "leaf" is a top-level leaf
//! (an entry into an object) or an object's leaf.
//!
//! ```sh
//! cargo run --release -p rebraid-cli --example visits -- SCENE... [--width W --height H]
//!     [--budget-per-prim X]
//! ```

use anyhow::Context;
use rebraid::bvh::TraversalCounters;
use rebraid::{AccelMode, RefBudget, Scene, SceneParams};
use rebraid_cli::camera::{Camera, UpAxis};
use rebraid_cli::loaders::{LoadOptions, Split};
use rebraid_cli::raysets::RaySets;
use rebraid_cli::scene_input::SceneInput;

fn main() -> anyhow::Result<()> {
    let mut scenes = Vec::new();
    let (mut width, mut height) = (480u32, 270u32);
    let mut budget_per_prim: Option<f32> = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--width" => width = args.next().context("--width N")?.parse()?,
            "--height" => height = args.next().context("--height N")?.parse()?,
            "--budget-per-prim" => {
                budget_per_prim = Some(args.next().context("--budget-per-prim X")?.parse()?)
            }
            _ => scenes.push(a),
        }
    }
    println!(
        "{:<24} {:<10} {:<8} {:>8} {:>8}",
        "scene", "mode", "rays", "nodes", "leaves"
    );
    for arg in scenes {
        let input = SceneInput::parse(&arg, 0.25, 1)?;
        let opts = LoadOptions {
            split: Split::Object,
            flatten_instances: false,
            ..LoadOptions::default()
        };
        let (desc, _) = input.load(&opts)?;
        let (_, bounds) = desc.world_boxes();
        let up = UpAxis::Auto.resolve(&bounds);
        let camera = Camera::fit(&bounds, up);
        let mut built = Vec::new();
        for mode in [AccelMode::Flat, AccelMode::TwoLevel, AccelMode::Rebraided] {
            let mut params = SceneParams {
                mode,
                ..Default::default()
            };
            if let (Some(x), RefBudget::Scaled { per_primitive, .. }) =
                (budget_per_prim, &mut params.rebraid.budget)
            {
                *per_primitive = x;
            }
            let mut scene = Scene::from_desc(&desc, params)?;
            scene.commit()?;
            built.push((mode, scene));
        }
        let sets = RaySets::generate(&camera, width, height, &bounds, up, |r, h| {
            built[0].1.intersect_batch(r, h)
        });
        for (mode, scene) in &built {
            for (set, rays) in [
                ("primary", &sets.primary),
                ("shadow", &sets.shadow),
                ("diffuse", &sets.diffuse),
            ] {
                let mut c = TraversalCounters::default();
                for r in rays {
                    if set == "shadow" {
                        scene.occluded_counted(r, &mut c);
                    } else {
                        scene.intersect_counted(r, &mut c);
                    }
                }
                let n = rays.len().max(1) as f64;
                println!(
                    "{:<24} {:<10} {:<8} {:>8.2} {:>8.2}",
                    input.name(),
                    mode.name(),
                    set,
                    c.inner_visited as f64 / n,
                    c.leaves_visited as f64 / n
                );
            }
        }
    }
    Ok(())
}
