//! Structural validation of a built BVH.

use super::{Bvh, MAX_DEPTH};
use crate::Aabb;

impl Bvh {
    /// Check the invariants every builder promises: each child's box inside
    /// its parent's, each primitive's box inside its leaf's, every primitive
    /// referenced by exactly one leaf, no empty leaf, every node reachable
    /// once, depth within [`MAX_DEPTH`]. `boxes` are the primitive boxes the
    /// tree was built over, indexed by primitive id.
    pub fn validate(&self, boxes: &[Aabb]) -> Result<(), String> {
        if self.nodes.is_empty() {
            return if boxes.is_empty() && self.prim_indices.is_empty() {
                Ok(())
            } else {
                Err("empty tree over a non-empty primitive set".into())
            };
        }
        if self.prim_indices.len() != boxes.len() {
            return Err(format!(
                "{} primitive indices for {} primitives",
                self.prim_indices.len(),
                boxes.len()
            ));
        }
        let mut seen_prim = vec![false; boxes.len()];
        let mut seen_slot = vec![false; self.prim_indices.len()];
        let mut seen_node = vec![false; self.nodes.len()];
        let mut stack = vec![(0usize, 1u32)];
        seen_node[0] = true;
        while let Some((i, depth)) = stack.pop() {
            if depth > MAX_DEPTH {
                return Err(format!("node {i} at depth {depth} > {MAX_DEPTH}"));
            }
            let node = &self.nodes[i];
            let b = node.bounds();
            if node.is_leaf() {
                let r = node.prim_range();
                if r.end > self.prim_indices.len() {
                    return Err(format!("leaf {i} range {r:?} out of bounds"));
                }
                for slot in r {
                    if std::mem::replace(&mut seen_slot[slot], true) {
                        return Err(format!("primitive slot {slot} in two leaves"));
                    }
                    let p = self.prim_indices[slot] as usize;
                    if p >= boxes.len() {
                        return Err(format!("leaf {i} references primitive {p} out of range"));
                    }
                    if std::mem::replace(&mut seen_prim[p], true) {
                        return Err(format!("primitive {p} referenced twice"));
                    }
                    if !b.contains_box(&boxes[p]) {
                        return Err(format!("primitive {p} not inside leaf {i}"));
                    }
                }
            } else {
                let c = node.index as usize;
                if c + 1 >= self.nodes.len() {
                    return Err(format!("node {i} children {c} out of bounds"));
                }
                for k in [c, c + 1] {
                    if std::mem::replace(&mut seen_node[k], true) {
                        return Err(format!("node {k} reachable twice"));
                    }
                    if !b.contains_box(&self.nodes[k].bounds()) {
                        return Err(format!("child {k} not inside parent {i}"));
                    }
                    stack.push((k, depth + 1));
                }
            }
        }
        if let Some(p) = seen_prim.iter().position(|s| !s) {
            return Err(format!("primitive {p} not referenced"));
        }
        if let Some(k) = seen_node.iter().position(|s| !s) {
            return Err(format!("node {k} unreachable"));
        }
        Ok(())
    }
}
