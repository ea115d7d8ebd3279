//! Triangle meshes and their BVHs (the object level of a two-level BVH).

use glam::{Vec3, Vec3A};
use rayon::prelude::*;

use crate::bvh::{
    BinBox, BoxRay, BuildParams, Bvh, BvhNode, BvhStats, SahCosts, TraversalCounters,
    build_bvh_aligned,
};
use crate::triangle::{WatertightRay, geometric_normal, intersect_triangle, is_degenerate};
use crate::{Aabb, Error, Hit, INVALID_ID, Ray};

/// The largest vertex coordinate magnitude a mesh may have: Embree's
/// `FLT_LARGE`, below whose square the sums of products of box extents (box
/// areas, the SAH's currency) stay finite. Embree drops primitives beyond
/// it without a word; we refuse them with an error. (A scene at 3e38 was
/// loaded before this check and built with NaN costs into a camera at
/// infinity, session 34.)
pub const MAX_COORDINATE: f32 = 1.844e18;

/// The first vertex that is not finite ([`Error::NonFiniteVertex`]) or has
/// a coordinate beyond [`MAX_COORDINATE`] ([`Error::VertexOutOfRange`]).
pub fn check_positions(positions: &[Vec3]) -> Result<(), Error> {
    // Each coordinate compared (a NaN fails its comparison; `max_element`
    // would pass over it).
    let bad = |p: &Vec3| !p.to_array().iter().all(|c| c.abs() <= MAX_COORDINATE);
    match positions.iter().position(bad) {
        None => Ok(()),
        Some(index) => {
            let value = positions[index].to_array();
            Err(if positions[index].is_finite() {
                Error::VertexOutOfRange { index, value }
            } else {
                Error::NonFiniteVertex { index, value }
            })
        }
    }
}

/// An indexed triangle mesh: vertex positions and one `[u32; 3]` per triangle.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriangleMesh {
    pub positions: Vec<Vec3>,
    pub indices: Vec<[u32; 3]>,
}

impl TriangleMesh {
    /// A checked mesh (see [`TriangleMesh::validate`]).
    pub fn new(positions: Vec<Vec3>, indices: Vec<[u32; 3]>) -> Result<Self, Error> {
        let m = Self { positions, indices };
        m.validate()?;
        Ok(m)
    }

    /// A mesh of independent triangles (a "soup").
    pub fn from_triangles(tris: &[[Vec3; 3]]) -> Result<Self, Error> {
        let positions = tris.iter().flatten().copied().collect();
        let indices = (0..tris.len() as u32)
            .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
            .collect();
        Self::new(positions, indices)
    }

    /// One mesh of the triangles of `parts` in order, each part's vertices
    /// moved by its transform if it has one: part `k`'s triangle `i` is
    /// triangle `i` plus the triangles of the parts before it. Fails when
    /// the vertices or triangles are more than `u32` indices name. The
    /// parts are taken as checked (not validated again); a transform that
    /// takes a vertex to infinity is caught by the BVH build.
    pub fn concat(parts: &[(&TriangleMesh, Option<&glam::Affine3A>)]) -> Result<Self, Error> {
        let vertices: usize = parts.iter().map(|(m, _)| m.positions.len()).sum();
        let triangles: usize = parts.iter().map(|(m, _)| m.len()).sum();
        if vertices > u32::MAX as usize || triangles >= INVALID_ID as usize {
            return Err(Error::TooManyPrimitives(triangles));
        }
        let mut positions = Vec::with_capacity(vertices);
        let mut indices = Vec::with_capacity(triangles);
        for &(m, xf) in parts {
            let base = positions.len() as u32;
            match xf {
                Some(t) => {
                    positions.par_extend(m.positions.par_iter().map(|&v| t.transform_point3(v)))
                }
                None => positions.extend_from_slice(&m.positions),
            }
            indices.extend(m.indices.iter().map(|t| t.map(|i| i + base)));
        }
        Ok(Self { positions, indices })
    }

