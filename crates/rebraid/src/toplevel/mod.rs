//! The top level of a two-level BVH: a BVH over references to object-BVH
//! subtrees, possibly through instance transforms.
//!
//! One structure serves both the plain two-level BVH (every reference is an
//! object root) and the re-braided one (references reach into the object
//! BVHs, see [`builder`]): a top-level leaf holds [`TopRef`]s, and traversal
//! continues from the leaf into the referenced object subtree, transforming
//! the ray into the instance's space first when the reference carries an
//! instance. The object BVHs are shared (`Arc`), never copied or modified.

pub mod builder;
mod layout;
mod walk;

use std::sync::Arc;

use glam::Affine3A;
use rayon::prelude::*;

use crate::bvh::occlusion_order::{OcclusionStats, order_for_occlusion_except};
use crate::bvh::triangle4::{
    LeafHit, Triangle4, block_hit_record, intersect_blocks, leaf_occlusion,
};
use crate::bvh::wide::{WIDE_EMPTY, WIDE_MAX_PRIMITIVES, decode_leaf, encode_leaf, is_leaf_ref};
use crate::bvh::{
    BoxRay, BoxTester, Bvh, BvhNode, Collapse, Kernel, MAX_DEPTH, SahCosts, TRAVERSAL_STACK,
    TesterFactory, TraversalCounters, WideBvh, WideNode, WideQuery, WideTriangleBvh,
    intersect_many, occluded_many, subtree_with, traverse_with, with_kernel,
};
use crate::transform::{transform_box, transform_normal};
use crate::triangle::WatertightRay;
use crate::{Aabb, Hit, INVALID_ID, MeshBvh, Ray};

pub use builder::{
    BuildRef, LayoutTimes, RebraidParams, RefBudget, TopLevelBuildStats, build_top_level,
};
use layout::*;
pub use layout::{LayoutBuffers, TopLevelLayout};
use walk::*;

/// An object's BVH with what the top-level builder needs besides: the number
/// of primitives under each node (the real counts the SAH weights refs by).
#[derive(Clone, Debug, Default)]
pub struct ObjectBvh {
    pub mesh: MeshBvh,
    /// Primitives under each node, indexed like `mesh.bvh.nodes`.
    pub subtree_prims: Vec<u32>,
    /// Expected SAH cost of each node's subtree for a ray that enters the
    /// node's box (traversal and intersection cost 1).
    pub subtree_cost: Vec<f32>,
    /// The 8-wide layout traversal uses, collapsed from `mesh.bvh` (which
    /// stays the build, re-braiding and statistics structure), with
    /// four-triangle leaf blocks; `None` when a binary leaf is too large for
    /// it.
    pub wide: Option<WideTriangleBvh>,
    /// For each binary node, the wide node collapsed from it (inner nodes),
    /// the wide leaf reference naming its blocks (leaves), or `WIDE_EMPTY`.
    pub wide_of: Vec<u32>,
    /// The rule `wide` was collapsed by (again after a refit).
    pub collapse: Collapse,
}

impl ObjectBvh {
    /// The object over `mesh`, collapsed by the default rule.
    pub fn new(mesh: MeshBvh) -> Self {
        Self::with_collapse(mesh, Collapse::default())
    }

    /// The object over `mesh`, its wide layout collapsed by `collapse`
    /// ([`crate::bvh::BuildParams::collapse`]).
    pub fn with_collapse(mesh: MeshBvh, collapse: Collapse) -> Self {
        let n = mesh.bvh.nodes.len();
        let mut o = Self {
            mesh,
            subtree_prims: vec![0; n],
            subtree_cost: vec![0.0; n],
            wide: None,
            wide_of: Vec::new(),
            collapse,
        };
        o.update_counts_and_costs();
        o.collapse_wide();
        o
    }

    /// (Re)collapse the 8-wide traversal layout from the binary tree; none
    /// when a binary leaf is too large for it (traversal stays binary then).
    fn collapse_wide(&mut self) {
        self.wide = WideTriangleBvh::from_mesh_with(&self.mesh, self.collapse).ok();
        self.wide_of = match &self.wide {
            Some(w) => {
                let mut map = w.wide.wide_of_binary(self.mesh.bvh.nodes.len());
                for (node, slots) in w.wide.nodes.iter().zip(&w.wide.slot_binary) {
                    for (&r, &b) in node.child.iter().zip(slots) {
                        if r != WIDE_EMPTY && is_leaf_ref(r) {
                            map[b as usize] = r;
                        }
                    }
                }
                map
            }
            None => Vec::new(),
        };
    }

    /// Primitive id and geometric normal (at its length) of a hit that
    /// [`ObjectBvh::query_entry`] reported for the wide reference `w`: a
    /// block lane when `w` names a wide node or leaf (the record comes from
    /// the block the test read), a leaf-order slot of the binary tree when
    /// `w` is `WIDE_EMPTY` (the binary fallback).
    #[inline(always)]
    pub fn hit_record(&self, w: u32, k: u32) -> (u32, glam::Vec3) {
        match &self.wide {
            Some(wide) if w != WIDE_EMPTY => block_hit_record(&wide.blocks, k),
            _ => self.mesh.hit_record(k),
        }
    }

    /// The wide node collapsed from binary inner node `node`, if any.
    #[inline(always)]
    pub fn wide_node(&self, node: u32) -> Option<u32> {
        self.wide_of
            .get(node as usize)
            .copied()
            .filter(|&w| !is_leaf_ref(w))
    }

