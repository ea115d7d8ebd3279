//! Rays through a committed top level and into the object BVHs: one ray at
//! a time ([`walk_ray`]), runs of rays in one kernel context, and packets.

use super::*;

/// The best hit so far inside a top-level traversal: (t, u, v, hit
/// reference within its object (see [`ObjectBvh::hit_record`]), ref index).
pub(super) type RefHit = (f32, f32, f32, u32, u32);

/// The closest-hit rule of the top level (see
/// [`crate::bvh::triangle4::nearer`]): nearer, or exactly as near with a
/// smaller (ref index, hit reference); each triangle has one such key, so
/// ties go the same way in any visit order.
#[inline(always)]
pub(super) fn nearer_ref(t: f32, ri: u32, k: u32, best: &Option<RefHit>) -> bool {
    best.is_none_or(|b| t < b.0 || (t == b.0 && (ri, k) < (b.4, b.3)))
}

/// The [`RefHit`] key as one integer (ref index above, hit reference
/// below), for the packet lanes' tie rule.
#[inline(always)]
pub(super) fn ref_key(ri: u32, k: u32) -> u64 {
    (ri as u64) << 32 | k as u64
}

/// The ref index of a [`RefHit`] in the top level's own copied blocks (the
/// hit reference is then a lane of [`TopLevelAccel::blocks`]).
pub(super) const INLINE_HIT: u32 = u32::MAX;

/// Prepared instance rays kept by a single-ray walk (see `RayState`).
pub(super) const INSTANCE_CACHE: usize = 4;

/// Prepared instance rays kept per lane of a packet: one. Each slot holds
/// the instance ray's AVX2 box tester too (about 500 bytes in all), so
/// four slots per lane made a packet's lane states 16 KB of its stack
/// frame, with one byte of each slot written when the states are made.
/// One slot, measured (session 15, paired medians of 10 alternations,
/// re-braided, one thread, 480x270): primary rays 4-8% faster on every
/// shared scene, shadow rays 2-4%, diffuse rays (walked alone) unchanged;
/// callgrind's first-level misses per samurai monastery primary ray 4.24
/// -> 3.51.
pub(super) const LANE_INSTANCE_CACHE: usize = 1;

/// An instance's id and the ray in its space, prepared for its box and
/// triangle tests, with its SIMD box tester (made when an entry into one of
/// the instance's wide nodes first needs it).
pub(super) type InstanceRay<T> = (u32, Ray, WatertightRay, Option<T>);

/// One ray through the top level and into the object BVHs, inside a SIMD
/// kernel's context (see [`with_kernel`]): testers are made for the world
/// ray once and for each instance's object-space ray once per run of refs
/// sharing the instance, not per top-level leaf. `ANY`: stop at the first
/// hit (occlusion). The caller has checked [`Ray::is_valid`].
#[inline(always)]
pub(super) fn walk_ray<const ANY: bool, F: TesterFactory>(
    a: &TopLevelAccel,
    ray: &Ray,
    factory: &F,
    counters: &mut TraversalCounters,
) -> Option<RefHit> {
    // No separate root-box test: the kernel tests the root's children.
    let Some(wide) = &a.wide else {
        return None;
    };
    let world = factory.make(ray);
    let mut state = RayState::<_, INSTANCE_CACHE>::new(ray);
    state.walk_from::<ANY, F>(a, &wide.nodes, factory, &world, 0, counters);
    counters.inner_visited += state.inner.inner_visited;
    counters.leaves_visited += state.inner.leaves_visited;
    counters.entries_visited += state.inner.entries_visited;
    state.best
}

/// What one ray's walk through the top level keeps besides its box
/// tester: the world ray's shear (made for the first ref placed directly:
/// scenes of instances never need it), the prepared instance rays, the
/// object levels' visit counts and the best hit so far.
pub(super) struct RayState<'r, T, const N: usize> {
    ray: &'r Ray,
    wray: Option<WatertightRay>,
    /// `N` prepared instance rays, direct-mapped by instance id: refs of
    /// a few overlapping instances alternate along a ray
    /// ([`INSTANCE_CACHE`] for a single-ray walk, [`LANE_INSTANCE_CACHE`]
    /// for a packet's lanes).
    cached: [Option<InstanceRay<T>>; N],
    inner: TraversalCounters,
    best: Option<RefHit>,
}

