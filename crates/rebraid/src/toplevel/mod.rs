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
    /// A collapse whose leaves are not packed yet ([`ObjectBvh::planned`]):
    /// `wide` is `None` until [`ObjectBvh::install`] puts the finished
    /// layout in.
    pending: Option<WideBvh<8>>,
    /// While the layout is pending or being finished, each wide node's
    /// slots as binary nodes (the collapse's `slot_binary`): what the
    /// top-level builder opens a node into ([`ObjectBvh::wide_slots`]).
    plan_slots: Vec<[u32; 8]>,
}

/// For each of `binary_nodes` binary nodes, the wide node collapsed from
/// it (inner nodes), the wide leaf reference naming its blocks (leaves), or
/// `WIDE_EMPTY` (see [`ObjectBvh::wide_of`]).
fn binary_map(w: &WideTriangleBvh, binary_nodes: usize) -> Vec<u32> {
    let mut map = w.wide.wide_of_binary(binary_nodes);
    for (node, slots) in w.wide.nodes.iter().zip(&w.wide.slot_binary) {
        for (&r, &b) in node.child.iter().zip(slots) {
            if r != WIDE_EMPTY && is_leaf_ref(r) {
                map[b as usize] = r;
            }
        }
    }
    map
}

impl ObjectBvh {
    /// The object over `mesh`, collapsed by the default rule.
    pub fn new(mesh: MeshBvh) -> Self {
        Self::with_collapse(mesh, Collapse::default())
    }

    /// The object over `mesh`, its wide layout collapsed by `collapse`
    /// ([`crate::bvh::BuildParams::collapse`]).
    pub fn with_collapse(mesh: MeshBvh, collapse: Collapse) -> Self {
        let mut o = Self::bare(mesh, collapse);
        o.collapse_wide();
        o
    }

    /// The binary tree with its counts and costs, no wide layout.
    fn bare(mesh: MeshBvh, collapse: Collapse) -> Self {
        let n = mesh.bvh.nodes.len();
        let mut o = Self {
            mesh,
            subtree_prims: vec![0; n],
            subtree_cost: vec![0.0; n],
            wide: None,
            wide_of: Vec::new(),
            collapse,
            pending: None,
            plan_slots: Vec::new(),
        };
        o.update_counts_and_costs();
        o
    }

    /// [`ObjectBvh::with_collapse`] up to the collapse: the binary tree,
    /// its counts and costs, and which binary nodes the wide nodes hold
    /// (`pending`, with `wide_of` for the inner nodes), which is all the
    /// re-braiding top-level builder reads of an object. The leaves'
    /// blocks and the occlusion order (two thirds of the wide layout's
    /// time) are made by [`ObjectBvh::finish_plan`] and put in by
    /// [`ObjectBvh::install`]: a scene's commit makes them while it builds
    /// the top level, on the threads the top level's serial phases leave
    /// idle. Not to be traced before then.
    pub(crate) fn planned(mesh: MeshBvh, collapse: Collapse) -> Self {
        let mut o = Self::bare(mesh, collapse);
        if let Ok(plan) = WideBvh::from_bvh_with(&o.mesh.bvh, collapse) {
            o.wide_of = plan.wide_of_binary(o.mesh.bvh.nodes.len());
            o.plan_slots.clone_from(&plan.slot_binary);
            o.pending = Some(plan);
        }
        o
    }

    /// Whether the wide layout waits for [`ObjectBvh::install`].
    pub(crate) fn is_pending(&self) -> bool {
        self.pending.is_some()
    }

    /// The pending collapse, taken out to be finished by
    /// [`ObjectBvh::finish_plan`]; its slots stay for the top-level builder
    /// until [`ObjectBvh::install`].
    pub(crate) fn take_plan(&mut self) -> Option<WideBvh<8>> {
        self.pending.take()
    }

    /// The wide layout of `mesh` from its collapse `plan` (taken out of a
    /// [`ObjectBvh::planned`] object), and its map from binary nodes, as
    /// [`ObjectBvh::install`] takes them.
    pub(crate) fn finish_plan(mesh: &MeshBvh, plan: WideBvh<8>) -> (WideTriangleBvh, Vec<u32>) {
        let wide = WideTriangleBvh::from_plan(mesh, plan);
        let map = binary_map(&wide, mesh.bvh.nodes.len());
        (wide, map)
    }

    /// Put in the layout [`ObjectBvh::finish_plan`] made of this object's
    /// pending collapse.
    pub(crate) fn install(&mut self, (wide, wide_of): (WideTriangleBvh, Vec<u32>)) {
        self.wide = Some(wide);
        self.wide_of = wide_of;
        self.pending = None;
        self.plan_slots = Vec::new();
    }

    /// The binary nodes held by the slots of wide node `w` (`WIDE_EMPTY`
    /// for empty slots), from the layout or, while it is pending, from the
    /// collapse.
    #[inline]
    pub(crate) fn wide_slots(&self, w: u32) -> Option<&[u32; 8]> {
        match &self.wide {
            Some(wide) => wide.wide.slot_binary.get(w as usize),
            None => self.plan_slots.get(w as usize),
        }
    }

