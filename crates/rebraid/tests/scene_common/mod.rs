//! Helpers of the scene and re-braiding tests: seeded random scenes (objects,
//! prototypes, instances with rotations, shears, non-uniform and mirroring
//! scales), a mirror of the scene contents, a world-space brute force over
//! every placed triangle, and checks of the top level.
//!
//! Used through `mod scene_common;` by `scene_modes.rs`, `scene_updates.rs`,
//! `rebraid_builder.rs` and `real_scenes_modes.rs` (not every test file uses
//! every helper).
#![allow(dead_code)]

use std::collections::{BTreeMap, HashMap};

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rebraid::glam::{Affine3A, EulerRot, Mat3, Quat, Vec3};
use rebraid::scene::Accel;
use rebraid::toplevel::TopLevelAccel;
use rebraid::triangle::{WatertightRay, geometric_normal, intersect_triangle, is_degenerate};
use rebraid::{Aabb, AccelMode, Hit, INVALID_ID, Ray, Scene, SceneParams, TriangleMesh};

pub fn rng(seed: u64) -> Pcg64 {
    Pcg64::seed_from_u64(seed)
}

pub fn rand_in(rng: &mut impl Rng, lo: Vec3, hi: Vec3) -> Vec3 {
    lo + Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) * (hi - lo)
}

/// A random unit vector.
pub fn rand_dir(rng: &mut impl Rng) -> Vec3 {
    loop {
        let v = Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) * 2.0 - 1.0;
        let l = v.length();
        if l > 0.1 && l <= 1.0 {
            return v / l;
        }
    }
}

/// `n` independent triangles of about `size` with corners around points
/// uniform in `[lo, hi]` (a scattered object when the box is the scene's).
pub fn soup(rng: &mut impl Rng, n: usize, lo: Vec3, hi: Vec3, size: f32) -> TriangleMesh {
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|_| {
            let c = rand_in(rng, lo, hi);
            let mut v = || c + (Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) - 0.5) * size;
            [v(), v(), v()]
        })
        .collect();
    TriangleMesh::from_triangles(&tris).unwrap()
}

/// A height-field grid of `nx * ny` quads over `[lo, hi]` (x, z), heights
/// within the box's y range: triangles share edges and vertices.
pub fn grid(rng: &mut impl Rng, nx: usize, ny: usize, lo: Vec3, hi: Vec3) -> TriangleMesh {
    let mut positions = Vec::new();
    for j in 0..=ny {
        for i in 0..=nx {
            let fx = i as f32 / nx as f32;
            let fz = j as f32 / ny as f32;
            let y = lo.y + (hi.y - lo.y) * rng.gen_range(0.0f32..1.0);
            positions.push(Vec3::new(
                lo.x + (hi.x - lo.x) * fx,
                y,
                lo.z + (hi.z - lo.z) * fz,
            ));
        }
    }
    let mut indices = Vec::new();
    let w = (nx + 1) as u32;
    for j in 0..ny as u32 {
        for i in 0..nx as u32 {
            let a = j * w + i;
            indices.push([a, a + 1, a + w + 1]);
            indices.push([a, a + w + 1, a + w]);
        }
    }
    TriangleMesh::new(positions, indices).unwrap()
}

/// A random invertible affine transform: rotation, non-uniform scale in
/// `0.3..2.5` (each axis mirrored with probability 1/2 when `mirror`), a
/// second rotation (so the linear part may shear), translation in `[lo, hi]`.
pub fn random_transform(rng: &mut impl Rng, lo: Vec3, hi: Vec3, mirror: bool) -> Affine3A {
    let mut s = Vec3::new(
        rng.gen_range(0.3..2.5),
        rng.gen_range(0.3..2.5),
        rng.gen_range(0.3..2.5),
    );
    if mirror {
        for k in 0..3 {
            if rng.gen_bool(0.5) {
                s[k] = -s[k];
            }
        }
    }
    let r1 = Quat::from_euler(
        EulerRot::XYZ,
        rng.gen_range(-3.1..3.1),
        rng.gen_range(-3.1..3.1),
        rng.gen_range(-3.1..3.1),
    );
    let shear = rng.gen_bool(0.3);
    let r2 = if shear {
        Quat::from_euler(
            EulerRot::ZYX,
            rng.gen_range(-1.5..1.5),
            rng.gen_range(-1.5..1.5),
            rng.gen_range(-1.5..1.5),
        )
    } else {
        Quat::IDENTITY
    };
    let m = Mat3::from_quat(r1) * Mat3::from_diagonal(s) * Mat3::from_quat(r2);
    Affine3A::from_mat3_translation(m, rand_in(rng, lo, hi))
}

