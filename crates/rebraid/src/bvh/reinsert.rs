//! Reinsertion: a built binary BVH improved by moving subtrees to where
//! they cost less.
//!
//! J. Bittner, M. Hapala, V. Havran, "Fast Insertion-Based Optimization of
//! Bounding Volume Hierarchies", Computer Graphics Forum 2013, and its
//! parallel form, D. Meister, J. Bittner, "Parallel Reinsertion for Bounding
//! Volume Hierarchy Optimization", Computer Graphics Forum 2018 (as
//! madmann91's `bvh` v2 and obvhs ship it). A pass takes the nodes of
//! largest area (the ones rays reach most often and whose placement matters
//! most), finds for each the sibling whose new parent would lower the summed
//! area of the inner nodes the most (a branch-and-bound search from the
//! node's old place up to the root), and applies the best moves that touch
//! disjoint nodes. Leaves keep their primitives and the node count stays
//! the same, so the SAH's leaf term is unchanged and the summed inner area
//! is the SAH cost the pass lowers.
//!
//! The searches run in parallel over a frozen tree and the moves are applied
//! in a fixed order (gain, then node index), so the result does not depend
//! on the thread count. A move whose target has meanwhile come to lie inside
//! the moved subtree is skipped (the conflict rule alone does not exclude
//! it), and a tree that came out deeper than [`MAX_DEPTH`] is given back
//! unchanged.

use rayon::prelude::*;

use super::refit::{refit_inner, refit_node};
use super::{Bvh, BvhNode, MAX_DEPTH, compact_slots};
use crate::Error;

/// How much reinsertion to do after a build: `passes` passes, each
/// searching a new place for the `batch_ratio` share of the tree's nodes
/// with the largest boxes, but at most `max_batch` of them (a pass that
/// moves nothing ends the optimisation).
///
/// The search costs some 0.3 us per node searched on this project's
/// machine (a walk to the root and a pruned descent at each ancestor; about
/// 20 nodes visited per search on the shared scenes' top levels, more in
/// deeper trees), so the cost is about `0.3 us * passes * min(batch_ratio
/// * nodes, max_batch)`, spread over the build's threads.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReinsertParams {
    /// Nodes searched per pass, as a share of the tree's nodes (0 ..= 1).
    pub batch_ratio: f32,
    /// Passes; each searches from the tree the previous one left.
    pub passes: u32,
    /// At most this many nodes searched per pass (0: no limit).
    pub max_batch: u32,
}

impl ReinsertParams {
    /// No reinsertion.
    pub const OFF: Self = Self {
        batch_ratio: 0.0,
        passes: 0,
        max_batch: 0,
    };

    /// `passes` passes over the `batch_ratio` share of the nodes, unlimited.
    pub const fn share(batch_ratio: f32, passes: u32) -> Self {
        Self {
            batch_ratio,
            passes,
            max_batch: 0,
        }
    }

    pub fn is_off(&self) -> bool {
        self.passes == 0 || self.batch_ratio <= 0.0
    }

    pub fn check(&self) -> Result<(), Error> {
        if !(0.0..=1.0).contains(&self.batch_ratio) {
            return Err(Error::InvalidParameter(format!(
                "reinsertion batch ratio must be in 0..=1, got {}",
                self.batch_ratio
            )));
        }
        if self.passes > 64 {
            return Err(Error::InvalidParameter(format!(
                "reinsertion passes must be at most 64, got {}",
                self.passes
            )));
        }
        Ok(())
    }
}

#[derive(Clone, Copy, Debug)]
struct Move {
    from: u32,
    to: u32,
    gain: f32,
}

/// A node's box as the search reads it: two SSE registers on x86-64,
/// `Aabb` elsewhere.
#[cfg(target_arch = "x86_64")]
mod search_box {
    use std::arch::x86_64::*;

    use super::BvhNode;

    #[derive(Clone, Copy)]
    pub struct SearchBox(__m128, __m128);

