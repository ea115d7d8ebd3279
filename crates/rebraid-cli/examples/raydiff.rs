//! Throwaway: per diffuse ray, re-braided visits minus flat visits, summed by the object the ray starts on.
use rebraid::bvh::TraversalCounters;
use rebraid::{AccelMode, Scene, SceneParams};
use rebraid_cli::camera::{Camera, UpAxis};
use rebraid_cli::loaders::{LoadOptions, Split};
use rebraid_cli::raysets::RaySets;
use rebraid_cli::scene_input::SceneInput;

fn main() -> anyhow::Result<()> {
    let arg = std::env::args().nth(1).unwrap();
    let input = SceneInput::parse(&arg, 0.25, 1)?;
    let opts = LoadOptions {
        split: Split::Object,
        flatten_instances: false,
    };
    let (desc, _) = input.load(&opts)?;
    let (_, bounds) = desc.world_boxes();
    let up = UpAxis::Auto.resolve(&bounds);
    let camera = Camera::fit(&bounds, up);
    let mk = |mode| -> anyhow::Result<Scene> {
        let mut s = Scene::from_desc(
            &desc,
            SceneParams {
                mode,
                ..Default::default()
            },
        )?;
        s.commit()?;
        Ok(s)
    };
    let flat = mk(AccelMode::Flat)?;
    if let Ok(pat) = std::env::var("MERGE") {
        let pats: Vec<&str> = pat.split(',').collect();
        let mut d2 = desc.clone();
        let (sel, rest): (Vec<_>, Vec<_>) = d2
            .objects
            .drain(..)
            .partition(|o| o.placed && pats.iter().any(|p| o.name.contains(p)));
        let parts: Vec<_> = sel.iter().map(|o| (&o.mesh, None)).collect();
        let mesh = rebraid::TriangleMesh::concat(&parts)?;
        println!("merged {} objects, {} tris", sel.len(), mesh.len());
        d2.objects = rest;
        d2.objects.push(rebraid::ObjectDesc {
            name: "merged".into(),
            mesh,
            placed: true,
        });
        let mut s = Scene::from_desc(
            &d2,
            SceneParams {
                mode: AccelMode::Rebraided,
                ..Default::default()
            },
        )?;
        s.commit()?;
        let sets = RaySets::generate(&camera, 480, 270, &bounds, up, |r, h| {
            flat.intersect_batch(r, h)
        });
        for sc in [&flat, &s] {
            let mut c = TraversalCounters::default();
            for r in &sets.diffuse {
                sc.intersect_counted(r, &mut c);
            }
            let n = sets.diffuse.len() as f64;
            println!(
                "inner {:.2} leaves {:.2} entries {:.2}",
                c.inner_visited as f64 / n,
                c.leaves_visited as f64 / n,
                c.entries_visited as f64 / n
            );
        }
        let base = mk(AccelMode::Rebraided)?;
        let mut out = vec![None; sets.diffuse.len()];
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
        pool.install(|| {
            let mut rat = Vec::new();
            for _ in 0..9 {
                let t = std::time::Instant::now();
                base.intersect_batch(&sets.diffuse, &mut out);
                let a = t.elapsed().as_secs_f64();
                let t = std::time::Instant::now();
                s.intersect_batch(&sets.diffuse, &mut out);
                let b = t.elapsed().as_secs_f64();
                let t = std::time::Instant::now();
                flat.intersect_batch(&sets.diffuse, &mut out);
                let c = t.elapsed().as_secs_f64();
                rat.push((a / b, a / c));
            }
            rat.sort_by(|x, y| x.0.total_cmp(&y.0));
            println!("merged-group over default (speed): median {:.3}", rat[4].0);
            rat.sort_by(|x, y| x.1.total_cmp(&y.1));
            println!("flat over default (speed): median {:.3}", rat[4].1);
        });
        return Ok(());
    }
    let rb = mk(AccelMode::Rebraided)?;
    let sets = RaySets::generate(&camera, 480, 270, &bounds, up, |r, h| {
        flat.intersect_batch(r, h)
    });
    let mut hits = vec![None; sets.primary.len()];
    flat.intersect_batch(&sets.primary, &mut hits);
    let origins: Vec<u32> = hits
        .iter()
        .flatten()
        .filter(|h| h.normal != rebraid::glam::Vec3::ZERO)
        .map(|h| h.object_id)
        .collect();
    assert_eq!(origins.len(), sets.diffuse.len());
    let nobj = desc.objects.len();
    let mut by_origin = vec![(0u64, 0i64, 0i64); nobj];
    let mut by_hit = vec![(0u64, 0i64); nobj + 1];
    let (mut tf, mut tr) = (0u64, 0u64);
    for (r, &o) in sets.diffuse.iter().zip(&origins) {
        let mut cf = TraversalCounters::default();
        let mut cr = TraversalCounters::default();
        let h = flat.intersect_counted(r, &mut cf);
        rb.intersect_counted(r, &mut cr);
        let f = (cf.inner_visited + cf.leaves_visited) as i64;
        let b = (cr.inner_visited + cr.leaves_visited) as i64;
        tf += f as u64;
        tr += b as u64;
        let e = &mut by_origin[o as usize];
        e.0 += 1;
        e.1 += b - f;
        e.2 += f;
        let hk = h.map(|h| h.object_id as usize).unwrap_or(nobj);
        by_hit[hk].0 += 1;
        by_hit[hk].1 += b - f;
    }
    let n = sets.diffuse.len() as f64;
    println!(
        "rays {} flat {:.2} rb {:.2} per ray",
        n,
        tf as f64 / n,
        tr as f64 / n
    );
    let mut v: Vec<usize> = (0..nobj).collect();
    v.sort_by_key(|&i| -by_origin[i].1);
    println!("by origin object: name rays excess/ray flat/ray share-of-excess");
    let total_ex = (tr as i64 - tf as i64) as f64;
    for &i in v.iter().take(15) {
        let (c, ex, f) = by_origin[i];
        if c == 0 {
            continue;
        }
        let m = &desc.objects[i];
        let b = m.mesh.bounds();
        println!(
            "{:<28} tris {:>6} rays {:>6} excess {:>6.2} flat {:>6.2} share {:.3} area {:.3}",
            m.name,
            m.mesh.len(),
            c,
            ex as f64 / c as f64,
            f as f64 / c as f64,
            ex as f64 / total_ex,
            b.half_area() / bounds.half_area()
        );
    }
    let mut v: Vec<usize> = (0..=nobj).collect();
    v.sort_by_key(|&i| -by_hit[i].1);
    println!("by hit object:");
    for &i in v.iter().take(8) {
        let (c, ex) = by_hit[i];
        let name = if i == nobj {
            "(miss)"
        } else {
            desc.objects[i].name.as_str()
        };
        println!(
            "{:<28} rays {:>6} excess {:>6.2} share {:.3}",
            name,
            c,
            ex as f64 / c.max(1) as f64,
            ex as f64 / total_ex
        );
    }
    Ok(())
}