/// What a test put into a scene, by the ids the scene gave: the brute force
/// traces this, and update tests apply every edit to both.
#[derive(Clone, Debug, Default)]
pub struct Model {
    /// Object id -> (mesh, placed directly).
    pub objects: BTreeMap<u32, (TriangleMesh, bool)>,
    /// Instance id -> (object, object-to-world transform).
    pub instances: BTreeMap<u32, (u32, Affine3A)>,
}

impl Model {
    /// Add an object (placed) or a prototype (not placed) to both.
    pub fn add_object(&mut self, scene: &mut Scene, mesh: TriangleMesh, placed: bool) -> u32 {
        let id = if placed {
            scene.add_object(mesh.clone()).unwrap()
        } else {
            scene.add_prototype(mesh.clone()).unwrap()
        };
        assert!(
            self.objects.insert(id, (mesh, placed)).is_none(),
            "id {id} reused"
        );
        id
    }

    pub fn add_instance(&mut self, scene: &mut Scene, object: u32, xf: Affine3A) -> u32 {
        let id = scene.add_instance(object, xf).unwrap();
        assert!(
            self.instances.insert(id, (object, xf)).is_none(),
            "id {id} reused"
        );
        id
    }

    /// A scene holding the model (ids must be 0..n in both maps).
    pub fn to_scene(&self, params: SceneParams) -> Scene {
        let mut s = Scene::with_params(params);
        for (&id, (mesh, placed)) in &self.objects {
            let got = if *placed {
                s.add_object(mesh.clone()).unwrap()
            } else {
                s.add_prototype(mesh.clone()).unwrap()
            };
            assert_eq!(got, id, "model ids must be dense to rebuild a scene");
        }
        for (&id, &(obj, xf)) in &self.instances {
            assert_eq!(s.add_instance(obj, xf).unwrap(), id);
        }
        s
    }

    /// Placements whose geometry the top level references: (object,
    /// instance) -> triangle count, for non-empty objects.
    pub fn placements(&self) -> HashMap<(u32, u32), usize> {
        let mut m = HashMap::new();
        for (&id, (mesh, placed)) in &self.objects {
            if *placed && !mesh.is_empty() {
                m.insert((id, INVALID_ID), mesh.len());
            }
        }
        for (&id, &(obj, _)) in &self.instances {
            let mesh = &self.objects[&obj].0;
            if !mesh.is_empty() {
                m.insert((obj, id), mesh.len());
            }
        }
        m
    }

    pub fn world_triangles(&self) -> usize {
        self.placements().values().sum()
    }

    /// Triangles of the distinct placed objects: an object placed directly
    /// and by several instances counts once.
    pub fn distinct_triangles(&self) -> usize {
        let placed: std::collections::BTreeSet<u32> =
            self.placements().keys().map(|&(obj, _)| obj).collect();
        placed.iter().map(|o| self.objects[o].0.len()).sum()
    }

    /// World-space triangles of every placement (degenerate ones dropped:
    /// they are never hit).
    pub fn world(&self) -> World {
        let mut tris = Vec::new();
        for (&id, (mesh, placed)) in &self.objects {
            if *placed {
                push_tris(&mut tris, mesh, None, id, INVALID_ID);
            }
        }
        for (&id, &(obj, xf)) in &self.instances {
            push_tris(&mut tris, &self.objects[&obj].0, Some(xf), obj, id);
        }
        World { tris }
    }
}

fn push_tris(
    out: &mut Vec<WorldTri>,
    mesh: &TriangleMesh,
    xf: Option<Affine3A>,
    object: u32,
    instance: u32,
) {
    for i in 0..mesh.len() {
        let mut v = mesh.triangle(i);
        if let Some(xf) = xf {
            v = v.map(|p| xf.transform_point3(p));
        }
        if !is_degenerate(v[0], v[1], v[2]) {
            out.push(WorldTri {
                v,
                object,
                instance,
                prim: i as u32,
            });
        }
    }
}

