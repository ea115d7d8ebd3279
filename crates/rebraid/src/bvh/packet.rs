//! Packets of up to eight rays that share a direction octant, traced
//! through 8-wide trees (AVX2) for occlusion and for closest hits: each
//! child box is tested against all the
//! packet's rays at once (one lane per ray), so coherent rays (shadow rays
//! towards one light, in pixel order) share the node fetches and the
//! traversal decisions that single-ray traversal repeats per ray (Wald,
//! Slusallek, Benthin, Wagner 2001, "Interactive Rendering with Coherent
//! Ray Tracing"). Where few rays of a packet remain in a subtree, each goes
//! on alone with the single-ray kernel (the hybrid of Benthin, Wald, Woop,
//! Ernst, Mark 2012, "Combining Single and Packet-Ray Tracing for Arbitrary
//! Ray Distributions on the Intel MIC Architecture", which Embree's stream
//! API also uses).
//!
//! Every lane's box test computes the single-ray AVX2 test's distances
//! (the same [`FmaSlab`] constants, one FMA per plane) and orders them as
//! floats with the [`ROBUST_FAR`] product, where the single-ray test orders
//! them as integers and pads the far distance by a few ulps on its bits
//! (`Avx2Tester::test_known` and `pad_far_bits` in `simd.rs`: one cycle
//! per step where the float operations take four on Intel cores; the
//! packet's tests are many and independent, and so done they made shadow
//! packets 2-8% slower, session 45). A ray enters the same boxes at the
//! same distances in a packet as alone, but for two cases that hold no
//! hit: a box whose entry lies within the few ulps by which the single-ray
//! pad is wider (entered alone only), and a box wholly behind the ray's
//! origin whose far distance underflows to `-0.0` (entered in a packet
//! only). A leaf that most of a packet reaches tests one
//! triangle for all its rays at once ([`TrianglePacket`], the four-triangle
//! test's operations per lane), other leaves one ray at a time: either way
//! a triangle is hit exactly when the single-ray test hits it, so an
//! occlusion answer is the same as the single-ray kernel's.
//!
//! Closest hits ([`intersect_packet_from`]) add per-lane running distances
//! (each lane's `t_max` shrinks with its hits and culls its own walk),
//! children visited nearest first, and the shared tie rule
//! ([`super::triangle4::nearer`]) that makes an answer independent of the
//! visit order: a lane answers exactly as its ray alone. They pay for
//! coherent rays only (camera rays: re-braided primary rays 5-25% fewer
//! instructions), so [`in_coherent_packets`] forms packets of consecutive
//! rays with close directions and leaves incoherent runs to the single-ray
//! kernel.

use core::arch::x86_64::*;
use std::mem::MaybeUninit;

use super::simd::FmaSlab;
use super::triangle4::{LeafHit, Triangle4};
use super::wide::{WideNode, decode_leaf, is_leaf_ref};
use super::{MAX_DEPTH, ROBUST_FAR};
use crate::Ray;
use crate::triangle::WatertightRay;

/// Rays per packet: the lanes of an AVX2 vector.
pub const PACKET: usize = 8;

/// Entries of a packet traversal stack: all hit children of each node on
/// the path (at most 8 per level, wide depth below [`MAX_DEPTH`]).
const PACKET_STACK: usize = 8 * MAX_DEPTH as usize;

/// A subtree reached by fewer active rays than this is traversed by each
/// of them alone: testing a node for one or two lanes costs about what the
/// single-ray test costs per ray, and the single-ray kernel's closer
/// per-ray culling wins then. With the node tests out of line (session
/// 32), 2 took 0.5-2.2% fewer instructions and flat rays 2-6% less time,
/// but re-braided rays moved only within the wall-clock noise (0.97-1.03):
/// left at 3.
pub const SINGLE_BELOW: u32 = 3;

/// The octant of a direction: its three sign bits. Rays of one packet
/// share it, so they share each axis's near and far plane.
#[inline(always)]
pub fn octant(ray: &Ray) -> usize {
    (ray.dir.x.is_sign_negative() as usize)
        | (ray.dir.y.is_sign_negative() as usize) << 1
        | (ray.dir.z.is_sign_negative() as usize) << 2
}

/// True when a valid ray can join a packet: its one-FMA slab constants are
/// finite (no zero direction component) and its `t_min` is at least
/// `+0.0`, as the single-ray AVX2 test requires for its fast path; other
/// rays are traced alone.
#[inline(always)]
pub fn packetable(ray: &Ray) -> bool {
    FmaSlab::new(ray.origin, ray.dir).is_finite() && !ray.t_min.is_sign_negative()
}

/// Rays whose directions are within this angle's cosine of the first
/// ray's trace closest hits as a packet; more divergent ones (diffuse
/// bounces share an octant but little else) alone.
pub const COHERENT_COS: f32 = 0.95;

/// The per-lane constants of a packet's box test.
#[derive(Clone, Copy)]
pub struct Packet8 {
    inv_dir: [__m256; 3],
    near_offset: [__m256; 3],
    far_offset: [__m256; 3],
    t_min: __m256,
    t_max: __m256,
    /// Byte offset in [`WideNode`] of each axis's near and far plane (see
    /// `Avx2Tester`): one choice for the octant.
    near: [usize; 3],
    far: [usize; 3],
    /// The lanes that hold a ray.
    pub lanes: u32,
}

impl Packet8 {
    /// A packet of `rays` (1 to 8, one octant, each [`packetable`]); lane
    /// `l` holds `rays[l]`.
    ///
    /// # Safety
    /// Callers must run on a CPU of the AVX2 level (the packet's existence
    /// is what `Packet8::test_child` relies on).
    #[inline(always)]
    pub unsafe fn new(rays: &[&Ray]) -> Self {
        // SAFETY: as this function's.
        let (packet, finite) = unsafe { Self::build(rays) };
        debug_assert!(finite, "every ray of a packet is packetable");
        packet
    }

    /// [`Packet8::new`] for rays not yet known to be [`packetable`]: `None`
    /// when one is not. Each ray's slab constants are computed once, here
    /// (checking them first and building the packet afterwards computed
    /// them twice, three divisions each).
    ///
    /// # Safety
    /// As [`Packet8::new`].
    #[inline(always)]
    pub unsafe fn try_new(rays: &[&Ray]) -> Option<Self> {
        // SAFETY: as this function's.
        let (packet, finite) = unsafe { Self::build(rays) };
        finite.then_some(packet)
    }

