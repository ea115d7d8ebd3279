//! Wide (4- and 8-ary) BVH layouts, collapsed from the binary [`Bvh`].
//!
//! Wide BVHs test the boxes of all children of a node with one SIMD
//! instruction sequence (I. Wald, C. Benthin, S. Boulos, "Getting Rid of
//! Packets: Efficient SIMD Single-Ray Traversal using Multi-branching BVHs",
//! RT 2008; H. Dammertz, J. Hanika, A. Keller, "Shallow Bounding Volume
//! Hierarchies for Fast SIMD Ray Tracing of Incoherent Rays", EGSR 2008).
//! As in Embree's BVH4/BVH8, they are not built directly but collapsed from
//! a binary SAH tree: each binary inner node either becomes a wide node or
//! is opened, its children taking slots of the wide node above. Which ones
//! stay is [`Collapse`]'s choice: by default the set of least summed area,
//! the SAH-optimal collapse ([`super::collapse`]); [`Collapse::Greedy`]
//! instead replaces the inner child of largest area by its two children
//! until the node has `W` children or only leaves remain, as Embree does.
//! Either way the wide tree keeps the binary tree's leaves and slot order
//! and is about `log2(W)` times shallower.
//!
//! Leaves keep the binary tree's leaf ranges, so they index the binary
//! tree's primitive order (a [`crate::MeshBvh`]'s leaf-order triangles)
//! directly.

use glam::Vec3;

use super::collapse::CollapsePlan;
use super::{Bvh, Collapse, MAX_DEPTH};
use crate::{Aabb, Error};

/// Flag bit of a child reference that is a leaf.
pub const WIDE_LEAF_FLAG: u32 = 1 << 31;
/// Bits of a leaf reference that hold `count - 1`.
pub const WIDE_LEAF_COUNT_BITS: u32 = 4;
/// Most primitives in one wide leaf (binary leaves larger than this are
/// rejected by [`WideBvh::from_bvh`]; the default `max_leaf_size` is 8).
pub const WIDE_MAX_LEAF_COUNT: u32 = 1 << WIDE_LEAF_COUNT_BITS;
/// Most primitives a wide BVH can index (27 bits of first-primitive index).
pub const WIDE_MAX_PRIMITIVES: usize = 1 << (31 - WIDE_LEAF_COUNT_BITS);
/// The reference of an empty child slot (its box can never be hit).
pub const WIDE_EMPTY: u32 = u32::MAX;

/// Encode a leaf over the primitives `first .. first + count`.
#[inline(always)]
pub const fn encode_leaf(first: u32, count: u32) -> u32 {
    WIDE_LEAF_FLAG | (first << WIDE_LEAF_COUNT_BITS) | (count - 1)
}

/// Decode a leaf reference into `(first, count)`.
#[inline(always)]
pub const fn decode_leaf(r: u32) -> (u32, u32) {
    (
        (r & !WIDE_LEAF_FLAG) >> WIDE_LEAF_COUNT_BITS,
        (r & (WIDE_MAX_LEAF_COUNT - 1)) + 1,
    )
}

/// True when a child reference is a leaf (or the empty slot marker, which
/// traversal never follows because its box is never hit).
#[inline(always)]
pub const fn is_leaf_ref(r: u32) -> bool {
    r & WIDE_LEAF_FLAG != 0
}

/// A node of a `W`-wide BVH: the boxes of its `W` children in SoA form (one
/// SIMD load per plane) and one `u32` reference per child.
///
/// `child[i]` is an inner node's index in [`WideBvh::nodes`], a leaf made by
/// [`encode_leaf`], or [`WIDE_EMPTY`]. Children fill the first slots; empty
/// slots have `min = +inf`, `max = -inf`, which the slab test of
/// [`super::simd`] can never hit (it picks the near plane by the direction's
/// sign, so an inverted box yields an entry at `+inf` and an exit at `-inf`).
///
/// 32-byte alignment lets AVX load each plane of a `W = 8` node without
/// crossing a cache line; `W = 4` nodes (112 bytes of data) are padded to
/// 128 bytes by it, two whole cache lines when the array is so aligned.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub struct WideNode<const W: usize> {
    pub min_x: [f32; W],
    pub min_y: [f32; W],
    pub min_z: [f32; W],
    pub max_x: [f32; W],
    pub max_y: [f32; W],
    pub max_z: [f32; W],
    pub child: [u32; W],
}