#[derive(Clone, Copy, Debug)]
pub struct WorldTri {
    pub v: [Vec3; 3],
    pub object: u32,
    pub instance: u32,
    pub prim: u32,
}

/// A brute-force hit: every triangle the ray meets, in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BruteHit {
    pub t: f32,
    pub u: f32,
    pub v: f32,
    pub object: u32,
    pub instance: u32,
    pub prim: u32,
    /// Unit world normal, winding-oriented: normalize((v1-v0) x (v2-v0)).
    pub normal: Vec3,
}

/// Every placed triangle in world space.
#[derive(Clone, Debug, Default)]
pub struct World {
    pub tris: Vec<WorldTri>,
}

impl World {
    /// The sum of the placements' box half areas (boxes of their
    /// non-degenerate world triangles) over the half area of their union.
    pub fn placement_overlap(&self) -> f64 {
        let mut boxes: HashMap<(u32, u32), Aabb> = HashMap::new();
        for t in &self.tris {
            let b = boxes.entry((t.object, t.instance)).or_insert(Aabb::EMPTY);
            for v in t.v {
                *b = b.grow(v);
            }
        }
        Aabb::overlap_ratio(boxes.into_values())
    }

    /// Every hit along the ray for t in [0, inf), sorted by t (the ray's
    /// interval is applied by the checks, which need hits just outside it).
    pub fn all_hits(&self, ray: &Ray) -> Vec<BruteHit> {
        if !ray.is_valid() {
            return Vec::new();
        }
        let w = WatertightRay::new(ray.origin, ray.dir);
        let mut hits: Vec<BruteHit> = self
            .tris
            .iter()
            .filter_map(|tri| {
                let [a, b, c] = tri.v;
                intersect_triangle(&w, a, b, c, 0.0, f32::INFINITY).map(|(t, u, v)| BruteHit {
                    t,
                    u,
                    v,
                    object: tri.object,
                    instance: tri.instance,
                    prim: tri.prim,
                    normal: geometric_normal(a, b, c).normalize_or_zero(),
                })
            })
            .collect();
        hits.sort_by(|a, b| a.t.total_cmp(&b.t));
        hits
    }

    /// The strict brute-force closest hit in the ray's interval (first of
    /// exact ties in triangle order).
    pub fn closest(&self, ray: &Ray) -> Option<BruteHit> {
        self.all_hits(ray)
            .into_iter()
            .find(|h| h.t >= ray.t_min && h.t <= ray.t_max)
    }

    /// A point on a random triangle (for rays aimed at geometry).
    pub fn random_point(&self, rng: &mut impl Rng) -> Vec3 {
        let tri = &self.tris[rng.gen_range(0..self.tris.len())];
        let (mut a, mut b): (f32, f32) = (rng.r#gen(), rng.r#gen());
        if a + b > 1.0 {
            a = 1.0 - a;
            b = 1.0 - b;
        }
        tri.v[0] * (1.0 - a - b) + tri.v[1] * a + tri.v[2] * b
    }
}

/// Tolerance on t between a world-space and an instance-space intersection
/// of the ray with a triangle of unit normal `n`: the rounding of the
/// transformed ray (a few ulps of the hit point's magnitude) moves t by that
/// distance over the ray's speed towards the plane, which grows without bound
/// at grazing angles.
pub fn t_tol(ray: &Ray, t: f32, n: Vec3) -> f32 {
    let d = ray.dir.length();
    let cos = (n.dot(ray.dir) / d).abs().max(1e-4);
    let pos_err = 4e-6 * (ray.origin.length() + t.abs() * d + 1.0);
    1e-4 * t.abs().max(1.0) + pos_err / (d * cos)
}

/// A barycentric coordinate within the rounding zone of an edge (wider at
/// grazing angles, where the hit point moves most).
fn near_edge(ray: &Ray, u: f32, v: f32, n: Vec3) -> bool {
    let cos = (n.dot(ray.dir) / ray.dir.length()).abs().max(1e-2);
    u.min(v).min(1.0 - u - v) < 1e-3 / cos
}

/// How a scene answer compared with the brute force.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Tally {
    pub rays: usize,
    pub hits: usize,
    /// Answers accepted only through the instance rounding allowance (a hit
    /// within rounding of an edge or of the interval's ends).
    pub tolerated: usize,
}

