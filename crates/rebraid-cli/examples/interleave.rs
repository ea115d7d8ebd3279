//! How finely a scene's objects interleave, measured on its triangles alone
//! (no BVH built): the question a rule for merging objects placed directly
//! (`rebraid --merge-placed`) would have to answer before the build.
//!
//! The world triangles (instances transformed) are sorted by the Morton code
//! of their centroids and cut into groups of `g` consecutive triangles, a
//! stand-in for the leaves one BVH over all of them would make. Two figures
//! per group size:
//!
//! - `objects`: placements other than the first per group, on average
//!   (0 when no group mixes placements);
//! - `R`: the summed surface area of the groups formed within each placement
//!   alone (its own triangles in Morton order, cut the same way: the leaves
//!   of per-object BVHs) over that of the groups over all triangles. Above 1,
//!   per-object leaves are larger than mixed ones would be: what re-braiding
//!   cannot undo, since it opens object BVHs but never mixes their leaves.
//!
//! - `seams`: the share of triangles with a vertex (its exact position) that
//!   a triangle of another placement also has: objects cut from one surface
//!   (by material, say) meet along such seams, and per-object leaves end at
//!   every seam.
//!
//! Session 46 (docs/performance.md): neither `objects` nor `R` tells nexuiz,
//! where merging makes diffuse rays 20% faster, from the library, where it
//! makes them 17% slower (R 1.9 against 2.8 at g = 4). Session 48: nor do
//! seams (nexuiz 21%, the library 5%, but openarena 37%, where merging gains
//! nothing).
//!
//! ```sh
//! cargo run --release -p rebraid-cli --example interleave -- SCENE... [library@SCALE]
//! ```

#[path = "support/morton.rs"]
mod morton;

use anyhow::Context;
use glam::Vec3;
use rebraid_cli::loaders::{LoadOptions, Split};
use rebraid_cli::scene_input::SceneInput;
use std::collections::HashMap;

/// A triangle in Morton order: its key, its placement and its box.
type Keyed = (u64, u32, Vec3, Vec3);

/// Half the surface area of the box around `group`.
fn half_area(group: &[Keyed]) -> f64 {
    let (lo, hi) = group.iter().fold(
        (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
        |(lo, hi), k| (lo.min(k.2), hi.max(k.3)),
    );
    let d = (hi - lo).as_dvec3();
    d.x * d.y + d.y * d.z + d.z * d.x
}

fn main() -> anyhow::Result<()> {
    let scenes: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        !scenes.is_empty(),
        "usage: interleave SCENE... [library@SCALE]"
    );
    for arg in scenes {
        let (name, scale) = match arg.split_once('@') {
            Some((a, s)) => (a.to_string(), s.parse().context("library@SCALE")?),
            None => (arg, 0.25),
        };
        let input = SceneInput::parse(&name, scale, 1)?;
        let opts = LoadOptions {
            split: Split::Object,
            flatten_instances: false,
            // The objects as the file's `o` statements cut them: what
            // these predictors were measured on (sessions 46 and 48).
            keep_touching_apart: true,
        };
        let (desc, _) = input.load(&opts)?;
        // Placements: objects placed directly, then instances.
        let mut tris: Vec<([Vec3; 3], u32)> = Vec::new();
        for (id, o) in desc.objects.iter().enumerate().filter(|(_, o)| o.placed) {
            tris.extend((0..o.mesh.len()).map(|t| (o.mesh.triangle(t), id as u32)));
        }
        let base = desc.objects.len() as u32;
        for (id, inst) in desc.instances.iter().enumerate() {
            let mesh = &desc.objects[inst.object as usize].mesh;
            tris.extend((0..mesh.len()).map(|t| {
                let world = mesh.triangle(t).map(|p| inst.transform.transform_point3(p));
                (world, base + id as u32)
            }));
        }
        // Seams: per exact vertex position, the first placement seen with
        // it and whether another has it too.
        let mut owner: HashMap<[u32; 3], (u32, bool)> = HashMap::new();
        let key = |p: Vec3| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
        for (t, id) in &tris {
            for &p in t {
                let e = owner.entry(key(p)).or_insert((*id, false));
                e.1 |= e.0 != *id;
            }
        }
        let seams = tris
            .iter()
            .filter(|(t, _)| t.iter().any(|&p| owner[&key(p)].1))
            .count();
        let centroid = |t: &[Vec3; 3]| (t[0] + t[1] + t[2]) / 3.0;
        let (lo, hi) = tris.iter().fold(
            (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
            |(lo, hi), (t, _)| (lo.min(centroid(t)), hi.max(centroid(t))),
        );
        let extent = (hi - lo).max(Vec3::splat(f32::MIN_POSITIVE));
        let mut keyed: Vec<Keyed> = tris
            .iter()
            .map(|(t, p)| {
                let key = morton::code(centroid(t), lo, extent);
                (key, *p, t[0].min(t[1]).min(t[2]), t[0].max(t[1]).max(t[2]))
            })
            .collect();
        keyed.sort_unstable_by_key(|k| k.0);
        let mut by_placement = keyed.clone();
        by_placement.sort_by_key(|k| (k.1, k.0));
        print!(
            "{:<26} {:>9} triangles, seams {:.1}%",
            input.name(),
            keyed.len(),
            100.0 * seams as f64 / keyed.len().max(1) as f64
        );
        for g in [4usize, 8, 32] {
            let (mut extra, mut groups) = (0usize, 0usize);
            for group in keyed.chunks(g) {
                let mut ids: Vec<u32> = group.iter().map(|k| k.1).collect();
                ids.sort_unstable();
                ids.dedup();
                extra += ids.len() - 1;
                groups += 1;
            }
            let mixed: f64 = keyed.chunks(g).map(half_area).sum();
            let apart: f64 = by_placement
                .chunk_by(|a, b| a.1 == b.1)
                .map(|own| own.chunks(g).map(half_area).sum::<f64>())
                .sum();
            print!(
                "  g={g}: objects {:.2} R {:.2}",
                extra as f64 / groups as f64,
                apart / mixed
            );
        }
        println!();
    }
    Ok(())
}
