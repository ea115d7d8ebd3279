//! SAH binning shared by the object builder and the top-level builders.
//!
//! Binned SAH after I. Wald, "On fast Construction of SAH-based Bounding Volume
//! Hierarchies", IEEE RT 2007: centroids are projected into `bins` equal
//! intervals per axis, each bin accumulates the bounds and the (weighted)
//! count of its primitives, and a sweep evaluates the `bins - 1` planes.
//!
//! Bin boxes are `Vec3A` pairs ([`BinBox`]), and builders fill bins in place
//! rather than returning them: together 1.43x faster flat builds and 1.57x
//! faster object builds of `library --scale 1` (one thread, `rebraid stats
//! library --scale 1 --modes flat,two-level`, 650 -> 455 ms and 455 -> 290 ms,
//! alternating the two binaries; SAH cost and trees unchanged).

use glam::{BVec3A, BVec4A, Vec3A, Vec4};

use crate::Aabb;

/// The largest number of bins a build may ask for.
pub const MAX_BINS: usize = 32;

/// Maps a centroid coordinate to its bin, identically during binning and
/// partitioning (so a partition can never disagree with the cost it was chosen by).
#[derive(Clone, Copy, Debug)]
pub struct BinMapping {
    pub bins: usize,
    pub origin: Vec3A,
    pub scale: Vec3A,
}

impl BinMapping {
    /// A mapping over centroid bounds. An axis of zero extent gets scale 0,
    /// which puts every centroid in bin 0: such an axis yields no split.
    /// So does an extent so small (subnormal) that the scale would overflow:
    /// an infinite scale makes `0 * inf = NaN` for the centroid at the
    /// origin, on which [`BinMapping::goes_left`] and [`BinMapping::bin`]
    /// would disagree.
    pub fn new(centroid_bounds: &Aabb, bins: usize) -> Self {
        let e = centroid_bounds.extent();
        let k = bins as f32 * (1.0 - 1.0e-5);
        let s = |x: f32| {
            let s = k / x;
            if x > 0.0 && s.is_finite() { s } else { 0.0 }
        };
        Self {
            bins,
            origin: centroid_bounds.min.into(),
            scale: Vec3A::new(s(e.x), s(e.y), s(e.z)),
        }
    }

    /// The bin of `c` along `axis`: the same lane arithmetic as
    /// [`BinMapping::bins3`], so partitions agree with the binning.
    #[inline(always)]
    pub fn bin(&self, c: Vec3A, axis: usize) -> usize {
        let b = ((c[axis] - self.origin[axis]) * self.scale[axis]) as usize; // saturating cast
        b.min(self.bins - 1)
    }

    /// `bin(c, AXIS) < split_bin` for a split bin in `1..bins` (as a
    /// [`SplitCandidate`] gives), by one float comparison: with `x` the
    /// scaled coordinate, `min(trunc(max(x, 0)), bins - 1) < k` holds
    /// exactly when `x < k` for an integer `1 <= k <= bins - 1`. The lane is
    /// a constant so the loop reads it without a spill; the indexed lane and
    /// the saturating cast were the hottest instructions of the partition
    /// loop (figures in `docs/performance.md`).
    #[inline(always)]
    pub fn goes_left<const AXIS: usize>(&self, c: Vec3A, split_bin: usize) -> bool {
        debug_assert!((1..self.bins).contains(&split_bin));
        (c[AXIS] - self.origin[AXIS]) * self.scale[AXIS] < split_bin as f32
    }