    /// Every vertex finite and within [`MAX_COORDINATE`], every index in
    /// range. Degenerate triangles are fine.
    pub fn validate(&self) -> Result<(), Error> {
        check_positions(&self.positions)?;
        let nv = self.positions.len();
        for (t, tri) in self.indices.iter().enumerate() {
            if let Some(&v) = tri.iter().find(|&&v| v as usize >= nv) {
                return Err(Error::IndexOutOfRange {
                    triangle: t,
                    vertex: v,
                    vertex_count: nv,
                });
            }
        }
        if self.indices.len() >= (1 << 31) {
            return Err(Error::TooManyPrimitives(self.indices.len()));
        }
        Ok(())
    }

    #[inline]
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    #[inline]
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// The three vertices of triangle `i` (panics if `i` is out of range).
    #[inline]
    pub fn triangle(&self, i: usize) -> [Vec3; 3] {
        let [a, b, c] = self.indices[i];
        [
            self.positions[a as usize],
            self.positions[b as usize],
            self.positions[c as usize],
        ]
    }

    /// Bounds of the referenced vertices.
    pub fn bounds(&self) -> Aabb {
        (0..self.len()).fold(Aabb::EMPTY, |b, i| {
            self.triangle(i).iter().fold(b, |b, &p| b.grow(p))
        })
    }

    /// [`TriangleMesh::prim_boxes`] in the aligned form
    /// [`crate::bvh::build_bvh_aligned`] takes (the same values).
    pub fn prim_build_boxes(&self) -> (Vec<BinBox>, Vec<Vec3A>) {
        triangle_build_boxes(self.len(), |i| self.triangle(i))
    }

    /// One box and one centroid per triangle (box centres, as Embree bins by):
    /// [`TriangleMesh::prim_build_boxes`] as `Aabb`s and `Vec3`s.
    pub fn prim_boxes(&self) -> (Vec<Aabb>, Vec<Vec3>) {
        let (boxes, centroids) = self.prim_build_boxes();
        (
            boxes.iter().map(|b| b.to_aabb()).collect(),
            centroids.into_iter().map(Vec3::from).collect(),
        )
    }
}

/// Box and centroid (the box centre) of each of `n` triangles, in the
/// aligned form [`crate::bvh::build_bvh_aligned`] takes.
#[inline]
fn triangle_build_boxes(
    n: usize,
    triangle: impl Fn(usize) -> [Vec3; 3] + Sync,
) -> (Vec<BinBox>, Vec<Vec3A>) {
    (0..n)
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| {
            let [a, b, c] = triangle(i).map(Vec3A::from);
            let b = BinBox {
                min: a.min(b).min(c),
                max: a.max(b).max(c),
            };
            (b, b.center())
        })
        .unzip()
}

/// A BVH over one mesh with the triangles stored in leaf order, as the
/// watertight intersector wants them (three vertices, 36 bytes).
///
/// Triangles of zero area are kept (so every primitive stays referenced) but
/// stored collapsed to one point, which the intersector never hits.
#[derive(Clone, Debug, Default)]
pub struct MeshBvh {
    pub bvh: Bvh,
    /// Vertices of each triangle, in leaf order.
    pub triangles: Vec<[Vec3; 3]>,
}

impl MeshBvh {
    /// Validate the mesh and build its BVH.
    pub fn build(mesh: &TriangleMesh, params: &BuildParams) -> Result<Self, Error> {
        mesh.validate()?;
        let (boxes, centroids) = mesh.prim_build_boxes();
        Self::build_over(&boxes, &centroids, |i| mesh.triangle(i), params)
    }

