//! Experiment (issue 6): a quantised 8-wide node layout against the
//! uncompressed one, one thread, AVX2.
//!
//! `QuantizedNode8` stores each child box as 8-bit offsets on a per-node
//! grid (Ylitie, Karras, Laine, "Efficient Incoherent Ray Traversal on GPUs
//! Through Compressed Wide BVHs", HPG 2017; Embree's `QBVH8`): the node's
//! origin and a power-of-two scale per axis, then `lo`/`hi` bytes per child
//! and axis, rounded outwards and checked in `f32` with the same fused
//! multiply-add the kernel dequantises with, so every dequantised box
//! contains its child's box. 128 bytes (two cache lines) against the
//! 224-byte `WideNode<8>` (3.5 lines); the price is two byte-to-float
//! conversions and two FMAs more per axis and node. Leaves are the same
//! `Triangle4` blocks, so hits are identical: before anything is timed the
//! quantised kernel's closest `t` and occlusion are checked against the
//! `WideMeshBvh<8>` AVX2 kernel on every ray.
//!
//! Run: `cargo bench -p rebraid --bench quantized` (prints the sizes; skips
//! on CPUs without the AVX2 level). Result and decision: `docs/performance.md`.

#[path = "../tests/common/mod.rs"]
mod common;
mod support;

use divan::counter::ItemsCount;
use divan::{Bencher, black_box};
use rebraid::bvh::triangle4::{LeafHit, Triangle4, intersect_blocks};
use rebraid::bvh::wide::{WIDE_EMPTY, decode_leaf, is_leaf_ref};
use rebraid::bvh::{FmaSlab, Kernel, ROBUST_FAR, WideMeshBvh, WideNode};
use rebraid::triangle::WatertightRay;
use rebraid::{BuildParams, MeshBvh, Ray};

fn main() {
    support::avx2_experiment_main("quantised", &SCENES, prepared);
}

const SCENES: [&str; 3] = ["generated_1m", "openarena_oa_thor", "samurai_monastery"];
const RAYS: usize = 256 * 256;
const VARIANTS: [&str; 3] = ["w8_avx2", "w8_local", "q8_avx2"];

/// A quantised 8-wide node: child box planes as bytes on a per-node grid.
/// `q` holds `[lo_x, lo_y, lo_z, hi_x, hi_y, hi_z]` (the plane order of
/// `WideNode::planes`, so the same near/far selection applies); a plane is
/// `fma(q, scale, origin)`. Empty slots have `lo = 255`, `hi = 0`, an
/// inverted box no ray enters.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct QuantizedNode8 {
    origin: [f32; 3],
    scale: [f32; 3],
    child: [u32; 8],
    q: [[u8; 8]; 6],
}

const _: () = assert!(std::mem::size_of::<QuantizedNode8>() == 128);

fn quantize(node: &WideNode<8>) -> QuantizedNode8 {
    let n = node.child_count();
    let mut q = QuantizedNode8 {
        origin: [0.0; 3],
        scale: [1.0; 3],
        child: node.child,
        q: [[255; 8], [255; 8], [255; 8], [0; 8], [0; 8], [0; 8]],
    };
    for axis in 0..3 {
        let planes = node.planes();
        let lo = planes[axis][..n]
            .iter()
            .copied()
            .fold(f32::INFINITY, f32::min);
        let hi = planes[axis + 3][..n]
            .iter()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max);
        let extent = (hi as f64 - lo as f64) / 255.0;
        // A power of two: `q * scale` is exact, so a plane rounds once.
        let scale = if extent > 0.0 {
            2f32.powi(extent.log2().ceil() as i32)
        } else {
            1.0
        };
        q.origin[axis] = lo;
        q.scale[axis] = scale;
        let deq = |k: u8| (k as f32).mul_add(scale, lo);
        let (mins, maxs) = (&planes[axis][..n], &planes[axis + 3][..n]);
        for (slot, (&bmin, &bmax)) in mins.iter().zip(maxs).enumerate() {
            let mut k = ((bmin - lo) / scale).floor().clamp(0.0, 255.0) as u8;
            while k > 0 && deq(k) > bmin {
                k -= 1;
            }
            let mut m = ((bmax - lo) / scale).ceil().clamp(0.0, 255.0) as u8;
            while m < 255 && deq(m) < bmax {
                m += 1;
            }
            assert!(
                deq(k) <= bmin && deq(m) >= bmax,
                "quantised box must contain the child's"
            );
            q.q[axis][slot] = k;
            q.q[axis + 3][slot] = m;
        }
    }
    q
}

