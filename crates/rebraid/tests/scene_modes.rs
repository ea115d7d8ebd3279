//! Every acceleration mode of a scene against a world-space brute force:
//! random multi-object scenes with instances (rotations, shears,
//! non-uniform and mirroring scales), the heavy-overlap "library" case, and
//! normals. Issue "Scenes of many objects".

mod scene_common;

use rebraid::glam::{Affine3A, Vec3};
use rebraid::scene::Accel;
use rebraid::{AccelMode, Hit, INVALID_ID, Ray, Scene, SceneParams, TriangleMesh};
use scene_common::*;

fn params(mode: AccelMode) -> SceneParams {
    SceneParams {
        mode,
        ..Default::default()
    }
}

/// Build the model's scene in every mode with every traversal kernel this
/// CPU runs (scalar, SSE, AVX2) and check each against the brute force (flat
/// mode bit-exactly, the two-level modes up to instance rounding).
fn all_modes_vs_brute(model: &Model, rays: &[Ray], what: &str) {
    for kernel in rebraid::bvh::Kernel::available() {
        let mut p = params(AccelMode::Flat);
        p.kernel = Some(kernel);
        all_modes_vs_brute_with(model, rays, &format!("{what} {kernel:?}"), p);
    }
}

fn all_modes_vs_brute_with(model: &Model, rays: &[Ray], what: &str, params: SceneParams) {
    let world = model.world();
    let mut scene = model.to_scene(params);
    for mode in AccelMode::ALL {
        scene.set_mode(mode);
        let rep = scene.commit().unwrap();
        assert_eq!(rep.mode, mode);
        if mode != AccelMode::Flat {
            check_top(top(&scene), model, &format!("{what} {mode:?}"));
        } else {
            assert!(matches!(scene.accel(), Accel::Flat(_)));
        }
        let exact = mode == AccelMode::Flat || model.instances.is_empty();
        let tally = check_scene(&scene, &world, rays, exact, &format!("{what} {mode:?}"));
        // The rays must actually test something.
        assert!(tally.hits * 4 >= rays.len(), "{what} {mode:?}: {tally:?}");
        eprintln!("{what} {mode:?}: {tally:?}");
    }
}

/// Clustered objects, grids and mirrored instances: heavy overlap.
fn clustered_with_instances() -> Gen {
    Gen {
        clustered: 10,
        scattered: 0,
        grids: 2,
        prototypes: 3,
        instances: 25,
        tris: 80,
        mirror: true,
    }
}

#[test]
fn random_instanced_scenes_match_brute_force_in_every_mode() {
    let shapes = [
        Gen::default(),
        clustered_with_instances(),
        Gen {
            clustered: 3,
            scattered: 1,
            grids: 0,
            prototypes: 1,
            instances: 8,
            tris: 200,
            mirror: false,
        },
        // Instances only (no placed objects).
        Gen {
            clustered: 0,
            scattered: 0,
            grids: 0,
            prototypes: 3,
            instances: 20,
            tris: 120,
            mirror: true,
        },
    ];
    for (seed, g) in shapes.iter().enumerate() {
        let mut rng = rng(100 + seed as u64);
        let model = random_model(&mut rng, g);
        let world = model.world();
        let rays = random_rays(&mut rng, &world, 1500, SCENE_LO, SCENE_HI);
        all_modes_vs_brute(&model, &rays, &format!("seed {seed}"));
    }
}

/// Coherent rays, as shadow rays towards one light are: the batch
/// occlusion query traces them in packets of eight (AVX2 kernel), where
/// each packet's rays share nodes until few remain in a subtree. Every
/// answer is the single-ray one and the brute force's, in every mode and
/// with every kernel; rays parallel to an axis (which cannot join a packet)
/// are mixed in, and each light's rays come in all eight octants.
#[test]
fn coherent_rays_in_packets_match_brute_force_in_every_mode() {
    for (seed, g) in [Gen::default(), clustered_with_instances()]
        .iter()
        .enumerate()
    {
        let mut rng = rng(300 + seed as u64);
        let model = random_model(&mut rng, g);
        let mut rays = Vec::new();
        let span = SCENE_HI - SCENE_LO;
        for light in [
            SCENE_LO + span * Vec3::new(0.5, 1.3, 0.5),
            SCENE_LO + span * Vec3::new(0.4, 0.5, 0.6),
        ] {
            // Origins on a grid through the scene, in pixel order.
            for i in 0..40 {
                for j in 0..30 {
                    let o = SCENE_LO
                        + span * Vec3::new(i as f32 / 39.0, 0.1 + 0.02 * j as f32, j as f32 / 29.0);
                    let d = light - o;
                    let d = if (i + j) % 37 == 0 {
                        Vec3::new(0.0, d.y, d.z)
                    } else {
                        d
                    };
                    rays.push(Ray {
                        origin: o,
                        t_min: 1e-3,
                        dir: d,
                        t_max: 1.0,
                    });
                }
            }
        }
        all_modes_vs_brute(&model, &rays, &format!("coherent seed {seed}"));
    }
}

/// Camera rays from `eye` through a 64 x 48 grid of points at height `y`
/// over the scene's floor, in pixel order (rows of neighbouring
/// directions: the closest-hit batch traces them in packets).
fn camera_rays(eye: Vec3, y: f32) -> Vec<Ray> {
    (0..48)
        .flat_map(|row| (0..64).map(move |col| (row, col)))
        .map(|(row, col)| {
            let target = Vec3::new(
                2.0 + 16.0 * col as f32 / 63.0,
                y,
                2.0 + 16.0 * row as f32 / 47.0,
            );
            Ray {
                origin: eye,
                t_min: 0.0,
                dir: target - eye,
                t_max: f32::INFINITY,
            }
        })
        .collect()
}