const _: () = assert!(std::mem::size_of::<WideNode<4>>() == 128);
const _: () = assert!(std::mem::size_of::<WideNode<8>>() == 224);
const _: () = assert!(std::mem::align_of::<WideNode<8>>() == 32);

impl<const W: usize> WideNode<W> {
    /// A node with every slot empty.
    pub const EMPTY: Self = Self {
        min_x: [f32::INFINITY; W],
        min_y: [f32::INFINITY; W],
        min_z: [f32::INFINITY; W],
        max_x: [f32::NEG_INFINITY; W],
        max_y: [f32::NEG_INFINITY; W],
        max_z: [f32::NEG_INFINITY; W],
        child: [WIDE_EMPTY; W],
    };

    /// The six planes as one array: `[min_x, min_y, min_z, max_x, max_y,
    /// max_z]`, so a kernel can pick the near plane of an axis by index.
    #[inline(always)]
    pub fn planes(&self) -> &[[f32; W]; 6] {
        // SAFETY: `repr(C)` lays the six `[f32; W]` fields out in declaration
        // order with no padding between them (each has the alignment of
        // f32 and a size that is a multiple of it), so they are exactly one
        // `[[f32; W]; 6]` at the start of the struct, which is aligned for it.
        unsafe { &*(self as *const Self as *const [[f32; W]; 6]) }
    }

    /// Box of child slot `i` (inverted for an empty slot).
    #[inline]
    pub fn child_bounds(&self, i: usize) -> Aabb {
        Aabb::new(
            Vec3::new(self.min_x[i], self.min_y[i], self.min_z[i]),
            Vec3::new(self.max_x[i], self.max_y[i], self.max_z[i]),
        )
    }

    /// Number of occupied slots (they come first).
    #[inline]
    pub fn child_count(&self) -> usize {
        self.child.iter().take_while(|&&c| c != WIDE_EMPTY).count()
    }

    pub(crate) fn set_child(&mut self, i: usize, b: &Aabb, r: u32) {
        self.min_x[i] = b.min.x;
        self.min_y[i] = b.min.y;
        self.min_z[i] = b.min.z;
        self.max_x[i] = b.max.x;
        self.max_y[i] = b.max.y;
        self.max_z[i] = b.max.z;
        self.child[i] = r;
    }
}

/// A `W`-wide BVH (`W` = 4 or 8). `nodes[0]` is the root when the tree is not
/// empty; `root_bounds` is its box, tested before the root's children.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WideBvh<const W: usize> {
    pub nodes: Vec<WideNode<W>>,
    /// The binary node each wide node was collapsed from, and the binary node
    /// of each child slot (`WIDE_EMPTY` for empty slots): the re-braiding
    /// top-level builder opens wide nodes and names them by binary node.
    pub binary_of: Vec<u32>,
    pub slot_binary: Vec<[u32; W]>,
    pub root_bounds: Aabb,
    /// Number of primitive slots the leaves cover (the binary tree's
    /// `prim_indices.len()`).
    pub prim_count: usize,
}

/// Size figures of a wide tree.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WideStats {
    pub nodes: usize,
    pub leaves: usize,
    /// Empty child slots over all nodes.
    pub empty_slots: usize,
    /// Depth of the deepest inner node (root = 1).
    pub max_depth: u32,
    /// Bytes of the node array.
    pub bytes: usize,
}