impl<'r, T: BoxTester<8> + Copy, const N: usize> RayState<'r, T, N> {
    #[inline(always)]
    fn new(ray: &'r Ray) -> Self {
        Self {
            ray,
            wray: None,
            cached: [None; N],
            inner: TraversalCounters::default(),
            best: None,
        }
    }

    /// Walk the top level from node `start` (whose box the ray entered)
    /// with the ray's tester `world`, within the closest hit so far.
    #[inline(always)]
    fn walk_from<const ANY: bool, F: TesterFactory<Tester = T>>(
        &mut self,
        a: &TopLevelAccel,
        nodes: &[WideNode<8>],
        factory: &F,
        world: &T,
        start: u32,
        counters: &mut TraversalCounters,
    ) {
        // A lane of a closest-hit packet goes on alone from its closest
        // hit so far (a fresh walk has none).
        let t_max = self.best.map_or(self.ray.t_max, |b| b.0);
        traverse_with::<ANY, _, _>(
            nodes,
            world,
            start,
            t_max,
            counters,
            #[inline(always)]
            |first, count, t_max| self.leaf::<ANY, F>(a, factory, world, first, count, t_max),
        );
    }

    /// A top-level leaf: its copied blocks or its entries into the object
    /// BVHs; returns `true` to stop (any hit).
    #[inline(always)]
    fn leaf<const ANY: bool, F: TesterFactory<Tester = T>>(
        &mut self,
        a: &TopLevelAccel,
        factory: &F,
        world: &T,
        first: u32,
        count: u32,
        t_max: &mut f32,
    ) -> bool {
        if first >= a.block_base {
            return self.copied_leaf::<ANY, F>(a, factory, first, count, t_max, T::SIMD_TRIANGLES);
        }
        for ri in first..first + count {
            if let Some((t, u, v, k)) = self.entry::<ANY, F>(a, factory, world, ri, *t_max) {
                if ANY {
                    self.best = Some((t, u, v, k, ri));
                    return true;
                }
                if nearer_ref(t, ri, k, &self.best) {
                    *t_max = t;
                    self.best = Some((t, u, v, k, ri));
                }
            }
        }
        false
    }

    /// A top-level leaf of copied blocks (`first >= a.block_base`): its
    /// hit becomes the best by the entries' rule (the blocks were tested
    /// against `t_max` inclusive, which equals the best hit's distance).
    /// Needs no box tester. Returns `true` to stop (any hit).
    #[inline(always)]
    fn copied_leaf<const ANY: bool, F: TesterFactory>(
        &mut self,
        a: &TopLevelAccel,
        factory: &F,
        first: u32,
        count: u32,
        t_max: &mut f32,
        simd: bool,
    ) -> bool {
        let mut hit = None;
        let stop = self.copied_blocks::<ANY, F>(a, factory, first, count, t_max, &mut hit, simd);
        if let Some((t, u, v, k)) = hit
            && (ANY || nearer_ref(t, INLINE_HIT, k, &self.best))
        {
            self.best = Some((t, u, v, k, INLINE_HIT));
        }
        stop
    }

    /// A top-level leaf naming an object leaf's triangle blocks copied into
    /// the top level (see `inline_leaf_blocks`; `first >= a.block_base`):
    /// tested here, and counted once, as the top-level leaf it is, into
    /// `hit` (the caller keeps it or not). Needs no box tester. Returns
    /// `true` to stop (any hit).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)] // the hot path: plain values
    fn copied_blocks<const ANY: bool, F: TesterFactory>(
        &mut self,
        a: &TopLevelAccel,
        factory: &F,
        first: u32,
        count: u32,
        t_max: &mut f32,
        hit: &mut Option<(f32, f32, f32, u32)>,
        simd: bool,
    ) -> bool {
        let ray = self.ray;
        let wray = self.wray(factory);
        intersect_blocks::<ANY>(
            &a.blocks,
            wray,
            ray.t_min,
            first - a.block_base,
            count,
            t_max,
            hit,
            simd,
        )
    }