/// Camera rays (closest-hit packets through the top level, into objects
/// placed directly and lane by lane into instances, mirrored ones
/// included; rays with a zero direction component mixed in) over random
/// scenes from outside and from inside: every
/// answer is the single-ray one and the brute force's, in every mode and
/// with every kernel.
#[test]
fn camera_rays_in_packets_match_brute_force_in_every_mode() {
    for (seed, g) in [Gen::default(), clustered_with_instances()]
        .iter()
        .enumerate()
    {
        let mut rng = rng(600 + seed as u64);
        let model = random_model(&mut rng, g);
        let mut rays = camera_rays(Vec3::new(9.3, 30.0, 11.1), 8.0);
        rays.extend(camera_rays(Vec3::new(10.7, 12.0, 9.2), 0.0));
        // A ray with a zero direction component cannot join a packet: the
        // packet it would have been in goes ray by ray.
        for r in rays.iter_mut().step_by(37) {
            r.dir.x = 0.0;
        }
        all_modes_vs_brute(&model, &rays, &format!("camera seed {seed}"));
    }
}

/// Exact ties: a height-field grid repeated as coincident surfaces (in two
/// objects whose other triangles differ, so their trees differ, and twice
/// within a third), seen by camera rays in pixel order, which the
/// closest-hit batch traces in packets (AVX2 kernel) that visit leaves in
/// the packet's order rather than each ray's own. Every answer, triangle
/// included, must be the single-ray one (`check_scene` compares them
/// exactly) and a brute-force hit at the closest distance, in every mode
/// and with every kernel; most rays must meet a tie.
#[test]
fn exact_ties_answer_alike_in_packets_and_alone() {
    let mut rng = rng(500);
    let g = grid(
        &mut rng,
        12,
        12,
        Vec3::new(2.0, 4.0, 2.0),
        Vec3::new(18.0, 6.0, 18.0),
    );
    let tris = |m: &TriangleMesh| (0..m.len()).map(|i| m.triangle(i)).collect::<Vec<_>>();
    let grid_tris = tris(&g);
    let with_soup = |rng: &mut _, lo: Vec3, hi: Vec3| {
        let mut t = tris(&soup(rng, 60, lo, hi, 1.5));
        t.extend(&grid_tris);
        t.extend(tris(&soup(rng, 60, lo, hi, 1.5)));
        TriangleMesh::from_triangles(&t).unwrap()
    };
    let mut model = Model::default();
    let a = with_soup(
        &mut rng,
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::new(20.0, 3.0, 8.0),
    );
    let b = with_soup(
        &mut rng,
        Vec3::new(0.0, 0.0, 12.0),
        Vec3::new(20.0, 3.0, 20.0),
    );
    let mut twice = grid_tris.clone();
    twice.extend(&grid_tris);
    model.objects.insert(0, (a, true));
    model.objects.insert(1, (b, true));
    model
        .objects
        .insert(2, (TriangleMesh::from_triangles(&twice).unwrap(), true));
    let world = model.world();
    let rays = camera_rays(Vec3::new(9.3, 30.0, 11.1), 5.0);
    let ties = rays
        .iter()
        .filter(|r| {
            let all = world.all_hits(r);
            let t = all.iter().map(|h| h.t).fold(f32::INFINITY, f32::min);
            all.iter().filter(|h| h.t == t).count() >= 2
        })
        .count();
    assert!(
        ties * 2 > rays.len(),
        "{ties} of {} rays meet a tie",
        rays.len()
    );
    all_modes_vs_brute(&model, &rays, "exact ties");
}

/// Object BVHs with leaves larger than a wide leaf holds keep the binary
/// layout (the traversal's scalar fallback, whose hits name leaf-order
/// slots rather than block lanes): hits, primitive ids and normals still
/// match the brute force in every mode and with every kernel, for placed
/// and instanced objects alike.
#[test]
fn objects_without_the_wide_layout_match_brute_force_in_every_mode() {
    let mut rng = rng(41);
    let model = random_model(
        &mut rng,
        &Gen {
            clustered: 4,
            scattered: 1,
            grids: 1,
            prototypes: 2,
            instances: 10,
            tris: 150,
            mirror: true,
        },
    );
    let world = model.world();
    let rays = random_rays(&mut rng, &world, 1500, SCENE_LO, SCENE_HI);
    for kernel in rebraid::bvh::Kernel::available() {
        let mut p = params(AccelMode::Flat);
        p.kernel = Some(kernel);
        // Leaves of up to 40 triangles: larger than a wide leaf's 16, and
        // the SAH makes them in some objects (a cheap intersection).
        p.object_build.max_leaf_size = 40;
        p.object_build.intersection_cost = 0.6;
        let mut scene = model.to_scene(p.clone());
        scene.set_mode(AccelMode::Rebraided);
        scene.commit().unwrap();
        let objects = &top(&scene).objects;
        let binary = objects
            .iter()
            .flatten()
            .filter(|o| o.wide.is_none())
            .count();
        assert!(
            binary > 0 && binary < objects.iter().flatten().count(),
            "{binary} of {} objects without the wide layout",
            objects.len()
        );
        all_modes_vs_brute_with(&model, &rays, &format!("large leaves {kernel:?}"), p);
    }
}

#[test]
fn objects_without_instances_are_bit_identical_across_modes() {
    let mut rng = rng(7);
    let model = random_model(
        &mut rng,
        &Gen {
            prototypes: 0,
            instances: 0,
            clustered: 8,
            scattered: 2,
            grids: 2,
            ..Gen::default()
        },
    );
    let world = model.world();
    let rays = random_rays(&mut rng, &world, 2000, SCENE_LO, SCENE_HI);
    let mut scene = model.to_scene(params(AccelMode::Flat));
    let mut answers: Vec<Vec<Option<Hit>>> = Vec::new();
    for mode in AccelMode::ALL {
        scene.set_mode(mode);
        scene.commit().unwrap();
        let mut hits = vec![None; rays.len()];
        scene.intersect_batch(&rays, &mut hits);
        check_scene(&scene, &world, &rays, true, &format!("{mode:?}"));
        answers.push(hits);
    }
    for (m, hits) in answers.iter().enumerate().skip(1) {
        for (i, (a, b)) in answers[0].iter().zip(hits).enumerate() {
            // Same t bit for bit; a different triangle only on an exact tie.
            assert_eq!(a.map(|h| h.t), b.map(|h| h.t), "mode {m} ray {i}");
            if let (Some(a), Some(b)) = (a, b)
                && (a.object_id, a.prim_id) != (b.object_id, b.prim_id)
            {
                let all = world.all_hits(&rays[i]);
                assert!(
                    all.iter()
                        .any(|h| (h.object, h.prim) == (b.object_id, b.prim_id) && h.t == a.t),
                    "mode {m} ray {i}: {a:?} vs {b:?} is no tie"
                );
            }
        }
    }
}

