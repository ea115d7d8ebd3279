//! A scene's placed triangles written as an OBJ whose objects are `K`
//! spatial chunks: the triangles in the Morton order of their centroids, cut
//! into `K` runs of equal length. Instances are flattened first.
//!
//! What it is for: telling what re-braiding loses to the object split of a
//! scene (its objects' leaves cannot mix triangles of two objects) from what
//! it loses to that split's shape. Session 48 (docs/performance.md), before
//! that session's leaf limit for boxes that hold the scene's volume: nexuiz
//! re-cut into 16-256 compact chunks traces diffuse rays re-braided at
//! 0.96-1.05 of its own 114 interleaved material objects, still 0.79-0.86
//! of the flat BVH over the same triangles: the loss grows with the number
//! of object boundaries (leaves per diffuse ray 3.34 at 2 chunks, 3.60 at
//! 16, 3.86 at 256, fully opened; 3.08 flat), not with how the objects
//! interleave.
//!
//! ```sh
//! cargo run --release -p rebraid-cli --example chunks -- SCENE K OUT.obj
//! ```
#[path = "support/morton.rs"]
mod morton;

use anyhow::Context;
use glam::Vec3;
use rebraid_cli::loaders::{LoadOptions, Split};
use rebraid_cli::scene_input::SceneInput;
use std::io::Write;

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(a.len() == 3, "usage: chunks SCENE|library@SCALE K OUT.obj");
    let (name, scale) = match a[0].split_once('@') {
        Some((n, s)) => (n.to_string(), s.parse().context("scale")?),
        None => (a[0].clone(), 0.25),
    };
    let k: usize = a[1].parse().context("K")?;
    anyhow::ensure!(k > 0, "K must be at least 1");
    let out = &a[2];
    let input = SceneInput::parse(&name, scale, 1)?;
    let opts = LoadOptions {
        split: Split::Object,
        flatten_instances: true,
        ..LoadOptions::default()
    };
    let (desc, _) = input.load(&opts)?;
    let mut tris: Vec<[Vec3; 3]> = Vec::new();
    for o in desc.objects.iter().filter(|o| o.placed) {
        tris.extend((0..o.mesh.len()).map(|t| o.mesh.triangle(t)));
    }
    let c = |t: &[Vec3; 3]| (t[0] + t[1] + t[2]) / 3.0;
    let (lo, hi) = tris.iter().fold(
        (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
        |(l, h), t| (l.min(c(t)), h.max(c(t))),
    );
    let e = (hi - lo).max(Vec3::splat(1e-20));
    let mut keyed: Vec<(u64, usize)> = tris
        .iter()
        .enumerate()
        .map(|(i, t)| (morton::code(c(t), lo, e), i))
        .collect();
    keyed.sort_unstable();
    let mut f = std::io::BufWriter::new(std::fs::File::create(out)?);
    for t in &tris {
        for p in t {
            writeln!(f, "v {} {} {}", p.x, p.y, p.z)?;
        }
    }
    let per = keyed.len().div_ceil(k).max(1);
    for (ci, chunk) in keyed.chunks(per).enumerate() {
        writeln!(f, "o chunk{ci}")?;
        for &(_, i) in chunk {
            writeln!(f, "f {} {} {}", 3 * i + 1, 3 * i + 2, 3 * i + 3)?;
        }
    }
    eprintln!(
        "{} triangles, {} chunks",
        tris.len(),
        keyed.len().div_ceil(per)
    );
    Ok(())
}