impl<const W: usize> WideBvh<W> {
    const WIDTH_OK: () = assert!(W == 4 || W == 8, "wide BVHs are 4 or 8 wide");

    /// Collapse a binary tree (see the module docs). Fails when a binary leaf
    /// holds more than [`WIDE_MAX_LEAF_COUNT`] primitives or the tree more
    /// than [`WIDE_MAX_PRIMITIVES`].
    pub fn from_bvh(bvh: &Bvh) -> Result<Self, Error> {
        Self::from_bvh_with(bvh, Collapse::default())
    }

    /// [`WideBvh::from_bvh`] by the rule `collapse`.
    pub fn from_bvh_with(bvh: &Bvh, collapse: Collapse) -> Result<Self, Error> {
        let mut out = Self::default();
        out.collapse_from_with(bvh, collapse)?;
        Ok(out)
    }

    /// [`WideBvh::from_bvh`] into this tree's arrays, reusing their memory
    /// (a top level rebuilt every frame collapses into the previous frame's
    /// arrays instead of fresh pages). On error the tree is left empty.
    pub fn collapse_from(&mut self, bvh: &Bvh) -> Result<(), Error> {
        self.collapse_from_with(bvh, Collapse::default())
    }

    /// [`WideBvh::collapse_from`] by the rule `collapse`.
    pub fn collapse_from_with(&mut self, bvh: &Bvh, collapse: Collapse) -> Result<(), Error> {
        let () = Self::WIDTH_OK;
        self.nodes.clear();
        self.binary_of.clear();
        self.slot_binary.clear();
        self.root_bounds = Aabb::default();
        self.prim_count = 0;
        let prim_count = bvh.prim_indices.len();
        if prim_count > WIDE_MAX_PRIMITIVES {
            return Err(Error::TooManyPrimitives(prim_count));
        }
        if let Some(n) = bvh.nodes.iter().find(|n| n.count > WIDE_MAX_LEAF_COUNT) {
            return Err(Error::InvalidParameter(format!(
                "a binary leaf of {} primitives exceeds the wide leaf limit of {WIDE_MAX_LEAF_COUNT} \
                 (build with max_leaf_size <= {WIDE_MAX_LEAF_COUNT})",
                n.count
            )));
        }
        let Some(root) = bvh.nodes.first() else {
            return Ok(());
        };
        let bin = &bvh.nodes;
        let (nodes, binary_of, slot_binary) =
            (&mut self.nodes, &mut self.binary_of, &mut self.slot_binary);
        nodes.reserve(bin.len() / (W - 1) + 1);
        nodes.push(WideNode::EMPTY);
        binary_of.push(0);
        slot_binary.push([WIDE_EMPTY; W]);
        // (binary node to collapse, wide node to fill)
        let mut work = vec![(0usize, 0usize)];
        // Candidate children with the area by which the next one to expand
        // is chosen (computed once per candidate; `-inf` for leaves, which
        // are never expanded).
        let mut kids: Vec<(usize, f32)> = Vec::with_capacity(W);
        let candidate = |k: usize| {
            let n = &bin[k];
            let a = if n.is_leaf() {
                f32::NEG_INFINITY
            } else {
                n.bounds().half_area()
            };
            (k, a)
        };
        let plan = (collapse == Collapse::SahOptimal).then(|| CollapsePlan::<W>::new(bin));
        while let Some((b, w)) = work.pop() {
            kids.clear();
            if bin[b].is_leaf() {
                // Only a leaf root gets here: one leaf child.
                kids.push(candidate(b));
            } else if let Some(plan) = &plan {
                plan.slots(bin, b, |k| kids.push(candidate(k)));
            } else {
                let c = bin[b].index as usize;
                kids.extend([candidate(c), candidate(c + 1)]);
                while kids.len() < W {
                    // The inner child of largest area (first of equals);
                    // areas may be infinite for huge boxes, never NaN for
                    // valid ones.
                    let mut best: Option<(usize, f32)> = None;
                    for (i, &(k, a)) in kids.iter().enumerate() {
                        if !bin[k].is_leaf() && best.is_none_or(|(_, ba)| a > ba) {
                            best = Some((i, a));
                        }
                    }
                    let Some((i, _)) = best else { break };
                    let c = bin[kids[i].0].index as usize;
                    kids[i] = candidate(c);
                    kids.insert(i + 1, candidate(c + 1));
                }
            }
            for (slot, &(k, _)) in kids.iter().enumerate() {
                let n = &bin[k];
                let r = if n.is_leaf() {
                    encode_leaf(n.index, n.count)
                } else {
                    let idx = nodes.len();
                    nodes.push(WideNode::EMPTY);
                    binary_of.push(k as u32);
                    slot_binary.push([WIDE_EMPTY; W]);
                    work.push((k, idx));
                    idx as u32
                };
                nodes[w].set_child(slot, &n.bounds(), r);
                slot_binary[w][slot] = k as u32;
            }
        }
        self.root_bounds = root.bounds();
        self.prim_count = prim_count;
        Ok(())
    }