    /// The packet of `rays`, and whether every ray's slab constants are
    /// finite (the packet is usable only then). Branch-free over the
    /// lanes: an early exit inside the loop cost the occlusion packets
    /// 14% more instructions (callgrind, samurai shadow rays). The eight
    /// rays (32 bytes each) are loaded whole and transposed in registers,
    /// and the constants computed per axis for all lanes at once
    /// ([`FmaSlab::new`]'s arithmetic, lane by lane, so the same bits):
    /// three divisions per packet instead of one per ray, and no lane
    /// arrays written as scalars and read back as vectors (a store the
    /// load cannot forward from).
    ///
    /// # Safety
    /// As [`Packet8::new`].
    #[inline(always)]
    unsafe fn build(rays: &[&Ray]) -> (Self, bool) {
        debug_assert!((1..=PACKET).contains(&rays.len()));
        // SAFETY: the caller runs on a CPU of the AVX2 level; each load
        // reads one whole `Ray` (32 bytes: origin, t_min, dir, t_max).
        unsafe {
            // Unused lanes repeat the first ray: masked off.
            let load = |l: usize| {
                let r: &Ray = rays.get(l).unwrap_or(&rays[0]);
                _mm256_loadu_ps((r as *const Ray).cast::<f32>())
            };
            let [r0, r1, r2, r3, r4, r5, r6, r7] = std::array::from_fn(load);
            // The 8x8 transpose: row k holds field k of every lane.
            let (t0, t1) = (_mm256_unpacklo_ps(r0, r1), _mm256_unpackhi_ps(r0, r1));
            let (t2, t3) = (_mm256_unpacklo_ps(r2, r3), _mm256_unpackhi_ps(r2, r3));
            let (t4, t5) = (_mm256_unpacklo_ps(r4, r5), _mm256_unpackhi_ps(r4, r5));
            let (t6, t7) = (_mm256_unpacklo_ps(r6, r7), _mm256_unpackhi_ps(r6, r7));
            let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
            let u1 = _mm256_shuffle_ps::<0xee>(t0, t2);
            let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
            let u3 = _mm256_shuffle_ps::<0xee>(t1, t3);
            let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
            let u5 = _mm256_shuffle_ps::<0xee>(t4, t6);
            let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
            let u7 = _mm256_shuffle_ps::<0xee>(t5, t7);
            let origin = [
                _mm256_permute2f128_ps::<0x20>(u0, u4),
                _mm256_permute2f128_ps::<0x20>(u1, u5),
                _mm256_permute2f128_ps::<0x20>(u2, u6),
            ];
            let t_min = _mm256_permute2f128_ps::<0x20>(u3, u7);
            let dir = [
                _mm256_permute2f128_ps::<0x31>(u0, u4),
                _mm256_permute2f128_ps::<0x31>(u1, u5),
                _mm256_permute2f128_ps::<0x31>(u2, u6),
            ];
            let t_max = _mm256_permute2f128_ps::<0x31>(u3, u7);
            let abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX));
            let sign = _mm256_set1_ps(-0.0);
            let two_eps = _mm256_set1_ps(2.0 * f32::EPSILON);
            let zero = _mm256_setzero_ps();
            // `0 * x` is zero for a finite `x`, NaN otherwise (as
            // `FmaSlab::is_finite`).
            let mut nonfinite = zero;
            let mut inv_dir = [zero; 3];
            let mut near_offset = [zero; 3];
            let mut far_offset = [zero; 3];
            for a in 0..3 {
                let inv = _mm256_div_ps(_mm256_set1_ps(1.0), dir[a]);
                let oi = _mm256_mul_ps(origin[a], inv);
                let pad = _mm256_mul_ps(_mm256_and_ps(oi, abs_mask), two_eps);
                // The far offset as `FmaSlab`'s: `-(pad - oi)`, `-0.0`
                // where zero.
                let near = _mm256_add_ps(oi, pad);
                let far = _mm256_xor_ps(_mm256_sub_ps(pad, oi), sign);
                for x in [inv, near, far] {
                    nonfinite = _mm256_add_ps(nonfinite, _mm256_mul_ps(zero, x));
                }
                (inv_dir[a], near_offset[a], far_offset[a]) = (inv, near, far);
            }
            // And no lane's `t_min` with its sign bit set (`packetable`).
            let finite = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(nonfinite, zero)) == 0xff
                && _mm256_movemask_ps(t_min) == 0;
            let first = FmaSlab::new(rays[0].origin, rays[0].dir);
            debug_assert!(rays.iter().all(|r| octant(r) == octant(rays[0])));
            let packet = Self {
                inv_dir,
                near_offset,
                far_offset,
                t_min,
                t_max,
                near: first.near_plane.map(|i| i * 32),
                far: first.far_plane.map(|i| i * 32),
                lanes: (1u32 << rays.len()) - 1,
            };
            (packet, finite)
        }
    }

    /// Lane `lane`'s `t_max` (for closest hit: its running closest distance).
    #[inline(always)]
    pub fn lane_t_max(&self, lane: usize) -> f32 {
        let t: [f32; PACKET] = bytemuck::cast(self.t_max);
        t[lane]
    }

    /// Shrink lane `lane`'s `t_max` to `t` (a closer hit).
    #[inline(always)]
    pub fn set_lane_t_max(&mut self, lane: usize, t: f32) {
        let mut all: [f32; PACKET] = bytemuck::cast(self.t_max);
        all[lane] = t;
        self.t_max = bytemuck::cast(all);
    }

    /// The lanes whose entry distance `near` (from
    /// [`Packet8::test_child_near`]) their `t_max` still reaches: the
    /// single-ray pop's test, `near <= t_max * ROBUST_FAR`.
    #[inline(always)]
    fn still_entered(&self, near: &[f32; PACKET]) -> u32 {
        // SAFETY: a `Packet8` exists only on CPUs with AVX2 (see
        // `Packet8::new`); the load reads the eight `f32` of `near`.
        unsafe {
            let far = _mm256_mul_ps(self.t_max, _mm256_set1_ps(ROBUST_FAR));
            let near = _mm256_loadu_ps(near.as_ptr());
            _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32
        }
    }

    /// The lanes whose ray enters each child slot of `node`: byte `c` of
    /// the answer is [`Packet8::test_child`]'s mask for slot `c` (empty
    /// slots' inverted boxes give 0). A function of its own, not inlined:
    /// inlined into the packet walks, the child test read the packet's
    /// eleven constant vectors from the stack for every child (31
    /// instructions per child, twelve of them such reads: LLVM spilled the
    /// constants across the leaf code); here they are loaded once per node
    /// and the eight slots are tested unrolled, about 19 instructions each.
    /// Measured (session 32, `docs/performance.md`): re-braided shadow
    /// rays 4.5-7.2% fewer instructions and 6-12% faster by wall clock,
    /// flat 2.5-9% faster.
    ///
    /// # Safety
    /// The CPU has the AVX2 level (a `Packet8` exists only there).
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
    #[inline(never)]
    unsafe fn test_node(&self, node: &WideNode<8>) -> u64 {
        let mut masks = 0u64;
        for c in 0..8 {
            masks |= (self.test_child(node, c) as u64) << (8 * c);
        }
        masks
    }

    /// The children of `node` that lanes of `mask` enter, as (entry
    /// distance of the first such lane, (child reference, lanes, each
    /// lane's entry distance)), nearest first (stable) in `hits[..k]`;
    /// returns `k`. Out of line for the reason [`Packet8::test_node`] is,
    /// with the sort: writing every slot's distances for the caller to sort
    /// cost more than the constants' reloads saved (re-braided primary rays
    /// +2% to +4% instructions); sorted here, 2% fewer.
    ///
    /// # Safety
    /// As [`Packet8::test_node`].
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
    #[inline(never)]
    unsafe fn hit_children_sorted(
        &self,
        node: &WideNode<8>,
        mask: u32,
        hits: &mut [MaybeUninit<(f32, PacketEntry)>; 8],
    ) -> usize {
        let mut k = 0usize;
        for c in 0..8 {
            let (hit, near) = self.test_child_near(node, c);
            let hit = hit & mask;
            if hit == 0 {
                continue;
            }
            let near: [f32; PACKET] = bytemuck::cast(near);
            let item = (
                near[hit.trailing_zeros() as usize],
                (node.child[c], hit, near),
            );
            let mut j = k;
            // SAFETY: `hits[..k]` are written (`k` grows only after a
            // write at or below it).
            while j > 0 && unsafe { hits[j - 1].assume_init_ref().0 } > item.0 {
                hits[j] = hits[j - 1];
                j -= 1;
            }
            hits[j].write(item);
            k += 1;
        }
        k
    }

    /// The lanes whose ray enters child slot `c` of `node` (all lanes
    /// tested; callers mask).
    #[inline(always)]
    fn test_child(&self, node: &WideNode<8>, c: usize) -> u32 {
        self.test_child_near(node, c).0
    }

    /// [`Packet8::test_child`] and each lane's entry distance into the
    /// child (meaningful for the lanes that enter it).
    #[inline(always)]
    fn test_child_near(&self, node: &WideNode<8>, c: usize) -> (u32, __m256) {
        debug_assert!(c < 8);
        let planes = node.planes().as_ptr().cast::<u8>();
        // SAFETY: a `Packet8` exists only on CPUs of the AVX2 level (see
        // `Packet8::new`); each broadcast reads the `f32` of slot `c < 8`
        // of one of the node's six 32-byte planes (offsets below 192 in
        // steps of 32, made by `Packet8::new` from `FmaSlab`'s plane
        // indices).
        unsafe {
            let plane = |off: usize| _mm256_broadcast_ss(&*planes.add(off + 4 * c).cast::<f32>());
            let mut near = self.t_min;
            let mut far = self.t_max;
            for a in 0..3 {
                let tn = _mm256_fmsub_ps(plane(self.near[a]), self.inv_dir[a], self.near_offset[a]);
                let tf = _mm256_fmsub_ps(plane(self.far[a]), self.inv_dir[a], self.far_offset[a]);
                near = _mm256_max_ps(near, tn);
                far = _mm256_min_ps(far, tf);
            }
            far = _mm256_mul_ps(far, _mm256_set1_ps(ROBUST_FAR));
            (
                _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32,
                near,
            )
        }
    }
}

