//! A small path tracer over a committed scene, and the traversal heat map.
//!
//! Diffuse surfaces coloured per object, a point light above the scene's
//! centre (inside the scene box, so closed levels and rooms are lit; see
//! [`render_light`]) tested with shadow rays through any-hit queries, a dim sky for rays that leave,
//! and cosine-sampled diffuse bounces. The heat map shows the number of BVH
//! nodes (both levels) a primary ray visits: the picture that shows why
//! re-braiding helps.

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use rebraid::bvh::TraversalCounters;
use rebraid::glam::Vec3;
use rebraid::{Aabb, Hit, Ray, Scene};

use crate::camera::Camera;
use crate::raysets::{cosine_direction, facing_normal, light_position, ray_epsilon};

/// What to render.
#[derive(Clone, Debug)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub bounces: u32,
    pub camera: Camera,
    pub bounds: Aabb,
    pub up: Vec3,
    pub progress: bool,
}

/// A linear RGB image.
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<Vec3>,
}

/// A stable, well-spread colour per object (and instance).
fn albedo(hit: &Hit) -> Vec3 {
    let mut h = (hit.object_id as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (hit.instance_id as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    h ^= h >> 29;
    let f = |s: u32| 0.25 + 0.6 * (((h >> s) & 0xff) as f32 / 255.0);
    Vec3::new(f(0), f(8), f(16))
}

fn progress_bar(show: bool, len: u64, what: &str) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} rows ({eta})")
            .expect("static template")
            .progress_chars("=> "),
    );
    pb.set_message(what.to_string());
    pb
}

/// The render's point light: of a few points between the eye and the
/// benchmarks' light above the scene's centre ([`light_position`]), the one
/// with the most free space around it, measured by probe rays. The
/// benchmarks' light alone can sit inside an object (in the `library`, it is
/// inside a bookcase) and leave the picture dark. Returns the light and the
/// mean free distance around it (which sets the exposure).
pub fn render_light(scene: &Scene, bounds: &Aabb, up: Vec3, eye: Vec3) -> (Vec3, f32) {
    let size = bounds.extent().max_element().max(1e-3);
    let base = light_position(bounds, up);
    let h = bounds.extent().dot(up.abs());
    let mut best = (f32::NEG_INFINITY, base, size);
    let candidates = [0.5, 0.3, 0.7, 1.0]
        .into_iter()
        .map(|a| eye.lerp(base, a))
        .chain([0.1, 0.2, -0.1].map(|f| base + up * (f * h)));
    for p in candidates {
        let (mean, near) = free_space(scene, p, size);
        let score = mean * (near / (0.05 * h).max(1e-6)).min(1.0);
        // Prefer earlier candidates unless a later one is clearly better.
        if score > best.0 * 1.25 {
            best = (score, p, mean);
        }
    }
    (best.1, best.2)
}

/// Mean and least free distance from `p` over a Fibonacci sphere of 128
/// directions (misses count as `size`).
fn free_space(scene: &Scene, p: Vec3, size: f32) -> (f32, f32) {
    let n = 128;
    let (mut sum, mut near) = (0.0f32, size);
    for i in 0..n {
        let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
        let r = (1.0 - z * z).max(0.0).sqrt();
        let phi = i as f32 * 2.399_963;
        let d = Vec3::new(r * phi.cos(), r * phi.sin(), z);
        let t = scene
            .intersect(&Ray::infinite(p, d))
            .map_or(size, |hit| hit.t.min(size));
        sum += t;
        near = near.min(t);
    }
    (sum / n as f32, near)
}

/// The point lights of a render with their intensities: the light of
/// [`render_light`], and a dimmer head light just above the eye, which
/// lights whatever the camera sees even where the main light is walled off
/// (the aisles of a large `library`).
fn render_lights(scene: &Scene, s: &RenderSettings) -> [(Vec3, f32); 2] {
    let (light, free) = render_light(scene, &s.bounds, s.up, s.camera.eye);
    let size = s.bounds.extent().max_element().max(1e-3);
    let (eye_free, eye_near) = free_space(scene, s.camera.eye, size);
    let head = s.camera.eye + s.up * (0.5 * eye_near);
    // Intensity so that a surface facing a light at its mean free distance
    // is lit about 1 (the head light at half that).
    let pi = std::f32::consts::PI;
    [
        (light, free * free * pi),
        (head, 0.5 * eye_free * eye_free * pi),
    ]
}

