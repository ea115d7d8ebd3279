//! Random edit sequences through the scene API, checked against the brute
//! force after every commit.
//!
//! The hand-written update tests (`scene_updates.rs`) walk one planned path
//! per feature: a merged BVH's members changing, a baked instance moving, a
//! top level walked directly. Here random sequences mix every edit the API
//! has (objects and prototypes added, meshes replaced or emptied, vertices
//! moved, placement toggled, update policies, instances added, moved and
//! removed, objects removed with their instances, mode switches, the top
//! level's buffers reused or not) and edits
//! the scene must refuse without changing anything (unknown ids, vertex
//! arrays of the wrong length, singular transforms), under parameter sets
//! that turn the top level's layout options on and off, so that the
//! features meet in orders no planned test takes. After each commit: the
//! scene's counts, the top level's validity and exact reachability
//! (`check_top`), and every ray's closest hit and occlusion against the
//! brute force over the model (`check_scene`). Seeded: a failure names its
//! parameter set, seed and step; `REBRAID_EDIT_SEEDS` runs more seeds.

mod scene_common;

use rand::Rng;
use rebraid::bvh::Kernel;
use rebraid::glam::{Affine3A, Vec3};
use rebraid::{AccelMode, Error, RebraidParams, Scene, SceneParams, TriangleMesh, UpdatePolicy};
use scene_common::*;

/// Parameter sets: the defaults, and each group of the top level's layout
/// options and object policies switched the other way.
fn param_sets() -> Vec<(&'static str, SceneParams)> {
    let with = |f: &dyn Fn(&mut SceneParams)| {
        let mut p = SceneParams::default();
        f(&mut p);
        p
    };
    vec![
        ("defaults", SceneParams::default()),
        ("merge placed", with(&|p| p.merge_placed = true)),
        (
            "merge placed, merged BVH behind entries",
            with(&|p| {
                p.merge_placed = true;
                p.rebraid.graft_merged_max_prims = 0;
            }),
        ),
        (
            "no baking, no copies, no grafts, no pulled nodes",
            with(&|p| {
                p.rebraid = RebraidParams {
                    bake_single_instances: false,
                    inline_leaf_blocks: false,
                    inline_instanced_leaves: false,
                    graft_max_prims: 0,
                    pull_entry_nodes: false,
                    ..RebraidParams::default()
                }
            }),
        ),
        (
            "every entry grafted",
            with(&|p| {
                p.rebraid.graft_max_prims = 1_000_000;
                p.rebraid.graft_budget = 1000.0;
            }),
        ),
        (
            "no opening, scalar kernel",
            with(&|p| {
                p.rebraid.open = false;
                p.kernel = Some(Kernel::Scalar);
            }),
        ),
        (
            "one top level: moved placements not split off",
            with(&|p| p.rebraid.moving_hold_commits = 0),
        ),
        (
            "moved placements split off whatever their share",
            with(&|p| p.rebraid.moving_split_max_share = f32::INFINITY),
        ),
        (
            "moved placements split off for one commit, merge placed",
            with(&|p| {
                p.rebraid.moving_hold_commits = 1;
                p.rebraid.moving_split_max_share = f32::INFINITY;
                p.merge_placed = true;
            }),
        ),
    ]
}

/// A random mesh: a soup or a grid somewhere in the scene box, now and
/// then empty.
fn random_mesh(rng: &mut impl Rng) -> TriangleMesh {
    let c = rand_in(rng, SCENE_LO, SCENE_HI);
    let h = Vec3::splat(rng.gen_range(0.5..4.0));
    match rng.gen_range(0..10) {
        0 => TriangleMesh::default(),
        1..=2 => {
            let (nx, ny) = (rng.gen_range(1..6), rng.gen_range(1..6));
            grid(rng, nx, ny, c - h, c + h)
        }
        _ => {
            let (n, size) = (rng.gen_range(1..80), rng.gen_range(0.3..1.5));
            soup(rng, n, c - h, c + h, size)
        }
    }
}

