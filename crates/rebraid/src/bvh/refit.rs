//! Refitting a mesh BVH to moved vertices.
//!
//! A refit keeps the tree's topology (which triangles share a leaf, and the
//! shape of the tree) and recomputes every box bottom-up from the new vertex
//! positions. It is valid whenever the triangles themselves (the index
//! buffer) are unchanged; its cost is linear in the mesh and far below a
//! rebuild, but the tree's quality degrades as the geometry moves away from
//! the pose it was built for (boxes grow and overlap). The scene decides per
//! object between refit and rebuild ([`crate::scene::UpdatePolicy`]).
//!
//! Work: the leaf-order triangles and the leaf boxes are updated in parallel
//! (fixed-size chunks) for large meshes; inner boxes follow in one reverse
//! sweep, which sees both children before their parent because every builder
//! stores children after their parent (checked; a post-order walk handles any
//! other layout).

use rayon::prelude::*;

use super::BvhNode;
use super::node::bottom_up;
use crate::triangle::is_degenerate;
use crate::{Aabb, Error, MeshBvh, TriangleMesh};

/// Meshes with at least this many triangles are refitted in parallel.
const PARALLEL_REFIT_MIN: usize = 1 << 14;
/// Chunk length of the parallel passes.
const CHUNK: usize = 1 << 11;

impl MeshBvh {
    /// Refit to `mesh`, which should have the triangles (indices) the tree
    /// was built over, with any vertex positions: the stored leaf-order
    /// triangles and every node box are recomputed, the topology is kept.
    /// (Other indices of the same count still give a correct tree, but one
    /// built for the wrong triangles: slow to trace.)
    ///
    /// Errors: [`Error::InvalidParameter`] when the mesh's triangle count
    /// differs from the tree's, and the mesh's own validation errors
    /// (non-finite vertex, index out of range). On error the BVH is unchanged.
    pub fn refit(&mut self, mesh: &TriangleMesh) -> Result<(), Error> {
        if mesh.len() != self.len() || self.bvh.prim_indices.len() != self.len() {
            return Err(Error::InvalidParameter(format!(
                "refit: the BVH holds {} triangles, the mesh has {}",
                self.len(),
                mesh.len()
            )));
        }
        mesh.validate()?;
        if self.is_empty() {
            return Ok(());
        }
        let parallel = self.len() >= PARALLEL_REFIT_MIN;
        let gather = |(tri, &p): (&mut [glam::Vec3; 3], &u32)| {
            let [a, b, c] = mesh.triangle(p as usize);
            *tri = if is_degenerate(a, b, c) {
                [a, a, a]
            } else {
                [a, b, c]
            };
        };
        if parallel {
            self.triangles
                .par_iter_mut()
                .zip(self.bvh.prim_indices.par_iter())
                .with_min_len(CHUNK)
                .for_each(gather);
        } else {
            self.triangles
                .iter_mut()
                .zip(self.bvh.prim_indices.iter())
                .for_each(gather);
        }

        // Leaf boxes from the stored triangles.
        let triangles = &self.triangles;
        let leaf_box = |n: &mut BvhNode| {
            if n.is_leaf() {
                let b = triangles[n.prim_range()]
                    .iter()
                    .fold(Aabb::EMPTY, |b, t| b.grow(t[0]).grow(t[1]).grow(t[2]));
                set_bounds(n, &b);
            }
        };
        let nodes = &mut self.bvh.nodes;
        if parallel {
            nodes.par_iter_mut().with_min_len(CHUNK).for_each(leaf_box);
        } else {
            nodes.iter_mut().for_each(leaf_box);
        }

        refit_inner(nodes);
        Ok(())
    }
}

/// Node `i`'s box made the union of its children's (a leaf is left as it
/// is).
#[inline]
pub(crate) fn refit_node(nodes: &mut [BvhNode], i: usize) {
    let n = nodes[i];
    if !n.is_leaf() {
        let c = n.index as usize;
        let b = nodes[c].bounds().union(nodes[c + 1].bounds());
        set_bounds(&mut nodes[i], &b);
    }
}

/// Every inner box made the union of its children's, bottom-up
/// ([`super::node::bottom_up`]).
pub(crate) fn refit_inner(nodes: &mut [BvhNode]) {
    for i in bottom_up(nodes) {
        refit_node(nodes, i);
    }
}

#[inline]
fn set_bounds(n: &mut BvhNode, b: &Aabb) {
    n.min = b.min.to_array();
    n.max = b.max.to_array();
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use crate::{BuildParams, MeshBvh, TriangleMesh};

    fn wavy(n: usize, phase: f32) -> TriangleMesh {
        let mut pos = Vec::new();
        let mut idx = Vec::new();
        for j in 0..=n {
            for i in 0..=n {
                let (x, z) = (i as f32 / n as f32, j as f32 / n as f32);
                pos.push(Vec3::new(x, 0.2 * (7.0 * x + phase).sin() * z, z));
            }
        }
        let w = n as u32 + 1;
        for j in 0..n as u32 {
            for i in 0..n as u32 {
                let a = j * w + i;
                idx.push([a, a + 1, a + w + 1]);
                idx.push([a, a + w + 1, a + w]);
            }
        }
        TriangleMesh::new(pos, idx).unwrap()
    }

    #[test]
    fn refit_matches_geometry_small_and_parallel() {
        for n in [5, 120] {
            let m0 = wavy(n, 0.0);
            let mut bvh = MeshBvh::build(&m0, &BuildParams::default()).unwrap();
            let m1 = wavy(n, 2.0);
            bvh.refit(&m1).unwrap();
            bvh.validate().unwrap();
            let rebuilt = MeshBvh::build(&m1, &BuildParams::default()).unwrap();
            assert_eq!(bvh.bvh.bounds(), rebuilt.bvh.bounds());
        }
    }

    #[test]
    fn refit_rejects_other_meshes() {
        let m0 = wavy(4, 0.0);
        let mut bvh = MeshBvh::build(&m0, &BuildParams::default()).unwrap();
        assert!(bvh.refit(&wavy(5, 0.0)).is_err());
        let mut bad = m0.clone();
        bad.positions[3].x = f32::NAN;
        let before = bvh.clone();
        assert!(bvh.refit(&bad).is_err());
        assert_eq!(bvh.triangles, before.triangles);
    }
}