    #[inline]
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Bytes of the node array and the binary-node maps.
    pub fn bytes(&self) -> usize {
        std::mem::size_of_val(self.nodes.as_slice())
            + std::mem::size_of_val(self.binary_of.as_slice())
            + std::mem::size_of_val(self.slot_binary.as_slice())
    }

    /// For each of the `binary_nodes` nodes of the binary tree this was
    /// collapsed from, the wide node collapsed from it, or `WIDE_EMPTY`.
    pub fn wide_of_binary(&self, binary_nodes: usize) -> Vec<u32> {
        let mut map = vec![WIDE_EMPTY; binary_nodes];
        for (w, &b) in self.binary_of.iter().enumerate() {
            map[b as usize] = w as u32;
        }
        map
    }

    /// Node, leaf and slot counts, depth and bytes.
    pub fn stats(&self) -> WideStats {
        let mut s = WideStats {
            nodes: self.nodes.len(),
            bytes: self.bytes(),
            ..Default::default()
        };
        if self.nodes.is_empty() {
            return s;
        }
        let mut stack = vec![(0usize, 1u32)];
        while let Some((i, d)) = stack.pop() {
            s.max_depth = s.max_depth.max(d);
            for &r in &self.nodes[i].child {
                if r == WIDE_EMPTY {
                    s.empty_slots += 1;
                } else if is_leaf_ref(r) {
                    s.leaves += 1;
                } else {
                    stack.push((r as usize, d + 1));
                }
            }
        }
        s
    }

    /// Check the binary-node maps against the binary tree this was
    /// collapsed from: each occupied slot names the binary node whose box
    /// it holds (exactly), each inner child's wide node was collapsed from
    /// that binary node, and leaf slots name binary leaves or subtrees.
    /// (The re-braiding builder opens wide nodes through these maps, so
    /// anything that reorders slots must move them along.)
    pub fn validate_slot_maps(&self, binary: &Bvh) -> Result<(), String> {
        if self.binary_of.len() != self.nodes.len() || self.slot_binary.len() != self.nodes.len() {
            return Err("binary maps and nodes differ in length".into());
        }
        for (n, node) in self.nodes.iter().enumerate() {
            for i in 0..node.child_count() {
                let b = self.slot_binary[n][i];
                let Some(bn) = binary.nodes.get(b as usize) else {
                    return Err(format!("node {n} slot {i}: binary node {b} out of range"));
                };
                if bn.bounds() != node.child_bounds(i) {
                    return Err(format!(
                        "node {n} slot {i}: box differs from binary node {b}'s"
                    ));
                }
                let r = node.child[i];
                if !is_leaf_ref(r) && self.binary_of[r as usize] != b {
                    return Err(format!(
                        "node {n} slot {i}: child {r} was collapsed from binary node {}, slot says {b}",
                        self.binary_of[r as usize]
                    ));
                }
            }
        }
        Ok(())
    }

