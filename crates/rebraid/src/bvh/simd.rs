//! Single-ray traversal of wide BVHs with SIMD box tests, and the wide mesh
//! BVH that uses them.
//!
//! One ray at a time tests all `W` children of a node at once (Wald et al.
//! 2008, "Getting Rid of Packets"; Dammertz et al. 2008, "Shallow Bounding
//! Volume Hierarchies"), then visits the nearest hit child and pushes the
//! others, sorted by entry distance so that the nearest pops first. Popped
//! entries farther than the current closest hit are skipped.
//!
//! Kernels ([`Kernel`]): a portable scalar-lane reference that loops over the
//! lanes with the binary traversal's own [`BoxRay::hit_node`]; SSE4.1 (four
//! lanes, two halves for `W = 8`); AVX2 (eight lanes, `W = 8`). The SSE
//! box test reproduces `hit_node` exactly: the same `(plane - origin) *
//! inv_dir` products (no FMA contraction, so the same roundings), a NaN in
//! either distance of an axis (origin on a slab plane, zero direction
//! component) widening that slab to `(-inf, inf)`, and the far distance
//! clamped to `t_max` and then padded by `1 + 2 gamma(3)` (T. Ize, "Robust
//! BVH Ray Traversal", JCGT 2(2), 2013). The near plane of each axis is
//! picked per ray by the direction's sign (Williams et al. 2005), which gives
//! the same values as `hit_node`'s min/max for real boxes and keeps the empty
//! slots' inverted boxes unhittable. The AVX2 test computes each distance
//! with one FMA, `plane * inv_dir - origin * inv_dir`, as Embree does, and
//! stays conservative by moving `origin * inv_dir` by a per-axis bound on
//! its rounding error (down for near planes, up for far ones), which costs
//! nothing per node; rays with a zero direction component take the exact
//! test. Measured: +2-4% shadow rays on samurai and nexuiz, one thread. Hits
//! stay identical; only box decisions within that bound may differ. Leaves
//! hold [`Triangle4`] blocks: the
//! SIMD kernels test four triangles at once, the scalar one loops over the
//! lanes, and both give hits bit-identical to [`MeshBvh`]'s (see
//! [`super::triangle4`]).

use std::mem::MaybeUninit;

use glam::{Vec3, Vec3A};

use super::triangle4::{
    LeafHit, Triangle4, block_boxes, block_hit_record, intersect_blocks, pack_triangle4,
    validate_blocks,
};
use super::wide::{WideBvh, WideNode, WideStats, decode_leaf, is_leaf_ref};
use super::{BoxRay, BvhNode, MAX_DEPTH, ROBUST_FAR, TraversalCounters};
use crate::mesh::MeshBvh;
use crate::triangle::WatertightRay;
use crate::{Error, Hit, Ray};

/// Entries of a wide traversal stack. The stack only holds siblings of the
/// nodes on the current path, at most `W - 1` per level; a wide inner node
/// is a binary inner node strictly deeper than its wide parent's, so the
/// wide depth is below [`MAX_DEPTH`] and `7 * MAX_DEPTH` covers `W <= 8`.
pub const WIDE_STACK: usize = 7 * MAX_DEPTH as usize;

/// A traversal kernel of a wide BVH.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Kernel {
    /// Portable: loops over the lanes with [`BoxRay::hit_node`]. The
    /// default, as the one kernel every CPU runs.
    #[default]
    Scalar,
    /// SSE4.1, four lanes per instruction (`W = 8` in two halves).
    Sse,
    /// The AVX2 level, eight lanes per instruction; a `W = 4` tree runs the
    /// SSE kernel under it (every AVX2 CPU has SSE4.1). The level is AVX2
    /// with FMA, BMI1, BMI2 and LZCNT, as Embree's AVX2 ISA defines it
    /// (every CPU with AVX2 has the others): BMI1's `blsr` and `andn`, BMI2's
    /// shifts and LZCNT shorten the traversal's mask and index arithmetic
    /// (callgrind, diffuse rays, re-braided: 1.5-2.4% fewer instructions per
    /// ray on samurai monastery, nexuiz, openarena and 2CylinderEngine).
    Avx2,
}

impl Kernel {
    pub const ALL: [Kernel; 3] = [Kernel::Scalar, Kernel::Sse, Kernel::Avx2];

