//! Rays and hit records.

use glam::{Vec3, Vec4};

use crate::Error;

/// Marks an absent object or instance id in a [`Hit`].
pub const INVALID_ID: u32 = u32::MAX;

/// A ray segment `origin + t * dir` for `t` in `[t_min, t_max]`.
///
/// The direction need not be normalised; `t` is measured in units of `dir`.
/// Queries accept any ray: a ray with a zero or non-finite direction, a
/// non-finite origin or an empty interval hits nothing. Use [`Ray::new`] to
/// have such rays rejected with an error instead.
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct Ray {
    pub origin: Vec3,
    pub t_min: f32,
    pub dir: Vec3,
    pub t_max: f32,
}

impl Ray {
    /// A checked ray: finite origin and direction, a non-zero direction, and
    /// `0 <= t_min <= t_max` (`t_max` may be infinite).
    pub fn new(origin: Vec3, dir: Vec3, t_min: f32, t_max: f32) -> Result<Self, Error> {
        let r = Self {
            origin,
            dir,
            t_min,
            t_max,
        };
        if !origin.is_finite() || !dir.is_finite() {
            return Err(Error::InvalidRay("origin and direction must be finite"));
        }
        if dir == Vec3::ZERO {
            return Err(Error::InvalidRay("direction has zero length"));
        }
        if t_min.is_nan() || t_max.is_nan() || t_min < 0.0 || t_min > t_max {
            return Err(Error::InvalidRay("need 0 <= t_min <= t_max"));
        }
        Ok(r)
    }

    /// An unchecked ray over `[0, inf)`.
    #[inline]
    pub fn infinite(origin: Vec3, dir: Vec3) -> Self {
        Self {
            origin,
            dir,
            t_min: 0.0,
            t_max: f32::INFINITY,
        }
    }

    /// True when a query can hit anything with this ray (see the type's docs).
    #[inline]
    pub fn is_valid(&self) -> bool {
        // In two four-lane vectors (the ray's two halves) and without
        // short-circuits: every ray takes this test, and six branches per
        // ray were a measurable share of a diffuse ray's instructions
        // (callgrind); the lane-by-lane fold compiled to some forty
        // instructions. `t_min <= t_max` fails for a NaN in either; `t_max`
        // may be infinite.
        let w: [f32; 8] = bytemuck::cast(*self);
        let origin = Vec4::from_slice(&w[..4]);
        let dir = Vec4::from_slice(&w[4..]);
        let finite =
            (origin.abs().cmplt(Vec4::INFINITY) & dir.abs().cmplt(Vec4::INFINITY)).bitmask() & 7
                == 7;
        let moving = dir.cmpne(Vec4::ZERO).bitmask() & 7 != 0;
        finite & moving & (self.t_min <= self.t_max)
    }

    #[inline]
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + self.dir * t
    }
}

/// Rays per task of the batch queries: small enough for two threads to
/// share a few thousand rays evenly, large enough that a task's set-up (a
/// kernel dispatch, see [`par_query_runs`]) is paid rarely.
pub const QUERY_RUN: usize = 256;

/// Answer many rays in parallel on the current rayon pool: `out[i] =
/// query(&rays[i])`. Every batch API (mesh, scene, the Embree baseline) goes
/// through [`par_query_runs`], so they share one chunking policy.
///
/// Panics when `rays` and `out` differ in length (a caller bug).
pub fn par_query<T, F>(rays: &[Ray], out: &mut [T], query: F)
where
    T: Send,
    F: Fn(&Ray) -> T + Sync,
{
    par_query_runs(rays, out, |rays, out| {
        for (o, r) in out.iter_mut().zip(rays) {
            *o = query(r);
        }
    });
}

/// Answer many rays in parallel on the current rayon pool, a run of up to
/// [`QUERY_RUN`] consecutive rays per call: `query(rays, out)` answers
/// `rays[i]` in `out[i]`. For queries whose per-call set-up is worth
/// sharing across rays. Results do not depend on the thread count as long
/// as each ray's answer depends only on the ray.
///
/// Every run is a task of its own (`with_max_len(1)`). Without it rayon
/// halves an indexed range until it has about two pieces per thread (four
/// at two threads) and runs each piece in one go unless another thread
/// steals it before it starts, so a thread that finishes early may find
/// nothing left to take while the other works through a quarter of the
/// batch. Where the cost of rays is uneven along the batch (the cocoa
/// temple's diffuse rays, which start from the two fifths of its image
/// that hit geometry) that cost the re-braided mode 10-20% of its
/// two-thread rate: 1 -> 2 threads 8.14 -> 13.49 Mrays/s against
/// `embree-flat`'s 7.87 -> 14.89 on the same harness, and with a task per
/// run 8.12 -> 15.09; `tools/ab-wall.sh` at two threads (4 rounds,
/// 1280x720) put the change at 1.217 against a control of 0.949, the other
/// scenes within their controls (docs/performance.md, session 40). A task
/// per 256-ray run costs nothing measurable at one thread.
///
/// Panics when `rays` and `out` differ in length (a caller bug).
pub fn par_query_runs<T, F>(rays: &[Ray], out: &mut [T], query: F)
where
    T: Send,
    F: Fn(&[Ray], &mut [T]) + Sync,
{
    use rayon::prelude::*;
    assert_eq!(rays.len(), out.len(), "one output per ray");
    out.par_chunks_mut(QUERY_RUN)
        .zip(rays.par_chunks(QUERY_RUN))
        .with_max_len(1)
        .for_each(|(o, r)| query(r, o));
}