/// The library incident: every object's triangles are scattered over the
/// whole scene box, so every object box is the scene box.
fn library_model(seed: u64, objects: usize, tris: usize, instances: usize) -> Model {
    let mut rng = rng(seed);
    let mut m = Model::default();
    for i in 0..objects as u32 {
        let mesh = soup(&mut rng, tris, SCENE_LO, SCENE_HI, 0.7);
        m.objects.insert(i, (mesh, true));
    }
    if instances > 0 {
        // A scattered prototype, placed by instances that each span the
        // scene (rotated, scaled about the scene's centre).
        let proto = objects as u32;
        let h = (SCENE_HI - SCENE_LO) * 0.5;
        m.objects
            .insert(proto, (soup(&mut rng, tris, -h, h, 0.7), false));
        for i in 0..instances as u32 {
            let xf = random_transform(&mut rng, SCENE_LO + h - 1.0, SCENE_LO + h + 1.0, true);
            m.instances.insert(i, (proto, xf));
        }
    }
    m
}

#[test]
fn heavy_overlap_rebraided_matches_flat_and_brute_force() {
    // Without instances: bit-identical answers.
    let model = library_model(11, 24, 250, 0);
    let world = model.world();
    let mut rng = rng(12);
    let rays = random_rays(&mut rng, &world, 2000, SCENE_LO, SCENE_HI);
    let mut scene = model.to_scene(params(AccelMode::Flat));
    scene.commit().unwrap();
    let mut flat = vec![None; rays.len()];
    scene.intersect_batch(&rays, &mut flat);
    scene.set_mode(AccelMode::Rebraided);
    let rep = scene.commit().unwrap();
    let st = rep.top.clone().unwrap();
    assert!(
        st.nodes_opened > 0,
        "the library scene must be re-braided: {st:?}"
    );
    check_top(top(&scene), &model, "library");
    check_scene(&scene, &world, &rays, true, "library rebraided");
    for (i, r) in rays.iter().enumerate() {
        let h = scene.intersect(r);
        assert_eq!(h.map(|h| h.t), flat[i].map(|h| h.t), "ray {i}");
        if h != flat[i] {
            // Only an exact tie may pick another triangle.
            let (a, b) = (h.unwrap(), flat[i].unwrap());
            let all = world.all_hits(r);
            assert!(
                all.iter()
                    .any(|x| (x.object, x.prim) == (a.object_id, a.prim_id) && x.t == b.t),
                "ray {i}: {a:?} vs flat {b:?}"
            );
        }
    }

    // With scattered instances.
    let model = library_model(13, 12, 200, 10);
    let world = model.world();
    let rays = random_rays(&mut rng, &world, 1500, SCENE_LO, SCENE_HI);
    all_modes_vs_brute(&model, &rays, "library+instances");
}

#[test]
fn mirrored_instance_normals_follow_world_winding() {
    // One triangle facing +z in object space, in the plane z = 1.
    let tri = TriangleMesh::from_triangles(&[[
        Vec3::new(0.0, 0.0, 1.0),
        Vec3::new(1.0, 0.0, 1.0),
        Vec3::new(0.0, 1.0, 1.0),
    ]])
    .unwrap();
    let cases = [
        (Affine3A::IDENTITY, Vec3::Z),
        // Mirror in x: the winding flips, so does the normal.
        (Affine3A::from_scale(Vec3::new(-1.0, 1.0, 1.0)), -Vec3::Z),
        // Mirror in z: the plane moves to z = -1, its winding seen from +z
        // is unchanged, so is the normal.
        (Affine3A::from_scale(Vec3::new(1.0, 1.0, -1.0)), Vec3::Z),
        // Mirror in x and z.
        (Affine3A::from_scale(Vec3::new(-1.0, 1.0, -2.0)), -Vec3::Z),
        // Non-uniform scale keeps the orientation.
        (Affine3A::from_scale(Vec3::new(3.0, 0.5, 2.0)), Vec3::Z),
        // Shear: the normal is the world cross product, not the transformed normal.
        (
            Affine3A::from_cols_array(&[
                1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.8, 0.0, 1.0, 0.0, 0.0, 0.0,
            ]),
            Vec3::Z,
        ),
        (
            Affine3A::from_cols_array(&[
                1.0, 0.0, 0.5, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0,
            ]),
            Vec3::new(-0.5, 0.0, 1.0).normalize(),
        ),
    ];
    for mode in AccelMode::ALL {
        for (k, (xf, want)) in cases.iter().enumerate() {
            let mut s = Scene::with_params(params(mode));
            let p = s.add_prototype(tri.clone()).unwrap();
            let inst = s.add_instance(p, *xf).unwrap();
            s.commit().unwrap();
            let target = xf.transform_point3(Vec3::new(0.25, 0.25, 1.0));
            for from in [
                target + Vec3::new(0.1, 0.2, 3.0),
                target - Vec3::new(0.1, -0.2, 3.0),
            ] {
                let ray = Ray::infinite(from, target - from);
                let h = s
                    .intersect(&ray)
                    .unwrap_or_else(|| panic!("{mode:?} case {k}: no hit"));
                assert_eq!((h.object_id, h.instance_id, h.prim_id), (p, inst, 0));
                assert!((h.t - 1.0).abs() < 1e-5, "{mode:?} case {k}: t {}", h.t);
                assert!(
                    (h.unit_normal() - *want).length() < 1e-5,
                    "{mode:?} case {k}: normal {:?}, want {want:?}",
                    h.normal
                );
            }
        }
    }
}

