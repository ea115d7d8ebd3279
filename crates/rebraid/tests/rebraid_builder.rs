//! The re-braiding top-level builder: exact reachability, budgets,
//! thresholds, the two-level special cases, thread-count independence, SAH
//! quality and a property test. Issue "Partial re-braiding".

mod scene_common;

use proptest::prelude::*;
use rebraid::glam::Vec3;
use rebraid::scene::Accel;
use rebraid::toplevel::builder::RefSources;
use rebraid::toplevel::{BuildRef, ObjectBvh, build_top_level};
use rebraid::{AccelMode, INVALID_ID, RebraidParams, RefBudget, Scene, SceneParams};
use scene_common::*;

fn rebraided(rebraid: RebraidParams) -> SceneParams {
    SceneParams {
        mode: AccelMode::Rebraided,
        rebraid,
        ..Default::default()
    }
}

fn huge_budget() -> RefBudget {
    RefBudget::Scaled {
        min: 1 << 20,
        per_initial_ref: 2.0,
        per_primitive: 0.001,
        overlap_unit: 0.0,
    }
}

/// Overlapping scenes: clustered and scattered objects plus instances.
fn overlapping_model(seed: u64) -> Model {
    random_model(
        &mut rng(seed),
        &Gen {
            clustered: 5,
            scattered: 4,
            grids: 1,
            tris: 120,
            prototypes: 2,
            instances: 10,
            mirror: true,
        },
    )
}

#[test]
fn budgets_and_thresholds_build_valid_reachable_trees_that_answer_right() {
    let budgets = [
        RefBudget::Spare(0),
        RefBudget::Spare(1),
        RefBudget::Spare(5),
        RebraidParams::default().budget,
        huge_budget(),
        // The per-primitive term decides: distinct against world counts.
        RefBudget::Scaled {
            min: 0,
            per_initial_ref: 0.0,
            per_primitive: 0.5,
            overlap_unit: 0.0,
        },
        // The same scaled by the placements' overlap (these scenes overlap
        // by more than 1, so the scale matters).
        RefBudget::Scaled {
            min: 0,
            per_initial_ref: 0.0,
            per_primitive: 0.05,
            overlap_unit: 1.0,
        },
    ];
    let thresholds = [0.0f32, 0.05, 0.1, 0.5, 10.0];
    for seed in [1u64, 2] {
        let model = overlapping_model(seed);
        let world = model.world();
        let rays = random_rays(&mut rng(seed + 50), &world, 250, SCENE_LO, SCENE_HI);
        let mut scene = model.to_scene(rebraided(RebraidParams::default()));
        for budget in budgets {
            for threshold in thresholds {
                let what = format!("seed {seed} {budget:?} threshold {threshold}");
                scene.params.rebraid = RebraidParams {
                    budget,
                    threshold,
                    ..Default::default()
                };
                let rep = scene.commit().unwrap();
                let t = top(&scene);
                check_top(t, &model, &what);
                let st = rep.top.clone().unwrap();
                assert_eq!(st, t.build_stats, "{what}");
                // The phase clocks: parts of the build and of the commit's
                // top-level time, none negative.
                let l = st.layout;
                for ms in [
                    st.build_ms,
                    st.reinsert_ms,
                    l.collapse_ms,
                    l.entries_ms,
                    l.graft_ms,
                    l.order_ms,
                    l.copy_ms,
                ] {
                    assert!(ms >= 0.0 && ms.is_finite(), "{what}: {st:?}");
                }
                assert!(st.reinsert_ms <= st.build_ms, "{what}: {st:?}");
                assert!(
                    st.build_ms + l.total_ms() <= rep.top_build_ms * 1.0001 + 1e-6,
                    "{what}: {st:?} against {}",
                    rep.top_build_ms
                );
                let n = st.refs_initial;
                // The budget counts each object once, however often placed.
                let prims = model.distinct_triangles() as u64;
                assert!(prims < model.world_triangles() as u64, "{what}");
                assert_eq!(
                    st.capacity,
                    budget.capacity(n, prims, st.overlap),
                    "{what}: {st:?}"
                );
                // The overlap of the placements' world boxes, near that of
                // their tight boxes (an instance's box is its object's box
                // transformed, which may be looser, in the sum and in the
                // union), and above 1 in these scenes.
                let tight = world.placement_overlap();
                assert!(
                    tight > 1.0 && st.overlap > 0.5 * tight && st.overlap < 2.0 * tight,
                    "{what}: overlap {} against {tight}",
                    st.overlap
                );
                if let RefBudget::Scaled {
                    overlap_unit: 1.0,
                    per_primitive,
                    ..
                } = budget
                {
                    let unscaled = (per_primitive as f64 * prims as f64).ceil() as usize;
                    assert!(st.capacity > unscaled.max(n), "{what}: {st:?}");
                }
                assert_eq!(st.spare_used, st.refs_final - n, "{what}: {st:?}");
                assert!(st.nodes_opened <= st.spare_used, "{what}: {st:?}");
                assert!(st.refs_final <= st.capacity, "{what}: {st:?}");
                if let RefBudget::Spare(s) = budget {
                    assert_eq!(st.capacity, n + s, "{what}: {st:?}");
                    assert!(st.spare_used <= s, "{what}: {st:?}");
                }
                if threshold >= 1.0 {
                    // No ref is longer than its list: nothing may open.
                    assert_eq!(st.nodes_opened, 0, "{what}: {st:?}");
                }
                if budget == RefBudget::Spare(0) {
                    assert_eq!(st.refs_final, n, "{what}: {st:?}");
                }
                // A wide node opens into up to 8 refs, taking up to 7 spare
                // slots: smaller budgets may open nothing.
                if threshold < 1.0 && !matches!(budget, RefBudget::Spare(s) if s < 7) {
                    // These scenes overlap: some opening must happen.
                    assert!(st.nodes_opened > 0, "{what}: {st:?}");
                }
                check_scene(&scene, &world, &rays, false, &what);
            }
        }
    }
}