    /// True when this CPU can run the kernel (detected at run time).
    pub fn is_available(self) -> bool {
        match self {
            Kernel::Scalar => true,
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse => std::arch::is_x86_feature_detected!("sse4.1"),
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 => {
                std::arch::is_x86_feature_detected!("avx2")
                    && std::arch::is_x86_feature_detected!("fma")
                    && std::arch::is_x86_feature_detected!("bmi1")
                    && std::arch::is_x86_feature_detected!("bmi2")
                    && std::arch::is_x86_feature_detected!("lzcnt")
            }
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// The fastest kernel this CPU runs.
    pub fn best() -> Kernel {
        [Kernel::Avx2, Kernel::Sse]
            .into_iter()
            .find(|k| k.is_available())
            .unwrap_or(Kernel::Scalar)
    }

    /// Every kernel this CPU runs.
    pub fn available() -> Vec<Kernel> {
        Self::ALL.into_iter().filter(|k| k.is_available()).collect()
    }
}

/// Tests a ray against the `W` child boxes of a node: returns the mask of
/// hit children and writes their entry distances to `dist`. A lane is hit
/// exactly when [`BoxRay::hit_node`] would return a finite distance for it.
pub trait BoxTester<const W: usize> {
    /// Whether leaves run the SSE four-triangle test
    /// ([`super::triangle4`]) under this tester; the scalar reference
    /// keeps the scalar triangle loop.
    const SIMD_TRIANGLES: bool = true;
    fn test(&self, node: &WideNode<W>, t_max: f32, dist: &mut [f32; W]) -> u32;

    /// Whether [`BoxTester::test`] takes a rare path of its own for this
    /// ray (the AVX2 tester's exact arithmetic for a zero direction
    /// component). [`traverse`] then runs a loop compiled for each answer
    /// ([`BoxTester::test_known`]), so that the common one has no branch on
    /// it per node.
    #[inline(always)]
    fn exact(&self) -> bool {
        false
    }

    /// [`BoxTester::test`] for a tester whose [`BoxTester::exact`] is
    /// `EXACT`.
    #[inline(always)]
    fn test_known<const EXACT: bool>(
        &self,
        node: &WideNode<W>,
        t_max: f32,
        dist: &mut [f32; W],
    ) -> u32 {
        self.test(node, t_max, dist)
    }
}

/// The reference: the binary traversal's test, lane by lane.
#[derive(Clone, Copy)]
struct ScalarTester {
    ray: BoxRay,
    t_min: f32,
}

impl<const W: usize> BoxTester<W> for ScalarTester {
    const SIMD_TRIANGLES: bool = false;
    #[inline(always)]
    fn test(&self, node: &WideNode<W>, t_max: f32, dist: &mut [f32; W]) -> u32 {
        let mut mask = 0;
        for (i, d) in dist.iter_mut().enumerate() {
            // `hit_node` takes min/max per axis, which would make an empty
            // slot's inverted box the whole space: skip empty slots.
            if node.child[i] == super::wide::WIDE_EMPTY {
                continue;
            }
            let b = BvhNode::inner(node.child_bounds(i), 0);
            *d = self.ray.hit_node(&b, self.t_min, t_max);
            if *d < f32::INFINITY {
                mask |= 1 << i;
            }
        }
        mask
    }
}

/// A ray's constants for the one-FMA slab test of the AVX2 kernel:
/// per axis, a box plane's distance is `plane * inv_dir - offset`, with the
/// near and far offsets `origin * inv_dir` padded outwards.
///
/// Why padded: `round(origin * inv_dir)` is within `|oi| * eps / 2` of the
/// exact product; a pad of `2 |oi| eps` still exceeds that after the
/// offsets' own rounding. The FMA's single rounding is relative and within
/// the [`ROBUST_FAR`] margin, as the exact form's are. So the test never
/// misses a box the exact sub-and-multiply test enters (unit-tested
/// against it). Public so that the experiments in `benches/` use the same
/// constants as the library's kernel.
///
/// A zero far offset is `-0.0`, so that the far distances the AVX2
/// kernels compute (`plane * inv_dir - far_offset`) are `-0.0` only by
/// underflow: their integer ordering of distances (see `Avx2Tester`)
/// needs no other sign of zero.
#[derive(Clone, Copy, Debug)]
pub struct FmaSlab {
    pub inv_dir: Vec3,
    pub near_offset: Vec3,
    pub far_offset: Vec3,
    /// Index into [`WideNode::planes`] of each axis's near plane.
    pub near_plane: [usize; 3],
    /// Index into [`WideNode::planes`] of each axis's far plane.
    pub far_plane: [usize; 3],
}

impl FmaSlab {
    /// In four-lane vectors: one division for the three axes and one sign
    /// mask for the plane order ([`OCTANT_PLANES`]). Each lane's arithmetic
    /// is the per-axis one, so the constants are the same bits.
    #[inline(always)]
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        let inv_dir = Vec3A::ONE / Vec3A::from(dir);
        let (near_plane, far_plane) = OCTANT_PLANES[octant(inv_dir)];
        let oi = Vec3A::from(origin) * inv_dir;
        let pad = oi.abs() * (2.0 * f32::EPSILON);
        Self {
            inv_dir: inv_dir.into(),
            near_offset: (oi + pad).into(),
            // `oi - pad` as `-(pad - oi)`: the same bits, but `-0.0` where
            // it is zero, so that `plane * inv_dir - far_offset` is never
            // `-0.0` but by underflow (see `Avx2Tester::test_known`).
            far_offset: (-(pad - oi)).into(),
            near_plane,
            far_plane,
        }
    }

    /// False for a zero direction component (or an overflowing offset):
    /// such a ray needs the exact sub-and-multiply test with its NaN fix.
    #[inline(always)]
    pub fn is_finite(&self) -> bool {
        // `0 * x` is zero for a finite `x`, NaN for an infinite or NaN
        // one: one compare for the nine values.
        let z = |v: Vec3| Vec3A::from(v) * 0.0;
        (z(self.inv_dir) + z(self.near_offset) + z(self.far_offset))
            .cmpeq(Vec3A::ZERO)
            .all()
    }
}

/// For each direction octant (bit `a` set: `inv_dir[a]` negative, `-0.0`
/// included), the index into [`WideNode::planes`] of each axis's near and
/// far plane (Williams et al. 2005: the near plane of a negative axis is
/// the box's maximum).
///
/// `static`, not `const`: a `const` array indexed at run time is a value
/// LLVM may build anew at each use, and in one build of session 45 it
/// copied this table onto the stack for every ray (a 384-byte `memcpy`
/// call before each ray's walk: diffuse rays 2-18% slower).
static OCTANT_PLANES: [([usize; 3], [usize; 3]); 8] = octant_planes(1);

/// [`OCTANT_PLANES`] as byte offsets of the planes in an 8-wide node
/// (32 bytes each): what the AVX2 tester adds to a node's address.
/// (`static` for the reason [`OCTANT_PLANES`] is).
static OCTANT_PLANE_BYTES: [([usize; 3], [usize; 3]); 8] = octant_planes(32);

/// The row of the octant tables for a ray with these reciprocal direction
/// components: bit `a` is the sign bit of `inv_dir[a]`.
#[inline(always)]
fn octant(inv_dir: Vec3A) -> usize {
    inv_dir.is_negative_bitmask() as usize & 7
}

/// The octant table with plane indices times `scale`.
const fn octant_planes(scale: usize) -> [([usize; 3], [usize; 3]); 8] {
    let mut t = [([0; 3], [0; 3]); 8];
    let mut m = 0;
    while m < 8 {
        let mut a = 0;
        while a < 3 {
            let negative = m >> a & 1 == 1;
            t[m].0[a] = scale * if negative { a + 3 } else { a };
            t[m].1[a] = scale * if negative { a } else { a + 3 };
            a += 1;
        }
        m += 1;
    }
    t
}

/// Per-ray plane selection of the SIMD testers: the index into
/// [`WideNode::planes`] of each axis's near and far plane.
#[inline(always)]
fn plane_order(inv_dir: Vec3) -> ([usize; 3], [usize; 3]) {
    OCTANT_PLANES[octant(inv_dir.into())]
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod x86 {
    use core::arch::x86_64::*;

    use super::{BoxTester, ROBUST_FAR, plane_order};
    use crate::Ray;
    use crate::bvh::wide::WideNode;
    use glam::Vec3;

    /// Units in the last place the AVX2 kernels add to a far distance in
    /// place of the [`ROBUST_FAR`] product (see [`pad_far_bits`]).
    pub(crate) const FAR_PAD_ULPS: i32 = 7;

    /// `far` padded outwards by [`FAR_PAD_ULPS`] added to its bits (capped
    /// at `+inf`), at least `far * ROBUST_FAR` for every `far >= +0.0`:
    /// `ROBUST_FAR` is `1 + 3 * 2^-23` as an `f32`, so the product of a
    /// normal `far` with significand `m` in `[1, 2)` lies `3 m < 6` of its
    /// ulps above it and rounds to at most six (fewer where it crosses into
    /// the next binade, whose ulps are twice as large); a subnormal or zero
    /// `far` moves by less than one. A negative `far` stays negative (a box
    /// behind the ray, missed either way). Why: the integer add and `min`
    /// take one cycle each on the node test's latency chain, the product
    /// four on Intel cores (diffuse rays 1-4.5% faster, session 45), and
    /// the pad is at most 7 ulps, about 8e-7 of the distance, against the
    /// product's 3.6e-7: a box entered in addition lies within that of the
    /// ray's interval.
    ///
    /// # Safety
    /// The caller runs on a CPU of the AVX2 level.
    #[inline(always)]
    pub(crate) unsafe fn pad_far_bits(far: __m256) -> __m256 {
        // SAFETY: the caller's CPU has AVX2 (this function's contract).
        unsafe {
            let bits = _mm256_add_epi32(_mm256_castps_si256(far), _mm256_set1_epi32(FAR_PAD_ULPS));
            _mm256_castsi256_ps(_mm256_min_epi32(
                bits,
                _mm256_set1_epi32(f32::INFINITY.to_bits() as i32),
            ))
        }
    }

    /// Four lanes per step; any `W` that is a multiple of 4.
    #[derive(Clone, Copy)]
    pub(super) struct SseTester {
        origin: [__m128; 3],
        inv_dir: [__m128; 3],
        near: [usize; 3],
        far: [usize; 3],
        t_min: __m128,
        /// Some direction component is zero: NaN distances are possible.
        fix_nan: bool,
    }

    impl SseTester {
        /// # Safety
        /// Callers must run on a CPU with SSE4.1: the tester's existence is
        /// what [`SseTester::test`] relies on.
        ///
        /// Plain code (lane arrays cast to vectors), not a target-feature
        /// function, so that it can be `inline(always)`: when LLVM chose
        /// not to inline the target-feature version, every ray and every
        /// instance ray paid a call and a copy of the returned tester
        /// (engine shadow rays 25% slower after an unrelated change
        /// elsewhere in the crate moved the inlining budget).
        #[inline(always)]
        pub(super) unsafe fn new(origin: Vec3, dir: Vec3, t_min: f32) -> Self {
            let inv = Vec3::ONE / dir;
            let (near, far) = plane_order(inv);
            let splat = |x: f32| -> __m128 { bytemuck::cast([x; 4]) };
            Self {
                origin: [splat(origin.x), splat(origin.y), splat(origin.z)],
                inv_dir: [splat(inv.x), splat(inv.y), splat(inv.z)],
                near,
                far,
                t_min: splat(t_min),
                fix_nan: !inv.is_finite(),
            }
        }
    }

    impl<const W: usize> BoxTester<W> for SseTester {
        #[inline(always)]
        fn test(&self, node: &WideNode<W>, t_max: f32, dist: &mut [f32; W]) -> u32 {
            let planes = node.planes();
            let mut mask = 0u32;
            for g in 0..W / 4 {
                // SAFETY: an `SseTester` exists only on CPUs with SSE4.1 (its
                // constructor is a `target_feature` fn whose callers check
                // it); every load and store reads or writes four in-bounds
                // floats at `4 * g` of a `[f32; W]`, `W` a multiple of 4.
                unsafe {
                    let mut near = self.t_min;
                    let mut far = _mm_set1_ps(t_max);
                    for a in 0..3 {
                        let pn = _mm_loadu_ps(planes[self.near[a]].as_ptr().add(4 * g));
                        let pf = _mm_loadu_ps(planes[self.far[a]].as_ptr().add(4 * g));
                        let mut tn = _mm_mul_ps(_mm_sub_ps(pn, self.origin[a]), self.inv_dir[a]);
                        let mut tf = _mm_mul_ps(_mm_sub_ps(pf, self.origin[a]), self.inv_dir[a]);
                        if self.fix_nan {
                            let nan = _mm_cmpunord_ps(tn, tf);
                            tn = _mm_blendv_ps(tn, _mm_set1_ps(f32::NEG_INFINITY), nan);
                            tf = _mm_blendv_ps(tf, _mm_set1_ps(f32::INFINITY), nan);
                        }
                        near = _mm_max_ps(near, tn);
                        far = _mm_min_ps(far, tf);
                    }
                    far = _mm_mul_ps(far, _mm_set1_ps(ROBUST_FAR));
                    let hit = _mm_and_ps(
                        _mm_cmple_ps(near, far),
                        _mm_cmplt_ps(near, _mm_set1_ps(f32::INFINITY)),
                    );
                    _mm_storeu_ps(dist.as_mut_ptr().add(4 * g), near);
                    mask |= (_mm_movemask_ps(hit) as u32) << (4 * g);
                }
            }
            mask
        }
    }

    /// Eight lanes in one step, `W = 8`.
    #[derive(Clone, Copy)]
    pub(crate) struct Avx2Tester {
        inv_dir: [__m256; 3],
        /// Minus `origin * inv_dir` minus (near) or plus (far) a bound on
        /// its rounding error, per axis: the one-FMA distances
        /// `fma(plane, inv_dir, neg_offset)` then never exceed (near) or
        /// fall short of (far) the exact ones beyond what `ROBUST_FAR`
        /// covers. Stored negated: kept positive, LLVM stored both signs
        /// (a negation and a broadcast more per axis and ray). On the
        /// exact path (`exact`), minus the ray's origin instead: the
        /// tester is copied per instance entry, and three fewer vectors
        /// are three fewer broadcasts and stores per ray.
        neg_near_offset: [__m256; 3],
        neg_far_offset: [__m256; 3],
        /// Byte offset in [`WideNode`] of each axis's near and far plane
        /// (`plane_order`'s index times 32, so below 192: inside the six
        /// planes). Stored premultiplied: callgrind showed the index loaded
        /// and shifted for each of the six plane loads of every node.
        near: [usize; 3],
        far: [usize; 3],
        t_min: __m256,
        /// Some `inv_dir` or offset is not finite (a zero direction
        /// component), or `t_min` has its sign bit set (the fast path's
        /// integer ordering needs `t_min >= +0.0`): this ray takes the
        /// exact sub-and-multiply test with the NaN fix, as `hit_node` and
        /// the SSE kernel do.
        exact: bool,
    }

    impl Avx2Tester {
        /// # Safety
        /// Callers must run on a CPU of the AVX2 level (see
        /// [`SseTester::new`], also for why this is not a target-feature
        /// function).
        ///
        /// The constants are [`super::FmaSlab::new`]'s bit for bit (the same
        /// lane arithmetic: one division, a product, the pad, a sum and a
        /// difference; `-x` is a sign flip either way), computed on the
        /// ray's two 16-byte halves as loaded (glam's three-lane vectors
        /// cost shuffles at every conversion). Only baseline SSE2
        /// intrinsics and plain arrays for the broadcasts: LLVM sometimes
        /// compiles a closure that makes a tester out of line, without the
        /// kernel's features (`Option::get_or_insert_with` for an
        /// instance's tester), and an AVX intrinsic there becomes a call
        /// per use (cocoa temple diffuse +3% instructions, session 20).
        #[inline(always)]
        pub(crate) unsafe fn new(ray: &Ray) -> Self {
            // SAFETY: SSE2 (every x86-64 CPU). The loads read 16 bytes
            // at offsets 0 and 16 of a 32-byte `repr(C)` `Ray`: `origin`
            // then `t_min`, `dir` then `t_max`. Lane 3 (`t_min`, `t_max`
            // and what follows from them) is never read: the masks keep
            // bits 0..=2 and the broadcasts take lanes 0..=2.
            unsafe {
                let base = (ray as *const Ray).cast::<f32>();
                let origin = _mm_loadu_ps(base);
                let dir = _mm_loadu_ps(base.add(4));
                let sign = _mm_set1_ps(-0.0);
                let inv_dir = _mm_div_ps(_mm_set1_ps(1.0), dir);
                let oi = _mm_mul_ps(origin, inv_dir);
                let pad = _mm_mul_ps(_mm_andnot_ps(sign, oi), _mm_set1_ps(2.0 * f32::EPSILON));
                let near_offset = _mm_add_ps(oi, pad);
                // `-(pad - oi)` is `FmaSlab`'s far offset (`-0.0` when
                // zero); kept negated, it is `pad - oi`.
                let neg_far_offset = _mm_sub_ps(pad, oi);
                // `FmaSlab::is_finite`: `0 * x` is NaN exactly for a
                // non-finite `x`.
                let zero = _mm_setzero_ps();
                let z = |v: __m128| _mm_mul_ps(v, zero);
                let sum = _mm_add_ps(_mm_add_ps(z(inv_dir), z(near_offset)), z(neg_far_offset));
                // A `t_min` with its sign bit set (negative, or `-0.0`)
                // takes the exact path too: the fast path orders distances
                // as integers, which needs `t_min >= +0.0` (see
                // `test_known`).
                let exact = _mm_movemask_ps(_mm_cmpeq_ps(sum, zero)) & 7 != 7
                    || ray.t_min.is_sign_negative();
                let octant = (_mm_movemask_ps(inv_dir) & 7) as usize;
                let (near, far) = super::OCTANT_PLANE_BYTES[octant];
                let splat = |v: __m128| -> [__m256; 3] {
                    let l: [f32; 4] = bytemuck::cast(v);
                    [
                        bytemuck::cast([l[0]; 8]),
                        bytemuck::cast([l[1]; 8]),
                        bytemuck::cast([l[2]; 8]),
                    ]
                };
                let near_or_origin = if exact { origin } else { near_offset };
                Self {
                    inv_dir: splat(inv_dir),
                    neg_near_offset: splat(_mm_xor_ps(near_or_origin, sign)),
                    neg_far_offset: splat(neg_far_offset),
                    near,
                    far,
                    t_min: bytemuck::cast([ray.t_min; 8]),
                    exact,
                }
            }
        }

        /// Lane 0 of each constant vector (`inv_dir`, the negated near and
        /// far offsets), the plane offsets and the exact flag, after
        /// checking that every vector holds one value in all eight lanes.
        #[cfg(test)]
        #[allow(clippy::type_complexity)]
        pub(crate) fn constants(&self) -> ([[f32; 3]; 3], [usize; 3], [usize; 3], f32, bool) {
            let lane0 = |v: __m256| {
                let l: [f32; 8] = bytemuck::cast(v);
                assert!(l.iter().all(|x| x.to_bits() == l[0].to_bits()), "{l:?}");
                l[0]
            };
            let three = |v: &[__m256; 3]| v.map(lane0);
            (
                [
                    three(&self.inv_dir),
                    three(&self.neg_near_offset),
                    three(&self.neg_far_offset),
                ],
                self.near,
                self.far,
                lane0(self.t_min),
                self.exact,
            )
        }
    }

    impl BoxTester<8> for Avx2Tester {
        #[inline(always)]
        fn test(&self, node: &WideNode<8>, t_max: f32, dist: &mut [f32; 8]) -> u32 {
            if self.exact {
                self.test_known::<true>(node, t_max, dist)
            } else {
                self.test_known::<false>(node, t_max, dist)
            }
        }

        #[inline(always)]
        fn exact(&self) -> bool {
            self.exact
        }

        // The axis index picks from four per-axis arrays at once.
        #[allow(clippy::needless_range_loop)]
        #[inline(always)]
        fn test_known<const EXACT: bool>(
            &self,
            node: &WideNode<8>,
            t_max: f32,
            dist: &mut [f32; 8],
        ) -> u32 {
            debug_assert_eq!(EXACT, self.exact);
            let planes = node.planes().as_ptr().cast::<u8>();
            debug_assert!(
                self.near
                    .iter()
                    .chain(&self.far)
                    .all(|&o| o < 192 && o % 32 == 0)
            );
            // SAFETY: an `Avx2Tester` exists only on CPUs of the AVX2 level
            // (see `Avx2Tester::new`); each load and the store cover exactly
            // one `[f32; 8]`: the plane loads read the 32-byte plane at a
            // private offset below 192 in steps of 32 (`Avx2Tester::new`),
            // one of the node's six planes.
            unsafe {
                let plane = |off: usize| _mm256_loadu_ps(planes.add(off).cast::<f32>());
                let mut near = self.t_min;
                // `+ 0.0` turns a `-0.0` (a hit at `t = -0.0`) into `+0.0`,
                // as the integer compare below needs; off the node's
                // latency chain (`t_max` is known before the node loads).
                let mut far = _mm256_set1_ps(t_max + 0.0);
                if EXACT {
                    // `neg_near_offset` holds minus the origin on this
                    // path: `p + (-o)` is `p - o`, bit for bit.
                    let neg_origin = &self.neg_near_offset;
                    for a in 0..3 {
                        let pn = plane(self.near[a]);
                        let pf = plane(self.far[a]);
                        let mut tn =
                            _mm256_mul_ps(_mm256_add_ps(pn, neg_origin[a]), self.inv_dir[a]);
                        let mut tf =
                            _mm256_mul_ps(_mm256_add_ps(pf, neg_origin[a]), self.inv_dir[a]);
                        let nan = _mm256_cmp_ps::<_CMP_UNORD_Q>(tn, tf);
                        tn = _mm256_blendv_ps(tn, _mm256_set1_ps(f32::NEG_INFINITY), nan);
                        tf = _mm256_blendv_ps(tf, _mm256_set1_ps(f32::INFINITY), nan);
                        near = _mm256_max_ps(near, tn);
                        far = _mm256_min_ps(far, tf);
                    }
                } else {
                    // The distances ordered as integers: `vpmaxsd` and
                    // `vpminsd` take one cycle where `vmaxps`/`vminps` take
                    // four on Intel cores (one on AMD's Zen), and a tree of
                    // two levels instead of a chain of three, as Embree's
                    // AVX2 BVH8 test does (`maxi`/`mini` over the three
                    // axes and the ray's interval). The same values as the
                    // float `max`/`min`: `t_min` is at least `+0.0` here
                    // (a sign bit takes the exact path), the non-negative
                    // floats order as their bits do, and every negative
                    // float (its bits a negative integer) is below them,
                    // so `near` is the float maximum; `far` is the float
                    // minimum whenever that is non-negative, and negative
                    // whenever that is (the box then lies behind the ray
                    // and is missed either way).
                    let tn = |a: usize| {
                        _mm256_castps_si256(_mm256_fmadd_ps(
                            plane(self.near[a]),
                            self.inv_dir[a],
                            self.neg_near_offset[a],
                        ))
                    };
                    let tf = |a: usize| {
                        _mm256_castps_si256(_mm256_fmadd_ps(
                            plane(self.far[a]),
                            self.inv_dir[a],
                            self.neg_far_offset[a],
                        ))
                    };
                    let n01 = _mm256_max_epi32(tn(0), tn(1));
                    let n2 = _mm256_max_epi32(tn(2), _mm256_castps_si256(near));
                    near = _mm256_castsi256_ps(_mm256_max_epi32(n01, n2));
                    let f01 = _mm256_min_epi32(tf(0), tf(1));
                    let f2 = _mm256_min_epi32(tf(2), _mm256_castps_si256(far));
                    far = _mm256_castsi256_ps(_mm256_min_epi32(f01, f2));
                }
                far = if EXACT {
                    _mm256_mul_ps(far, _mm256_set1_ps(ROBUST_FAR))
                } else {
                    pad_far_bits(far)
                };
                // `near < inf` only matters on the exact path (a zero
                // direction component can make both distances `+inf`); the
                // FMA path's finite constants give an empty slot `+inf`
                // and `-inf`. There, `near` is `+inf` only for a box beyond
                // the `f32` range of an unbounded ray, where no hit can lie:
                // entering it costs a test, never an answer.
                //
                // The fast path compares as integers too (one cycle against
                // four): `near` is non-negative, so `near <= far` holds as
                // integers exactly when it holds as floats, except where
                // the far distance before its pad was `-0.0` (as a float
                // compare `0 <= -0.0` holds; padded on its bits it is a
                // negative integer). `t_max` is made `+0.0` above and the
                // far offsets are never `-0.0` (`FmaSlab`), so such a
                // distance comes only from one below zero that underflowed:
                // a box wholly behind the ray's origin, where no hit at
                // `t >= 0` lies.
                let mut hit = if EXACT {
                    _mm256_cmp_ps::<_CMP_LE_OQ>(near, far)
                } else {
                    // `far > near - 1`, which is `near <= far` for the
                    // non-negative `near` (no wrap): the hit mask itself,
                    // with no inversion after the compare on the chain
                    // (diffuse rays 0.6-1.9% faster than `!(near > far)`,
                    // session 45).
                    let below = _mm256_sub_epi32(_mm256_castps_si256(near), _mm256_set1_epi32(1));
                    _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_castps_si256(far), below))
                };
                if EXACT {
                    hit = _mm256_and_ps(
                        hit,
                        _mm256_cmp_ps::<_CMP_LT_OQ>(near, _mm256_set1_ps(f32::INFINITY)),
                    );
                }
                _mm256_storeu_ps(dist.as_mut_ptr(), near);
                _mm256_movemask_ps(hit) as u32
            }
        }
    }
}

