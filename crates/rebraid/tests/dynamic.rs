//! Dynamic scenes (issue "Dynamic scenes: animated objects with per-frame
//! rebuilds"): every commit of an animation answers like a world-space brute
//! force over the interpolated geometry, in every mode; refit and rebuild
//! agree; refitted BVHs validate; objects come and go between frames; the
//! commit report lists refitted and rebuilt objects exactly; key-frame
//! interpolation.

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rebraid::animation::{AnimatedTransform, KeyframedMesh, SceneAnimation};
use rebraid::glam::{Affine3A, Quat, Vec3};
use rebraid::procedural_dynamic::{DynamicKind, DynamicObject, DynamicParams};
use rebraid::scene::Accel;
use rebraid::triangle::{WatertightRay, intersect_triangle, is_degenerate};
use rebraid::{
    Aabb, AccelMode, CommitReport, Hit, INVALID_ID, Ray, RebraidParams, Scene, SceneParams,
    TriangleMesh, UpdatePolicy,
};

const LO: Vec3 = Vec3::new(0.0, 0.0, 0.0);
const HI: Vec3 = Vec3::new(20.0, 6.0, 10.0);

fn rng(seed: u64) -> Pcg64 {
    Pcg64::seed_from_u64(seed)
}

fn rand_in(rng: &mut impl Rng, lo: Vec3, hi: Vec3) -> Vec3 {
    lo + Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) * (hi - lo)
}

fn soup(rng: &mut impl Rng, n: usize, lo: Vec3, hi: Vec3, size: f32) -> TriangleMesh {
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|_| {
            let c = rand_in(rng, lo, hi);
            [0, 1, 2].map(|_| c + rand_in(rng, Vec3::splat(-0.5), Vec3::splat(0.5)) * size)
        })
        .collect();
    TriangleMesh::from_triangles(&tris).unwrap()
}