/// Compare a scene's closest hit and occlusion with the brute force.
///
/// `exact`: the scene traces world-space triangles identical to the brute
/// force's (flat mode, or no instances), so t, u, v and normals must be
/// bit-identical and only exact ties may differ. Otherwise hits through an
/// instance are compared with [`t_tol`] and may differ from the brute force
/// within rounding of an edge.
pub fn check_ray(
    all: &[BruteHit],
    ray: &Ray,
    got: Option<Hit>,
    occluded: bool,
    exact: bool,
) -> Result<bool, String> {
    let approx_inst = |inst: u32| !exact && inst != INVALID_ID;
    let in_iv = |t: f32| t >= ray.t_min && t <= ray.t_max;
    // A brute-force hit a correct instance traversal may still miss.
    let skippable = |b: &BruteHit| {
        approx_inst(b.instance)
            && (near_edge(ray, b.u, b.v, b.normal)
                || (b.t - ray.t_min).abs() <= t_tol(ray, b.t, b.normal)
                || (b.t - ray.t_max).abs() <= t_tol(ray, b.t, b.normal))
    };
    let mut tolerated = false;
    if got.is_some() != occluded {
        return Err(format!(
            "intersect {got:?} disagrees with occluded {occluded}"
        ));
    }
    match got {
        None => {
            for b in all.iter().filter(|b| in_iv(b.t)) {
                if skippable(b) {
                    tolerated = true;
                } else {
                    return Err(format!("scene missed {b:?}"));
                }
            }
        }
        Some(h) => {
            if !in_iv(h.t) {
                return Err(format!("hit t {} outside the ray interval", h.t));
            }
            // The scene's normal is not normalised (`Hit::normal`); its
            // direction is what must match the brute force's.
            let hn = h.unit_normal();
            if (hn.length() - 1.0).abs() > 1e-5 {
                return Err(format!("normal {:?} is zero or not finite", h.normal));
            }
            let approx_h = approx_inst(h.instance_id);
            let same = all.iter().find(|b| {
                (b.object, b.instance, b.prim) == (h.object_id, h.instance_id, h.prim_id)
                    && if approx_h {
                        (b.t - h.t).abs() <= t_tol(ray, h.t, hn)
                    } else {
                        b.t == h.t
                    }
            });
            match same {
                Some(b) => {
                    if approx_h {
                        if (hn - b.normal).length() > 2e-3 {
                            return Err(format!(
                                "normal {:?} differs from world normal {:?}",
                                hn, b.normal
                            ));
                        }
                    } else if (h.u, h.v, hn) != (b.u, b.v, b.normal) {
                        return Err(format!("u, v or normal of {h:?} differs from {b:?}"));
                    }
                }
                None if approx_h && near_edge(ray, h.u, h.v, hn) => tolerated = true,
                None => return Err(format!("scene hit {h:?} is no brute-force hit")),
            }
            for b in all.iter().filter(|b| in_iv(b.t) && b.t < h.t) {
                if approx_h || approx_inst(b.instance) {
                    if h.t - b.t <= t_tol(ray, h.t, hn).max(t_tol(ray, b.t, b.normal)) {
                        continue;
                    }
                    if skippable(b) {
                        tolerated = true;
                        continue;
                    }
                }
                return Err(format!("scene hit {h:?} but {b:?} is closer"));
            }
        }
    }
    Ok(tolerated)
}

/// Rays over a box: random origins and directions, a few axis-aligned
/// directions, half of them aimed at points of the world's triangles, and
/// every kind of interval ([0, inf), t_min > 0, finite t_max, both).
pub fn random_rays(rng: &mut impl Rng, world: &World, n: usize, lo: Vec3, hi: Vec3) -> Vec<Ray> {
    let pad = (hi - lo) * 0.15;
    (0..n)
        .map(|i| {
            let o = rand_in(rng, lo - pad, hi + pad);
            let mut d = if i % 2 == 0 && !world.tris.is_empty() {
                let p = world.random_point(rng);
                (p - o).normalize_or(Vec3::X)
            } else {
                rand_dir(rng)
            };
            if i % 23 == 0 {
                // Axis-aligned: zero components give infinite inverses.
                let k = rng.gen_range(0..3);
                d = Vec3::ZERO;
                d[k] = if rng.gen_bool(0.5) { 1.0 } else { -1.0 };
            }
            d *= rng.gen_range(0.5f32..2.0);
            let (t_min, t_max) = match i % 4 {
                0 => (0.0, f32::INFINITY),
                1 => (rng.gen_range(0.0..8.0), f32::INFINITY),
                2 => (0.0, rng.gen_range(1.0..20.0)),
                _ => {
                    let a = rng.gen_range(0.0..8.0);
                    (a, a + rng.gen_range(0.0..10.0))
                }
            };
            Ray::new(o, d, t_min, t_max).unwrap()
        })
        .collect()
}