    /// Refit the object BVH to moved vertices (same triangles, see
    /// [`MeshBvh::refit`]) and recompute the subtree costs, which depend on
    /// the boxes; the primitive counts do not change.
    pub fn refit(&mut self, mesh: &crate::TriangleMesh) -> Result<(), crate::Error> {
        self.mesh.refit(mesh)?;
        self.update_counts_and_costs();
        self.collapse_wide();
        Ok(())
    }

    /// Recompute `subtree_prims` and `subtree_cost` from the nodes.
    fn update_counts_and_costs(&mut self) {
        let nodes = &self.mesh.bvh.nodes;
        let counts = &mut self.subtree_prims;
        let cost = &mut self.subtree_cost;
        counts.resize(nodes.len(), 0);
        cost.resize(nodes.len(), 0.0);
        // Children are stored after their parent, so a reverse sweep sees
        // both children before the parent.
        for i in (0..nodes.len()).rev() {
            let n = &nodes[i];
            if n.is_leaf() {
                counts[i] = n.count;
                cost[i] = n.count as f32;
            } else {
                let (l, r) = (n.index as usize, n.index as usize + 1);
                counts[i] = counts[l] + counts[r];
                let a = n.bounds().half_area();
                cost[i] = if a > 0.0 {
                    1.0 + (nodes[l].bounds().half_area() * cost[l]
                        + nodes[r].bounds().half_area() * cost[r])
                        / a
                } else {
                    1.0 + cost[l] + cost[r]
                };
            }
        }
    }

    #[inline]
    pub fn nodes(&self) -> &[BvhNode] {
        &self.mesh.bvh.nodes
    }

    /// The closest hit (or, with `ANY`, some hit) within `[ray.t_min, t_max]`
    /// in the subtree of binary node `node`, whose box the caller has tested
    /// (a top-level leaf), as (t, u, v, hit reference: see
    /// [`ObjectBvh::hit_record`]). `w` is the node's
    /// wide reference (`wide_of[node]`, or `WIDE_EMPTY`), which the top level
    /// stores per ref in [`RefEntry`]. `ray` is in object space, `wray` and
    /// `tester` its prepared forms. An inner node collapsed into the wide
    /// layout is traversed with the caller's SIMD tester, a leaf's triangle
    /// blocks are tested directly, and an object without the wide layout
    /// runs the binary scalar kernel.
    #[allow(clippy::too_many_arguments)] // the hot path: plain values
    #[inline(always)]
    pub fn query_entry<const ANY: bool, B: BoxTester<8>>(
        &self,
        w: u32,
        node: u32,
        ray: &Ray,
        wray: &WatertightRay,
        tester: &B,
        t_max: f32,
        counters: &mut TraversalCounters,
    ) -> Option<(f32, f32, f32, u32)> {
        let t_min = ray.t_min;
        if let Some(wide) = &self.wide {
            if !is_leaf_ref(w) {
                return subtree_with::<8, ANY, B>(
                    &wide.wide.nodes,
                    &wide.blocks,
                    tester,
                    wray,
                    t_min,
                    w,
                    t_max,
                    counters,
                );
            }
            if w != WIDE_EMPTY {
                // A binary leaf: its blocks directly.
                counters.leaves_visited += 1;
                let (first, count) = decode_leaf(w);
                let (mut t_max, mut best) = (t_max, None);
                intersect_blocks::<ANY>(
                    &wide.blocks,
                    wray,
                    t_min,
                    first,
                    count,
                    &mut t_max,
                    &mut best,
                    B::SIMD_TRIANGLES,
                );
                return best;
            }
        }
        // The binary fallback (objects without the wide layout: a leaf
        // larger than a wide leaf holds). Its setup lives here, not in every
        // ray's walk.
        let bray = BoxRay::new(ray.origin, ray.dir);
        let mut stack = [(0u32, 0.0f32); TRAVERSAL_STACK];
        let mut best = None;
        self.mesh.bvh.traverse_from(
            node,
            &bray,
            t_min,
            t_max,
            &mut stack,
            counters,
            |leaf, tm| {
                if ANY {
                    if self.mesh.occluded_leaf(wray, leaf, t_min, *tm) {
                        best = Some((0.0, 0.0, 0.0, 0));
                        return true;
                    }
                    return false;
                }
                self.mesh.intersect_leaf(wray, leaf, t_min, tm, &mut best);
                false
            },
        );
        best
    }
}

/// A top-level leaf entry: object-BVH node `node` of object `object`, placed
/// by instance `instance` (or directly when [`INVALID_ID`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct TopRef {
    pub object: u32,
    pub node: u32,
    pub instance: u32,
    /// Primitives under the node.
    pub prims: u32,
}

const _: () = assert!(std::mem::size_of::<TopRef>() == 16);

/// What traversal needs of a ref, in one 16-byte load: the object, the
/// instance, the wide reference of the ref's node (`wide_of[node]`, or
/// `WIDE_EMPTY` when the object has no wide layout) and the binary node.
/// Looking these up through `refs`, the object and its `wide_of` map cost
/// a chain of dependent cache misses per top-level leaf.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(C)]
pub struct RefEntry {
    pub object: u32,
    pub instance: u32,
    pub wide: u32,
    pub node: u32,
}