    impl SearchBox {
        #[inline(always)]
        pub fn of(n: &BvhNode) -> Self {
            // SAFETY: `BvhNode` is `repr(C)`, 32 bytes: `min` (12 bytes),
            // `index`, `max` (12 bytes), `count`, so both unaligned 16-byte
            // loads stay inside it; SSE2 is part of x86-64. The fourth lanes
            // (the index and count bits) are zeroed so that no denormal or
            // NaN enters the arithmetic.
            unsafe {
                let p = (n as *const BvhNode).cast::<f32>();
                let keep = _mm_castsi128_ps(_mm_set_epi32(0, -1, -1, -1));
                Self(
                    _mm_and_ps(_mm_loadu_ps(p), keep),
                    _mm_and_ps(_mm_loadu_ps(p.add(4)), keep),
                )
            }
        }

        #[inline(always)]
        pub fn union(self, o: Self) -> Self {
            // SAFETY: SSE2 is part of x86-64.
            unsafe { Self(_mm_min_ps(self.0, o.0), _mm_max_ps(self.1, o.1)) }
        }

        /// `e.x * e.y + e.y * e.z + e.z * e.x`, summed in that order (as
        /// `Aabb::half_area`).
        #[inline(always)]
        pub fn half_area(self) -> f32 {
            // SAFETY: SSE2 is part of x86-64.
            unsafe {
                let e = _mm_sub_ps(self.1, self.0);
                // (y, z, x, w)
                let r = _mm_shuffle_ps::<0b11_00_10_01>(e, e);
                let p = _mm_mul_ps(e, r);
                let p1 = _mm_shuffle_ps::<0b01_01_01_01>(p, p);
                let p2 = _mm_shuffle_ps::<0b10_10_10_10>(p, p);
                _mm_cvtss_f32(_mm_add_ss(_mm_add_ss(p, p1), p2))
            }
        }