/// Prefetch the cache lines of wide node `r` (nothing for a leaf or an
/// empty slot): for each hit child of a node with two or more hits, as it
/// leaves the hit mask (see `traverse_loop`), so that its node is in the
/// first-level cache when it is taken or popped, as Embree's BVH8
/// traversal prefetches the children it keeps. Prefetching at all, then
/// only the pushed children after the sort, was measured in session 16
/// (fastest of 15 alternations per binary, one thread, 480x270, against
/// no prefetch):
/// re-braided 0.996-1.019 on five shared scenes and the library (diffuse
/// +0.1% to +1.6%), flat primary and shadow rays +3% to +11% (presumably
/// the rays that go on alone from their packets, through this loop); see
/// `docs/performance.md`, session 16.
#[inline(always)]
fn prefetch_node<const W: usize>(nodes: &[WideNode<W>], r: u32) {
    #[cfg(target_arch = "x86_64")]
    if !is_leaf_ref(r) {
        use core::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let p = nodes.as_ptr().wrapping_add(r as usize).cast::<i8>();
        let size = std::mem::size_of::<WideNode<W>>();
        let mut off = 0;
        while off < size {
            // SAFETY: a prefetch never faults, whatever the address.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(off)) };
            off += 64;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (nodes, r);
}

/// The traversal loop shared by every kernel, from wide node `start` (whose
/// box the caller has tested). `leaf(first, count, t_max)` handles a leaf's
/// primitive slots, may shrink `t_max` (closest hit) and returns `true` to
/// stop (any hit).
#[inline(always)]
fn traverse<const W: usize, const ANY: bool, B, L>(
    nodes: &[WideNode<W>],
    tester: &B,
    start: u32,
    t_max: f32,
    counters: &mut TraversalCounters,
    leaf: L,
) where
    B: BoxTester<W>,
    L: FnMut(u32, u32, &mut f32) -> bool,
{
    // Unswitched on the tester's rare path: the AVX2 node test branched
    // on it at every node. Unswitched, 0.6-2.1% fewer instructions per
    // re-braided diffuse ray and 2.1-3.7% per flat one on the shared
    // scenes (samurai flat 785.9 -> 757.1, callgrind; docs/performance.md,
    // session 22).
    if tester.exact() {
        traverse_loop::<W, ANY, true, B, L>(nodes, tester, start, t_max, counters, leaf)
    } else {
        traverse_loop::<W, ANY, false, B, L>(nodes, tester, start, t_max, counters, leaf)
    }
}

/// [`traverse`]'s loop for a tester whose [`BoxTester::exact`] is `EXACT`.
#[inline(always)]
fn traverse_loop<const W: usize, const ANY: bool, const EXACT: bool, B, L>(
    nodes: &[WideNode<W>],
    tester: &B,
    start: u32,
    mut t_max: f32,
    counters: &mut TraversalCounters,
    mut leaf: L,
) where
    B: BoxTester<W>,
    L: FnMut(u32, u32, &mut f32) -> bool,
{
    let mut stack = [MaybeUninit::<(u32, f32)>::uninit(); WIDE_STACK];
    let mut sp = 0usize;
    let mut current = start;
    loop {
        if is_leaf_ref(current) {
            counters.leaves_visited += 1;
            let (first, count) = decode_leaf(current);
            if leaf(first, count, &mut t_max) {
                return;
            }
        } else {
            counters.inner_visited += 1;
            let node = &nodes[current as usize];
            let mut dist = [0.0f32; W];
            let mut mask = tester.test_known::<EXACT>(node, t_max, &mut dist);
            if mask != 0 {
                let i = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                if mask == 0 {
                    current = node.child[i];
                    continue;
                }
                if ANY {
                    // Occlusion: any hit ends the query, so sorting does
                    // not pay (measured, see docs/performance.md): visit
                    // the hit children in slot order, the first now and
                    // the others pushed so that they pop in ascending order.
                    let first = node.child[i];
                    while mask != 0 {
                        let j = 31 - mask.leading_zeros() as usize;
                        mask &= !(1 << j);
                        stack[sp].write((node.child[j], dist[j]));
                        sp += 1;
                    }
                    current = first;
                    continue;
                }
                // Two hits (the most common case after one): go to the
                // nearer, push the other; equal distances keep slot order, as
                // the sort below does. Counted with callgrind: the sort's
                // array traffic cost about 8 instructions more per such node
                // (samurai diffuse, flat: 1,061 -> 1,048 per ray).
                let j = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                // Both children prefetched as they leave the hit mask,
                // before their distances are read back and compared, as
                // Embree's BVH8 traversal does: the node taken next starts
                // its trip from memory a comparison earlier, and the one
                // pushed is on its way when popped. Against prefetching
                // only the pushed children, after the sort (one thread,
                // 480x270, medians of 8-10 rounds, controls within 1%):
                // diffuse rays +0.5% to +4.4% re-braided and +1% to +6%
                // flat on six shared scenes, primary and shadow rays
                // within 1.2% (docs/performance.md, session 24).
                prefetch_node(nodes, node.child[i]);
                prefetch_node(nodes, node.child[j]);
                let (near, far) = if dist[j] < dist[i] { (j, i) } else { (i, j) };
                if mask == 0 {
                    stack[sp].write((node.child[far], dist[far]));
                    sp += 1;
                    current = node.child[near];
                    continue;
                }
                // Three or more: insertion-sort them by entry distance
                // (stable, so equal distances keep slot order), push all but
                // the nearest, farthest first, and go to the nearest.
                // Uninitialised: zeroing 64 bytes per node showed in profiles.
                let mut hits = [MaybeUninit::<(f32, u32)>::uninit(); W];
                hits[0].write((dist[near], node.child[near]));
                hits[1].write((dist[far], node.child[far]));
                let mut n = 2;
                while mask != 0 {
                    let i = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    let item = (dist[i], node.child[i]);
                    prefetch_node(nodes, item.1);
                    let mut j = n;
                    // SAFETY: `hits[..n]` are written (`n` grows only after
                    // a write at or below it).
                    while j > 0 && unsafe { hits[j - 1].assume_init().0 } > item.0 {
                        hits[j] = hits[j - 1];
                        j -= 1;
                    }
                    hits[j].write(item);
                    n += 1;
                }
                for h in hits[1..n].iter().rev() {
                    // SAFETY: as above, `hits[..n]` are written.
                    let (d, r) = unsafe { h.assume_init() };
                    stack[sp].write((r, d));
                    sp += 1;
                }
                // SAFETY: `hits[0]` was written first.
                current = unsafe { hits[0].assume_init().1 };
                continue;
            }
        }
        // Pop, skipping entries a shrunken t_max now culls (the same test
        // as the binary traversal's).
        loop {
            if sp == 0 {
                return;
            }
            sp -= 1;
            // SAFETY: entries below `sp` were all written by the push above
            // (`sp` only grows by writing `stack[sp]`).
            let (r, d) = unsafe { stack[sp].assume_init() };
            // An any-hit query never shrinks `t_max`: nothing to cull.
            if ANY || d <= t_max * ROBUST_FAR {
                current = r;
                break;
            }
        }
    }
}

/// A wide BVH over one mesh, collapsed from a [`MeshBvh`].
///
/// It owns a copy of the leaf-order triangles and primitive ids rather than
/// borrowing the `MeshBvh`: no lifetime parameter for the scene and the top
/// level to carry later, and the copy (40 bytes per triangle) is cheap next
/// to the build; the binary tree may be dropped afterwards.
#[derive(Clone, Debug)]
pub struct WideMeshBvh<const W: usize> {
    /// The wide tree; its leaves name ranges of `blocks`.
    pub wide: WideBvh<W>,
    /// The leaves' triangles, four to a block.
    pub blocks: Vec<Triangle4>,
    /// Vertices of each triangle, in the binary tree's leaf order (what
    /// validation checks the blocks against; hits read the blocks).
    pub triangles: Vec<[Vec3; 3]>,
    /// Mesh primitive id of each leaf-order slot (for validation).
    pub prim_indices: Vec<u32>,
    /// Private so that it always names a kernel this CPU runs.
    kernel: Kernel,
}

impl<const W: usize> WideMeshBvh<W> {
    /// Collapse the mesh BVH's tree (see [`WideBvh::from_bvh`]) and copy its
    /// triangles; the kernel is [`Kernel::best`].
    pub fn from_mesh(mesh: &MeshBvh) -> Result<Self, Error> {
        let mut wide = WideBvh::from_bvh(&mesh.bvh)?;
        let blocks = pack_triangle4(&mut wide, &mesh.triangles, &mesh.bvh.prim_indices);
        Ok(Self {
            wide,
            blocks,
            triangles: mesh.triangles.clone(),
            prim_indices: mesh.bvh.prim_indices.clone(),
            kernel: Kernel::best(),
        })
    }

    /// The kernel [`WideMeshBvh::intersect`] and friends use.
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// Use `kernel` from now on; fails when this CPU cannot run it.
    pub fn set_kernel(&mut self, kernel: Kernel) -> Result<(), Error> {
        if !kernel.is_available() {
            return Err(Error::InvalidParameter(format!(
                "kernel {kernel:?} is not supported by this CPU"
            )));
        }
        self.kernel = kernel;
        Ok(())
    }

    #[inline]
    pub fn len(&self) -> usize {
        self.triangles.len()
    }

    #[inline]
    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Closest hit along the ray, if any.
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        self.query::<false>(self.kernel, ray)
            .map(|h| self.make_hit(h))
    }

    /// True when anything is hit within `[t_min, t_max]`.
    #[inline]
    pub fn occluded(&self, ray: &Ray) -> bool {
        self.query::<true>(self.kernel, ray).is_some()
    }

    /// [`WideMeshBvh::intersect`] with a given kernel (panics if this CPU
    /// cannot run it): for tests and benchmarks.
    pub fn intersect_with(&self, kernel: Kernel, ray: &Ray) -> Option<Hit> {
        assert!(kernel.is_available(), "{kernel:?} is not available");
        self.query::<false>(kernel, ray).map(|h| self.make_hit(h))
    }

    /// [`WideMeshBvh::occluded`] with a given kernel (panics if this CPU
    /// cannot run it).
    pub fn occluded_with(&self, kernel: Kernel, ray: &Ray) -> bool {
        assert!(kernel.is_available(), "{kernel:?} is not available");
        self.query::<true>(kernel, ray).is_some()
    }

    /// Closest hits of many rays, in parallel; `out[i]` answers `rays[i]`.
    pub fn intersect_batch(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        crate::ray::par_query(rays, out, |r| self.intersect(r));
    }

    /// Occlusion of many rays, in parallel; `out[i]` answers `rays[i]`.
    pub fn occluded_batch(&self, rays: &[Ray], out: &mut [bool]) {
        crate::ray::par_query(rays, out, |r| self.occluded(r));
    }

    /// Node statistics; `bytes` adds the blocks, triangles and primitive
    /// ids.
    pub fn stats(&self) -> WideStats {
        let mut s = self.wide.stats();
        s.bytes += std::mem::size_of_val(self.blocks.as_slice())
            + std::mem::size_of_val(self.triangles.as_slice())
            + std::mem::size_of_val(self.prim_indices.as_slice());
        s
    }

    /// Validate the wide tree against the triangles it stores.
    pub fn validate(&self) -> Result<(), String> {
        if self.prim_indices.len() != self.triangles.len() {
            return Err("primitive ids and triangles differ in number".into());
        }
        validate_blocks(&self.blocks, &self.triangles, &self.prim_indices)?;
        self.wide.validate(&block_boxes(
            &self.blocks,
            &self.triangles,
            &self.prim_indices,
        ))
    }

    fn make_hit(&self, (t, u, v, k): LeafHit) -> Hit {
        let (prim_id, normal) = block_hit_record(&self.blocks, k);
        Hit::on_mesh(t, u, v, prim_id, normal)
    }

    /// The closest (or, with `ANY`, some) hit as (t, u, v, block lane).
    /// `kernel` must be available (checked by every caller).
    #[inline(always)]
    fn query<const ANY: bool>(&self, kernel: Kernel, ray: &Ray) -> Option<LeafHit> {
        // No separate root-box test: the root's children are tested at once
        // by the kernel (the scalar test and its three divisions cost 15%
        // of a coherent ray, `cargo bench -p rebraid --bench quantized`).
        if !ray.is_valid() || self.wide.is_empty() {
            return None;
        }
        match kernel {
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 if W == 8 => {
                // SAFETY: `kernel` is available (callers check it), so the
                // CPU has the AVX2 level.
                unsafe { self.query_avx2::<ANY>(ray) }
            }
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse | Kernel::Avx2 => {
                // SAFETY: `kernel` is available; AVX2 CPUs have SSE4.1 too.
                unsafe { self.query_sse::<ANY>(ray) }
            }
            _ => {
                let tester = ScalarTester {
                    ray: BoxRay::new(ray.origin, ray.dir),
                    t_min: ray.t_min,
                };
                self.run::<ANY, _>(&tester, ray)
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "sse4.1")]
    fn query_sse<const ANY: bool>(&self, ray: &Ray) -> Option<LeafHit> {
        // SAFETY: this function runs only on CPUs with SSE4.1.
        let tester = unsafe { x86::SseTester::new(ray.origin, ray.dir, ray.t_min) };
        self.run::<ANY, _>(&tester, ray)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
    fn query_avx2<const ANY: bool>(&self, ray: &Ray) -> Option<LeafHit> {
        // SAFETY: this function runs only on CPUs of the AVX2 level.
        let tester = unsafe { x86::Avx2Tester::new(ray) };
        // `W == 8` on this path (see `query`); the cast is a no-op then.
        let nodes: &[WideNode<8>] = {
            assert_eq!(W, 8);
            // SAFETY: `W == 8`, so `WideNode<W>` and `WideNode<8>` are the
            // same type.
            unsafe {
                std::slice::from_raw_parts(
                    self.wide.nodes.as_ptr() as *const WideNode<8>,
                    self.wide.nodes.len(),
                )
            }
        };
        run_on::<8, ANY, _>(
            nodes,
            &self.blocks,
            &tester,
            ray,
            0,
            ray.t_max,
            &mut TraversalCounters::default(),
        )
    }

    #[inline(always)]
    fn run<const ANY: bool, B: BoxTester<W>>(&self, tester: &B, ray: &Ray) -> Option<LeafHit> {
        run_on::<W, ANY, B>(
            &self.wide.nodes,
            &self.blocks,
            tester,
            ray,
            0,
            ray.t_max,
            &mut TraversalCounters::default(),
        )
    }
}

/// One query over a wide tree whose leaves name [`Triangle4`] blocks (the
/// same answers and tie rule as [`MeshBvh::intersect_leaf`] and
/// [`MeshBvh::occluded_leaf`]).
#[inline(always)]
fn run_on<const W: usize, const ANY: bool, B: BoxTester<W>>(
    nodes: &[WideNode<W>],
    blocks: &[Triangle4],
    tester: &B,
    ray: &Ray,
    start: u32,
    t_max: f32,
    counters: &mut TraversalCounters,
) -> Option<LeafHit> {
    let wray = WatertightRay::new(ray.origin, ray.dir);
    subtree_with::<W, ANY, B>(
        nodes, blocks, tester, &wray, ray.t_min, start, t_max, counters,
    )
}

/// [`query_subtree`] with a caller's tester and prepared watertight ray,
/// for any width: the one leaf loop of every wide query over triangles.
#[allow(clippy::too_many_arguments)] // the hot path: plain values
#[inline(always)]
pub fn subtree_with<const W: usize, const ANY: bool, B: BoxTester<W>>(
    nodes: &[WideNode<W>],
    blocks: &[Triangle4],
    tester: &B,
    wray: &WatertightRay,
    t_min: f32,
    start: u32,
    t_max: f32,
    counters: &mut TraversalCounters,
) -> Option<LeafHit> {
    let mut best: Option<LeafHit> = None;
    traverse::<W, ANY, _, _>(
        nodes,
        tester,
        start,
        t_max,
        counters,
        #[inline(always)]
        |first, count, t_max| {
            intersect_blocks::<ANY>(
                blocks,
                wray,
                t_min,
                first,
                count,
                t_max,
                &mut best,
                B::SIMD_TRIANGLES,
            )
        },
    );
    best
}

/// Traverse an 8-wide tree from node `start` (whose box the caller has
/// tested) with `kernel`, near children first, calling `leaf(first, count,
/// t_max)` for each leaf the ray segment `[ray.t_min, t_max]` enters; the
/// callback may shrink `t_max` (closest hit) and returns `true` to stop.
/// With `ANY` (occlusion) children are visited in slot order instead, and
/// the callback must not shrink `t_max`. The top level (leaves are refs) and the object level (leaves are
/// triangles) both run through this. An unavailable `kernel` falls back to
/// the scalar one.
#[inline]
pub fn traverse_wide<const ANY: bool, L>(
    nodes: &[WideNode<8>],
    kernel: Kernel,
    start: u32,
    ray: &Ray,
    t_max: f32,
    counters: &mut TraversalCounters,
    leaf: L,
) where
    L: FnMut(u32, u32, &mut f32) -> bool,
{
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx2 if kernel.is_available() => {
            // SAFETY: the CPU has the AVX2 level (checked just above).
            unsafe { traverse_avx2::<ANY, _>(nodes, start, ray, t_max, counters, leaf) }
        }
        #[cfg(target_arch = "x86_64")]
        Kernel::Sse | Kernel::Avx2 if Kernel::Sse.is_available() => {
            // SAFETY: the CPU has SSE4.1 (checked just above).
            unsafe { traverse_sse::<ANY, _>(nodes, start, ray, t_max, counters, leaf) }
        }
        _ => {
            let tester = ScalarTester {
                ray: BoxRay::new(ray.origin, ray.dir),
                t_min: ray.t_min,
            };
            traverse::<8, ANY, _, _>(nodes, &tester, start, t_max, counters, leaf)
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
fn traverse_avx2<const ANY: bool, L: FnMut(u32, u32, &mut f32) -> bool>(
    nodes: &[WideNode<8>],
    start: u32,
    ray: &Ray,
    t_max: f32,
    counters: &mut TraversalCounters,
    leaf: L,
) {
    // SAFETY: this function runs only on CPUs of the AVX2 level.
    let tester = unsafe { x86::Avx2Tester::new(ray) };
    traverse::<8, ANY, _, _>(nodes, &tester, start, t_max, counters, leaf)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "sse4.1")]
fn traverse_sse<const ANY: bool, L: FnMut(u32, u32, &mut f32) -> bool>(
    nodes: &[WideNode<8>],
    start: u32,
    ray: &Ray,
    t_max: f32,
    counters: &mut TraversalCounters,
    leaf: L,
) {
    // SAFETY: this function runs only on CPUs with SSE4.1.
    let tester = unsafe { x86::SseTester::new(ray.origin, ray.dir, ray.t_min) };
    traverse::<8, ANY, _, _>(nodes, &tester, start, t_max, counters, leaf)
}

/// Makes one kernel's box tester for a ray. A two-level traversal gets a
/// factory through [`with_kernel`] and runs entirely inside that kernel's
/// target-feature context, making testers for the world ray and for each
/// instance's object-space ray only (not one per top-level leaf).
pub trait TesterFactory {
    type Tester: BoxTester<8> + Copy;
    fn make(&self, ray: &Ray) -> Self::Tester;

    /// The ray's watertight form for the leaf tests, made as this kernel's
    /// context allows: [`WatertightRay::new`] bit for bit (the AVX2
    /// kernel's [`WatertightRay::new_avx`] permutes lanes instead of
    /// indexing arrays by the axes).
    #[inline(always)]
    fn watertight(&self, ray: &Ray) -> WatertightRay {
        WatertightRay::new(ray.origin, ray.dir)
    }
}

/// A query run by [`with_kernel`] with the factory of the chosen kernel.
pub trait WideQuery {
    fn run<F: TesterFactory>(&mut self, factory: &F);
}

struct ScalarFactory;

impl TesterFactory for ScalarFactory {
    type Tester = ScalarTester;
    #[inline(always)]
    fn make(&self, ray: &Ray) -> ScalarTester {
        ScalarTester {
            ray: BoxRay::new(ray.origin, ray.dir),
            t_min: ray.t_min,
        }
    }
}

#[cfg(target_arch = "x86_64")]
struct SseFactory;

#[cfg(target_arch = "x86_64")]
impl TesterFactory for SseFactory {
    type Tester = x86::SseTester;
    #[inline(always)]
    fn make(&self, ray: &Ray) -> x86::SseTester {
        // SAFETY: an `SseFactory` exists only inside `run_sse`, which runs
        // only on CPUs with SSE4.1 (checked by `with_kernel`).
        unsafe { x86::SseTester::new(ray.origin, ray.dir, ray.t_min) }
    }
}

/// The AVX2 kernel's tester factory. Only this module makes one (the
/// private field), and only inside AVX2 target-feature functions
/// ([`run_avx2`], [`with_avx2`]) on CPUs of the AVX2 level.
#[cfg(target_arch = "x86_64")]
pub(crate) struct Avx2Factory(());

#[cfg(target_arch = "x86_64")]
impl TesterFactory for Avx2Factory {
    type Tester = x86::Avx2Tester;
    #[inline(always)]
    fn make(&self, ray: &Ray) -> x86::Avx2Tester {
        // SAFETY: an `Avx2Factory` exists only inside `run_avx2` and
        // `with_avx2`, which run only on CPUs of the AVX2 level (checked by
        // `with_kernel` and `with_avx2`).
        unsafe { x86::Avx2Tester::new(ray) }
    }

    #[inline(always)]
    fn watertight(&self, ray: &Ray) -> WatertightRay {
        // SAFETY: as in `make`: an `Avx2Factory` exists only on CPUs of the
        // AVX2 level, which includes AVX.
        unsafe { WatertightRay::new_avx(ray) }
    }
}

/// Run `f` inside the AVX2 kernel's target-feature context with its
/// tester factory (for code that needs more of AVX2 than a box tester,
/// such as packet traversal); `None` when the CPU lacks the AVX2 level.
#[cfg(target_arch = "x86_64")]
#[inline]
pub(crate) fn with_avx2<R>(f: impl FnOnce(&Avx2Factory) -> R) -> Option<R> {
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
    fn run<R>(f: impl FnOnce(&Avx2Factory) -> R) -> R {
        f(&Avx2Factory(()))
    }
    if !Kernel::Avx2.is_available() {
        return None;
    }
    // SAFETY: the CPU has the AVX2 level (checked just above).
    Some(unsafe { run(f) })
}

/// Run `query` with `kernel`'s tester factory, inside that kernel's
/// target-feature context (an unavailable kernel falls back to scalar).
#[inline]
pub fn with_kernel<Q: WideQuery>(kernel: Kernel, query: &mut Q) {
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx2 if kernel.is_available() => {
            // SAFETY: the CPU has the AVX2 level (checked just above).
            unsafe { run_avx2(query) }
        }
        #[cfg(target_arch = "x86_64")]
        Kernel::Sse | Kernel::Avx2 if Kernel::Sse.is_available() => {
            // SAFETY: the CPU has SSE4.1 (checked just above).
            unsafe { run_sse(query) }
        }
        _ => query.run(&ScalarFactory),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
fn run_avx2<Q: WideQuery>(query: &mut Q) {
    query.run(&Avx2Factory(()))
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "sse4.1")]
fn run_sse<Q: WideQuery>(query: &mut Q) {
    query.run(&SseFactory)
}

/// [`traverse_wide`] with a caller's tester (inside [`WideQuery::run`]).
#[inline(always)]
pub fn traverse_with<const ANY: bool, B, L>(
    nodes: &[WideNode<8>],
    tester: &B,
    start: u32,
    t_max: f32,
    counters: &mut TraversalCounters,
    leaf: L,
) where
    B: BoxTester<8>,
    L: FnMut(u32, u32, &mut f32) -> bool,
{
    traverse::<8, ANY, _, _>(nodes, tester, start, t_max, counters, leaf)
}

/// Closest (or, with `ANY`, some) hit within `[ray.t_min, t_max]` in the
/// subtree of node `start` of an 8-wide tree whose leaves name `blocks`,
/// as (t, u, v, leaf-order slot), counting visited nodes. The caller has
/// tested `start`'s box (a top-level leaf entering an object BVH).
#[inline]
pub fn query_subtree<const ANY: bool>(
    nodes: &[WideNode<8>],
    blocks: &[Triangle4],
    kernel: Kernel,
    start: u32,
    ray: &Ray,
    t_max: f32,
    counters: &mut TraversalCounters,
) -> Option<LeafHit> {
    let wray = WatertightRay::new(ray.origin, ray.dir);
    let t_min = ray.t_min;
    let simd = kernel != Kernel::Scalar;
    let mut best: Option<LeafHit> = None;
    traverse_wide::<ANY, _>(
        nodes,
        kernel,
        start,
        ray,
        t_max,
        counters,
        #[inline(always)]
        |first, count, t_max| {
            intersect_blocks::<ANY>(blocks, &wray, t_min, first, count, t_max, &mut best, simd)
        },
    );
    best
}

/// One ray's query from the root of an 8-wide triangle tree with the
/// kernel's tester and watertight ray (the ray valid, the tree not empty):
/// the single-ray body of the batch queries.
#[inline(always)]
fn query_root<const ANY: bool, F: TesterFactory>(
    nodes: &[WideNode<8>],
    blocks: &[Triangle4],
    factory: &F,
    ray: &Ray,
) -> Option<LeafHit> {
    let wray = factory.watertight(ray);
    subtree_with::<8, ANY, F::Tester>(
        nodes,
        blocks,
        &factory.make(ray),
        &wray,
        ray.t_min,
        0,
        ray.t_max,
        &mut TraversalCounters::default(),
    )
}

/// [`query_subtree`] from the root for a run of rays, `out[i]` answering
/// `rays[i]` through `answer` (`None` for an invalid ray), with one kernel
/// dispatch for the whole run instead of one per ray. The tree must not be
/// empty. Panics when the lengths differ.
pub fn query_many<const ANY: bool, O>(
    nodes: &[WideNode<8>],
    blocks: &[Triangle4],
    kernel: Kernel,
    rays: &[Ray],
    out: &mut [O],
    answer: impl Fn(Option<LeafHit>) -> O,
) {
    assert_eq!(rays.len(), out.len(), "one output per ray");
    struct Many<'a, const ANY: bool, O, A> {
        nodes: &'a [WideNode<8>],
        blocks: &'a [Triangle4],
        rays: &'a [Ray],
        out: &'a mut [O],
        answer: A,
    }
    impl<const ANY: bool, O, A: Fn(Option<LeafHit>) -> O> WideQuery for Many<'_, ANY, O, A> {
        #[inline(always)]
        fn run<F: TesterFactory>(&mut self, factory: &F) {
            for (o, ray) in self.out.iter_mut().zip(self.rays) {
                let hit = ray
                    .is_valid()
                    .then(|| query_root::<ANY, _>(self.nodes, self.blocks, factory, ray));
                *o = (self.answer)(hit.flatten());
            }
        }
    }
    with_kernel(
        kernel,
        &mut Many::<ANY, O, _> {
            nodes,
            blocks,
            rays,
            out,
            answer,
        },
    );
}

/// Occlusion of a run of rays over an 8-wide triangle tree from its root
/// (not empty), `out[i]` answering `rays[i]`: with the AVX2 kernel in
/// packets of eight rays of one direction octant (see
/// [`super::packet`]), with the others ray by ray as [`query_many`]. The
/// answers are the single-ray kernel's.
pub fn occluded_many(
    nodes: &[WideNode<8>],
    blocks: &[Triangle4],
    kernel: Kernel,
    rays: &[Ray],
    out: &mut [bool],
) {
    #[cfg(target_arch = "x86_64")]
    if kernel == Kernel::Avx2
        && with_avx2(|f| {
            // SAFETY: an `Avx2Factory` exists only where the CPU has AVX2
            // and FMA.
            unsafe { occluded_packets_avx2(f, nodes, blocks, rays, out) }
        })
        .is_some()
    {
        return;
    }
    query_many::<true, _>(nodes, blocks, kernel, rays, out, |h| h.is_some());
}

/// Closest hits of a run of rays over an 8-wide triangle tree from its
/// root (not empty), `out[i]` answering `rays[i]` through `answer` (`None`
/// for an invalid ray): with the AVX2 kernel in packets of eight rays of
/// one direction octant ([`super::packet::intersect_packet_from`]), with
/// the others ray by ray as [`query_many`]. Coherent runs (camera rays in
/// pixel order) form packets, others go ray by ray
/// ([`super::packet::in_coherent_packets`]). The answers are the
/// single-ray kernel's, exact ties included.
pub fn intersect_many<O>(
    nodes: &[WideNode<8>],
    blocks: &[Triangle4],
    kernel: Kernel,
    rays: &[Ray],
    out: &mut [O],
    answer: impl Fn(Option<LeafHit>) -> O,
) {
    #[cfg(target_arch = "x86_64")]
    if kernel == Kernel::Avx2
        && with_avx2(|f| {
            // SAFETY: an `Avx2Factory` exists only where the CPU has AVX2
            // and FMA.
            unsafe { intersect_packets_avx2(f, nodes, blocks, rays, out, &answer) }
        })
        .is_some()
    {
        return;
    }
    query_many::<false, _>(nodes, blocks, kernel, rays, out, answer);
}

/// A packet's box-test constants, its lanes' watertight rays (unused lanes
/// repeat the first ray; never read) and, when the rays share the axis
/// permutation, its triangle-test constants; `None` when a ray is not
/// [`super::packet::packetable`].
///
/// # Safety
/// The CPU has the AVX2 level (see [`super::packet::Packet8::new`]).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(clippy::type_complexity)] // three parts of one packet, used together
unsafe fn packet_constants(
    rays: &[&Ray],
) -> Option<(
    super::packet::Packet8,
    [WatertightRay; super::packet::PACKET],
    Option<super::packet::TrianglePacket>,
)> {
    use super::packet::{Packet8, TrianglePacket};
    // SAFETY: the caller's promise.
    let packet = unsafe { Packet8::try_new(rays) }?;
    // A plain loop, not `std::array::from_fn`: its closure was compiled
    // out of line (without AVX), making every intrinsic of `new_avx` a
    // call (flat primary rays +13% instructions, callgrind).
    // SAFETY: the caller's promise (AVX2 includes AVX).
    let mut wrays = [unsafe { WatertightRay::new_avx(rays[0]) }; super::packet::PACKET];
    for (w, r) in wrays.iter_mut().zip(rays).skip(1) {
        // SAFETY: as above.
        *w = unsafe { WatertightRay::new_avx(r) };
    }
    // SAFETY: the caller's promise.
    let triangles = unsafe { TrianglePacket::new(rays, |l| wrays[l]) };
    Some((packet, wrays, triangles))
}

/// [`intersect_many`] in packets (a target-feature function, as
/// [`occluded_packets_avx2`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
fn intersect_packets_avx2<O>(
    factory: &Avx2Factory,
    nodes: &[WideNode<8>],
    blocks: &[Triangle4],
    rays: &[Ray],
    out: &mut [O],
    answer: &impl Fn(Option<LeafHit>) -> O,
) {
    use super::packet::{PACKET, in_coherent_packets, intersect_packet_from};
    in_coherent_packets(
        rays,
        out,
        |rays, out| {
            for (o, ray) in out.iter_mut().zip(rays) {
                let hit = ray
                    .is_valid()
                    .then(|| query_root::<false, _>(nodes, blocks, factory, ray));
                *o = answer(hit.flatten());
            }
        },
        |rays, answers| {
            // SAFETY: this function runs only on CPUs of the AVX2 level.
            let Some((mut packet, wrays, triangles)) = (unsafe { packet_constants(rays) }) else {
                return false;
            };
            let mut testers = [None; PACKET];
            let mut lanes = ClosestTriangleLanes {
                lanes: TriangleLanes {
                    nodes,
                    blocks,
                    factory,
                    rays,
                    testers: &mut testers,
                    wrays,
                    triangles: triangles.as_ref(),
                },
                hits: [None; PACKET],
                best: super::packet::LaneKeys::NONE,
                key_base: 0,
            };
            let all = packet.lanes;
            intersect_packet_from(nodes, &mut packet, 0, all, &mut lanes);
            for (a, h) in answers.iter_mut().zip(lanes.hits) {
                *a = answer(h);
            }
            true
        },
    );
}

/// [`TriangleLanes`] for closest hits: each lane's closest hit so far.
#[cfg(target_arch = "x86_64")]
pub(crate) struct ClosestTriangleLanes<'a, 'r, W> {
    pub lanes: TriangleLanes<'a, 'r, W>,
    /// The lanes' new closest hits (each nearer, or as near with a smaller
    /// key, than the lane's closest before).
    pub hits: [Option<LeafHit>; super::packet::PACKET],
    /// The keys of the lanes' closest hits, these and any before.
    pub best: super::packet::LaneKeys,
    /// The key of a hit here is `key_base | slot`.
    pub key_base: u64,
}

#[cfg(target_arch = "x86_64")]
impl<W: LaneWrays> ClosestTriangleLanes<'_, '_, W> {
    /// Record `hit` for `lane` when it replaces the lane's closest by the
    /// single-ray rule ([`nearer`](super::triangle4::nearer)), shrinking
    /// the lane's `t_max`.
    #[inline(always)]
    fn offer(&mut self, packet: &mut super::packet::Packet8, lane: usize, hit: LeafHit) {
        let key = self.key_base | hit.3 as u64;
        if self.best.wins(lane, hit.0, packet.lane_t_max(lane), key) {
            packet.set_lane_t_max(lane, hit.0);
            self.hits[lane] = Some(hit);
            self.best.set(lane, key);
        }
    }

    /// Leaf `(first, count)` for lane `lane` alone (the single-ray leaf
    /// test from the lane's running closest).
    #[inline(always)]
    fn leaf_lane(
        &mut self,
        packet: &mut super::packet::Packet8,
        lane: usize,
        first: u32,
        count: u32,
    ) {
        let l = &mut self.lanes;
        let r = l.rays[lane];
        // The leaf's own closest (ties by slot), then the lane's rule.
        let mut t_max = packet.lane_t_max(lane);
        let mut best = None;
        intersect_blocks::<false>(
            l.blocks,
            l.wrays.wray(lane),
            r.t_min,
            first,
            count,
            &mut t_max,
            &mut best,
            true,
        );
        if let Some(h) = best {
            self.offer(packet, lane, h);
        }
    }
}

#[cfg(target_arch = "x86_64")]
impl<W: LaneWrays> super::packet::ClosestLanes for ClosestTriangleLanes<'_, '_, W> {
    #[inline(always)]
    fn leaf_packet(
        &mut self,
        packet: &mut super::packet::Packet8,
        mask: u32,
        first: u32,
        count: u32,
    ) {
        use super::packet::PACKET_TRIANGLES_FROM;
        match self.lanes.triangles {
            Some(triangles) if mask.count_ones() >= PACKET_TRIANGLES_FROM => {
                let (rays, wrays, hits) = (self.lanes.rays, &mut self.lanes.wrays, &mut self.hits);
                triangles.closest_blocks(
                    self.lanes.blocks,
                    first,
                    count,
                    mask,
                    packet,
                    &mut self.best,
                    self.key_base,
                    |lane, h| hits[lane] = Some(h),
                    |lane, b, j, t_max| {
                        super::packet::scalar_closest(rays[lane], wrays.wray(lane), b, j, t_max)
                    },
                );
            }
            _ => {
                let mut m = mask;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    self.leaf_lane(packet, lane, first, count);
                }
            }
        }
    }

    #[inline(always)]
    fn alone(&mut self, packet: &mut super::packet::Packet8, lane: usize, node: u32) {
        let l = &mut self.lanes;
        let r = l.rays[lane];
        let tester = l.testers[lane].get_or_insert_with(|| l.factory.make(r));
        let hit = subtree_with::<8, false, _>(
            l.nodes,
            l.blocks,
            tester,
            l.wrays.wray(lane),
            r.t_min,
            node,
            packet.lane_t_max(lane),
            &mut TraversalCounters::default(),
        );
        if let Some(h) = hit {
            self.offer(packet, lane, h);
        }
    }
}

/// The watertight rays of a packet's lanes.
#[cfg(target_arch = "x86_64")]
pub(crate) trait LaneWrays {
    fn wray(&mut self, lane: usize) -> &WatertightRay;
}

#[cfg(target_arch = "x86_64")]
impl LaneWrays for [WatertightRay; super::packet::PACKET] {
    #[inline(always)]
    fn wray(&mut self, lane: usize) -> &WatertightRay {
        &self[lane]
    }
}

/// A packet's rays in an 8-wide triangle tree (a flat scene's, or an
/// object's placed directly, entered from the top level): each lane's
/// leaves are tested and its lone walks run with the lane's own watertight
/// ray and single-ray tester (made when first needed).
#[cfg(target_arch = "x86_64")]
pub(crate) struct TriangleLanes<'a, 'r, W> {
    pub nodes: &'a [WideNode<8>],
    pub blocks: &'a [Triangle4],
    pub factory: &'a Avx2Factory,
    pub rays: &'a [&'r Ray],
    pub testers: &'a mut [Option<x86::Avx2Tester>; super::packet::PACKET],
    pub wrays: W,
    /// The packet's triangle-test constants, if its rays share the axis
    /// permutation.
    pub triangles: Option<&'a super::packet::TrianglePacket>,
}