    /// The bins of `c` along the three axes (one SSE subtract and multiply).
    #[inline(always)]
    pub fn bins3(&self, c: Vec3A) -> [usize; 3] {
        // Clamped in floats (exact: `bins - 1` is an integer), so the
        // conversion needs no saturation: one `cvttps2dq` on x86-64.
        let last = (self.bins - 1) as f32;
        let x = (c - self.origin) * self.scale;
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{
                __m128, _mm_cvttps_epi32, _mm_max_ps, _mm_min_ps, _mm_set1_ps, _mm_setzero_ps,
            };
            // SAFETY: SSE2 is part of the x86-64 baseline. `maxps` returns
            // its second operand when either is NaN, so a NaN coordinate
            // becomes 0 here, and every lane ends in `0..=last`: the bins
            // index unchecked on that (`Bins::add`).
            let i: [i32; 4] = bytemuck::cast(unsafe {
                let clamped = _mm_min_ps(
                    _mm_max_ps(__m128::from(x), _mm_setzero_ps()),
                    _mm_set1_ps(last),
                );
                _mm_cvttps_epi32(clamped)
            });
            [i[0] as usize, i[1] as usize, i[2] as usize]
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            // `f32::max` and `min` return the number when one side is NaN,
            // and `as usize` saturates: every index ends in `0..=last`.
            let b = x.max(Vec3A::ZERO).min(Vec3A::splat(last));
            [b.x as usize, b.y as usize, b.z as usize]
        }
    }

    #[inline]
    pub fn axis_usable(&self, axis: usize) -> bool {
        self.scale[axis] > 0.0
    }
}

/// Per-axis bins: bounds and weight (primitive count) of each bin.
///
/// `N` is the capacity; builders pick the smallest of 4, 8, 16 or 32 that holds
/// the bins a range needs (see [`with_bins`]), because most nodes of a tree
/// are small and clearing and sweeping 32 bins for them dominated build
/// time (measured: 38% of a flat build in `best_split` before this).
#[derive(Clone, Debug)]
pub struct Bins<const N: usize = MAX_BINS> {
    pub bounds: [[BinRow; N]; 3],
    pub weight: [[u64; N]; 3],
}

impl<const N: usize> Default for Bins<N> {
    fn default() -> Self {
        Self {
            bounds: [[BinRow::EMPTY; N]; 3],
            weight: [[0; N]; 3],
        }
    }
}

/// A bin's box as [`Bins`] keep it: the minimum and the negated maximum
/// in one 32-byte row, so that growing it by a box is one eight-lane `min`
/// (`vminps` on a `ymm` register, one load-and-min and one store per axis
/// and primitive, where a [`BinBox`] takes a `min` and a `max` with a load
/// and a store each). `max(a, b)` is `-min(-a, -b)` exactly (both return
/// the second operand on equal inputs), so the bins, costs and trees are
/// those of `BinBox` unions bit for bit.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub struct BinRow {
    pub min: Vec3A,
    pub neg_max: Vec3A,
}

const _: () = assert!(std::mem::size_of::<BinRow>() == 32);

impl BinRow {
    pub const EMPTY: BinRow = BinRow {
        min: Vec3A::splat(f32::INFINITY),
        neg_max: Vec3A::splat(f32::INFINITY),
    };

    #[inline(always)]
    pub fn from_box(b: &BinBox) -> Self {
        Self {
            min: b.min,
            neg_max: -b.max,
        }
    }

    #[inline(always)]
    pub fn to_box(self) -> BinBox {
        BinBox {
            min: self.min,
            max: -self.neg_max,
        }
    }

    /// Grow by `o` (a union of the boxes), two four-lane `min`s.
    #[inline(always)]
    pub fn grow(&mut self, o: &BinRow) {
        self.min = self.min.min(o.min);
        self.neg_max = self.neg_max.min(o.neg_max);
    }
}

/// Per axis, whether `v` is finite: `|v| < inf` is false for NaN and
/// infinities alike (no branch, unlike `Vec3A::is_finite`).
#[inline(always)]
pub fn finite_lanes(v: Vec3A) -> BVec3A {
    v.abs().cmplt(Vec3A::INFINITY)
}

/// A bin's box in 16-byte SIMD vectors: binning is unions of boxes, and
/// `Vec3A` does each min and max in one SSE instruction where `Vec3` needs
/// three scalar ones (measured: see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BinBox {
    pub min: Vec3A,
    pub max: Vec3A,
}

impl BinBox {
    pub const EMPTY: BinBox = BinBox {
        min: Vec3A::splat(f32::INFINITY),
        max: Vec3A::splat(f32::NEG_INFINITY),
    };

