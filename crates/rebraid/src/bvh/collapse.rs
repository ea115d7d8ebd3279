//! Which binary nodes become wide nodes: the SAH-optimal collapse.
//!
//! A wide BVH is collapsed from a binary one ([`super::WideBvh`]): each
//! binary inner node either becomes a wide node or is opened, its children
//! taking slots of the wide node above it. With the leaves given (the
//! binary build decides them), the SAH cost of the wide tree, the one
//! Embree reports for its own trees (inner nodes at cost 1, leaves at their
//! blocks), varies only with the summed surface area of the binary nodes
//! that stay: every ray that enters a kept node's box pays one node test.
//! The greedy rule (Embree's BVH8 builders; ours before session 37) opens
//! the child of largest area until a node has `W` children; it leaves
//! nodes whose children are all leaves with few slots filled, and the
//! slots it spends at the top are not the ones that save the most area.
//!
//! `CollapsePlan` minimises the summed area exactly by dynamic
//! programming over the binary tree (Ylitie, Karras, Laine, "Efficient
//! Incoherent Ray Traversal on GPUs Through Compressed Wide BVHs", HPG 2017,
//! section 3.1, without their leaf merging: our leaves stay the binary
//! build's, so that the re-braiding builder, which opens object BVHs by
//! binary node, finds every wide leaf at a binary leaf). For a binary node
//! `n` and a budget of `k` slots in its parent (1 ..= `W`):
//!
//! - `cost(leaf, k) = 0`;
//! - `keep(n) = area(n) + share(n, W)`, the node kept as a wide node in one
//!   slot, its children sharing its own `W` slots;
//! - `share(n, k) = min over 1 <= j < k of cost(left, j) + cost(right, k - j)`;
//! - `cost(n, 1) = keep(n)`, `cost(n, k) = min(keep(n), share(n, k))`.
//!
//! The root is always kept. One pass bottom-up fills a row of `W` costs
//! per node (about 30 additions and comparisons), one pass top-down reads
//! the choices back. Embree's statistic of the traversed trees
//! (`rebraid stats SCENE --modes flat,rebraided`, column `wide SAH`),
//! greedy -> optimal: flat nexuiz 16.72 -> 16.06, samurai 10.73 -> 10.22,
//! the 2CylinderEngine 34.87 -> 33.28, openarena 10.29 -> 9.95;
//! re-braided nexuiz 17.83 -> 17.13, samurai 10.71 -> 10.07, the engine
//! 35.20 -> 33.25, cocoa 6.02 -> 5.79, ravenbridge 10.53 -> 10.14,
//! openarena 10.02 -> 9.55. The optimal trees have fewer nodes (openarena's
//! flat tree 3,688 -> 2,511, empty slots 14,011 -> 5,772) and are deeper
//! (8 -> 10 levels): they mix leaves and inner nodes in one node where the
//! greedy rule gave nodes of a few leaves each.
//!
//! Wall time against the greedy rule, same binary (`--collapse greedy`;
//! `tools/ab-wall.sh 8`, one thread, 480x270, the control within 0.99-1.02;
//! docs/performance.md, session 37), re-braided mode: diffuse rays the
//! engine +6.1%, the library at 0.25 +12.6%, nexuiz +2.4%, samurai +2.5%,
//! cocoa +2.2%, openarena +1.2%, ravenbridge -1.8%; primary -4.2% (the
//! engine) to +8.5% (the library); shadow -7.2% (openarena, whose shadow
//! rays visit 4.36 -> 5.77 inner nodes at 240x135: the deeper tree puts
//! the occluders farther down) to +6.8%. Builds 0-5% slower on one thread:
//! the plan and the collapse by it took about twice the greedy collapse's
//! time (18 against 9 ms over the 376K binary nodes of the library at 1M
//! triangles as one tree). Since session 38 the rows of nodes with a leaf
//! child skip the general split (`CollapsePlan::fill`): the flat library
//! at 1M triangles collapses in 2.3 times the greedy rule's instructions
//! instead of 3.2 (callgrind), whole builds take 3-4% fewer instructions.

use super::BvhNode;
use super::node::bottom_up;

/// How [`super::WideBvh`] chooses the binary nodes that become wide nodes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Collapse {
    /// Open the inner child of largest area until the node has `W`
    /// children or only leaves remain (Embree's BVH4/BVH8 builders).
    Greedy,
    /// The choice of least summed area (`CollapsePlan`, module docs).
    #[default]
    SahOptimal,
}

