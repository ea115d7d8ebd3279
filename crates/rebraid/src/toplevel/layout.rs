//! The layout pass of a committed top level: the binary tree collapsed to
//! 8 wide, object nodes pulled and grafted into it, its slots put in
//! occlusion order, and the object leaves it enters copied into it
//! ([`TopLevelAccel::new`]).

use super::*;

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
pub(super) fn clear_for<T>(v: &mut Vec<T>, len: usize) {
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
pub(super) fn direct_slot(refs: &[TopRef], objects: &[Option<Arc<ObjectBvh>>]) -> Option<u32> {
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
pub(super) fn inline_leaf_blocks(
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
pub(super) const BLOCK_COPY_CHUNK: usize = 1024;

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
pub(super) fn pull_into_top_level(
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
pub(super) fn entered_inner_node<'o>(
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
pub(super) fn split_entry(
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
pub(super) fn graft_entries(
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
pub(super) fn ref_occlusion(
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
pub(super) fn order_top_level(
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
    pub(super) fn place_blocks(&mut self) {
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
    pub(super) fn entry_placement(&self, ri: u32) -> (u32, u32) {
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
    pub(super) fn block_entry_normal_scale(&self, ri: u32) -> f32 {
        let e = &self.entries[ri as usize];
        match self.instances.get(e.instance as usize) {
            Some(xf) if e.instance != INVALID_ID => xf.world_to_object.matrix3.determinant().abs(),
            _ => 1.0,
        }
    }
}