/// A closest-hit packet walk's stack entry: a child reference, the lanes
/// that entered it and each lane's entry distance.
type PacketEntry = (u32, u32, [f32; PACKET]);

/// A leaf reached by at least this many rays of a packet is tested one
/// triangle for all the rays at once ([`TrianglePacket`]); fewer test
/// their blocks one ray at a time, four triangles per step.
pub const PACKET_TRIANGLES_FROM: u32 = 4;

/// The per-lane constants of the watertight triangle test (Woop, Benthin,
/// Wald 2013) for a packet whose rays share the axis permutation (one
/// octant and one dominant axis): one triangle is tested against eight rays per step,
/// where a lone ray tests four triangles per step. Every lane computes the
/// operations of the four-triangle SSE test in the same order (separate
/// multiplies and subtractions, a true division), so its decisions are
/// that test's, and lanes whose edge functions round to exactly zero go
/// to the scalar `f64` test as they do there.
#[derive(Clone, Copy)]
pub struct TrianglePacket {
    /// The rays' origins in the permuted order `(kx, ky, kz)`.
    origin: [__m256; 3],
    /// The shear constants `sx, sy, sz`.
    shear: [__m256; 3],
    t_min: __m256,
    t_max: __m256,
    /// The shared permutation `(kx, ky, kz)`.
    k: [usize; 3],
}