#[cfg(target_arch = "x86_64")]
impl<W: LaneWrays> super::packet::PacketLanes for TriangleLanes<'_, '_, W> {
    /// Leaves most of the packet reaches test one triangle for all its
    /// rays at once.
    #[inline(always)]
    fn leaf_packet(
        &mut self,
        packet: &super::packet::Packet8,
        mask: u32,
        first: u32,
        count: u32,
    ) -> u32 {
        use super::packet::{PACKET_TRIANGLES_FROM, leaf_by_lane, scalar_triangle};
        let _ = packet;
        match self.triangles {
            Some(triangles) if mask.count_ones() >= PACKET_TRIANGLES_FROM => {
                let (rays, wrays) = (self.rays, &mut self.wrays);
                triangles.occluded_blocks(self.blocks, first, count, mask, |lane, b, j| {
                    scalar_triangle(rays[lane], wrays.wray(lane), b, j)
                })
            }
            _ => leaf_by_lane(self, mask, first, count),
        }
    }

    #[inline(always)]
    fn leaf(&mut self, lane: usize, first: u32, count: u32) -> bool {
        let r = self.rays[lane];
        intersect_blocks::<true>(
            self.blocks,
            self.wrays.wray(lane),
            r.t_min,
            first,
            count,
            &mut r.t_max.clone(),
            &mut None,
            true,
        )
    }

