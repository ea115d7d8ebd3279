//! The binary BVH node: plain data, 32 bytes, two nodes to a 64-byte line.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use crate::Aabb;

/// A node of a binary BVH.
///
/// `count == 0`: an inner node whose two children are the adjacent nodes
/// `index` and `index + 1` (siblings are stored as pairs so that a traversal
/// step loads both boxes from one cache line).
/// `count > 0`: a leaf over the primitives `index .. index + count` of the
/// BVH's primitive order.
///
/// This is the layout every builder emits; wide layouts are produced from it
/// by collapsing (a node's pair of children, and theirs, are the candidates
/// for the 4 or 8 children of a wide node).
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct BvhNode {
    pub min: [f32; 3],
    pub index: u32,
    pub max: [f32; 3],
    pub count: u32,
}

const _: () = assert!(std::mem::size_of::<BvhNode>() == 32);
const _: () = assert!(std::mem::align_of::<BvhNode>() == 4);

impl BvhNode {
    #[inline]
    pub fn leaf(bounds: Aabb, first: u32, count: u32) -> Self {
        debug_assert!(count > 0);
        Self {
            min: bounds.min.to_array(),
            index: first,
            max: bounds.max.to_array(),
            count,
        }
    }

    #[inline]
    pub fn inner(bounds: Aabb, first_child: u32) -> Self {
        Self {
            min: bounds.min.to_array(),
            index: first_child,
            max: bounds.max.to_array(),
            count: 0,
        }
    }

    #[inline(always)]
    pub fn is_leaf(&self) -> bool {
        self.count > 0
    }

    #[inline(always)]
    pub fn bounds(&self) -> Aabb {
        Aabb::new(Vec3::from_array(self.min), Vec3::from_array(self.max))
    }

    /// Primitive range of a leaf.
    #[inline(always)]
    pub fn prim_range(&self) -> std::ops::Range<usize> {
        self.index as usize..(self.index + self.count) as usize
    }
}

/// The nodes of a binary tree (root 0), children before their parents:
/// what a bottom-up pass (a refit, the collapse's plan) walks. Every builder
/// here stores children after their parents, so that is one backward sweep
/// over the indices, with no allocation; any other layout gets a reversed
/// preorder (a parent precedes all its descendants in preorder).
pub(crate) enum BottomUp {
    Backward(std::ops::Range<usize>),
    ReversedPreorder(std::iter::Rev<std::vec::IntoIter<usize>>),
}

impl Iterator for BottomUp {
    type Item = usize;

    #[inline]
    fn next(&mut self) -> Option<usize> {
        match self {
            BottomUp::Backward(r) => r.next_back(),
            BottomUp::ReversedPreorder(it) => it.next(),
        }
    }
}

/// [`BottomUp`] over `nodes` (empty for an empty tree).
pub(crate) fn bottom_up(nodes: &[BvhNode]) -> BottomUp {
    let children_after_parents = nodes
        .iter()
        .enumerate()
        .all(|(i, n)| n.is_leaf() || n.index as usize > i);
    if children_after_parents || nodes.is_empty() {
        return BottomUp::Backward(0..nodes.len());
    }
    let mut preorder = Vec::with_capacity(nodes.len());
    let mut stack = vec![0usize];
    while let Some(i) = stack.pop() {
        preorder.push(i);
        if !nodes[i].is_leaf() {
            let c = nodes[i].index as usize;
            stack.extend([c + 1, c]);
        }
    }
    BottomUp::ReversedPreorder(preorder.into_iter().rev())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each node once, after both its children, in either layout.
    #[test]
    fn bottom_up_visits_children_first() {
        let b = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let [forward, backward] = crate::bvh::test_trees::two_layouts(b, b, b);
        for nodes in [&forward[..], &backward[..]] {
            let order: Vec<usize> = bottom_up(nodes).collect();
            let pos = |i: usize| order.iter().position(|&k| k == i).unwrap();
            assert_eq!(order.len(), nodes.len(), "{order:?}");
            for (i, n) in nodes.iter().enumerate() {
                if !n.is_leaf() {
                    let c = n.index as usize;
                    assert!(pos(c) < pos(i) && pos(c + 1) < pos(i), "{order:?}");
                }
            }
        }
        assert_eq!(bottom_up(&[]).count(), 0);
    }
}