impl TrianglePacket {
    /// The constants of `rays` (1 to 8) from their watertight rays
    /// (`wray(l)` of `rays[l]`), or `None` when their axis permutations
    /// differ (the packet's rays then test triangles one ray at a time).
    ///
    /// # Safety
    /// Callers must run on a CPU with AVX2 (see [`Packet8::new`]).
    // The lane index picks from eight per-lane arrays at once.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    pub unsafe fn new(rays: &[&Ray], mut wray: impl FnMut(usize) -> WatertightRay) -> Option<Self> {
        let w0 = wray(0);
        let mut lane = [[0.0f32; PACKET]; 8];
        for l in 0..PACKET {
            let (r, w) = if l < rays.len() && l > 0 {
                (rays[l], wray(l))
            } else {
                (rays[0], w0)
            };
            if (w.kx, w.ky, w.kz) != (w0.kx, w0.ky, w0.kz) {
                return None;
            }
            for a in 0..3 {
                lane[a][l] = w.origin_k[a];
            }
            lane[3][l] = w.sx;
            lane[4][l] = w.sy;
            lane[5][l] = w.sz;
            lane[6][l] = r.t_min;
            lane[7][l] = r.t_max;
        }
        let v = |k: usize| -> __m256 { bytemuck::cast(lane[k]) };
        Some(Self {
            origin: [v(0), v(1), v(2)],
            shear: [v(3), v(4), v(5)],
            t_min: v(6),
            t_max: v(7),
            k: [w0.kx, w0.ky, w0.kz],
        })
    }

    /// The watertight test of triangle `j` of `b` on every lane, or `None`
    /// when every lane of `active` passes outside it (most tests end
    /// there, as the SSE test's do for its four triangles). Otherwise: the
    /// lanes that hit within `[t_min, t_max]` (`t_max` per lane: the
    /// packet's own for occlusion, the running closest for closest hit),
    /// the lanes whose edge functions round to exactly zero (for the
    /// scalar test), and each lane's `t`, `u`, `v`.
    #[inline(always)]
    fn test_triangle(
        &self,
        b: &Triangle4,
        j: usize,
        t_max: __m256,
        active: u32,
    ) -> Option<(u32, u32, __m256, __m256, __m256)> {
        // SAFETY: a `TrianglePacket` exists only on CPUs with AVX2 (see
        // `TrianglePacket::new`); the intrinsics touch registers only (the
        // vertex values are read by indexing).
        unsafe {
            let [sx, sy, sz] = self.shear;
            let vertex = |i: usize| sheared_vertex(b, i, j, self.k, &self.origin, sx, sy);
            let (ax, ay, az) = vertex(0);
            let (bx, by, bz) = vertex(1);
            let (cx, cy, cz) = vertex(2);
            let u = _mm256_sub_ps(_mm256_mul_ps(cx, by), _mm256_mul_ps(cy, bx));
            let v = _mm256_sub_ps(_mm256_mul_ps(ax, cy), _mm256_mul_ps(ay, cx));
            let w = _mm256_sub_ps(_mm256_mul_ps(bx, ay), _mm256_mul_ps(by, ax));
            let zero = _mm256_setzero_ps();
            let lo = _mm256_min_ps(u, _mm256_min_ps(v, w));
            let hi = _mm256_max_ps(u, _mm256_max_ps(v, w));
            // "All >= 0 or all <= 0", so that NaN edge functions (a
            // padding or collapsed triangle) count as outside, as in the
            // SSE block test: a packet meeting a partial block then stops
            // here at its padding triangles.
            let inside = _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(lo, zero),
                _mm256_cmp_ps::<_CMP_LE_OQ>(hi, zero),
            );
            if _mm256_movemask_ps(inside) as u32 & active == 0 {
                return None;
            }
            let on_edge = _mm256_and_ps(
                inside,
                _mm256_or_ps(
                    _mm256_cmp_ps::<_CMP_EQ_OQ>(lo, zero),
                    _mm256_cmp_ps::<_CMP_EQ_OQ>(hi, zero),
                ),
            );
            let det = _mm256_add_ps(_mm256_add_ps(u, v), w);
            let t_scaled = _mm256_add_ps(
                _mm256_add_ps(
                    _mm256_mul_ps(u, _mm256_mul_ps(sz, az)),
                    _mm256_mul_ps(v, _mm256_mul_ps(sz, bz)),
                ),
                _mm256_mul_ps(w, _mm256_mul_ps(sz, cz)),
            );
            let rcp = _mm256_div_ps(_mm256_set1_ps(1.0), det);
            let t = _mm256_mul_ps(t_scaled, rcp);
            let in_range = _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(t, self.t_min),
                _mm256_cmp_ps::<_CMP_LE_OQ>(t, t_max),
            );
            let ok = _mm256_andnot_ps(
                on_edge,
                _mm256_and_ps(
                    inside,
                    _mm256_and_ps(_mm256_cmp_ps::<_CMP_NEQ_UQ>(det, zero), in_range),
                ),
            );
            Some((
                _mm256_movemask_ps(ok) as u32,
                _mm256_movemask_ps(on_edge) as u32,
                t,
                _mm256_mul_ps(v, rcp),
                _mm256_mul_ps(w, rcp),
            ))
        }
    }

    /// The lanes of `mask` whose rays hit a triangle of blocks `first ..
    /// first + count` within their `[t_min, t_max]`. `scalar(lane, block,
    /// j)` decides lane `lane` against triangle `j` of `block` with the
    /// scalar test (edge functions of exactly zero).
    #[inline(always)]
    pub fn occluded_blocks(
        &self,
        blocks: &[Triangle4],
        first: u32,
        count: u32,
        mask: u32,
        mut scalar: impl FnMut(usize, &Triangle4, usize) -> bool,
    ) -> u32 {
        let mut hit = 0u32;
        for b in &blocks[first as usize..(first + count) as usize] {
            for j in 0..4 {
                let active = mask & !hit;
                if active == 0 {
                    return hit;
                }
                let Some((ok, on_edge, ..)) = self.test_triangle(b, j, self.t_max, active) else {
                    continue;
                };
                hit |= ok & active;
                let mut m = on_edge & active & !hit;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    if scalar(lane, b, j) {
                        hit |= 1 << lane;
                    }
                }
            }
        }
        hit
    }

    /// Closest hits of the lanes of `mask` among blocks `first .. first +
    /// count` with the single-ray leaf test's answers and rule
    /// ([`super::triangle4::nearer`]: nearer, or as near with a smaller
    /// key), so each lane ends with the hit its ray finds alone.
    /// `packet`'s per-lane `t_max` is each lane's running closest distance
    /// (shrunk here); `best` holds the keys of the lanes' closest hits so
    /// far, and a triangle's key is `key_base | slot`. `hit(lane, (t, u,
    /// v, slot))` records a new closest hit; `scalar(lane, block, j,
    /// t_max)` runs the scalar test for a lane whose edge functions round
    /// to zero.
    #[allow(clippy::too_many_arguments)] // the hot path: plain values
    #[inline(always)]
    pub fn closest_blocks(
        &self,
        blocks: &[Triangle4],
        first: u32,
        count: u32,
        mask: u32,
        packet: &mut Packet8,
        best: &mut LaneKeys,
        key_base: u64,
        mut hit: impl FnMut(usize, LeafHit),
        mut scalar: impl FnMut(usize, &Triangle4, usize, f32) -> Option<(f32, f32, f32)>,
    ) {
        for (i, b) in blocks[first as usize..(first + count) as usize]
            .iter()
            .enumerate()
        {
            let slot0 = (first + i as u32) * 4;
            for j in 0..4 {
                let Some((ok, on_edge, t, u, v)) = self.test_triangle(b, j, packet.t_max, mask)
                else {
                    continue;
                };
                let slot = slot0 + j as u32;
                let key = key_base | slot as u64;
                // SAFETY: AVX2 as in `test_triangle`; register arithmetic
                // and stores into local arrays.
                unsafe {
                    let mut ok = ok & mask;
                    // A lane's hit at exactly its closest distance (which
                    // `t <= t_max` lets through) wins on the smaller key.
                    let mut tie = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(t, packet.t_max))
                        as u32
                        & ok
                        & best.has;
                    while tie != 0 {
                        let lane = tie.trailing_zeros() as usize;
                        tie &= tie - 1;
                        if key >= best.keys[lane] {
                            ok &= !(1 << lane);
                        }
                    }
                    if ok != 0 {
                        let sel = lane_mask(ok);
                        packet.t_max = _mm256_blendv_ps(packet.t_max, t, sel);
                        let (mut tt, mut uu, mut vv) = ([0.0f32; 8], [0.0f32; 8], [0.0f32; 8]);
                        _mm256_storeu_ps(tt.as_mut_ptr(), t);
                        _mm256_storeu_ps(uu.as_mut_ptr(), u);
                        _mm256_storeu_ps(vv.as_mut_ptr(), v);
                        let mut m = ok;
                        while m != 0 {
                            let lane = m.trailing_zeros() as usize;
                            m &= m - 1;
                            best.set(lane, key);
                            hit(lane, (tt[lane], uu[lane], vv[lane], slot));
                        }
                    }
                }
                let mut m = on_edge & mask;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    let t_max = packet.lane_t_max(lane);
                    if let Some((t, u, v)) = scalar(lane, b, j, t_max)
                        && best.wins(lane, t, t_max, key)
                    {
                        packet.set_lane_t_max(lane, t);
                        best.set(lane, key);
                        hit(lane, (t, u, v, slot));
                    }
                }
            }
        }
    }
}

/// The keys of a packet's lanes' closest hits so far (see
/// [`TrianglePacket::closest_blocks`]): a hit's key orders exact ties.
#[derive(Clone, Copy, Debug)]
pub struct LaneKeys {
    /// The lanes holding a hit.
    pub has: u32,
    pub keys: [u64; PACKET],
}

impl LaneKeys {
    pub const NONE: LaneKeys = LaneKeys {
        has: 0,
        keys: [u64::MAX; PACKET],
    };

    /// Whether a hit at `t` with key `key` replaces lane `lane`'s closest,
    /// whose distance is `t_max` (the lane's running `t_max`, which equals
    /// it once the lane has a hit).
    #[inline(always)]
    pub fn wins(&self, lane: usize, t: f32, t_max: f32, key: u64) -> bool {
        self.has >> lane & 1 == 0 || t < t_max || (t == t_max && key < self.keys[lane])
    }

    #[inline(always)]
    pub fn set(&mut self, lane: usize, key: u64) {
        self.has |= 1 << lane;
        self.keys[lane] = key;
    }
}

/// An all-ones 32-bit lane for each set bit of `mask` (a blend selector).
///
/// # Safety
/// AVX2.
#[inline(always)]
unsafe fn lane_mask(mask: u32) -> __m256 {
    // SAFETY: register arithmetic on an AVX2 CPU (the caller's promise).
    unsafe {
        let bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
        let m = _mm256_and_si256(_mm256_set1_epi32(mask as i32), bits);
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(m, bits))
    }
}

/// Vertex `i` of triangle `j` of `b` relative to each lane's origin,
/// sheared: `(x - sx z, y - sy z, z)` in the permutation `k`, as the SSE
/// test computes it. A function, not a closure, so that it is always
/// inlined into the AVX2 caller (an out-of-line closure is not compiled for
/// AVX, and its intrinsics became calls).
#[inline(always)]
fn sheared_vertex(
    b: &Triangle4,
    i: usize,
    j: usize,
    [kx, ky, kz]: [usize; 3],
    origin: &[__m256; 3],
    sx: __m256,
    sy: __m256,
) -> (__m256, __m256, __m256) {
    // SAFETY: called only from `TrianglePacket::occluded_blocks`, whose
    // packet exists only on CPUs with AVX2; register arithmetic only.
    unsafe {
        let x = _mm256_sub_ps(_mm256_set1_ps(b.v[i][kx][j]), origin[0]);
        let y = _mm256_sub_ps(_mm256_set1_ps(b.v[i][ky][j]), origin[1]);
        let z = _mm256_sub_ps(_mm256_set1_ps(b.v[i][kz][j]), origin[2]);
        (
            _mm256_sub_ps(x, _mm256_mul_ps(sx, z)),
            _mm256_sub_ps(y, _mm256_mul_ps(sy, z)),
            z,
        )
    }
}

