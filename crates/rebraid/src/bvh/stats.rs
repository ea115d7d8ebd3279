//! Tree statistics and the SAH cost as Embree reports it.

use super::Bvh;

/// Costs of the SAH statistic. Embree's statistic uses 1 for both.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SahCosts {
    pub traversal: f32,
    pub intersection: f32,
}

impl Default for SahCosts {
    fn default() -> Self {
        Self {
            traversal: 1.0,
            intersection: 1.0,
        }
    }
}

/// Size and quality figures of a tree.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BvhStats {
    pub nodes: usize,
    pub inner_nodes: usize,
    pub leaves: usize,
    pub primitives: usize,
    /// Depth of the deepest leaf (root = 1).
    pub max_depth: u32,
    /// Bytes of nodes and primitive data.
    pub bytes: usize,
    /// `(sum over inner nodes of half-area * traversal + sum over leaves of
    /// half-area * primitives * intersection) / half-area(root)`: the SAH
    /// statistic of `rebraiding.md` with a block size of one primitive.
    pub sah_cost: f64,
}

impl Bvh {
    /// Statistics of the tree. `bytes` counts nodes and primitive indices;
    /// callers that store more per primitive add it.
    pub fn stats(&self, costs: SahCosts) -> BvhStats {
        let mut s = BvhStats {
            nodes: self.nodes.len(),
            primitives: self.prim_indices.len(),
            bytes: self.bytes(),
            ..Default::default()
        };
        let Some(root) = self.nodes.first() else {
            return s;
        };
        let root_area = root.bounds().half_area() as f64;
        let mut sum = 0.0f64;
        let mut stack = vec![(0usize, 1u32)];
        while let Some((i, d)) = stack.pop() {
            let n = &self.nodes[i];
            let a = n.bounds().half_area() as f64;
            s.max_depth = s.max_depth.max(d);
            if n.is_leaf() {
                s.leaves += 1;
                sum += a * n.count as f64 * costs.intersection as f64;
            } else {
                s.inner_nodes += 1;
                sum += a * costs.traversal as f64;
                stack.push((n.index as usize, d + 1));
                stack.push((n.index as usize + 1, d + 1));
            }
        }
        s.sah_cost = if root_area > 0.0 {
            sum / root_area
        } else {
            0.0
        };
        s
    }
}
