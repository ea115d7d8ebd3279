//! Quick cross-mode sanity check of the scene (fuller suites live in scene_*.rs).
use rand::{Rng, SeedableRng};
use rebraid::glam::{Affine3A, Quat, Vec3};
use rebraid::scene::Accel;
use rebraid::*;

fn soup(rng: &mut impl Rng, n: usize, spread: f32) -> TriangleMesh {
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|_| {
            let c = Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) * spread;
            let mut v = || c + (Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) - 0.5) * 0.6;
            [v(), v(), v()]
        })
        .collect();
    TriangleMesh::from_triangles(&tris).unwrap()
}

#[test]
fn modes_agree_on_overlapping_instanced_scene() {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
    let mut scene = Scene::new();
    for _ in 0..12 {
        let m = soup(&mut rng, 400, 10.0);
        scene.add_object(m).unwrap();
    }
    let proto = scene.add_prototype(soup(&mut rng, 300, 2.0)).unwrap();
    for _ in 0..20 {
        let t = Affine3A::from_scale_rotation_translation(
            Vec3::new(
                rng.gen_range(0.3..2.0),
                rng.gen_range(0.3..2.0),
                rng.gen_range(-2.0..-0.3),
            ),
            Quat::from_euler(
                rebraid::glam::EulerRot::XYZ,
                rng.r#gen(),
                rng.r#gen(),
                rng.r#gen(),
            ),
            Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) * 10.0,
        );
        scene.add_instance(proto, t).unwrap();
    }
    let rays: Vec<Ray> = (0..20000)
        .map(|_| {
            let o = Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) * 14.0 - 2.0;
            let d = Vec3::new(rng.r#gen(), rng.r#gen(), rng.r#gen()) - 0.5;
            Ray::infinite(o, d)
        })
        .collect();
    let mut results = Vec::new();
    for mode in AccelMode::ALL {
        scene.set_mode(mode);
        let rep = scene.commit().unwrap();
        let st = scene.stats();
        println!(
            "{mode:?}: {rep:?}\n  sah {:.2} bytes {}",
            st.sah_cost, st.bytes
        );
        if let Accel::TopLevel(t) = scene.accel() {
            let counts = t.reachable_counts();
            assert_eq!(counts.len(), 12 + 20);
            for c in counts.values() {
                assert!(c.iter().all(|&x| x == 1));
            }
        }
        let mut hits = vec![None; rays.len()];
        scene.intersect_batch(&rays, &mut hits);
        let mut occ = vec![false; rays.len()];
        scene.occluded_batch(&rays, &mut occ);
        results.push((hits, occ));
    }
    let (h0, o0) = &results[0];
    for (h, o) in &results[1..] {
        let mut mismatches = 0;
        for i in 0..rays.len() {
            assert_eq!(h0[i].is_some(), o0[i]);
            assert_eq!(h[i].is_some(), o[i]);
            match (h0[i], h[i]) {
                (Some(a), Some(b)) => {
                    assert!((a.t - b.t).abs() <= 1e-4 * a.t.max(1.0), "{a:?} {b:?}");
                    if (a.object_id, a.instance_id, a.prim_id)
                        != (b.object_id, b.instance_id, b.prim_id)
                    {
                        mismatches += 1;
                    }
                }
                (None, None) => {}
                (a, b) => panic!("ray {i}: {a:?} vs {b:?}"),
            }
        }
        assert!(mismatches < 5, "{mismatches}");
    }
}