    /// (Re)collapse the 8-wide traversal layout from the binary tree; none
    /// when a binary leaf is too large for it (traversal stays binary then).
    fn collapse_wide(&mut self) {
        self.pending = None;
        self.plan_slots = Vec::new();
        self.wide = WideTriangleBvh::from_mesh_with(&self.mesh, self.collapse).ok();
        self.wide_of = match &self.wide {
            Some(w) => binary_map(w, self.mesh.bvh.nodes.len()),
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

/// The arrays of a previous top level's layout, handed back for the next
/// one's ([`TopLevelAccel::take_layout_buffers`], kept between commits by
/// [`builder::TopLevelScratch`]).
///
/// Why: a scene whose top level is rebuilt every frame (one object moving
/// through a re-braided scene) would otherwise lay it out in fresh memory
/// each time, every 4 KiB page of it a fault the kernel answers by zeroing
/// the page: 9,200 faults per frame of `rebraid animate library --scale 2`
/// (about 37 MB: the copied leaf blocks, the collapsed nodes, the entries),
/// before these arrays were reused (docs/performance.md, session 35).
#[derive(Clone, Debug, Default)]
pub struct LayoutBuffers {
    wide: WideBvh<8>,
    entry_refs: Vec<TopRef>,
    entries: Vec<RefEntry>,
    grafted: Vec<(RefEntry, Aabb)>,
    blocks: Vec<Triangle4>,
    block_entry: Vec<u32>,
    block_placement: Vec<(u32, u32)>,
    block_normal_scale: Vec<f32>,
}

impl LayoutBuffers {
    /// Bytes the buffers hold (their capacities).
    pub fn bytes(&self) -> usize {
        fn cap<T>(v: &Vec<T>) -> usize {
            v.capacity() * std::mem::size_of::<T>()
        }
        cap(&self.wide.nodes)
            + cap(&self.wide.binary_of)
            + cap(&self.wide.slot_binary)
            + cap(&self.entry_refs)
            + cap(&self.entries)
            + cap(&self.grafted)
            + cap(&self.blocks)
            + cap(&self.block_entry)
            + cap(&self.block_placement)
            + cap(&self.block_normal_scale)
    }
}

/// Empty `v` and make room for `len` items. A buffer handed back from an
/// earlier top level that is too short grows with 1/16 to spare, so that a
/// scene whose layout grows by a few items per frame does not move to
/// fresh memory every frame (the library's copied blocks vary by +-0.3%
/// from frame to frame of `rebraid animate`); a first allocation is exact.
fn clear_for<T>(v: &mut Vec<T>, len: usize) {
    v.clear();
    if v.capacity() < len {
        let spare = if v.capacity() > 0 { len / 16 } else { 0 };
        v.reserve_exact(len + spare);
    }
}

/// How a committed top level is laid out and traversed, beyond the build.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TopLevelLayout {
    /// The traversal kernel (a scene's choice, by default [`Kernel::best`]).
    pub kernel: Kernel,
    /// See [`RebraidParams::pull_entry_nodes`].
    pub pull_entry_nodes: bool,
    /// See [`RebraidParams::inline_leaf_blocks`].
    pub inline_leaf_blocks: bool,
    /// See [`RebraidParams::inline_instanced_leaves`].
    pub inline_instanced_leaves: bool,
    /// See [`RebraidParams::graft_max_prims`] (0: none).
    pub graft_max_prims: u32,
    /// See [`RebraidParams::graft_budget`].
    pub graft_budget: f32,
    /// See [`RebraidParams::graft_share_per_prim`].
    pub graft_share_per_prim: f32,
    /// An object slot whose entries (placed directly) are grafted whole,
    /// whatever their size and outside the budget: a scene's merged BVH
    /// (see [`crate::scene::SceneParams::merge_placed`]), which stands for
    /// the many objects that re-braiding would have opened, so that the
    /// top level takes its whole tree. On nexuiz (every object merged)
    /// 1,462.5 -> 1,374.3 instructions per diffuse ray, wall time 1.05
    /// (docs/performance.md, session 30), for a copy of its nodes and
    /// blocks (15.1 -> 23.7 MB); since session 31 such a scene, the merged
    /// BVH alone, is walked directly instead ([`TopLevelAccel::direct`]:
    /// 1,271.0), and the graft serves a merged BVH beside other objects or
    /// instances.
    pub graft_whole: Option<u32>,
    /// See [`RebraidParams::collapse`].
    pub collapse: Collapse,
}

/// The object slot that every ref names, placed directly, when it has a
/// wide layout (see [`TopLevelAccel::direct`]). The refs of a top level
/// cover its initial refs' primitives, so refs of one object placed
/// directly (its root, or nodes opened from it) mean the scene is that
/// object.
fn direct_slot(refs: &[TopRef], objects: &[Option<Arc<ObjectBvh>>]) -> Option<u32> {
    let first = refs.first()?;
    let one = refs
        .iter()
        .all(|r| r.object == first.object && r.instance == INVALID_ID);
    let wide = objects
        .get(first.object as usize)?
        .as_deref()?
        .wide
        .as_ref()
        .is_some_and(|w| !w.wide.nodes.is_empty());
    (one && wide).then_some(first.object)
}

/// Copy the triangle blocks of the object leaves that top-level leaves
/// enter directly (one ref, no instance) into the top level, and point
/// those leaves at the copies. Returns the blocks and the entry of each.
/// With `instanced`, leaves entered through an instance are copied too,
/// their vertices transformed into world space (see below).
///
/// Re-braiding opens objects down to their leaves where they overlap (on
/// the shared scenes 44-58% of the refs are object leaves, and on samurai
/// monastery nearly every node a ray visits is a top-level node), so most
/// entries test a few blocks and leave. Through the entry, that is a chain
/// of loads (the entry, the object table, the object, its block array)
/// before the first block load; from the top level's own array it is what
/// a flat BVH's leaf costs. The copies cost 160 bytes per block and a copy
/// per top-level build.
///
/// Instanced leaves: session 7 copied them in object space, their rays
/// transformed through the instance ray cache as an entry's are, and the
/// instanced scenes got slower (paired A/B, 30 alternations: cocoa temple
/// 0.92-0.99, ravenbridge 0.93-0.98, 2CylinderEngine 0.96-0.98). Copied
/// in world space (`instanced`), one copy per placement, they are tested
/// with the world ray like a direct leaf's copy: no entry, no instance
/// ray. The copy is one affine transform per vertex, as
/// [`crate::mesh::MeshBvh::build_transformed`] bakes a placement.
fn inline_leaf_blocks(
    wide: &mut WideBvh<8>,
    entries: &[RefEntry],
    objects: &[Option<Arc<ObjectBvh>>],
    instances: &[InstanceXf],
    instanced: bool,
    (mut blocks, mut block_entry): (Vec<Triangle4>, Vec<u32>),
) -> (Vec<Triangle4>, Vec<u32>) {
    let block_base = entries.len();
    // The object leaf a slot enters, as (entry, object blocks, the
    // instance's transform for a leaf entered through one).
    type Copied<'a> = (u32, &'a [Triangle4], Option<&'a Affine3A>);
    let copied_leaf = |c: u32| -> Option<Copied<'_>> {
        if !is_leaf_ref(c) || c == WIDE_EMPTY {
            return None;
        }
        let (ri, count) = decode_leaf(c);
        let e = &entries[ri as usize];
        if count != 1 || e.wide == WIDE_EMPTY || !is_leaf_ref(e.wide) {
            return None;
        }
        let xf = if e.instance == INVALID_ID {
            None
        } else if instanced {
            Some(&instances.get(e.instance as usize)?.object_to_world)
        } else {
            return None;
        };
        let ow = objects.get(e.object as usize)?.as_deref()?.wide.as_ref()?;
        let (first, n) = decode_leaf(e.wide);
        Some((ri, &ow.blocks[first as usize..(first + n) as usize], xf))
    };
    // Planned first, in slot order (which slots are copied and where),
    // then copied in parallel into one allocation: into the previous
    // commit's buffer when the scene hands it back. Fresh memory's page
    // faults take most of the copy's time (0.3-0.8 ms for samurai
    // monastery's 5,512 blocks; 36-175 ms for the library scene's 274,675
    // blocks at 3M triangles), and faults on two threads take half as long;
    // on huge pages (`crate::huge_pages`) a third as long again.
    let mut plan: Vec<Copied<'_>> = Vec::new();
    let mut total = block_base;
    for node in &mut wide.nodes {
        for slot in 0..node.child_count() {
            let Some((ri, leaf, xf)) = copied_leaf(node.child[slot]) else {
                continue;
            };
            if total + leaf.len() > WIDE_MAX_PRIMITIVES {
                // Leaf indices have 27 bits: the rest stay entries.
                continue;
            }
            plan.push((ri, leaf, xf));
            node.child[slot] = encode_leaf(total as u32, leaf.len() as u32);
            total += leaf.len();
        }
    }
    let total = total - block_base;
    clear_for(&mut blocks, total);
    crate::huge_pages::advise(&mut blocks);
    clear_for(&mut block_entry, total);
    // Pieces of about `BLOCK_COPY_CHUNK` blocks each, whole leaves, with
    // their destinations: the same pieces at any thread count.
    let mut pieces = Vec::new();
    let (mut dst, mut dst_entry) = (
        &mut blocks.spare_capacity_mut()[..total],
        &mut block_entry.spare_capacity_mut()[..total],
    );
    let mut rest = &plan[..];
    while !rest.is_empty() {
        let mut n = 0;
        let mut take = 0;
        while take < rest.len() && (n == 0 || n + rest[take].1.len() <= BLOCK_COPY_CHUNK) {
            n += rest[take].1.len();
            take += 1;
        }
        let (d, d_rest) = std::mem::take(&mut dst).split_at_mut(n);
        let (e, e_rest) = std::mem::take(&mut dst_entry).split_at_mut(n);
        pieces.push((&rest[..take], d, e));
        (dst, dst_entry, rest) = (d_rest, e_rest, &rest[take..]);
    }
    pieces.into_par_iter().for_each(|(plan, d, e)| {
        let mut at = 0;
        for &(ri, leaf, xf) in plan {
            for (k, b) in leaf.iter().enumerate() {
                d[at + k].write(match xf {
                    None => *b,
                    Some(xf) => b.transformed(xf),
                });
                e[at + k].write(ri);
            }
            at += leaf.len();
        }
    });
    // SAFETY: the pieces cover the first `total` slots of both spare
    // capacities exactly (they were split off in order and the plan's leaf
    // lengths sum to `total`), and each piece wrote every slot it holds.
    unsafe {
        blocks.set_len(total);
        block_entry.set_len(total);
    }
    (blocks, block_entry)
}

/// Blocks per piece of `inline_leaf_blocks`' parallel copy (160 KB).
const BLOCK_COPY_CHUNK: usize = 1024;

/// Fill the empty slots of the collapsed top level's nodes with the child
/// slots of the object nodes its refs enter.
///
/// A top-level leaf holding one ref sends a ray that hits its box into the
/// object, where the first thing it does is test the 8-wide node the ref
/// names. When the top-level node holding the leaf has room for that node's
/// children (`k - 1` free slots for `k` children), its slot is replaced by
/// them, each a new entry into the object (a wide node or a leaf of
/// triangle blocks), and the object node is never visited: one node test
/// fewer for each ray that enters there, at the cost of entering the object
/// through whichever of the children it hits. By the SAH every such
/// replacement is a gain (a node's cost goes, its children's boxes are
/// tested in a node that is tested anyway); slots are replaced largest box
/// first while any fit, pulled children included. The children come from
/// the objects' wide layouts (as the builder's opening does), their world
/// boxes as the builder makes them (`placed_bounds`).
///
/// This is the collapse step of a wide build carried across the boundary
/// between the top level and the objects: the top-level tree is collapsed
/// to 8 wide on its own, and its nodes hold 4.3-4.7 children on average on
/// the shared scenes.
fn pull_into_top_level(
    wide: &mut WideBvh<8>,
    entry_refs: &mut Vec<TopRef>,
    entries: &mut Vec<RefEntry>,
    objects: &[Option<Arc<ObjectBvh>>],
    instances: &[InstanceXf],
) {
    // The entry a slot's single-ref leaf names and the child count of the
    // object wide node it enters, if that node has children to pull.
    let pullable = |leaf: u32, entries: &[RefEntry]| -> Option<(u32, usize)> {
        let (first, node) = entered_inner_node(leaf, entries, objects)?;
        Some((first, node.child_count()))
    };
    for n in 0..wide.nodes.len() {
        loop {
            let node = &wide.nodes[n];
            let used = node.child_count();
            let free = 8 - used;
            if free == 0 {
                break;
            }
            let mut best: Option<(usize, u32, f32)> = None;
            for s in 0..used {
                if let Some((first, k)) = pullable(node.child[s], entries)
                    && k - 1 <= free
                {
                    let area = node.child_bounds(s).half_area();
                    if best.is_none_or(|b| area > b.2) {
                        best = Some((s, first, area));
                    }
                }
            }
            let Some((s, first, _)) = best else { break };
            let parent_box = wide.nodes[n].child_bounds(s);
            let node = &mut wide.nodes[n];
            let slot_binary = &mut wide.slot_binary[n];
            let split = (&mut *entry_refs, &mut *entries);
            split_entry(
                first,
                &parent_box,
                split,
                objects,
                instances,
                |j, ri, b, _| {
                    // The first child takes the ref's place (entry and slot).
                    let slot = if j == 0 { s } else { used + j - 1 };
                    node.set_child(slot, b, encode_leaf(ri, 1));
                    // The slot no longer holds a top-level binary node.
                    slot_binary[slot] = WIDE_EMPTY;
                },
            );
        }
    }
}

/// The entry that top-level child reference `leaf` names when it is a
/// single-entry leaf entering an inner node of an object's wide layout, and
/// that node: what `pull_into_top_level` and `graft_entries` can open.
fn entered_inner_node<'o>(
    leaf: u32,
    entries: &[RefEntry],
    objects: &'o [Option<Arc<ObjectBvh>>],
) -> Option<(u32, &'o WideNode<8>)> {
    if !is_leaf_ref(leaf) || leaf == WIDE_EMPTY {
        return None;
    }
    let (first, count) = decode_leaf(leaf);
    let e = entries[first as usize];
    if count != 1 || e.wide == WIDE_EMPTY || is_leaf_ref(e.wide) {
        return None;
    }
    let obj = objects.get(e.object as usize)?.as_deref()?;
    Some((first, &obj.wide.as_ref()?.wide.nodes[e.wide as usize]))
}