/// Check every ray of a committed scene against the brute force, and the
/// batch queries against the single ones. Panics with the first mismatch.
pub fn check_scene(scene: &Scene, world: &World, rays: &[Ray], exact: bool, what: &str) -> Tally {
    let mut hits = vec![None; rays.len()];
    scene.intersect_batch(rays, &mut hits);
    let mut occ = vec![false; rays.len()];
    scene.occluded_batch(rays, &mut occ);
    let mut tally = Tally {
        rays: rays.len(),
        ..Default::default()
    };
    for (i, r) in rays.iter().enumerate() {
        let single = scene.intersect(r);
        assert_eq!(single, hits[i], "{what}: batch != single, ray {i} {r:?}");
        assert_eq!(
            scene.occluded(r),
            occ[i],
            "{what}: occluded batch != single, ray {i} {r:?}"
        );
        let all = world.all_hits(r);
        match check_ray(&all, r, single, occ[i], exact) {
            Ok(t) => tally.tolerated += t as usize,
            Err(e) => panic!("{what}: ray {i} {r:?}: {e}"),
        }
        tally.hits += single.is_some() as usize;
    }
    // The rounding allowance must stay an exception, or the test proves little.
    assert!(
        tally.tolerated * 100 <= rays.len(),
        "{what}: {tally:?}: too many answers only within rounding"
    );
    tally
}

/// A scene after a commit against its model: nothing left to commit, the
/// model's counts and meshes, the acceleration structure of the scene's
/// mode (a top level valid and reaching every placement once, see
/// [`check_top`]), and `n_rays` random rays answered as the brute force over
/// the model answers them (nothing is traced in an empty world).
pub fn check_commit(scene: &Scene, model: &Model, n_rays: usize, seed: u64, what: &str) {
    let mode = scene.mode();
    assert!(!scene.needs_commit(), "{what}");
    assert_eq!(scene.object_count(), model.objects.len(), "{what}");
    assert_eq!(scene.instance_count(), model.instances.len(), "{what}");
    assert_eq!(scene.world_triangles(), model.world_triangles(), "{what}");
    for (&id, (mesh, _)) in &model.objects {
        assert_eq!(scene.mesh(id).unwrap(), mesh, "{what}: object {id}");
    }
    match scene.accel() {
        Accel::TopLevel(t) => {
            assert_ne!(mode, AccelMode::Flat, "{what}");
            check_top(t, model, what);
        }
        Accel::Split(s) => {
            assert_eq!(mode, AccelMode::Rebraided, "{what}: split accel");
            check_tops(&[&s.fixed, &s.moving], model, what);
        }
        Accel::Flat(_) => assert_eq!(mode, AccelMode::Flat, "{what}: flat accel"),
        Accel::Empty => assert_eq!(model.world_triangles(), 0, "{what}"),
    }
    let world = model.world();
    if world.tris.is_empty() {
        return;
    }
    let rays = random_rays(&mut rng(seed), &world, n_rays, SCENE_LO, SCENE_HI);
    check_scene(
        scene,
        &world,
        &rays,
        mode == AccelMode::Flat || model.instances.is_empty(),
        what,
    );
}

/// The committed top level (panics in flat mode or when empty).
pub fn top(scene: &Scene) -> &TopLevelAccel {
    match scene.accel() {
        Accel::TopLevel(t) => t,
        Accel::Flat(_) => panic!("flat accel where a top level was expected"),
        Accel::Split(_) => panic!("split accel where one top level was expected"),
        Accel::Empty => panic!("empty accel where a top level was expected"),
    }
}

/// Validity, exact reachability (every primitive of every placement once)
/// and consistent build statistics of a committed top level.
pub fn check_top(t: &TopLevelAccel, model: &Model, what: &str) {
    check_tops(&[t], model, what);
}