    /// The closest (or, with `ANY`, some) hit within `t_max` through entry
    /// `ri`, as [`ObjectBvh::query_entry`] reports it.
    #[inline(always)]
    fn entry<const ANY: bool, F: TesterFactory<Tester = T>>(
        &mut self,
        a: &TopLevelAccel,
        factory: &F,
        world: &T,
        ri: u32,
        t_max: f32,
    ) -> Option<(f32, f32, f32, u32)> {
        let ray = self.ray;
        self.inner.entries_visited += 1;
        let r = &a.entries[ri as usize];
        let obj = a
            .objects
            .get(r.object as usize)
            .and_then(|o| o.as_deref())?;
        if r.instance == INVALID_ID {
            let wray = self.wray.get_or_insert_with(|| factory.watertight(ray));
            obj.query_entry::<ANY, _>(r.wide, r.node, ray, wray, world, t_max, &mut self.inner)
        } else {
            let slot = &mut self.cached[r.instance as usize % N];
            if slot.as_ref().is_none_or(|c| c.0 != r.instance) {
                let lr = a.instances[r.instance as usize].local_ray(ray);
                let lw = factory.watertight(&lr);
                *slot = Some((r.instance, lr, lw, None));
            }
            let (_, lr, lw, lt) = slot.as_mut().expect("set just above");
            // The box tester only for an entry into a wide node: a leaf's
            // blocks (and the binary fallback) never use it, and most
            // instanced entries of a re-braided top level are leaves.
            let tester = if is_leaf_ref(r.wide) {
                world
            } else {
                &*lt.get_or_insert_with(|| factory.make(lr))
            };
            obj.query_entry::<ANY, _>(r.wide, r.node, lr, lw, tester, t_max, &mut self.inner)
        }
    }

    /// The world ray's watertight form (made on first use).
    #[inline(always)]
    fn wray<F: TesterFactory>(&mut self, factory: &F) -> &WatertightRay {
        let ray = self.ray;
        self.wray.get_or_insert_with(|| factory.watertight(ray))
    }
}

/// One ray's query, run by [`with_kernel`].
pub(super) struct RayWalk<'a, const ANY: bool> {
    pub(super) accel: &'a TopLevelAccel,
    pub(super) ray: &'a Ray,
    pub(super) counters: &'a mut TraversalCounters,
    pub(super) best: Option<RefHit>,
}

impl<const ANY: bool> WideQuery for RayWalk<'_, ANY> {
    #[inline(always)]
    fn run<F: TesterFactory>(&mut self, factory: &F) {
        self.best = walk_ray::<ANY, F>(self.accel, self.ray, factory, self.counters);
    }
}

/// A run of rays answered inside one kernel context: the kernel dispatch,
/// the call into the target-feature function and its frame set-up are paid
/// once per run instead of once per ray (callgrind: about 90 of samurai
/// monastery's 939 instructions per shadow ray were that set-up).
/// `answer(accel, hit)` makes each ray's output from its walk.
pub(super) struct BatchWalk<'a, const ANY: bool, O, A> {
    pub(super) accel: &'a TopLevelAccel,
    pub(super) rays: &'a [Ray],
    pub(super) out: &'a mut [O],
    pub(super) answer: A,
}

impl<const ANY: bool, O, A> WideQuery for BatchWalk<'_, ANY, O, A>
where
    A: Fn(&TopLevelAccel, Option<RefHit>) -> O,
{
    #[inline(always)]
    fn run<F: TesterFactory>(&mut self, factory: &F) {
        let a = self.accel;
        for (o, ray) in self.out.iter_mut().zip(self.rays) {
            let hit = if ray.is_valid() {
                walk_ray::<ANY, F>(a, ray, factory, &mut TraversalCounters::default())
            } else {
                None
            };
            *o = (self.answer)(a, hit);
        }
    }
}

