//! Child order for occlusion rays: the RTSAH order.
//!
//! T. Ize, C. Hansen, "RTSAH Traversal Order for Occlusion Rays",
//! Eurographics 2011. An occlusion (any-hit) query stops at the first hit,
//! so the order in which it visits a node's hit children decides how much
//! of the tree it sees before it is occluded; distance order, the right
//! order for closest hits, is no better than any other here. The ray
//! termination SAH estimates, for a ray that enters a box, the probability
//! `p` that it hits something inside and the expected cost `c` of finding
//! out; visiting children in decreasing `p / c` minimises the expected cost
//! of a sequence of independent tests that each end the search with
//! probability `p` (the classic ordering argument). The order is static:
//! it is computed once per tree and stored as the slot order, which the
//! occlusion kernels follow (slot order among the hit children; closest-hit
//! queries sort by entry distance and use slot order only for ties).
//!
//! Estimates, for a ray entering a box with half area `S` (a random line
//! through a convex box meets a flat triangle of area `A` inside it with
//! probability `A / S`, after Cauchy's projection formula: mean projected
//! areas are `S / 2` for the box and `A / 2` for the two-sided triangle):
//! - a leaf: `p = 1 - prod(1 - min(1, A_j / S))` over its triangles,
//!   `c` = its blocks' test cost;
//! - a node with children `i` (box half areas `S_i`, entered with
//!   probability `q_i = S_i / S`) in the chosen order:
//!   `c = NODE_COST + sum_i q_i c_i prod_{j<i} (1 - q_j p_j)` and
//!   `p = 1 - prod_i (1 - q_i p_i)` (independent children).
//!
//! Object and flat trees are ordered when they are packed (the blocks' miss
//! probabilities are computed while the triangles are at hand, see
//! [`super::triangle4::pack_triangle4_with_misses`]); the top level orders
//! its slots by the stats of the object subtrees its refs enter
//! (`TopLevelAccel::new`), so both levels agree on what occludes.
//!
//! Measured against the collapse's order (`rebraid bench SCENES --modes
//! flat,rebraided --threads 1 --width 640 --height 360 --reps 3` on the
//! shared scenes and `library --scale 1`, two alternations of the two
//! binaries): re-braided shadow rays library +24-30% (10.6-10.8 -> 13.4-13.8
//! Mrays/s), ravenbridge +4-7%, samurai, openarena and cocoa temple equal,
//! nexuiz and 2CylinderEngine -3-5%; closest-hit rays change only where
//! entry distances tie (rays starting inside several boxes): library
//! primary +35-40%, flat samurai primary +12-16%, flat nexuiz primary -6%,
//! diffuse equal to +9%. Builds +1-3% (the sweep and the areas). The
//! session-3 experiments with a static order by box area alone (library
//! shadow +60% but nexuiz -19%, engine -15%) show why the key must weigh
//! what a box holds against what it costs.

use rayon::prelude::*;

use super::wide::{WIDE_EMPTY, WideBvh, WideNode, is_leaf_ref};
use crate::Aabb;

/// Cost of testing one wide node's child boxes, in the unit of one leaf
/// block (four triangles) test.
pub const NODE_COST: f32 = 1.0;

/// What a ray entering a subtree's box can expect of it (see the module
/// docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OcclusionStats {
    /// Probability that the ray hits a primitive of the subtree.
    pub hit_probability: f32,
    /// Expected cost of an occlusion query through the subtree, in leaf
    /// block tests.
    pub cost: f32,
}

impl OcclusionStats {
    /// Nothing to hit (an empty slot).
    pub const EMPTY: Self = Self {
        hit_probability: 0.0,
        cost: NODE_COST,
    };

    /// Stats of a leaf whose primitives have the given hit probabilities.
    pub fn leaf(probabilities: impl IntoIterator<Item = f32>, cost: f32) -> Self {
        let miss: f32 = probabilities
            .into_iter()
            .map(|p| 1.0 - sanitize(p))
            .product();
        Self::from_miss(miss, cost)
    }

    /// Stats of a leaf (or a group of refs) that a ray misses with
    /// probability `miss` (the product over its parts).
    pub fn from_miss(miss: f32, cost: f32) -> Self {
        Self {
            hit_probability: 1.0 - sanitize(miss),
            cost: cost.max(f32::MIN_POSITIVE),
        }
    }