/// `Hit::normal` is not normalised (as Embree's `Ng`): a directly placed
/// triangle's is the world cross product of its edges, twice its area long;
/// through an instance it points the same way as the placed triangle's;
/// `unit_normal` is its unit vector. Packets and single rays alike.
#[test]
fn hit_normals_are_geometric_not_unit() {
    // Area 3 (legs 2 and 3), facing +z, in the plane z = 1.
    let tri = TriangleMesh::from_triangles(&[[
        Vec3::new(0.0, 0.0, 1.0),
        Vec3::new(2.0, 0.0, 1.0),
        Vec3::new(0.0, 3.0, 1.0),
    ]])
    .unwrap();
    let xf = Affine3A::from_scale_rotation_translation(
        Vec3::new(2.0, 0.5, 1.5),
        rebraid::glam::Quat::from_rotation_x(0.4),
        Vec3::new(5.0, 0.0, 0.0),
    );
    for mode in AccelMode::ALL {
        let mut s = Scene::with_params(params(mode));
        s.add_object(tri.clone()).unwrap();
        let p = s.add_prototype(tri.clone()).unwrap();
        s.add_instance(p, xf).unwrap();
        // A second instance, so that the prototype is not baked into world
        // space and the first one's hits take the instance transform.
        s.add_instance(p, Affine3A::from_translation(Vec3::new(-50.0, 0.0, 0.0)))
            .unwrap();
        s.commit().unwrap();
        // Eight rays (one packet) at the direct triangle, then at the
        // instance's.
        let direct: Vec<Ray> = (0..8)
            .map(|i| Ray::infinite(Vec3::new(0.2 + 0.1 * i as f32, 0.3, 4.0), -Vec3::Z))
            .collect();
        let world_n = xf
            .transform_vector3(Vec3::new(2.0, 0.0, 0.0))
            .cross(xf.transform_vector3(Vec3::new(0.0, 3.0, 0.0)));
        let target = xf.transform_point3(Vec3::new(0.3, 0.4, 1.0));
        let placed: Vec<Ray> = (0..8)
            .map(|i| {
                let from = target + world_n.normalize() * (2.0 + 0.1 * i as f32);
                Ray::infinite(from, target - from)
            })
            .collect();
        for (rays, want) in [(&direct, Vec3::new(0.0, 0.0, 6.0)), (&placed, world_n)] {
            let mut batch = vec![None; rays.len()];
            s.intersect_batch(rays, &mut batch);
            for (r, b) in rays.iter().zip(&batch) {
                let h = s.intersect(r).unwrap_or_else(|| panic!("{mode:?}: no hit"));
                assert_eq!(Some(h), *b, "{mode:?}: batch and single ray differ");
                assert!(
                    (h.unit_normal() - want.normalize()).length() < 1e-5,
                    "{mode:?}: normal {:?}, want along {want:?}",
                    h.normal
                );
                assert!((h.unit_normal().length() - 1.0).abs() < 1e-6);
                if h.instance_id == INVALID_ID || mode == AccelMode::Flat {
                    // Placed directly, or traced in flat mode (which bakes
                    // every instance into world space): the world cross
                    // product itself.
                    assert!(
                        (h.normal - want).length() < 1e-4 * want.length(),
                        "{mode:?}: normal {:?}, want {want:?}",
                        h.normal
                    );
                }
            }
        }
    }
}

#[test]
fn directly_placed_hits_have_no_instance_id() {
    let mut rng = rng(21);
    let model = random_model(&mut rng, &Gen::default());
    let world = model.world();
    let rays = random_rays(&mut rng, &world, 800, SCENE_LO, SCENE_HI);
    let mut scene = model.to_scene(params(AccelMode::Rebraided));
    scene.commit().unwrap();
    let mut seen = (0, 0);
    for r in &rays {
        if let Some(h) = scene.intersect(r) {
            let (_, placed) = &model.objects[&h.object_id];
            if h.instance_id == INVALID_ID {
                assert!(placed, "{h:?}: a prototype hit without an instance");
                seen.0 += 1;
            } else {
                assert_eq!(model.instances[&h.instance_id].0, h.object_id, "{h:?}");
                seen.1 += 1;
            }
        }
    }
    assert!(seen.0 > 0 && seen.1 > 0, "{seen:?}");
}

#[test]
fn invalid_rays_hit_nothing_in_every_mode() {
    let mut rng = rng(5);
    let model = random_model(&mut rng, &Gen::default());
    let world = model.world();
    let mut scene = model.to_scene(params(AccelMode::Flat));
    let c = (SCENE_LO + SCENE_HI) * 0.5;
    let bad = [
        Ray::infinite(c, Vec3::ZERO),
        Ray::infinite(c, Vec3::new(f32::NAN, 1.0, 0.0)),
        Ray::infinite(Vec3::new(f32::INFINITY, 0.0, 0.0), Vec3::X),
        Ray {
            origin: c,
            dir: Vec3::X,
            t_min: 5.0,
            t_max: 1.0,
        },
        Ray {
            origin: c,
            dir: Vec3::X,
            t_min: f32::NAN,
            t_max: 1.0,
        },
    ];
    for mode in AccelMode::ALL {
        scene.set_mode(mode);
        scene.commit().unwrap();
        for r in &bad {
            assert_eq!(scene.intersect(r), None, "{mode:?} {r:?}");
            assert!(!scene.occluded(r), "{mode:?} {r:?}");
        }
        let mut out = vec![Some(Hit::NONE); bad.len()];
        scene.intersect_batch(&bad, &mut out);
        assert!(out.iter().all(|h| h.is_none()));
        // Mixed into a batch of valid rays that spans several runs (the
        // batch queries answer runs of rays in one kernel call): every ray
        // is answered as alone.
        let mixed: Vec<Ray> = random_rays(&mut rng, &world, 700, SCENE_LO, SCENE_HI)
            .into_iter()
            .enumerate()
            .map(|(i, r)| if i % 7 == 3 { bad[i % bad.len()] } else { r })
            .collect();
        let mut hits = vec![Some(Hit::NONE); mixed.len()];
        scene.intersect_batch(&mixed, &mut hits);
        let mut occ = vec![true; mixed.len()];
        scene.occluded_batch(&mixed, &mut occ);
        for (i, r) in mixed.iter().enumerate() {
            assert_eq!(hits[i], scene.intersect(r), "{mode:?} ray {i}");
            assert_eq!(occ[i], scene.occluded(r), "{mode:?} ray {i}");
        }
        assert!(hits.iter().filter(|h| h.is_some()).count() * 4 >= mixed.len());
    }
}