/// [`check_top`] for the top levels of a split scene together: each valid
/// and consistent, every primitive of every placement reachable from
/// exactly one of them, once.
pub fn check_tops(tops: &[&TopLevelAccel], model: &Model, what: &str) {
    let want = model.placements();
    let mut counts: HashMap<(u32, u32), Vec<u32>> = HashMap::new();
    let mut refs_initial = 0;
    for t in tops {
        for (key, c) in t.reachable_counts() {
            assert!(
                counts.insert(key, c).is_none(),
                "{what}: placement {key:?} reachable from two top levels"
            );
        }
        refs_initial += check_one_top(t, what);
    }
    assert_eq!(
        counts.len(),
        want.len(),
        "{what}: reachable placements {:?} vs expected {:?}",
        sorted_keys(&counts),
        sorted_keys(&want)
    );
    for (key, c) in &counts {
        let n = want
            .get(key)
            .unwrap_or_else(|| panic!("{what}: unexpected placement {key:?}"));
        assert_eq!(c.len(), *n, "{what}: {key:?} prim count");
        if let Some(p) = c.iter().position(|&x| x != 1) {
            panic!("{what}: {key:?} primitive {p} reachable {} times", c[p]);
        }
    }
    assert_eq!(refs_initial, want.len(), "{what}: initial refs");
}

/// Validity and build statistics of one top level; its initial refs, a
/// merged BVH counted once per member.
fn check_one_top(t: &TopLevelAccel, what: &str) -> usize {
    t.validate()
        .unwrap_or_else(|e| panic!("{what}: invalid top level: {e}"));
    // A merged BVH is one initial ref for all its members, if the top
    // level has it.
    let merged_members = t
        .merged
        .as_ref()
        .filter(|m| t.refs.iter().any(|r| r.object == m.slot))
        .map_or(0, |m| {
            let members: std::collections::BTreeSet<u32> =
                m.origins.iter().map(|&(o, _)| o).collect();
            members.len() - 1
        });
    let s = &t.build_stats;
    assert_eq!(s.refs_final, t.refs.len(), "{what}: {s:?}");
    assert!(s.refs_final <= s.capacity, "{what}: {s:?}");
    assert_eq!(s.spare_used, s.refs_final - s.refs_initial, "{what}: {s:?}");
    // Each opened node takes one spare slot per child but the first: one
    // (binary) to seven (8-wide).
    assert!(
        s.nodes_opened <= s.spare_used && s.spare_used <= 7 * s.nodes_opened,
        "{what}: {s:?}"
    );
    assert_eq!(s.top_nodes, t.tree.nodes.len(), "{what}: {s:?}");
    let leaves = t.tree.nodes.iter().filter(|n| n.is_leaf()).count();
    assert_eq!(leaves, t.refs.len(), "{what}: one ref per top-level leaf");
    s.refs_initial + merged_members
}

fn sorted_keys<V>(m: &HashMap<(u32, u32), V>) -> Vec<(u32, u32)> {
    let mut k: Vec<_> = m.keys().copied().collect();
    k.sort();
    k
}

/// Shape of a random scene.
#[derive(Clone, Debug)]
pub struct Gen {
    /// Placed objects clustered in a random sub-box.
    pub clustered: usize,
    /// Placed objects whose triangles are scattered over the whole scene box.
    pub scattered: usize,
    /// Placed height-field grids (shared edges).
    pub grids: usize,
    pub tris: usize,
    /// Prototypes (not placed) and instances of them (or of placed objects).
    pub prototypes: usize,
    pub instances: usize,
    /// Instance transforms may mirror.
    pub mirror: bool,
}

pub const SCENE_LO: Vec3 = Vec3::ZERO;
pub const SCENE_HI: Vec3 = Vec3::splat(20.0);

impl Default for Gen {
    fn default() -> Self {
        Self {
            clustered: 6,
            scattered: 2,
            grids: 1,
            tris: 150,
            prototypes: 2,
            instances: 12,
            mirror: true,
        }
    }
}