/// The scalar watertight test of triangle `j` of `block` for one ray (the
/// `f64` path of edge functions that round to zero): `true` on a hit.
#[inline(always)]
pub fn scalar_triangle(ray: &Ray, wray: &WatertightRay, block: &Triangle4, j: usize) -> bool {
    let [p0, p1, p2] = block.triangle(j);
    crate::triangle::intersect_triangle(wray, p0, p1, p2, ray.t_min, ray.t_max).is_some()
}

/// The scalar watertight test of triangle `j` of `block` for one ray
/// within `[ray.t_min, t_max]`, as `(t, u, v)`: the closest-hit form of
/// [`scalar_triangle`].
#[inline(always)]
pub fn scalar_closest(
    ray: &Ray,
    wray: &WatertightRay,
    block: &Triangle4,
    j: usize,
    t_max: f32,
) -> Option<(f32, f32, f32)> {
    let [p0, p1, p2] = block.triangle(j);
    crate::triangle::intersect_triangle(wray, p0, p1, p2, ray.t_min, t_max)
}

/// What a packet traversal does with one lane's ray where the packet
/// leaves off.
pub trait PacketLanes {
    /// Test leaf `(first, count)` for lane `lane`'s ray; `true` on a hit.
    fn leaf(&mut self, lane: usize, first: u32, count: u32) -> bool;
    /// Finish lane `lane`'s ray alone (the single-ray kernel) in the
    /// subtree of inner node `node`, whose box it entered; `true` on a hit.
    fn alone(&mut self, lane: usize, node: u32) -> bool;
    /// Test leaf `(first, count)` for the rays of the lanes in `mask` (the
    /// packet's); returns the lanes hit. Lane by lane unless overridden
    /// (the top level takes a packet on into an object BVH).
    #[inline(always)]
    fn leaf_packet(&mut self, packet: &Packet8, mask: u32, first: u32, count: u32) -> u32 {
        let _ = packet;
        leaf_by_lane(self, mask, first, count)
    }
}

/// Leaf `(first, count)` tested for each lane of `mask` alone
/// ([`PacketLanes::leaf`]); returns the lanes hit.
#[inline(always)]
pub fn leaf_by_lane(
    lanes: &mut (impl PacketLanes + ?Sized),
    mask: u32,
    first: u32,
    count: u32,
) -> u32 {
    let (mut m, mut hit) = (mask, 0);
    while m != 0 {
        let lane = m.trailing_zeros() as usize;
        m &= m - 1;
        if lanes.leaf(lane, first, count) {
            hit |= 1 << lane;
        }
    }
    hit
}

/// Occlusion of a packet's rays in the 8-wide tree `nodes` from its root:
/// returns the lanes found occluded. Children are visited in slot order,
/// as single-ray occlusion visits them.
#[inline(always)]
pub fn occluded_packet(
    nodes: &[WideNode<8>],
    packet: &Packet8,
    lanes: &mut impl PacketLanes,
) -> u32 {
    occluded_packet_from(nodes, packet, 0, packet.lanes, lanes)
}

/// [`occluded_packet`] for the lanes of `mask` from inner node `start`,
/// whose box their rays entered.
#[inline(always)]
pub fn occluded_packet_from(
    nodes: &[WideNode<8>],
    packet: &Packet8,
    start: u32,
    mask: u32,
    lanes: &mut impl PacketLanes,
) -> u32 {
    let all = mask;
    let mut stack = [MaybeUninit::<(u32, u32)>::uninit(); PACKET_STACK];
    let mut sp = 0usize;
    let mut done = 0u32;
    let (mut current, mut mask) = (start, mask);
    loop {
        mask &= !done;
        if mask != 0 {
            if is_leaf_ref(current) {
                let (first, count) = decode_leaf(current);
                done |= lanes.leaf_packet(packet, mask, first, count);
            } else if mask.count_ones() < SINGLE_BELOW {
                let mut m = mask;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    if lanes.alone(lane, current) {
                        done |= 1 << lane;
                    }
                }
            } else {
                let node = &nodes[current as usize];
                // SAFETY: a `Packet8` exists only on CPUs of the AVX2 level.
                let masks = unsafe { packet.test_node(node) };
                // Push the hit children last slot first, so that they pop
                // in slot order.
                for c in (0..8).rev() {
                    let hit = (masks >> (8 * c)) as u32 & mask;
                    if hit != 0 {
                        debug_assert!(sp < PACKET_STACK);
                        stack[sp].write((node.child[c], hit));
                        sp += 1;
                    }
                }
            }
        }
        if sp == 0 || done == all {
            return done;
        }
        sp -= 1;
        // SAFETY: entries below `sp` were all written by the push above
        // (`sp` only grows by writing `stack[sp]`).
        (current, mask) = unsafe { stack[sp].assume_init() };
    }
}

/// What a closest-hit packet traversal does with the lanes' rays where
/// the packet leaves off. Each keeps its lanes' closest hits; a closer hit
/// shrinks the lane's `t_max` in the packet, which culls the rest of the
/// walk for that lane.
pub trait ClosestLanes {
    /// Test leaf `(first, count)` for the rays of the lanes in `mask`.
    fn leaf_packet(&mut self, packet: &mut Packet8, mask: u32, first: u32, count: u32);
    /// Finish lane `lane`'s ray alone (the single-ray kernel, from the
    /// lane's running `t_max`) in the subtree of inner node `node`, whose
    /// box it entered.
    fn alone(&mut self, packet: &mut Packet8, lane: usize, node: u32);
}

/// Closest hits of the lanes of `mask` in the 8-wide tree `nodes` from
/// inner node `start` (whose box their rays entered; 0 for the root).
///
/// Every lane decides each box as its ray alone would (the single-ray
/// test's arithmetic against the lane's running `t_max`), so it visits a
/// subset of the leaves its ray visits alone, and every leaf holding a
/// triangle as near as its closest: with the shared closest-hit rule
/// ([`super::triangle4::nearer`], exact ties to the smaller key, whatever
/// the visit order) each lane ends with its ray's single-ray answer, bit
/// for bit and triangle for triangle. Hit children are visited nearest
/// first by the entry distance of the first lane that enters each (a cheap
/// stand-in for the packet's order); a popped entry keeps only the lanes
/// whose entry distance their `t_max` has not since passed (the single-ray
/// pop's test per lane).
#[inline(always)]
pub fn intersect_packet_from(
    nodes: &[WideNode<8>],
    packet: &mut Packet8,
    start: u32,
    mask: u32,
    lanes: &mut impl ClosestLanes,
) {
    let mut stack = [MaybeUninit::<PacketEntry>::uninit(); PACKET_STACK];
    let mut sp = 0usize;
    let (mut current, mut mask) = (start, mask);
    'walk: loop {
        if is_leaf_ref(current) {
            let (first, count) = decode_leaf(current);
            lanes.leaf_packet(packet, mask, first, count);
        } else if mask.count_ones() < SINGLE_BELOW {
            let mut m = mask;
            while m != 0 {
                let lane = m.trailing_zeros() as usize;
                m &= m - 1;
                lanes.alone(packet, lane, current);
            }
        } else {
            let node = &nodes[current as usize];
            // Hit children, sorted by distance (insertion sort, stable).
            let mut hits = [MaybeUninit::<(f32, PacketEntry)>::uninit(); 8];
            // SAFETY: a `Packet8` exists only on CPUs of the AVX2 level.
            let k = unsafe { packet.hit_children_sorted(node, mask, &mut hits) };
            if k > 0 {
                for h in hits[1..k].iter().rev() {
                    debug_assert!(sp < PACKET_STACK);
                    // SAFETY: as above, `hits[..k]` are written.
                    stack[sp].write(unsafe { h.assume_init_ref().1 });
                    sp += 1;
                }
                // SAFETY: `hits[0]` is written (`k > 0`).
                (current, mask, _) = unsafe { hits[0].assume_init_ref().1 };
                continue 'walk;
            }
        }
        loop {
            if sp == 0 {
                return;
            }
            sp -= 1;
            // SAFETY: entries below `sp` were all written by the push above
            // (`sp` only grows by writing `stack[sp]`).
            let (node, m, near) = unsafe { stack[sp].assume_init() };
            let m = m & packet.still_entered(&near);
            if m != 0 {
                (current, mask) = (node, m);
                break;
            }
        }
    }
}