const _: () = assert!(std::mem::size_of::<RefEntry>() == 16);

/// An instance's transforms as traversal needs them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InstanceXf {
    pub object_to_world: Affine3A,
    pub world_to_object: Affine3A,
    /// Sign of the determinant: a mirroring transform flips the winding.
    pub det_sign: f32,
    /// How the transform scales areas on average, `|det|^(2/3)` (exact for
    /// uniform scaling): occlusion estimates of opened refs use it.
    pub area_scale: f32,
}

impl InstanceXf {
    pub fn new(object_to_world: Affine3A) -> Self {
        Self {
            object_to_world,
            world_to_object: object_to_world.inverse(),
            det_sign: object_to_world.matrix3.determinant().signum(),
            area_scale: object_to_world.matrix3.determinant().abs().powf(2.0 / 3.0),
        }
    }

    /// The ray in the instance's object space (the direction is
    /// transformed unnormalised, so `t` means the same).
    #[inline]
    pub fn local_ray(&self, ray: &Ray) -> Ray {
        Ray {
            origin: self.world_to_object.transform_point3(ray.origin),
            dir: self.world_to_object.transform_vector3(ray.dir),
            t_min: ray.t_min,
            t_max: ray.t_max,
        }
    }

    /// World box of an object-space box.
    #[inline]
    pub fn world_box(&self, local: &Aabb) -> Aabb {
        transform_box(&self.object_to_world, local)
    }
}

/// A committed two-level (or re-braided) acceleration structure.
#[derive(Clone, Debug, Default)]
pub struct TopLevelAccel {
    /// The top-level tree; leaves index into `refs`.
    pub tree: Bvh,
    pub refs: Vec<TopRef>,
    /// Object BVHs by object id (`None` for removed or empty objects, and
    /// for the members of a merged BVH), then a merged BVH's (see
    /// [`TopLevelAccel::merged`]), then in the last `baked.len()` slots the
    /// world-space BVHs of baked placements (see [`TopLevelAccel::baked`]).
    pub objects: Vec<Option<Arc<ObjectBvh>>>,
    /// Instance transforms by instance id.
    pub instances: Vec<InstanceXf>,
    pub build_stats: TopLevelBuildStats,
    /// The 8-wide layout of `tree` that traversal uses (leaves are single
    /// refs); `None` only for an empty tree.
    pub wide: Option<WideBvh<8>>,
    /// The traversal kernel (the scene's choice, by default [`Kernel::best`]).
    pub kernel: Kernel,
    /// The refs the leaves of `wide` index: `refs`, unless entry nodes were
    /// pulled into the top level (see `pull_into_top_level` in this module), which
    /// replaces some refs by their children.
    pub entry_refs: Vec<TopRef>,
    /// One [`RefEntry`] per entry ref, made with the accel.
    pub entries: Vec<RefEntry>,
    /// Copies of the triangle blocks of object leaves that top-level leaves
    /// enter directly (see `inline_leaf_blocks` in this module): a wide leaf whose first
    /// index is at least `block_base` names `blocks[first - block_base..]`.
    pub blocks: Vec<Triangle4>,
    /// The entry each block of `blocks` was copied for.
    pub block_entry: Vec<u32>,
    /// The (object, instance) a hit on each block of `blocks` reports: its
    /// entry's placement ([`TopLevelAccel::placement_of_slot`] of the
    /// entry's object), kept per block so that a hit record reads one
    /// value instead of the entry, then the baked placements (about 15
    /// instructions of the 85 that made a hit record per ray, session 21).
    pub block_placement: Vec<(u32, u32)>,
    /// Per block of `blocks`, the factor its hits' normals take (see
    /// `TopLevelAccel::block_entry_normal_scale`): 1 but for instanced
    /// leaves copied in world space.
    pub block_normal_scale: Vec<f32>,
    /// Leaf indices from here on name `blocks`, below it `entries`.
    pub block_base: u32,
    /// The placements traced from world-space BVHs (objects that one
    /// instance places, see [`crate::toplevel::RebraidParams::bake_single_instances`]),
    /// as (object, instance): `objects[baked_base() + k]` is the BVH of
    /// `baked[k]`, entered as a directly placed object; hits on it report
    /// the object and the instance.
    pub baked: Vec<(u32, u32)>,
    /// The last `grafted.len()` nodes of `wide` are grafted copies of
    /// object nodes (see `graft_entries` in this module), left in the
    /// object's occlusion order: for each, the entry it replaced and that
    /// entry's slot box.
    pub grafted: Vec<(RefEntry, Aabb)>,
    /// The slot of a BVH over several objects placed directly (see
    /// [`crate::scene::SceneParams::merge_placed`]), entered as one object
    /// placed directly, and per primitive of it the (object, primitive) a
    /// hit on it reports. The slot is below [`TopLevelAccel::baked_base`].
    pub merged: Option<MergedSlot>,
    /// The object slot every ref of the top level names, placed directly
    /// (no instance), when there is one and it has a wide layout: the
    /// whole scene is that one BVH, which traversal then walks as the flat
    /// mode walks its tree ([`crate::bvh::query_subtree`],
    /// [`crate::bvh::intersect_many`]), without the top level. A scene of
    /// one object, or one whose objects are all merged (see
    /// [`crate::scene::SceneParams::merge_placed`]), is such a scene. The
    /// top-level walk over the same tree costs 9% more instructions per
    /// diffuse ray, almost all in its leaves (nexuiz as one object,
    /// 1,363.6 against 1,253; docs/performance.md, session 30); its
    /// grafts and leaf copies are not made (the merged BVH's whole graft
    /// was 26M of nexuiz's 270M commit instructions).
    pub direct: Option<u32>,
}

