//! Experiment (issue 6): packets of eight coherent rays against single-ray
//! traversal of the same 8-wide BVH, one thread, AVX2.
//!
//! The packet kernel walks the tree once for eight rays (a 4x2 pixel tile):
//! at each node every still-active ray runs the single-ray kernel's 8-wide
//! box test (the same conservative FMA slab test with per-axis offsets), the
//! union of their hit masks decides which children the packet visits, and
//! each child is entered with the mask of the rays that hit it (an 8x8 bit
//! transpose). Children are ordered by the first active ray's entry
//! distance; a popped entry is skipped when no ray of its mask can still
//! find a nearer hit. Leaves run the `Triangle4` test for each ray of the
//! mask, so hits are the single-ray kernel's: before anything is timed,
//! every ray's closest `t` and occlusion answer are checked against
//! `WideMeshBvh<8>`'s AVX2 kernel. What packets share is the node fetch and
//! the loop (stack, ordering, branches); what they lose is the rays that
//! are dragged into nodes they miss (masked off, but the node is fetched).
//!
//! Run: `cargo bench -p rebraid --bench packets` (skips on CPUs without
//! the AVX2 level). Result and decision: `docs/performance.md`.

#[path = "../tests/common/mod.rs"]
mod common;
mod support;

use std::arch::x86_64::*;

use divan::counter::ItemsCount;
use divan::{Bencher, black_box};
use rebraid::bvh::triangle4::{LeafHit, Triangle4, block_hit_record, intersect_blocks};
use rebraid::bvh::wide::{WIDE_EMPTY, decode_leaf, is_leaf_ref};
use rebraid::bvh::{FmaSlab, Kernel, ROBUST_FAR, WideMeshBvh, WideNode};
use rebraid::glam::Vec3;
use rebraid::triangle::WatertightRay;
use rebraid::{BuildParams, MeshBvh, Ray};

fn main() {
    support::avx2_experiment_main("packet", &SCENES, prepared);
}

const SCENES: [&str; 3] = ["generated_1m", "openarena_oa_thor", "samurai_monastery"];
/// A square image of camera rays, traced in 4x2 tiles.
const SIDE: usize = 256;
const VARIANTS: [&str; 2] = ["single", "packet8"];

/// One ray's box-test constants, as the library's AVX2 tester keeps them.
#[derive(Clone, Copy)]
struct RayBox {
    near_plane: [usize; 3],
    far_plane: [usize; 3],
    inv: [__m256; 3],
    near_off: [__m256; 3],
    far_off: [__m256; 3],
    t_min: __m256,
}

/// `None` for a ray with a zero direction component (the experiment leaves
/// those packets to the single-ray kernel, whose exact path handles them).
fn ray_box(ray: &Ray) -> Option<RayBox> {
    // The library kernel's own constants.
    let slab = FmaSlab::new(ray.origin, ray.dir);
    if !slab.is_finite() {
        return None;
    }
    let splat = |v: Vec3| -> [__m256; 3] { [v.x, v.y, v.z].map(|x| bytemuck::cast([x; 8])) };
    Some(RayBox {
        near_plane: slab.near_plane,
        far_plane: slab.far_plane,
        inv: splat(slab.inv_dir),
        near_off: splat(slab.near_offset),
        far_off: splat(slab.far_offset),
        t_min: bytemuck::cast([ray.t_min; 8]),
    })
}

/// The single-ray kernel's 8-wide box test: hit mask, and the entry
/// distances with `+inf` in the lanes missed.
///
/// # Safety
/// The CPU has the AVX2 level.
#[inline(always)]
unsafe fn test_node(b: &RayBox, node: &WideNode<8>, t_max: f32) -> (u32, __m256) {
    let p = node.planes();
    // SAFETY: the AVX2 level per the contract; each load reads one `[f32; 8]`.
    unsafe {
        let mut near = b.t_min;
        let mut far = _mm256_set1_ps(t_max);
        for a in 0..3 {
            let pn = _mm256_loadu_ps(p[b.near_plane[a]].as_ptr());
            let pf = _mm256_loadu_ps(p[b.far_plane[a]].as_ptr());
            near = _mm256_max_ps(near, _mm256_fmsub_ps(pn, b.inv[a], b.near_off[a]));
            far = _mm256_min_ps(far, _mm256_fmsub_ps(pf, b.inv[a], b.far_off[a]));
        }
        far = _mm256_mul_ps(far, _mm256_set1_ps(ROBUST_FAR));
        let hit = _mm256_cmp_ps::<_CMP_LE_OQ>(near, far);
        let dist = _mm256_blendv_ps(_mm256_set1_ps(f32::INFINITY), near, hit);
        (_mm256_movemask_ps(hit) as u32, dist)
    }
}