    /// The ordering key: termination probability per unit of cost.
    #[inline]
    fn key(&self) -> f32 {
        self.hit_probability / self.cost
    }
}

/// Probability that a line entering a box misses a flat triangle of area
/// `area` inside it: `1 - min(1, area / S)` for the box's half area `S`,
/// given as `inv_half_area = 1 / S` (infinite for a box without area, in
/// which every line meets a triangle that has one). A NaN area (padding,
/// collapsed triangles) misses.
#[inline(always)]
pub fn triangle_miss_probability(area: f32, inv_half_area: f32) -> f32 {
    let p = area * inv_half_area;
    if p >= 0.0 { 1.0 - p.min(1.0) } else { 1.0 }
}

/// Clamp to `[0, 1]`, NaN to 0.
#[inline]
fn sanitize(p: f32) -> f32 {
    if p.is_nan() { 0.0 } else { p.clamp(0.0, 1.0) }
}

/// Reorder every node's occupied slots by decreasing `p / c` and return
/// the stats of each node's subtree (indexed like `wide.nodes`).
/// `leaf(reference, slot_box)` gives a leaf child's stats. Slot maps
/// (`slot_binary`) move with their slots; the tree stays valid.
///
/// Children are stored after their parents (as [`WideBvh::from_bvh`]
/// lays them out), so one reverse sweep sees every child first.
pub fn order_for_occlusion<const W: usize>(
    wide: &mut WideBvh<W>,
    leaf: impl Fn(u32, &Aabb) -> OcclusionStats + Sync,
) -> Vec<OcclusionStats> {
    let len = wide.nodes.len();
    order_for_occlusion_from(
        wide,
        leaf,
        PARALLEL_ORDER_NODES,
        (len, |_| OcclusionStats::EMPTY),
    )
}

/// [`order_for_occlusion`] for a tree whose nodes from `fixed_from` on are
/// already in order and whose subtree stats `fixed(n)` gives: those nodes
/// are left as they are (the re-braided top level's grafted copies of
/// object nodes, which the objects' own builds ordered).
pub fn order_for_occlusion_except<const W: usize>(
    wide: &mut WideBvh<W>,
    leaf: impl Fn(u32, &Aabb) -> OcclusionStats + Sync,
    fixed_from: usize,
    fixed: impl Fn(usize) -> OcclusionStats + Sync,
) -> Vec<OcclusionStats> {
    order_for_occlusion_from(wide, leaf, PARALLEL_ORDER_NODES, (fixed_from, fixed))
}

/// [`order_for_occlusion_except`], by levels in parallel from
/// `parallel_nodes` nodes on (the tests compare both ways on one tree).
fn order_for_occlusion_from<const W: usize>(
    wide: &mut WideBvh<W>,
    leaf: impl Fn(u32, &Aabb) -> OcclusionStats + Sync,
    parallel_nodes: usize,
    (fixed_from, fixed): (usize, impl Fn(usize) -> OcclusionStats + Sync),
) -> Vec<OcclusionStats> {
    let len = wide.nodes.len();
    let mut stats = vec![OcclusionStats::EMPTY; len];
    for (n, st) in stats.iter_mut().enumerate().skip(fixed_from) {
        *st = fixed(n);
    }
    let len = len.min(fixed_from);
    if len < parallel_nodes {
        for n in (0..len).rev() {
            let (st, order) = order_node(&wide.nodes[n], n, &stats, &leaf);
            stats[n] = st;
            if let Some(order) = order {
                reorder_slots(wide, n, &order);
            }
        }
        return stats;
    }
    // Large trees (a re-braided top level: tens of thousands of nodes for
    // the library scene at 3M triangles) level by level from the deepest, the
    // nodes of a level in parallel: each node needs only its children's
    // stats, from deeper levels. Same answers as the sweep above.
    // (Fixed nodes get depths too, as children, but are not ordered.)
    let mut depth = vec![0u32; wide.nodes.len()];
    for n in 0..len {
        for &c in &wide.nodes[n].child {
            if c != WIDE_EMPTY && !is_leaf_ref(c) {
                depth[c as usize] = depth[n] + 1;
            }
        }
    }
    let depth = &depth[..len];
    let levels = depth.iter().max().map_or(0, |&d| d as usize + 1);
    // Nodes by level (a counting sort, each level in index order).
    let mut start = vec![0usize; levels + 1];
    for &d in depth {
        start[d as usize + 1] += 1;
    }
    for l in 0..levels {
        start[l + 1] += start[l];
    }
    let mut by_level = vec![0u32; len];
    let mut at = start.clone();
    for (n, &d) in depth.iter().enumerate() {
        by_level[at[d as usize]] = n as u32;
        at[d as usize] += 1;
    }
    let mut results = Vec::new();
    for l in (0..levels).rev() {
        let level = &by_level[start[l]..start[l + 1]];
        let nodes = &wide.nodes;
        let done = &stats;
        level
            .par_iter()
            .with_min_len(256)
            .map(|&n| order_node(&nodes[n as usize], n as usize, done, &leaf))
            .collect_into_vec(&mut results);
        for (&n, &(st, order)) in level.iter().zip(&results) {
            stats[n as usize] = st;
            if let Some(order) = order {
                reorder_slots(wide, n as usize, &order);
            }
        }
    }
    stats
}