    #[inline(always)]
    pub fn from_aabb(b: &Aabb) -> Self {
        Self {
            min: b.min.into(),
            max: b.max.into(),
        }
    }

    #[inline(always)]
    pub fn union(self, o: BinBox) -> Self {
        Self {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }

    #[inline(always)]
    pub fn half_area(&self) -> f32 {
        let e = (self.max - self.min).max(Vec3A::ZERO);
        e.x * e.y + e.y * e.z + e.z * e.x
    }

    /// Finite, with `min <= max` on every axis.
    #[inline]
    pub fn is_valid(&self) -> bool {
        self.valid_lanes().all()
    }

    /// [`BinBox::is_valid`] per axis, without a branch (for checks folded
    /// into a pass over many boxes, `build_bvh_aligned`'s bounds pass).
    #[inline(always)]
    pub fn valid_lanes(&self) -> BVec3A {
        finite_lanes(self.min) & finite_lanes(self.max) & self.min.cmple(self.max)
    }

    #[inline(always)]
    pub fn center(&self) -> Vec3A {
        (self.min + self.max) * 0.5
    }

    #[inline(always)]
    pub fn grow(self, p: Vec3A) -> Self {
        Self {
            min: self.min.min(p),
            max: self.max.max(p),
        }
    }

    #[inline(always)]
    pub fn to_aabb(self) -> Aabb {
        Aabb::new(self.min.into(), self.max.into())
    }
}

/// Something that bins a range and reports its best split, for any bin capacity.
pub trait BinRange {
    fn run<const N: usize>(&self, map: &BinMapping) -> Option<SplitCandidate>;
}

/// Run `f` with the smallest bin capacity that holds `map.bins`.
#[inline]
pub fn with_bins<F: BinRange>(map: &BinMapping, f: &F) -> Option<SplitCandidate> {
    if map.bins <= 4 {
        f.run::<4>(map)
    } else if map.bins <= 8 {
        f.run::<8>(map)
    } else if map.bins <= 16 {
        f.run::<16>(map)
    } else {
        f.run::<MAX_BINS>(map)
    }
}

/// The best plane found by [`Bins::best_split`].
#[derive(Clone, Copy, Debug)]
pub struct SplitCandidate {
    pub axis: usize,
    /// Elements whose bin is below this go left.
    pub bin: usize,
    /// `area(L) * weight(L) + area(R) * weight(R)` (half areas).
    pub cost: f32,
    pub left_bounds: Aabb,
    pub right_bounds: Aabb,
    pub left_weight: u64,
    pub right_weight: u64,
}

impl<const N: usize> Bins<N> {
    /// Add a primitive (its box, centroid and weight) to its bin on each
    /// axis. Panics when `map` has no bins or more than `N`.
    #[inline(always)]
    pub fn add(&mut self, map: &BinMapping, bounds: &BinBox, centroid: Vec3A, weight: u64) {
        // Checked once per call, which the binning loops hoist out (the
        // mapping does not change inside them); the three indices below
        // then need no checks of their own (three compares and branches
        // per primitive in the hottest loop of a build).
        assert!(
            (1..=N).contains(&map.bins),
            "{} bins for a capacity of {N}",
            map.bins
        );
        let row = BinRow::from_box(bounds);
        let b = map.bins3(centroid);
        for (axis, &bin) in b.iter().enumerate() {
            debug_assert!(bin < map.bins);
            // SAFETY: `bins3` clamps every index to `0..=map.bins - 1`,
            // whatever the centroid (NaN included, see there), and
            // `map.bins <= N` was asserted above; `axis < 3`.
            unsafe {
                let slot = self.bounds.get_unchecked_mut(axis).get_unchecked_mut(bin);
                slot.grow(&row);
                *self.weight.get_unchecked_mut(axis).get_unchecked_mut(bin) += weight;
            }
        }
    }