/// Transpose an 8x8 bit matrix held as eight row bytes: bit `c` of row `r`
/// becomes bit `r` of row `c` (rays' child masks -> children's ray masks).
#[inline(always)]
fn transpose8(rows: [u8; 8]) -> [u8; 8] {
    let mut x = u64::from_le_bytes(rows);
    // Knuth's three delta swaps of 1x1, 2x2 and 4x4 blocks.
    let t = (x ^ (x >> 7)) & 0x00AA_00AA_00AA_00AA;
    x ^= t ^ (t << 7);
    let t = (x ^ (x >> 14)) & 0x0000_CCCC_0000_CCCC;
    x ^= t ^ (t << 14);
    let t = (x ^ (x >> 28)) & 0x0000_0000_F0F0_F0F0;
    x ^= t ^ (t << 28);
    x.to_le_bytes()
}

/// Closest hits of eight rays walked as one packet; `None` when some ray
/// has a zero direction component.
///
/// # Safety
/// The CPU must have the AVX2 level.
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
unsafe fn intersect_packet(
    nodes: &[WideNode<8>],
    blocks: &[Triangle4],
    rays: &[Ray; 8],
) -> Option<[Option<LeafHit>; 8]> {
    let mut boxes = [None; 8];
    for (b, r) in boxes.iter_mut().zip(rays) {
        *b = Some(ray_box(r)?);
    }
    let boxes = boxes.map(|b| b.expect("set above"));
    let wrays = rays.each_ref().map(|r| WatertightRay::new(r.origin, r.dir));
    let mut t_max = rays.each_ref().map(|r| r.t_max);
    let mut best: [Option<LeafHit>; 8] = [None; 8];
    // Entries: (node, ray mask, nearest entry distance of those rays).
    let mut stack = [(0u32, 0u8, 0.0f32); 7 * 64];
    let mut sp = 0usize;
    let (mut current, mut active) = (0u32, 0xFFu8);
    loop {
        if !is_leaf_ref(current) {
            let node = &nodes[current as usize];
            let mut rows = [0u8; 8];
            let mut nearest = _mm256_set1_ps(f32::INFINITY);
            let mut lanes = active;
            while lanes != 0 {
                let r = lanes.trailing_zeros() as usize;
                lanes &= lanes - 1;
                // SAFETY: the AVX2 level per this function's contract.
                let (mask, dist) = unsafe { test_node(&boxes[r], node, t_max[r]) };
                rows[r] = mask as u8;
                nearest = _mm256_min_ps(nearest, dist);
            }
            if rows != [0; 8] {
                let mut dist = [0.0f32; 8];
                // SAFETY: AVX per this function's contract; one `[f32; 8]`.
                unsafe { _mm256_storeu_ps(dist.as_mut_ptr(), nearest) };
                let masks = transpose8(rows);
                // Children in order of their nearest entry over the rays.
                let mut hits = [(0.0f32, 0u32, 0u8); 8];
                let mut n = 0;
                for (c, &m) in masks.iter().enumerate() {
                    if m == 0 {
                        continue;
                    }
                    let item = (dist[c], node.child[c], m);
                    let mut j = n;
                    while j > 0 && hits[j - 1].0 > item.0 {
                        hits[j] = hits[j - 1];
                        j -= 1;
                    }
                    hits[j] = item;
                    n += 1;
                }
                for &(d, r, m) in hits[1..n].iter().rev() {
                    stack[sp] = (r, m, d);
                    sp += 1;
                }
                (current, active) = (hits[0].1, hits[0].2);
                continue;
            }
        } else if current != WIDE_EMPTY {
            let (first, count) = decode_leaf(current);
            let mut lanes = active;
            while lanes != 0 {
                let r = lanes.trailing_zeros() as usize;
                lanes &= lanes - 1;
                intersect_blocks::<false>(
                    blocks,
                    &wrays[r],
                    rays[r].t_min,
                    first,
                    count,
                    &mut t_max[r],
                    &mut best[r],
                    true,
                );
            }
        }
        // Pop, keeping the rays of the entry that may still hit nearer: a
        // ray's own entry distance is at least the entry's nearest one.
        loop {
            if sp == 0 {
                return Some(best);
            }
            sp -= 1;
            let (r, m, d) = stack[sp];
            let mut still = 0u8;
            let mut lanes = m;
            while lanes != 0 {
                let k = lanes.trailing_zeros() as usize;
                lanes &= lanes - 1;
                if d <= t_max[k] * ROBUST_FAR {
                    still |= 1 << k;
                }
            }
            if still != 0 {
                (current, active) = (r, still);
                break;
            }
        }
    }
}