/// Split entry `ri` into entries for the children of the object wide node
/// it enters: the first child's replaces it (ref and entry), the others are
/// appended. `place(j, entry index, placed box, child's wide reference)`
/// puts child `j` into a top-level slot; its box is placed as the builder
/// places opened nodes ([`builder::placed_bounds`], clipped to `slot_box`),
/// from the object node just read (the binary node would be another load).
/// The entry must enter an inner node of an object with a wide layout.
fn split_entry(
    ri: u32,
    slot_box: &Aabb,
    (entry_refs, entries): (&mut Vec<TopRef>, &mut Vec<RefEntry>),
    objects: &[Option<Arc<ObjectBvh>>],
    instances: &[InstanceXf],
    mut place: impl FnMut(usize, u32, &Aabb, u32),
) {
    let e = entries[ri as usize];
    let obj = objects[e.object as usize]
        .as_deref()
        .expect("split entries have objects");
    let ow = &obj.wide.as_ref().expect("split entries are wide").wide;
    let on = &ow.nodes[e.wide as usize];
    let xf = (e.instance != INVALID_ID).then(|| &instances[e.instance as usize]);
    for j in 0..on.child_count() {
        let b = ow.slot_binary[e.wide as usize][j];
        let child = TopRef {
            object: e.object,
            node: b,
            instance: e.instance,
            prims: obj.subtree_prims[b as usize],
        };
        let entry = RefEntry {
            wide: on.child[j],
            node: b,
            ..e
        };
        let cri = if j == 0 {
            entry_refs[ri as usize] = child;
            entries[ri as usize] = entry;
            ri
        } else {
            entry_refs.push(child);
            entries.push(entry);
            (entries.len() - 1) as u32
        };
        let bounds = builder::placed_bounds(obj, xf, b, on.child_bounds(j), slot_box);
        place(j, cri, &bounds, on.child[j]);
    }
}