/// A wavy grid over x, z in `[x0, x0 + 4] x [2, 8]`, height by `phase`.
fn wavy_grid(n: usize, x0: f32, phase: f32) -> TriangleMesh {
    let mut pos = Vec::new();
    let mut idx = Vec::new();
    for j in 0..=n {
        for i in 0..=n {
            let (u, v) = (i as f32 / n as f32, j as f32 / n as f32);
            let y = 2.0 + 1.5 * (6.0 * u + phase).sin() * (4.0 * v - phase).cos();
            pos.push(Vec3::new(x0 + 4.0 * u, y, 2.0 + 6.0 * v));
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

/// World-space brute force over every placed triangle of a scene.
struct World {
    /// (triangle, object, instance, prim)
    tris: Vec<([Vec3; 3], u32, u32, u32)>,
}

impl World {
    fn of(scene: &Scene, placed: &[u32]) -> Self {
        let mut tris = Vec::new();
        for &o in placed {
            let m = scene.mesh(o).unwrap();
            for p in 0..m.len() {
                tris.push((m.triangle(p), o, INVALID_ID, p as u32));
            }
        }
        for (id, o, xf) in scene.instances() {
            let m = scene.mesh(o).unwrap();
            for p in 0..m.len() {
                let t = m.triangle(p).map(|v| xf.transform_point3(v));
                tris.push((t, o, id, p as u32));
            }
        }
        Self { tris }
    }

    fn hit_t(tri: &[Vec3; 3], w: &WatertightRay, r: &Ray) -> Option<f32> {
        let [a, b, c] = *tri;
        if is_degenerate(a, b, c) {
            return None;
        }
        intersect_triangle(w, a, b, c, r.t_min, r.t_max).map(|h| h.0)
    }

    fn closest(&self, r: &Ray) -> Option<(f32, u32, u32, u32)> {
        let w = WatertightRay::new(r.origin, r.dir);
        let mut best: Option<(f32, u32, u32, u32)> = None;
        for (tri, o, i, p) in &self.tris {
            if let Some(t) = Self::hit_t(tri, &w, r)
                && best.is_none_or(|b| t < b.0)
            {
                best = Some((t, *o, *i, *p));
            }
        }
        best
    }

    /// Where the ray meets the given triangle, if it does.
    fn t_of(&self, r: &Ray, h: &Hit) -> Option<f32> {
        let w = WatertightRay::new(r.origin, r.dir);
        self.tris
            .iter()
            .find(|(_, o, i, p)| (*o, *i, *p) == (h.object_id, h.instance_id, h.prim_id))
            .and_then(|(tri, ..)| Self::hit_t(tri, &w, r))
    }
}

fn close(a: f32, b: f32) -> bool {
    (a - b).abs() <= 1e-4 * a.abs().max(b.abs()).max(1e-3)
}

/// Random rays through the box, half of them aimed at world triangles.
fn rays(rng: &mut impl Rng, world: &World, n: usize) -> Vec<Ray> {
    (0..n)
        .map(|k| {
            let o = rand_in(rng, LO - 1.0, HI + 1.0);
            let target = if k % 2 == 0 && !world.tris.is_empty() {
                let (t, ..) = world.tris[rng.gen_range(0..world.tris.len())];
                (t[0] + t[1] + t[2]) / 3.0
            } else {
                rand_in(rng, LO, HI)
            };
            Ray::new(o, target - o, 0.0, f32::INFINITY).unwrap()
        })
        .collect()
}

/// The scene answers like the brute force: same hit or miss, t within a
/// relative 1e-4, the reported triangle really hit at that t; occlusion
/// agrees. Rounding may flip a grazing ray through an instance: at most 1%.
fn check(scene: &Scene, world: &World, rays: &[Ray], what: &str) {
    let mut flipped = 0;
    let mut hits = 0;
    for (k, r) in rays.iter().enumerate() {
        let got = scene.intersect(r);
        hits += got.is_some() as usize;
        let want = world.closest(r);
        match (got, want) {
            (None, None) => {}
            (Some(h), Some((t, ..))) => {
                assert!(close(h.t, t), "{what}: ray {k}: t {} vs {t}", h.t);
                let own = world.t_of(r, &h);
                assert!(
                    own.is_some_and(|o| close(o, t)),
                    "{what}: ray {k}: reported triangle {h:?} not hit at {t} ({own:?})"
                );
            }
            (g, w) => {
                flipped += 1;
                assert!(
                    g.map_or(w.is_some_and(|w| w.2 != INVALID_ID), |h| h.instance_id
                        != INVALID_ID),
                    "{what}: ray {k}: got {g:?}, brute force {w:?}"
                );
            }
        }
        assert_eq!(
            scene.occluded(r),
            got.is_some(),
            "{what}: ray {k}: occluded disagrees with intersect"
        );
    }
    assert!(
        flipped * 100 <= rays.len(),
        "{what}: {flipped} flipped rays"
    );
    assert!(hits * 3 >= rays.len(), "{what}: only {hits} hits");
}

/// Object ids of the test scene.
struct Ids {
    statics: Vec<u32>,
    wave: u32,
    robot: u32,
    blob: u32,
    torus: u32,
    inst: u32,
}

struct Anim {
    wave: KeyframedMesh,
    robot: DynamicObject,
    torus: DynamicObject,
    spin: AnimatedTransform,
}

fn animation() -> Anim {
    let frames: Vec<Vec<Vec3>> = (0..3)
        .map(|k| wavy_grid(24, 1.0, k as f32 * 1.3).positions)
        .collect();
    let wave =
        KeyframedMesh::new(wavy_grid(24, 1.0, 0.0).indices, frames, vec![0.0, 0.5, 1.0]).unwrap();
    let bounds = Aabb::new(LO, HI);
    let p = DynamicParams::in_box(&bounds, Vec3::Y, 3000);
    let robot = DynamicObject::new(DynamicKind::Robot, &p).unwrap();
    let p2 = DynamicParams {
        start: Vec3::new(17.0, 0.5, 8.0),
        end: Vec3::new(6.0, 0.5, 2.0),
        triangles: 2000,
        ..p
    };
    let torus = DynamicObject::new(DynamicKind::Deforming, &p2).unwrap();
    let key = |s: f32, a: f32, p: Vec3| {
        Affine3A::from_scale_rotation_translation(Vec3::splat(s), Quat::from_rotation_y(a), p)
    };
    let spin = AnimatedTransform::new(vec![
        (0.0, key(1.0, 0.0, Vec3::new(12.0, 3.0, 5.0))),
        (0.5, key(1.5, 1.5, Vec3::new(14.0, 4.0, 6.0))),
        (1.0, key(0.7, 3.0, Vec3::new(10.0, 2.0, 7.0))),
    ])
    .unwrap();
    Anim {
        wave,
        robot,
        torus,
        spin,
    }
}

fn build(mode: AccelMode, a: &Anim, policy: UpdatePolicy) -> (Scene, Ids) {
    let mut r = rng(7);
    let mut s = Scene::with_params(SceneParams {
        mode,
        ..Default::default()
    });
    let statics = (0..3)
        .map(|k| {
            let lo = Vec3::new(k as f32 * 6.0, 0.0, 0.0);
            s.add_object(soup(&mut r, 400, lo, lo + Vec3::new(8.0, 6.0, 10.0), 0.8))
                .unwrap()
        })
        .collect();
    let wave = s.add_object(a.wave.mesh_at(0.0).unwrap()).unwrap();
    let robot = s.add_object(a.robot.mesh_at(0.0)).unwrap();
    let torus = s.add_object(a.torus.mesh_at(0.0)).unwrap();
    let blob = s
        .add_prototype(soup(&mut r, 300, Vec3::splat(-1.0), Vec3::splat(1.0), 0.4))
        .unwrap();
    let inst = s.add_instance(blob, a.spin.at(0.0)).unwrap();
    s.set_update_policy(wave, policy).unwrap();
    s.set_update_policy(robot, policy).unwrap();
    // The torus is always rebuilt.
    (
        s,
        Ids {
            statics,
            wave,
            robot,
            blob,
            torus,
            inst,
        },
    )
}

fn pose(s: &mut Scene, ids: &Ids, a: &Anim, t: f32, buf: &mut Vec<Vec3>) {
    a.wave.positions_into(t, buf);
    s.set_vertices(ids.wave, buf).unwrap();
    a.robot.positions_into(t, buf);
    s.set_vertices(ids.robot, buf).unwrap();
    a.torus.positions_into(t, buf);
    s.set_vertices(ids.torus, buf).unwrap();
    s.set_instance_transform(ids.inst, a.spin.at(t)).unwrap();
}

fn sorted(v: &[u32]) -> Vec<u32> {
    let mut v = v.to_vec();
    v.sort_unstable();
    v
}

fn validate_object_bvhs(scene: &Scene, what: &str) {
    if let Accel::TopLevel(t) = scene.accel() {
        for (id, o) in t.objects.iter().enumerate() {
            if let Some(o) = o {
                o.mesh
                    .validate()
                    .unwrap_or_else(|e| panic!("{what}: object {id}: {e}"));
                let fresh = rebraid::toplevel::ObjectBvh::new(o.mesh.clone());
                assert_eq!(o.subtree_cost, fresh.subtree_cost, "{what}: costs");
                assert_eq!(o.subtree_prims, fresh.subtree_prims, "{what}: counts");
            }
        }
        t.validate()
            .unwrap_or_else(|e| panic!("{what}: top level: {e}"));
    }
}

#[test]
fn animation_matches_brute_force_in_every_mode() {
    let a = animation();
    let mut buf = Vec::new();
    for mode in AccelMode::ALL {
        let (mut s, ids) = build(mode, &a, UpdatePolicy::Refit);
        let placed: Vec<u32> = ids
            .statics
            .iter()
            .copied()
            .chain([ids.wave, ids.robot, ids.torus])
            .collect();
        let frames = 6;
        for f in 0..frames {
            let t = f as f32 / (frames - 1) as f32;
            pose(&mut s, &ids, &a, t, &mut buf);
            let rep = s.commit().unwrap();
            let what = format!("{mode:?} frame {f}");
            if mode == AccelMode::Flat {
                assert!(rep.objects_refitted.is_empty() && rep.objects_rebuilt.is_empty());
            } else if f == 0 {
                // First BVHs are built, whatever the policy. The blob's one
                // instance has not moved yet (frame 0 sets the transform it
                // was added with): it is baked.
                assert_eq!(rep.objects_rebuilt.len(), s.object_count(), "{what}");
                assert!(rep.objects_refitted.is_empty(), "{what}");
                assert_eq!(rep.instances_baked, vec![ids.inst], "{what}");
            } else if f == 1 {
                // Its first move: the blob's BVH is built in object space,
                // once.
                assert_eq!(sorted(&rep.objects_refitted), vec![ids.wave, ids.robot]);
                assert_eq!(sorted(&rep.objects_rebuilt), vec![ids.torus, ids.blob]);
                assert_eq!(rep.objects_reused, 3, "{what}: statics");
                assert!(rep.instances_baked.is_empty(), "{what}");
            } else {
                assert_eq!(sorted(&rep.objects_refitted), vec![ids.wave, ids.robot]);
                assert_eq!(rep.objects_rebuilt, vec![ids.torus], "{what}");
                assert_eq!(rep.objects_reused, 4, "{what}: statics and blob");
                assert!(rep.instances_baked.is_empty(), "{what}");
                assert_eq!(
                    rep.triangles_refitted,
                    s.mesh(ids.wave).unwrap().len() + s.mesh(ids.robot).unwrap().len()
                );
            }
            validate_object_bvhs(&s, &what);
            let world = World::of(&s, &placed);
            let rays = rays(&mut rng(100 + f), &world, 300);
            check(&s, &world, &rays, &what);
        }
    }
}

#[test]
fn refit_and_rebuild_agree() {
    let a = animation();
    let mut buf = Vec::new();
    for mode in [AccelMode::TwoLevel, AccelMode::Rebraided] {
        let (mut refit, ids) = build(mode, &a, UpdatePolicy::Refit);
        let (mut rebuild, _) = build(mode, &a, UpdatePolicy::Rebuild);
        for f in 0..5 {
            let t = 0.1 + 0.2 * f as f32;
            pose(&mut refit, &ids, &a, t, &mut buf);
            pose(&mut rebuild, &ids, &a, t, &mut buf);
            let r1 = refit.commit().unwrap();
            let r2 = rebuild.commit().unwrap();
            if f > 0 {
                assert_eq!(r1.objects_refitted.len(), 2);
                assert!(r2.objects_refitted.is_empty());
                assert_eq!(r2.objects_rebuilt.len(), 3);
            }
            let world = World::of(&refit, &[ids.wave, ids.robot, ids.torus]);
            let mut r = rng(500 + f);
            for (k, ray) in rays(&mut r, &world, 400).iter().enumerate() {
                let (h1, h2) = (refit.intersect(ray), rebuild.intersect(ray));
                assert_eq!(
                    h1.map(|h| h.t),
                    h2.map(|h| h.t),
                    "{mode:?} frame {f} ray {k}: {h1:?} vs {h2:?}"
                );
                assert_eq!(refit.occluded(ray), rebuild.occluded(ray));
            }
        }
    }
}

#[test]
fn objects_removed_and_readded_between_frames() {
    let a = animation();
    let mut buf = Vec::new();
    for mode in AccelMode::ALL {
        let (mut s, mut ids) = build(mode, &a, UpdatePolicy::Refit);
        s.commit().unwrap();
        for f in 1..5 {
            let t = f as f32 / 4.0;
            let what = format!("{mode:?} frame {f}");
            let mut expect_rebuilt = vec![ids.torus];
            match f {
                // Robot leaves; the prototype and its instance too.
                1 => {
                    s.remove_object(ids.robot).unwrap();
                    assert_eq!(s.remove_object(ids.blob).unwrap(), vec![ids.inst]);
                }
                // They come back under new ids: built, not refitted.
                2 => {
                    ids.robot = s.add_object(a.robot.mesh_at(t)).unwrap();
                    s.set_update_policy(ids.robot, UpdatePolicy::Refit).unwrap();
                    let mut r = rng(9);
                    ids.blob = s
                        .add_prototype(soup(&mut r, 300, Vec3::splat(-1.0), Vec3::splat(1.0), 0.4))
                        .unwrap();
                    ids.inst = s.add_instance(ids.blob, a.spin.at(t)).unwrap();
                    expect_rebuilt.extend([ids.robot, ids.blob]);
                }
                // The new instance was baked at frame 2 (its transform set
                // again unchanged); its first move builds the blob's BVH
                // in object space.
                3 if mode != AccelMode::Flat => expect_rebuilt.push(ids.blob),
                _ => {}
            }
            a.wave.positions_into(t, &mut buf);
            s.set_vertices(ids.wave, &buf).unwrap();
            a.torus.positions_into(t, &mut buf);
            s.set_vertices(ids.torus, &buf).unwrap();
            let robot_live = f != 1;
            if robot_live {
                a.robot.positions_into(t, &mut buf);
                s.set_vertices(ids.robot, &buf).unwrap();
                s.set_instance_transform(ids.inst, a.spin.at(t)).unwrap();
            } else {
                assert!(s.set_vertices(ids.robot, &buf).is_err());
            }
            let rep = s.commit().unwrap();
            if mode != AccelMode::Flat {
                assert_eq!(
                    sorted(&rep.objects_rebuilt),
                    sorted(&expect_rebuilt),
                    "{what}"
                );
                let refitted = if f == 2 || !robot_live {
                    vec![ids.wave]
                } else {
                    vec![ids.wave, ids.robot]
                };
                assert_eq!(sorted(&rep.objects_refitted), refitted, "{what}");
            }
            validate_object_bvhs(&s, &what);
            let mut placed: Vec<u32> = ids.statics.clone();
            placed.extend([ids.wave, ids.torus]);
            if robot_live {
                placed.push(ids.robot);
            }
            let world = World::of(&s, &placed);
            check(&s, &world, &rays(&mut rng(f), &world, 200), &what);
        }
    }
}

#[test]
fn report_lists_refitted_and_rebuilt_exactly() {
    let mut r = rng(3);
    let mut s = Scene::new();
    let meshes: Vec<TriangleMesh> = (0..5)
        .map(|k| wavy_grid(8 + k, 2.0 * k as f32, 0.0))
        .collect();
    let ids: Vec<u32> = meshes
        .iter()
        .map(|m| s.add_object(m.clone()).unwrap())
        .collect();
    for &id in &ids[..4] {
        s.set_update_policy(id, UpdatePolicy::Refit).unwrap();
    }
    assert_eq!(s.update_policy(ids[0]).unwrap(), UpdatePolicy::Refit);
    assert_eq!(s.update_policy(ids[4]).unwrap(), UpdatePolicy::Rebuild);
    assert!(s.set_update_policy(99, UpdatePolicy::Refit).is_err());
    let rep = s.commit().unwrap();
    assert_eq!(sorted(&rep.objects_rebuilt), ids);
    assert!(rep.objects_refitted.is_empty());

    let moved = |m: &TriangleMesh| -> Vec<Vec3> {
        m.positions
            .iter()
            .map(|p| *p + Vec3::new(0.3, 0.1, 0.0))
            .collect()
    };
    // 0: moved (refit). 1: new mesh with the same triangles (refit).
    // 2: new topology (rebuild despite Refit). 3: untouched. 4: moved, Rebuild.
    s.set_vertices(ids[0], &moved(&meshes[0])).unwrap();
    s.set_mesh(ids[1], wavy_grid(9, 2.0, 1.0)).unwrap();
    s.set_mesh(ids[2], soup(&mut r, 50, LO, HI, 1.0)).unwrap();
    s.set_vertices(ids[4], &moved(&meshes[4])).unwrap();
    let rep: CommitReport = s.commit().unwrap();
    assert_eq!(rep.objects_refitted, vec![ids[0], ids[1]]);
    assert_eq!(sorted(&rep.objects_rebuilt), vec![ids[2], ids[4]]);
    assert_eq!(rep.objects_reused, 1);
    assert_eq!(rep.triangles_refitted, meshes[0].len() + meshes[1].len());
    assert_eq!(rep.triangles_rebuilt, 50 + meshes[4].len());
    assert!(rep.refit_ms >= 0.0 && rep.object_build_ms >= 0.0);

    // The soup of object 2 is now refittable.
    let soup2 = s.mesh(ids[2]).unwrap().clone();
    s.set_vertices(ids[2], &moved(&soup2)).unwrap();
    let rep = s.commit().unwrap();
    assert_eq!(rep.objects_refitted, vec![ids[2]]);
    assert!(rep.objects_rebuilt.is_empty());
    assert_eq!(rep.objects_reused, 4);

    // Flat commits build no object BVHs; the objects stay stale and are
    // refitted when a two-level commit comes.
    s.set_mode(AccelMode::Flat);
    s.set_vertices(ids[0], &meshes[0].positions).unwrap();
    let rep = s.commit().unwrap();
    assert!(rep.objects_refitted.is_empty() && rep.objects_rebuilt.is_empty());
    s.set_mode(AccelMode::Rebraided);
    let rep = s.commit().unwrap();
    assert_eq!(rep.objects_refitted, vec![ids[0]]);
}

#[test]
fn refit_is_in_place_unless_the_old_structure_is_shared() {
    let mut s = Scene::new();
    let m = wavy_grid(40, 0.0, 0.0);
    let id = s.add_object(m.clone()).unwrap();
    s.add_object(wavy_grid(10, 5.0, 0.0)).unwrap();
    s.set_update_policy(id, UpdatePolicy::Refit).unwrap();
    s.commit().unwrap();
    // Once it moves, the object is traced from the moving part of a split
    // scene, and the kept part holds no reference to it.
    let ptr = |s: &Scene| match s.accel() {
        Accel::TopLevel(t) => Arc::as_ptr(t.objects[id as usize].as_ref().unwrap()),
        Accel::Split(sp) => {
            assert!(sp.fixed.objects[id as usize].is_none());
            Arc::as_ptr(sp.moving.objects[id as usize].as_ref().unwrap())
        }
        _ => panic!("two-level"),
    };
    let p0 = ptr(&s);
    let up = |d: f32| -> Vec<Vec3> { m.positions.iter().map(|p| *p + Vec3::Y * d).collect() };
    s.set_vertices(id, &up(1.0)).unwrap();
    s.commit().unwrap();
    assert_eq!(ptr(&s), p0, "refitted in place");
    // A caller holding the old structure keeps its geometry.
    let old = s.accel().clone();
    s.set_vertices(id, &up(2.0)).unwrap();
    s.commit().unwrap();
    assert_ne!(ptr(&s), p0, "copied on write");
    let ray = Ray::new(Vec3::new(1.0, 10.0, 5.0), Vec3::NEG_Y, 0.0, f32::INFINITY).unwrap();
    let h_old = match old {
        Accel::TopLevel(t) => t.intersect(&ray),
        Accel::Split(sp) => sp.intersect(&ray),
        _ => panic!("two-level"),
    };
    let (h_old, h_new) = (h_old.unwrap(), s.intersect(&ray).unwrap());
    assert!(
        (h_old.t - h_new.t - 1.0).abs() < 1e-3,
        "{h_old:?} {h_new:?}"
    );
    // Buffers are kept between commits.
    assert!(s.top_level_buffer_bytes() > 0);
    s.set_reuse_top_level_buffers(false);
    s.set_vertices(id, &up(3.0)).unwrap();
    s.commit().unwrap();
    assert_eq!(s.top_level_buffer_bytes(), 0);
    assert!((s.intersect(&ray).unwrap().t - (h_new.t - 1.0)).abs() < 1e-3);
}

#[test]
fn keyframed_mesh_interpolates() {
    let f0 = vec![Vec3::ZERO, Vec3::X, Vec3::Y];
    let f1 = vec![
        Vec3::splat(2.0),
        Vec3::new(3.0, 0.0, 1.0),
        Vec3::new(0.1, 0.2, 0.3),
    ];
    let f2 = vec![Vec3::splat(-1.0), Vec3::ONE, Vec3::Z];
    let k = KeyframedMesh::new(
        vec![[0, 1, 2]],
        vec![f0.clone(), f1.clone(), f2.clone()],
        vec![1.0, 2.0, 4.0],
    )
    .unwrap();
    // Keys exact.
    assert_eq!(k.positions_at(1.0), f0);
    assert_eq!(k.positions_at(2.0), f1);
    assert_eq!(k.positions_at(4.0), f2);
    // Midpoints.
    let mid = k.positions_at(3.0);
    for i in 0..3 {
        assert!(mid[i].abs_diff_eq((f1[i] + f2[i]) * 0.5, 1e-6));
    }
    let q = k.positions_at(1.25);
    assert!(q[1].abs_diff_eq(f0[1] * 0.75 + f1[1] * 0.25, 1e-6));
    // Clamped.
    assert_eq!(k.positions_at(-5.0), f0);
    assert_eq!(k.positions_at(100.0), f2);
    assert_eq!(k.positions_at(f32::NAN), f0);
    // Into a caller buffer: no reallocation.
    let mut buf = Vec::with_capacity(3);
    let p = buf.as_ptr();
    for t in [1.0, 1.5, 3.3, 9.0] {
        k.positions_into(t, &mut buf);
        assert_eq!(buf.len(), 3);
        assert_eq!(buf.as_ptr(), p);
    }
    assert_eq!(k.mesh_at(2.0).unwrap().positions, f1);
    // Applied to a scene.
    let mut s = Scene::new();
    let id = s.add_object(k.mesh_at(1.0).unwrap()).unwrap();
    let mut anim = SceneAnimation::new();
    anim.add_mesh(id, k.clone()).unwrap();
    anim.apply(&mut s, 3.0).unwrap();
    assert_eq!(s.mesh(id).unwrap().positions, mid);
}

#[test]
fn animated_transform_interpolates() {
    let a = Affine3A::from_scale_rotation_translation(
        Vec3::new(1.0, 2.0, 1.0),
        Quat::IDENTITY,
        Vec3::new(0.0, 0.0, 0.0),
    );
    let b = Affine3A::from_scale_rotation_translation(
        Vec3::new(3.0, 2.0, 1.0),
        Quat::from_rotation_y(std::f32::consts::FRAC_PI_2),
        Vec3::new(10.0, -4.0, 2.0),
    );
    let x = AnimatedTransform::new(vec![(0.0, a), (2.0, b)]).unwrap();
    assert_eq!(x.at(0.0), a);
    assert_eq!(x.at(2.0), b);
    assert_eq!(x.at(-1.0), a);
    assert_eq!(x.at(7.0), b);
    let (s, r, t) = x.at(1.0).to_scale_rotation_translation();
    assert!(s.abs_diff_eq(Vec3::new(2.0, 2.0, 1.0), 1e-5), "{s}");
    assert!(t.abs_diff_eq(Vec3::new(5.0, -2.0, 1.0), 1e-5), "{t}");
    let want = Quat::from_rotation_y(std::f32::consts::FRAC_PI_4);
    assert!(r.dot(want).abs() > 1.0 - 1e-5, "{r}");
    // Shorter arc: 350 degrees from 0 goes back by 10.
    let c = AnimatedTransform::new(vec![
        (0.0, Affine3A::IDENTITY),
        (1.0, Affine3A::from_rotation_y(350f32.to_radians())),
    ])
    .unwrap();
    let (_, r, _) = c.at(0.5).to_scale_rotation_translation();
    assert!(
        r.dot(Quat::from_rotation_y(-5f32.to_radians())).abs() > 1.0 - 1e-5,
        "{r}"
    );
    // Applied to a scene.
    let mut scene = Scene::new();
    let o = scene
        .add_prototype(TriangleMesh::from_triangles(&[[Vec3::ZERO, Vec3::X, Vec3::Y]]).unwrap())
        .unwrap();
    let i = scene.add_instance(o, a).unwrap();
    rebraid::animation::apply_animated_transform(&mut scene, i, &x, 2.0).unwrap();
    assert_eq!(scene.instance_transform(i).unwrap(), b);
    assert!(rebraid::animation::apply_animated_transform(&mut scene, 42, &x, 0.0).is_err());
}

/// The re-braided top level copies the triangle blocks of the object leaves
/// it enters directly (`RebraidParams::inline_leaf_blocks`); a scene
/// committed again hands the previous copies' buffer, and the rest of its
/// layout's arrays (collapsed nodes, entries, per-block placements), to
/// the next top level instead of allocating (and paging in) others.
#[test]
fn layout_arrays_reuse_the_previous_commits_buffers() {
    // One top level over everything, rebuilt at each commit (without
    // reinsertion, whose moves may add a few blocks after the small move
    // below: the test wants the same structure built again).
    let mut s = Scene::with_params(SceneParams {
        mode: AccelMode::Rebraided,
        rebraid: RebraidParams {
            moving_hold_commits: 0,
            reinsert: rebraid::bvh::ReinsertParams::OFF,
            ..Default::default()
        },
        ..Default::default()
    });
    let m = wavy_grid(40, 0.0, 0.0);
    let id = s.add_object(m.clone()).unwrap();
    s.add_object(wavy_grid(40, 1.0, 0.5)).unwrap();
    s.set_update_policy(id, UpdatePolicy::Refit).unwrap();
    s.commit().unwrap();
    let blocks = |s: &Scene| match s.accel() {
        Accel::TopLevel(t) => (t.blocks.as_ptr(), t.blocks.len()),
        _ => panic!("re-braided"),
    };
    // The other arrays' addresses, and their lengths.
    let others = |s: &Scene| match s.accel() {
        Accel::TopLevel(t) => {
            let w = t.wide.as_ref().expect("a wide top level");
            (
                [
                    w.nodes.as_ptr() as usize,
                    t.entries.as_ptr() as usize,
                    t.entry_refs.as_ptr() as usize,
                    t.block_entry.as_ptr() as usize,
                    t.block_placement.as_ptr() as usize,
                    t.block_normal_scale.as_ptr() as usize,
                ],
                [w.nodes.len(), t.entries.len()],
            )
        }
        _ => panic!("re-braided"),
    };
    let (p0, n0) = blocks(&s);
    let (q0, m0) = others(&s);
    assert!(n0 > 0, "the overlapping grids open down to leaves");
    let moved: Vec<Vec3> = m.positions.iter().map(|p| *p + Vec3::Y * 0.01).collect();
    s.set_vertices(id, &moved).unwrap();
    s.commit().unwrap();
    let (p1, n1) = blocks(&s);
    let (q1, m1) = others(&s);
    // A small move: as many blocks copied (or fewer), into the old buffer.
    assert!(n1 > 0 && n1 <= n0, "{n1} blocks after {n0}");
    assert_eq!(p1, p0, "the buffer was not reused");
    // As many nodes and entries (or fewer), in the old arrays.
    assert!(m1[0] <= m0[0] && m1[1] <= m0[1], "{m1:?} after {m0:?}");
    assert_eq!(q1, q0, "the layout's arrays were not reused");
    // Without buffer reuse the scratch keeps nothing.
    s.set_reuse_top_level_buffers(false);
    s.set_vertices(id, &m.positions).unwrap();
    s.commit().unwrap();
    assert_eq!(s.top_level_buffer_bytes(), 0);
}