/// A BVH over several objects placed directly, in one object slot of a top
/// level (see [`crate::scene::SceneParams::merge_placed`]).
#[derive(Clone, Debug, PartialEq)]
pub struct MergedSlot {
    /// Its slot in [`TopLevelAccel::objects`] (below the baked placements').
    pub slot: u32,
    /// Per primitive of the slot's BVH, the (object, primitive) a hit on it
    /// reports.
    pub origins: Arc<[(u32, u32)]>,
}

impl TopLevelAccel {
    /// Name the last `baked.len()` slots of `objects` as the world-space
    /// BVHs of these placements, (object, instance) each: hits on them
    /// report that object and instance. Fails when there are fewer slots.
    pub fn with_baked(mut self, baked: Vec<(u32, u32)>) -> Result<Self, crate::Error> {
        if baked.len() > self.objects.len() {
            return Err(crate::Error::InvalidParameter(format!(
                "{} baked placements but {} object slots",
                baked.len(),
                self.objects.len()
            )));
        }
        self.baked = baked;
        self.place_blocks();
        Ok(self)
    }

    /// Name object slot `slot` (below the baked placements') as a BVH over
    /// several objects' triangles, primitive `p` of which is `origins[p]`
    /// as (object, primitive): hits on it report that object and primitive.
    /// Fails when the slot is empty, among the baked placements', or has
    /// another number of primitives.
    pub fn with_merged(mut self, merged: Option<MergedSlot>) -> Result<Self, crate::Error> {
        self.merged = merged;
        self.check_merged()
            .map_err(crate::Error::InvalidParameter)?;
        Ok(self)
    }

    /// The merged slot, if any, is a live slot below the baked placements'
    /// with one origin per primitive.
    fn check_merged(&self) -> Result<(), String> {
        let Some(MergedSlot { slot, origins }) = &self.merged else {
            return Ok(());
        };
        let prims = self
            .objects
            .get(*slot as usize)
            .and_then(|o| o.as_deref())
            .map(|o| o.mesh.len());
        if *slot >= self.baked_base() || prims != Some(origins.len()) {
            return Err(format!(
                "merged slot {slot}: {} origins for {prims:?} primitives (baked from {})",
                origins.len(),
                self.baked_base()
            ));
        }
        Ok(())
    }

    /// Slot of the first baked placement's BVH in `objects`.
    #[inline]
    pub fn baked_base(&self) -> u32 {
        (self.objects.len() - self.baked.len()) as u32
    }

    /// The (object, instance) an object slot places: a baked placement's,
    /// or the slot's own object placed directly.
    #[inline]
    pub fn placement_of_slot(&self, slot: u32) -> (u32, u32) {
        match slot.checked_sub(self.baked_base()) {
            Some(k) => self.baked[k as usize],
            None => (slot, INVALID_ID),
        }
    }

    /// The wide top level as it indexes entries: leaves naming copied
    /// blocks (see [`inline_leaf_blocks`]) named by their entry again.
    fn wide_by_entry(&self) -> Option<WideBvh<8>> {
        let mut w = self.wide.clone()?;
        for node in &mut w.nodes {
            for c in &mut node.child {
                if is_leaf_ref(*c) && *c != WIDE_EMPTY {
                    let (first, _) = decode_leaf(*c);
                    if first >= self.block_base {
                        let e = self.block_entry[(first - self.block_base) as usize];
                        *c = encode_leaf(e, 1);
                    }
                }
            }
        }
        Some(w)
    }

    #[inline(always)]
    fn object(&self, r: &TopRef) -> Option<&ObjectBvh> {
        self.objects
            .get(r.object as usize)
            .and_then(|o| o.as_deref())
    }