/// Nodes from which [`order_for_occlusion`] goes level by level in
/// parallel (object BVHs are ordered one per thread, and most are smaller).
const PARALLEL_ORDER_NODES: usize = 8192;

/// The stats of node `n`'s subtree, given its inner children's in `stats`,
/// and the order of its occupied slots by decreasing `p / c` when that is
/// not the order they are in (`order[i]`: the slot that goes to slot `i`).
#[inline]
fn order_node<const W: usize>(
    node: &WideNode<W>,
    n: usize,
    stats: &[OcclusionStats],
    leaf: &impl Fn(u32, &Aabb) -> OcclusionStats,
) -> (OcclusionStats, Option<[u8; W]>) {
    // Every slot's half area and the union's, lane by lane (empty slots
    // are inverted boxes: area 0, and neutral in the union).
    let extent = |lo: &[f32; W], hi: &[f32; W]| -> [f32; W] {
        std::array::from_fn(|i| (hi[i] - lo[i]).max(0.0))
    };
    let (ex, ey, ez) = (
        extent(&node.min_x, &node.max_x),
        extent(&node.min_y, &node.max_y),
        extent(&node.min_z, &node.max_z),
    );
    let areas: [f32; W] = std::array::from_fn(|i| ex[i] * ey[i] + ey[i] * ez[i] + ez[i] * ex[i]);
    let span = |lo: &[f32; W], hi: &[f32; W]| {
        let l = lo.iter().fold(f32::INFINITY, |a, &b| a.min(b));
        let h = hi.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        (h - l).max(0.0)
    };
    let (ux, uy, uz) = (
        span(&node.min_x, &node.max_x),
        span(&node.min_y, &node.max_y),
        span(&node.min_z, &node.max_z),
    );
    let parent_area = ux * uy + uy * uz + uz * ux;
    // (key, stats, original slot) of each occupied slot, insertion-
    // sorted by decreasing key (stable: equal keys keep the collapse's
    // order).
    let mut kids = [(0.0f32, OcclusionStats::EMPTY, 0usize); W];
    let mut count = 0;
    for i in 0..W {
        let r = node.child[i];
        if r == WIDE_EMPTY {
            break;
        }
        let st = if is_leaf_ref(r) {
            leaf(r, &node.child_bounds(i))
        } else {
            debug_assert!(r as usize > n, "children follow their parent");
            stats[r as usize]
        };
        let item = (sanitize_key(st.key()), st, i);
        let mut j = count;
        while j > 0 && kids[j - 1].0 < item.0 {
            kids[j] = kids[j - 1];
            j -= 1;
        }
        kids[j] = item;
        count += 1;
    }
    let kids = &kids[..count];
    let inv_parent = if parent_area > 0.0 {
        1.0 / parent_area
    } else {
        f32::INFINITY
    };
    let (mut miss, mut cost) = (1.0f32, NODE_COST);
    for &(_, st, i) in kids {
        // Probability of entering the child given the parent (SAH).
        let q = if parent_area > 0.0 {
            sanitize(areas[i] * inv_parent)
        } else {
            1.0
        };
        cost += miss * q * st.cost;
        miss *= 1.0 - q * st.hit_probability;
    }
    let st = OcclusionStats {
        hit_probability: 1.0 - miss,
        cost,
    };
    if kids.iter().enumerate().all(|(i, k)| k.2 == i) {
        return (st, None);
    }
    let mut order = [0u8; W];
    for (i, k) in kids.iter().enumerate() {
        order[i] = k.2 as u8;
    }
    (st, Some(order))
}