    /// Check the invariants the kernels rely on: every node reachable once,
    /// every primitive slot in exactly one leaf, occupied slots first and
    /// empty slots inverted (`+inf` / `-inf`), every child box inside the
    /// slot box its parent holds for it (the root's inside `root_bounds`),
    /// every primitive box inside its leaf's box, depth within
    /// [`MAX_DEPTH`]. `prim_boxes` are indexed by primitive slot (leaf order).
    pub fn validate(&self, prim_boxes: &[Aabb]) -> Result<(), String> {
        if prim_boxes.len() != self.prim_count {
            return Err(format!(
                "{} primitive boxes for {} slots",
                prim_boxes.len(),
                self.prim_count
            ));
        }
        if self.nodes.is_empty() {
            return if self.prim_count == 0 {
                Ok(())
            } else {
                Err("empty wide tree over primitives".into())
            };
        }
        let mut seen_slot = vec![false; self.prim_count];
        let mut seen_node = vec![false; self.nodes.len()];
        seen_node[0] = true;
        let mut stack = vec![(0usize, self.root_bounds, 1u32)];
        while let Some((i, parent, depth)) = stack.pop() {
            if depth > MAX_DEPTH {
                return Err(format!("node {i} at depth {depth} > {MAX_DEPTH}"));
            }
            let node = &self.nodes[i];
            let n = node.child_count();
            if n == 0 {
                return Err(format!("node {i} has no children"));
            }
            for s in 0..W {
                let b = node.child_bounds(s);
                let r = node.child[s];
                if s >= n {
                    if r != WIDE_EMPTY
                        || node.child_bounds(s) != WideNode::<W>::EMPTY.child_bounds(0)
                    {
                        return Err(format!(
                            "node {i} slot {s}: occupied after an empty slot, or an empty slot with a box"
                        ));
                    }
                    continue;
                }
                if !parent.contains_box(&b) {
                    return Err(format!(
                        "node {i} slot {s}: box {b:?} not inside {parent:?}"
                    ));
                }
                if is_leaf_ref(r) {
                    let (first, count) = decode_leaf(r);
                    let range = first as usize..(first + count) as usize;
                    if range.end > self.prim_count {
                        return Err(format!("node {i} slot {s}: leaf {range:?} out of bounds"));
                    }
                    for p in range {
                        if std::mem::replace(&mut seen_slot[p], true) {
                            return Err(format!("primitive slot {p} in two leaves"));
                        }
                        if !b.contains_box(&prim_boxes[p]) {
                            return Err(format!("primitive slot {p} not inside its leaf box"));
                        }
                    }
                } else {
                    let k = r as usize;
                    if k >= self.nodes.len() {
                        return Err(format!("node {i} slot {s}: child {k} out of bounds"));
                    }
                    if std::mem::replace(&mut seen_node[k], true) {
                        return Err(format!("node {k} reachable twice"));
                    }
                    stack.push((k, b, depth + 1));
                }
            }
        }
        if let Some(p) = seen_slot.iter().position(|s| !s) {
            return Err(format!("primitive slot {p} not in any leaf"));
        }
        if let Some(k) = seen_node.iter().position(|s| !s) {
            return Err(format!("node {k} unreachable"));
        }
        Ok(())
    }
}

