use rebraid::glam::Vec3;
use rebraid::{BuildParams, MeshBvh, TriangleMesh};

fn main() -> anyhow::Result<()> {
    // Placeholder until the CLI issue: build a BVH over a generated grid and print its statistics.
    let n = 256u32;
    let positions: Vec<Vec3> = (0..=n)
        .flat_map(|j| (0..=n).map(move |i| Vec3::new(i as f32, (i as f32 * 0.1).sin() * (j as f32 * 0.1).cos(), j as f32)))
        .collect();
    let idx = |i: u32, j: u32| j * (n + 1) + i;
    let indices = (0..n)
        .flat_map(|j| (0..n).flat_map(move |i| [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)], [idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]]))
        .collect();
    let mesh = TriangleMesh::new(positions, indices)?;
    let t = std::time::Instant::now();
    let bvh = MeshBvh::build(&mesh, &BuildParams::default())?;
    println!("built a BVH over {} triangles in {:.1} ms: {:?}", mesh.len(), t.elapsed().as_secs_f64() * 1e3, bvh.stats());
    Ok(())
}