    #[inline(always)]
    fn alone(&mut self, lane: usize, node: u32) -> bool {
        let r = self.rays[lane];
        let tester = self.testers[lane].get_or_insert_with(|| self.factory.make(r));
        subtree_with::<8, true, _>(
            self.nodes,
            self.blocks,
            tester,
            self.wrays.wray(lane),
            r.t_min,
            node,
            r.t_max,
            &mut TraversalCounters::default(),
        )
        .is_some()
    }
}

/// [`occluded_many`] in packets. A target-feature function so that the
/// closures inside are compiled for AVX2 (see `toplevel`'s packet path).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
fn occluded_packets_avx2(
    factory: &Avx2Factory,
    nodes: &[WideNode<8>],
    blocks: &[Triangle4],
    rays: &[Ray],
    out: &mut [bool],
) {
    use super::packet::{PACKET, occluded_in_packets, occluded_packet};
    occluded_in_packets(
        rays,
        out,
        |ray| query_root::<true, _>(nodes, blocks, factory, ray).is_some(),
        |rays| {
            // SAFETY: this function runs only on CPUs of the AVX2 level;
            // the rays were grouped as packetable.
            let (packet, wrays, triangles) = unsafe { packet_constants(rays) }
                .expect("occlusion groups hold packetable rays only");
            let mut testers = [None; PACKET];
            let mut lanes = TriangleLanes {
                nodes,
                blocks,
                factory,
                rays,
                testers: &mut testers,
                wrays,
                triangles: triangles.as_ref(),
            };
            occluded_packet(nodes, &packet, &mut lanes)
        },
    );
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::Aabb;

    /// The four-lane slab constants are the per-axis scalar ones, bit for
    /// bit, and the octant table picks each axis's near plane by the sign
    /// of `inv_dir` (`-0.0` directions included).
    #[test]
    fn slab_constants_match_the_per_axis_arithmetic() {
        let mut rng = Pcg64::seed_from_u64(3);
        let special = [0.0, -0.0, 1.0, -1.0, 1e-30, -1e30, f32::MIN_POSITIVE];
        for i in 0..20_000 {
            let mut v = || {
                if i % 3 == 0 {
                    special[rng.gen_range(0..special.len())]
                } else {
                    rng.gen_range(-100.0f32..100.0) * 10f32.powi(rng.gen_range(-6..6))
                }
            };
            let (origin, dir) = (Vec3::new(v(), v(), v()), Vec3::new(v(), v(), v()));
            let s = FmaSlab::new(origin, dir);
            for a in 0..3 {
                let inv = 1.0 / dir[a];
                let oi = origin[a] * inv;
                let pad = oi.abs() * (2.0 * f32::EPSILON);
                assert_eq!(s.inv_dir[a].to_bits(), inv.to_bits());
                assert_eq!(s.near_offset[a].to_bits(), (oi + pad).to_bits());
                // `oi - pad`, but `-0.0` where that is zero (and a NaN of
                // either sign where it is NaN: such a ray takes the exact
                // path, which does not read it).
                let far = if oi - pad == 0.0 { -0.0 } else { oi - pad };
                if far.is_nan() {
                    assert!(s.far_offset[a].is_nan());
                } else {
                    assert_eq!(s.far_offset[a].to_bits(), far.to_bits());
                }
                let (near, far) = if inv.is_sign_negative() {
                    (a + 3, a)
                } else {
                    (a, a + 3)
                };
                assert_eq!((s.near_plane[a], s.far_plane[a]), (near, far), "{dir}");
            }
            let finite = [s.inv_dir, s.near_offset, s.far_offset]
                .iter()
                .all(|v| v.is_finite());
            assert_eq!(s.is_finite(), finite, "{origin} {dir}");
            #[cfg(target_arch = "x86_64")]
            if Kernel::Avx2.is_available() {
                // The AVX2 tester's constants are these, bit for bit
                // (minus the origin instead of the near offset on the
                // exact path), the plane offsets the octant's in bytes.
                let ray = Ray {
                    origin,
                    t_min: v(),
                    dir,
                    t_max: v(),
                };
                // SAFETY: the AVX2 level is available (checked above).
                let avx = unsafe { x86::Avx2Tester::new(&ray) };
                let ([inv, neg_near, neg_far], near, far, t_min, exact) = avx.constants();
                let bits = |v: [f32; 3]| v.map(f32::to_bits);
                // A `t_min` with its sign bit set takes the exact path too.
                let want_exact = !finite || ray.t_min.is_sign_negative();
                let near_or_origin = if want_exact { origin } else { s.near_offset };
                assert_eq!(exact, want_exact, "{origin} {dir} {}", ray.t_min);
                assert_eq!(bits(inv), bits(s.inv_dir.to_array()));
                assert_eq!(bits(neg_near), bits((-near_or_origin).to_array()));
                assert_eq!(bits(neg_far), bits((-s.far_offset).to_array()));
                assert_eq!(near, s.near_plane.map(|p| 32 * p));
                assert_eq!(far, s.far_plane.map(|p| 32 * p));
                assert_eq!(t_min.to_bits(), ray.t_min.to_bits());
            }
        }
    }

    /// The SSE kernel reproduces the scalar reference's box test exactly
    /// (see the module docs), so the two walk alike, not only answer alike:
    /// the same leaves in the same order, each entered with the same
    /// `t_max` (so the same sorts, pushes, pops and culls), the same visit
    /// counts and the same hit, for closest and any hits, 4- and 8-wide,
    /// on a procedural scene's objects and a random soup, with rays whose
    /// direction has zero components, whose origin lies on a box plane (a
    /// vertex's coordinate) or which pass through a vertex among them.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn sse_kernel_walks_as_the_scalar_reference() {
        if !Kernel::Sse.is_available() {
            eprintln!("skipped: no SSE4.1 on this CPU");
            return;
        }
        /// One walk: the leaves entered (with the `t_max` each was entered
        /// with), the inner and leaf visits, and the hit.
        type Walk = (Vec<(u32, u32, u32)>, u32, u32, Option<LeafHit>);
        fn walk<const W: usize, const ANY: bool, B: BoxTester<W>>(
            w: &WideMeshBvh<W>,
            tester: &B,
            wray: &WatertightRay,
            t_max: f32,
        ) -> Walk {
            let (mut seen, mut best) = (Vec::new(), None);
            let mut c = TraversalCounters::default();
            traverse::<W, ANY, _, _>(
                &w.wide.nodes,
                tester,
                0,
                t_max,
                &mut c,
                |first, count, t| {
                    seen.push((first, count, t.to_bits()));
                    intersect_blocks::<ANY>(&w.blocks, wray, 0.0, first, count, t, &mut best, true)
                },
            );
            (seen, c.inner_visited, c.leaves_visited, best)
        }
        fn walks<const W: usize, const ANY: bool>(
            w: &WideMeshBvh<W>,
            rays: &[(Vec3, Vec3, f32)],
        ) -> usize {
            let mut leaves = 0;
            for &(origin, dir, t_max) in rays {
                let wray = WatertightRay::new(origin, dir);
                let scalar = ScalarTester {
                    ray: BoxRay::new(origin, dir),
                    t_min: 0.0,
                };
                // SAFETY: the CPU has SSE4.1 (checked above).
                let sse = unsafe { x86::SseTester::new(origin, dir, 0.0) };
                let a = walk::<W, ANY, _>(w, &scalar, &wray, t_max);
                let b = walk::<W, ANY, _>(w, &sse, &wray, t_max);
                assert_eq!(a.0, b.0, "leaves, ray {origin} {dir}");
                assert_eq!((a.1, a.2), (b.1, b.2), "visits, ray {origin} {dir}");
                assert_eq!(a.3, b.3, "hit, ray {origin} {dir}");
                leaves += a.0.len();
            }
            leaves
        }
        let mut rng = Pcg64::seed_from_u64(41);
        let mut meshes: Vec<_> = crate::procedural::random_overlapping(4, 3000, 9)
            .objects
            .into_iter()
            .map(|o| o.mesh)
            .collect();
        let mut positions = Vec::new();
        for _ in 0..6000 {
            positions.push(Vec3::new(
                rng.gen_range(0.0..100.0),
                rng.gen_range(0.0..100.0),
                rng.gen_range(0.0..100.0),
            ));
        }
        let indices = (0..2000u32)
            .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
            .collect();
        meshes.push(crate::mesh::TriangleMesh::new(positions, indices).unwrap());
        let mut total = 0;
        for mesh in &meshes {
            let bvh = MeshBvh::build(mesh, &Default::default()).unwrap();
            let mut rays = Vec::new();
            for i in 0..1500 {
                let mut origin = Vec3::new(
                    rng.gen_range(-20.0..120.0),
                    rng.gen_range(-20.0..120.0),
                    rng.gen_range(-20.0..120.0),
                );
                let mut dir = Vec3::new(
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-1.0..1.0),
                );
                if i % 5 == 0 {
                    dir[rng.gen_range(0..3)] = 0.0;
                }
                if i % 7 == 0 {
                    // On the plane of some triangle's vertex: a box plane
                    // of the leaf holding it, where NaN distances arise.
                    let v = bvh.triangles[rng.gen_range(0..bvh.triangles.len())][0];
                    let a = rng.gen_range(0..3);
                    origin[a] = v[a];
                }
                if i % 11 == 0 {
                    // Through some triangle's vertex, which lies on its
                    // leaf's box: entry and exit distances meet there.
                    let v = bvh.triangles[rng.gen_range(0..bvh.triangles.len())][1];
                    origin = v - dir * rng.gen_range(0.0..30.0);
                }
                if dir == Vec3::ZERO {
                    continue;
                }
                let t_max = if i % 3 == 0 {
                    rng.gen_range(1.0..60.0)
                } else {
                    f32::INFINITY
                };
                rays.push((origin, dir, t_max));
            }
            let w8 = WideMeshBvh::<8>::from_mesh(&bvh).unwrap();
            let w4 = WideMeshBvh::<4>::from_mesh(&bvh).unwrap();
            total += walks::<8, false>(&w8, &rays) + walks::<8, true>(&w8, &rays);
            total += walks::<4, false>(&w4, &rays) + walks::<4, true>(&w4, &rays);
        }
        // The walks reached many leaves (the comparison is not vacuous).
        assert!(total > 50_000, "{total}");
    }

    /// The FMA box test of the AVX2 kernel is conservative: it enters every
    /// box the exact test (`hit_node`, the SSE and scalar kernels) enters,
    /// including rays whose origin is far from the coordinate origin (large
    /// `origin * inv_dir`, where the FMA form loses most), boxes touching
    /// the ray's start, and axis-parallel rays.
    #[test]
    fn avx2_box_test_never_misses_what_the_exact_test_hits() {
        if !Kernel::Avx2.is_available() {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        let mut rng = Pcg64::seed_from_u64(11);
        let (mut exact_hits, mut extra) = (0u32, 0u32);
        for _ in 0..20_000 {
            let scale = [1.0f32, 1e3, 1e5][rng.gen_range(0..3)];
            let centre = Vec3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
            ) * scale;
            let mut node = WideNode::<8>::EMPTY;
            for i in 0..8 {
                let lo = centre
                    + Vec3::new(
                        rng.gen_range(-2.0..2.0),
                        rng.gen_range(-2.0..2.0),
                        rng.gen_range(-2.0..2.0),
                    );
                // Some flat boxes (a planar object's), most not.
                let dz = if rng.gen_bool(0.2) {
                    0.0
                } else {
                    rng.gen_range(0.0..1.0)
                };
                let hi = lo + Vec3::new(rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0), dz);
                node.set_child(i, &Aabb::new(lo, hi), i as u32);
            }
            // Aim at a box corner or face point, from near or far.
            let k = rng.gen_range(0..8);
            let b = node.child_bounds(k);
            let target = Vec3::new(
                if rng.gen_bool(0.5) {
                    b.min.x
                } else {
                    rng.gen_range(b.min.x..=b.max.x)
                },
                if rng.gen_bool(0.5) {
                    b.max.y
                } else {
                    rng.gen_range(b.min.y..=b.max.y)
                },
                b.min.z,
            );
            let mut dir = Vec3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
            );
            if rng.gen_bool(0.2) {
                dir.x = 0.0;
            }
            if dir == Vec3::ZERO {
                continue;
            }
            let dist = rng.gen_range(0.0..5.0f32);
            let origin = target - dir * dist;
            let t_max = if rng.gen_bool(0.3) {
                dist
            } else {
                f32::INFINITY
            };
            let scalar = ScalarTester {
                ray: BoxRay::new(origin, dir),
                t_min: 0.0,
            };
            let mut d = [0.0f32; 8];
            let want = BoxTester::<8>::test(&scalar, &node, t_max, &mut d);
            // SAFETY: the AVX2 level checked above.
            let tester = unsafe {
                x86::Avx2Tester::new(&Ray {
                    origin,
                    t_min: 0.0,
                    dir,
                    t_max: f32::INFINITY,
                })
            };
            let got = tester.test(&node, t_max, &mut d);
            assert_eq!(
                want & !got,
                0,
                "AVX2 missed boxes {:#b}: origin {origin:?} dir {dir:?} t_max {t_max}",
                want & !got
            );
            exact_hits += want.count_ones();
            // Every extra box is one the ray passes within the rounding
            // bound of: the exact test hits it grown by a few ulps of the
            // coordinates involved.
            let margin = 8.0 * f32::EPSILON * (origin.abs().max_element() + scale);
            let mut extras = got & !want;
            while extras != 0 {
                let i = extras.trailing_zeros() as usize;
                extras &= extras - 1;
                let b = node.child_bounds(i);
                let grown = BvhNode::inner(Aabb::new(b.min - margin, b.max + margin), 0);
                let d = scalar
                    .ray
                    .hit_node(&grown, 0.0, t_max * (1.0 + 1e-5) + margin);
                assert!(
                    d < f32::INFINITY,
                    "AVX2 entered box {i} far from the ray: origin {origin:?} dir {dir:?}"
                );
                extra += 1;
            }
        }
        assert!(exact_hits > 10_000);
        eprintln!("{extra} boxes entered beyond the {exact_hits} of the exact test");
    }

    /// The AVX2 fast path orders distances as integers (`vpmaxsd`,
    /// `vpminsd`, `vpcmpgtd`); the float ordering of the same FMA distances
    /// (the test before session 45, written out lane by lane here) enters
    /// the same boxes at the same distances. Signed zeros and tiny values
    /// in the planes, the origins and the ray interval are where the two
    /// orderings could part; the one case the integer test may skip (a far
    /// distance below zero that underflows to `-0.0` with `near` zero: a
    /// box wholly behind the origin) is counted, and must stay rare.
    #[test]
    fn avx2_integer_ordering_enters_what_the_float_ordering_enters() {
        if !Kernel::Avx2.is_available() {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        let mut rng = Pcg64::seed_from_u64(45);
        let special = [0.0f32, -0.0, 1e-30, -1e-30, 1e-38, 1.0, -1.0, 3.0];
        let (mut fast, mut entered, mut underflow, mut wider) = (0u32, 0u32, 0u32, 0u32);
        for i in 0..40_000 {
            let mut v = |range: f32| {
                if i % 2 == 0 {
                    special[rng.gen_range(0..special.len())]
                } else {
                    rng.gen_range(-range..range)
                }
            };
            let mut node = WideNode::<8>::EMPTY;
            for c in 0..7 {
                let a = Vec3::new(v(4.0), v(4.0), v(4.0));
                let b = Vec3::new(v(4.0), v(4.0), v(4.0));
                node.set_child(c, &Aabb::new(a.min(b), a.max(b)), c as u32);
            }
            let dir = Vec3::new(v(1.0), v(1.0), v(1.0));
            let ray = Ray {
                origin: Vec3::new(v(4.0), v(4.0), v(4.0)),
                t_min: [0.0, 0.0, 1e-30, 0.5][i % 4],
                dir,
                t_max: [f32::INFINITY, 0.0, -0.0, 2.0][(i / 4) % 4],
            };
            if !ray.is_valid() {
                continue;
            }
            // SAFETY: the AVX2 level checked above.
            let tester = unsafe { x86::Avx2Tester::new(&ray) };
            let ([inv, neg_near, neg_far], near_plane, far_plane, t_min, exact) =
                tester.constants();
            if exact {
                continue;
            }
            fast += 1;
            let mut dist = [0.0f32; 8];
            let got = tester.test(&node, ray.t_max, &mut dist);
            let planes = node.planes();
            for c in 0..8 {
                // The float ordering: `vmaxps`/`vminps` in a chain from the
                // ray's interval (`t_max + 0.0` as the kernel takes it, the
                // same for a float compare), then the `ROBUST_FAR` product
                // and `vcmpps` (`<=`).
                let (mut near, mut far) = (t_min, ray.t_max + 0.0);
                for a in 0..3 {
                    let tn = planes[near_plane[a] / 32][c].mul_add(inv[a], neg_near[a]);
                    let tf = planes[far_plane[a] / 32][c].mul_add(inv[a], neg_far[a]);
                    near = if near > tn { near } else { tn };
                    far = if far < tf { far } else { tf };
                }
                let float = near <= far * ROBUST_FAR;
                // What the fast path computes from the same distances: a
                // far distance with its sign bit set is missed (below any
                // `near` as an integer), any other padded on its bits
                // (`pad_far_bits`).
                let padded = f32::from_bits(
                    (far.to_bits() + x86::FAR_PAD_ULPS as u32).min(f32::INFINITY.to_bits()),
                );
                let want = !far.is_sign_negative() && near <= padded;
                let hit = got >> c & 1 == 1;
                assert_eq!(hit, want, "child {c}: {ray:?}, near {near} far {far}");
                if float && !hit {
                    // Only a far distance that underflowed to `-0.0`.
                    assert!(
                        far == 0.0 && near == 0.0,
                        "child {c} missed: {ray:?}, near {near} far {far}"
                    );
                    underflow += 1;
                }
                if hit && !float {
                    wider += 1;
                }
                if hit {
                    // The same distance (up to the sign of a zero).
                    assert_eq!(dist[c], near, "child {c}: {ray:?}");
                    entered += 1;
                }
            }
        }
        eprintln!(
            "{fast} fast-path rays, {entered} boxes entered ({wider} by the wider pad only), \
             {underflow} underflows"
        );
        assert!(fast > 10_000 && entered > 10_000, "{fast} {entered}");
        assert!(underflow * 1000 < entered, "{underflow} of {entered}");
        assert!(wider * 1000 < entered, "{wider} of {entered}");
    }

    /// `pad_far_bits` is never below the `ROBUST_FAR` product for a far
    /// distance at or above zero, and at most `FAR_PAD_ULPS` above the
    /// distance: on powers of two and the values just below them (where
    /// the product's rounding is tightest), subnormals, zero, the largest
    /// finite value, infinity and random values of every exponent.
    #[test]
    fn far_pad_on_the_bits_bounds_the_robust_product() {
        if !Kernel::Avx2.is_available() {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        assert_eq!(ROBUST_FAR.to_bits(), 1.0f32.to_bits() + 3, "1 + 3 * 2^-23");
        let mut rng = Pcg64::seed_from_u64(7);
        let mut values = vec![
            0.0f32,
            f32::MIN_POSITIVE,
            1e-45,
            1e-40,
            f32::MAX,
            f32::INFINITY,
        ];
        for e in -149..128 {
            let p = 2f32.powi(e);
            values.extend([p, f32::from_bits(p.to_bits().saturating_sub(1))]);
        }
        values.extend((0..20_000).map(|_| f32::from_bits(rng.gen_range(0..0x7f80_0000u32))));
        for chunk in values.chunks(8) {
            let mut lanes = [0.0f32; 8];
            lanes[..chunk.len()].copy_from_slice(chunk);
            // SAFETY: the AVX2 level checked above.
            let padded: [f32; 8] =
                unsafe { bytemuck::cast(x86::pad_far_bits(bytemuck::cast(lanes))) };
            for (&f, &p) in lanes.iter().zip(&padded) {
                assert!(p >= f * ROBUST_FAR, "{f:e}: {p:e} < {:e}", f * ROBUST_FAR);
                let most = (f.to_bits() + x86::FAR_PAD_ULPS as u32).min(f32::INFINITY.to_bits());
                assert!(p.to_bits() <= most, "{f:e}: {p:e}");
            }
        }
        // A negative distance stays negative (the box is missed).
        // SAFETY: as above.
        let neg: [f32; 8] =
            unsafe { bytemuck::cast(x86::pad_far_bits(bytemuck::cast([-1.0f32; 8]))) };
        assert!(neg.iter().all(|&n| n < 0.0));
    }
}
