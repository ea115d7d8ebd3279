//! Throwaway: placed objects grouped by shared vertex positions, merged per group; re-braided
//! commit time and Mrays/s against the ungrouped scene (one thread, alternating).
use rebraid::{AccelMode, ObjectDesc, Scene, SceneDesc, SceneParams, TriangleMesh};
use rebraid_cli::camera::{Camera, UpAxis};
use rebraid_cli::loaders::{LoadOptions, Split};
use rebraid_cli::raysets::RaySets;
use rebraid_cli::scene_input::SceneInput;
use std::collections::HashMap;

fn find(p: &mut [usize], mut x: usize) -> usize {
    while p[x] != x {
        p[x] = p[p[x]];
        x = p[x];
    }
    x
}

fn grouped(desc: &SceneDesc, min_shared: usize, rel: f64) -> anyhow::Result<SceneDesc> {
    let n = desc.objects.len();
    let mut owners: HashMap<[u32; 3], Vec<u32>> = HashMap::new();
    let mut nverts = vec![0usize; n];
    for (oi, o) in desc.objects.iter().enumerate() {
        if !o.placed || !desc.instances.iter().all(|i| i.object as usize != oi) {
            continue;
        }
        let mut seen = std::collections::HashSet::new();
        for t in 0..o.mesh.len() {
            for v in o.mesh.triangle(t) {
                let k = v.to_array().map(f32::to_bits);
                if seen.insert(k) {
                    let e = owners.entry(k).or_default();
                    e.push(oi as u32);
                }
            }
        }
        nverts[oi] = seen.len();
    }
    let mut pairs: HashMap<(u32, u32), usize> = HashMap::new();
    for v in owners.values() {
        for a in 0..v.len() {
            for b in a + 1..v.len() {
                *pairs.entry((v[a], v[b])).or_default() += 1;
            }
        }
    }
    let mut par: Vec<usize> = (0..n).collect();
    for (&(a, b), &c) in &pairs {
        let small = nverts[a as usize].min(nverts[b as usize]) as f64;
        if c >= min_shared && c as f64 >= rel * small {
            let (ra, rb) = (find(&mut par, a as usize), find(&mut par, b as usize));
            par[ra] = rb;
        }
    }
    let mut groups: HashMap<usize, Vec<usize>> = HashMap::new();
    for i in 0..n {
        let r = find(&mut par, i);
        groups.entry(r).or_default().push(i);
    }
    let mut out = desc.clone();
    out.objects.clear();
    let mut remap = vec![u32::MAX; n];
    let mut keys: Vec<usize> = groups.keys().copied().collect();
    keys.sort();
    let mut merged_objs = 0;
    for k in keys {
        let g = &groups[&k];
        let id = out.objects.len() as u32;
        for &i in g {
            remap[i] = id;
        }
        if g.len() == 1 {
            out.objects.push(desc.objects[g[0]].clone());
        } else {
            merged_objs += g.len();
            let parts: Vec<_> = g.iter().map(|&i| (&desc.objects[i].mesh, None)).collect();
            out.objects.push(ObjectDesc {
                name: format!("group{k}"),
                mesh: TriangleMesh::concat(&parts)?,
                placed: true,
            });
        }
    }
    for inst in &mut out.instances {
        inst.object = remap[inst.object as usize];
    }
    println!(
        "  min_shared {min_shared} rel {rel}: {} objects -> {} ({} merged)",
        n,
        out.objects.len(),
        merged_objs
    );
    Ok(out)
}

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
    let mk = |d: &SceneDesc| -> anyhow::Result<Scene> {
        let mut s = Scene::from_desc(
            d,
            SceneParams {
                mode: AccelMode::Rebraided,
                ..Default::default()
            },
        )?;
        s.commit()?;
        Ok(s)
    };
    let base = mk(&desc)?;
    let sets = RaySets::generate(&camera, 480, 270, &bounds, up, |r, h| {
        base.intersect_batch(r, h)
    });
    let configs: Vec<(usize, f64)> = std::env::var("CONFIGS")
        .unwrap_or("1:0".into())
        .split(',')
        .map(|c| {
            let mut it = c.split(':');
            (
                it.next().unwrap().parse().unwrap(),
                it.next().unwrap().parse().unwrap(),
            )
        })
        .collect();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    for (ms, rel) in configs {
        let d2 = grouped(&desc, ms, rel)?;
        pool.install(|| -> anyhow::Result<()> {
            let s2 = mk(&d2)?;
            let mut out = vec![None; sets.primary.len()];
            let mut occ = vec![false; sets.shadow.len()];
            let mut r = [Vec::new(), Vec::new(), Vec::new(), Vec::new()];
            for _ in 0..7 {
                let mut tm = [[0.0f64; 4]; 2];
                for (k, sc) in [&base, &s2].into_iter().enumerate() {
                    let t = std::time::Instant::now();
                    sc.intersect_batch(&sets.primary, &mut out);
                    tm[k][0] = t.elapsed().as_secs_f64();
                    let t = std::time::Instant::now();
                    sc.occluded_batch(&sets.shadow, &mut occ);
                    tm[k][1] = t.elapsed().as_secs_f64();
                    let t = std::time::Instant::now();
                    sc.intersect_batch(&sets.diffuse[..], &mut out[..sets.diffuse.len()]);
                    tm[k][2] = t.elapsed().as_secs_f64();
                    let d = if k == 0 { &desc } else { &d2 };
                    let mut s = Scene::from_desc(d, SceneParams { mode: AccelMode::Rebraided, ..Default::default() })?;
                    let t = std::time::Instant::now();
                    s.commit()?;
                    tm[k][3] = t.elapsed().as_secs_f64();
                }
                for j in 0..4 {
                    r[j].push(tm[0][j] / tm[1][j]);
                }
            }
            for v in &mut r {
                v.sort_by(|a, b| a.total_cmp(b));
            }
            println!("    grouped over default (speed ratios; build: default time / grouped time): primary {:.3} shadow {:.3} diffuse {:.3} build {:.3}", r[0][3], r[1][3], r[2][3], r[3][3]);
            Ok(())
        })?;
    }
    Ok(())
}
