//! A re-braided scene traced from two top levels: one over the placements
//! that have not moved lately, kept between commits, and one over those
//! that have, built at every commit (see
//! [`crate::RebraidParams::moving_hold_commits`]).
//!
//! Why: the re-braided top level is a build over every placement, opened
//! deep into the object BVHs, and laid out anew (collapse, pulled and
//! grafted entries, copied leaf blocks). When one object of a large scene
//! moves every frame, rebuilding all of it for that one object costs far
//! more than the object's own refit (the library scene at 2M triangles
//! with a walking robot: 95 ms per frame, the refit 10 of them;
//! docs/performance.md, session 35). A smaller opening budget makes the
//! rebuild cheap but gives up the rays re-braiding bought (the static
//! library at 2M triangles, one thread: diffuse 4.35 Mrays/s at the
//! default budget with a top level of 157 ms, 1.83 at Embree's with 1.7
//! ms; the plain two-level BVH 0.85). Split, the scene keeps the full
//! re-braiding where nothing moves and rebuilds only what moved, at the
//! cost of a second walk for the rays that reach the moving part's box.
//!
//! This is the static/dynamic split real-time engines make by hand (one
//! acceleration structure for the level, one rebuilt per frame for what
//! moves), made by the scene from its own edit history.

use crate::bvh::TraversalCounters;
use crate::toplevel::TopLevelAccel;
use glam::Vec3A;

use crate::{Aabb, Hit, Ray};

/// Two top levels queried as one scene: a ray's answer is the nearer of
/// the two, its occlusion either's. The fixed part is asked first, then
/// the moving part for the rays that, cut off at the fixed part's hit, may
/// still meet its box.
#[derive(Clone, Debug, Default)]
pub struct SplitAccel {
    /// Over the placements that have not moved for
    /// [`crate::RebraidParams::moving_hold_commits`] commits; kept from the
    /// commit that built it while that set stays the same.
    pub fixed: TopLevelAccel,
    /// Over the placements that moved within that window; built at every
    /// commit.
    pub moving: TopLevelAccel,
}

/// A box to ask whether rays may meet it within their interval: a slab
/// test that errs towards yes (the box's faces are moved out by a millionth of its
/// coordinates' magnitude, the exit distance by a relative 1e-5, about
/// 80 ulps, far beyond the test's own rounding), so that no ray that a
/// walk of the part would hit is turned away.
///
/// Why: the moving part is usually small (a robot in a library: 5% of the
/// camera rays of `rebraid animate library --scale 2` meet its box), but a
/// batch walk of it costs every ray of the batch its set-up and a root
/// test, hit or miss: walking every ray through the robot after (or
/// before) the library, the split scene traced 15.8-16.0 primary Mrays/s
/// against one top level's 21.7-23.7. With the rays that may meet the box
/// picked first (5.4 ns per ray), 21.3-22.1 (session 35; picked by an
/// iterator chain into `unzip`, 22 ns per ray, it was 17.4-18.8).
#[derive(Clone, Copy)]
struct PaddedBox {
    lo: Vec3A,
    hi: Vec3A,
}

impl PaddedBox {
    fn new(b: &Aabb) -> Self {
        let (lo, hi) = (Vec3A::from(b.min), Vec3A::from(b.max));
        let pad = lo.abs().max(hi.abs()) * 1e-6;
        Self {
            lo: lo - pad,
            hi: hi + pad,
        }
    }

    /// Whether `ray` may meet the box between its `t_min` and `t_max`.
    #[inline(always)]
    fn meets(&self, ray: &Ray, t_max: f32) -> bool {
        let (o, d) = (Vec3A::from(ray.origin), Vec3A::from(ray.dir));
        // Below the smallest normal float a reciprocal overflows, and an
        // infinity times a zero distance would be a NaN.
        if d.abs().cmplt(Vec3A::splat(f32::MIN_POSITIVE)).any() {
            return self.meets_axis_parallel(ray, t_max);
        }
        let inv = d.recip();
        let (t0, t1) = ((self.lo - o) * inv, (self.hi - o) * inv);
        let near = t0.min(t1).max_element().max(ray.t_min);
        let far = t1.max(t0).min_element().min(t_max);
        near <= far + far.abs() * 1e-5
    }

