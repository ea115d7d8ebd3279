//! Scenes, ray sets and harness helpers shared by the benches.

use rand::Rng;
use rebraid::glam::Vec3;
use rebraid::{Aabb, Ray, TriangleMesh};

use crate::common;

/// A per-process cache of prepared scenes: `make` runs once per name (and
/// may fail with `None`, say for a scene file that is missing); every later
/// call gets the same leaked value. The benches build each scene once and
/// share it between their traversal benchmarks.
pub type SceneCache<P> = std::sync::OnceLock<
    std::sync::Mutex<std::collections::HashMap<&'static str, Option<&'static P>>>,
>;

pub fn cached<P: Sync + 'static>(
    cache: &'static SceneCache<P>,
    name: &'static str,
    make: impl FnOnce() -> Option<P>,
) -> Option<&'static P> {
    let mut map = cache.get_or_init(Default::default).lock().unwrap();
    *map.entry(name)
        .or_insert_with(|| make().map(|p| &*Box::leak(Box::new(p))))
}

/// The `main` of an AVX2 experiment bench: skip with a message on CPUs
/// without the AVX2 level; otherwise prepare (and so validate) every scene
/// before `divan` times anything.
#[allow(dead_code)] // only the experiment benches
pub fn avx2_experiment_main<P: 'static>(
    kernel: &str,
    scenes: &[&'static str],
    prepare: fn(&'static str) -> Option<&'static P>,
) {
    if !rebraid::bvh::Kernel::Avx2.is_available() {
        eprintln!(
            "SKIPPED: the {kernel} kernel needs the AVX2 level (AVX2, FMA, BMI1, BMI2, LZCNT)"
        );
        return;
    }
    for &scene in scenes {
        prepare(scene);
    }
    divan::main();
}

/// Every `scene/variant` pair, as `divan` arguments.
#[allow(dead_code)] // not every bench has variants
pub fn cases(scenes: &[&str], variants: &[&str]) -> Vec<&'static str> {
    scenes
        .iter()
        .flat_map(|s| variants.iter().map(move |v| &*format!("{s}/{v}").leak()))
        .collect()
}

/// The prepared scene and the variant of a `scene/variant` case (`None`
/// when the scene is unknown or could not be prepared).
#[allow(dead_code)] // not every bench has variants
pub fn case<'a, P: 'static>(
    case: &'a str,
    scenes: &[&'static str],
    prepared: impl Fn(&'static str) -> Option<&'static P>,
) -> Option<(&'static P, &'a str)> {
    let (scene, variant) = case.split_once('/')?;
    let name = *scenes.iter().find(|s| **s == scene)?;
    Some((prepared(name)?, variant))
}

/// About a million triangles: a 500 x 500 height-field terrain (500k) and
/// 400 icospheres of 1,280 triangles scattered over it (512k).
pub fn generated_scene() -> TriangleMesh {
    let mut r = common::rng(7);
    // A 500 x 500 grid raised into hills (vertices in the grid's row order,
    // which is also the order the random offsets are drawn in).
    let TriangleMesh {
        mut positions,
        mut indices,
    } = common::grid(500, 500);
    for p in &mut positions {
        p.z = 8.0 * (p.x * 0.05).sin() * (p.y * 0.037).cos() + r.gen_range(0.0..0.3);
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
pub fn load(name: &str) -> Option<TriangleMesh> {
    if name == "generated_1m" {
        return Some(generated_scene());
    }
    let path = common::obj::scene_path_or_skip(&format!("{name}.obj"))?;
    Some(common::obj::load_obj(&path))
}

/// Pinhole camera rays from the middle of the scene towards a fixed, slightly
/// downward direction (every scene has content around its centre).
pub fn camera_rays(bounds: &Aabb, rays: usize) -> Vec<Ray> {
    let eye = bounds.center();
    let forward = Vec3::new(1.0, 0.35, -0.25).normalize();
    let right = forward.cross(Vec3::Z).normalize();
    let up = right.cross(forward);
    let side = (rays as f64).sqrt() as usize;
    (0..rays)
        .map(|i| {
            let (x, y) = (i % side, i / side);
            let sx = (x as f32 + 0.5) / side as f32 * 2.0 - 1.0;
            let sy = (y as f32 + 0.5) / side as f32 * 2.0 - 1.0;
            Ray::infinite(eye, forward + right * sx + up * sy)
        })
        .collect()
}

/// Random origins in the scene box and random directions.
pub fn random_rays(bounds: &Aabb, rays: usize) -> Vec<Ray> {
    let mut r = common::rng(8);
    (0..rays)
        .map(|_| Ray::infinite(common::point_in(&mut r, bounds), common::unit_dir(&mut r)))
        .collect()
}
