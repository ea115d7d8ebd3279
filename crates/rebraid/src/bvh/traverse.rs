//! Scalar traversal of binary BVHs: iterative, fixed-size stack, near child first.

use glam::Vec3;

use super::{Bvh, BvhNode, MAX_DEPTH};

/// Entries of a traversal stack: enough for any tree the builders emit, since
/// each level pushes at most one node.
pub const TRAVERSAL_STACK: usize = MAX_DEPTH as usize;

/// Robustness factor for the slab test: `t_far` is scaled by `1 + 2 * gamma(3)`
/// (T. Ize, "Robust BVH Ray Traversal", JCGT 2(2), 2013) so that rounding in the
/// box test never culls a box a hit lies in.
pub const ROBUST_FAR: f32 =
    1.0 + 2.0 * (3.0 * f32::EPSILON * 0.5) / (1.0 - 3.0 * f32::EPSILON * 0.5);

/// A ray prepared for slab tests: origin and reciprocal direction.
///
/// A zero direction component gives an infinite reciprocal; the slab test
/// then yields `+-inf` (outside or inside that slab) or NaN when the origin
/// lies exactly on the slab plane, which [`BoxRay::hit_node`] treats as
/// inside that slab for every `t`.
#[derive(Clone, Copy, Debug)]
pub struct BoxRay {
    pub origin: Vec3,
    pub inv_dir: Vec3,
}

impl BoxRay {
    #[inline(always)]
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        Self {
            origin,
            inv_dir: Vec3::ONE / dir,
        }
    }

    /// Entry distance into the node's box, or `+inf` on a miss.
    #[inline(always)]
    pub fn hit_node(&self, node: &BvhNode, t_min: f32, t_max: f32) -> f32 {
        let t0 = (Vec3::from_array(node.min) - self.origin) * self.inv_dir;
        let t1 = (Vec3::from_array(node.max) - self.origin) * self.inv_dir;
        // A NaN (0 * inf: zero direction component, origin on a slab plane)
        // means the ray lies in that plane: inside the slab for every t. The
        // other bound of that slab is then +-inf, so NaN-ignoring min/max
        // would yield an empty slab; widen such slabs to (-inf, inf) instead.
        let in_plane = t0.is_nan_mask() | t1.is_nan_mask();
        let lo = Vec3::select(in_plane, Vec3::NEG_INFINITY, t0.min(t1));
        let hi = Vec3::select(in_plane, Vec3::INFINITY, t0.max(t1));
        let near = lo.x.max(lo.y).max(lo.z).max(t_min);
        // Pad after clamping to t_max: the entry distance of a box whose
        // surface holds a hit at t_max (a shared vertex or edge on the box's
        // face) can round above t_max while a neighbour in that box is hit a
        // few ulps before it; culling that box would lose the closest hit.
        let far = hi.x.min(hi.y).min(hi.z).min(t_max) * ROBUST_FAR;
        if near <= far { near } else { f32::INFINITY }
    }
}

/// The stack of a traversal: (node, entry distance) pairs. Callers that
/// traverse many subtrees per ray (the top level entering object BVHs) keep
/// one and pass it to every [`Bvh::traverse_from`], so no per-subtree setup.
pub type TraversalStack = [(u32, f32); TRAVERSAL_STACK];

/// Work counters of one traversal, for heat maps and statistics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TraversalCounters {
    /// Inner nodes whose children were tested.
    pub inner_visited: u32,
    /// Leaves entered.
    pub leaves_visited: u32,
    /// Of the leaves, top-level leaves that entered an object BVH (the
    /// two-level modes; each is also one of `leaves_visited`): the entries,
    /// whose cost is a transition, not a triangle test. A re-braided walk
    /// over the same tree as a flat one visits as many nodes and leaves
    /// plus these (nexuiz as one object: 3.07 leaves per diffuse ray flat,
    /// 3.07 + 1.34 entries re-braided).
    pub entries_visited: u32,
}

impl Bvh {
    /// Visit every leaf whose box the ray segment `[t_min, t_max]` enters, near
    /// children first. `leaf(node, t_max)` is called with each leaf and the
    /// current `t_max`, which it may shrink (closest hit); it returns `true` to
    /// stop the traversal (any hit).
    ///
    /// No allocation: the stack is a fixed array of [`TRAVERSAL_STACK`] entries.
    #[inline(always)]
    pub fn traverse<F>(
        &self,
        ray: &BoxRay,
        t_min: f32,
        t_max: f32,
        counters: &mut TraversalCounters,
        leaf: F,
    ) where
        F: FnMut(&BvhNode, &mut f32) -> bool,
    {
        match self.nodes.first() {
            Some(root) if ray.hit_node(root, t_min, t_max) < f32::INFINITY => {
                let mut stack = [(0u32, 0.0f32); TRAVERSAL_STACK];
                self.traverse_from(0, ray, t_min, t_max, &mut stack, counters, leaf)
            }
            _ => {}
        }
    }

    /// [`Bvh::traverse`] of the subtree rooted at node `start` (a top-level
    /// leaf of a re-braided tree enters an object BVH this way), using the
    /// caller's `stack`. The caller has already tested `start`'s box, so it
    /// is not tested again.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)] // the hot path: plain values, no argument struct
    pub fn traverse_from<F>(
        &self,
        start: u32,
        ray: &BoxRay,
        t_min: f32,
        mut t_max: f32,
        stack: &mut TraversalStack,
        counters: &mut TraversalCounters,
        mut leaf: F,
    ) where
        F: FnMut(&BvhNode, &mut f32) -> bool,
    {
        let nodes = self.nodes.as_slice();
        if start as usize >= nodes.len() {
            return;
        }
        let mut sp = 0usize;
        let mut current = start;
        loop {
            let node = &nodes[current as usize];
            if node.is_leaf() {
                counters.leaves_visited += 1;
                if leaf(node, &mut t_max) {
                    return;
                }
            } else {
                counters.inner_visited += 1;
                let c = node.index;
                let dl = ray.hit_node(&nodes[c as usize], t_min, t_max);
                let dr = ray.hit_node(&nodes[c as usize + 1], t_min, t_max);
                match (dl < f32::INFINITY, dr < f32::INFINITY) {
                    (true, true) => {
                        let (near, far) = if dl <= dr {
                            (c, (c + 1, dr))
                        } else {
                            (c + 1, (c, dl))
                        };
                        stack[sp] = far;
                        sp += 1;
                        current = near;
                        continue;
                    }
                    (true, false) => {
                        current = c;
                        continue;
                    }
                    (false, true) => {
                        current = c + 1;
                        continue;
                    }
                    (false, false) => {}
                }
            }
            // Pop, skipping nodes that a shrunken t_max now culls.
            loop {
                if sp == 0 {
                    return;
                }
                sp -= 1;
                let (node, entry) = stack[sp];
                if entry <= t_max * ROBUST_FAR {
                    current = node;
                    break;
                }
            }
        }
    }
}