#[test]
fn open_false_gives_exactly_the_two_level_tree() {
    for seed in [3u64, 4] {
        let model = overlapping_model(seed);
        let mut scene = model.to_scene(SceneParams {
            mode: AccelMode::TwoLevel,
            ..Default::default()
        });
        scene.commit().unwrap();
        let (nodes, refs, sah) = {
            let t = top(&scene);
            assert!(
                t.refs.iter().all(|r| r.node == 0),
                "two-level refs are roots"
            );
            assert_eq!(t.build_stats.nodes_opened, 0);
            (t.tree.nodes.clone(), t.refs.clone(), scene.stats().sah_cost)
        };
        scene.params.rebraid.open = false;
        scene.set_mode(AccelMode::Rebraided);
        scene.commit().unwrap();
        let t = top(&scene);
        check_top(t, &model, "open: false");
        assert_eq!(t.refs, refs, "seed {seed}");
        assert_eq!(t.tree.nodes, nodes, "seed {seed}");
        assert_eq!(scene.stats().sah_cost, sah, "seed {seed}");
        assert_eq!(t.build_stats.capacity, t.build_stats.refs_initial);
    }
}

#[test]
fn open_instances_false_never_opens_an_instanced_ref() {
    let model = overlapping_model(5);
    let world = model.world();
    let rays = random_rays(&mut rng(55), &world, 400, SCENE_LO, SCENE_HI);
    for open_instances in [true, false] {
        let mut scene = model.to_scene(rebraided(RebraidParams {
            open_instances,
            budget: huge_budget(),
            ..Default::default()
        }));
        scene.commit().unwrap();
        let t = top(&scene);
        check_top(t, &model, &format!("open_instances {open_instances}"));
        let opened_inst = t
            .refs
            .iter()
            .filter(|r| r.instance != INVALID_ID && r.node != 0)
            .count();
        let opened_direct = t
            .refs
            .iter()
            .filter(|r| r.instance == INVALID_ID && r.node != 0)
            .count();
        assert!(opened_direct > 0, "direct objects must still be opened");
        if open_instances {
            // Otherwise the check below would prove nothing.
            assert!(opened_inst > 0, "this scene opens instances when allowed");
        } else {
            assert_eq!(opened_inst, 0, "an instanced ref was opened");
        }
        check_scene(&scene, &world, &rays, false, "open_instances");
    }
}