/// The counted queries answer as the plain ones do, in every mode, and count
/// the nodes they visit: a ray that hits nothing visits the same nodes and
/// leaves whether it asks for the closest hit or for any hit.
#[test]
fn counted_queries_agree_with_the_plain_ones() {
    use rebraid::bvh::TraversalCounters;
    let mut rng = rng(17);
    let model = random_model(&mut rng, &Gen::default());
    let world = model.world();
    let rays = random_rays(&mut rng, &world, 400, SCENE_LO, SCENE_HI);
    let mut scene = model.to_scene(params(AccelMode::Flat));
    for mode in AccelMode::ALL {
        scene.set_mode(mode);
        scene.commit().unwrap();
        let (mut total, mut misses) = (TraversalCounters::default(), 0);
        for r in &rays {
            let (mut closest, mut any) =
                (TraversalCounters::default(), TraversalCounters::default());
            let hit = scene.intersect_counted(r, &mut closest);
            assert_eq!(hit, scene.intersect(r), "{mode:?}");
            let occluded = scene.occluded_counted(r, &mut any);
            assert_eq!(occluded, scene.occluded(r), "{mode:?}");
            if !occluded {
                assert_eq!(
                    (any.inner_visited, any.leaves_visited),
                    (closest.inner_visited, closest.leaves_visited),
                    "{mode:?}: a miss visits the same nodes either way"
                );
                misses += 1;
            }
            total.inner_visited += closest.inner_visited;
        }
        assert!(total.inner_visited > 0, "{mode:?}");
        assert!(
            misses > 0 && misses < rays.len(),
            "{mode:?}: {misses} misses"
        );
    }
}

/// A top-level leaf whose object leaf's blocks were copied into the top
/// level (`RebraidParams::inline_leaf_blocks`) is one leaf visit, as in a
/// flat BVH: no entry into the object is made, so none is counted.
#[test]
fn a_copied_object_leaf_counts_as_one_leaf() {
    use rebraid::bvh::TraversalCounters;
    let tri = |x: f32| {
        TriangleMesh::from_triangles(&[[
            Vec3::new(x, 0.0, 0.0),
            Vec3::new(x + 1.0, 0.0, 0.0),
            Vec3::new(x, 1.0, 0.0),
        ]])
        .unwrap()
    };
    let mut scene = Scene::with_params(params(AccelMode::Rebraided));
    scene.add_object(tri(0.0)).unwrap();
    scene.add_object(tri(10.0)).unwrap();
    scene.commit().unwrap();
    let ray = Ray::new(Vec3::new(0.25, 0.25, 1.0), Vec3::NEG_Z, 0.0, f32::INFINITY).unwrap();
    let mut counted = TraversalCounters::default();
    let hit = scene
        .intersect_counted(&ray, &mut counted)
        .expect("hits the first");
    assert_eq!(hit.object_id, 0);
    // The root (two leaf slots) and the one leaf the ray enters.
    assert_eq!((counted.inner_visited, counted.leaves_visited), (1, 1));
}