    /// [`Bins::add`] for every `(box, centroid, weight)` of `items`: with
    /// AVX where the CPU has it (each axis's bin grown by one eight-lane
    /// `min`, see [`BinRow`]), else `add` by `add`. The same bins either
    /// way, bit for bit (`avx_fill_matches_add`).
    ///
    /// A dispatching function rather than AVX intrinsics in `add`: an AVX
    /// intrinsic compiled into a function without the AVX feature becomes
    /// a call (see `WatertightRay::new_avx`).
    #[inline]
    pub fn fill(
        &mut self,
        map: &BinMapping,
        items: impl ExactSizeIterator<Item = (BinBox, Vec3A, u64)>,
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX (checked just above).
            unsafe { self.fill_avx(map, items) };
            return;
        }
        for (b, c, w) in items {
            self.add(map, &b, c, w);
        }
    }

    /// See [`Bins::fill`].
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    unsafe fn fill_avx(
        &mut self,
        map: &BinMapping,
        items: impl ExactSizeIterator<Item = (BinBox, Vec3A, u64)>,
    ) {
        use std::arch::x86_64::{
            __m128, _mm_cvttps_epi32, _mm_extract_epi32, _mm_max_ps, _mm_min_ps, _mm_mul_ps,
            _mm_set1_ps, _mm_setzero_ps, _mm_slli_epi32, _mm_sub_ps, _mm256_load_ps,
            _mm256_loadu_ps, _mm256_min_ps, _mm256_set_ps, _mm256_store_ps, _mm256_xor_ps,
        };
        assert!(
            (1..=N).contains(&map.bins),
            "{} bins for a capacity of {N}",
            map.bins
        );
        // The upper half's sign flipped: `[min, -max]`.
        let flip = _mm256_set_ps(-0.0, -0.0, -0.0, -0.0, 0.0, 0.0, 0.0, 0.0);
        let (origin, scale) = (__m128::from(map.origin), __m128::from(map.scale));
        let last = _mm_set1_ps((map.bins - 1) as f32);
        let add = |bins: &mut Bins<N>, (bounds, centroid, weight): (BinBox, Vec3A, u64)| {
            // SAFETY: a `BinBox` is two 16-byte `Vec3A`s (32 bytes, `min`
            // then `max`, no padding between): one unaligned 32-byte load.
            let row = _mm256_xor_ps(
                unsafe { _mm256_loadu_ps((&bounds as *const BinBox).cast::<f32>()) },
                flip,
            );
            // `BinMapping::bins3`'s lane arithmetic (the same bins: the
            // test below), the indices times 8: the byte offset of a bin's
            // `u64` weight, and of its 32-byte row at scale 4, so that no
            // axis needs a shift of its own.
            let x = _mm_mul_ps(_mm_sub_ps(__m128::from(centroid), origin), scale);
            let eight = _mm_slli_epi32(
                _mm_cvttps_epi32(_mm_min_ps(_mm_max_ps(x, _mm_setzero_ps()), last)),
                3,
            );
            let offsets = [
                _mm_extract_epi32::<0>(eight) as u32 as usize,
                _mm_extract_epi32::<1>(eight) as u32 as usize,
                _mm_extract_epi32::<2>(eight) as u32 as usize,
            ];
            let rows = bins.bounds.as_mut_ptr().cast::<u8>();
            let weights = bins.weight.as_mut_ptr().cast::<u8>();
            for (axis, &off) in offsets.iter().enumerate() {
                debug_assert!(off / 8 < map.bins);
                // SAFETY: as in `add`, every bin index `off / 8` is in
                // `0..map.bins` (`maxps` turns NaN into 0, the clamp does
                // the rest) and `map.bins <= N` (asserted above), `axis <
                // 3`: the row at byte `axis * N * 32 + off * 4` and the
                // weight at `axis * N * 8 + off` are elements of the
                // arrays. A `BinRow` is 32 bytes aligned to 32, the
                // aligned load and store's size and alignment.
                unsafe {
                    let p = rows.add(axis * N * 32 + off * 4).cast::<f32>();
                    _mm256_store_ps(p, _mm256_min_ps(_mm256_load_ps(p), row));
                    *weights.add(axis * N * 8 + off).cast::<u64>() += weight;
                }
            }
        };
        for item in items {
            add(self, item);
        }
    }