        /// The half areas of `self` joined with `a`, with `b`, and of `a`
        /// and `b` alone, in one pass over four boxes: bit for bit what
        /// [`SearchBox::half_area`] gives for each (the same products,
        /// summed in the same order, lane by lane after a transpose).
        #[inline(always)]
        pub fn pair_areas(self, a: Self, b: Self) -> [f32; 4] {
            // SAFETY: SSE2 is part of x86-64.
            unsafe {
                let mut e0 = _mm_sub_ps(_mm_max_ps(self.1, a.1), _mm_min_ps(self.0, a.0));
                let mut e1 = _mm_sub_ps(_mm_max_ps(self.1, b.1), _mm_min_ps(self.0, b.0));
                let mut e2 = _mm_sub_ps(a.1, a.0);
                let mut e3 = _mm_sub_ps(b.1, b.0);
                // Rows become columns: x, y, z (and the zeroed fourth
                // lane) of the four boxes.
                _MM_TRANSPOSE4_PS(&mut e0, &mut e1, &mut e2, &mut e3);
                let (x, y, z) = (e0, e1, e2);
                let s = _mm_add_ps(
                    _mm_add_ps(_mm_mul_ps(x, y), _mm_mul_ps(y, z)),
                    _mm_mul_ps(z, x),
                );
                let mut out = [0.0f32; 4];
                _mm_storeu_ps(out.as_mut_ptr(), s);
                out
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod search_box {
    use super::BvhNode;
    use crate::Aabb;

    #[derive(Clone, Copy)]
    pub struct SearchBox(Aabb);

    impl SearchBox {
        #[inline(always)]
        pub fn of(n: &BvhNode) -> Self {
            Self(n.bounds())
        }

        #[inline(always)]
        pub fn union(self, o: Self) -> Self {
            Self(self.0.union(o.0))
        }

        #[inline(always)]
        pub fn half_area(self) -> f32 {
            self.0.half_area()
        }

        #[inline(always)]
        pub fn pair_areas(self, a: Self, b: Self) -> [f32; 4] {
            [
                self.union(a).half_area(),
                self.union(b).half_area(),
                a.half_area(),
                b.half_area(),
            ]
        }
    }
}

use search_box::SearchBox;

#[inline(always)]
fn sibling(i: u32) -> u32 {
    // Children pairs start at odd indices (the root is 0, pairs follow it).
    if i % 2 == 1 { i + 1 } else { i - 1 }
}

/// What a move overwrote, to undo it.
#[derive(Clone, Copy)]
struct Undo {
    slots: [(u32, BvhNode); 3],
    parents: [(u32, u32); 6],
}

/// The tree being improved, in place, with each node's parent.
struct Tree<'a> {
    nodes: &'a mut [BvhNode],
    parents: Vec<u32>,
}

impl<'a> Tree<'a> {
    fn new(nodes: &'a mut [BvhNode]) -> Self {
        let mut parents = vec![0u32; nodes.len()];
        for (i, node) in nodes.iter().enumerate() {
            if !node.is_leaf() {
                parents[node.index as usize] = i as u32;
                parents[node.index as usize + 1] = i as u32;
            }
        }
        Self { nodes, parents }
    }

    #[inline(always)]
    fn area(&self, i: u32) -> f32 {
        SearchBox::of(&self.nodes[i as usize]).half_area()
    }

    #[inline(always)]
    fn parent(&self, i: u32) -> u32 {
        self.parents[i as usize]
    }

    /// Whether `i` lies in the subtree of `root`.
    fn is_inside(&self, mut i: u32, root: u32) -> bool {
        loop {
            if i == root {
                return true;
            }
            if i == 0 {
                return false;
            }
            i = self.parent(i);
        }
    }

    fn depth(&self) -> u32 {
        let mut max = 0;
        let mut stack = vec![(0u32, 1u32)];
        while let Some((i, d)) = stack.pop() {
            max = max.max(d);
            let n = &self.nodes[i as usize];
            if !n.is_leaf() {
                stack.push((n.index, d + 1));
                stack.push((n.index + 1, d + 1));
            }
        }
        max
    }

    /// The best place for node `from` (never the root): the node `to` that
    /// should become its sibling, and the summed inner area that saves
    /// (`None` when no move saves anything).
    ///
    /// Removing `from` deletes its parent and shrinks the ancestors above
    /// it; placing it beside `to` makes a parent of both and grows every
    /// ancestor of `to` that does not yet contain it. The search walks up
    /// from the old place; at each ancestor it descends into the other
    /// side, pricing each candidate as the saving so far minus the new
    /// parent's area, and prunes a subtree once even a parent of `from`'s
    /// area alone could not beat the best (at the push as well as the pop:
    /// half the visits on nexuiz's top level).
    fn find_move(&self, from: u32, stack: &mut Vec<(f32, u32)>) -> Option<Move> {
        let nodes = &*self.nodes;
        let bounds = SearchBox::of(&nodes[from as usize]);
        let area = bounds.half_area();
        let parent = self.parent(from);
        let mut best = Move {
            from,
            to: 0,
            gain: 0.0,
        };
        // Saving before any growth: the removed parent's area.
        let mut saved = self.area(parent);
        let mut side = sibling(from);
        let mut pivot = parent;
        // Bounds of what stays under `pivot` once `from` is gone.
        let mut kept = SearchBox::of(&nodes[side as usize]);
        loop {
            // `side` itself, then the children pairs below it: a stack
            // entry is a pair (its first child's index) with the saving
            // that holds above both, so that one step prices two siblings
            // (`SearchBox::pair_areas`: four areas in one set of vector
            // operations) and the stack is popped half as often.
            stack.clear();
            if saved - area > best.gain {
                let dst = &nodes[side as usize];
                let dst_box = SearchBox::of(dst);
                let gain = saved - bounds.union(dst_box).half_area();
                if gain > best.gain {
                    best.to = side;
                    best.gain = gain;
                }
                if !dst.is_leaf() {
                    // Below `dst`, `dst` itself grows to contain `from`; a
                    // new parent there has at least `from`'s area.
                    let below = gain + dst_box.half_area();
                    if below - area > best.gain {
                        stack.push((below, dst.index));
                    }
                }
            }
            while let Some((gain_here, first)) = stack.pop() {
                if gain_here - area <= best.gain {
                    continue;
                }
                let (l, r) = (&nodes[first as usize], &nodes[first as usize + 1]);
                let (l_box, r_box) = (SearchBox::of(l), SearchBox::of(r));
                let [l_joined, r_joined, l_area, r_area] = bounds.pair_areas(l_box, r_box);
                let (l_gain, r_gain) = (gain_here - l_joined, gain_here - r_joined);
                // The right child first, as the stack of single nodes
                // popped them (a tie keeps the first found).
                if r_gain > best.gain {
                    best.to = first + 1;
                    best.gain = r_gain;
                }
                if l_gain > best.gain {
                    best.to = first;
                    best.gain = l_gain;
                }
                for (n, gain, own) in [(l, l_gain, l_area), (r, r_gain, r_area)] {
                    if !n.is_leaf() {
                        let below = gain + own;
                        if below - area > best.gain {
                            stack.push((below, n.index));
                        }
                    }
                }
            }
            if pivot != parent {
                // `pivot` no longer contains `from`: it shrinks to `kept`.
                kept = kept.union(SearchBox::of(&nodes[side as usize]));
                saved += self.area(pivot) - kept.half_area();
            }
            if pivot == 0 {
                break;
            }
            side = sibling(pivot);
            pivot = self.parent(pivot);
        }
        let useless = best.gain <= 0.0 || best.to == sibling(from) || best.to == parent;
        (!useless).then_some(best)
    }

    /// Make `to` the sibling of `from`: `from`'s old sibling takes its
    /// parent's slot, `to`'s content moves into the old sibling's slot, and
    /// `to` becomes the parent of the pair (`from`, old `to`). Boxes are
    /// refitted up from both places. Returns what it overwrote.
    fn apply_move(&mut self, from: u32, to: u32) -> Undo {
        let side = sibling(from);
        let parent = self.parent(from);
        let side_node = self.nodes[side as usize];
        let to_node = self.nodes[to as usize];
        let parent_node = self.nodes[parent as usize];
        let child_of = |n: &BvhNode| if n.is_leaf() { None } else { Some(n.index) };
        let (sc, tc) = (child_of(&side_node), child_of(&to_node));
        self.nodes[parent as usize] = side_node;
        self.nodes[side as usize] = to_node;
        self.nodes[to as usize] = BvhNode::inner(to_node.bounds(), from.min(side));
        // `from` and its old sibling hang below `to`; the moved contents'
        // children follow them. Unused entries repeat the first (undone
        // last, it restores `from`'s parent either way).
        let mut changes = [(from, to); 6];
        changes[1] = (side, to);
        let mut k = 2;
        for (slot, c) in [(parent, sc), (side, tc)] {
            if let Some(c) = c {
                changes[k] = (c, slot);
                changes[k + 1] = (c + 1, slot);
                k += 2;
            }
        }
        let mut undo = Undo {
            slots: [(parent, parent_node), (side, side_node), (to, to_node)],
            parents: [(from, self.parent(from)); 6],
        };
        for (e, &(i, p)) in undo.parents.iter_mut().zip(&changes[..k]) {
            *e = (i, self.parents[i as usize]);
            self.parents[i as usize] = p;
        }
        self.refit_up(to);
        self.refit_up(parent);
        undo
    }

    fn refit_up(&mut self, mut i: u32) {
        loop {
            refit_node(self.nodes, i as usize);
            if i == 0 {
                break;
            }
            i = self.parent(i);
        }
    }

    /// Undo moves, last first, then refit every box bottom-up (the
    /// restored layout has children after their parents).
    fn undo(&mut self, log: &[Undo]) {
        for u in log.iter().rev() {
            for &(i, p) in u.parents.iter().rev() {
                self.parents[i as usize] = p;
            }
            for &(i, n) in u.slots.iter().rev() {
                self.nodes[i as usize] = n;
            }
        }
        refit_inner(self.nodes);
    }
}

/// Improve `nodes` (a binary tree in this crate's sibling-pair layout, root
/// at 0, children after their parents, each inner box the union of its
/// children's) by reinsertion, in place. The node array keeps its length;
/// the layout is no longer depth-first (see [`reorder_depth_first`]).
/// Returns whether the tree changed.
pub fn reinsert(nodes: &mut [BvhNode], params: &ReinsertParams) -> bool {
    if params.is_off() || nodes.len() < 5 {
        return false;
    }
    let n = nodes.len();
    let mut tree = Tree::new(nodes);
    let mut order: Vec<u32> = Vec::new();
    let mut keys: Vec<u64> = Vec::new();
    let mut touched = vec![false; n];
    let mut log: Vec<Undo> = Vec::new();
    let batch = ((n - 1) as f32 * params.batch_ratio.min(1.0)) as usize;
    let mut batch = batch.clamp(1, n - 1);
    if params.max_batch > 0 {
        batch = batch.min(params.max_batch as usize);
    }
    for _ in 0..params.passes {
        // The `batch` largest nodes (ties by index, for determinism): keys
        // `(!area bits, index)`, smallest first (areas are non-negative, so
        // their bits order as they do).
        keys.clear();
        keys.extend(
            (1..n as u32).map(|i| (u64::from(!tree.area(i).to_bits()) << 32) | u64::from(i)),
        );
        if batch < keys.len() {
            keys.select_nth_unstable(batch);
        }
        order.clear();
        order.extend(keys[..batch].iter().map(|&k| k as u32));
        let frozen = &tree;
        let mut moves: Vec<Move> = order
            .par_iter()
            .with_min_len(64)
            .map_init(Vec::new, |stack, &i| frozen.find_move(i, stack))
            .flatten_iter()
            .collect();
        moves.sort_unstable_by(|a, b| b.gain.total_cmp(&a.gain).then(a.from.cmp(&b.from)));
        touched.fill(false);
        let before = log.len();
        for m in &moves {
            let from_parent = tree.parent(m.from);
            let conflicts = [
                m.from,
                sibling(m.from),
                from_parent,
                m.to,
                if m.to == 0 { 0 } else { tree.parent(m.to) },
            ];
            let stale =
                m.to == sibling(m.from) || m.to == from_parent || tree.is_inside(m.to, m.from);
            if stale || conflicts.iter().any(|&c| touched[c as usize]) {
                continue;
            }
            for c in conflicts {
                touched[c as usize] = true;
            }
            log.push(tree.apply_move(m.from, m.to));
        }
        if log.len() == before {
            break;
        }
    }
    if log.is_empty() {
        return false;
    }
    if tree.depth() > MAX_DEPTH {
        tree.undo(&log);
        return false;
    }
    true
}

impl Bvh {
    /// [`reinsert`] this tree, then lay it out depth-first again with its
    /// primitive indices in the new leaf order. Returns whether it changed.
    pub fn reinsert(&mut self, params: &ReinsertParams) -> bool {
        if !reinsert(&mut self.nodes, params) {
            return false;
        }
        let map = reorder_depth_first(&mut self.nodes);
        self.prim_indices = map.iter().map(|&k| self.prim_indices[k as usize]).collect();
        true
    }
}

/// Lay `nodes` out in depth-first pair order again (as the builders lay
/// trees out, `compact_slots`), and the leaves' ranges in that order:
/// returns, for each new primitive position, the old one (`new[k] =
/// old[map[k]]`).
pub fn reorder_depth_first(nodes: &mut Vec<BvhNode>) -> Vec<u32> {
    let old = std::mem::take(nodes);
    let mut map = Vec::new();
    compact_slots(&old, nodes, |leaf| {
        let first = map.len() as u32;
        map.extend(leaf.prim_range().map(|p| p as u32));
        leaf.index = first;
    });
    map
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;
    use crate::Aabb;
    use crate::bvh::test_trees::{build_over as build, scattered_boxes as boxes};

    /// The search's box arithmetic (SSE on x86-64) gives `Aabb`'s half
    /// areas bit for bit, one box at a time and four at once
    /// (`pair_areas`), so that reinsertion finds the moves the plain
    /// arithmetic would: flat and point boxes, negative and large
    /// coordinates included.
    #[test]
    fn search_box_areas_match_aabb_bit_for_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(47);
        let random_box = |rng: &mut rand_pcg::Pcg64| {
            let scale = [1e-3f32, 1.0, 1e4][rng.gen_range(0..3)];
            let mut v = || rng.gen_range(-scale..scale);
            let a = glam::Vec3::new(v(), v(), v());
            let mut b = glam::Vec3::new(v(), v(), v());
            if rng.gen_range(0..5) == 0 {
                b.y = a.y; // flat
            }
            Aabb::new(a.min(b), a.max(b))
        };
        for _ in 0..20_000 {
            let (o, a, b) = (
                random_box(&mut rng),
                random_box(&mut rng),
                random_box(&mut rng),
            );
            let of = |x: &Aabb| SearchBox::of(&BvhNode::leaf(*x, 7, 3));
            let got = of(&o).pair_areas(of(&a), of(&b)).map(f32::to_bits);
            let want = [
                o.union(a).half_area(),
                o.union(b).half_area(),
                a.half_area(),
                b.half_area(),
            ]
            .map(f32::to_bits);
            assert_eq!(got, want, "{o:?} {a:?} {b:?}");
            assert_eq!(of(&a).half_area().to_bits(), want[2]);
            assert_eq!(of(&o).union(of(&a)).half_area().to_bits(), want[0]);
        }
    }

    fn inner_area(bvh: &Bvh) -> f64 {
        bvh.nodes
            .iter()
            .filter(|n| !n.is_leaf())
            .map(|n| n.bounds().half_area() as f64)
            .sum()
    }

    /// Each leaf's set of primitives, sorted (reinsertion moves leaves,
    /// never their contents).
    fn leaves(bvh: &Bvh) -> Vec<Vec<u32>> {
        let mut v: Vec<Vec<u32>> = bvh
            .nodes
            .iter()
            .filter(|n| n.is_leaf())
            .map(|n| {
                let mut p = bvh.prim_indices[n.prim_range()].to_vec();
                p.sort_unstable();
                p
            })
            .collect();
        v.sort();
        v
    }

    /// Every inner box is exactly the union of its children's, and every
    /// child comes after its parent.
    fn check_tight(bvh: &Bvh) {
        for (i, n) in bvh.nodes.iter().enumerate() {
            if !n.is_leaf() {
                let c = n.index as usize;
                assert!(c > i, "child {c} before parent {i}");
                let u = bvh.nodes[c].bounds().union(bvh.nodes[c + 1].bounds());
                assert_eq!(n.bounds(), u, "node {i} not the union of its children");
            }
        }
    }

    #[test]
    fn reinsertion_lowers_the_inner_area_and_keeps_every_leaf() {
        for (seed, max_leaf) in [(1, 1), (2, 4), (3, 8)] {
            let boxes = boxes(seed, 3000);
            let built = build(&boxes, max_leaf);
            for params in [ReinsertParams::share(0.1, 4), ReinsertParams::share(1.0, 3)] {
                let mut bvh = built.clone();
                assert!(bvh.reinsert(&params), "{seed} {params:?}: nothing moved");
                bvh.validate(&boxes).unwrap();
                check_tight(&bvh);
                assert_eq!(bvh.nodes.len(), built.nodes.len());
                assert_eq!(leaves(&bvh), leaves(&built));
                let (a, b) = (inner_area(&built), inner_area(&bvh));
                assert!(b < a * 0.995, "{seed} {params:?}: {a} -> {b}");
            }
        }
    }

    /// `max_batch` bounds the nodes searched per pass, so the moves too.
    #[test]
    fn the_batch_limit_bounds_the_moves() {
        let boxes = boxes(4, 3000);
        let built = build(&boxes, 1);
        let changed = |max_batch| {
            let mut nodes = built.nodes.clone();
            let params = ReinsertParams {
                batch_ratio: 1.0,
                passes: 3,
                max_batch,
            };
            reinsert(&mut nodes, &params);
            nodes
                .iter()
                .zip(&built.nodes)
                .filter(|(a, b)| a != b)
                .count()
        };
        // A pass searching 16 nodes makes at most 16 moves, each rewriting
        // three slots and refitting the boxes on two paths to the root.
        let (few, all) = (changed(16), changed(0));
        assert!(few > 0 && few < all, "{few} slots changed, {all} unlimited");
        assert!(few <= 3 * 16 * (3 + 2 * MAX_DEPTH as usize), "{few}");
    }

    #[test]
    fn reinsertion_does_not_depend_on_the_thread_count() {
        let boxes = boxes(7, 5000);
        let built = build(&boxes, 2);
        let params = ReinsertParams::share(0.5, 3);
        let run = |threads| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut bvh = built.clone();
            pool.install(|| bvh.reinsert(&params));
            bvh
        };
        let one = run(1);
        assert_ne!(one, built);
        assert_eq!(one, run(2));
        assert_eq!(one, run(3));
    }