/// Graft the object subtrees of at most `max_prims` primitives that
/// top-level slots enter into the top level: such a slot's entry becomes a
/// copy of the object's wide node it enters, in a new top-level node whose
/// slots are entries into that node's children (boxes placed as the
/// builder places opened nodes, [`builder::placed_bounds`]), and so on down
/// to the object's leaves, which `inline_leaf_blocks` then copies (in
/// world space when instanced). The first child's entry reuses the
/// grafted entry's index, as `pull_into_top_level` does.
///
/// Why: an entry into an object's inner node costs a ray about 120
/// instructions (the entry record, the object, the nested walk's set-up;
/// session 27), and re-braiding leaves most entries at small subtrees
/// (nexuiz: 1,079 of 1,536 entries at 64 primitives or fewer). Unlike
/// opening those refs in the builder, which bins them by the SAH, the
/// graft copies the object's own wide nodes (one read per node, no
/// collapse). Depth stays within [`MAX_DEPTH`] (deeper nodes stay entries).
///
/// The copies cost build time and memory in proportion to the primitives
/// under the grafted entries, so at most `budget` of them are grafted, the
/// entries with the most slot area per primitive first (the likeliest to
/// be entered per primitive copied): at a tenth of the distinct
/// primitives, 58-77% of what grafting every entry of up to 64 primitives
/// saves on nexuiz, the engine and cocoa, and on the 3M-triangle library
/// 19 MB of copies instead of 116 MB.
///
/// Past the budget, an entry whose slot box has at least `share_per_prim`
/// of the root box's area per primitive under it is grafted all the same,
/// up to `cap` primitives in all: rays through the scene enter such a
/// slot often enough that the copy pays for itself after about 100,000 of
/// them (see [`builder::RebraidParams::graft_share_per_prim`]).
///
/// Appends to `grafted`, for each new node (they are appended, in order),
/// the entry it replaced and that entry's slot box: what `order_top_level` needs to
/// leave the copies in the object's own occlusion order.
fn graft_entries(
    wide: &mut WideBvh<8>,
    (entry_refs, entries, grafted): (
        &mut Vec<TopRef>,
        &mut Vec<RefEntry>,
        &mut Vec<(RefEntry, Aabb)>,
    ),
    objects: &[Option<Arc<ObjectBvh>>],
    instances: &[InstanceXf],
    max_prims: u32,
    (budget, share_per_prim, cap, whole): (u64, f32, u64, Option<u32>),
) {
    // Depth of every node (the root is 1).
    let mut depth = vec![0u32; wide.nodes.len()];
    let mut stack = vec![(0u32, 1u32)];
    while let Some((n, d)) = stack.pop() {
        depth[n as usize] = d;
        let node = &wide.nodes[n as usize];
        for &c in &node.child[..node.child_count()] {
            if !is_leaf_ref(c) {
                stack.push((c, d + 1));
            }
        }
    }
    let graftable = |c: u32, entries: &[RefEntry]| -> Option<u32> {
        entered_inner_node(c, entries, objects).map(|(ri, _)| ri)
    };
    // Entries of the slot grafted whole (see `TopLevelLayout::graft_whole`).
    let is_whole = |e: &RefEntry| whole == Some(e.object) && e.instance == INVALID_ID;
    // Candidates by the chance that a ray reaching the top level enters
    // them (their slot's area) per primitive copied: most entries saved
    // for the budget first. Ties by slot, so the order is deterministic.
    let mut candidates: Vec<(f32, u32, u32)> = Vec::new();
    for (n, node) in wide.nodes.iter().enumerate() {
        if depth[n] == 0 || depth[n] >= MAX_DEPTH {
            continue;
        }
        for s in 0..node.child_count() {
            if let Some(ri) = graftable(node.child[s], entries) {
                let prims = entry_refs[ri as usize].prims;
                if prims <= max_prims || is_whole(&entries[ri as usize]) {
                    let area = node.child_bounds(s).half_area();
                    candidates.push((area / prims.max(1) as f32, n as u32, s as u32));
                }
            }
        }
    }
    candidates.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then((a.1, a.2).cmp(&(b.1, b.2))));
    // Beyond the budget: candidates whose slot area per primitive is at
    // least `share_per_prim` of the root box's, up to `cap` primitives.
    let dense_from = share_per_prim * wide.root_bounds.half_area();
    let (mut spent, mut whole_prims) = (0u64, 0u64);
    candidates.retain(|&(density, n, s)| {
        let ri = decode_leaf(wide.nodes[n as usize].child[s as usize]).0;
        let prims = entry_refs[ri as usize].prims as u64;
        if is_whole(&entries[ri as usize]) {
            whole_prims += prims;
            return true;
        }
        let dense = share_per_prim > 0.0 && density >= dense_from;
        if spent + prims > budget && !(dense && spent + prims <= cap) {
            return false;
        }
        spent += prims;
        true
    });
    // Room for the copies at once (about a node per eight primitives and
    // an entry per two; growing the arrays one push at a time copied them
    // over and over: 4M instructions of the 2CylinderEngine's grafts).
    let more = (spent + whole_prims) as usize;
    wide.nodes.reserve(more / 8);
    wide.binary_of.reserve(more / 8);
    wide.slot_binary.reserve(more / 8);
    depth.reserve(more / 8);
    grafted.reserve(more / 8);
    entries.reserve(more / 2);
    entry_refs.reserve(more / 2);
    let mut work = Vec::new();
    for &(_, n, s) in &candidates {
        // The subtree, node by node: a grafted node's inner children are
        // grafted in turn (each within the subtree's primitives).
        work.clear();
        work.push((n, s));
        while let Some((n, s)) = work.pop() {
            let (n, s) = (n as usize, s as usize);
            let Some(ri) = graftable(wide.nodes[n].child[s], entries) else {
                continue;
            };
            if depth[n] >= MAX_DEPTH {
                continue;
            }
            let slot_box = wide.nodes[n].child_bounds(s);
            let new = wide.nodes.len() as u32;
            grafted.push((entries[ri as usize], slot_box));
            let mut node = WideNode::<8>::EMPTY;
            let split = (&mut *entry_refs, &mut *entries);
            split_entry(ri, &slot_box, split, objects, instances, |j, cri, b, w| {
                node.set_child(j, b, encode_leaf(cri, 1));
                if !is_leaf_ref(w) {
                    work.push((new, j as u32));
                }
            });
            wide.nodes.push(node);
            // Grafted nodes hold no top-level binary node.
            wide.binary_of.push(WIDE_EMPTY);
            wide.slot_binary.push([WIDE_EMPTY; 8]);
            depth.push(depth[n] + 1);
            wide.nodes[n].child[s] = new;
            wide.slot_binary[n][s] = WIDE_EMPTY;
        }
    }
}

