//! The three ray sets every benchmark traces, generated once per scene and
//! camera so that every mode (and Embree) traces exactly the same rays:
//! primary camera rays, one shadow ray per primary hit towards a point light
//! above the scene's centre, and one cosine-distributed diffuse bounce per
//! primary hit (the workload of `shared/docs/anchors.md`).

use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use rebraid::glam::Vec3;
use rebraid::{Aabb, Hit, Ray};

use crate::camera::Camera;

/// Rays of one benchmark workload.
#[derive(Clone, Debug, Default)]
pub struct RaySets {
    pub primary: Vec<Ray>,
    pub shadow: Vec<Ray>,
    pub diffuse: Vec<Ray>,
}

/// The point light: above the centre, inside the scene box.
pub fn light_position(bounds: &Aabb, up: Vec3) -> Vec3 {
    bounds.center() + up * (0.25 * bounds.extent().dot(up.abs()))
}

/// Offset for secondary-ray origins, relative to the scene size.
pub fn ray_epsilon(bounds: &Aabb) -> f32 {
    1e-5 * bounds.extent().max_element().max(1e-3)
}

/// A direction drawn from the cosine-weighted hemisphere around `n`.
pub fn cosine_direction(n: Vec3, u1: f32, u2: f32) -> Vec3 {
    let r = u1.sqrt();
    let phi = 2.0 * std::f32::consts::PI * u2;
    let (s, c) = phi.sin_cos();
    let local = Vec3::new(r * c, r * s, (1.0 - u1).max(0.0).sqrt());
    let t = n.any_orthonormal_vector();
    let b = n.cross(t);
    (t * local.x + b * local.y + n * local.z).normalize()
}

/// The hit's unit normal turned to face the incoming ray.
#[inline]
pub fn facing_normal(hit: &Hit, ray: &Ray) -> Vec3 {
    let n = hit.unit_normal();
    if n.dot(ray.dir) > 0.0 { -n } else { n }
}

impl RaySets {
    /// Primary rays for `camera`; shadow and diffuse rays from the primary
    /// hits that `trace` (any mode's closest-hit batch query) returns. Seeded:
    /// the same inputs give the same rays.
    pub fn generate<F>(
        camera: &Camera,
        width: u32,
        height: u32,
        bounds: &Aabb,
        up: Vec3,
        trace: F,
    ) -> Self
    where
        F: Fn(&[Ray], &mut [Option<Hit>]),
    {
        let cam = camera.rays(width, height);
        let primary: Vec<Ray> = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| cam.pixel_ray(x, y))
            .collect();
        let mut hits = vec![None; primary.len()];
        trace(&primary, &mut hits);
        let light = light_position(bounds, up);
        let eps = ray_epsilon(bounds);
        let per_hit: Vec<Option<(Ray, Ray)>> = primary
            .par_iter()
            .zip(hits.par_iter())
            .enumerate()
            .map(|(i, (r, h))| {
                let h = h.as_ref()?;
                let n = facing_normal(h, r);
                if n == Vec3::ZERO {
                    return None;
                }
                let p = r.at(h.t) + n * eps;
                let to_light = light - p;
                let shadow = Ray {
                    origin: p,
                    dir: to_light,
                    t_min: 0.0,
                    t_max: 1.0 - 1e-4,
                };
                let mut rng = rand_pcg::Pcg32::seed_from_u64(0x5eed ^ i as u64);
                let d = cosine_direction(n, rng.r#gen(), rng.r#gen());
                Some((shadow, Ray::infinite(p, d)))
            })
            .collect();
        let (shadow, diffuse) = per_hit.into_iter().flatten().unzip();
        Self {
            primary,
            shadow,
            diffuse,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cosine_directions_lie_in_the_hemisphere() {
        let mut rng = rand_pcg::Pcg32::seed_from_u64(1);
        for n in [Vec3::X, -Vec3::Y, Vec3::new(1.0, 2.0, 3.0).normalize()] {
            let mut mean = Vec3::ZERO;
            for _ in 0..2000 {
                let d = cosine_direction(n, rng.r#gen(), rng.r#gen());
                assert!(d.dot(n) >= -1e-6);
                assert!((d.length() - 1.0).abs() < 1e-4);
                mean += d;
            }
            // E[cos] = 2/3 for the cosine-weighted hemisphere.
            assert!((mean / 2000.0).dot(n) > 0.6);
        }
    }
}