fn pick<T: Copy>(rng: &mut impl Rng, keys: impl Iterator<Item = T>) -> Option<T> {
    let v: Vec<T> = keys.collect();
    (!v.is_empty()).then(|| v[rng.gen_range(0..v.len())])
}

/// A transform the scene must refuse (singular or not finite).
fn bad_transform(rng: &mut impl Rng) -> Affine3A {
    match rng.gen_range(0..3) {
        0 => Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0)),
        1 => Affine3A::from_translation(Vec3::new(f32::NAN, 0.0, 0.0)),
        _ => Affine3A::from_scale(Vec3::splat(f32::INFINITY)),
    }
}

/// One random edit, applied to the scene and the model alike (or refused
/// by the scene, which the model then does not see). Returns what it did.
fn random_edit(rng: &mut impl Rng, scene: &mut Scene, model: &mut Model) -> String {
    let object = |rng: &mut _, model: &Model| pick(rng, model.objects.keys().copied());
    let instance = |rng: &mut _, model: &Model| pick(rng, model.instances.keys().copied());
    match rng.gen_range(0..15) {
        0 | 1 => {
            let placed = rng.gen_bool(0.6);
            let id = model.add_object(scene, random_mesh(rng), placed);
            format!("add object {id} (placed {placed})")
        }
        2 | 3 => {
            let Some(id) = object(rng, model) else {
                return "no object to move".into();
            };
            let mesh = &model.objects[&id].0;
            let shift = rand_in(rng, Vec3::splat(-2.0), Vec3::splat(2.0));
            let v: Vec<Vec3> = mesh
                .positions
                .iter()
                .map(|p| *p + shift + rand_in(rng, Vec3::splat(-0.1), Vec3::splat(0.1)))
                .collect();
            scene.set_vertices(id, &v).unwrap();
            model.objects.get_mut(&id).unwrap().0.positions = v;
            format!("set_vertices {id}")
        }
        4 => {
            let Some(id) = object(rng, model) else {
                return "no object to replace".into();
            };
            let mesh = random_mesh(rng);
            scene.set_mesh(id, mesh.clone()).unwrap();
            model.objects.get_mut(&id).unwrap().0 = mesh;
            format!("set_mesh {id}")
        }
        5 => {
            let Some(id) = object(rng, model) else {
                return "no object to place".into();
            };
            let placed = !model.objects[&id].1;
            scene.set_object_placed(id, placed).unwrap();
            model.objects.get_mut(&id).unwrap().1 = placed;
            format!("set_object_placed {id} {placed}")
        }
        6 => {
            let Some(id) = object(rng, model) else {
                return "no object for a policy".into();
            };
            let policy = if rng.gen_bool(0.5) {
                UpdatePolicy::Refit
            } else {
                UpdatePolicy::Rebuild
            };
            scene.set_update_policy(id, policy).unwrap();
            assert_eq!(scene.update_policy(id).unwrap(), policy);
            format!("set_update_policy {id} {policy:?}")
        }
        7 | 8 => {
            let Some(obj) = object(rng, model) else {
                return "no object to instance".into();
            };
            let xf = random_transform(rng, SCENE_LO, SCENE_HI, true);
            let id = model.add_instance(scene, obj, xf);
            format!("add instance {id} of {obj}")
        }
        9 => {
            let Some(id) = instance(rng, model) else {
                return "no instance to move".into();
            };
            let xf = random_transform(rng, SCENE_LO, SCENE_HI, true);
            scene.set_instance_transform(id, xf).unwrap();
            model.instances.get_mut(&id).unwrap().1 = xf;
            format!("move instance {id}")
        }
        10 => {
            let Some(id) = instance(rng, model) else {
                return "no instance to remove".into();
            };
            scene.remove_instance(id).unwrap();
            model.instances.remove(&id);
            format!("remove instance {id}")
        }
        11 => {
            let Some(id) = object(rng, model) else {
                return "no object to remove".into();
            };
            let mut gone = scene.remove_object(id).unwrap();
            gone.sort_unstable();
            let want: Vec<u32> = model
                .instances
                .iter()
                .filter(|(_, (o, _))| *o == id)
                .map(|(i, _)| *i)
                .collect();
            assert_eq!(gone, want, "remove_object {id}: instances removed");
            model.objects.remove(&id);
            model.instances.retain(|_, (o, _)| *o != id);
            format!("remove object {id}")
        }
        12 if rng.gen_bool(0.8) => {
            let mode = AccelMode::ALL[rng.gen_range(0..3)];
            scene.set_mode(mode);
            format!("set_mode {mode:?}")
        }
        12 => {
            let reuse = rng.gen_bool(0.5);
            scene.set_reuse_top_level_buffers(reuse);
            format!("set_reuse_top_level_buffers {reuse}")
        }
        _ => refused_edit(rng, scene, model),
    }
}