/// Occlusion statistics of entry `r` seen from a top-level slot of box
/// `slot_box` (see [`crate::bvh::occlusion_order`]): those of its object
/// subtree, the hit probability scaled by the chance that a ray entering the
/// slot box enters the subtree's (placed) box. Entering an instance costs
/// about one more unit (transforming the ray, preparing its testers).
///
/// `alone`: the slot holds this entry only. A direct entry's placed box is
/// then the slot box itself (the builder, the collapse, `pull_into_top_level`
/// and `graft_entries` all give it the node's box), so the scale is 1 and
/// the object's binary node is not read: one cache miss per slot less in a
/// pass over every slot of the top level.
fn ref_occlusion(
    objects: &[Option<Arc<ObjectBvh>>],
    instances: &[InstanceXf],
    r: &RefEntry,
    slot_box: &Aabb,
    alone: bool,
) -> OcclusionStats {
    let Some(obj) = objects.get(r.object as usize).and_then(|o| o.as_deref()) else {
        return OcclusionStats::EMPTY;
    };
    let w = r.wide;
    let mut st = match &obj.wide {
        Some(wide) if w != WIDE_EMPTY && !is_leaf_ref(w) => wide.occlusion[w as usize],
        Some(wide) if w != WIDE_EMPTY => leaf_occlusion(&wide.block_misses, w),
        // No wide layout: the binary subtree's SAH cost, and no claim to
        // occlude (visited last).
        _ => OcclusionStats {
            hit_probability: 0.0,
            cost: obj.subtree_cost[r.node as usize].max(1.0),
        },
    };
    let (placed_area, entry_cost) = match instances.get(r.instance as usize) {
        Some(xf) if r.instance != INVALID_ID => (
            obj.nodes()[r.node as usize].bounds().half_area() * xf.area_scale,
            1.0,
        ),
        _ if alone => return st,
        _ => (obj.nodes()[r.node as usize].bounds().half_area(), 0.0),
    };
    let slot_area = slot_box.half_area();
    if slot_area > 0.0 && placed_area.is_finite() {
        st.hit_probability *= (placed_area / slot_area).clamp(0.0, 1.0);
    }
    st.cost += entry_cost;
    st
}