    /// [`MeshBvh::build`] over the mesh's vertices moved by `xf` (a baked
    /// placement, see `RebraidParams::bake_single_instances`): the tree and
    /// triangles of the moved mesh, whose index array is the mesh's own (not
    /// copied). Each vertex is transformed once (transforming the three of
    /// every triangle where they are read made the engine's re-braided
    /// builds 6% slower, 16 alternations). A transform that takes a vertex
    /// to infinity is an [`Error::NonFiniteVertex`], beyond
    /// [`MAX_COORDINATE`] an [`Error::VertexOutOfRange`].
    pub fn build_transformed(
        mesh: &TriangleMesh,
        xf: &glam::Affine3A,
        params: &BuildParams,
    ) -> Result<Self, Error> {
        mesh.validate()?;
        let moved: Vec<Vec3> = mesh
            .positions
            .par_iter()
            .with_min_len(4096)
            .map(|&v| xf.transform_point3(v))
            .collect();
        check_positions(&moved)?;
        let triangle = |i: usize| mesh.indices[i].map(|k| moved[k as usize]);
        let (boxes, centroids) = triangle_build_boxes(mesh.len(), triangle);
        Self::build_over(&boxes, &centroids, triangle, params)
    }

    /// The tree over per-triangle boxes and centroids, and the triangles
    /// (`triangle(i)` gives triangle `i`'s vertices) in leaf order.
    fn build_over(
        boxes: &[BinBox],
        centroids: &[Vec3A],
        triangle: impl Fn(usize) -> [Vec3; 3] + Sync,
        params: &BuildParams,
    ) -> Result<Self, Error> {
        let bvh = build_bvh_aligned(boxes, centroids, params)?;
        let triangles = bvh
            .prim_indices
            .par_iter()
            .with_min_len(4096)
            .map(|&p| {
                let [a, b, c] = triangle(p as usize);
                if is_degenerate(a, b, c) {
                    [a, a, a]
                } else {
                    [a, b, c]
                }
            })
            .collect();
        Ok(Self { bvh, triangles })
    }

    /// Number of triangles.
    #[inline]
    pub fn len(&self) -> usize {
        self.triangles.len()
    }

    #[inline]
    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Intersect the triangles of one leaf, shrinking `t_max` and recording
    /// the closest hit as (t, u, v, leaf-order index).
    #[inline(always)]
    pub fn intersect_leaf(
        &self,
        wray: &WatertightRay,
        node: &BvhNode,
        t_min: f32,
        t_max: &mut f32,
        best: &mut Option<(f32, f32, f32, u32)>,
    ) {
        for k in node.prim_range() {
            let [a, b, c] = self.triangles[k];
            if let Some((t, u, v)) = intersect_triangle(wray, a, b, c, t_min, *t_max) {
                // `intersect_triangle` accepts t == t_max; an exact tie goes
                // to the smaller slot (the rule of every kernel).
                if crate::bvh::triangle4::nearer(t, k as u32, best) {
                    *t_max = t;
                    *best = Some((t, u, v, k as u32));
                }
            }
        }
    }

    /// True when some triangle of the leaf is hit within `[t_min, t_max]`.
    #[inline(always)]
    pub fn occluded_leaf(
        &self,
        wray: &WatertightRay,
        node: &BvhNode,
        t_min: f32,
        t_max: f32,
    ) -> bool {
        node.prim_range().any(|k| {
            let [a, b, c] = self.triangles[k];
            intersect_triangle(wray, a, b, c, t_min, t_max).is_some()
        })
    }

    /// Turn a leaf-order hit into a [`Hit`] with the mesh's primitive id.
    #[inline]
    pub fn make_hit(&self, (t, u, v, k): (f32, f32, f32, u32)) -> Hit {
        let (prim_id, normal) = self.hit_record(k);
        Hit::on_mesh(t, u, v, prim_id, normal)
    }

    /// The primitive id and the geometric normal at its length (`(v1 -
    /// v0) x (v2 - v0)`) of leaf-order slot `k`, for callers that transform
    /// the normal before normalising it once (instance hits).
    #[inline]
    pub fn hit_record(&self, k: u32) -> (u32, Vec3) {
        let [a, b, c] = self.triangles[k as usize];
        (self.bvh.prim_indices[k as usize], geometric_normal(a, b, c))
    }