    #[test]
    fn off_small_and_single_leaf_trees_are_left_alone() {
        let boxes = boxes(3, 500);
        let built = build(&boxes, 4);
        let mut bvh = built.clone();
        assert!(!bvh.reinsert(&ReinsertParams::OFF));
        assert!(!bvh.reinsert(&ReinsertParams::share(0.0, 8)));
        assert_eq!(bvh, built);
        for n in [1, 2, 3] {
            let few = build(&boxes[..n], 1);
            let mut t = few.clone();
            assert!(!t.reinsert(&ReinsertParams::share(1.0, 4)));
            assert_eq!(t, few);
        }
        let bad = ReinsertParams::share(f32::NAN, 1);
        assert!(bad.check().is_err());
        assert!(ReinsertParams::share(0.5, 65).check().is_err());
    }

    /// The undo log restores the tree bit for bit (the path taken when a
    /// tree comes out deeper than [`MAX_DEPTH`]).
    #[test]
    fn undoing_every_move_restores_the_tree() {
        let boxes = boxes(11, 2000);
        let built = build(&boxes, 2);
        let mut nodes = built.nodes.clone();
        let n = nodes.len();
        let mut tree = Tree::new(&mut nodes);
        let mut log = Vec::new();
        let mut stack = Vec::new();
        for from in 1..n as u32 {
            if let Some(m) = tree.find_move(from, &mut stack) {
                let fresh = m.to != sibling(m.from)
                    && m.to != tree.parent(m.from)
                    && !tree.is_inside(m.to, m.from);
                if fresh {
                    log.push(tree.apply_move(m.from, m.to));
                }
            }
        }
        assert!(log.len() > 10, "{} moves", log.len());
        tree.undo(&log);
        assert_eq!(nodes, built.nodes);
    }

    #[test]
    fn a_depth_first_tree_reorders_to_itself() {
        let boxes = boxes(5, 1000);
        let mut bvh = build(&boxes, 3);
        let before = bvh.clone();
        let map = reorder_depth_first(&mut bvh.nodes);
        assert_eq!(bvh, before);
        assert!(map.iter().enumerate().all(|(k, &m)| k as u32 == m));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn reinserted_trees_stay_valid(seed in 1u32.., n in 4usize..400, leaf in 1u32..6, ratio in 0.01f32..1.0, passes in 1u32..6) {
            let boxes = boxes(seed, n);
            let built = build(&boxes, leaf);
            let mut bvh = built.clone();
            bvh.reinsert(&ReinsertParams::share(ratio, passes));
            bvh.validate(&boxes).unwrap();
            check_tight(&bvh);
            // (The summed area is not checked here: a move priced on the
            // pass's frozen tree may gain less once others have moved.)
            prop_assert_eq!(leaves(&bvh), leaves(&built));
        }
    }
}