/// The dynamic program's row for one binary node.
#[derive(Clone, Copy)]
struct Row<const W: usize> {
    /// `cost[k - 1]`: least summed area of the wide nodes in this subtree
    /// when it gets `k` slots of its parent.
    cost: [f32; W],
    /// `left[k - 1]` (k >= 2): the left child's share of `k` slots when
    /// the node is opened.
    left: [u8; W],
    /// Bit `k - 1`: opening beats keeping with `k` slots.
    open: u16,
}

/// The SAH-optimal collapse of one binary tree (see the module docs):
/// built once, then asked for each wide node's slots.
pub(crate) struct CollapsePlan<const W: usize> {
    rows: Vec<Row<W>>,
}

impl<const W: usize> CollapsePlan<W> {
    /// Fill the rows bottom-up ([`super::node::bottom_up`]).
    pub(crate) fn new(bin: &[BvhNode]) -> Self {
        const {
            assert!(
                W >= 2 && W <= 16,
                "slot budgets fit the u8 shares and u16 masks"
            )
        };
        let empty = Row {
            cost: [0.0; W],
            left: [0; W],
            open: 0,
        };
        let mut rows = vec![empty; bin.len()];
        for n in bottom_up(bin) {
            Self::fill(bin, &mut rows, n);
        }
        Self { rows }
    }

    /// Row `n` from its children's rows (leaves keep the empty row).
    ///
    /// A leaf child's costs are all zero, and every row's costs never rise
    /// with `k` (a slot more never hurts: by induction from the leaves, as
    /// `share` is a minimum over more splits of sums that do not rise, and
    /// float addition is monotonic). So with a leaf on the left the best
    /// split of `k` slots gives it one and the right child `k - 1`, and with
    /// a leaf on the right the left child takes the fewest slots that reach
    /// its least cost: what the general loop finds, ties included, without
    /// its 28 sums per node at width 8. At least about half the inner
    /// nodes of a binary tree have a leaf child (every leaf's parent does,
    /// and a parent has two children: `L` leaves, `L - 1` inner nodes);
    /// `CollapsePlan::new` took 10% of the 2CylinderEngine's build
    /// instructions before (callgrind).
    #[inline]
    fn fill(bin: &[BvhNode], rows: &mut [Row<W>], n: usize) {
        let node = &bin[n];
        if node.is_leaf() {
            return;
        }
        let c = node.index as usize;
        let (l, r) = (rows[c].cost, rows[c + 1].cost);
        let (share, left) = if bin[c].is_leaf() {
            Self::share_left_leaf(&r)
        } else if bin[c + 1].is_leaf() {
            Self::share_right_leaf(&l)
        } else {
            Self::share(&l, &r)
        };
        let keep = node.bounds().half_area() + share[W - 1];
        let mut row = Row {
            cost: [keep; W],
            left,
            open: 0,
        };
        for k in 2..=W {
            if share[k - 1] < keep {
                row.cost[k - 1] = share[k - 1];
                row.open |= 1 << (k - 1);
            }
        }
        rows[n] = row;
    }

    /// The least cost of `k` slots shared between children of costs `l`
    /// and `r`, and the left child's share, for every `k` in 2 ..= `W`
    /// (index `k - 1`; index 0 unused).
    #[inline]
    fn share(l: &[f32; W], r: &[f32; W]) -> ([f32; W], [u8; W]) {
        let mut share = [f32::INFINITY; W];
        let mut left = [1u8; W];
        for k in 2..=W {
            // One slot to the left child unless a sum is smaller (infinite
            // areas of huge boxes still give a valid split); selects, not
            // branches, as which split wins is data.
            let (mut best, mut arg) = (l[0] + r[k - 2], 1u8);
            for j in 2..k {
                let v = l[j - 1] + r[k - j - 1];
                let better = v < best;
                best = if better { v } else { best };
                arg = if better { j as u8 } else { arg };
            }
            share[k - 1] = best;
            left[k - 1] = arg;
        }
        (share, left)
    }

    /// [`Self::share`] with a leaf on the left (`l` all zero): one slot to
    /// it, `k - 1` to the right child, whose cost is least there.
    #[inline]
    fn share_left_leaf(r: &[f32; W]) -> ([f32; W], [u8; W]) {
        let mut share = [f32::INFINITY; W];
        share[1..].copy_from_slice(&r[..W - 1]);
        (share, [1u8; W])
    }

    /// [`Self::share`] with a leaf on the right (`r` all zero): the left
    /// child's least cost within `k - 1` slots, `l[k - 2]`, at the fewest
    /// slots that reach it (the general loop keeps the first of equal
    /// sums).
    #[inline]
    fn share_right_leaf(l: &[f32; W]) -> ([f32; W], [u8; W]) {
        let mut share = [f32::INFINITY; W];
        let mut left = [1u8; W];
        let mut first = 0;
        for k in 2..=W {
            if l[k - 2] < l[first] {
                first = k - 2;
            }
            share[k - 1] = l[first];
            left[k - 1] = first as u8 + 1;
        }
        (share, left)
    }