    /// Closest hit along the ray, if any.
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        self.intersect_counted(ray, &mut TraversalCounters::default())
    }

    /// [`MeshBvh::intersect`] that also counts the nodes it visits.
    pub fn intersect_counted(&self, ray: &Ray, counters: &mut TraversalCounters) -> Option<Hit> {
        if !ray.is_valid() {
            return None;
        }
        let bray = BoxRay::new(ray.origin, ray.dir);
        let wray = WatertightRay::new(ray.origin, ray.dir);
        let mut best = None;
        self.bvh
            .traverse(&bray, ray.t_min, ray.t_max, counters, |node, t_max| {
                self.intersect_leaf(&wray, node, ray.t_min, t_max, &mut best);
                false
            });
        best.map(|h| self.make_hit(h))
    }

    /// True when anything is hit within `[t_min, t_max]` (any hit).
    pub fn occluded(&self, ray: &Ray) -> bool {
        if !ray.is_valid() {
            return false;
        }
        let bray = BoxRay::new(ray.origin, ray.dir);
        let wray = WatertightRay::new(ray.origin, ray.dir);
        let mut hit = false;
        self.bvh.traverse(
            &bray,
            ray.t_min,
            ray.t_max,
            &mut TraversalCounters::default(),
            |node, t_max| {
                hit = self.occluded_leaf(&wray, node, ray.t_min, *t_max);
                hit
            },
        );
        hit
    }

    /// Closest hits of many rays, in parallel; `out[i]` answers `rays[i]`.
    pub fn intersect_batch(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        crate::ray::par_query(rays, out, |r| self.intersect(r));
    }

    /// Occlusion of many rays, in parallel; `out[i]` answers `rays[i]`.
    pub fn occluded_batch(&self, rays: &[Ray], out: &mut [bool]) {
        crate::ray::par_query(rays, out, |r| self.occluded(r));
    }

    /// Tree statistics; `bytes` includes the triangle storage.
    pub fn stats(&self) -> BvhStats {
        let mut s = self.bvh.stats(SahCosts::default());
        s.bytes += std::mem::size_of_val(self.triangles.as_slice());
        s
    }

    /// Validate the tree against the triangles it stores.
    pub fn validate(&self) -> Result<(), String> {
        let mut boxes = vec![Aabb::EMPTY; self.len()];
        for (k, &p) in self.bvh.prim_indices.iter().enumerate() {
            let b = boxes
                .get_mut(p as usize)
                .ok_or_else(|| format!("primitive id {p} out of range"))?;
            *b = Aabb::from_points(&self.triangles[k]);
        }
        self.bvh.validate(&boxes)
    }
}

/// Brute-force reference: every ray against every triangle. Used by tests
/// and by `validate` commands to check the traversal kernels.
pub fn brute_force_intersect(mesh: &TriangleMesh, ray: &Ray) -> Option<Hit> {
    if !ray.is_valid() {
        return None;
    }
    let wray = WatertightRay::new(ray.origin, ray.dir);
    let mut best: Option<Hit> = None;
    let mut t_max = ray.t_max;
    for i in 0..mesh.len() {
        let [a, b, c] = mesh.triangle(i);
        let [a, b, c] = if is_degenerate(a, b, c) {
            [a, a, a]
        } else {
            [a, b, c]
        };
        if let Some((t, u, v)) = intersect_triangle(&wray, a, b, c, ray.t_min, t_max)
            && best.is_none_or(|h| t < h.t)
        {
            t_max = t;
            best = Some(Hit {
                t,
                u,
                v,
                prim_id: i as u32,
                object_id: INVALID_ID,
                instance_id: INVALID_ID,
                normal: geometric_normal(a, b, c),
            });
        }
    }
    best
}