/// Put the top level's slots in occlusion order (see
/// [`crate::bvh::occlusion_order`]) by the stats of the refs under them.
///
/// The nodes `graft_entries` appended (from `first_grafted`, each with the
/// entry it replaced and its slot box) are copies of object nodes, which
/// the object's build already put in occlusion order: they are left as
/// they are, each with the stats of the entry it replaced. Ordering them
/// again took about 700 instructions per node, a quarter of what grafting
/// the 2CylinderEngine's dense entries cost (callgrind, session 29).
fn order_top_level(
    wide: &mut WideBvh<8>,
    entries: &[RefEntry],
    objects: &[Option<Arc<ObjectBvh>>],
    instances: &[InstanceXf],
    first_grafted: usize,
    grafted: &[(RefEntry, Aabb)],
) -> Vec<OcclusionStats> {
    let leaf = |leaf: u32, slot_box: &Aabb| {
        let (first, count) = decode_leaf(leaf);
        let (mut miss, mut cost) = (1.0f32, 0.0f32);
        for r in &entries[first as usize..(first + count) as usize] {
            let st = ref_occlusion(objects, instances, r, slot_box, count == 1);
            miss *= 1.0 - st.hit_probability;
            cost += st.cost;
        }
        OcclusionStats::from_miss(miss, cost)
    };
    let fixed = |n: usize| {
        let (r, slot_box) = &grafted[n - first_grafted];
        ref_occlusion(objects, instances, r, slot_box, true)
    };
    order_for_occlusion_except(wide, leaf, first_grafted, fixed)
}

