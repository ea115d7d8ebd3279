//! Occlusion of packets of up to eight rays that share a direction octant,
//! through 8-wide trees (AVX2): each child box is tested against all the
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
//! Every lane's box test is the single-ray AVX2 test's arithmetic in the
//! same order (the same [`FmaSlab`] constants, one FMA per plane, the same
//! `max`/`min` chain and [`ROBUST_FAR`] pad), so a ray enters exactly the
//! boxes it enters alone, and the triangle tests are the single-ray ones:
//! an occlusion answer is the same as the single-ray kernel's.

use core::arch::x86_64::*;
use std::mem::MaybeUninit;

use super::simd::FmaSlab;
use super::wide::{WIDE_EMPTY, WideNode, decode_leaf, is_leaf_ref};
use super::{MAX_DEPTH, ROBUST_FAR};
use crate::Ray;

/// Rays per packet: the lanes of an AVX2 vector.
pub const PACKET: usize = 8;

/// Entries of a packet traversal stack: all hit children of each node on
/// the path (at most 8 per level, wide depth below [`MAX_DEPTH`]).
const PACKET_STACK: usize = 8 * MAX_DEPTH as usize;

/// A subtree reached by fewer active rays than this is traversed by each
/// of them alone: testing a node for one or two lanes costs about what the
/// single-ray test costs per ray, and the single-ray kernel's closer
/// per-ray culling wins then.
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
/// finite (no zero direction component), as the single-ray AVX2 test
/// requires for its fast path; other rays are traced alone.
#[inline(always)]
pub fn packetable(ray: &Ray) -> bool {
    FmaSlab::new(ray.origin, ray.dir).is_finite()
}

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
    /// Callers must run on a CPU with AVX2 and FMA (the packet's existence
    /// is what [`Packet8::test_child`] relies on).
    // The lane index picks from eleven per-lane arrays at once.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    pub unsafe fn new(rays: &[&Ray]) -> Self {
        debug_assert!((1..=PACKET).contains(&rays.len()));
        let mut lane = [[0.0f32; PACKET]; 11];
        for l in 0..PACKET {
            // Unused lanes repeat the first ray: finite, and masked off.
            let r = rays.get(l).unwrap_or(&rays[0]);
            let s = FmaSlab::new(r.origin, r.dir);
            debug_assert!(s.is_finite());
            for a in 0..3 {
                lane[a][l] = s.inv_dir[a];
                lane[3 + a][l] = s.near_offset[a];
                lane[6 + a][l] = s.far_offset[a];
            }
            lane[9][l] = r.t_min;
            lane[10][l] = r.t_max;
        }
        let first = FmaSlab::new(rays[0].origin, rays[0].dir);
        debug_assert!(rays.iter().all(|r| octant(r) == octant(rays[0])));
        let v = |k: usize| -> __m256 { bytemuck::cast(lane[k]) };
        Self {
            inv_dir: [v(0), v(1), v(2)],
            near_offset: [v(3), v(4), v(5)],
            far_offset: [v(6), v(7), v(8)],
            t_min: v(9),
            t_max: v(10),
            near: first.near_plane.map(|i| i * 32),
            far: first.far_plane.map(|i| i * 32),
            lanes: (1u32 << rays.len()) - 1,
        }
    }

    /// The lanes whose ray enters child slot `c` of `node` (all lanes
    /// tested; callers mask).
    #[inline(always)]
    fn test_child(&self, node: &WideNode<8>, c: usize) -> u32 {
        debug_assert!(c < 8);
        let planes = node.planes().as_ptr().cast::<u8>();
        // SAFETY: a `Packet8` exists only on CPUs with AVX2 and FMA (see
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
            _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32
        }
    }
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
                // Children fill the first slots; push the hit ones last slot
                // first, so that they pop in slot order.
                let n = node
                    .child
                    .iter()
                    .position(|&c| c == WIDE_EMPTY)
                    .unwrap_or(8);
                for c in (0..n).rev() {
                    let hit = packet.test_child(node, c) & mask;
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

/// Answer the occlusion of a run of rays in packets: valid rays that can
/// join a packet ([`packetable`]) are grouped by [`octant`] in their order
/// and traced eight at a time by `packet(rays)` (returning the occluded
/// lanes), the rest of the groups at the end; other valid rays by
/// `alone(ray)`; invalid rays are not occluded. `out[i]` answers `rays[i]`.
#[inline(always)]
pub fn occluded_in_packets(
    rays: &[Ray],
    out: &mut [bool],
    mut alone: impl FnMut(&Ray) -> bool,
    mut packet: impl FnMut(&[&Ray]) -> u32,
) {
    assert_eq!(rays.len(), out.len(), "one output per ray");
    let mut pending = [[0usize; PACKET]; 8];
    let mut count = [0usize; 8];
    let mut trace = |idx: &[usize], out: &mut [bool]| {
        let mut refs = [&rays[idx[0]]; PACKET];
        for (r, &i) in refs.iter_mut().zip(idx) {
            *r = &rays[i];
        }
        let done = packet(&refs[..idx.len()]);
        for (l, &i) in idx.iter().enumerate() {
            out[i] = done >> l & 1 != 0;
        }
    };
    for (i, r) in rays.iter().enumerate() {
        if !r.is_valid() {
            out[i] = false;
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
    for o in 0..8 {
        if count[o] > 0 {
            trace(&pending[o][..count[o]], out);
        }
    }
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

    /// Each lane of the packet test decides every child exactly as the
    /// single-ray AVX2 test decides it for that lane's ray alone: random
    /// nodes (some flat boxes, some empty slots), packets of 1 to 8 rays of
    /// one octant aimed at the node's boxes, with finite and infinite
    /// `t_max`.
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
        let (mut hits, mut misses) = (0u32, 0u32);
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
            // SAFETY: AVX2 and FMA are available (checked above).
            let packet = unsafe { Packet8::new(&refs) };
            assert_eq!(packet.lanes, (1 << n) - 1);
            for (l, r) in rays.iter().enumerate() {
                // SAFETY: as above.
                let alone = unsafe { Avx2Tester::new(r.origin, r.dir, r.t_min) };
                let mut dist = [0.0; 8];
                let want = alone.test(&node, r.t_max, &mut dist);
                for c in 0..8 {
                    let got = packet.test_child(&node, c) >> l & 1;
                    assert_eq!(got, want >> c & 1, "lane {l} child {c}: {r:?}");
                    hits += got;
                    misses += 1 - got;
                }
            }
        }
        // Both answers must be common, or the test proves little.
        assert!(
            hits > 3_000 && misses > 10_000,
            "{hits} hits, {misses} misses"
        );
    }
}