    /// The binary nodes that fill the slots of the wide node collapsed from
    /// inner node `b`, in the binary tree's left-to-right order, passed to
    /// `slot` one by one (at most `W`).
    #[inline]
    pub(crate) fn slots(&self, bin: &[BvhNode], b: usize, mut slot: impl FnMut(usize)) {
        // (binary node, its slot budget); the right child is pushed first
        // so that the left one's slots come first.
        let mut pending = [(0usize, 0usize); W];
        let mut len = 0;
        let open = |n: usize, k: usize, pending: &mut [(usize, usize); W], len: &mut usize| {
            let c = bin[n].index as usize;
            let j = self.rows[n].left[k - 1] as usize;
            pending[*len] = (c + 1, k - j);
            pending[*len + 1] = (c, j);
            *len += 2;
        };
        open(b, W, &mut pending, &mut len);
        while len > 0 {
            len -= 1;
            let (n, k) = pending[len];
            if bin[n].is_leaf() || self.rows[n].open & (1 << (k - 1)) == 0 {
                slot(n);
            } else {
                open(n, k, &mut pending, &mut len);
            }
        }
    }

    /// Least summed area of the wide nodes under the root, the root's own
    /// included: what the plan minimises (for tests).
    #[cfg(test)]
    pub(crate) fn root_cost(&self) -> f32 {
        self.rows[0].cost[0]
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;
    use proptest::prelude::*;

    use super::*;
    use crate::Aabb;
    use crate::bvh::test_trees::{build_over as build, scattered_boxes as boxes, two_layouts};
    use crate::bvh::wide::{decode_leaf, is_leaf_ref};
    use crate::bvh::{Bvh, WideBvh};

    /// What both rules are judged by: the summed area of the binary nodes
    /// that became wide nodes.
    fn kept_area<const W: usize>(wide: &WideBvh<W>, bin: &Bvh) -> f64 {
        wide.binary_of
            .iter()
            .map(|&b| bin.nodes[b as usize].bounds().half_area() as f64)
            .sum()
    }

    /// The binary leaves a wide tree's leaf slots name, sorted.
    fn leaf_slots<const W: usize>(wide: &WideBvh<W>) -> Vec<(u32, u32)> {
        let mut v: Vec<(u32, u32)> = wide
            .nodes
            .iter()
            .flat_map(|n| n.child)
            .filter(|&r| is_leaf_ref(r) && r != crate::bvh::wide::WIDE_EMPTY)
            .map(decode_leaf)
            .collect();
        v.sort_unstable();
        v
    }

    /// Both collapses of `bin`: valid wide trees over the same leaves, the
    /// optimal one's summed area what its plan says and never above the
    /// greedy one's.
    fn check<const W: usize>(bin: &Bvh) -> (f64, f64) {
        let greedy = WideBvh::<W>::from_bvh_with(bin, Collapse::Greedy).unwrap();
        let optimal = WideBvh::<W>::from_bvh_with(bin, Collapse::SahOptimal).unwrap();
        for w in [&greedy, &optimal] {
            w.validate_slot_maps(bin).unwrap();
            assert_eq!(leaf_slots(w), leaf_slots(&greedy));
            assert_eq!(w.binary_of.first(), Some(&0), "the root is kept");
        }
        let (g, o) = (kept_area(&greedy, bin), kept_area(&optimal, bin));
        // A leaf root becomes one wide node over it, outside the plan.
        let planned = match &bin.nodes[0] {
            root if root.is_leaf() => root.bounds().half_area() as f64,
            _ => CollapsePlan::<W>::new(&bin.nodes).root_cost() as f64,
        };
        assert!(
            (o - planned).abs() <= 1e-4 * planned,
            "{o} against the plan's {planned}"
        );
        assert!(o <= g * (1.0 + 1e-6), "optimal {o} above greedy {g}");
        (g, o)
    }

    /// The least summed area over every set of inner nodes to keep (the
    /// root always) whose nodes each fill at most `w` slots: exhaustive, for
    /// trees of a few inner nodes.
    fn brute_force_optimum(bin: &Bvh, w: usize) -> f64 {
        let inner: Vec<usize> = (0..bin.nodes.len())
            .filter(|&n| !bin.nodes[n].is_leaf())
            .collect();
        assert!(inner.len() <= 16);
        let slots = |kept: &dyn Fn(usize) -> bool, n: usize| {
            // Slots a kept node's box holds: its descendants down to kept
            // nodes and leaves.
            let mut count = 0;
            let c = bin.nodes[n].index as usize;
            let mut stack = vec![c, c + 1];
            while let Some(k) = stack.pop() {
                if bin.nodes[k].is_leaf() || kept(k) {
                    count += 1;
                } else {
                    let c = bin.nodes[k].index as usize;
                    stack.extend([c, c + 1]);
                }
            }
            count
        };
        let mut best = f64::INFINITY;
        for mask in 0u32..1 << inner.len() {
            let kept = |n: usize| {
                n == 0
                    || inner
                        .iter()
                        .position(|&i| i == n)
                        .is_some_and(|p| mask & (1 << p) != 0)
            };
            if inner.iter().any(|&n| kept(n) && slots(&kept, n) > w) {
                continue;
            }
            let area: f64 = inner
                .iter()
                .filter(|&&n| kept(n))
                .map(|&n| bin.nodes[n].bounds().half_area() as f64)
                .sum();
            best = best.min(area);
        }
        best
    }

    #[test]
    fn small_trees_get_the_exhaustive_optimum() {
        for seed in 1..40u32 {
            let n = 3 + (seed as usize * 7) % 11;
            let bin = build(&boxes(seed, n), 1);
            let optimal = WideBvh::<4>::from_bvh_with(&bin, Collapse::SahOptimal).unwrap();
            let got = kept_area(&optimal, &bin);
            let want = brute_force_optimum(&bin, 4);
            assert!(
                (got - want).abs() <= 1e-5 * want,
                "seed {seed}: {got} against {want}"
            );
            check::<4>(&bin);
        }
    }

    /// The plan is not the greedy rule under another name: on random trees
    /// of 60 boxes it keeps at least 1% less area somewhere.
    #[test]
    fn the_greedy_rule_is_beaten_where_it_opens_the_wrong_node() {
        let mut found = None;
        for seed in 1..200u32 {
            let bin = build(&boxes(seed, 60), 2);
            let (g, o) = check::<4>(&bin);
            if o < g * 0.99 {
                found = Some((seed, g, o));
                break;
            }
        }
        let (seed, g, o) = found.expect("some random tree where the optimum saves 1%");
        assert!(o < g, "seed {seed}: {o} against {g}");
    }

    #[test]
    fn children_before_parents_give_the_same_plan() {
        let bx = |x0: f32, x1: f32| Aabb::new(Vec3::new(x0, 0.0, 0.0), Vec3::new(x1, 1.0, 1.0));
        let (a, b, c) = (bx(0.0, 1.0), bx(1.5, 2.0), bx(5.0, 9.0));
        let [forward, backward] = two_layouts(a, b, c);
        let ab = a.union(b);
        let all = ab.union(c);
        let f = CollapsePlan::<2>::new(&forward);
        let k = CollapsePlan::<2>::new(&backward);
        assert_eq!(f.root_cost(), k.root_cost());
        assert_eq!(f.root_cost(), all.half_area() + ab.half_area());
        let mut slots = Vec::new();
        k.slots(&backward, 0, |n| slots.push(n));
        assert_eq!(slots, [3, 4]);
    }

    /// The leaf-child shortcuts give the general loop's rows, bit for bit
    /// (ties included), on every row of random trees and on rows with
    /// equal costs.
    #[test]
    fn leaf_child_shortcuts_match_the_general_split() {
        fn rows_agree<const W: usize>(c: &[f32; W]) {
            let zero = [0.0f32; W];
            assert_eq!(
                CollapsePlan::<W>::share_left_leaf(c),
                CollapsePlan::<W>::share(&zero, c)
            );
            assert_eq!(
                CollapsePlan::<W>::share_right_leaf(c),
                CollapsePlan::<W>::share(c, &zero)
            );
        }
        fn plan_rows_agree<const W: usize>(bin: &Bvh) {
            for row in &CollapsePlan::<W>::new(&bin.nodes).rows {
                rows_agree(&row.cost);
            }
        }
        for seed in 1..60u32 {
            let bin = build(&boxes(seed, 20 + seed as usize * 9), 1 + seed % 8);
            plan_rows_agree::<8>(&bin);
            plan_rows_agree::<4>(&bin);
        }
        // Plateaus: the fewest slots that reach the least cost.
        rows_agree(&[5.0, 3.0, 3.0, 3.0, 1.0, 1.0, 1.0, 1.0]);
        rows_agree(&[2.0, 2.0, 2.0, 2.0]);
        rows_agree(&[f32::INFINITY, f32::INFINITY, 4.0, 4.0]);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn optimal_collapse_is_valid_and_never_worse(seed in 1u32.., n in 1usize..600, leaf in 1u32..9) {
            let bin = build(&boxes(seed, n), leaf);
            check::<8>(&bin);
            check::<4>(&bin);
        }
    }
}