/// The closest hit along a ray.
///
/// `u` and `v` are barycentric coordinates: the hit point is
/// `(1 - u - v) * v0 + u * v1 + v * v2` of the triangle's vertices.
/// `normal` is the geometric normal in world space, oriented by the
/// triangle's winding as placed in the world, and **not normalised** (as
/// Embree's `Ng`): `(v1 - v0) x (v2 - v0)` of the world-space vertices, and
/// for a hit through an instance the object-space one transformed as a
/// normal (by the inverse transpose, negated by a mirroring transform), so
/// its length is then not the placed triangle's. [`Hit::unit_normal`] gives
/// the unit vector. Why: the normalisation's square root and division sat
/// on every hit's latency chain, about 7% of a re-braided diffuse ray on
/// openarena by `perf` samples (`docs/performance.md`, session 19), for
/// callers that often need only the normal's side or shade with their own
/// normals.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f32,
    pub u: f32,
    pub v: f32,
    /// Index of the triangle in its object's index buffer.
    pub prim_id: u32,
    /// Object (mesh) id, or [`INVALID_ID`] for a query on a single mesh BVH.
    pub object_id: u32,
    /// Instance id, or [`INVALID_ID`] when the object was hit directly.
    pub instance_id: u32,
    pub normal: Vec3,
}

impl Hit {
    /// A hit on one mesh, from its leaf record: the primitive id and the
    /// geometric normal (as the leaf gives it, not normalised); no object
    /// or instance id yet.
    #[inline(always)]
    pub fn on_mesh(t: f32, u: f32, v: f32, prim_id: u32, normal: Vec3) -> Hit {
        Hit {
            t,
            u,
            v,
            prim_id,
            object_id: INVALID_ID,
            instance_id: INVALID_ID,
            normal,
        }
    }

    /// The unit geometric normal (`normal` normalised), or zero for a
    /// placeholder hit.
    #[inline]
    pub fn unit_normal(&self) -> Vec3 {
        self.normal.normalize_or_zero()
    }

    /// A placeholder that any real hit replaces.
    pub const NONE: Hit = Hit {
        t: f32::INFINITY,
        u: 0.0,
        v: 0.0,
        prim_id: INVALID_ID,
        object_id: INVALID_ID,
        instance_id: INVALID_ID,
        normal: Vec3::ZERO,
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every slot gets its own ray's answer, once, whatever the batch's
    /// length against [`QUERY_RUN`] and the pool's size (one task per run,
    /// stolen in any order).
    #[test]
    fn runs_answer_every_slot_with_its_own_ray() {
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a test pool");
            for len in [0, 1, QUERY_RUN - 1, QUERY_RUN, 5 * QUERY_RUN + 7] {
                let rays: Vec<Ray> = (0..len)
                    .map(|i| Ray::infinite(Vec3::new(i as f32, 0.0, 0.0), Vec3::X))
                    .collect();
                let mut out = vec![(-1.0f32, 0u32); len];
                pool.install(|| {
                    par_query_runs(&rays, &mut out, |rays, out| {
                        assert!(rays.len() <= QUERY_RUN && rays.len() == out.len());
                        for (o, r) in out.iter_mut().zip(rays) {
                            *o = (r.origin.x, o.1 + 1);
                        }
                    })
                });
                for (i, o) in out.iter().enumerate() {
                    assert_eq!(*o, (i as f32, 1), "{threads} threads, {len} rays, slot {i}");
                }
            }
        }
    }

    #[test]
    fn checked_constructor_rejects_bad_rays() {
        assert!(Ray::new(Vec3::ZERO, Vec3::ZERO, 0.0, 1.0).is_err());
        assert!(Ray::new(Vec3::NAN, Vec3::X, 0.0, 1.0).is_err());
        assert!(Ray::new(Vec3::ZERO, Vec3::X, 2.0, 1.0).is_err());
        assert!(Ray::new(Vec3::ZERO, Vec3::X, -1.0, 1.0).is_err());
        assert!(Ray::new(Vec3::ZERO, Vec3::X, 0.0, f32::INFINITY).is_ok());
        assert!(!Ray::infinite(Vec3::ZERO, Vec3::ZERO).is_valid());
    }

    /// The branch-free validity test agrees with the plain one on every
    /// mix of special values.
    #[test]
    fn validity_matches_the_short_circuit_rule() {
        let specials = [
            0.0,
            -0.0,
            1.0,
            -2.5,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        let plain = |r: &Ray| {
            r.origin.is_finite()
                && r.dir.is_finite()
                && r.dir != Vec3::ZERO
                && r.t_min <= r.t_max
                && !r.t_min.is_nan()
        };
        let mut checked = 0;
        for &a in &specials {
            for &b in &specials {
                for &c in &specials {
                    for (t_min, t_max) in [
                        (0.0, 1.0),
                        (1.0, 0.0),
                        (0.0, f32::INFINITY),
                        (f32::NAN, 1.0),
                        (0.0, f32::NAN),
                    ] {
                        for r in [
                            Ray {
                                origin: Vec3::new(a, 1.0, 2.0),
                                t_min,
                                dir: Vec3::new(b, c, 0.0),
                                t_max,
                            },
                            Ray {
                                origin: Vec3::new(1.0, b, c),
                                t_min,
                                dir: Vec3::new(0.0, a, 1.0),
                                t_max,
                            },
                            Ray {
                                origin: Vec3::ZERO,
                                t_min,
                                dir: Vec3::new(a, b, c),
                                t_max,
                            },
                        ] {
                            assert_eq!(r.is_valid(), plain(&r), "{r:?}");
                            checked += 1;
                        }
                    }
                }
            }
        }
        assert_eq!(checked, 7 * 7 * 7 * 5 * 3);
    }
}