#[test]
fn trees_do_not_depend_on_the_thread_count() {
    let model = random_model(
        &mut rng(6),
        &Gen {
            clustered: 30,
            scattered: 10,
            grids: 4,
            tris: 300,
            prototypes: 4,
            instances: 60,
            mirror: true,
        },
    );
    let mut params = rebraided(RebraidParams {
        // Exercise the data-parallel opening, binning and partitioning.
        parallel_threshold: 16,
        budget: huge_budget(),
        ..Default::default()
    });
    params.object_build.parallel_threshold = 64;
    let mut results = Vec::new();
    for threads in [1usize, 2, 4] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let mut out = Vec::new();
        for mode in AccelMode::ALL {
            let mut scene = model.to_scene(params.clone());
            scene.set_mode(mode);
            pool.install(|| scene.commit()).unwrap();
            let sah = scene.stats().sah_cost;
            match scene.accel() {
                Accel::TopLevel(t) => {
                    check_top(t, &model, &format!("{threads} threads"));
                    let objects: Vec<_> = t
                        .objects
                        .iter()
                        .map(|o| o.as_ref().map(|o| o.mesh.bvh.clone()))
                        .collect();
                    out.push((t.tree.clone(), t.refs.clone(), objects, sah));
                }
                Accel::Flat(f) => out.push((f.bvh.bvh.clone(), Vec::new(), Vec::new(), sah)),
                Accel::Split(_) => panic!("nothing moved: one top level"),
                Accel::Empty => panic!("empty"),
            }
        }
        results.push(out);
    }
    let st = &results[0][2];
    assert!(
        st.1.len() > st.2.len(),
        "the re-braided tree must open refs"
    );
    for (k, r) in results.iter().enumerate().skip(1) {
        for (m, (a, b)) in results[0].iter().zip(r).enumerate() {
            assert!(a.0 == b.0, "mode {m}: tree differs with pool {k}");
            assert!(a.1 == b.1, "mode {m}: refs differ with pool {k}");
            assert!(a.2 == b.2, "mode {m}: object BVHs differ with pool {k}");
            assert_eq!(a.3, b.3, "mode {m}: SAH differs with pool {k}");
        }
    }
}

/// A commit builds the top level while it finishes the new objects' wide
/// layouts (their blocks and occlusion order), opening them by their
/// collapse alone: the top level must be the one a later commit builds over
/// the same objects finished, and each object's layout the one
/// `ObjectBvh::with_collapse` makes.
#[test]
fn top_levels_over_new_and_kept_objects_agree() {
    let model = overlapping_model(41);
    let mut scene = model.to_scene(rebraided(RebraidParams::default()));
    let tops = |scene: &Scene| match scene.accel() {
        Accel::TopLevel(t) => (t.tree.clone(), t.refs.clone()),
        _ => panic!("one top level expected"),
    };
    let report = scene.commit().unwrap();
    assert!(!report.objects_rebuilt.is_empty());
    let fresh = tops(&scene);
    // Back and forth through the two-level mode: the objects are kept.
    scene.set_mode(AccelMode::TwoLevel);
    scene.commit().unwrap();
    scene.set_mode(AccelMode::Rebraided);
    let report = scene.commit().unwrap();
    assert!(report.objects_rebuilt.is_empty(), "objects kept");
    let kept = tops(&scene);
    assert!(
        fresh.1.len() > model.placements().len(),
        "the top level opens refs"
    );
    assert!(fresh == kept, "top levels over new and kept objects differ");
    let Accel::TopLevel(t) = scene.accel() else {
        unreachable!()
    };
    for o in t.objects.iter().flatten() {
        let again = ObjectBvh::with_collapse(o.mesh.clone(), o.collapse);
        let (Some(a), Some(b)) = (&o.wide, &again.wide) else {
            panic!("every object has its layout");
        };
        assert!(a.wide == b.wide, "finished nodes differ");
        // Blocks pad their empty lanes with NaN: compared as printed.
        assert_eq!(format!("{:?}", a.blocks), format!("{:?}", b.blocks));
        assert!(a.occlusion == b.occlusion && a.block_misses == b.block_misses);
        assert!(o.wide_of == again.wide_of, "finished map differs");
    }
}

/// The library incident (every object spans the scene box), with or
/// without scattered instances.
fn library(seed: u64, instances: usize) -> Model {
    let mut rng = rng(seed);
    let mut m = Model::default();
    for i in 0..16u32 {
        m.objects
            .insert(i, (soup(&mut rng, 200, SCENE_LO, SCENE_HI, 0.7), true));
    }
    if instances > 0 {
        let h = (SCENE_HI - SCENE_LO) * 0.5;
        m.objects
            .insert(16, (soup(&mut rng, 200, -h, h, 0.7), false));
        for i in 0..instances as u32 {
            let xf = random_transform(&mut rng, h - 1.0, h + 1.0, true);
            m.instances.insert(i, (16, xf));
        }
    }
    m
}