/// Brute-force occlusion reference.
pub fn brute_force_occluded(mesh: &TriangleMesh, ray: &Ray) -> bool {
    if !ray.is_valid() {
        return false;
    }
    let wray = WatertightRay::new(ray.origin, ray.dir);
    (0..mesh.len()).any(|i| {
        let [a, b, c] = mesh.triangle(i);
        !is_degenerate(a, b, c)
            && intersect_triangle(&wray, a, b, c, ray.t_min, ray.t_max).is_some()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Affine3A, Quat};

    /// `concat`: each part's triangles in order, moved by its transform,
    /// bit for bit `transform_point3`'s vertices.
    #[test]
    fn concat_keeps_each_parts_triangles_in_order() {
        let a = TriangleMesh::from_triangles(&[
            [Vec3::ZERO, Vec3::X, Vec3::Y],
            [Vec3::Z, Vec3::X, Vec3::ONE],
        ])
        .unwrap();
        let b = TriangleMesh::new(
            vec![
                Vec3::new(2.0, 0.0, 0.0),
                Vec3::new(3.0, 1.0, 0.5),
                Vec3::new(2.0, 2.0, 1.0),
            ],
            vec![[0, 1, 2], [2, 1, 0]],
        )
        .unwrap();
        let xf = Affine3A::from_scale_rotation_translation(
            Vec3::new(1.5, 0.5, 2.0),
            Quat::from_rotation_y(0.7),
            Vec3::new(-3.0, 4.0, 0.25),
        );
        let m = TriangleMesh::concat(&[(&a, None), (&b, Some(&xf)), (&a, Some(&xf))]).unwrap();
        m.validate().unwrap();
        let moved = |t: [Vec3; 3]| t.map(|v| xf.transform_point3(v));
        let want: Vec<[Vec3; 3]> = (0..a.len())
            .map(|i| a.triangle(i))
            .chain((0..b.len()).map(|i| moved(b.triangle(i))))
            .chain((0..a.len()).map(|i| moved(a.triangle(i))))
            .collect();
        let got: Vec<[Vec3; 3]> = (0..m.len()).map(|i| m.triangle(i)).collect();
        assert_eq!(got, want);
        assert_eq!(TriangleMesh::concat(&[]).unwrap(), TriangleMesh::default());
    }

    /// A baked placement's BVH is the moved mesh's, bit for bit, and a
    /// transform that overflows a vertex is an error.
    #[test]
    fn transformed_build_equals_the_moved_mesh_build() {
        let mut positions = Vec::new();
        let mut indices = Vec::new();
        // A strip of triangles sharing edges, in a 7x5 grid.
        for y in 0..5u32 {
            for x in 0..7u32 {
                positions.push(Vec3::new(
                    x as f32 * 0.7,
                    y as f32 * 1.3,
                    ((x * y) % 3) as f32,
                ));
            }
        }
        for y in 0..4u32 {
            for x in 0..6u32 {
                let v = y * 7 + x;
                indices.push([v, v + 1, v + 7]);
                indices.push([v + 1, v + 8, v + 7]);
            }
        }
        // A degenerate one too: kept, stored collapsed.
        indices.push([0, 0, 1]);
        let mesh = TriangleMesh::new(positions, indices).unwrap();
        let xf = Affine3A::from_scale_rotation_translation(
            Vec3::new(1.5, -0.5, 2.0),
            Quat::from_rotation_y(0.7) * Quat::from_rotation_x(-0.3),
            Vec3::new(10.0, -3.0, 4.5),
        );
        let moved = TriangleMesh::new(
            mesh.positions
                .iter()
                .map(|&p| xf.transform_point3(p))
                .collect(),
            mesh.indices.clone(),
        )
        .unwrap();
        let params = BuildParams {
            max_leaf_size: 2,
            ..Default::default()
        };
        let a = MeshBvh::build_transformed(&mesh, &xf, &params).unwrap();
        let b = MeshBvh::build(&moved, &params).unwrap();
        assert_eq!(a.bvh, b.bvh);
        assert_eq!(a.triangles, b.triangles);
        let huge = Affine3A::from_scale(Vec3::splat(f32::MAX));
        assert!(matches!(
            MeshBvh::build_transformed(&mesh, &huge, &params),
            Err(Error::NonFiniteVertex { .. } | Error::VertexOutOfRange { .. })
        ));
        let far = Affine3A::from_translation(Vec3::splat(1e19));
        assert!(matches!(
            MeshBvh::build_transformed(&mesh, &far, &params),
            Err(Error::VertexOutOfRange { index: 0, .. })
        ));
    }
}