/// Path-trace the scene.
pub fn render(scene: &Scene, s: &RenderSettings) -> Image {
    let cam = s.camera.rays(s.width, s.height);
    let lights = render_lights(scene, s);
    let eps = ray_epsilon(&s.bounds);
    let sky = |d: Vec3| {
        let k = 0.5 + 0.5 * d.dot(s.up);
        Vec3::new(0.35, 0.4, 0.5) * (0.3 + 0.7 * k)
    };
    let pb = progress_bar(s.progress, s.height as u64, "render");
    // A task per row (as `rebraid::ray::par_query_runs` takes one per run
    // of rays): rows cost unevenly (sky against geometry), and rayon's
    // default pieces (a quarter of the rows each at two threads) can leave
    // one thread idle at the end (the cocoa temple at 960x540, 8 spp, two
    // threads: 0.85 -> 0.83 s, median of 6 alternations).
    let rows: Vec<Vec<Vec3>> = (0..s.height)
        .into_par_iter()
        .with_max_len(1)
        .map(|y| {
            let mut rng = rand_pcg::Pcg32::seed_from_u64(0xbeef ^ y as u64);
            let row = (0..s.width)
                .map(|x| {
                    let mut sum = Vec3::ZERO;
                    for _ in 0..s.spp {
                        let mut ray =
                            cam.ray(x as f32 + rng.r#gen::<f32>(), y as f32 + rng.r#gen::<f32>());
                        let mut throughput = Vec3::ONE;
                        for bounce in 0..=s.bounces {
                            let Some(hit) = scene.intersect(&ray) else {
                                sum +=
                                    throughput * sky(ray.dir) * if bounce == 0 { 1.0 } else { 0.5 };
                                break;
                            };
                            let n = facing_normal(&hit, &ray);
                            let p = ray.at(hit.t) + n * eps;
                            let a = albedo(&hit);
                            for &(light, intensity) in &lights {
                                let to_light = light - p;
                                let d2 = to_light.length_squared().max(1e-12);
                                let cos = n.dot(to_light) / d2.sqrt();
                                if cos <= 0.0 {
                                    continue;
                                }
                                let shadow = Ray {
                                    origin: p,
                                    dir: to_light,
                                    t_min: 0.0,
                                    t_max: 1.0 - 1e-4,
                                };
                                if !scene.occluded(&shadow) {
                                    sum += throughput
                                        * a
                                        * (cos * intensity / (std::f32::consts::PI * d2));
                                }
                            }
                            throughput *= a;
                            let d = cosine_direction(n, rng.r#gen(), rng.r#gen());
                            ray = Ray::infinite(p, d);
                        }
                    }
                    sum / s.spp as f32
                })
                .collect();
            pb.inc(1);
            row
        })
        .collect();
    pb.finish_and_clear();
    Image {
        width: s.width,
        height: s.height,
        pixels: rows.into_iter().flatten().collect(),
    }
}

/// Nodes visited per primary ray (inner nodes plus leaves, both levels).
pub fn heat_counts(scene: &Scene, s: &RenderSettings) -> Vec<u32> {
    let cam = s.camera.rays(s.width, s.height);
    let pb = progress_bar(s.progress, s.height as u64, "heatmap");
    let out = (0..s.height)
        .into_par_iter()
        .with_max_len(1)
        .flat_map_iter(|y| {
            let row: Vec<u32> = (0..s.width)
                .map(|x| {
                    let mut c = TraversalCounters::default();
                    scene.intersect_counted(&cam.pixel_ray(x, y), &mut c);
                    c.inner_visited + c.leaves_visited
                })
                .collect();
            pb.inc(1);
            row
        })
        .collect();
    pb.finish_and_clear();
    out
}

/// A false-colour ramp (black, blue, cyan, green, yellow, red, white).
pub fn heat_colour(x: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 7] = [
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        [0.0, 1.0, 1.0],
        [0.0, 1.0, 0.0],
        [1.0, 1.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 1.0],
    ];
    let x = x.clamp(0.0, 1.0) * (STOPS.len() - 1) as f32;
    let i = (x as usize).min(STOPS.len() - 2);
    let f = x - i as f32;
    let c = |k: usize| ((STOPS[i][k] * (1.0 - f) + STOPS[i + 1][k] * f) * 255.0).round() as u8;
    [c(0), c(1), c(2)]
}

/// Write the heat map as a PNG with a colour bar along the bottom (left end
/// 0 nodes, right end `scale_max` nodes or more).
pub fn write_heatmap(
    path: &std::path::Path,
    counts: &[u32],
    width: u32,
    height: u32,
    scale_max: u32,
) -> anyhow::Result<()> {
    let bar = (height / 24).max(4);
    let mut img = image::RgbImage::new(width, height + bar);
    for (i, &c) in counts.iter().enumerate() {
        let (x, y) = (i as u32 % width, i as u32 / width);
        img.put_pixel(
            x,
            y,
            image::Rgb(heat_colour(c as f32 / scale_max.max(1) as f32)),
        );
    }
    for x in 0..width {
        let col = heat_colour(x as f32 / (width - 1).max(1) as f32);
        for y in height..height + bar {
            img.put_pixel(x, y, image::Rgb(col));
        }
    }
    save_png(path, &img)
}

/// Write a PNG with the best compression (noisy renders compress badly).
fn save_png(path: &std::path::Path, img: &image::RgbImage) -> anyhow::Result<()> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    let file =
        std::fs::File::create(path).with_context(|| format!("writing {}", path.display()))?;
    let enc = PngEncoder::new_with_quality(
        std::io::BufWriter::new(file),
        CompressionType::Best,
        FilterType::Adaptive,
    );
    img.write_with_encoder(enc)
        .with_context(|| format!("writing {}", path.display()))
}

/// Tone-map (exposure, then sRGB-like gamma) and write a PNG.
pub fn write_png(path: &std::path::Path, img: &Image) -> anyhow::Result<()> {
    let mut out = image::RgbImage::new(img.width, img.height);
    for (i, p) in img.pixels.iter().enumerate() {
        let m = *p / (Vec3::ONE + *p);
        let g = |v: f32| (v.clamp(0.0, 1.0).powf(1.0 / 2.2) * 255.0).round() as u8;
        out.put_pixel(
            i as u32 % img.width,
            i as u32 / img.width,
            image::Rgb([g(m.x), g(m.y), g(m.z)]),
        );
    }
    save_png(path, &out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heat_ramp_ends() {
        assert_eq!(heat_colour(0.0), [0, 0, 0]);
        assert_eq!(heat_colour(1.0), [255, 255, 255]);
        assert_eq!(heat_colour(2.0), [255, 255, 255]);
    }
}
