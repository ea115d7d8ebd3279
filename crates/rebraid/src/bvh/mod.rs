//! Binary BVHs: node layout, builder, traversal, validation and statistics.

pub mod binning;
mod build;
pub mod collapse;
mod node;
pub mod occlusion_order;
#[cfg(target_arch = "x86_64")]
pub mod packet;
mod refit;
pub mod reinsert;
pub mod simd;
mod stats;
#[cfg(test)]
pub(crate) mod test_trees;
mod traverse;
pub mod triangle4;
mod validate;
pub mod wide;

pub use binning::BinBox;
pub use build::{
    BuildParams, LargeLeafSplit, MAX_DEPTH, MEDIAN_FROM_DEPTH, SceneVolumeLeafLimit, build_bvh,
    build_bvh_aligned,
};
pub(crate) use build::{compact_slots, split_slots};
pub use collapse::Collapse;
pub use node::BvhNode;
pub use reinsert::ReinsertParams;
pub use simd::{
    BoxTester, FmaSlab, Kernel, TesterFactory, WIDE_STACK, WideMeshBvh, WideQuery, intersect_many,
    occluded_many, query_many, query_subtree, subtree_with, traverse_wide, traverse_with,
    with_kernel,
};
pub use stats::{BvhStats, SahCosts};
pub use traverse::{BoxRay, ROBUST_FAR, TRAVERSAL_STACK, TraversalCounters, TraversalStack};
pub use triangle4::{Triangle4, WideTriangleBvh};
pub use wide::{WideBvh, WideNode, WideStats};

/// A binary BVH over primitives known only by index.
///
/// `nodes[0]` is the root (when there is one); `prim_indices` lists the
/// primitives in leaf order, so a leaf's range indexes into it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Bvh {
    pub nodes: Vec<BvhNode>,
    pub prim_indices: Vec<u32>,
}

impl Bvh {
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Bounds of the whole tree (empty for an empty tree).
    pub fn bounds(&self) -> crate::Aabb {
        self.nodes
            .first()
            .map_or(crate::Aabb::EMPTY, |n| n.bounds())
    }

    /// Bytes of the node and index arrays.
    pub fn bytes(&self) -> usize {
        std::mem::size_of_val(self.nodes.as_slice())
            + std::mem::size_of_val(self.prim_indices.as_slice())
    }
}