/// A node layout the experiment's kernel can test: its child references
/// and, per axis, its eight near and far planes for a ray.
trait Node8 {
    fn child(&self) -> &[u32; 8];
    /// # Safety
    /// The CPU has the AVX2 level.
    unsafe fn planes(
        &self,
        near_plane: usize,
        far_plane: usize,
        axis: usize,
    ) -> (std::arch::x86_64::__m256, std::arch::x86_64::__m256);
}

impl Node8 for QuantizedNode8 {
    #[inline(always)]
    fn child(&self) -> &[u32; 8] {
        &self.child
    }
    #[inline(always)]
    unsafe fn planes(
        &self,
        near_plane: usize,
        far_plane: usize,
        a: usize,
    ) -> (std::arch::x86_64::__m256, std::arch::x86_64::__m256) {
        use std::arch::x86_64::*;
        // SAFETY: AVX2 per the contract; each load reads one `[u8; 8]` row.
        unsafe {
            let scale = _mm256_set1_ps(self.scale[a]);
            let origin = _mm256_set1_ps(self.origin[a]);
            let rn = self.q[near_plane].as_ptr() as *const __m128i;
            let rf = self.q[far_plane].as_ptr() as *const __m128i;
            let qn = _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_loadl_epi64(rn)));
            let qf = _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_loadl_epi64(rf)));
            (
                _mm256_fmadd_ps(qn, scale, origin),
                _mm256_fmadd_ps(qf, scale, origin),
            )
        }
    }
}

impl Node8 for WideNode<8> {
    #[inline(always)]
    fn child(&self) -> &[u32; 8] {
        &self.child
    }
    #[inline(always)]
    unsafe fn planes(
        &self,
        near_plane: usize,
        far_plane: usize,
        _a: usize,
    ) -> (std::arch::x86_64::__m256, std::arch::x86_64::__m256) {
        use std::arch::x86_64::*;
        let p = self.planes();
        // SAFETY: AVX2 per the contract; each load reads one `[f32; 8]`.
        unsafe {
            (
                _mm256_loadu_ps(p[near_plane].as_ptr()),
                _mm256_loadu_ps(p[far_plane].as_ptr()),
            )
        }
    }
}