#[test]
fn rebraiding_lowers_the_sah_cost_of_overlapping_scenes() {
    for (what, model) in [
        ("library", library(8, 0)),
        ("library+instances", library(9, 8)),
        ("overlapping", overlapping_model(10)),
    ] {
        let mut scene = model.to_scene(SceneParams::default());
        let mut sah = Vec::new();
        for mode in AccelMode::ALL {
            scene.set_mode(mode);
            scene.commit().unwrap();
            sah.push(scene.stats().sah_cost);
        }
        eprintln!(
            "{what}: SAH flat {:.2}, two-level {:.2}, rebraided {:.2}",
            sah[0], sah[1], sah[2]
        );
        assert!(sah.iter().all(|s| s.is_finite() && *s > 0.0), "{sah:?}");
        assert!(
            sah[2] <= sah[1],
            "{what}: rebraided SAH {} above two-level {}",
            sah[2],
            sah[1]
        );
        if what.starts_with("library") {
            // Opening must recover much of the flat quality here.
            assert!(sah[2] < 0.8 * sah[1], "{what}: {sah:?}");
        }
    }
}

#[test]
fn builder_rejects_bad_refs_and_accepts_no_refs() {
    let model = overlapping_model(11);
    let mut scene = model.to_scene(SceneParams::default());
    scene.commit().unwrap();
    let t = top(&scene);
    let src = RefSources {
        objects: &t.objects,
        instances: &t.instances,
    };
    let (tree, refs, st) = build_top_level(&[], src, &RebraidParams::default()).unwrap();
    assert!(tree.nodes.is_empty() && refs.is_empty() && st.refs_final == 0);
    let obj = t.objects[0].as_ref().unwrap();
    // Built field by field from zeroes (every field is plain numbers), so
    // that the test does not break when the builder adds a field.
    // SAFETY: BuildRef is `repr(C)` plain data (f32 and u32 fields); all
    // zeroes is a valid value.
    let mut good: BuildRef = unsafe { std::mem::zeroed() };
    good.bounds = obj.mesh.bvh.bounds();
    good.object = 0;
    good.node = 0;
    good.instance = INVALID_ID;
    good.prims = obj.mesh.len() as u32;
    assert!(build_top_level(&[good], src, &RebraidParams::default()).is_ok());
    let bad = [
        BuildRef {
            node: obj.mesh.bvh.nodes.len() as u32,
            ..good
        },
        BuildRef {
            object: 1000,
            ..good
        },
        BuildRef {
            instance: 1000,
            ..good
        },
        BuildRef {
            bounds: rebraid::Aabb::EMPTY,
            ..good
        },
        BuildRef {
            bounds: rebraid::Aabb::new(Vec3::ZERO, Vec3::new(f32::NAN, 1.0, 1.0)),
            ..good
        },
    ];
    for b in bad {
        assert_eq!(
            build_top_level(&[good, b], src, &RebraidParams::default()).err(),
            Some(rebraid::Error::InvalidBounds { index: 1 }),
            "{b:?}"
        );
    }
    for p in [
        RebraidParams {
            bins: 1,
            ..Default::default()
        },
        RebraidParams {
            threshold: -0.1,
            ..Default::default()
        },
        RebraidParams {
            threshold: f32::NAN,
            ..Default::default()
        },
    ] {
        assert!(build_top_level(&[good], src, &p).is_err(), "{p:?}");
        let mut s = model.to_scene(rebraided(p.clone()));
        assert!(s.commit().is_err(), "scene commit with {p:?}");
    }
}

