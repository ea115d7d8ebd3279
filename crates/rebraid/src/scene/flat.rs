//! The flat acceleration mode: one BVH over every triangle of the scene in
//! world space (instanced objects' triangles transformed and duplicated).
//! The quality reference for the two-level modes, and their slow-build,
//! no-instancing foil.

use crate::bvh::triangle4::block_hit_record;
use crate::bvh::{
    BuildParams, Kernel, TraversalCounters, WideTriangleBvh, intersect_many, occluded_many,
};
use crate::{Error, Hit, MeshBvh, Ray, TriangleMesh};

/// Where a triangle of the flat BVH came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PrimOrigin {
    pub object: u32,
    pub instance: u32,
    pub prim: u32,
}

/// One BVH over the whole scene.
#[derive(Clone, Debug, Default)]
pub struct FlatAccel {
    pub bvh: MeshBvh,
    /// The 8-wide traversal layout collapsed from `bvh` (`None` when a leaf
    /// is too large for it: traversal stays binary then).
    pub wide: Option<WideTriangleBvh>,
    pub kernel: Kernel,
    /// Origin of each world triangle, by flat primitive id.
    pub origins: Vec<PrimOrigin>,
}

/// A placement to flatten: the object's mesh, the transform (None for the
/// identity) and the ids to report.
pub struct FlatPart<'a> {
    pub mesh: &'a TriangleMesh,
    pub transform: Option<glam::Affine3A>,
    pub object: u32,
    pub instance: u32,
}

impl FlatAccel {
    /// Embree's SAH statistic of the wide layout (see
    /// [`crate::bvh::wide::wide_sah_sum`]); 0 without one.
    pub fn wide_sah_cost(&self) -> f64 {
        self.wide.as_ref().map_or(0.0, |w| w.wide_sah_cost())
    }

    pub fn build(parts: &[FlatPart], params: &BuildParams, kernel: Kernel) -> Result<Self, Error> {
        let meshes: Vec<_> = parts
            .iter()
            .map(|p| (p.mesh, p.transform.as_ref()))
            .collect();
        let mesh = TriangleMesh::concat(&meshes)?;
        let mut origins = Vec::with_capacity(mesh.len());
        for p in parts {
            origins.extend((0..p.mesh.len() as u32).map(|prim| PrimOrigin {
                object: p.object,
                instance: p.instance,
                prim,
            }));
        }
        let bvh = MeshBvh::build(&mesh, params)?;
        let wide = WideTriangleBvh::from_mesh_with(&bvh, params.collapse).ok();
        Ok(Self {
            bvh,
            wide,
            kernel,
            origins,
        })
    }

    fn map_hit(&self, mut h: Hit) -> Hit {
        let o = self.origins[h.prim_id as usize];
        h.prim_id = o.prim;
        h.object_id = o.object;
        h.instance_id = o.instance;
        h
    }

    /// The wide tree when it exists and the ray is valid: `None` = no wide
    /// layout, `Some(None)` = nothing to trace. (No separate root-box test:
    /// the kernel tests the root's children at once.)
    fn wide_entry(&self, ray: &Ray) -> Option<Option<&WideTriangleBvh>> {
        let wide = self.wide.as_ref()?;
        let enters = ray.is_valid() && !self.bvh.bvh.nodes.is_empty();
        Some(enters.then_some(wide))
    }

    pub fn intersect_counted(&self, ray: &Ray, counters: &mut TraversalCounters) -> Option<Hit> {
        match self.wide_entry(ray) {
            None => self
                .bvh
                .intersect_counted(ray, counters)
                .map(|h| self.map_hit(h)),
            Some(None) => None,
            Some(Some(w)) => {
                let (t, u, v, k) = w.query::<false>(self.kernel, ray, counters)?;
                let (prim_id, normal) = block_hit_record(&w.blocks, k);
                Some(self.map_hit(Hit::on_mesh(t, u, v, prim_id, normal)))
            }
        }
    }

    /// Closest hits of a run of rays on the calling thread, as
    /// [`FlatAccel::intersect_counted`] answers each, with one kernel
    /// dispatch for the run. Panics when the lengths differ.
    pub fn intersect_many(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        match &self.wide {
            Some(w) if !self.bvh.bvh.nodes.is_empty() => {
                intersect_many(&w.wide.nodes, &w.blocks, self.kernel, rays, out, |h| {
                    h.map(|(t, u, v, k)| {
                        let (prim_id, normal) = block_hit_record(&w.blocks, k);
                        self.map_hit(Hit::on_mesh(t, u, v, prim_id, normal))
                    })
                })
            }
            _ => {
                assert_eq!(rays.len(), out.len(), "one output per ray");
                for (o, r) in out.iter_mut().zip(rays) {
                    *o = self.intersect_counted(r, &mut TraversalCounters::default());
                }
            }
        }
    }

    /// Occlusion of a run of rays on the calling thread (see
    /// [`FlatAccel::intersect_many`]).
    pub fn occluded_many(&self, rays: &[Ray], out: &mut [bool]) {
        match &self.wide {
            Some(w) if !self.bvh.bvh.nodes.is_empty() => {
                occluded_many(&w.wide.nodes, &w.blocks, self.kernel, rays, out)
            }
            _ => {
                assert_eq!(rays.len(), out.len(), "one output per ray");
                for (o, r) in out.iter_mut().zip(rays) {
                    *o = self.occluded(r);
                }
            }
        }
    }

    pub fn occluded(&self, ray: &Ray) -> bool {
        self.occluded_counted(ray, &mut TraversalCounters::default())
    }

    /// Occlusion, counting visited nodes (the binary fallback counts none).
    pub fn occluded_counted(&self, ray: &Ray, counters: &mut TraversalCounters) -> bool {
        match self.wide_entry(ray) {
            None => self.bvh.occluded(ray),
            Some(None) => false,
            Some(Some(w)) => w.query::<true>(self.kernel, ray, counters).is_some(),
        }
    }
}