/// Closest (or any) hit with the quantised nodes; `None` from the outer
/// `Option` when the ray has a zero direction component (the experiment
/// leaves those to the uncompressed kernel).
///
/// # Safety
/// The CPU must have the AVX2 level.
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt")]
unsafe fn query_quantized<const ANY: bool, N: Node8>(
    nodes: &[N],
    blocks: &[Triangle4],
    ray: &Ray,
) -> Option<Option<LeafHit>> {
    use std::arch::x86_64::*;
    // The library kernel's own constants.
    let slab = FmaSlab::new(ray.origin, ray.dir);
    if !slab.is_finite() {
        return None;
    }
    let (inv, n_off, f_off) = (slab.inv_dir, slab.near_offset, slab.far_offset);
    let (near_plane, far_plane) = (slab.near_plane, slab.far_plane);
    let wray = WatertightRay::new(ray.origin, ray.dir);
    let mut t_max = ray.t_max;
    let mut best: Option<LeafHit> = None;
    // The same loop as the library's `traverse` (fixed stack, insertion
    // sort for closest hits, slot order for occlusion), so that only the
    // node layout differs.
    let mut stack = [std::mem::MaybeUninit::<(u32, f32)>::uninit(); 7 * 64];
    let mut sp = 0usize;
    let mut current = 0u32;
    // SAFETY: the AVX2 level per this function's contract; every load reads
    // 8 bytes of one `[u8; 8]` row of a node; stack entries below `sp` were
    // written before they are read.
    unsafe {
        loop {
            if !is_leaf_ref(current) {
                let node = &nodes[current as usize];
                let mut near = _mm256_set1_ps(ray.t_min);
                let mut far = _mm256_set1_ps(t_max);
                for a in 0..3 {
                    let (pn, pf) = node.planes(near_plane[a], far_plane[a], a);
                    let inv_a = _mm256_set1_ps(inv[a]);
                    let tn = _mm256_fmsub_ps(pn, inv_a, _mm256_set1_ps(n_off[a]));
                    let tf = _mm256_fmsub_ps(pf, inv_a, _mm256_set1_ps(f_off[a]));
                    near = _mm256_max_ps(near, tn);
                    far = _mm256_min_ps(far, tf);
                }
                far = _mm256_mul_ps(far, _mm256_set1_ps(ROBUST_FAR));
                let hit = _mm256_cmp_ps::<_CMP_LE_OQ>(near, far);
                let mut dist = [0.0f32; 8];
                _mm256_storeu_ps(dist.as_mut_ptr(), near);
                let mut mask = _mm256_movemask_ps(hit) as u32;
                if mask != 0 {
                    let i = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    if mask == 0 {
                        current = node.child()[i];
                        continue;
                    }
                    if ANY {
                        let first = node.child()[i];
                        while mask != 0 {
                            let j = 31 - mask.leading_zeros() as usize;
                            mask &= !(1 << j);
                            stack[sp].write((node.child()[j], dist[j]));
                            sp += 1;
                        }
                        current = first;
                        continue;
                    }
                    let mut hits = [(0.0f32, 0u32); 8];
                    hits[0] = (dist[i], node.child()[i]);
                    let mut n = 1;
                    while mask != 0 {
                        let i = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        let item = (dist[i], node.child()[i]);
                        let mut j = n;
                        while j > 0 && hits[j - 1].0 > item.0 {
                            hits[j] = hits[j - 1];
                            j -= 1;
                        }
                        hits[j] = item;
                        n += 1;
                    }
                    for &(d, r) in hits[1..n].iter().rev() {
                        stack[sp].write((r, d));
                        sp += 1;
                    }
                    current = hits[0].1;
                    continue;
                }
            } else if current != WIDE_EMPTY {
                let (first, count) = decode_leaf(current);
                if intersect_blocks::<ANY>(
                    blocks, &wray, ray.t_min, first, count, &mut t_max, &mut best, true,
                ) {
                    return Some(best);
                }
            }
            loop {
                if sp == 0 {
                    return Some(best);
                }
                sp -= 1;
                let (r, d) = stack[sp].assume_init();
                if ANY || d <= t_max * ROBUST_FAR {
                    current = r;
                    break;
                }
            }
        }
    }
}

struct Prepared {
    w8: WideMeshBvh<8>,
    quantized: Vec<QuantizedNode8>,
    coherent: Vec<Ray>,
    incoherent: Vec<Ray>,
}

fn local_answer<N: Node8>(p: &Prepared, nodes: &[N], r: &Ray) -> (Option<u32>, bool) {
    // SAFETY: `main` checked the AVX2 level.
    let closest = unsafe { query_quantized::<false, _>(nodes, &p.w8.blocks, r) };
    let any = unsafe { query_quantized::<true, _>(nodes, &p.w8.blocks, r) };
    match (closest, any) {
        (Some(c), Some(a)) => (c.map(|h| h.0.to_bits()), a.is_some()),
        _ => wide_answer(p, r),
    }
}