    /// Merge another set of bins (exact: unions and integer sums), so that a
    /// chunked parallel binning gives the same result as a sequential one.
    pub fn merge(&mut self, o: &Bins<N>, bins: usize) {
        for axis in 0..3 {
            for i in 0..bins {
                self.bounds[axis][i].grow(&o.bounds[axis][i]);
                self.weight[axis][i] += o.weight[axis][i];
            }
        }
    }

    /// The plane of least `area * weight` sum; ties go to the lower axis, then
    /// the lower bin. `None` when every usable axis has all weight on one side.
    #[inline]
    pub fn best_split(&self, map: &BinMapping) -> Option<SplitCandidate> {
        self.best_split_blocks(map, 0)
    }

    /// [`Bins::best_split`] with each side's weight counted in blocks of
    /// `1 << block_shift` (rounded up): the cost of leaves that test that
    /// many primitives at once (Embree's `sahBlockSize`). The candidate's
    /// `cost` uses the block counts; its weights stay primitive counts.
    pub fn best_split_blocks(&self, map: &BinMapping, block_shift: u32) -> Option<SplitCandidate> {
        let n = map.bins;
        let round = (1u64 << block_shift) - 1;
        // Through `i64` (exact: weights are far below 2^63), which x86-64
        // converts to `f32` in one instruction; `u64` takes a branchy
        // sequence.
        let blocks = |w: u64| (((w + round) >> block_shift) as i64) as f32;
        let blocks3 = |w: &[u64; 3]| Vec4::new(blocks(w[0]), blocks(w[1]), blocks(w[2]), 0.0);
        debug_assert!(n <= N);
        // The three axes sweep together, one per vector lane (lane 3 idle),
        // and the sweeps keep costs only: the winner's boxes and weights
        // are summed once at the end. Axis by axis, storing every plane's
        // right box and weight, this function was 13% of an object build's
        // instructions and a quarter of the top level's (callgrind).
        // Every lane does the scalar arithmetic (`half_areas3`), so the
        // costs are the scalar sweep's bit for bit. A side without
        // primitives costs infinity: never below the best.
        let usable = BVec4A::new(
            map.axis_usable(0),
            map.axis_usable(1),
            map.axis_usable(2),
            false,
        );
        // One side's cost per lane after adding bin `i` to it.
        let grow = |b: &mut [BinBox; 3], w: &mut [u64; 3], i: usize| {
            for a in 0..3 {
                b[a] = b[a].union(self.bounds[a][i].to_box());
                w[a] += self.weight[a][i];
            }
            let k = blocks3(w);
            Vec4::select(k.cmpeq(Vec4::ZERO), Vec4::INFINITY, half_areas3(b) * k)
        };
        let mut right_cost = [Vec4::ZERO; N];
        let (mut b, mut w) = ([BinBox::EMPTY; 3], [0u64; 3]);
        for i in (1..n).rev() {
            right_cost[i] = grow(&mut b, &mut w, i);
        }
        // Per lane, the first bin of least cost; then the lane of least
        // cost, the lower axis on ties: the scalar sweep's choice (axis by
        // axis, bins ascending, strictly better only).
        let (mut best, mut best_bin) = (Vec4::INFINITY, [0usize; 3]);
        let (mut b, mut w) = ([BinBox::EMPTY; 3], [0u64; 3]);
        for (i, right) in right_cost.iter().enumerate().take(n).skip(1) {
            let cost = grow(&mut b, &mut w, i - 1) + *right;
            let better = cost.cmplt(best) & usable;
            best = Vec4::select(better, cost, best);
            let m = better.bitmask();
            for (a, bin) in best_bin.iter_mut().enumerate() {
                if m & (1 << a) != 0 {
                    *bin = i;
                }
            }
        }
        let costs = best.to_array();
        let best_axis = (1..3).fold(0, |a, x| if costs[x] < costs[a] { x } else { a });
        let (best_cost, best_bin) = (costs[best_axis], best_bin[best_axis]);
        if best_cost == f32::INFINITY {
            return None;
        }
        let side = |range: std::ops::Range<usize>| {
            range.fold((BinBox::EMPTY, 0u64), |(b, w), i| {
                (
                    b.union(self.bounds[best_axis][i].to_box()),
                    w + self.weight[best_axis][i],
                )
            })
        };
        let ((lb, lw), (rb, rw)) = (side(0..best_bin), side(best_bin..n));
        Some(SplitCandidate {
            axis: best_axis,
            bin: best_bin,
            cost: best_cost,
            left_bounds: lb.to_aabb(),
            right_bounds: rb.to_aabb(),
            left_weight: lw,
            right_weight: rw,
        })
    }
}

