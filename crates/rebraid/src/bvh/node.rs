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