struct Prepared {
    w8: WideMeshBvh<8>,
    /// Camera rays in 4x2 tiles (eight consecutive rays are one tile).
    tiles: Vec<[Ray; 8]>,
    /// Random rays (origins in the box, any direction) in eights: what
    /// packets cost when the rays do not share a path.
    random: Vec<[Ray; 8]>,
}

fn tiled_camera_rays(rays: &[Ray]) -> Vec<[Ray; 8]> {
    let mut out = Vec::with_capacity(rays.len() / 8);
    for ty in 0..SIDE / 2 {
        for tx in 0..SIDE / 4 {
            out.push(std::array::from_fn(|i| {
                let (x, y) = (4 * tx + i % 4, 2 * ty + i / 4);
                rays[y * SIDE + x]
            }));
        }
    }
    out
}

fn prepared(name: &'static str) -> Option<&'static Prepared> {
    static CACHE: support::SceneCache<Prepared> = support::SceneCache::new();
    support::cached(&CACHE, name, || {
        let mesh = support::load(name)?;
        let bvh = MeshBvh::build(&mesh, &BuildParams::default()).unwrap();
        let w8 = WideMeshBvh::<8>::from_mesh(&bvh).unwrap();
        w8.validate().unwrap();
        let rays = support::camera_rays(&mesh.bounds(), SIDE * SIDE);
        let random = support::random_rays(&mesh.bounds(), SIDE * SIDE);
        let p = Prepared {
            w8,
            tiles: tiled_camera_rays(&rays),
            random: random
                .chunks_exact(8)
                .map(|c| std::array::from_fn(|i| c[i]))
                .collect(),
        };
        let mut bad = 0;
        for tile in p.tiles.iter().chain(&p.random) {
            let want = tile.each_ref().map(|r| {
                p.w8.intersect_with(Kernel::Avx2, r)
                    .map(|h| (h.t.to_bits(), h.prim_id))
            });
            let got = packet_hits(&p, tile);
            bad += want.iter().zip(&got).filter(|(a, b)| a != b).count();
        }
        assert_eq!(bad, 0, "{name}: the packet kernel disagrees on {bad} rays");
        eprintln!("{name}: {} packets; answers agree", p.tiles.len());
        Some(p)
    })
}

/// Each ray's closest (t bits, primitive id) by the packet kernel (or the
/// single-ray kernel for a packet it declines). Each hit's normal is made
/// as the single-ray kernel's hit record makes it, so that both variants
/// do the same work per hit.
fn packet_hits(p: &Prepared, tile: &[Ray; 8]) -> [Option<(u32, u32)>; 8] {
    // SAFETY: `main` checked the AVX2 level.
    match unsafe { intersect_packet(&p.w8.wide.nodes, &p.w8.blocks, tile) } {
        Some(hits) => hits.map(|h| {
            h.map(|(t, _, _, k)| {
                let (prim, normal) = block_hit_record(&p.w8.blocks, k);
                black_box(normal);
                (t.to_bits(), prim)
            })
        }),
        None => tile.each_ref().map(|r| {
            p.w8.intersect_with(Kernel::Avx2, r)
                .map(|h| (h.t.to_bits(), h.prim_id))
        }),
    }
}

fn trace(bencher: Bencher, case: &str, coherent: bool) {
    let Some((p, variant)) = support::case(case, &SCENES, prepared) else {
        return;
    };
    let packets = variant == "packet8";
    let tiles = if coherent { &p.tiles } else { &p.random };
    bencher
        .counter(ItemsCount::new(tiles.len() * 8))
        .bench_local(|| {
            let mut n = 0usize;
            for tile in black_box(tiles) {
                if packets {
                    n += packet_hits(p, tile).iter().flatten().count();
                } else {
                    for r in tile {
                        n += p.w8.intersect_with(Kernel::Avx2, r).is_some() as usize;
                    }
                }
            }
            n
        });
}

fn cases() -> Vec<&'static str> {
    support::cases(&SCENES, &VARIANTS)
}

#[divan::bench(args = cases(), sample_count = 8)]
fn closest_camera_tiles(b: Bencher, case: &str) {
    trace(b, case, true);
}
#[divan::bench(args = cases(), sample_count = 8)]
fn closest_random_eights(b: Bencher, case: &str) {
    trace(b, case, false);
}