/// Occlusion and closest hits in packets through the top level (AVX2).
#[cfg(target_arch = "x86_64")]
pub(super) mod packets {
    use super::{INLINE_HIT, LANE_INSTANCE_CACHE, RayState, RefHit, TopLevelAccel};
    use crate::bvh::packet::{
        ClosestLanes, LaneKeys, PACKET, PACKET_TRIANGLES_FROM, Packet8, PacketLanes, SINGLE_BELOW,
        TrianglePacket, in_coherent_packets, intersect_packet_from, leaf_by_lane,
        occluded_in_packets, occluded_packet, occluded_packet_from, scalar_closest,
        scalar_triangle,
    };
    use crate::bvh::simd::x86::Avx2Tester;
    use crate::bvh::simd::{Avx2Factory, ClosestTriangleLanes, LaneWrays, TriangleLanes};
    use crate::bvh::triangle4::LeafHit;
    use crate::bvh::wide::is_leaf_ref;
    use crate::bvh::{TesterFactory, TraversalCounters, WideNode};
    use crate::triangle::WatertightRay;
    use crate::{Hit, INVALID_ID, Ray};

    /// A packet's rays: each lane's world tester (made when the lane first
    /// needs it) and walk state.
    struct Lanes<'a> {
        accel: &'a TopLevelAccel,
        nodes: &'a [WideNode<8>],
        factory: &'a Avx2Factory,
        rays: &'a [&'a Ray],
        worlds: [Option<Avx2Tester>; PACKET],
        states: [RayState<'a, Avx2Tester, LANE_INSTANCE_CACHE>; PACKET],
        /// The packet triangle test's constants, made when a leaf most of
        /// the packet reaches first needs them (instanced scenes rarely
        /// do): `Some(None)` when the rays' axis permutations differ.
        triangles: Option<Option<TrianglePacket>>,
    }

    impl Lanes<'_> {
        /// See [`Lanes::triangles`].
        #[inline(always)]
        fn triangles(&mut self) -> Option<&TrianglePacket> {
            if self.triangles.is_none() {
                let (states, factory) = (&mut self.states, self.factory);
                // SAFETY: `Lanes` exist only inside `occluded`, which runs
                // only on CPUs of the AVX2 level.
                let t = unsafe { TrianglePacket::new(self.rays, |l| *states[l].wray(factory)) };
                self.triangles = Some(t);
            }
            self.triangles.as_ref().and_then(Option::as_ref)
        }
    }

    /// The lanes' watertight rays inside an object BVH placed directly:
    /// the world rays', kept in the lanes' walk states (made on first use).
    struct StateWrays<'s, 'r> {
        states: &'s mut [RayState<'r, Avx2Tester, LANE_INSTANCE_CACHE>; PACKET],
        factory: &'s Avx2Factory,
    }

    impl LaneWrays for StateWrays<'_, '_> {
        #[inline(always)]
        fn wray(&mut self, lane: usize) -> &WatertightRay {
            self.states[lane].wray(self.factory)
        }
    }

    impl PacketLanes for Lanes<'_> {
        /// Entries into object BVHs placed directly take the packet on
        /// into the object's wide tree (the world ray is the object's ray,
        /// so the packet's constants hold there); instanced entries,
        /// copied blocks and entries few rays reach go lane by lane.
        #[inline(always)]
        fn leaf_packet(&mut self, packet: &Packet8, mask: u32, first: u32, count: u32) -> u32 {
            let a = self.accel;
            if first >= a.block_base {
                // Copied blocks: one triangle for all the rays at once
                // when most of the packet is here, else lane by lane.
                if mask.count_ones() < PACKET_TRIANGLES_FROM {
                    return leaf_by_lane(self, mask, first, count);
                }
                let Some(&triangles) = self.triangles() else {
                    return leaf_by_lane(self, mask, first, count);
                };
                let (rays, states, factory) = (self.rays, &mut self.states, self.factory);
                return triangles.occluded_blocks(
                    &a.blocks,
                    first - a.block_base,
                    count,
                    mask,
                    |lane, b, j| scalar_triangle(rays[lane], states[lane].wray(factory), b, j),
                );
            }
            let mut left = mask;
            for ri in first..first + count {
                if left == 0 {
                    break;
                }
                let e = &a.entries[ri as usize];
                let Some(obj) = a.objects.get(e.object as usize).and_then(|o| o.as_deref()) else {
                    continue;
                };
                if e.instance == INVALID_ID
                    && left.count_ones() >= SINGLE_BELOW
                    && !is_leaf_ref(e.wide)
                    && let Some(w) = &obj.wide
                {
                    // The world testers serve inside: the object is in
                    // world space.
                    let triangles = self.triangles().copied();
                    let mut sub = TriangleLanes {
                        nodes: &w.wide.nodes,
                        blocks: &w.blocks,
                        factory: self.factory,
                        rays: self.rays,
                        testers: &mut self.worlds,
                        wrays: StateWrays {
                            states: &mut self.states,
                            factory: self.factory,
                        },
                        triangles: triangles.as_ref(),
                    };
                    left &= !occluded_packet_from(&w.wide.nodes, packet, e.wide, left, &mut sub);
                    continue;
                }
                let mut m = left;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    let r = self.rays[lane];
                    let world = self.worlds[lane].get_or_insert_with(|| self.factory.make(r));
                    if self.states[lane]
                        .entry::<true, _>(a, self.factory, world, ri, r.t_max)
                        .is_some()
                    {
                        left &= !(1 << lane);
                    }
                }
            }
            mask & !left
        }

        #[inline(always)]
        fn leaf(&mut self, lane: usize, first: u32, count: u32) -> bool {
            let r = self.rays[lane];
            let a = self.accel;
            if first >= a.block_base {
                // Copied blocks need no box tester: not made for them.
                return self.states[lane].copied_blocks::<true, _>(
                    a,
                    self.factory,
                    first,
                    count,
                    &mut r.t_max.clone(),
                    &mut None,
                    true,
                );
            }
            self.entries_leaf::<true>(lane, first, count, &mut r.t_max.clone())
        }

        #[inline(always)]
        fn alone(&mut self, lane: usize, node: u32) -> bool {
            let r = self.rays[lane];
            let world = self.worlds[lane].get_or_insert_with(|| self.factory.make(r));
            let state = &mut self.states[lane];
            state.walk_from::<true, _>(
                self.accel,
                self.nodes,
                self.factory,
                world,
                node,
                &mut TraversalCounters::default(),
            );
            state.best.is_some()
        }
    }

    impl Lanes<'_> {
        /// The entries of top-level leaf `(first, count)` for lane `lane`
        /// alone, within `t_max` ([`RayState::leaf`], with the lane's world
        /// tester made on first use): the occlusion and closest-hit lanes'
        /// one path into the objects.
        #[inline(always)]
        fn entries_leaf<const ANY: bool>(
            &mut self,
            lane: usize,
            first: u32,
            count: u32,
            t_max: &mut f32,
        ) -> bool {
            let r = self.rays[lane];
            let world = self.worlds[lane].get_or_insert_with(|| self.factory.make(r));
            self.states[lane].leaf::<ANY, _>(self.accel, self.factory, world, first, count, t_max)
        }

        /// The keys of the lanes' closest hits (see
        /// [`super::nearer_ref`]).
        #[inline(always)]
        fn lane_keys(&self) -> LaneKeys {
            let mut keys = LaneKeys::NONE;
            for (l, s) in self.states.iter().enumerate() {
                if let Some(b) = s.best {
                    keys.set(l, super::ref_key(b.4, b.3));
                }
            }
            keys
        }

        /// Make the lanes' new closest hits `hits` (each one replaces the
        /// lane's closest before by the rule: see `ClosestTriangleLanes`)
        /// their best, as hits through ref `ri`.
        #[inline(always)]
        fn take_hits(&mut self, hits: [Option<LeafHit>; PACKET], ri: u32) {
            for (state, h) in self.states.iter_mut().zip(hits) {
                if let Some((t, u, v, k)) = h {
                    state.best = Some((t, u, v, k, ri));
                }
            }
        }

        /// Leaf `(first, count)` for lane `lane` alone: the single-ray
        /// walk's leaf, from the lane's closest hit so far.
        #[inline(always)]
        fn closest_leaf_lane(&mut self, packet: &mut Packet8, lane: usize, first: u32, count: u32) {
            let mut t_max = packet.lane_t_max(lane);
            if first >= self.accel.block_base {
                // Copied blocks need no box tester: not made for them.
                let (a, factory) = (self.accel, self.factory);
                self.states[lane]
                    .copied_leaf::<false, _>(a, factory, first, count, &mut t_max, true);
            } else {
                self.entries_leaf::<false>(lane, first, count, &mut t_max);
            }
            packet.set_lane_t_max(lane, t_max);
        }
    }

    impl ClosestLanes for Lanes<'_> {
        /// As [`PacketLanes::leaf_packet`] for occlusion: copied blocks
        /// most of the packet reaches test one triangle for all its rays,
        /// entries into objects placed directly take the packet on into the
        /// object's tree, the rest go lane by lane; every lane keeps the
        /// single-ray walk's rule (`nearer_ref`: nearer, or as near with a
        /// smaller key).
        #[inline(always)]
        fn leaf_packet(&mut self, packet: &mut Packet8, mask: u32, first: u32, count: u32) {
            let a = self.accel;
            if first >= a.block_base {
                if mask.count_ones() >= PACKET_TRIANGLES_FROM
                    && let Some(&triangles) = self.triangles()
                {
                    let mut keys = self.lane_keys();
                    let mut hits = [None; PACKET];
                    let (rays, states, factory) = (self.rays, &mut self.states, self.factory);
                    triangles.closest_blocks(
                        &a.blocks,
                        first - a.block_base,
                        count,
                        mask,
                        packet,
                        &mut keys,
                        super::ref_key(INLINE_HIT, 0),
                        |lane, h| hits[lane] = Some(h),
                        |lane, b, j, t_max| {
                            scalar_closest(rays[lane], states[lane].wray(factory), b, j, t_max)
                        },
                    );
                    self.take_hits(hits, INLINE_HIT);
                    return;
                }
                let mut m = mask;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    self.closest_leaf_lane(packet, lane, first, count);
                }
                return;
            }
            for ri in first..first + count {
                let e = &a.entries[ri as usize];
                let Some(obj) = a.objects.get(e.object as usize).and_then(|o| o.as_deref()) else {
                    continue;
                };
                if e.instance == INVALID_ID
                    && mask.count_ones() >= SINGLE_BELOW
                    && !is_leaf_ref(e.wide)
                    && let Some(w) = &obj.wide
                {
                    let triangles = self.triangles().copied();
                    let best = self.lane_keys();
                    let mut sub = ClosestTriangleLanes {
                        lanes: TriangleLanes {
                            nodes: &w.wide.nodes,
                            blocks: &w.blocks,
                            factory: self.factory,
                            rays: self.rays,
                            testers: &mut self.worlds,
                            wrays: StateWrays {
                                states: &mut self.states,
                                factory: self.factory,
                            },
                            triangles: triangles.as_ref(),
                        },
                        hits: [None; PACKET],
                        best,
                        key_base: super::ref_key(ri, 0),
                    };
                    intersect_packet_from(&w.wide.nodes, packet, e.wide, mask, &mut sub);
                    let hits = sub.hits;
                    self.take_hits(hits, ri);
                    continue;
                }
                let mut m = mask;
                while m != 0 {
                    let lane = m.trailing_zeros() as usize;
                    m &= m - 1;
                    let r = self.rays[lane];
                    let world = self.worlds[lane].get_or_insert_with(|| self.factory.make(r));
                    let t_max = packet.lane_t_max(lane);
                    let state = &mut self.states[lane];
                    if let Some((t, u, v, k)) =
                        state.entry::<false, _>(a, self.factory, world, ri, t_max)
                        && super::nearer_ref(t, ri, k, &state.best)
                    {
                        state.best = Some((t, u, v, k, ri));
                        packet.set_lane_t_max(lane, t);
                    }
                }
            }
        }

        #[inline(always)]
        fn alone(&mut self, packet: &mut Packet8, lane: usize, node: u32) {
            let r = self.rays[lane];
            let world = self.worlds[lane].get_or_insert_with(|| self.factory.make(r));
            let state = &mut self.states[lane];
            state.walk_from::<false, _>(
                self.accel,
                self.nodes,
                self.factory,
                world,
                node,
                &mut TraversalCounters::default(),
            );
            if let Some(b) = state.best {
                packet.set_lane_t_max(lane, b.0);
            }
        }
    }

    /// A ray's answer from its walk's best hit, inlined into the kernel
    /// (through `Option::map`'s closure it was a call per ray).
    #[inline(always)]
    #[allow(clippy::manual_map)] // the closure was not inlined
    fn answer(accel: &TopLevelAccel, best: Option<RefHit>) -> Option<Hit> {
        match best {
            Some(h) => Some(accel.make_hit(h)),
            None => None,
        }
    }

    /// See [`TopLevelAccel::intersect_many`]; `nodes` is the wide top
    /// level. A target-feature function for the reason given at
    /// [`occluded`]. The hit records are made here, in this function's
    /// AVX2 context: made through an answer closure passed in, they were
    /// compiled out of line, a call per ray.
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
    pub(in crate::toplevel) fn intersect(
        accel: &TopLevelAccel,
        nodes: &[WideNode<8>],
        factory: &Avx2Factory,
        rays: &[Ray],
        out: &mut [Option<Hit>],
    ) {
        in_coherent_packets(
            rays,
            out,
            |rays, out| {
                for (o, ray) in out.iter_mut().zip(rays) {
                    let hit = if ray.is_valid() {
                        super::walk_ray::<false, _>(
                            accel,
                            ray,
                            factory,
                            &mut TraversalCounters::default(),
                        )
                    } else {
                        None
                    };
                    *o = answer(accel, hit);
                }
            },
            |rays, answers| {
                // SAFETY: an `Avx2Factory` exists only where the CPU has
                // the AVX2 level.
                let Some(mut packet) = (unsafe { Packet8::try_new(rays) }) else {
                    return false;
                };
                let mut lanes = Lanes {
                    accel,
                    nodes,
                    factory,
                    rays,
                    worlds: [None; PACKET],
                    states: std::array::from_fn(|l| RayState::new(rays.get(l).unwrap_or(&rays[0]))),
                    triangles: None,
                };
                let all = packet.lanes;
                intersect_packet_from(nodes, &mut packet, 0, all, &mut lanes);
                for (a, s) in answers.iter_mut().zip(&lanes.states) {
                    *a = answer(accel, s.best);
                }
                true
            },
        );
    }

    /// See [`TopLevelAccel::occluded_many`]; `nodes` is the wide top level.
    /// A target-feature function, so that the closures below are compiled
    /// for AVX2 too: left to inherit it by inlining, they were not, and
    /// every intrinsic of the packet test became a call (ten times slower).
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
    pub(in crate::toplevel) fn occluded(
        accel: &TopLevelAccel,
        nodes: &[WideNode<8>],
        factory: &Avx2Factory,
        rays: &[Ray],
        out: &mut [bool],
    ) {
        occluded_in_packets(
            rays,
            out,
            |ray| {
                super::walk_ray::<true, _>(accel, ray, factory, &mut TraversalCounters::default())
                    .is_some()
            },
            |rays| {
                // SAFETY: an `Avx2Factory` exists only where the CPU has
                // the AVX2 level.
                let packet = unsafe { Packet8::new(rays) };
                let mut lanes = Lanes {
                    accel,
                    nodes,
                    factory,
                    rays,
                    worlds: [None; PACKET],
                    states: std::array::from_fn(|l| RayState::new(rays.get(l).unwrap_or(&rays[0]))),
                    triangles: None,
                };
                occluded_packet(nodes, &packet, &mut lanes)
            },
        );
    }
}