/// Answer a run of rays in packets: valid rays that can join a packet
/// ([`packetable`]) are grouped by [`octant`] in their order and traced
/// eight at a time by `packet(rays, answers)` (writing lane `l`'s answer to
/// `answers[l]`), the rest of the groups at the end; other valid rays by
/// `alone(ray)`; invalid rays get `invalid`. `out[i]` answers `rays[i]`.
#[inline(always)]
pub fn in_packets<T: Copy>(
    rays: &[Ray],
    out: &mut [T],
    invalid: T,
    mut alone: impl FnMut(&Ray) -> T,
    mut packet: impl FnMut(&[&Ray], &mut [T; PACKET]),
) {
    assert_eq!(rays.len(), out.len(), "one output per ray");
    let mut pending = [[0usize; PACKET]; 8];
    let mut count = [0usize; 8];
    let mut trace = |idx: &[usize], out: &mut [T]| {
        let mut refs = [&rays[idx[0]]; PACKET];
        for (r, &i) in refs.iter_mut().zip(idx) {
            *r = &rays[i];
        }
        let mut answers = [invalid; PACKET];
        packet(&refs[..idx.len()], &mut answers);
        for (&a, &i) in answers.iter().zip(idx) {
            out[i] = a;
        }
    };
    for (i, r) in rays.iter().enumerate() {
        if !r.is_valid() {
            out[i] = invalid;
        } else if !packetable(r) {
            out[i] = alone(r);
        } else {
            let o = octant(r);
            pending[o][count[o]] = i;
            count[o] += 1;
            if count[o] == PACKET {
                trace(&pending[o], out);
                count[o] = 0;
            }
        }
    }
    for (group, &n) in pending.iter().zip(&count) {
        if n > 0 {
            trace(&group[..n], out);
        }
    }
}

/// Answer a run of rays in packets where consecutive rays are coherent:
/// from each valid ray on, the following rays that share its octant and
/// have a direction within [`COHERENT_COS`] of its own (up to eight, all
/// valid) are traced together by `packet(rays, out)` when there are at
/// least [`PACKET_FROM`] of them (writing `out[l]` for `rays[l]`; it returns
/// `false`, writing nothing, when a ray is not [`packetable`], and the ray
/// goes alone); the stretches of rays between packets, invalid ones
/// included, go to `alone(rays, out)`, which answers them one by one.
/// Camera rays in pixel order form packets of neighbouring pixels. A run
/// whose first rays are mostly incoherent (diffuse bounces) goes to
/// `alone` whole, without the per-ray checks (which cost such rays about
/// 50 instructions each, 3-4%: callgrind).
#[inline(always)]
pub fn in_coherent_packets<T>(
    rays: &[Ray],
    out: &mut [T],
    mut alone: impl FnMut(&[Ray], &mut [T]),
    mut packet: impl FnMut(&[&Ray], &mut [T]) -> bool,
) {
    assert_eq!(rays.len(), out.len(), "one output per ray");
    let c2 = COHERENT_COS * COHERENT_COS;
    let close = |a: &Ray, b: &Ray| {
        let d = a.dir.dot(b.dir);
        d > 0.0 && d * d >= c2 * a.dir.length_squared() * b.dir.length_squared()
    };
    let sample = rays.len().min(COHERENCE_SAMPLE);
    let close_pairs = rays[..sample]
        .windows(2)
        .filter(|w| close(&w[0], &w[1]))
        .count();
    if 2 * close_pairs < sample.saturating_sub(1) {
        alone(rays, out);
        return;
    }
    let (mut i, mut lone_from) = (0, 0);
    while i < rays.len() {
        let r0 = &rays[i];
        if !r0.is_valid() {
            i += 1;
            continue;
        }
        // Cheapest tests first: incoherent rays fail the cosine test.
        let (d0, o) = (r0.dir, octant(r0));
        let c2l0 = c2 * d0.length_squared();
        let mut n = 1;
        while n < PACKET && i + n < rays.len() {
            let r = &rays[i + n];
            let d = d0.dot(r.dir);
            if d <= 0.0 || d * d < c2l0 * r.dir.length_squared() || !r.is_valid() || octant(r) != o
            {
                break;
            }
            n += 1;
        }
        if n >= PACKET_FROM {
            if lone_from < i {
                alone(&rays[lone_from..i], &mut out[lone_from..i]);
                lone_from = i;
            }
            let mut refs = [r0; PACKET];
            for (r, q) in refs.iter_mut().zip(&rays[i..i + n]) {
                *r = q;
            }
            if packet(&refs[..n], &mut out[i..i + n]) {
                i += n;
                lone_from = i;
                continue;
            }
        }
        i += 1;
    }
    if lone_from < rays.len() {
        alone(&rays[lone_from..], &mut out[lone_from..]);
    }
}

/// Rays at the start of a run whose neighbours [`in_coherent_packets`]
/// compares to decide whether to look for packets in the run at all.
pub const COHERENCE_SAMPLE: usize = 16;

/// The fewest coherent rays traced as a packet by [`in_coherent_packets`].
pub const PACKET_FROM: usize = 4;

/// Answer the occlusion of a run of rays in packets: valid rays that can
/// join a packet ([`packetable`]) are grouped by [`octant`] in their order
/// and traced eight at a time by `packet(rays)` (returning the occluded
/// lanes), the rest of the groups at the end; other valid rays by
/// `alone(ray)`; invalid rays are not occluded. `out[i]` answers `rays[i]`.
/// (Grouping by octant and dominant axis instead, so that every packet
/// could run [`TrianglePacket`], split the packets three ways: re-braided
/// shadow rays on the instanced scenes 0.85-0.91, paired A/B.)
#[inline(always)]
pub fn occluded_in_packets(
    rays: &[Ray],
    out: &mut [bool],
    alone: impl FnMut(&Ray) -> bool,
    mut packet: impl FnMut(&[&Ray]) -> u32,
) {
    in_packets(rays, out, false, alone, |rays, answers| {
        let done = packet(rays);
        for (l, a) in answers.iter_mut().enumerate() {
            *a = done >> l & 1 != 0;
        }
    });
}

#[cfg(test)]
mod tests {
    use glam::Vec3;
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::Aabb;
    use crate::bvh::simd::x86::Avx2Tester;
    use crate::bvh::{BoxTester, Kernel};