/// Embree's SAH statistic (`BVHNStatistics`, printed with `verbose=2`) of
/// the part of a wide tree below `node`, entered through a box of half area
/// `area`, as a sum not yet divided by the root's area: each node visited
/// counts its box's half area (the box its parent tests), each leaf what
/// `leaf(reference, slot_area)` returns (the slot box's half area times its
/// `Triangle4` blocks, or a whole subtree's sum for a leaf that enters
/// another tree). `box_area` gives a slot box's half area (world-space for
/// an instanced tree). Comparing this with Embree's own figure compares
/// trees as traversed, layout and all, rather than binary build trees.
pub fn wide_sah_sum<const W: usize>(
    wide: &WideBvh<W>,
    node: u32,
    area: f64,
    box_area: &impl Fn(&Aabb) -> f64,
    leaf: &mut impl FnMut(u32, f64) -> f64,
) -> f64 {
    let mut sum = 0.0;
    let mut stack = vec![(node, area)];
    while let Some((n, a)) = stack.pop() {
        sum += a;
        let node = &wide.nodes[n as usize];
        for i in 0..node.child_count() {
            let (c, slot_area) = (node.child[i], box_area(&node.child_bounds(i)));
            if is_leaf_ref(c) {
                sum += leaf(c, slot_area);
            } else {
                stack.push((c, slot_area));
            }
        }
    }
    sum
}

/// The half area of the union of a wide node's slot boxes: the root's box.
pub fn wide_root_area<const W: usize>(wide: &WideBvh<W>) -> f64 {
    let Some(root) = wide.nodes.first() else {
        return 0.0;
    };
    (0..root.child_count())
        .fold(Aabb::EMPTY, |u, i| u.union(root.child_bounds(i)))
        .half_area() as f64
}

#[cfg(test)]
mod tests {

    #[test]
    fn wide_sah_counts_each_node_and_leaf_as_embree_does() {
        use crate::BvhNode;
        let bx = |x0: f32, x1: f32| Aabb::new(Vec3::new(x0, 0.0, 0.0), Vec3::new(x1, 1.0, 1.0));
        // Binary: root (1, 2); 1 = (3, 4); leaves 2, 3, 4 of 2, 3, 1 primitives.
        let (l2, l3, l4) = (bx(4.0, 6.0), bx(0.0, 1.0), bx(2.0, 3.0));
        let n1 = l3.union(l4);
        let root = n1.union(l2);
        let bvh = Bvh {
            nodes: vec![
                BvhNode::inner(root, 1),
                BvhNode::inner(n1, 3),
                BvhNode::leaf(l2, 0, 2),
                BvhNode::leaf(l3, 2, 3),
                BvhNode::leaf(l4, 5, 1),
            ],
            prim_indices: (0..6).collect(),
        };
        let wide = WideBvh::<8>::from_bvh(&bvh).unwrap();
        // One wide node holding the three leaves: the root once, each leaf
        // by its area times its count, over the root's area.
        assert_eq!(wide.nodes.len(), 1);
        let ra = wide_root_area(&wide);
        assert_eq!(ra, root.half_area() as f64);
        let area = |b: &Aabb| b.half_area() as f64;
        let sum = wide_sah_sum(&wide, 0, ra, &area, &mut |c, a| a * decode_leaf(c).1 as f64);
        let expected =
            ra + l2.half_area() as f64 * 2.0 + l3.half_area() as f64 * 3.0 + l4.half_area() as f64;
        assert!(
            (sum - expected).abs() <= 1e-9 * expected,
            "{sum} against {expected}"
        );
    }

    use super::*;

    #[test]
    fn leaf_encoding_round_trips() {
        for (first, count) in [(0, 1), (5, 16), ((WIDE_MAX_PRIMITIVES - 1) as u32, 3)] {
            let r = encode_leaf(first, count);
            assert!(is_leaf_ref(r));
            assert_ne!(r, WIDE_EMPTY);
            assert_eq!(decode_leaf(r), (first, count));
        }
        assert!(!is_leaf_ref(12345));
    }

    #[test]
    fn planes_alias_the_fields() {
        let mut n = WideNode::<8>::EMPTY;
        n.min_y[3] = 1.5;
        n.max_z[7] = -2.0;
        assert_eq!(n.planes()[1][3], 1.5);
        assert_eq!(n.planes()[5][7], -2.0);
    }
}