fn budget_of(k: usize) -> RefBudget {
    match k {
        0 => RefBudget::Spare(0),
        1 => RefBudget::Spare(1),
        2 => RefBudget::Spare(5),
        3 => RebraidParams::default().budget,
        _ => huge_budget(),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn random_small_scenes_are_valid_reachable_and_right(
        seed in any::<u64>(),
        clustered in 0usize..4,
        scattered in 0usize..3,
        prototypes in 0usize..3,
        instances in 0usize..8,
        tris in 1usize..40,
        budget in 0usize..5,
        threshold in prop::sample::select(vec![0.0f32, 0.05, 0.1, 0.3, 0.5, 10.0]),
        open_instances in any::<bool>(),
        short_list in 0usize..6,
    ) {
        let mut rng = rng(seed);
        let model = random_model(&mut rng, &Gen {
            clustered,
            scattered,
            grids: 0,
            tris,
            prototypes,
            instances,
            mirror: true,
        });
        let mut scene: Scene = model.to_scene(rebraided(RebraidParams {
            budget: budget_of(budget),
            threshold,
            open_instances,
            short_list,
            ..Default::default()
        }));
        let rep = scene.commit().unwrap();
        let world = model.world();
        let rays = random_rays(&mut rng, &world, 40, SCENE_LO, SCENE_HI);
        match scene.accel() {
            Accel::Empty => {
                prop_assert_eq!(model.world_triangles(), 0);
                for r in &rays {
                    prop_assert!(scene.intersect(r).is_none());
                }
            }
            Accel::TopLevel(t) => {
                check_top(t, &model, "proptest");
                let st = rep.top.unwrap();
                prop_assert_eq!(st.spare_used, st.refs_final - st.refs_initial);
                if let RefBudget::Spare(s) = budget_of(budget) {
                    prop_assert!(st.spare_used <= s);
                }
                if !open_instances {
                    prop_assert!(t.refs.iter().all(|r| r.instance == INVALID_ID || r.node == 0));
                }
                for (i, r) in rays.iter().enumerate() {
                    let h = scene.intersect(r);
                    let all = world.all_hits(r);
                    if let Err(e) = check_ray(&all, r, h, scene.occluded(r), false) {
                        prop_assert!(false, "ray {} {:?}: {}", i, r, e);
                    }
                }
            }
            Accel::Flat(_) => prop_assert!(false, "flat accel in rebraided mode"),
            Accel::Split(_) => prop_assert!(false, "split accel before any move"),
        }
    }
}

/// Regression (found by these tests): the world box of an instanced node
/// must hold its transformed vertices even when the translation cancels most
/// of the rotated coordinates (the rounding of `transform_point3` scales with
/// the terms' magnitudes, not with the result's). Before the fix the vertex
/// below lay 1.4e-6 outside the box and the debug build of the top level
/// panicked "top-level builder produced an invalid tree" in every mode.
#[test]
fn instance_box_holds_vertices_when_translation_cancels() {
    use rebraid::glam::{Affine3A, Mat3};
    let m = Mat3::from_cols(
        Vec3::new(0.7111757, -1.6282743, -0.373367),
        Vec3::new(0.4379876, -0.30216265, 2.152011),
        Vec3::new(0.9706653, 0.45461673, -0.13372192),
    );
    let xf = Affine3A::from_mat3_translation(m, Vec3::new(5.114732, 9.0247965, 2.634989));
    let tri = [
        Vec3::new(8.178403, 5.9691014, 15.956962),
        Vec3::new(8.32962, 6.331254, 15.837656),
        Vec3::new(7.936898, 6.147912, 15.999273),
    ];
    let wb = rebraid::transform::transform_box(&xf, &rebraid::Aabb::from_points(&tri));
    for v in tri {
        let p = xf.transform_point3(v);
        assert!(wb.contains_point(p), "{p:?} outside {wb:?}");
    }
    let mesh = rebraid::TriangleMesh::from_triangles(&[tri]).unwrap();
    for mode in AccelMode::ALL {
        let mut s = Scene::new();
        let p = s.add_prototype(mesh.clone()).unwrap();
        s.add_instance(p, xf).unwrap();
        s.set_mode(mode);
        s.commit().unwrap();
        if let Accel::TopLevel(t) = s.accel() {
            t.validate().unwrap();
        }
    }
}

/// Separated objects (no two boxes overlap): re-braiding finds nothing worth
/// the cost. With `open_only_overlapping` nothing opens at all and the tree
/// is the plain two-level one; by default the SAH cost stays that of the
/// two-level tree.
#[test]
fn separated_objects_cost_nearly_nothing() {
    let desc = rebraid::procedural::separated(8, 60, 5);
    let commit = |params: SceneParams| {
        let mut scene = Scene::from_desc(&desc, params).unwrap();
        scene.commit().unwrap();
        let st = scene.stats();
        let refs = match scene.accel() {
            Accel::TopLevel(t) => t.refs.clone(),
            _ => panic!("two-level modes build a top level"),
        };
        (st, refs)
    };
    let (two, two_refs) = commit(SceneParams {
        mode: AccelMode::TwoLevel,
        ..Default::default()
    });
    let (only, only_refs) = commit(rebraided(RebraidParams {
        open_only_overlapping: true,
        ..Default::default()
    }));
    assert_eq!(only.top.as_ref().unwrap().nodes_opened, 0);
    assert_eq!(only_refs, two_refs);
    assert_eq!(only.sah_cost, two.sah_cost);
    let (default, _) = commit(rebraided(RebraidParams::default()));
    assert!(
        default.sah_cost <= two.sah_cost * 1.01,
        "{} vs {}",
        default.sah_cost,
        two.sah_cost
    );
}

/// Pulling the object nodes that top-level leaves enter into the top
/// level's empty slots (`RebraidParams::pull_entry_nodes`): the same
/// answers as brute force with and without it, every primitive reachable
/// once through the wide top level, no node left with room for a ref's
/// children, and each pull of `k` children filling `k - 1` empty slots.
#[test]
fn pulled_entry_nodes_answer_right_and_fill_the_top_level() {
    use rebraid::bvh::wide::{decode_leaf, is_leaf_ref};
    let mut pulled_anywhere = 0;
    for (seed, budget) in [
        (3u64, RebraidParams::default().budget),
        (4, RebraidParams::default().budget),
        (3, RefBudget::Spare(0)),
        (4, RefBudget::Spare(20)),
    ] {
        let model = overlapping_model(seed);
        let world = model.world();
        let rays = random_rays(&mut rng(seed + 60), &world, 250, SCENE_LO, SCENE_HI);
        let (mut empty, mut pulled) = (Vec::new(), 0);
        for pull in [false, true] {
            let what = format!("seed {seed} {budget:?} pull {pull}");
            let mut scene = model.to_scene(rebraided(RebraidParams {
                pull_entry_nodes: pull,
                budget,
                // Grafting replaces entries too (its own test below).
                graft_max_prims: 0,
                ..Default::default()
            }));
            scene.commit().unwrap();
            let t = top(&scene);
            check_top(t, &model, &what);
            check_scene(&scene, &world, &rays, false, &what);
            let wide = t.wide.as_ref().expect("a top level");
            empty.push(wide.stats().empty_slots);
            if !pull {
                assert_eq!(t.entry_refs, t.refs, "{what}");
                continue;
            }
            pulled = t.entries.len() - t.refs.len();
            for node in &wide.nodes {
                let used = node.child_count();
                for &c in &node.child[..used] {
                    // Inner nodes, and copied blocks (no entry), pull nothing.
                    if !is_leaf_ref(c) || decode_leaf(c).0 >= t.block_base {
                        continue;
                    }
                    let e = t.entries[decode_leaf(c).0 as usize];
                    let Some(obj) = t.objects[e.object as usize].as_deref() else {
                        continue;
                    };
                    if let Some(ow) = &obj.wide
                        && !is_leaf_ref(e.wide)
                    {
                        let k = ow.wide.nodes[e.wide as usize].child_count();
                        assert!(k > 8 - used + 1, "{what}: a node has room for {k} children");
                    }
                }
            }
        }
        assert_eq!(
            empty[0] - empty[1],
            pulled,
            "seed {seed} {budget:?}: {empty:?}"
        );
        pulled_anywhere += pulled;
    }
    // Lists opened down to object leaves have nothing left to pull; the
    // small budgets leave object nodes behind top-level leaves.
    assert!(pulled_anywhere > 0, "nothing pulled in any configuration");
}

/// Copying the blocks of object leaves into the top level
/// (`RebraidParams::inline_leaf_blocks`, and with
/// `inline_instanced_leaves` the instanced ones in world space): the same
/// answers as brute force with and without it (with and without pulled
/// entry nodes), the copies checked against the objects' (transformed)
/// blocks by `validate`, and no top-level slot left entering a leaf it
/// could copy through an entry.
#[test]
fn inlined_leaf_blocks_answer_right() {
    use rebraid::bvh::wide::{decode_leaf, is_leaf_ref};
    for seed in [5u64, 6] {
        let model = overlapping_model(seed);
        let world = model.world();
        let rays = random_rays(&mut rng(seed + 70), &world, 250, SCENE_LO, SCENE_HI);
        for (inline, pull, instanced) in [
            (false, false, false),
            (true, false, false),
            (true, true, false),
            (true, false, true),
            (true, true, true),
        ] {
            let what = format!("seed {seed} inline {inline} pull {pull} instanced {instanced}");
            let mut scene = model.to_scene(rebraided(RebraidParams {
                inline_leaf_blocks: inline,
                inline_instanced_leaves: instanced,
                pull_entry_nodes: pull,
                ..Default::default()
            }));
            scene.commit().unwrap();
            let t = top(&scene);
            check_top(t, &model, &what);
            check_scene(&scene, &world, &rays, false, &what);
            assert_eq!(t.block_base as usize, t.entries.len(), "{what}");
            assert_eq!(t.blocks.len(), t.block_entry.len(), "{what}");
            if !inline {
                assert!(t.blocks.is_empty(), "{what}");
                continue;
            }
            assert!(!t.blocks.is_empty(), "{what}: nothing copied");
            // `validate` compares the copies with the objects' blocks.
            let mut bad = t.clone();
            bad.blocks[0].v[0][0][0] += 1.0;
            assert!(bad.validate().is_err(), "{what}: a changed copy passed");
            for node in &t.wide.as_ref().expect("a top level").nodes {
                for &c in &node.child[..node.child_count()] {
                    if !is_leaf_ref(c) || decode_leaf(c).0 >= t.block_base {
                        continue;
                    }
                    let e = t.entries[decode_leaf(c).0 as usize];
                    assert!(
                        (e.instance != INVALID_ID && !instanced) || !is_leaf_ref(e.wide),
                        "{what}: a leaf entered through an entry"
                    );
                }
            }
            // Instanced copies exist exactly when asked for.
            let instanced_copies = t
                .block_entry
                .iter()
                .filter(|&&ri| t.entries[ri as usize].instance != INVALID_ID)
                .count();
            assert_eq!(
                instanced_copies > 0,
                instanced,
                "{what}: {instanced_copies}"
            );
        }
    }
}

/// Object subtrees that top-level slots enter grafted into the top level
/// (`RebraidParams::graft_max_prims`): the same answers as brute force at
/// every graft size, with and without pulled entry nodes and copied
/// leaves, a valid top level (`check_top`: every placement's primitives
/// reachable once), and no slot left entering an inner object node of at
/// most that many primitives.
#[test]
fn grafted_entries_answer_right() {
    use rebraid::bvh::wide::{WIDE_EMPTY, decode_leaf, is_leaf_ref};
    for seed in [5u64, 6] {
        let model = overlapping_model(seed);
        let world = model.world();
        let rays = random_rays(&mut rng(seed + 110), &world, 250, SCENE_LO, SCENE_HI);
        let mut entries_at = Vec::new();
        // (size, budget per distinct primitive, share of the root area per
        // primitive past the budget, pull, inline); a budget of 0 grafts
        // nothing, one this large everything up to the size; a share this
        // small makes every entry dense (grafted up to the distinct
        // primitives), one this large none.
        for (graft, budget, share, pull, inline) in [
            (0, 1e6, 0.0, true, true),
            (8, 1e6, 0.0, true, true),
            (64, 1e6, 0.0, true, true),
            (64, 1e6, 0.0, false, true),
            (64, 1e6, 0.0, true, false),
            (u32::MAX, 1e6, 0.0, true, true),
            (u32::MAX, 0.0, 0.0, true, true),
            (u32::MAX, 0.1, 0.0, true, true),
            (u32::MAX, 1e-6, 0.0, true, true),
            (u32::MAX, 1e-6, 1e-12, true, true),
            (u32::MAX, 1e-6, 1e3, true, true),
        ] {
            let what = format!(
                "seed {seed} graft {graft} budget {budget} share {share} pull {pull} inline {inline}"
            );
            let mut scene = model.to_scene(rebraided(RebraidParams {
                graft_max_prims: graft,
                graft_budget: budget,
                graft_share_per_prim: share,
                pull_entry_nodes: pull,
                inline_leaf_blocks: inline,
                // A small budget leaves inner object nodes of every size
                // behind top-level leaves.
                budget: RefBudget::Spare(40),
                ..Default::default()
            }));
            scene.commit().unwrap();
            let t = top(&scene);
            check_top(t, &model, &what);
            check_scene(&scene, &world, &rays, false, &what);
            let mut inner_entries = 0;
            for node in &t.wide.as_ref().expect("a top level").nodes {
                for &c in &node.child[..node.child_count()] {
                    if !is_leaf_ref(c) || decode_leaf(c).0 >= t.block_base {
                        continue;
                    }
                    let (ri, _) = decode_leaf(c);
                    let e = t.entries[ri as usize];
                    if e.wide != WIDE_EMPTY && !is_leaf_ref(e.wide) {
                        inner_entries += 1;
                        assert!(
                            t.entry_refs[ri as usize].prims > graft || budget < 1e6,
                            "{what}: entry {ri} of {} primitives not grafted",
                            t.entry_refs[ri as usize].prims
                        );
                    }
                }
            }
            entries_at.push(inner_entries);
        }
        assert!(entries_at[0] > 0, "seed {seed}: no entries to graft");
        assert!(entries_at[2] < entries_at[0], "seed {seed}: {entries_at:?}");
        assert_eq!(entries_at[5], 0, "seed {seed}: entries left at any size");
        assert_eq!(
            entries_at[6], entries_at[0],
            "seed {seed}: grafted without budget"
        );
        assert!(
            0 < entries_at[7] && entries_at[7] < entries_at[0],
            "seed {seed}: a tenth of the primitives grafts some entries, not all: {entries_at:?}"
        );
        // Past a budget that grafts next to nothing: every entry dense
        // grafts what the distinct primitives allow, none dense adds none.
        assert!(
            entries_at[9] < entries_at[8],
            "seed {seed}: dense entries past the budget: {entries_at:?}"
        );
        assert_eq!(
            entries_at[10], entries_at[8],
            "seed {seed}: no entry dense: {entries_at:?}"
        );
    }
}

/// An instanced leaf copied into the top level in world space
/// (`RebraidParams::inline_instanced_leaves`) reports what the same leaf
/// reports through its entry: the same placement and primitive, `t`, `u`
/// and `v` within rounding, and the normal at the entry path's length
/// (its world cross product rescaled), mirroring instances included.
#[test]
fn instanced_leaf_copies_report_what_their_entries_report() {
    for seed in [5u64, 6, 7] {
        let model = overlapping_model(seed);
        let world = model.world();
        let rays = random_rays(&mut rng(seed + 90), &world, 400, SCENE_LO, SCENE_HI);
        let scene = |instanced: bool| {
            let mut s = model.to_scene(rebraided(RebraidParams {
                inline_instanced_leaves: instanced,
                ..Default::default()
            }));
            s.commit().unwrap();
            s
        };
        let (entered, copied) = (scene(false), scene(true));
        let mut compared = 0;
        for r in &rays {
            let (Some(a), Some(b)) = (entered.intersect(r), copied.intersect(r)) else {
                continue;
            };
            if (a.object_id, a.instance_id, a.prim_id) != (b.object_id, b.instance_id, b.prim_id) {
                // A tie or a grazing hit decided by rounding.
                continue;
            }
            // Barycentrics computed in another space differ by more than
            // `t` does on long rays to small triangles.
            let t_close = (a.t - b.t).abs() <= 1e-4 * a.t.abs().max(1.0);
            let uv_close = (a.u - b.u).abs() <= 2e-3 && (a.v - b.v).abs() <= 2e-3;
            assert!(t_close && uv_close, "seed {seed}: {a:?} {b:?}");
            assert!(
                (a.normal - b.normal).length() <= 1e-4 * a.normal.length(),
                "seed {seed}: normal {:?} through the entry, {:?} from the copy",
                a.normal,
                b.normal
            );
            compared += (a.instance_id != INVALID_ID) as usize;
        }
        assert!(
            compared > 20,
            "seed {seed}: {compared} instanced hits compared"
        );
    }
}

/// Objects placed by exactly one instance traced from world-space BVHs
/// (`RebraidParams::bake_single_instances`): the same answers as brute
/// force with and without it in both two-level modes, hits on them naming
/// their object and instance (`check_scene` compares ids), every placement
/// reachable once under its (object, instance) key (`check_top`), and the
/// baked objects' leaves copied into the top level like direct ones.
#[test]
fn baked_placements_answer_right() {
    for seed in [11u64, 12] {
        let (model, singles) = single_use_model(seed);
        let world = model.world();
        let rays = random_rays(&mut rng(seed + 80), &world, 300, SCENE_LO, SCENE_HI);
        for mode in [AccelMode::TwoLevel, AccelMode::Rebraided] {
            for bake in [false, true] {
                let what = format!("seed {seed} {mode:?} bake {bake}");
                let mut scene = model.to_scene(SceneParams {
                    mode,
                    rebraid: RebraidParams {
                        bake_single_instances: bake,
                        ..Default::default()
                    },
                    ..Default::default()
                });
                let rep = scene.commit().unwrap();
                let t = top(&scene);
                check_top(t, &model, &what);
                let tally = check_scene(&scene, &world, &rays, false, &what);
                assert!(tally.hits > 50, "{what}: {tally:?}");
                let mut baked = rep.instances_baked.clone();
                baked.sort_unstable();
                if !bake {
                    assert!(baked.is_empty() && t.baked.is_empty(), "{what}");
                    continue;
                }
                assert_eq!(baked, singles, "{what}");
                assert_eq!(t.baked.len(), singles.len(), "{what}");
                for &(obj, inst) in &t.baked {
                    assert_eq!(model.instances[&inst].0, obj, "{what}");
                }
                // Some rays hit a baked placement, and report it.
                let baked_hits = rays
                    .iter()
                    .filter_map(|r| scene.intersect(r))
                    .filter(|h| singles.contains(&h.instance_id))
                    .count();
                assert!(baked_hits > 0, "{what}: no ray hit a baked placement");
                // A baked slot entered through an instance fails validation.
                if let Some(i) = t.refs.iter().position(|r| r.object >= t.baked_base()) {
                    let mut bad = t.clone();
                    bad.refs[i].instance = 0;
                    assert!(bad.validate().is_err(), "{what}");
                }
            }
        }
    }
}