/// The best hit so far inside a top-level traversal: (t, u, v, hit
/// reference within its object (see [`ObjectBvh::hit_record`]), ref index).
type RefHit = (f32, f32, f32, u32, u32);

/// The closest-hit rule of the top level (see
/// [`crate::bvh::triangle4::nearer`]): nearer, or exactly as near with a
/// smaller (ref index, hit reference); each triangle has one such key, so
/// ties go the same way in any visit order.
#[inline(always)]
fn nearer_ref(t: f32, ri: u32, k: u32, best: &Option<RefHit>) -> bool {
    best.is_none_or(|b| t < b.0 || (t == b.0 && (ri, k) < (b.4, b.3)))
}

/// The [`RefHit`] key as one integer (ref index above, hit reference
/// below), for the packet lanes' tie rule.
#[inline(always)]
fn ref_key(ri: u32, k: u32) -> u64 {
    (ri as u64) << 32 | k as u64
}

/// The ref index of a [`RefHit`] in the top level's own copied blocks (the
/// hit reference is then a lane of [`TopLevelAccel::blocks`]).
const INLINE_HIT: u32 = u32::MAX;

/// Prepared instance rays kept by a single-ray walk (see `RayState`).
const INSTANCE_CACHE: usize = 4;

/// Prepared instance rays kept per lane of a packet: one. Each slot holds
/// the instance ray's AVX2 box tester too (about 500 bytes in all), so
/// four slots per lane made a packet's lane states 16 KB of its stack
/// frame, with one byte of each slot written when the states are made.
/// One slot, measured (session 15, paired medians of 10 alternations,
/// re-braided, one thread, 480x270): primary rays 4-8% faster on every
/// shared scene, shadow rays 2-4%, diffuse rays (walked alone) unchanged;
/// callgrind's first-level misses per samurai monastery primary ray 4.24
/// -> 3.51.
const LANE_INSTANCE_CACHE: usize = 1;

/// An instance's id and the ray in its space, prepared for its box and
/// triangle tests, with its SIMD box tester (made when an entry into one of
/// the instance's wide nodes first needs it).
type InstanceRay<T> = (u32, Ray, WatertightRay, Option<T>);

