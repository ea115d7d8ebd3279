//! Throwaway: the top of the flat tree, node by node.
use rebraid::Aabb;
use rebraid::bvh::{BuildParams, build_bvh};
use rebraid_cli::loaders::{LoadOptions, Split};
use rebraid_cli::scene_input::SceneInput;

fn main() -> anyhow::Result<()> {
    let arg = std::env::args().nth(1).unwrap();
    let depth_max: usize = std::env::args()
        .nth(2)
        .map(|s| s.parse().unwrap())
        .unwrap_or(5);
    let input = SceneInput::parse(&arg, 0.25, 1)?;
    let opts = LoadOptions {
        split: Split::Object,
        flatten_instances: false,
    };
    let (desc, _) = input.load(&opts)?;
    let mut boxes = Vec::new();
    let mut cents = Vec::new();
    let mut obj = Vec::new();
    for (oi, o) in desc.objects.iter().enumerate() {
        if !o.placed {
            continue;
        }
        for i in 0..o.mesh.len() {
            let t = o.mesh.triangle(i);
            let b = Aabb::from_points(&t);
            boxes.push(b);
            cents.push(b.center());
            obj.push(oi);
        }
    }
    let bvh = build_bvh(&boxes, &cents, &BuildParams::default())?;
    let root = bvh.nodes[0].bounds();
    let (ra, rv) = (root.half_area(), root.volume());
    fn count(bvh: &rebraid::bvh::Bvh, n: usize) -> usize {
        let nd = &bvh.nodes[n];
        if nd.is_leaf() {
            nd.count as usize
        } else {
            count(bvh, nd.index as usize) + count(bvh, nd.index as usize + 1)
        }
    }
    let mut stack = vec![(0usize, 0usize)];
    while let Some((n, d)) = stack.pop() {
        let nd = &bvh.nodes[n];
        let b = nd.bounds();
        let c = count(&bvh, n);
        let e = b.extent();
        let mut line = format!(
            "{}{} n={} area={:.3} vol={:.4} ext=({:.1},{:.1},{:.1})",
            "  ".repeat(d),
            n,
            c,
            b.half_area() / ra,
            b.volume() / rv,
            e.x,
            e.y,
            e.z
        );
        if nd.is_leaf() || c <= 16 {
            let mut names: Vec<&str> = Vec::new();
            let mut st = vec![n];
            while let Some(m) = st.pop() {
                let x = &bvh.nodes[m];
                if x.is_leaf() {
                    for k in x.prim_range() {
                        let p = bvh.prim_indices[k] as usize;
                        let nm = desc.objects[obj[p]].name.as_str();
                        if !names.contains(&nm) {
                            names.push(nm);
                        }
                    }
                } else {
                    st.push(x.index as usize);
                    st.push(x.index as usize + 1);
                }
            }
            line += &format!(" objs={:?}", names);
        }
        println!("{line}");
        if !nd.is_leaf() && d < depth_max && c > 16 {
            stack.push((nd.index as usize + 1, d + 1));
            stack.push((nd.index as usize, d + 1));
        }
    }
    Ok(())
}