/// A random scene model (not yet in a scene: see [`Model::to_scene`]).
pub fn random_model(rng: &mut impl Rng, g: &Gen) -> Model {
    let mut m = Model::default();
    let mut id = 0u32;
    let mut push = |m: &mut Model, mesh: TriangleMesh, placed: bool| {
        m.objects.insert(id, (mesh, placed));
        id += 1;
    };
    for _ in 0..g.clustered {
        let c = rand_in(rng, SCENE_LO, SCENE_HI);
        let h = Vec3::splat(rng.gen_range(1.0..4.0));
        push(&mut m, soup(rng, g.tris, c - h, c + h, 0.8), true);
    }
    for _ in 0..g.scattered {
        push(&mut m, soup(rng, g.tris, SCENE_LO, SCENE_HI, 1.0), true);
    }
    for _ in 0..g.grids {
        let c = rand_in(rng, SCENE_LO, SCENE_HI);
        let k = ((g.tris / 2) as f32).sqrt().max(1.0) as usize;
        push(
            &mut m,
            grid(
                rng,
                k,
                k,
                c - Vec3::new(5.0, 1.0, 5.0),
                c + Vec3::new(5.0, 1.0, 5.0),
            ),
            true,
        );
    }
    for _ in 0..g.prototypes {
        push(
            &mut m,
            soup(rng, g.tris, Vec3::splat(-2.0), Vec3::splat(2.0), 0.8),
            false,
        );
    }
    let n = m.objects.len() as u32;
    for i in 0..g.instances as u32 {
        if n == 0 {
            break;
        }
        // Mostly prototypes; some instances of placed objects too.
        let obj = if g.prototypes > 0 && rng.gen_bool(0.8) {
            n - 1 - rng.gen_range(0..g.prototypes as u32)
        } else {
            rng.gen_range(0..n)
        };
        let xf = random_transform(rng, SCENE_LO, SCENE_HI, g.mirror);
        m.instances.insert(i, (obj, xf));
    }
    m
}

/// A model whose prototypes are mostly placed by exactly one instance
/// (what a glTF scene's nodes give), so that commits bake them (see
/// `RebraidParams::bake_single_instances`), among placed objects they
/// overlap, one prototype placed twice and one placed object also placed by
/// an instance (neither baked). Returns the model and the instances a
/// commit bakes.
pub fn single_use_model(seed: u64) -> (Model, Vec<u32>) {
    let mut rng = rng(seed);
    let g = Gen {
        clustered: 4,
        scattered: 1,
        grids: 1,
        tris: 120,
        prototypes: 0,
        instances: 0,
        mirror: true,
    };
    let mut m = random_model(&mut rng, &g);
    let placed = m.objects.len() as u32;
    let mut inst = 0u32;
    let mut singles = Vec::new();
    for k in 0..6 {
        let next = placed + k;
        let mesh = soup(&mut rng, 120, Vec3::splat(-2.0), Vec3::splat(2.0), 0.8);
        m.objects.insert(next, (mesh, false));
        // The last prototype is placed twice.
        for _ in 0..if k == 5 { 2 } else { 1 } {
            let xf = random_transform(&mut rng, SCENE_LO, SCENE_HI, true);
            m.instances.insert(inst, (next, xf));
            if k < 5 {
                singles.push(inst);
            }
            inst += 1;
        }
    }
    let xf = random_transform(&mut rng, SCENE_LO, SCENE_HI, true);
    m.instances.insert(inst, (placed - 1, xf));
    (m, singles)
}

/// An OBJ scene as a model: one placed object per `o`.
pub fn load_obj_objects(path: &std::path::Path) -> Model {
    let (models, _) = tobj::load_obj(
        path,
        &tobj::LoadOptions {
            triangulate: true,
            single_index: false,
            ..Default::default()
        },
    )
    .unwrap_or_else(|e| panic!("loading {}: {e}", path.display()));
    let mut m = Model::default();
    for (i, model) in models.iter().enumerate() {
        let positions: Vec<Vec3> = model
            .mesh
            .positions
            .chunks_exact(3)
            .map(|p| Vec3::new(p[0], p[1], p[2]))
            .collect();
        let indices: Vec<[u32; 3]> = model
            .mesh
            .indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect();
        let mesh = TriangleMesh::new(positions, indices)
            .unwrap_or_else(|e| panic!("{}: object {}: {e}", path.display(), model.name));
        m.objects.insert(i as u32, (mesh, true));
    }
    m
}

#[path = "../support/scenes.rs"]
mod scenes;
#[allow(unused_imports)] // not every test crate reads real scenes
pub use scenes::scene_path_or_skip as scene_file_or_skip;