    /// Closest hit along the ray.
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        self.intersect_counted(ray, &mut TraversalCounters::default())
    }

    /// Closest hit, counting visited nodes of both levels.
    pub fn intersect_counted(&self, ray: &Ray, counters: &mut TraversalCounters) -> Option<Hit> {
        if !ray.is_valid() {
            return None;
        }
        if let Some((slot, w)) = self.direct_bvh() {
            let h = w.query::<false>(self.kernel, ray, counters)?;
            return Some(self.direct_hit(slot, w, h));
        }
        let mut walk = RayWalk::<false> {
            accel: self,
            ray,
            counters,
            best: None,
        };
        with_kernel(self.kernel, &mut walk);
        walk.best.map(|h| self.make_hit(h))
    }

    /// Closest hits of a run of rays on the calling thread, `out[i]`
    /// answering `rays[i]` as [`TopLevelAccel::intersect`] does (exact ties
    /// included: see `nearer_ref`), with one kernel dispatch for the whole
    /// run. Panics when the lengths
    /// differ.
    ///
    /// With the AVX2 kernel, runs of coherent rays (camera rays in pixel
    /// order) go through the top level and into objects placed directly in
    /// packets of up to eight ([`crate::bvh::packet::intersect_packet_from`]);
    /// incoherent rays go alone.
    pub fn intersect_many(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        assert_eq!(rays.len(), out.len(), "one output per ray");
        if let Some((slot, w)) = self.direct_bvh() {
            let answer = |h: Option<LeafHit>| h.map(|h| self.direct_hit(slot, w, h));
            return intersect_many(&w.wide.nodes, &w.blocks, self.kernel, rays, out, answer);
        }
        let answer = |a: &TopLevelAccel, h: Option<RefHit>| h.map(|h| a.make_hit(h));
        #[cfg(target_arch = "x86_64")]
        if self.kernel == Kernel::Avx2
            && let Some(wide) = &self.wide
            && crate::bvh::simd::with_avx2(|f| {
                // SAFETY: an `Avx2Factory` exists only where the CPU has
                // the AVX2 level.
                unsafe { packets::intersect(self, &wide.nodes, f, rays, out) }
            })
            .is_some()
        {
            return;
        }
        let mut walk = BatchWalk::<false, _, _> {
            accel: self,
            rays,
            out,
            answer,
        };
        with_kernel(self.kernel, &mut walk);
    }

    /// Occlusion of a run of rays on the calling thread (see
    /// [`TopLevelAccel::intersect_many`]).
    ///
    /// With the AVX2 kernel the rays go through the top level in packets of
    /// eight of one direction octant ([`crate::bvh::packet`]), each ray on
    /// alone from its entries into the object BVHs and where few rays of
    /// its packet remain; the answers are the single-ray kernel's.
    pub fn occluded_many(&self, rays: &[Ray], out: &mut [bool]) {
        assert_eq!(rays.len(), out.len(), "one output per ray");
        if let Some((_, w)) = self.direct_bvh() {
            return occluded_many(&w.wide.nodes, &w.blocks, self.kernel, rays, out);
        }
        #[cfg(target_arch = "x86_64")]
        if self.kernel == Kernel::Avx2
            && let Some(wide) = &self.wide
            && crate::bvh::simd::with_avx2(|f| {
                // SAFETY: an `Avx2Factory` exists only where the CPU has
                // the AVX2 level.
                unsafe { packets::occluded(self, &wide.nodes, f, rays, out) }
            })
            .is_some()
        {
            return;
        }
        let mut walk = BatchWalk::<true, _, _> {
            accel: self,
            rays,
            out,
            answer: |_: &TopLevelAccel, h: Option<RefHit>| h.is_some(),
        };
        with_kernel(self.kernel, &mut walk);
    }

    #[inline(always)]
    fn make_hit(&self, (t, u, v, k, ri): RefHit) -> Hit {
        let (prim_id, normal, (object_id, instance_id)) = if ri == INLINE_HIT {
            // A copied block: world-space vertices, its normal scaled as
            // its entry would report it.
            let (prim, normal) = block_hit_record(&self.blocks, k);
            let b = (k / 4) as usize;
            (
                prim,
                normal * self.block_normal_scale[b],
                self.block_placement[b],
            )
        } else {
            let e = &self.entries[ri as usize];
            let obj = self
                .objects
                .get(e.object as usize)
                .and_then(|o| o.as_deref())
                .expect("hit refs have objects");
            let (prim, normal) = obj.hit_record(e.wide, k);
            if e.instance == INVALID_ID {
                // Already a world-space normal (a baked placement's too:
                // its blocks hold the transformed vertices).
                (prim, normal, self.placement_of_slot(e.object))
            } else {
                // Not normalised (see `Hit`): transformed as a normal and
                // flipped with a mirroring transform's winding.
                let xf = &self.instances[e.instance as usize];
                let normal = transform_normal(&xf.world_to_object, normal) * xf.det_sign;
                (prim, normal, (e.object, e.instance))
            }
        };
        self.finish_hit(t, u, v, prim_id, normal, (object_id, instance_id))
    }

    /// The wide BVH of [`TopLevelAccel::direct`]'s slot, when set.
    #[inline(always)]
    fn direct_bvh(&self) -> Option<(u32, &WideTriangleBvh)> {
        let slot = self.direct?;
        let w = self.objects.get(slot as usize)?.as_deref()?.wide.as_ref()?;
        Some((slot, w))
    }

    /// The hit a walk of [`TopLevelAccel::direct`]'s BVH reports.
    #[inline(always)]
    fn direct_hit(&self, slot: u32, w: &WideTriangleBvh, (t, u, v, k): LeafHit) -> Hit {
        let (prim_id, normal) = block_hit_record(&w.blocks, k);
        self.finish_hit(t, u, v, prim_id, normal, self.placement_of_slot(slot))
    }

    /// A hit on object slot `object_id`'s primitive `prim_id` (or a copied
    /// block's), as the scene reports it.
    #[inline(always)]
    fn finish_hit(
        &self,
        t: f32,
        u: f32,
        v: f32,
        prim_id: u32,
        normal: glam::Vec3,
        (object_id, instance_id): (u32, u32),
    ) -> Hit {
        // A hit on the merged BVH names the member and its own primitive.
        let (object_id, prim_id) = match &self.merged {
            Some(m) if object_id == m.slot => m.origins[prim_id as usize],
            _ => (object_id, prim_id),
        };
        Hit {
            t,
            u,
            v,
            prim_id,
            object_id,
            instance_id,
            normal,
        }
    }

    /// True when anything is hit within the ray's interval.
    pub fn occluded(&self, ray: &Ray) -> bool {
        self.occluded_counted(ray, &mut TraversalCounters::default())
    }

    /// Occlusion, counting visited nodes of both levels.
    pub fn occluded_counted(&self, ray: &Ray, counters: &mut TraversalCounters) -> bool {
        if !ray.is_valid() {
            return false;
        }
        if let Some((_, w)) = self.direct_bvh() {
            return w.query::<true>(self.kernel, ray, counters).is_some();
        }
        let mut walk = RayWalk::<true> {
            accel: self,
            ray,
            counters,
            best: None,
        };
        with_kernel(self.kernel, &mut walk);
        walk.best.is_some()
    }

    /// Embree's SAH statistic of the wide tree as traversed (see
    /// [`crate::bvh::wide::wide_sah_sum`]): the top level's 8-wide nodes,
    /// the leaf blocks copied into it, and from each entry the object's
    /// wide nodes and blocks (an instanced object's boxes by their world
    /// boxes). An entry that starts at an object node counts that node's
    /// test at its top-level slot box. A top level walked directly
    /// ([`TopLevelAccel::direct`]) counts its slot's tree alone, as the
    /// flat mode counts its own. 0 without a wide layout.
    pub fn wide_sah_cost(&self) -> f64 {
        use crate::bvh::wide::{wide_root_area, wide_sah_sum};
        // Walked directly, the tree is the slot's alone.
        if let Some((_, w)) = self.direct_bvh() {
            return w.wide_sah_cost();
        }
        let Some(top) = &self.wide else { return 0.0 };
        let root_area = wide_root_area(top);
        if root_area <= 0.0 {
            return 0.0;
        }
        let blocks = |c: u32| decode_leaf(c).1 as f64;
        let world_area = |b: &Aabb| b.half_area() as f64;
        let mut top_leaf = |c: u32, a: f64| -> f64 {
            let (first, count) = decode_leaf(c);
            if first >= self.block_base {
                return a * count as f64;
            }
            let mut sum = 0.0;
            for e in &self.entries[first as usize..(first + count) as usize] {
                let ow = self
                    .objects
                    .get(e.object as usize)
                    .and_then(|o| o.as_deref())
                    .and_then(|o| o.wide.as_ref());
                let xf = (e.instance != INVALID_ID).then(|| &self.instances[e.instance as usize]);
                let placed_area = |b: &Aabb| match xf {
                    Some(xf) => xf.world_box(b).half_area() as f64,
                    None => b.half_area() as f64,
                };
                sum += match ow.filter(|_| e.wide != WIDE_EMPTY) {
                    // No wide layout: one test, not followed further.
                    None => a,
                    Some(_) if is_leaf_ref(e.wide) => a * blocks(e.wide),
                    Some(ow) => {
                        wide_sah_sum(&ow.wide, e.wide, a, &placed_area, &mut |c, a| a * blocks(c))
                    }
                };
            }
            sum
        };
        wide_sah_sum(top, 0, root_area, &world_area, &mut top_leaf) / root_area
    }

    /// The SAH statistic of the tree as traversed: from the top-level root
    /// down into the shared object nodes (world-space boxes; a ref's node is
    /// counted once, as the top-level leaf that tests its box). It walks the
    /// build's binary tree, so it does not see the layout steps after the
    /// build (pulled entry nodes, copied leaf blocks), which only remove
    /// node tests and entries.
    pub fn sah_cost(&self, costs: SahCosts) -> f64 {
        let Some(root) = self.tree.nodes.first() else {
            return 0.0;
        };
        let root_area = root.bounds().half_area() as f64;
        if root_area <= 0.0 {
            return 0.0;
        }
        let (ct, ci) = (costs.traversal as f64, costs.intersection as f64);
        let top: f64 = self
            .tree
            .nodes
            .iter()
            .filter(|n| !n.is_leaf())
            .map(|n| n.bounds().half_area() as f64 * ct)
            .sum();
        let braided: f64 = self
            .tree
            .nodes
            .par_iter()
            .filter(|n| n.is_leaf())
            .map(|leaf| {
                let mut s = 0.0;
                for r in &self.refs[leaf.prim_range()] {
                    let Some(obj) = self.object(r) else { continue };
                    let xf =
                        (r.instance != INVALID_ID).then(|| &self.instances[r.instance as usize]);
                    let area = |n: &BvhNode| match xf {
                        Some(xf) => xf.world_box(&n.bounds()).half_area() as f64,
                        None => n.bounds().half_area() as f64,
                    };
                    let nodes = obj.nodes();
                    let start = &nodes[r.node as usize];
                    let a = leaf.bounds().half_area() as f64;
                    if start.is_leaf() {
                        s += a * start.count as f64 * ci;
                        continue;
                    }
                    s += a * ct;
                    let mut stack = vec![start.index as usize, start.index as usize + 1];
                    while let Some(i) = stack.pop() {
                        let n = &nodes[i];
                        if n.is_leaf() {
                            s += area(n) * n.count as f64 * ci;
                        } else {
                            s += area(n) * ct;
                            stack.push(n.index as usize);
                            stack.push(n.index as usize + 1);
                        }
                    }
                }
                s
            })
            .sum();
        (top + braided) / root_area
    }

    /// How often each primitive of each placement is reachable by traversal:
    /// walks every entry ref (each the leaf of one slot of the wide top
    /// level, which [`TopLevelAccel::validate`] checks) into its object
    /// subtree. Keys are (object, instance), also for baked placements and
    /// for the members of a merged BVH (see [`TopLevelAccel::merged`]).
    pub fn reachable_counts(&self) -> std::collections::HashMap<(u32, u32), Vec<u32>> {
        let mut counts: std::collections::HashMap<(u32, u32), Vec<u32>> = Default::default();
        for r in &self.entry_refs {
            let Some(obj) = self.object(r) else { continue };
            let key = if r.instance == INVALID_ID {
                self.placement_of_slot(r.object)
            } else {
                (r.object, r.instance)
            };
            let c = counts.entry(key).or_insert_with(|| vec![0; obj.mesh.len()]);
            let nodes = obj.nodes();
            let mut stack = vec![r.node as usize];
            while let Some(i) = stack.pop() {
                let n = &nodes[i];
                if n.is_leaf() {
                    for k in n.prim_range() {
                        c[obj.mesh.bvh.prim_indices[k] as usize] += 1;
                    }
                } else {
                    stack.push(n.index as usize);
                    stack.push(n.index as usize + 1);
                }
            }
        }
        if let Some(MergedSlot { slot, origins }) = &self.merged
            && let Some(c) = counts.remove(&(*slot, INVALID_ID))
        {
            let mut len = std::collections::HashMap::<u32, usize>::new();
            for &(o, p) in origins.iter() {
                let l = len.entry(o).or_default();
                *l = (*l).max(p as usize + 1);
            }
            for (&(o, p), &n) in origins.iter().zip(&c) {
                counts
                    .entry((o, INVALID_ID))
                    .or_insert_with(|| vec![0; len[&o]])[p as usize] += n;
            }
        }
        counts
    }

    /// Check the top-level tree: child boxes inside parents, each ref's world
    /// box inside its leaf, each object node's world box inside its ref's box.
    pub fn validate(&self) -> Result<(), String> {
        // Direct refs: the node's box. Instanced refs: the box of the
        // transformed vertices under the node (the builder clips transformed
        // boxes to their parents', so the geometry is what must be inside).
        let boxes: Vec<Aabb> = self
            .refs
            .par_iter()
            .map(|r| self.placed_geometry_box(r))
            .collect();
        // Leaves hold refs in order, so the ref array is the primitive order.
        let tree = Bvh {
            nodes: self.tree.nodes.clone(),
            prim_indices: (0..self.refs.len() as u32).collect(),
        };
        if let Some(i) = boxes.iter().position(|b| b.is_empty()) {
            return Err(format!("ref {i} has no object"));
        }
        if self.baked.len() > self.objects.len() {
            return Err("more baked placements than object slots".into());
        }
        self.check_merged()?;
        if self.direct != direct_slot(&self.refs, &self.objects) {
            return Err(format!(
                "direct slot {:?}, but the refs name {:?}",
                self.direct,
                direct_slot(&self.refs, &self.objects)
            ));
        }
        if let Some(i) = self
            .refs
            .iter()
            .position(|r| r.object >= self.baked_base() && r.instance != INVALID_ID)
        {
            return Err(format!(
                "ref {i} enters a baked placement through an instance"
            ));
        }
        tree.validate(&boxes)?;
        if self.block_entry.len() != self.blocks.len()
            || self.block_placement.len() != self.blocks.len()
            || self.block_normal_scale.len() != self.blocks.len()
        {
            return Err("copied blocks and their entries differ in length".into());
        }
        for (b, (&ri, &placed)) in self
            .block_entry
            .iter()
            .zip(&self.block_placement)
            .enumerate()
        {
            if self.entries.get(ri as usize).is_none() {
                return Err(format!("copied block {b}: no entry {ri}"));
            }
            if placed != self.entry_placement(ri) {
                return Err(format!(
                    "copied block {b}: placed as {placed:?}, its entry {ri} places {:?}",
                    self.entry_placement(ri)
                ));
            }
            if self.block_normal_scale[b] != self.block_entry_normal_scale(ri) {
                return Err(format!("copied block {b}: wrong normal scale"));
            }
        }
        // Each run of copied blocks is its entry's object leaf, bit for bit
        // (an instanced leaf's transformed into world space).
        let mut b = 0;
        while b < self.blocks.len() {
            let ri = self.block_entry[b];
            let e = &self.entries[ri as usize];
            let ow = self
                .objects
                .get(e.object as usize)
                .and_then(|o| o.as_deref())
                .and_then(|o| o.wide.as_ref())
                .ok_or_else(|| format!("copied block {b}: entry {ri} has no wide object"))?;
            if !is_leaf_ref(e.wide) || e.wide == WIDE_EMPTY {
                return Err(format!("copied block {b}: entry {ri} is no leaf"));
            }
            let xf = match e.instance {
                INVALID_ID => None,
                i => Some(
                    self.instances
                        .get(i as usize)
                        .ok_or_else(|| format!("copied block {b}: no instance {i}"))?
                        .object_to_world,
                ),
            };
            let (first, n) = decode_leaf(e.wide);
            // Bit for bit: padding lanes hold NaN vertices.
            let bits = |blocks: &[Triangle4]| {
                blocks
                    .iter()
                    .flat_map(|t| {
                        t.v.as_flattened()
                            .as_flattened()
                            .iter()
                            .map(|x| x.to_bits())
                    })
                    .chain(blocks.iter().flat_map(|t| t.prim))
                    .collect::<Vec<u32>>()
            };
            let copy = self.blocks.get(b..b + n as usize).map(bits);
            let leaf = &ow.blocks[first as usize..(first + n) as usize];
            let want = match &xf {
                None => bits(leaf),
                Some(xf) => bits(&leaf.iter().map(|t| t.transformed(xf)).collect::<Vec<_>>()),
            };
            if copy != Some(want) {
                return Err(format!(
                    "copied blocks at {b} differ from entry {ri}'s leaf"
                ));
            }
            b += n as usize;
        }
        if let Some(wide) = &self.wide_by_entry() {
            // The wide tree's leaves index the entry refs: the refs, some
            // replaced by their children when entry nodes were pulled up.
            let entry_boxes: Vec<Aabb> = self
                .entry_refs
                .par_iter()
                .map(|r| self.placed_geometry_box(r))
                .collect();
            if self.entries.len() != self.entry_refs.len() {
                return Err("entries and entry refs differ in length".into());
            }
            for (i, (e, r)) in self.entries.iter().zip(&self.entry_refs).enumerate() {
                let wide_of = self
                    .object(r)
                    .filter(|o| o.wide.is_some())
                    .and_then(|o| o.wide_of.get(r.node as usize).copied())
                    .unwrap_or(WIDE_EMPTY);
                if (e.object, e.instance, e.node, e.wide) != (r.object, r.instance, r.node, wide_of)
                {
                    return Err(format!("entry {i} does not match its ref"));
                }
            }
            wide.validate(&entry_boxes)?;
            // Grafted nodes are exempt from the order check below: each must
            // copy the object node its entry entered, slot for slot.
            let first_grafted = wide.nodes.len().checked_sub(self.grafted.len());
            let first_grafted = first_grafted.ok_or("more grafted nodes than nodes")?;
            for (k, (e, _)) in self.grafted.iter().enumerate() {
                let copied = &wide.nodes[first_grafted + k];
                let source = self
                    .objects
                    .get(e.object as usize)
                    .and_then(|o| o.as_deref())
                    .and_then(|o| o.wide.as_ref())
                    .filter(|_| !is_leaf_ref(e.wide))
                    .and_then(|w| w.wide.nodes.get(e.wide as usize));
                if source.map(|s| s.child_count()) != Some(copied.child_count()) {
                    return Err(format!(
                        "grafted node {} is no copy of its entry's node",
                        first_grafted + k
                    ));
                }
            }
            let mut ordered = wide.clone();
            order_top_level(
                &mut ordered,
                &self.entries,
                &self.objects,
                &self.instances,
                first_grafted,
                &self.grafted,
            );
            if ordered != *wide {
                return Err("top-level slots are not in occlusion order".into());
            }
        }
        // Object layouts: blocks, boxes and occlusion order, and the slot
        // maps the builder opens object BVHs through.
        for (i, obj) in self.objects.iter().enumerate() {
            let Some(obj) = obj.as_deref() else { continue };
            if let Some(wide) = &obj.wide {
                wide.validate(&obj.mesh)
                    .and_then(|()| wide.wide.validate_slot_maps(&obj.mesh.bvh))
                    .map_err(|e| format!("object {i}: {e}"))?;
            }
        }
        Ok(())
    }

    /// What must lie inside the world box of ref `r`: for a direct ref its
    /// node's box, for an instanced one the box of its transformed vertices
    /// (the builder clips transformed boxes to their parents', so the
    /// geometry is what must be inside); empty without an object.
    fn placed_geometry_box(&self, r: &TopRef) -> Aabb {
        match self.object(r) {
            Some(obj) if r.instance == INVALID_ID => obj.nodes()[r.node as usize].bounds(),
            Some(obj) => {
                let xf = &self.instances[r.instance as usize];
                let nodes = obj.nodes();
                let mut b = Aabb::EMPTY;
                let mut stack = vec![r.node as usize];
                while let Some(i) = stack.pop() {
                    let n = &nodes[i];
                    if n.is_leaf() {
                        for t in &obj.mesh.triangles[n.prim_range()] {
                            for v in t {
                                b = b.grow(xf.object_to_world.transform_point3(*v));
                            }
                        }
                    } else {
                        stack.push(n.index as usize);
                        stack.push(n.index as usize + 1);
                    }
                }
                b
            }
            None => Aabb::EMPTY,
        }
    }

    /// Bytes of the top-level tree, its refs, the wide top level's entries
    /// and its copied leaf blocks (object BVHs and the wide top-level nodes
    /// not included).
    pub fn top_bytes(&self) -> usize {
        std::mem::size_of_val(self.tree.nodes.as_slice())
            + std::mem::size_of_val(self.refs.as_slice())
            + std::mem::size_of_val(self.entry_refs.as_slice())
            + std::mem::size_of_val(self.entries.as_slice())
            + std::mem::size_of_val(self.blocks.as_slice())
            + std::mem::size_of_val(self.block_entry.as_slice())
            + std::mem::size_of_val(self.block_placement.as_slice())
            + std::mem::size_of_val(self.block_normal_scale.as_slice())
            + self
                .merged
                .as_ref()
                .map_or(0, |m| std::mem::size_of_val(&*m.origins))
    }
}