    /// [`PaddedBox::meets`] for a ray with a zero or subnormal direction
    /// component: parallel to two of the box's faces (it meets their slab
    /// only if it starts in it), or so nearly so that the slab is not
    /// tested at all (erring towards yes).
    #[cold]
    fn meets_axis_parallel(&self, ray: &Ray, t_max: f32) -> bool {
        let (mut near, mut far) = (ray.t_min, t_max);
        for a in 0..3 {
            let (o, d) = (ray.origin[a], ray.dir[a]);
            if d == 0.0 {
                if o < self.lo[a] || o > self.hi[a] {
                    return false;
                }
                continue;
            }
            if d.abs() < f32::MIN_POSITIVE {
                continue;
            }
            let (t0, t1) = ((self.lo[a] - o) / d, (self.hi[a] - o) / d);
            near = near.max(t0.min(t1));
            far = far.min(t0.max(t1));
        }
        near <= far + far.abs() * 1e-5
    }
}

/// `ray` cut off at `hit` (a hit of the other part at the same distance is
/// an exact tie, which either part may answer).
#[inline]
fn before(ray: &Ray, hit: &Option<Hit>) -> Ray {
    match hit {
        Some(h) => Ray { t_max: h.t, ..*ray },
        None => *ray,
    }
}

/// The nearer of the first part's answer and the second's (asked only up
/// to the first one's distance); the first one at a tie.
#[inline]
fn nearer(first: Option<Hit>, second: Option<Hit>) -> Option<Hit> {
    match (first, second) {
        (Some(f), Some(s)) if s.t < f.t => Some(s),
        (Some(f), _) => Some(f),
        (None, s) => s,
    }
}