/// The half areas of three boxes, one per lane (lane 3: 0), each computed
/// as [`BinBox::half_area`] computes it (same operations in the same order,
/// so the same bits).
#[inline(always)]
fn half_areas3(b: &[BinBox; 3]) -> Vec4 {
    let e = b.map(|b| (b.max - b.min).max(Vec3A::ZERO));
    let x = Vec4::new(e[0].x, e[1].x, e[2].x, 0.0);
    let y = Vec4::new(e[0].y, e[1].y, e[2].y, 0.0);
    let z = Vec4::new(e[0].z, e[1].z, e[2].z, 0.0);
    x * y + y * z + z * x
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn splits_two_clusters() {
        let boxes: Vec<Aabb> = [0.0f32, 0.1, 0.2, 10.0, 10.1]
            .iter()
            .map(|&x| Aabb::new(Vec3::new(x, 0.0, 0.0), Vec3::new(x + 0.05, 1.0, 1.0)))
            .collect();
        let cb = boxes.iter().fold(Aabb::EMPTY, |b, x| b.grow(x.center()));
        let map = BinMapping::new(&cb, 16);
        let mut bins = Bins::<16>::default();
        for b in &boxes {
            bins.add(&map, &BinBox::from_aabb(b), b.center().into(), 1);
        }
        let s = bins.best_split(&map).unwrap();
        assert_eq!(s.axis, 0);
        assert_eq!((s.left_weight, s.right_weight), (3, 2));
        for b in &boxes {
            let left = map.bin(b.center().into(), 0) < s.bin;
            assert_eq!(left, b.min.x < 5.0);
        }
    }

    /// The partition's float comparison and the binning's vector
    /// conversion agree with the scalar bin of every coordinate, including
    /// coordinates on and just beside bin boundaries.
    #[test]
    fn fast_bin_tests_agree_with_scalar_bins() {
        let cb = Aabb::new(Vec3::new(-3.0, 0.0, 1.0e-3), Vec3::new(5.0, 1.0e4, 2.0e-3));
        for bins in [4, 7, 16, 32] {
            let map = BinMapping::new(&cb, bins);
            let mut seed = 0x9e37_79b9u32;
            for i in 0..20_000u32 {
                seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let t = (seed >> 8) as f32 / (1u32 << 24) as f32;
                // Every 4th point sits on a bin boundary (and one ulp off).
                let t = if i % 4 == 0 {
                    let b = (t * bins as f32).floor() / bins as f32;
                    f32::from_bits(b.to_bits().wrapping_add(i % 3)).min(1.0)
                } else {
                    t
                };
                let c: Vec3A = (cb.min + (cb.max - cb.min) * t).into();
                let scalar = [map.bin(c, 0), map.bin(c, 1), map.bin(c, 2)];
                assert_eq!(map.bins3(c), scalar, "{c:?}");
                for k in 1..bins {
                    assert_eq!(map.goes_left::<0>(c, k), scalar[0] < k);
                    assert_eq!(map.goes_left::<1>(c, k), scalar[1] < k);
                    assert_eq!(map.goes_left::<2>(c, k), scalar[2] < k);
                }
            }
        }
    }

    /// Centroids a subnormal distance apart: no infinite scale (whose
    /// `0 * inf` would be a NaN bin), the axis is simply unusable.
    #[test]
    fn subnormal_extent_is_unusable() {
        let tiny = f32::from_bits(1); // the smallest subnormal
        let cb = Aabb::new(Vec3::ZERO, Vec3::new(tiny, 1.0, 0.0));
        let map = BinMapping::new(&cb, 32);
        assert!(!map.axis_usable(0));
        assert!(map.axis_usable(1));
        assert!(map.scale.is_finite());
        for x in [0.0, tiny] {
            let c = Vec3A::new(x, 0.5, 0.0);
            assert_eq!(map.bins3(c), [0, map.bin(c, 1), 0]);
        }
    }

    /// The split chosen axis by axis with scalar arithmetic (the sweep
    /// before it was vectorised): what `best_split_blocks` must return.
    fn scalar_best_split<const N: usize>(
        bins: &Bins<N>,
        map: &BinMapping,
        shift: u32,
    ) -> Option<(usize, usize, f32, u64, u64, Aabb, Aabb)> {
        let blocks = |w: u64| ((w + (1 << shift) - 1) >> shift) as f32;
        let mut best: Option<(usize, usize, f32, u64, u64, Aabb, Aabb)> = None;
        for axis in (0..3).filter(|&a| map.axis_usable(a)) {
            for i in 1..map.bins {
                let side = |r: std::ops::Range<usize>| {
                    r.fold((BinBox::EMPTY, 0u64), |(b, w), k| {
                        (
                            b.union(bins.bounds[axis][k].to_box()),
                            w + bins.weight[axis][k],
                        )
                    })
                };
                let ((lb, lw), (rb, rw)) = (side(0..i), side(i..map.bins));
                if lw == 0 || rw == 0 {
                    continue;
                }
                let cost = lb.half_area() * blocks(lw) + rb.half_area() * blocks(rw);
                if best.is_none_or(|b| cost < b.2) {
                    best = Some((axis, i, cost, lw, rw, lb.to_aabb(), rb.to_aabb()));
                }
            }
        }
        best
    }

    /// The three-lane sweep picks the scalar sweep's split (axis, bin,
    /// cost bit for bit, weights, boxes) on random bins with empty bins,
    /// repeated boxes (ties), unusable axes and block sizes 1 and 4.
    #[test]
    fn lane_sweep_matches_the_scalar_sweep() {
        let mut seed = 0x2545_f491u32;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 17;
            seed ^= seed << 5;
            seed
        };
        for case in 0..3000 {
            let n = 2 + (next() % 31) as usize;
            let cb = Aabb::new(
                Vec3::ZERO,
                Vec3::new(1.0, if case % 5 == 0 { 0.0 } else { 1.0 }, 1.0),
            );
            let map = BinMapping::new(&cb, n);
            let mut bins = Bins::<MAX_BINS>::default();
            // A few distinct boxes, reused, so that costs tie.
            let palette: Vec<BinBox> = (0..3)
                .map(|_| {
                    let mut v = |k: u32| (next() % k) as f32 * 0.25;
                    let lo = Vec3A::new(v(4), v(4), v(4));
                    BinBox {
                        min: lo,
                        max: lo + Vec3A::new(v(5), v(5), v(5)),
                    }
                })
                .collect();
            for axis in 0..3 {
                for i in 0..n {
                    if next() % 3 == 0 {
                        continue; // an empty bin
                    }
                    bins.bounds[axis][i] = BinRow::from_box(&palette[(next() % 3) as usize]);
                    bins.weight[axis][i] = 1 + (next() % 9) as u64;
                }
            }
            for shift in [0, 2] {
                let got = bins.best_split_blocks(&map, shift).map(|s| {
                    (
                        s.axis,
                        s.bin,
                        s.cost,
                        s.left_weight,
                        s.right_weight,
                        s.left_bounds,
                        s.right_bounds,
                    )
                });
                let want = scalar_best_split(&bins, &map, shift);
                assert_eq!(
                    got.map(|g| (g.0, g.1, g.2.to_bits(), g.3, g.4)),
                    want.map(|w| (w.0, w.1, w.2.to_bits(), w.3, w.4)),
                    "case {case}, shift {shift}"
                );
                assert_eq!(got.map(|g| (g.5, g.6)), want.map(|w| (w.5, w.6)));
            }
        }
    }

    /// `fill` (the AVX path where the CPU has it) makes the bins `add` by
    /// `add` makes, bit for bit: boxes with shared and signed-zero
    /// coordinates (where `min` and `max` pick an operand), odd centroids,
    /// weights above one, every bin count of a capacity.
    #[test]
    fn avx_fill_matches_add() {
        let mut seed = 0x2545_f491u32;
        let mut next = move || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            seed >> 8
        };
        let coords = [-0.0f32, 0.0, 1.0, -1.0, 0.5, 2.0, -3.25, 1e-30];
        let mut items: Vec<(BinBox, Vec3A, u64)> = (0..500)
            .map(|_| {
                let mut pick = || coords[(next() % 8) as usize];
                let a = Vec3A::new(pick(), pick(), pick());
                let b = Vec3A::new(pick(), pick(), pick());
                let bx = BinBox {
                    min: a.min(b),
                    max: a.max(b),
                };
                (bx, bx.center(), 1 + (next() % 3) as u64)
            })
            .collect();
        items.push((
            BinBox::from_aabb(&Aabb::new(Vec3::ZERO, Vec3::ONE)),
            Vec3A::NAN,
            1,
        ));
        let cb = Aabb::new(Vec3::splat(-3.25), Vec3::splat(2.0));
        for bins in 1..=16 {
            let map = BinMapping::new(&cb, bins);
            let (mut by_add, mut by_fill) = (Bins::<16>::default(), Bins::<16>::default());
            for (b, c, w) in &items {
                by_add.add(&map, b, *c, *w);
            }
            by_fill.fill(&map, items.iter().copied());
            let bits = |bins: &Bins<16>| {
                bins.bounds
                    .iter()
                    .flatten()
                    .flat_map(|r| {
                        let b = r.to_box();
                        [b.min.to_array(), b.max.to_array()]
                    })
                    .flatten()
                    .map(f32::to_bits)
                    .collect::<Vec<u32>>()
            };
            assert_eq!(bits(&by_fill), bits(&by_add), "{bins} bins");
            assert_eq!(by_fill.weight, by_add.weight, "{bins} bins");
        }
    }

    /// `add` indexes its bins unchecked: any centroid (NaN, infinite, far
    /// outside the mapping) lands in a bin of the mapping, for every bin
    /// count up to the capacity; more bins than the capacity panic.
    #[test]
    fn add_keeps_every_centroid_inside_the_bins() {
        let cb = Aabb::new(Vec3::ZERO, Vec3::new(1.0, 2.0, 0.0));
        let b = BinBox::from_aabb(&cb);
        let odd = [
            Vec3A::NAN,
            Vec3A::INFINITY,
            Vec3A::NEG_INFINITY,
            Vec3A::new(1e30, -1e30, 0.5),
            Vec3A::new(0.5, 1.0, f32::NAN),
            Vec3A::splat(1.0),
        ];
        for bins in 1..=8 {
            let map = BinMapping::new(&cb, bins);
            let mut all = Bins::<8>::default();
            for &c in &odd {
                all.add(&map, &b, c, 1);
            }
            for axis in 0..3 {
                let inside: u64 = all.weight[axis][..bins].iter().sum();
                assert_eq!(inside, odd.len() as u64, "{bins} bins, axis {axis}");
            }
        }
        let map = BinMapping::new(&cb, 16);
        let r = std::panic::catch_unwind(|| Bins::<8>::default().add(&map, &b, Vec3A::ZERO, 1));
        assert!(r.is_err(), "16 bins in a capacity of 8 must panic");
    }

    #[test]
    fn degenerate_axis_is_unusable() {
        let cb = Aabb::new(Vec3::ZERO, Vec3::new(0.0, 1.0, 0.0));
        let map = BinMapping::new(&cb, 8);
        assert!(!map.axis_usable(0));
        assert!(map.axis_usable(1));
        assert_eq!(map.bin(Vec3A::new(0.0, 1.0, 0.0), 1), 7);
        assert_eq!(map.bin(Vec3A::new(0.0, -5.0, 0.0), 1), 0);
    }
}