    /// A packet's lane constants are each ray's [`FmaSlab`] ones bit for
    /// bit (the transposed eight-lane arithmetic against the single-ray
    /// one), its unused lanes repeat the first ray, and it is refused
    /// exactly when some ray is not [`packetable`] (zero direction
    /// components, huge offsets).
    #[test]
    fn packet_constants_are_each_rays_slab_constants() {
        if !Kernel::Avx2.is_available() {
            eprintln!("SKIPPED: no AVX2 on this CPU");
            return;
        }
        let mut rng = Pcg64::seed_from_u64(11);
        let mut refused = 0;
        for case in 0..5_000 {
            let n = rng.gen_range(1..=PACKET);
            let sign = Vec3::new(
                if rng.gen_bool(0.5) { 1.0 } else { -1.0 },
                if rng.gen_bool(0.5) { 1.0 } else { -1.0 },
                if rng.gen_bool(0.5) { 1.0 } else { -1.0 },
            );
            let rays: Vec<Ray> = (0..n)
                .map(|_| {
                    let mut d = Vec3::new(
                        rng.gen_range(0.001f32..1.0),
                        rng.gen_range(0.001f32..1.0),
                        rng.gen_range(0.001f32..1.0),
                    ) * sign;
                    if case % 7 == 0 && rng.gen_bool(0.3) {
                        d.y = 0.0 * sign.y;
                    }
                    let o = Vec3::new(
                        rng.gen_range(-1e3f32..1e3),
                        rng.gen_range(-1.0f32..1.0),
                        if case % 11 == 0 {
                            3e38
                        } else {
                            rng.gen_range(-5.0..5.0)
                        },
                    );
                    Ray {
                        origin: o,
                        t_min: rng.gen_range(0.0f32..0.1),
                        dir: d,
                        t_max: rng.gen_range(1.0f32..100.0),
                    }
                })
                .collect();
            let refs: Vec<&Ray> = rays.iter().collect();
            let all = rays.iter().all(packetable);
            // SAFETY: the AVX2 level is available (checked above).
            let Some(p) = (unsafe { Packet8::try_new(&refs) }) else {
                assert!(!all, "a packet of packetable rays was refused");
                refused += 1;
                continue;
            };
            assert!(all, "a packet with an unpacketable ray was built");
            let lanes = |v: __m256| -> [u32; PACKET] { bytemuck::cast(v) };
            for l in 0..PACKET {
                let r = &rays[if l < n { l } else { 0 }];
                let s = FmaSlab::new(r.origin, r.dir);
                for a in 0..3 {
                    assert_eq!(lanes(p.inv_dir[a])[l], s.inv_dir[a].to_bits());
                    assert_eq!(lanes(p.near_offset[a])[l], s.near_offset[a].to_bits());
                    assert_eq!(lanes(p.far_offset[a])[l], s.far_offset[a].to_bits());
                }
                assert_eq!(lanes(p.t_min)[l], r.t_min.to_bits());
                assert_eq!(lanes(p.t_max)[l], r.t_max.to_bits());
            }
            assert_eq!(p.lanes, (1u32 << n) - 1);
            let first = FmaSlab::new(rays[0].origin, rays[0].dir);
            assert_eq!(p.near, first.near_plane.map(|i| i * 32));
            assert_eq!(p.far, first.far_plane.map(|i| i * 32));
        }
        assert!(refused > 100, "the refusals were exercised: {refused}");
    }

