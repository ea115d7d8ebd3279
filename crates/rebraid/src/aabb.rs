//! Axis-aligned bounding boxes.

use glam::Vec3;

/// An axis-aligned box. The empty box has `min = +inf`, `max = -inf`, so that
/// growing it by any point or box yields that point or box.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Default for Aabb {
    fn default() -> Self {
        Self::EMPTY
    }
}

impl Aabb {
    /// The empty box: the identity of [`Aabb::union`].
    pub const EMPTY: Aabb = Aabb {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };

    #[inline]
    pub fn new(min: Vec3, max: Vec3) -> Self {
        Self { min, max }
    }

    /// The smallest box holding every point.
    pub fn from_points(points: &[Vec3]) -> Self {
        points.iter().fold(Self::EMPTY, |b, &p| b.grow(p))
    }

    #[inline]
    pub fn grow(self, p: Vec3) -> Self {
        Self {
            min: self.min.min(p),
            max: self.max.max(p),
        }
    }

    #[inline]
    pub fn union(self, o: Aabb) -> Self {
        Self {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }

    /// The overlap of two boxes (possibly empty).
    #[inline]
    pub fn intersection(self, o: Aabb) -> Self {
        Self {
            min: self.min.max(o.min),
            max: self.max.min(o.max),
        }
    }

    /// True when the box holds no point (`min > max` on some axis).
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.min.x > self.max.x || self.min.y > self.max.y || self.min.z > self.max.z
    }

    /// True when the boxes share at least one point (touching counts).
    #[inline]
    pub fn overlaps(&self, o: &Aabb) -> bool {
        !self.intersection(*o).is_empty()
    }

    /// True when the boxes share a volume of non-zero size along every axis.
    #[inline]
    pub fn overlaps_strictly(&self, o: &Aabb) -> bool {
        let i = self.intersection(*o);
        i.min.x < i.max.x && i.min.y < i.max.y && i.min.z < i.max.z
    }

    #[inline]
    pub fn contains_box(&self, o: &Aabb) -> bool {
        o.is_empty() || (self.min.cmple(o.min).all() && o.max.cmple(self.max).all())
    }

    #[inline]
    pub fn contains_point(&self, p: Vec3) -> bool {
        self.min.cmple(p).all() && p.cmple(self.max).all()
    }

    /// Extent along each axis; zero for the empty box.
    #[inline]
    pub fn extent(&self) -> Vec3 {
        (self.max - self.min).max(Vec3::ZERO)
    }

    #[inline]
    pub fn center(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }

    /// Half the surface area, the measure the SAH uses; zero for the empty box.
    #[inline]
    pub fn half_area(&self) -> f32 {
        let e = self.extent();
        e.x * e.y + e.y * e.z + e.z * e.x
    }

    /// Volume; zero for the empty box and for flat boxes.
    #[inline]
    pub fn volume(&self) -> f32 {
        let e = self.extent();
        e.x * e.y * e.z
    }

    /// The sum of the boxes' half areas over the half area of their union:
    /// about how many of them cover a point of it (1 for boxes side by
    /// side, more as they overlap; 0 when the union has no area). The
    /// scene's "overlap" ([`crate::SceneDesc::overlap_ratio`]) and the
    /// re-braiding budget's ([`crate::toplevel::builder::placement_overlap`]).
    pub fn overlap_ratio(boxes: impl IntoIterator<Item = Aabb>) -> f64 {
        let (all, sum) = boxes.into_iter().fold((Aabb::EMPTY, 0.0f64), |(u, s), b| {
            (u.union(b), s + b.half_area() as f64)
        });
        let area = all.half_area() as f64;
        // Also catches NaN.
        if area.is_nan() || area <= 0.0 {
            return 0.0;
        }
        sum / area
    }

    /// The axis (0, 1, 2) along which the box is longest; the first one on ties.
    #[inline]
    pub fn largest_axis(&self) -> usize {
        let e = self.extent();
        if e.x >= e.y && e.x >= e.z {
            0
        } else if e.y >= e.z {
            1
        } else {
            2
        }
    }

    /// True when every coordinate is finite and the box is not empty.
    #[inline]
    pub fn is_finite(&self) -> bool {
        self.min.is_finite() && self.max.is_finite()
    }

    /// The eight corners, in `x` fastest order.
    pub fn corners(&self) -> [Vec3; 8] {
        let (a, b) = (self.min, self.max);
        [
            Vec3::new(a.x, a.y, a.z),
            Vec3::new(b.x, a.y, a.z),
            Vec3::new(a.x, b.y, a.z),
            Vec3::new(b.x, b.y, a.z),
            Vec3::new(a.x, a.y, b.z),
            Vec3::new(b.x, a.y, b.z),
            Vec3::new(a.x, b.y, b.z),
            Vec3::new(b.x, b.y, b.z),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_is_union_identity() {
        let b = Aabb::new(Vec3::new(-1.0, 0.0, 2.0), Vec3::new(1.0, 3.0, 4.0));
        assert_eq!(Aabb::EMPTY.union(b), b);
        assert!(Aabb::EMPTY.is_empty());
        assert_eq!(Aabb::EMPTY.half_area(), 0.0);
        assert!(b.contains_box(&Aabb::EMPTY));
    }

    #[test]
    fn half_area_and_axis() {
        let b = Aabb::new(Vec3::ZERO, Vec3::new(1.0, 2.0, 3.0));
        assert_eq!(b.half_area(), 2.0 + 6.0 + 3.0);
        assert_eq!(b.largest_axis(), 2);
        assert_eq!(Aabb::new(Vec3::ZERO, Vec3::ONE).largest_axis(), 0);
    }

    #[test]
    fn volume_of_boxes_empty_and_flat() {
        assert_eq!(
            Aabb::new(Vec3::ZERO, Vec3::new(1.0, 2.0, 3.0)).volume(),
            6.0
        );
        assert_eq!(Aabb::EMPTY.volume(), 0.0);
        assert_eq!(
            Aabb::new(Vec3::ZERO, Vec3::new(4.0, 0.0, 3.0)).volume(),
            0.0
        );
    }

    #[test]
    fn overlap_tests() {
        let a = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let b = Aabb::new(Vec3::splat(1.0), Vec3::splat(2.0));
        let c = Aabb::new(Vec3::splat(0.5), Vec3::splat(2.0));
        assert!(a.overlaps(&b));
        assert!(!a.overlaps_strictly(&b));
        assert!(a.overlaps_strictly(&c));
        assert!(!a.overlaps(&Aabb::new(Vec3::splat(1.5), Vec3::splat(2.0))));
    }
}