/// An edit the scene must refuse with an error, leaving it as it was.
fn refused_edit(rng: &mut impl Rng, scene: &mut Scene, model: &Model) -> String {
    let unknown = 1_000_000 + rng.gen_range(0..10);
    let needed = scene.needs_commit();
    let what = match (rng.gen_range(0..5), model.objects.keys().next().copied()) {
        (0, _) => {
            let e = scene.set_vertices(unknown, &[]).unwrap_err();
            assert_eq!(e, Error::UnknownObject(unknown));
            "set_vertices of an unknown object"
        }
        (1, _) => {
            let e = scene.set_instance_transform(unknown, Affine3A::IDENTITY);
            assert_eq!(e.unwrap_err(), Error::UnknownInstance(unknown));
            "move an unknown instance"
        }
        (2, Some(id)) => {
            let n = model.objects[&id].0.positions.len();
            assert!(scene.set_vertices(id, &vec![Vec3::ZERO; n + 1]).is_err());
            "set_vertices of the wrong length"
        }
        (3, Some(id)) => {
            assert!(scene.add_instance(id, bad_transform(rng)).is_err());
            "add an instance with a bad transform"
        }
        (_, Some(id)) => {
            let mut v = model.objects[&id].0.positions.clone();
            if v.is_empty() {
                return "no vertex to spoil".into();
            }
            let k = rng.gen_range(0..v.len());
            v[k].y = f32::NAN;
            assert!(scene.set_vertices(id, &v).is_err());
            "set_vertices with a NaN"
        }
        _ => "no object for a refused edit",
    };
    assert_eq!(
        scene.needs_commit(),
        needed,
        "{what}: a refused edit changed the scene"
    );
    what.into()
}

#[test]
fn random_edit_sequences_match_brute_force() {
    // `REBRAID_EDIT_SEEDS=200` for a longer run.
    let seeds: u64 = std::env::var("REBRAID_EDIT_SEEDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    const COMMITS: usize = 24;
    for (name, params) in param_sets() {
        for seed in 0..seeds {
            let mut rng = rng(0x5eed_0000 + seed);
            let g = Gen {
                clustered: 3,
                scattered: 1,
                grids: 1,
                tris: 60,
                prototypes: 2,
                instances: 4,
                mirror: true,
            };
            let mut model = random_model(&mut rng, &g);
            let mut params = params.clone();
            params.mode = AccelMode::ALL[rng.gen_range(0..3)];
            let mut scene = model.to_scene(params);
            let mut log = Vec::new();
            for step in 0..COMMITS {
                for _ in 0..rng.gen_range(1..4) {
                    log.push(random_edit(&mut rng, &mut scene, &mut model));
                }
                let what = format!(
                    "{name}, seed {seed}, commit {step} ({:?}) after: {}",
                    scene.mode(),
                    log.join("; ")
                );
                scene
                    .commit()
                    .unwrap_or_else(|e| panic!("{what}: commit failed: {e}"));
                check_commit(&scene, &model, 150, seed * 1000 + step as u64, &what);
                // Keep the last steps only in the message.
                let keep = log.len().saturating_sub(12);
                log.drain(..keep);
            }
        }
    }
}