    /// Each lane of the packet test decides every child exactly as the
    /// single-ray AVX2 test decides it for that lane's ray alone: random
    /// nodes (some flat boxes, some empty slots), packets of 1 to 8 rays of
    /// one octant aimed at the node's boxes, with finite and infinite
    /// `t_max`; and the node-level tests the walks call answer as the
    /// child test does slot by slot.
    #[test]
    fn each_lane_enters_the_boxes_its_ray_enters_alone() {
        if !Kernel::Avx2.is_available() {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        let mut rng = Pcg64::seed_from_u64(23);
        let v = |rng: &mut Pcg64, s: f32| {
            Vec3::new(
                rng.gen_range(-s..s),
                rng.gen_range(-s..s),
                rng.gen_range(-s..s),
            )
        };
        let (mut hits, mut misses, mut band) = (0u32, 0u32, 0u32);
        for _ in 0..10_000 {
            let mut node = WideNode::<8>::EMPTY;
            let children = rng.gen_range(2..=8);
            for i in 0..children {
                let lo = v(&mut rng, 4.0);
                let mut ext = v(&mut rng, 1.0).abs();
                if rng.gen_bool(0.2) {
                    ext.y = 0.0;
                }
                node.set_child(i, &Aabb::new(lo, lo + ext), i as u32);
            }
            let octant_signs = v(&mut rng, 1.0).signum();
            let n = rng.gen_range(1..=PACKET);
            let rays: Vec<Ray> = (0..n)
                .map(|_| {
                    // Aimed near a child's centre from the packet's octant.
                    let target =
                        node.child_bounds(rng.gen_range(0..children)).center() + v(&mut rng, 0.7);
                    let dir = v(&mut rng, 1.0).abs().max(Vec3::splat(1e-3)) * octant_signs;
                    let origin = target - dir * rng.gen_range(0.5..8.0);
                    Ray {
                        origin,
                        t_min: 0.0,
                        dir,
                        t_max: if rng.gen_bool(0.5) {
                            f32::INFINITY
                        } else {
                            rng.gen_range(0.1..10.0)
                        },
                    }
                })
                .collect();
            assert!(rays.iter().all(packetable));
            let refs: Vec<&Ray> = rays.iter().collect();
            // SAFETY: the AVX2 level is available (checked above).
            let packet = unsafe { Packet8::new(&refs) };
            assert_eq!(packet.lanes, (1 << n) - 1);
            // The node-level tests the walks use are the child test per
            // slot: the masks, and the hit children sorted by the first
            // entering lane's distance (stable), each with its lanes'
            // distances.
            // SAFETY: as above.
            let masks = unsafe { packet.test_node(&node) };
            let mask = rng.gen_range(1..=packet.lanes);
            let mut sorted = [MaybeUninit::uninit(); 8];
            // SAFETY: as above.
            let k = unsafe { packet.hit_children_sorted(&node, mask, &mut sorted) };
            let mut want_sorted = Vec::new();
            for c in 0..8 {
                let (hit, near) = packet.test_child_near(&node, c);
                assert_eq!((masks >> (8 * c)) as u32 & 0xff, hit, "slot {c}");
                let near: [f32; PACKET] = bytemuck::cast(near);
                if hit & mask != 0 {
                    let first = (hit & mask).trailing_zeros() as usize;
                    want_sorted.push((near[first], (node.child[c], hit & mask, near)));
                }
            }
            want_sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
            assert_eq!(k, want_sorted.len());
            for (i, w) in want_sorted.iter().enumerate() {
                // SAFETY: `hit_children_sorted` wrote `sorted[..k]`.
                let got = unsafe { sorted[i].assume_init() };
                assert_eq!(got.0.to_bits(), w.0.to_bits(), "entry {i}");
                assert_eq!((got.1.0, got.1.1), (w.1.0, w.1.1), "entry {i}");
                assert_eq!(got.1.2.map(f32::to_bits), w.1.2.map(f32::to_bits));
            }
            for (l, r) in rays.iter().enumerate() {
                // SAFETY: as above.
                let alone = unsafe { Avx2Tester::new(r) };
                let mut dist = [0.0; 8];
                let want = alone.test(&node, r.t_max, &mut dist);
                for c in 0..8 {
                    let got = packet.test_child(&node, c) >> l & 1;
                    if got != want >> c & 1 {
                        // The single-ray test's pad is a few ulps wider
                        // (`pad_far_bits`): only it may enter an extra box
                        // (but for a box behind the origin whose far
                        // distance underflowed to `-0.0`, which only the
                        // float test enters and these rays do not meet).
                        assert_eq!(got, 0, "lane {l} child {c}: {r:?}");
                        band += 1;
                    }
                    hits += got;
                    misses += 1 - got;
                }
            }
        }
        // Both answers must be common, or the test proves little; boxes
        // only the wider pad enters, rare.
        assert!(
            hits > 3_000 && misses > 10_000,
            "{hits} hits, {misses} misses"
        );
        assert!(band * 10_000 < hits, "{band} boxes entered alone only");
    }

    /// Blocks of the given triangles, four to a block, the last padded
    /// with NaN vertices (as `pack_triangle4` pads).
    fn blocks_of(tris: &[[Vec3; 3]]) -> Vec<crate::bvh::Triangle4> {
        tris.chunks(4)
            .map(|c| {
                let mut b = crate::bvh::Triangle4 {
                    v: [[[f32::NAN; 4]; 3]; 3],
                    prim: [u32::MAX; 4],
                };
                for (j, t) in c.iter().enumerate() {
                    for (vertex, p) in b.v.iter_mut().zip(t) {
                        for (axis, x) in vertex.iter_mut().zip(p.to_array()) {
                            axis[j] = x;
                        }
                    }
                    b.prim[j] = j as u32;
                }
                b
            })
            .collect()
    }

    /// The packet triangle test answers each lane as the ray's own
    /// four-triangle test does, for occlusion and for the closest hit:
    /// random triangles and rays of one octant and
    /// dominant axis aimed at them, and integer triangles with rays through
    /// their vertices and edges exactly (edge functions of zero, which both
    /// hand to the scalar test), with infinite and short `t_max`.
    #[test]
    fn packet_triangle_test_answers_as_each_ray_alone() {
        use crate::bvh::triangle4::intersect_blocks;
        if !Kernel::Avx2.is_available() {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        let mut rng = Pcg64::seed_from_u64(29);
        let (mut hits, mut misses, mut edges) = (0u32, 0u32, 0u32);
        for round in 0..3_000 {
            let exact = round % 3 == 0;
            let tris: Vec<[Vec3; 3]> = (0..rng.gen_range(1..=9))
                .map(|_| {
                    if exact {
                        let p = Vec3::new(
                            rng.gen_range(-4..4) as f32,
                            rng.gen_range(-4..4) as f32,
                            rng.gen_range(-4..4) as f32,
                        );
                        [p, p + Vec3::X * 2.0, p + Vec3::Y * 2.0]
                    } else {
                        let p = Vec3::new(
                            rng.gen_range(-3.0..3.0),
                            rng.gen_range(-3.0..3.0),
                            rng.gen_range(-3.0..3.0),
                        );
                        let e = |rng: &mut Pcg64| {
                            Vec3::new(
                                rng.gen_range(-1.5..1.5),
                                rng.gen_range(-1.5..1.5),
                                rng.gen_range(-1.5..1.5),
                            )
                        };
                        [p, p + e(&mut rng), p + e(&mut rng)]
                    }
                })
                .collect();
            let blocks = blocks_of(&tris);
            // One octant, z dominant: signs shared, |dz| largest.
            let sign = |rng: &mut Pcg64| if rng.gen_bool(0.5) { 1.0 } else { -1.0 };
            let signs = Vec3::new(sign(&mut rng), sign(&mut rng), sign(&mut rng));
            let n = rng.gen_range(1..=PACKET);
            let rays: Vec<Ray> = (0..n)
                .map(|_| {
                    let t = tris[rng.gen_range(0..tris.len())];
                    let (target, dir) = if exact {
                        // Through a vertex or an edge's midpoint exactly.
                        let target = match rng.gen_range(0..3) {
                            0 => t[0],
                            1 => (t[0] + t[1]) * 0.5,
                            _ => t[1],
                        };
                        (target, Vec3::new(1.0, 1.0, 4.0) * signs)
                    } else {
                        let (a, b) = (rng.gen_range(0.0..0.7f32), rng.gen_range(0.0..0.7f32));
                        let target = t[0] + (t[1] - t[0]) * a + (t[2] - t[0]) * b * (1.0 - a);
                        let d = Vec3::new(
                            rng.gen_range(0.05..0.9),
                            rng.gen_range(0.05..0.9),
                            rng.gen_range(1.0..2.0),
                        );
                        (target, d * signs)
                    };
                    Ray {
                        origin: target - dir * 2.0,
                        t_min: 0.0,
                        dir,
                        t_max: if rng.gen_bool(0.3) {
                            rng.gen_range(0.5..2.5)
                        } else {
                            f32::INFINITY
                        },
                    }
                })
                .collect();
            let refs: Vec<&Ray> = rays.iter().collect();
            let wrays: Vec<WatertightRay> = rays
                .iter()
                .map(|r| WatertightRay::new(r.origin, r.dir))
                .collect();
            // SAFETY: AVX2 is available (checked above).
            let packet = unsafe { TrianglePacket::new(&refs, |l| wrays[l]) }
                .expect("one octant and one dominant axis share the permutation");
            let mask = (1u32 << n) - 1;
            let mut scalar_lanes = 0;
            let got = packet.occluded_blocks(&blocks, 0, blocks.len() as u32, mask, |l, b, j| {
                scalar_lanes += 1;
                scalar_triangle(&rays[l], &wrays[l], b, j)
            });
            edges += scalar_lanes;
            // Closest hits: each lane's is its ray's own leaf test's, bit
            // for bit (t, u, v and slot).
            // SAFETY: the AVX2 level is available (checked above).
            let mut lanes8 = unsafe { Packet8::new(&refs) };
            let mut keys = LaneKeys::NONE;
            let mut closest = [None; PACKET];
            packet.closest_blocks(
                &blocks,
                0,
                blocks.len() as u32,
                mask,
                &mut lanes8,
                &mut keys,
                0,
                |l, h| closest[l] = Some(h),
                |l, b, j, t_max| scalar_closest(&rays[l], &wrays[l], b, j, t_max),
            );
            for (l, r) in rays.iter().enumerate() {
                let mut best = None;
                intersect_blocks::<false>(
                    &blocks,
                    &wrays[l],
                    r.t_min,
                    0,
                    blocks.len() as u32,
                    &mut r.t_max.clone(),
                    &mut best,
                    true,
                );
                let bits = |h: Option<LeafHit>| {
                    h.map(|(t, u, v, k)| (t.to_bits(), u.to_bits(), v.to_bits(), k))
                };
                assert_eq!(
                    bits(closest[l]),
                    bits(best),
                    "round {round} lane {l}: {r:?}"
                );
                assert_eq!(keys.has >> l & 1 != 0, best.is_some());
            }
            for (l, r) in rays.iter().enumerate() {
                let alone = intersect_blocks::<true>(
                    &blocks,
                    &wrays[l],
                    r.t_min,
                    0,
                    blocks.len() as u32,
                    &mut r.t_max.clone(),
                    &mut None,
                    true,
                );
                assert_eq!(got >> l & 1 != 0, alone, "round {round} lane {l}: {r:?}");
                hits += alone as u32;
                misses += !alone as u32;
            }
        }
        assert!(
            hits > 2_000 && misses > 2_000 && edges > 100,
            "{hits} hits, {misses} misses, {edges} scalar tests"
        );
    }
}