impl SplitAccel {
    /// Closest hit along the ray.
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        self.intersect_counted(ray, &mut TraversalCounters::default())
    }

    /// Closest hit, counting the nodes and leaves both walks visit.
    pub fn intersect_counted(&self, ray: &Ray, counters: &mut TraversalCounters) -> Option<Hit> {
        let fixed = self.fixed.intersect_counted(ray, counters);
        let cut = before(ray, &fixed);
        let moving = self
            .meets_moving(&cut)
            .then(|| self.moving.intersect_counted(&cut, counters))
            .flatten();
        nearer(fixed, moving)
    }

    /// True when either part has a hit within the ray's interval.
    pub fn occluded(&self, ray: &Ray) -> bool {
        self.occluded_counted(ray, &mut TraversalCounters::default())
    }

    /// Occlusion, counting what the walks visit (the moving part is walked
    /// only when the fixed one has no hit and the ray meets its box).
    pub fn occluded_counted(&self, ray: &Ray, counters: &mut TraversalCounters) -> bool {
        self.fixed.occluded_counted(ray, counters)
            || (self.meets_moving(ray) && self.moving.occluded_counted(ray, counters))
    }

    /// Whether `ray` may meet the moving part's box ([`PaddedBox`]).
    #[inline]
    fn meets_moving(&self, ray: &Ray) -> bool {
        self.moving_box().is_some_and(|b| b.meets(ray, ray.t_max))
    }

    /// The moving part's box, padded ([`PaddedBox`]).
    #[inline]
    fn moving_box(&self) -> Option<PaddedBox> {
        self.moving
            .tree
            .nodes
            .first()
            .map(|root| PaddedBox::new(&root.bounds()))
    }

    /// Closest hits of a run of rays on the calling thread (see
    /// [`TopLevelAccel::intersect_many`]): the run through the fixed part,
    /// then the rays that, cut off at those hits, may still meet the
    /// moving part's box, through it.
    pub fn intersect_many(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        assert_eq!(rays.len(), out.len(), "one output per ray");
        self.fixed.intersect_many(rays, out);
        let Some(b) = self.moving_box() else { return };
        // (A plain loop: the same filter as an iterator chain into `unzip`
        // took four times as long, 22 ns per ray.)
        let (mut idx, mut sub) = (Vec::new(), Vec::new());
        for (i, (r, h)) in rays.iter().zip(out.iter()).enumerate() {
            if b.meets(r, h.map_or(r.t_max, |h| h.t)) {
                idx.push(i);
                sub.push(before(r, h));
            }
        }
        if sub.is_empty() {
            return;
        }
        let mut hits = vec![None; sub.len()];
        self.moving.intersect_many(&sub, &mut hits);
        for (&i, h) in idx.iter().zip(hits) {
            out[i] = nearer(out[i], h);
        }
    }

    /// Occlusion of a run of rays on the calling thread: the fixed part's,
    /// then the moving part's for the rays it left unoccluded that may
    /// meet its box.
    pub fn occluded_many(&self, rays: &[Ray], out: &mut [bool]) {
        assert_eq!(rays.len(), out.len(), "one output per ray");
        self.fixed.occluded_many(rays, out);
        let Some(b) = self.moving_box() else { return };
        let (mut idx, mut sub) = (Vec::new(), Vec::new());
        for (i, (r, &o)) in rays.iter().zip(out.iter()).enumerate() {
            if !o && b.meets(r, r.t_max) {
                idx.push(i);
                sub.push(*r);
            }
        }
        if sub.is_empty() {
            return;
        }
        let mut hit = vec![false; sub.len()];
        self.moving.occluded_many(&sub, &mut hit);
        for (&i, h) in idx.iter().zip(hit) {
            out[i] = h;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn may_meet(ray: &Ray, b: &Aabb) -> bool {
        PaddedBox::new(b).meets(ray, ray.t_max)
    }

    fn hit(t: f32, object: u32) -> Hit {
        Hit {
            t,
            u: 0.0,
            v: 0.0,
            prim_id: 0,
            object_id: object,
            instance_id: crate::INVALID_ID,
            normal: Vec3::Z,
        }
    }

    #[test]
    fn the_nearer_part_answers_and_the_first_one_at_ties() {
        assert_eq!(nearer(None, None), None);
        assert_eq!(nearer(Some(hit(2.0, 0)), None).unwrap().object_id, 0);
        assert_eq!(nearer(None, Some(hit(2.0, 1))).unwrap().object_id, 1);
        assert_eq!(
            nearer(Some(hit(2.0, 0)), Some(hit(1.0, 1)))
                .unwrap()
                .object_id,
            1
        );
        assert_eq!(
            nearer(Some(hit(2.0, 0)), Some(hit(2.0, 1)))
                .unwrap()
                .object_id,
            0
        );
    }

    #[test]
    fn the_second_part_is_asked_up_to_the_first_hit() {
        let ray = Ray::new(Vec3::ZERO, Vec3::X, 0.5, f32::INFINITY).unwrap();
        let cut = before(&ray, &Some(hit(3.0, 0)));
        assert_eq!((cut.t_min, cut.t_max), (0.5, 3.0));
        assert_eq!(before(&ray, &None).t_max, f32::INFINITY);
    }

    #[test]
    fn rays_are_turned_away_only_when_they_miss_the_box() {
        let b = Aabb::new(Vec3::splat(1.0), Vec3::splat(2.0));
        let ray = |o: Vec3, d: Vec3, t_max: f32| Ray::new(o, d, 0.0, t_max).unwrap();
        let inf = f32::INFINITY;
        // Through, along an axis inside the slabs, and grazing faces and edges.
        assert!(may_meet(&ray(Vec3::ZERO, Vec3::ONE, inf), &b));
        assert!(may_meet(&ray(Vec3::new(0.0, 1.5, 1.5), Vec3::X, inf), &b));
        assert!(may_meet(&ray(Vec3::new(0.0, 2.0, 1.5), Vec3::X, inf), &b));
        assert!(may_meet(&ray(Vec3::new(0.0, 2.0, 2.0), Vec3::X, inf), &b));
        assert!(may_meet(
            &ray(Vec3::new(0.0, 0.0, 1.5), Vec3::new(1.0, 1.0, 0.0), inf),
            &b
        ));
        // Ending on the near face.
        assert!(may_meet(&ray(Vec3::new(0.0, 1.5, 1.5), Vec3::X, 1.0), &b));
        // Past it, short of it, beside it, pointing away.
        assert!(!may_meet(&ray(Vec3::new(0.0, 2.1, 1.5), Vec3::X, inf), &b));
        assert!(!may_meet(&ray(Vec3::new(0.0, 1.5, 1.5), Vec3::X, 0.99), &b));
        assert!(!may_meet(
            &ray(Vec3::new(0.0, 0.0, 1.5), Vec3::new(1.0, 3.0, 0.0), inf),
            &b
        ));
        assert!(!may_meet(&ray(Vec3::ZERO, -Vec3::ONE, inf), &b));
        // Starting inside, or past the box.
        assert!(may_meet(&ray(Vec3::splat(1.5), Vec3::Y, inf), &b));
        assert!(!may_meet(
            &Ray::new(Vec3::ZERO, Vec3::X, 3.0, inf).unwrap(),
            &Aabb::new(Vec3::ZERO, Vec3::ONE)
        ));
        // A subnormal component, the origin on the padded face's plane.
        let tiny = Vec3::new(1.0, 1e-40, 0.0);
        let on_face = Vec3::new(0.0, 1.0 - 2e-6, 1.5);
        assert!(may_meet(&ray(on_face, tiny, inf), &b));
    }
}