/// The scenes and rays the tree-shaping options (reinsertion, the collapse
/// rule) are checked on: clustered random objects with instances and the
/// library case with instances (seeds `seed`, `seed + 1`), random rays
/// (`seed + 2`) and camera rays.
fn tree_option_cases(seed: u64) -> [(Model, &'static str, Vec<Ray>); 2] {
    let with_rays = |model: Model, what| {
        let mut rays = random_rays(&mut rng(seed + 2), &model.world(), 1200, SCENE_LO, SCENE_HI);
        rays.extend(camera_rays(Vec3::new(9.3, 30.0, 11.1), 8.0));
        (model, what, rays)
    };
    [
        with_rays(
            random_model(&mut rng(seed), &clustered_with_instances()),
            "clustered",
        ),
        with_rays(library_model(seed + 1, 16, 200, 4), "library+instances"),
    ]
}

/// The statistics of `model`'s scene built with `p` and committed in `mode`:
/// how the tree-option tests see that an option reached the trees.
fn committed_stats(model: &Model, p: SceneParams, mode: AccelMode) -> rebraid::SceneStats {
    let mut scene = model.to_scene(p);
    scene.set_mode(mode);
    scene.commit().unwrap();
    scene.stats()
}

/// Reinsertion over every object and flat BVH (`BuildParams::reinsert`)
/// and a heavy one over the re-braided top level, with every kernel: the
/// trees change, the answers do not.
#[test]
fn reinserted_trees_match_brute_force_in_every_mode() {
    let reinserted = |kernel| {
        let mut p = SceneParams {
            kernel: Some(kernel),
            ..params(AccelMode::Flat)
        };
        p.object_build.reinsert = rebraid::bvh::ReinsertParams::share(0.5, 4);
        p.rebraid.reinsert = rebraid::bvh::ReinsertParams::share(1.0, 8);
        p
    };
    for (model, what, rays) in &tree_option_cases(950) {
        for kernel in rebraid::bvh::Kernel::available() {
            let what = format!("reinserted {what} {kernel:?}");
            all_modes_vs_brute_with(model, rays, &what, reinserted(kernel));
        }
        // The option reaches the trees: the object trees' SAH is lower.
        let sah = |p| committed_stats(model, p, AccelMode::Flat).sah_cost;
        let best = rebraid::bvh::Kernel::best();
        let plain = sah(params(AccelMode::Flat));
        let better = sah(reinserted(best));
        assert!(better < plain, "{what}: flat SAH {plain} -> {better}");
    }
}

/// The flat and merged builds with and without
/// `BuildParams::large_leaf_split` (on by default), with every kernel: the
/// same answers as the brute force, on the tree-option cases and on a room
/// whose floor and ceiling the rule splits; and the rule reaches the room's
/// flat tree (a lower wide SAH cost: the slabs leave the room-sized leaf).
#[test]
fn large_leaf_split_on_and_off_match_brute_force_in_every_mode() {
    let with = |kernel, merge_placed, rule: bool| {
        let mut p = SceneParams {
            kernel: Some(kernel),
            merge_placed,
            ..params(AccelMode::Flat)
        };
        if !rule {
            p.object_build.large_leaf_split = None;
        }
        p
    };
    let mut cases: Vec<_> = tree_option_cases(970).into_iter().collect();
    let room = room_model(971);
    let rays = random_rays(
        &mut rng(972),
        &room.world(),
        1200,
        SCENE_LO,
        SCENE_HI.with_y(4.0),
    );
    cases.push((room, "room", rays));
    for (model, what, rays) in &cases {
        for kernel in rebraid::bvh::Kernel::available() {
            for merge in [false, true] {
                for rule in [false, true] {
                    let what =
                        format!("large-leaf split {rule}, merged {merge}, {what} {kernel:?}");
                    all_modes_vs_brute_with(model, rays, &what, with(kernel, merge, rule));
                }
            }
        }
        // With `scene_volume_leaf_limit` off, which splits the room's leaf
        // too (it holds the room's volume).
        let wide_sah = |mut p: SceneParams| {
            p.object_build.scene_volume_leaf_limit = None;
            committed_stats(model, p, AccelMode::Flat).wide_sah_cost
        };
        let best = rebraid::bvh::Kernel::best();
        let (on, off) = (
            wide_sah(with(best, false, true)),
            wide_sah(with(best, false, false)),
        );
        eprintln!("{what}: flat wide SAH with the rule {on:.4}, without {off:.4}");
        if *what == "room" {
            assert!(on < off, "{what}: the rule did not split the room's leaf");
        }
    }
}

/// Every mode with and without `BuildParams::scene_volume_leaf_limit` (on
/// by default), with every kernel: the brute force's answers on the room,
/// whose floor and ceiling leaf holds the room's volume; and the limit
/// reaches the flat tree and the object trees of the two-level modes (the
/// room's slabs are an object placed directly, whose BVH is measured
/// against the scene's volume).
#[test]
fn scene_volume_leaf_limit_on_and_off_match_brute_force_in_every_mode() {
    let with = |kernel, mode, limit: bool| {
        let mut p = SceneParams {
            kernel: Some(kernel),
            ..params(mode)
        };
        // The large-leaf rule off: it would split the flat tree's leaf too.
        p.object_build.large_leaf_split = None;
        if !limit {
            p.object_build.scene_volume_leaf_limit = None;
        }
        p
    };
    let room = room_model(973);
    let rays = random_rays(
        &mut rng(974),
        &room.world(),
        1200,
        SCENE_LO,
        SCENE_HI.with_y(4.0),
    );
    for kernel in rebraid::bvh::Kernel::available() {
        for limit in [false, true] {
            let what = format!("scene-volume leaf limit {limit}, room {kernel:?}");
            all_modes_vs_brute_with(&room, &rays, &what, with(kernel, AccelMode::Flat, limit));
        }
    }
    let best = rebraid::bvh::Kernel::best();
    for mode in [AccelMode::Flat, AccelMode::TwoLevel, AccelMode::Rebraided] {
        let wide_sah = |limit| committed_stats(&room, with(best, mode, limit), mode).wide_sah_cost;
        let (on, off) = (wide_sah(true), wide_sah(false));
        assert!(
            on != off,
            "{mode:?}: the limit did not reach the room's leaf ({on} both)"
        );
    }
}

/// A low, wide room (floor and ceiling slabs over the scene box's width and
/// depth, two triangles per face, one object) around four objects of small
/// triangles inside it: the SAH alone keeps the slabs in one leaf of two
/// blocks whose box is the room's ([`rebraid::bvh::LargeLeafSplit`]).
fn room_model(seed: u64) -> Model {
    let (lo, mut hi) = (SCENE_LO, SCENE_HI);
    hi.y = lo.y + 4.0;
    let mut tris = Vec::new();
    for y in [lo.y, lo.y + 0.1, hi.y - 0.1, hi.y] {
        let c = [(lo.x, lo.z), (hi.x, lo.z), (hi.x, hi.z), (lo.x, hi.z)]
            .map(|(x, z)| Vec3::new(x, y, z));
        tris.push([c[0], c[1], c[2]]);
        tris.push([c[0], c[2], c[3]]);
    }
    let mut m = Model::default();
    m.objects
        .insert(0, (TriangleMesh::from_triangles(&tris).unwrap(), true));
    let mut rng = rng(seed);
    let inner = Vec3::new(0.0, 0.5, 0.0);
    for i in 1..5 {
        let mesh = soup(&mut rng, 300, lo + inner, hi - inner, 0.7);
        m.objects.insert(i, (mesh, true));
    }
    m
}

/// Embree's greedy collapse (`Collapse::Greedy`) for every object, flat and
/// top-level tree, with every kernel: the same answers as the brute force;
/// and the default, SAH-optimal collapse gives each mode a wide SAH cost no
/// higher than the greedy one.
#[test]
fn both_collapse_rules_match_brute_force_in_every_mode() {
    use rebraid::bvh::Collapse;
    let collapsed = |kernel, collapse| {
        let mut p = SceneParams {
            kernel: Some(kernel),
            ..params(AccelMode::Flat)
        };
        p.object_build.collapse = collapse;
        p.rebraid.collapse = collapse;
        p
    };
    for (model, what, rays) in &tree_option_cases(960) {
        for kernel in rebraid::bvh::Kernel::available() {
            let what = format!("greedy collapse, {what} {kernel:?}");
            all_modes_vs_brute_with(model, rays, &what, collapsed(kernel, Collapse::Greedy));
        }
        let wide_sah = |collapse, mode| {
            let p = collapsed(rebraid::bvh::Kernel::best(), collapse);
            committed_stats(model, p, mode).wide_sah_cost
        };
        for mode in [AccelMode::Flat, AccelMode::TwoLevel, AccelMode::Rebraided] {
            let greedy = wide_sah(Collapse::Greedy, mode);
            let optimal = wide_sah(Collapse::SahOptimal, mode);
            assert!(
                optimal <= greedy * (1.0 + 1e-6),
                "{what} {mode:?}: wide SAH optimal {optimal} above greedy {greedy}"
            );
            eprintln!("{what} {mode:?}: wide SAH greedy {greedy:.3}, optimal {optimal:.3}");
        }
    }
}

/// `SceneParams::merge_placed`: the objects placed directly traced from one
/// BVH over all their triangles. Random scenes (objects placed and also
/// instanced, which stay out, prototypes, mirrored instances), the library
/// case with and without instances, and camera rays in packets, in every
/// mode with every kernel against the brute force; hits name each member's
/// own object and primitive (bit-identical to the flat mode without
/// instances).
#[test]
fn merged_placed_objects_match_brute_force_in_every_mode() {
    let merged = |kernel| SceneParams {
        kernel: Some(kernel),
        merge_placed: true,
        ..params(AccelMode::Flat)
    };
    let cases = [
        (random_model(&mut rng(900), &Gen::default()), "random"),
        (
            random_model(&mut rng(901), &clustered_with_instances()),
            "clustered",
        ),
        (library_model(902, 16, 200, 0), "library"),
        (library_model(903, 10, 150, 6), "library+instances"),
    ];
    for (k, (model, what)) in cases.iter().enumerate() {
        let world = model.world();
        let mut rays = random_rays(&mut rng(904), &world, 1200, SCENE_LO, SCENE_HI);
        if k < 2 {
            // Packets (the library's soups leave most camera rays unhit).
            rays.extend(camera_rays(Vec3::new(9.3, 30.0, 11.1), 8.0));
        }
        for kernel in rebraid::bvh::Kernel::available() {
            let what = format!("merged {what} {kernel:?}");
            all_modes_vs_brute_with(model, &rays, &what, merged(kernel));
        }
        // The members: placed, not empty, without instances.
        let mut scene = model.to_scene(merged(rebraid::bvh::Kernel::best()));
        scene.set_mode(AccelMode::Rebraided);
        let rep = scene.commit().unwrap();
        let instanced: std::collections::BTreeSet<u32> =
            model.instances.values().map(|&(o, _)| o).collect();
        let members = model
            .objects
            .iter()
            .filter(|(id, (m, placed))| *placed && !m.is_empty() && !instanced.contains(id))
            .count();
        assert!(members >= 2, "{what}: the case must merge");
        assert_eq!(rep.objects_merged, members, "{what}");
        assert!(rep.merged_rebuilt, "{what}");
        assert_eq!(
            rep.objects_rebuilt.len() + members,
            model
                .objects
                .values()
                .filter(|(m, _)| !m.is_empty())
                .count()
                + model.objects.values().filter(|(m, _)| m.is_empty()).count(),
            "{what}: every other object built"
        );
        let rebraid::toplevel::MergedSlot { slot, origins } =
            top(&scene).merged.clone().expect("merged");
        assert_eq!(
            slot as usize,
            model.objects.len(),
            "{what}: slot after the objects"
        );
        assert_eq!(
            origins.len(),
            model
                .objects
                .iter()
                .filter(|(id, (_, placed))| *placed && !instanced.contains(id))
                .map(|(_, (m, _))| m.len())
                .sum::<usize>(),
            "{what}"
        );
        // A merged slot that does not fit its BVH is refused.
        let t = top(&scene);
        let short: std::sync::Arc<[(u32, u32)]> = origins[1..].into();
        for bad in [
            rebraid::toplevel::MergedSlot {
                slot,
                origins: short,
            },
            rebraid::toplevel::MergedSlot {
                slot: slot + 1 + t.baked.len() as u32,
                origins: origins.clone(),
            },
        ] {
            let mut broken = t.clone();
            broken.merged = Some(bad.clone());
            assert!(broken.validate().is_err(), "{what}: {bad:?}");
            assert!(t.clone().with_merged(Some(bad)).is_err(), "{what}");
        }
    }
    // The model's scene merged in `mode`, the merged BVH grafted whole or
    // never, committed; with a label and the merged slot.
    let committed = |model: &Model, mode: AccelMode, graft_merged: bool, what: &str| {
        let what = format!("{what}, {mode:?} graft_merged {graft_merged}");
        let mut p = merged(rebraid::bvh::Kernel::best());
        p.mode = mode;
        p.rebraid.graft_merged_max_prims = if graft_merged { u32::MAX } else { 0 };
        let mut scene = model.to_scene(p);
        scene.commit().unwrap();
        let slot = top(&scene).merged.as_ref().expect("merged").slot;
        (scene, slot, what)
    };
    // The library case has no other object: in both two-level modes its
    // top level is the merged BVH alone, walked directly (no entry, no
    // graft), whatever the graft limit.
    let (model, _) = &cases[2];
    let world = model.world();
    let rays = random_rays(&mut rng(906), &world, 500, SCENE_LO, SCENE_HI);
    for (mode, graft_merged) in [
        (AccelMode::Rebraided, true),
        (AccelMode::Rebraided, false),
        (AccelMode::TwoLevel, false),
    ] {
        let (scene, slot, what) = committed(model, mode, graft_merged, "alone");
        let t = top(&scene);
        assert_eq!(t.direct, Some(slot), "{what}");
        assert!(t.grafted.is_empty() && t.blocks.is_empty(), "{what}");
        let mut counters = rebraid::bvh::TraversalCounters::default();
        for r in &rays {
            scene.intersect_counted(r, &mut counters);
        }
        assert_eq!(counters.entries_visited, 0, "{what}: {counters:?}");
        assert!(counters.inner_visited > 0, "{what}: {counters:?}");
        check_scene(&scene, &world, &rays, true, &what);
    }
    // With an instanced object beside it the top level is walked: grafted
    // whole, the merged BVH is entered by no top-level leaf; in the plain
    // two-level mode (no grafts), as any object, it is.
    let mut beside = model.clone();
    let proto = beside.objects.len() as u32;
    let small = beside.objects[&0].0.clone();
    beside.objects.insert(proto, (small, false));
    beside.instances.insert(
        0,
        (
            proto,
            Affine3A::from_translation(Vec3::new(0.5, 0.25, -0.5)),
        ),
    );
    let world = beside.world();
    let rays = random_rays(&mut rng(907), &world, 500, SCENE_LO, SCENE_HI);
    for (mode, graft_merged) in [
        (AccelMode::Rebraided, true),
        (AccelMode::Rebraided, false),
        (AccelMode::TwoLevel, true),
    ] {
        let (scene, slot, what) = committed(&beside, mode, graft_merged, "beside an instance");
        let t = top(&scene);
        assert_eq!(t.direct, None, "{what}");
        let entered = entered_slots(t).contains(&slot);
        match (mode, graft_merged) {
            (AccelMode::Rebraided, true) => assert!(!entered, "{what}"),
            (AccelMode::TwoLevel, _) => assert!(entered, "{what}"),
            _ => {}
        }
        check_scene(&scene, &world, &rays, true, &what);
    }
    // Without instances the merged scene answers as the flat mode does,
    // bit for bit (up to exact ties).
    let world = model.world();
    let rays = random_rays(&mut rng(905), &world, 1500, SCENE_LO, SCENE_HI);
    let mut scene = model.to_scene(params(AccelMode::Flat));
    scene.commit().unwrap();
    let mut flat = vec![None; rays.len()];
    scene.intersect_batch(&rays, &mut flat);
    scene.params.merge_placed = true;
    scene.set_mode(AccelMode::Rebraided);
    scene.commit().unwrap();
    let mut got = vec![None; rays.len()];
    scene.intersect_batch(&rays, &mut got);
    for (i, (a, b)) in flat.iter().zip(&got).enumerate() {
        assert_eq!(a.map(|h| h.t), b.map(|h| h.t), "ray {i}");
        if let (Some(a), Some(b)) = (a, b)
            && (a.object_id, a.prim_id) != (b.object_id, b.prim_id)
        {
            assert!(
                world
                    .all_hits(&rays[i])
                    .iter()
                    .any(|h| (h.object, h.prim) == (b.object_id, b.prim_id) && h.t == a.t),
                "ray {i}: {a:?} vs flat {b:?} is no tie"
            );
        }
    }
}

/// The object slots the leaves of a top level's wide tree enter (entries,
/// not the blocks copied into it).
fn entered_slots(t: &rebraid::toplevel::TopLevelAccel) -> std::collections::BTreeSet<u32> {
    use rebraid::bvh::wide::{WIDE_EMPTY, decode_leaf, is_leaf_ref};
    let w = t.wide.as_ref().expect("a wide top level");
    w.nodes
        .iter()
        .flat_map(|n| n.child)
        .filter(|&c| c != WIDE_EMPTY && is_leaf_ref(c))
        .flat_map(|c| {
            let (first, count) = decode_leaf(c);
            (first..first + count)
                .filter(|&i| i < t.block_base)
                .map(|i| t.entries[i as usize].object)
        })
        .collect()
}

/// A top level whose refs all name one object slot placed directly is
/// walked as that slot's BVH alone (`TopLevelAccel::direct`): one object
/// placed (beside a prototype nothing places), and one prototype placed by
/// a single instance (baked into world space, reported as the instance).
/// Every mode and kernel against the brute force, random and camera rays;
/// no entries counted.
#[test]
fn a_scene_of_one_bvh_is_walked_directly() {
    let mut r = rng(950);
    let mut one = Model::default();
    one.objects
        .insert(0, (soup(&mut r, 1500, SCENE_LO, SCENE_HI, 1.5), true));
    one.objects
        .insert(1, (soup(&mut r, 50, SCENE_LO, SCENE_HI, 1.5), false));
    let mut baked = Model::default();
    baked
        .objects
        .insert(0, (soup(&mut r, 1500, SCENE_LO, SCENE_HI, 1.5), false));
    let xf = Affine3A::from_rotation_translation(
        rebraid::glam::Quat::from_rotation_y(0.3),
        Vec3::new(0.5, -0.25, 0.75),
    );
    baked.instances.insert(0, (0, xf));
    for (model, what, slot, report) in [
        (&one, "one object", 0, (0, INVALID_ID)),
        (&baked, "one instance", 1, (0, 0)),
    ] {
        let world = model.world();
        let mut rays = random_rays(&mut rng(951), &world, 1200, SCENE_LO, SCENE_HI);
        rays.extend(camera_rays(Vec3::new(9.3, 30.0, 11.1), 8.0));
        all_modes_vs_brute(model, &rays, what);
        let mut flat = model.to_scene(params(AccelMode::Flat));
        flat.commit().unwrap();
        let Accel::Flat(f) = flat.accel() else {
            panic!("{what}: not flat")
        };
        for mode in [AccelMode::TwoLevel, AccelMode::Rebraided] {
            let what = format!("{what} {mode:?}");
            let mut scene = model.to_scene(params(mode));
            scene.commit().unwrap();
            let t = top(&scene);
            assert_eq!(t.direct, Some(slot), "{what}");
            assert_eq!(t.placement_of_slot(slot), report, "{what}");
            // The statistic counts the walk: the slot's tree, as the flat
            // mode's (the same tree here), without the unwalked top level.
            assert!(f.wide_sah_cost() > 0.0, "{what}");
            assert_eq!(t.wide_sah_cost(), f.wide_sah_cost(), "{what}");
            let mut counters = rebraid::bvh::TraversalCounters::default();
            let mut hits = 0;
            for ray in &rays {
                if let Some(h) = scene.intersect_counted(ray, &mut counters) {
                    assert_eq!((h.object_id, h.instance_id), report, "{what}");
                    hits += 1;
                }
            }
            assert!(hits * 4 >= rays.len(), "{what}: {hits} hits");
            assert_eq!(counters.entries_visited, 0, "{what}: {counters:?}");
            assert!(counters.inner_visited > 0, "{what}: {counters:?}");
        }
    }
}