/// One ray through the top level and into the object BVHs, inside a SIMD
/// kernel's context (see [`with_kernel`]): testers are made for the world
/// ray once and for each instance's object-space ray once per run of refs
/// sharing the instance, not per top-level leaf. `ANY`: stop at the first
/// hit (occlusion). The caller has checked [`Ray::is_valid`].
#[inline(always)]
fn walk_ray<const ANY: bool, F: TesterFactory>(
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
struct RayState<'r, T, const N: usize> {
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
struct RayWalk<'a, const ANY: bool> {
    accel: &'a TopLevelAccel,
    ray: &'a Ray,
    counters: &'a mut TraversalCounters,
    best: Option<RefHit>,
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
struct BatchWalk<'a, const ANY: bool, O, A> {
    accel: &'a TopLevelAccel,
    rays: &'a [Ray],
    out: &'a mut [O],
    answer: A,
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
mod packets {
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
    pub(super) fn intersect(
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
    pub(super) fn occluded(
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

impl TopLevelAccel {
    /// Assemble a committed top level and collapse its tree to 8 wide;
    /// traversal runs `layout.kernel` (falling back to scalar when
    /// unavailable). `block_buffer` is memory for the copied leaf blocks
    /// (a previous top level's [`TopLevelAccel::blocks`], or empty).
    ///
    /// `layout` says how: its `pull_entry_nodes` fills the collapsed top
    /// level's empty slots from the object nodes its refs enter
    /// (`pull_into_top_level`), its `inline_leaf_blocks` copies the blocks
    /// of object leaves entered directly into the top level
    /// (`inline_leaf_blocks`, both in this module).
    pub fn new(
        tree: Bvh,
        refs: Vec<TopRef>,
        objects: Vec<Option<Arc<ObjectBvh>>>,
        instances: Vec<InstanceXf>,
        build_stats: TopLevelBuildStats,
        layout: TopLevelLayout,
        buffers: LayoutBuffers,
    ) -> Self {
        let mut clock = std::time::Instant::now();
        let mut lap = || {
            let now = std::time::Instant::now();
            let ms = (now - clock).as_secs_f64() * 1e3;
            clock = now;
            ms
        };
        let mut times = LayoutTimes::default();
        let LayoutBuffers {
            wide: mut wide_buffer,
            mut entry_refs,
            mut entries,
            mut grafted,
            blocks: block_buffer,
            block_entry: block_entry_buffer,
            block_placement,
            block_normal_scale,
        } = buffers;
        let mut wide = wide_buffer
            .collapse_from_with(&tree, layout.collapse)
            .ok()
            .map(|()| wide_buffer)
            .filter(|w| !w.is_empty());
        times.collapse_ms = lap();
        clear_for(&mut entry_refs, refs.len());
        entry_refs.extend_from_slice(&refs);
        clear_for(&mut entries, refs.len());
        refs.par_iter()
            .with_min_len(4096)
            .map(|r| RefEntry {
                object: r.object,
                instance: r.instance,
                wide: objects
                    .get(r.object as usize)
                    .and_then(|o| o.as_deref())
                    .and_then(|o| o.wide.as_ref().and(o.wide_of.get(r.node as usize)))
                    .copied()
                    .unwrap_or(WIDE_EMPTY),
                node: r.node,
            })
            .collect_into_vec(&mut entries);
        let direct = direct_slot(&refs, &objects);
        grafted.clear();
        if let Some(w) = &mut wide {
            // A direct top level is never walked: no pulls, grafts or
            // copies to make for it.
            if layout.pull_entry_nodes && direct.is_none() {
                pull_into_top_level(w, &mut entry_refs, &mut entries, &objects, &instances);
            }
            times.entries_ms = lap();
            let first_grafted = w.nodes.len();
            if direct.is_none()
                && ((layout.graft_max_prims > 0 && layout.graft_budget > 0.0)
                    || layout.graft_whole.is_some())
            {
                // Primitives of the distinct objects, each counted once.
                let prims: u64 = objects.iter().flatten().map(|o| o.mesh.len() as u64).sum();
                graft_entries(
                    w,
                    (&mut entry_refs, &mut entries, &mut grafted),
                    &objects,
                    &instances,
                    layout.graft_max_prims,
                    (
                        (layout.graft_budget as f64 * prims as f64) as u64,
                        layout.graft_share_per_prim,
                        prims,
                        layout.graft_whole,
                    ),
                );
            }
            times.graft_ms = lap();
            // Leaves index the entries directly (the tree has no index array).
            w.prim_count = entry_refs.len();
            order_top_level(w, &entries, &objects, &instances, first_grafted, &grafted);
            times.order_ms = lap();
        } else {
            times.entries_ms = lap();
        }
        let block_base = entries.len() as u32;
        let (blocks, block_entry) = match &mut wide {
            Some(w) if layout.inline_leaf_blocks && direct.is_none() => inline_leaf_blocks(
                w,
                &entries,
                &objects,
                &instances,
                layout.inline_instanced_leaves,
                (block_buffer, block_entry_buffer),
            ),
            _ => Default::default(),
        };
        let mut accel = Self {
            tree,
            refs,
            objects,
            instances,
            build_stats,
            wide,
            kernel: layout.kernel,
            entry_refs,
            entries,
            blocks,
            block_entry,
            block_placement,
            block_normal_scale,
            block_base,
            baked: Vec::new(),
            grafted,
            merged: None,
            direct,
        };
        accel.place_blocks();
        times.copy_ms = lap();
        accel.build_stats.layout = times;
        accel
    }

    /// Fill `block_placement` and `block_normal_scale` from `block_entry`
    /// and the baked placements.
    fn place_blocks(&mut self) {
        // A leaf's blocks share their entry: each entry's values are made
        // once (an instanced entry's scale is a determinant).
        type Placed = ((u32, u32), f32);
        let mut last: Option<(u32, Placed)> = None;
        // Into the arrays' own memory (handed back from an earlier top
        // level, see `LayoutBuffers`).
        let (mut placement, mut scale) = (
            std::mem::take(&mut self.block_placement),
            std::mem::take(&mut self.block_normal_scale),
        );
        clear_for(&mut placement, self.block_entry.len());
        clear_for(&mut scale, self.block_entry.len());
        for &ri in &self.block_entry {
            let (p, n) = match last {
                Some((r, v)) if r == ri => v,
                _ => {
                    let v = (self.entry_placement(ri), self.block_entry_normal_scale(ri));
                    last = Some((ri, v));
                    v
                }
            };
            placement.push(p);
            scale.push(n);
        }
        self.block_placement = placement;
        self.block_normal_scale = scale;
    }

    /// Take the arrays of this top level's layout for the next top level's
    /// (see [`LayoutBuffers`]), leaving this one empty of them: it must
    /// not be traced afterwards.
    pub fn take_layout_buffers(&mut self) -> LayoutBuffers {
        LayoutBuffers {
            wide: self.wide.take().unwrap_or_default(),
            entry_refs: std::mem::take(&mut self.entry_refs),
            entries: std::mem::take(&mut self.entries),
            grafted: std::mem::take(&mut self.grafted),
            blocks: std::mem::take(&mut self.blocks),
            block_entry: std::mem::take(&mut self.block_entry),
            block_placement: std::mem::take(&mut self.block_placement),
            block_normal_scale: std::mem::take(&mut self.block_normal_scale),
        }
    }

    /// The (object, instance) a hit on a block copied for entry `ri`
    /// reports: the entry's placement.
    fn entry_placement(&self, ri: u32) -> (u32, u32) {
        let e = &self.entries[ri as usize];
        if e.instance == INVALID_ID {
            self.placement_of_slot(e.object)
        } else {
            (e.object, e.instance)
        }
    }

    /// What turns the world cross product of a block copied for entry `ri`
    /// into the normal the entry's own path reports: 1 for a direct leaf;
    /// for an instanced leaf copied in world space `|det|` of the
    /// world-to-object transform, as the world cross product is `det(M)
    /// M^-T n` and the entry's normal `sign(det M) M^-T n`.
    fn block_entry_normal_scale(&self, ri: u32) -> f32 {
        let e = &self.entries[ri as usize];
        match self.instances.get(e.instance as usize) {
            Some(xf) if e.instance != INVALID_ID => xf.world_to_object.matrix3.determinant().abs(),
            _ => 1.0,
        }
    }

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