fn wide_answer(p: &Prepared, r: &Ray) -> (Option<u32>, bool) {
    (
        p.w8.intersect_with(Kernel::Avx2, r).map(|h| h.t.to_bits()),
        p.w8.occluded_with(Kernel::Avx2, r),
    )
}

fn prepared(name: &'static str) -> Option<&'static Prepared> {
    static CACHE: support::SceneCache<Prepared> = support::SceneCache::new();
    support::cached(&CACHE, name, || {
        let mesh = support::load(name)?;
        let bvh = MeshBvh::build(&mesh, &BuildParams::default()).unwrap();
        let w8 = WideMeshBvh::<8>::from_mesh(&bvh).unwrap();
        w8.validate().unwrap();
        let quantized: Vec<QuantizedNode8> = w8.wide.nodes.iter().map(quantize).collect();
        let b = mesh.bounds();
        let p = Prepared {
            w8,
            quantized,
            coherent: support::camera_rays(&b, RAYS),
            incoherent: support::random_rays(&b, RAYS),
        };
        for rays in [&p.coherent, &p.incoherent] {
            let bad = rays
                .iter()
                .filter(|r| {
                    let want = wide_answer(&p, r);
                    local_answer(&p, &p.quantized, r) != want
                        || local_answer(&p, &p.w8.wide.nodes, r) != want
                })
                .count();
            assert_eq!(
                bad, 0,
                "{name}: the experiment's kernel disagrees on {bad} rays"
            );
        }
        eprintln!(
            "{name}: {} wide nodes, {} KB uncompressed, {} KB quantised; answers agree",
            p.w8.wide.nodes.len(),
            std::mem::size_of_val(p.w8.wide.nodes.as_slice()) / 1024,
            std::mem::size_of_val(p.quantized.as_slice()) / 1024,
        );
        Some(p)
    })
}

fn trace(bencher: Bencher, case: &str, coherent: bool, any: bool) {
    let Some((p, variant)) = support::case(case, &SCENES, prepared) else {
        return;
    };
    let rays = if coherent { &p.coherent } else { &p.incoherent };
    let (q, w) = (&p.quantized, &p.w8.wide.nodes);
    let blocks = &p.w8.blocks;
    bencher
        .counter(ItemsCount::new(rays.len()))
        .bench_local(|| {
            let mut n = 0usize;
            for r in black_box(rays) {
                // SAFETY: `main` checked the AVX2 level.
                let hit = unsafe {
                    match (variant, any) {
                        ("q8_avx2", true) => {
                            query_quantized::<true, _>(q, blocks, r).flatten().is_some()
                        }
                        ("q8_avx2", false) => query_quantized::<false, _>(q, blocks, r)
                            .flatten()
                            .is_some(),
                        ("w8_local", true) => {
                            query_quantized::<true, _>(w, blocks, r).flatten().is_some()
                        }
                        ("w8_local", false) => query_quantized::<false, _>(w, blocks, r)
                            .flatten()
                            .is_some(),
                        (_, true) => p.w8.occluded_with(Kernel::Avx2, r),
                        (_, false) => p.w8.intersect_with(Kernel::Avx2, r).is_some(),
                    }
                };
                n += hit as usize;
            }
            n
        });
}

fn cases() -> Vec<&'static str> {
    support::cases(&SCENES, &VARIANTS)
}

#[divan::bench(args = cases(), sample_count = 8)]
fn closest_coherent(b: Bencher, case: &str) {
    trace(b, case, true, false);
}
#[divan::bench(args = cases(), sample_count = 8)]
fn closest_incoherent(b: Bencher, case: &str) {
    trace(b, case, false, false);
}
#[divan::bench(args = cases(), sample_count = 8)]
fn occluded_coherent(b: Bencher, case: &str) {
    trace(b, case, true, true);
}
#[divan::bench(args = cases(), sample_count = 8)]
fn occluded_incoherent(b: Bencher, case: &str) {
    trace(b, case, false, true);
}