/// Move node `n`'s slots (boxes, references and slot maps) so that slot
/// `i` holds what slot `order[i]` held, for its occupied slots.
fn reorder_slots<const W: usize>(wide: &mut WideBvh<W>, n: usize, order: &[u8; W]) {
    let old = wide.nodes[n];
    let old_slots = wide.slot_binary[n];
    for (i, &from) in order[..old.child_count()].iter().enumerate() {
        let from = from as usize;
        wide.nodes[n].set_child(i, &old.child_bounds(from), old.child[from]);
        wide.slot_binary[n][i] = old_slots[from];
    }
}

#[inline]
fn sanitize_key(k: f32) -> f32 {
    if k.is_nan() { f32::NEG_INFINITY } else { k }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::wide::{WideNode, encode_leaf};
    use glam::Vec3;

    /// A root over three leaves: a sparse cloud in a large box, a dense wall
    /// in a small one, and an empty-looking leaf; `p` per leaf by its ref.
    fn tree() -> (WideBvh<8>, [Aabb; 3]) {
        let boxes = [
            Aabb::new(Vec3::ZERO, Vec3::splat(4.0)),
            Aabb::new(Vec3::new(5.0, 0.0, 0.0), Vec3::new(5.1, 1.0, 1.0)),
            Aabb::new(Vec3::new(0.0, 5.0, 0.0), Vec3::new(1.0, 6.0, 1.0)),
        ];
        let mut root = WideNode::<8>::EMPTY;
        for (i, b) in boxes.iter().enumerate() {
            root.set_child(i, b, encode_leaf(i as u32, 1));
        }
        let wide = WideBvh {
            nodes: vec![root],
            binary_of: vec![0],
            slot_binary: vec![[10, 11, 12, u32::MAX, u32::MAX, u32::MAX, u32::MAX, u32::MAX]],
            root_bounds: boxes.iter().fold(Aabb::EMPTY, |a, b| a.union(*b)),
            prim_count: 3,
        };
        (wide, boxes)
    }

    fn leaf_stats(r: u32) -> OcclusionStats {
        let (first, _) = crate::bvh::wide::decode_leaf(r);
        // sparse: rarely hit, two blocks; wall: nearly always, one block;
        // third: never.
        let (p, c) = [(0.1, 2.0), (0.9, 1.0), (0.0, 1.0)][first as usize];
        OcclusionStats::leaf([p], c)
    }

    #[test]
    fn children_go_by_decreasing_hit_probability_per_cost() {
        let (mut wide, boxes) = tree();
        let stats = order_for_occlusion(&mut wide, |r, _| leaf_stats(r));
        let node = &wide.nodes[0];
        // Keys 0.9, 0.05, 0.0: wall, cloud, empty.
        assert_eq!(
            &node.child[..3],
            &[encode_leaf(1, 1), encode_leaf(0, 1), encode_leaf(2, 1)]
        );
        assert_eq!(&wide.slot_binary[0][..3], &[11, 10, 12]);
        assert_eq!(node.child_bounds(0), boxes[1]);
        assert_eq!(node.child_bounds(1), boxes[0]);
        assert_eq!(node.child_bounds(2), boxes[2]);
        // The formulas, in that order.
        let parent = wide.root_bounds.half_area();
        let q: Vec<f32> = [1, 0, 2]
            .iter()
            .map(|&i| boxes[i].half_area() / parent)
            .collect();
        let (p, c) = ([0.9f32, 0.1, 0.0], [1.0f32, 2.0, 1.0]);
        let cost = NODE_COST
            + q[0] * c[0]
            + (1.0 - q[0] * p[0]) * q[1] * c[1]
            + (1.0 - q[0] * p[0]) * (1.0 - q[1] * p[1]) * q[2] * c[2];
        let miss = (1.0 - q[0] * p[0]) * (1.0 - q[1] * p[1]) * (1.0 - q[2] * p[2]);
        assert!((stats[0].cost - cost).abs() < 1e-5, "{stats:?} vs {cost}");
        assert!((stats[0].hit_probability - (1.0 - miss)).abs() < 1e-6);
        // A second pass changes nothing (the order is a fixed point).
        let before = wide.clone();
        assert_eq!(order_for_occlusion(&mut wide, |r, _| leaf_stats(r)), stats);
        assert_eq!(wide, before);
    }

    #[test]
    fn by_levels_in_parallel_as_in_one_sweep() {
        use crate::bvh::build::{BuildParams, build_bvh};
        let mut rng = 0x9e37_79b9_u32;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 17;
            rng ^= rng << 5;
            rng as f32 / u32::MAX as f32
        };
        let boxes: Vec<Aabb> = (0..4000)
            .map(|_| {
                let c = Vec3::new(next(), next(), next()) * 100.0;
                Aabb::new(c, c + Vec3::new(next(), next(), next()) * 3.0)
            })
            .collect();
        let centroids: Vec<Vec3> = boxes.iter().map(|b| b.center()).collect();
        let params = BuildParams {
            max_leaf_size: 2,
            ..BuildParams::default()
        };
        let bvh = build_bvh(&boxes, &centroids, &params).unwrap();
        let wide = WideBvh::<8>::from_bvh(&bvh).unwrap();
        assert!(wide.nodes.len() > 100, "{} nodes", wide.nodes.len());
        // Leaf stats that depend on the leaf and its box.
        let leaf = |r: u32, b: &Aabb| {
            let (first, count) = crate::bvh::wide::decode_leaf(r);
            OcclusionStats::leaf(
                [(first % 7) as f32 / 7.0],
                count as f32 + b.half_area() * 0.01,
            )
        };
        let (mut one, mut levels) = (wide.clone(), wide.clone());
        let none = (usize::MAX, |_| OcclusionStats::EMPTY);
        let a = order_for_occlusion_from(&mut one, leaf, usize::MAX, none);
        let b = order_for_occlusion_from(&mut levels, leaf, 0, none);
        assert_ne!(one, wide, "some slots move");
        assert_eq!(a, b);
        assert_eq!(one, levels);
        assert!(a[0].cost > 1.0);
        // Nodes from `k` on fixed (given their stats, left in place):
        // with the stats and order the full pass gave them, the rest comes
        // out as the full pass left it too, both ways; the fixed nodes of
        // the unordered tree stay unordered.
        let k = wide.nodes.len() / 2;
        for parallel in [usize::MAX, 0] {
            let mut t = wide.clone();
            for n in k..t.nodes.len() {
                t.nodes[n] = one.nodes[n];
                t.slot_binary[n] = one.slot_binary[n];
            }
            let st = order_for_occlusion_from(&mut t, leaf, parallel, (k, |n| a[n]));
            assert_eq!(st, a);
            assert_eq!(t, one);
            let mut u = wide.clone();
            order_for_occlusion_from(&mut u, leaf, parallel, (k, |n| a[n]));
            assert_eq!(u.nodes[k..], wide.nodes[k..]);
        }
    }

    #[test]
    fn equal_keys_keep_their_order_and_odd_inputs_stay_in_range() {
        let (mut wide, _) = tree();
        let before = wide.clone();
        order_for_occlusion(&mut wide, |_, _| OcclusionStats::leaf([0.5], 1.0));
        assert_eq!(wide, before);
        let odd = OcclusionStats::leaf([f32::NAN, 2.0, -1.0], 0.0);
        assert_eq!(odd.hit_probability, 1.0);
        assert!(odd.cost > 0.0);
        assert_eq!(triangle_miss_probability(1.0, f32::INFINITY), 0.0);
        assert_eq!(triangle_miss_probability(0.0, f32::INFINITY), 1.0);
        assert_eq!(triangle_miss_probability(1.0, 0.25), 0.75);
        assert_eq!(triangle_miss_probability(8.0, 0.25), 0.0);
        assert_eq!(triangle_miss_probability(f32::NAN, 0.25), 1.0);
    }
}
