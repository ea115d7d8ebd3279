//! Leaves of four triangles tested at once: the `Triangle4` layout.
//!
//! A wide leaf of `n` triangles is stored as `ceil(n / 4)` blocks, each
//! holding the vertices of up to four triangles in SoA form (one 16-byte
//! vector per vertex coordinate), as Embree's `Triangle4` does (I. Wald et
//! al., "Embree: A Kernel Framework for Efficient CPU Ray Tracing", ACM TOG
//! 33(4), 2014). One pass of SSE arithmetic then runs the watertight test
//! (Woop, Benthin, Wald, JCGT 2013) on four triangles, where the scalar loop
//! ran it four times. SSE2 is part of x86-64, so this kernel needs no run-time
//! detection; the scalar lane loop stays as the reference and as the path of
//! [`super::Kernel::Scalar`].
//!
//! The SIMD lanes compute exactly the scalar test's operations in the same
//! order (separate multiplies and subtractions, never FMA; a true division
//! for the reciprocal), so every lane's `(t, u, v)` is bit-identical to
//! [`intersect_triangle`]'s. Lanes where an edge function rounds to exactly
//! zero, which the scalar test recomputes in `f64`, are handed to the scalar
//! test itself. Within a leaf the closest lane wins and equal distances keep
//! the first lane, the scalar loop's rule, so the leaf answers are the same
//! triangle, not only the same distance.
//!
//! Degenerate triangles (stored collapsed to one point by
//! [`crate::MeshBvh`]) and the padding of a partial block have NaN vertices,
//! which no lane ever hits; their primitive id stays recorded (padding:
//! [`TRIANGLE4_NO_PRIM`]) so that the blocks still account for every
//! triangle.
//!
//! A block carries everything a hit record needs: each lane's primitive id
//! beside its vertices, from which the geometric normal is computed. A leaf
//! hit names its lane ([`LeafHit`]: block index times four plus lane), so
//! finishing the hit reads the block the test has just loaded instead of
//! the leaf-order triangle and primitive-id arrays, two dependent cache
//! misses per incoherent ray (see `docs/performance.md`, session 5).
//!
//! The binary builder prices leaves by blocks when asked
//! ([`super::BuildParams::leaf_block_size`]), as Embree's SAH does for its
//! `Triangle4` leaves: up to four triangles cost one test.

use glam::Vec3;

use super::occlusion_order::{OcclusionStats, order_for_occlusion, triangle_miss_probability};
use super::wide::{WIDE_EMPTY, WideBvh, decode_leaf, encode_leaf, is_leaf_ref};
use crate::Aabb;
use crate::triangle::{WatertightRay, intersect_triangle};

/// Primitive id of a padding lane.
pub const TRIANGLE4_NO_PRIM: u32 = u32::MAX;

/// Up to four triangles in SoA form: `v[vertex][axis][lane]`, and the
/// primitive id of each lane's triangle (its index in the mesh, what a hit
/// reports).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(16))]
pub struct Triangle4 {
    pub v: [[[f32; 4]; 3]; 3],
    pub prim: [u32; 4],
}

const _: () = assert!(std::mem::size_of::<Triangle4>() == 160);
const _: () = assert!(std::mem::align_of::<Triangle4>() == 16);

/// A hit inside a leaf: (t, u, v, hit reference). Over [`Triangle4`]
/// blocks the reference is the lane, `4 * block + lane` (see
/// [`block_hit_record`]); over a binary tree's leaves it is the leaf-order
/// slot.
pub type LeafHit = (f32, f32, f32, u32);

/// The closest-hit rule every kernel shares: a hit at `t` with key `k`
/// (its leaf-order slot) replaces `best` when it is nearer, or exactly as
/// near with a smaller key. Keying exact ties (a ray through the edge two
/// triangles share) makes the answer independent of the order in which
/// leaves are visited, so a ray traced in a packet, whose visit order is
/// the packet's, answers as it does alone, triangle and all.
#[inline(always)]
pub fn nearer(t: f32, k: u32, best: &Option<LeafHit>) -> bool {
    best.is_none_or(|h| t < h.0 || (t == h.0 && k < h.3))
}

/// The primitive id and the geometric normal, `(v1 - v0) x (v2 - v0)` at its
/// length, of the block lane `lane_ref` (`4 * block + lane`, as the block
/// kernels report hits): bit for bit what the leaf-order triangle gives, as
/// the block holds its exact vertices.
#[inline(always)]
pub fn block_hit_record(blocks: &[Triangle4], lane_ref: u32) -> (u32, Vec3) {
    let b = &blocks[(lane_ref / 4) as usize];
    let lane = (lane_ref % 4) as usize;
    let [p0, p1, p2] = b.triangle(lane);
    (b.prim[lane], crate::triangle::geometric_normal(p0, p1, p2))
}

impl Triangle4 {
    /// Four padding lanes.
    pub const EMPTY: Self = Self {
        v: [[[f32::NAN; 4]; 3]; 3],
        prim: [TRIANGLE4_NO_PRIM; 4],
    };

    /// Put triangle `tri` (primitive id `prim`) in lane `lane`; a triangle
    /// collapsed to one point gets NaN vertices (never hit).
    #[inline]
    pub fn set(&mut self, lane: usize, prim: u32, tri: [Vec3; 3]) {
        let collapsed = tri[0] == tri[1] && tri[1] == tri[2];
        for (i, p) in tri.iter().enumerate() {
            for axis in 0..3 {
                self.v[i][axis][lane] = if collapsed { f32::NAN } else { p[axis] };
            }
        }
        self.prim[lane] = prim;
    }

    /// Area of each lane's triangle (NaN for padding and collapsed lanes),
    /// lane by lane in plain arrays so that the compiler vectorises it.
    #[inline]
    pub fn areas(&self) -> [f32; 4] {
        let v = &self.v;
        let edge = |i: usize| -> [[f32; 4]; 3] {
            std::array::from_fn(|a| std::array::from_fn(|l| v[i][a][l] - v[0][a][l]))
        };
        let (e1, e2) = (edge(1), edge(2));
        std::array::from_fn(|l| {
            let x = e1[1][l] * e2[2][l] - e1[2][l] * e2[1][l];
            let y = e1[2][l] * e2[0][l] - e1[0][l] * e2[2][l];
            let z = e1[0][l] * e2[1][l] - e1[1][l] * e2[0][l];
            0.5 * (x * x + y * y + z * z).sqrt()
        })
    }

    /// The block with every vertex moved by `xf` (each vertex transformed
    /// on its own, as a world-space build transforms it, so that vertices
    /// neighbouring triangles share stay shared); padding lanes stay NaN.
    ///
    /// Computed a coordinate row at a time over the four lanes (plain
    /// arrays, which the compiler vectorises), with `transform_point3`'s
    /// operations in its order, `((x c0 + y c1) + z c2) + t`, never fused:
    /// bit for bit what it gives each vertex
    /// (`transformed_matches_transform_point3`). The lane-by-lane loop it
    /// replaced took 1.9-3.1 ms for the 2CylinderEngine's copies with every
    /// entry of up to 1,024 primitives grafted (about 24,400 blocks, one
    /// thread), this 1.0-1.5 ms (session 29).
    #[inline]
    pub fn transformed(&self, xf: &glam::Affine3A) -> Self {
        let m = xf.matrix3;
        let (c0, c1, c2, t) = (m.x_axis, m.y_axis, m.z_axis, xf.translation);
        // Plain loops: the nested `array::from_fn` closures this was first
        // written with were not all inlined (150 instructions per block).
        let mut v = [[[0.0f32; 4]; 3]; 3];
        for (out, [x, y, z]) in v.iter_mut().zip(&self.v) {
            for (r, row) in out.iter_mut().enumerate() {
                for (l, o) in row.iter_mut().enumerate() {
                    *o = ((x[l] * c0[r] + y[l] * c1[r]) + z[l] * c2[r]) + t[r];
                }
            }
        }
        Self { v, prim: self.prim }
    }

    /// Vertices of lane `lane`.
    #[inline]
    pub fn triangle(&self, lane: usize) -> [Vec3; 3] {
        std::array::from_fn(|i| {
            Vec3::new(self.v[i][0][lane], self.v[i][1][lane], self.v[i][2][lane])
        })
    }
}

/// Store the triangles of every leaf of `wide` as [`Triangle4`] blocks and
/// rewrite each leaf reference to name its blocks (first block, block
/// count) instead of its triangle slots. `triangles` are the leaf-order
/// triangles the leaves index and `prim_indices` their primitive ids (the
/// BVH's index array), which the blocks store. Blocks follow the node
/// array's order, so a node's leaves lie close together. Afterwards `wide.prim_count` is the
/// number of blocks (what [`WideBvh::validate`] checks against, with
/// [`block_boxes`]).
pub fn pack_triangle4<const W: usize>(
    wide: &mut WideBvh<W>,
    triangles: &[[Vec3; 3]],
    prim_indices: &[u32],
) -> Vec<Triangle4> {
    pack_triangle4_with_misses(wide, triangles, prim_indices).0
}

/// [`pack_triangle4`], also returning for each block the probability that
/// a line entering its leaf's box misses the block's triangles,
/// `prod(1 - min(1, A / S))` over their areas `A` with `S` the leaf box's
/// half area (see [`super::occlusion_order`]): computed here, while the
/// triangles are at hand, rather than by reading the blocks again.
pub fn pack_triangle4_with_misses<const W: usize>(
    wide: &mut WideBvh<W>,
    triangles: &[[Vec3; 3]],
    prim_indices: &[u32],
) -> (Vec<Triangle4>, Vec<f32>) {
    assert_eq!(triangles.len(), prim_indices.len(), "one id per triangle");
    // Pass 1 (nodes only): give each leaf its blocks, rewrite its ref, and
    // note each block's triangle range (first slot, count) and the
    // reciprocal of its leaf box's half area.
    let mut sources: Vec<(u32, u32, f32)> = Vec::with_capacity(triangles.len() / 2 + 1);
    let mut next = 0u32;
    for node in &mut wide.nodes {
        for i in 0..W {
            let r = node.child[i];
            if r == WIDE_EMPTY || !is_leaf_ref(r) {
                continue;
            }
            let (first, count) = decode_leaf(r);
            let end = first + count;
            let h = node.child_bounds(i).half_area();
            let inv_h = if h > 0.0 { 1.0 / h } else { f32::INFINITY };
            sources.extend(
                (first..end)
                    .step_by(4)
                    .map(|b| (b, (end - b).min(4), inv_h)),
            );
            let n = count.div_ceil(4);
            node.child[i] = encode_leaf(next, n);
            next += n;
        }
    }
    // Pass 2: fill the blocks, one exact-size collect (in parallel for long
    // inputs; the result does not depend on the thread count).
    let block = |&(first, count, inv_h): &(u32, u32, f32)| {
        let mut b = Triangle4::EMPTY;
        for lane in 0..count {
            let k = first + lane;
            b.set(
                lane as usize,
                prim_indices[k as usize],
                triangles[k as usize],
            );
        }
        let m = b.areas().map(|a| triangle_miss_probability(a, inv_h));
        (b, m[0] * m[1] * m[2] * m[3])
    };
    let (blocks, misses): (Vec<Triangle4>, Vec<f32>) = if triangles.len() >= 1 << 15 {
        use rayon::prelude::*;
        sources.par_iter().with_min_len(4096).map(block).unzip()
    } else {
        sources.iter().map(block).unzip()
    };
    debug_assert_eq!(blocks.len(), next as usize);
    wide.prim_count = blocks.len();
    (blocks, misses)
}

/// Leaf-order slot of each primitive id: the inverse of a BVH's index
/// array, or an error when it is not a permutation.
fn slots_of_prims(prim_indices: &[u32]) -> Result<Vec<u32>, String> {
    let mut slots = vec![u32::MAX; prim_indices.len()];
    for (s, &p) in prim_indices.iter().enumerate() {
        match slots.get_mut(p as usize) {
            Some(x) if *x == u32::MAX => *x = s as u32,
            Some(_) => return Err(format!("primitive {p} at two slots")),
            None => return Err(format!("slot {s}: primitive {p} out of range")),
        }
    }
    Ok(slots)
}

/// Box of each block: the union of its triangles' boxes, taken from the
/// leaf-order `triangles` through the lanes' primitive ids (so degenerate
/// lanes count too). `prim_indices` must be a permutation (checked by
/// [`validate_blocks`]; lanes it does not name add nothing).
pub fn block_boxes(
    blocks: &[Triangle4],
    triangles: &[[Vec3; 3]],
    prim_indices: &[u32],
) -> Vec<Aabb> {
    let slots = slots_of_prims(prim_indices).unwrap_or_default();
    blocks
        .iter()
        .map(|b| {
            b.prim
                .iter()
                .filter_map(|&p| slots.get(p as usize))
                .fold(Aabb::EMPTY, |acc, &s| {
                    acc.union(Aabb::from_points(&triangles[s as usize]))
                })
        })
        .collect()
}

/// Check that the blocks hold exactly the leaf-order triangles, each once,
/// with its primitive id from `prim_indices` (collapsed ones as NaN).
pub fn validate_blocks(
    blocks: &[Triangle4],
    triangles: &[[Vec3; 3]],
    prim_indices: &[u32],
) -> Result<(), String> {
    if triangles.len() != prim_indices.len() {
        return Err("one primitive id per triangle expected".into());
    }
    let slots = slots_of_prims(prim_indices)?;
    let mut seen = vec![false; triangles.len()];
    for (i, b) in blocks.iter().enumerate() {
        for lane in 0..4 {
            let p = b.prim[lane];
            if p == TRIANGLE4_NO_PRIM {
                continue;
            }
            let Some(&s) = slots.get(p as usize) else {
                return Err(format!("block {i} lane {lane}: primitive {p} out of range"));
            };
            if std::mem::replace(&mut seen[s as usize], true) {
                return Err(format!("primitive {p} in two blocks"));
            }
            let mut expect = Triangle4::EMPTY;
            expect.set(lane, p, triangles[s as usize]);
            let (got, want) = (b.triangle(lane), expect.triangle(lane));
            let same = got
                .iter()
                .zip(&want)
                .all(|(g, w)| g.to_array().map(f32::to_bits) == w.to_array().map(f32::to_bits));
            if !same {
                return Err(format!(
                    "block {i} lane {lane}: vertices differ from primitive {p}"
                ));
            }
        }
    }
    match seen.iter().position(|s| !s) {
        Some(s) => Err(format!("primitive {} in no block", prim_indices[s])),
        None => Ok(()),
    }
}

/// Intersect the blocks `first .. first + count` (one wide leaf): shrinks
/// `t_max` and records the closest hit in `best`, naming its lane as
/// `4 * block + lane` (equal distances keep the earlier triangle, also
/// against a `best` from an earlier leaf), or with
/// `ANY` records some hit and returns `true` (stop). `simd` selects the SSE
/// lanes (x86-64) over the scalar loop; both give the same answers.
#[allow(clippy::too_many_arguments)] // the hot path: plain values
#[inline(always)]
pub fn intersect_blocks<const ANY: bool>(
    blocks: &[Triangle4],
    wray: &WatertightRay,
    t_min: f32,
    first: u32,
    count: u32,
    t_max: &mut f32,
    best: &mut Option<LeafHit>,
    simd: bool,
) -> bool {
    for (i, b) in blocks[first as usize..(first + count) as usize]
        .iter()
        .enumerate()
    {
        let bi = first + i as u32;
        #[cfg(target_arch = "x86_64")]
        if simd {
            // SAFETY: SSE2 is part of the x86-64 baseline.
            let lanes = unsafe { x86::lanes(b, wray, t_min, *t_max) };
            if take_lanes::<ANY>(b, bi * 4, lanes, wray, t_min, t_max, best) {
                return true;
            }
            continue;
        }
        let _ = simd;
        if scalar_block::<ANY>(b, bi * 4, wray, t_min, t_max, best) {
            return true;
        }
    }
    false
}

/// The reference: the scalar watertight test lane by lane, in lane order;
/// hits are named `lane0 + lane`.
#[inline(always)]
fn scalar_block<const ANY: bool>(
    b: &Triangle4,
    lane0: u32,
    wray: &WatertightRay,
    t_min: f32,
    t_max: &mut f32,
    best: &mut Option<LeafHit>,
) -> bool {
    for lane in 0..4 {
        if b.prim[lane] == TRIANGLE4_NO_PRIM {
            break;
        }
        let [p0, p1, p2] = b.triangle(lane);
        if let Some((t, u, v)) = intersect_triangle(wray, p0, p1, p2, t_min, *t_max) {
            let k = lane0 + lane as u32;
            if ANY {
                *best = Some((t, u, v, k));
                return true;
            }
            if nearer(t, k, best) {
                *t_max = t;
                *best = Some((t, u, v, k));
            }
        }
    }
    false
}

/// Lane results of one block: hit mask, lanes the scalar test must decide,
/// and each lane's t, u, v.
#[cfg(target_arch = "x86_64")]
type Lanes = (
    u32,
    u32,
    std::arch::x86_64::__m128,
    std::arch::x86_64::__m128,
    std::arch::x86_64::__m128,
);

/// Fold a block's lane results into the leaf's answer, lanes in order (the
/// scalar loop's order and tie rule).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn take_lanes<const ANY: bool>(
    b: &Triangle4,
    lane0: u32,
    (hits, scalar, t, u, v): Lanes,
    wray: &WatertightRay,
    t_min: f32,
    t_max: &mut f32,
    best: &mut Option<LeafHit>,
) -> bool {
    let mut todo = hits | scalar;
    // In vectors until a lane is taken: returned as arrays, the lanes' t,
    // u and v were zeroed and stored at every block test that passed the
    // edge test, hit or not (about 9 instructions each, session 21).
    let (t, u, v): ([f32; 4], [f32; 4], [f32; 4]) =
        (bytemuck::cast(t), bytemuck::cast(u), bytemuck::cast(v));
    while todo != 0 {
        let lane = todo.trailing_zeros() as usize;
        todo &= todo - 1;
        let hit = if scalar & (1 << lane) != 0 {
            // Rare: an edge function was exactly zero; the scalar test
            // redoes it in f64. `t_max` here may already be shrunk by an
            // earlier lane, which only rejects hits the rule below would.
            let [p0, p1, p2] = b.triangle(lane);
            intersect_triangle(wray, p0, p1, p2, t_min, *t_max)
        } else {
            Some((t[lane], u[lane], v[lane]))
        };
        let Some((t, u, v)) = hit else { continue };
        let k = lane0 + lane as u32;
        if ANY {
            *best = Some((t, u, v, k));
            return true;
        }
        if nearer(t, k, best) {
            *t_max = t;
            *best = Some((t, u, v, k));
        }
    }
    false
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    #[cfg(target_arch = "x86_64")]
    use std::arch::x86_64::*;

    use super::{Lanes, Triangle4};
    use crate::triangle::WatertightRay;

    /// The watertight test on the four lanes of `b` (see the module docs):
    /// the lanes hit within `[t_min, t_max]`, the lanes whose edge functions
    /// need the scalar `f64` recomputation, and every lane's t, u, v.
    ///
    /// # Safety
    /// SSE2 only, which every x86-64 CPU has.
    #[inline(always)]
    pub(super) unsafe fn lanes(b: &Triangle4, r: &WatertightRay, t_min: f32, t_max: f32) -> Lanes {
        // SAFETY: plain SSE2 arithmetic; each load reads one aligned
        // `[f32; 4]` of the block (`Triangle4` is 16-byte aligned and its
        // rows are 16 bytes); the volatile reads read `f32` fields of `r`
        // (valid and aligned: it is a reference).
        unsafe {
            let (kx, ky, kz) = (r.kx, r.ky, r.kz);
            // The ray's six constants are read here, at every block, by
            // volatile loads, which LLVM may not hoist: hoisted out of a
            // leaf's block loop, the broadcasts ran out of registers and
            // were stored to stack slots at every leaf entry and read back
            // per block (26 of a copied leaf's 61 entry instructions).
            // Per diffuse ray, re-braided: samurai 883.8 -> 862.6
            // instructions, nexuiz 1,876.1 -> 1,821.6 (callgrind, session
            // 21).
            let rd = |x: &f32| _mm_set1_ps(std::ptr::read_volatile(x));
            let o = [rd(&r.origin_k[0]), rd(&r.origin_k[1]), rd(&r.origin_k[2])];
            let (sx, sy, sz) = (rd(&r.sx), rd(&r.sy), rd(&r.sz));
            // Vertex `i` relative to the origin, sheared: (x, y, z) with z
            // not yet scaled, as `intersect_triangle` computes them.
            let vertex = |i: usize| {
                let x = _mm_sub_ps(_mm_load_ps(b.v[i][kx].as_ptr()), o[0]);
                let y = _mm_sub_ps(_mm_load_ps(b.v[i][ky].as_ptr()), o[1]);
                let z = _mm_sub_ps(_mm_load_ps(b.v[i][kz].as_ptr()), o[2]);
                (
                    _mm_sub_ps(x, _mm_mul_ps(sx, z)),
                    _mm_sub_ps(y, _mm_mul_ps(sy, z)),
                    z,
                )
            };
            let (ax, ay, az) = vertex(0);
            let (bx, by, bz) = vertex(1);
            let (cx, cy, cz) = vertex(2);
            let u = _mm_sub_ps(_mm_mul_ps(cx, by), _mm_mul_ps(cy, bx));
            let v = _mm_sub_ps(_mm_mul_ps(ax, cy), _mm_mul_ps(ay, cx));
            let w = _mm_sub_ps(_mm_mul_ps(bx, ay), _mm_mul_ps(by, ax));
            let zero = _mm_setzero_ps();
            // Some edge function negative and some positive: the ray
            // passes outside. Rounding is monotonic, so a strictly signed
            // `f32` edge function has the sign of the exact one: such a
            // lane is outside for the scalar test too, even when another
            // of its edge functions is zero and the scalar test takes the
            // `f64` path (which then sees the same strict signs). Min and
            // max give the six compares' answer for every lane that is not
            // NaN. `inside` is written as "all >= 0 or all <= 0" so that a
            // NaN `lo` / `hi` (exactly the lanes whose `w` is NaN: padding,
            // collapsed triangles) counts as outside: those lanes' `t` is
            // NaN and never a hit, and a block whose other lanes are all
            // missed then skips the second stage below. (Written as
            // "outside = lo < 0 and hi > 0" instead, every partial block
            // went on to the division: session 16.)
            let lo = _mm_min_ps(u, _mm_min_ps(v, w));
            let hi = _mm_max_ps(u, _mm_max_ps(v, w));
            let inside = _mm_or_ps(_mm_cmpge_ps(lo, zero), _mm_cmple_ps(hi, zero));
            // Most tested triangles are missed here: skip the rest unless
            // some lane is still a candidate.
            if _mm_movemask_ps(inside) == 0 {
                return (0, 0, zero, zero, zero);
            }
            // A lane that is not outside has an edge function of exactly
            // zero iff its smallest or largest one is zero (all are >= 0 or
            // all <= 0): the scalar test decides it in `f64`.
            let scalar = _mm_and_ps(
                inside,
                _mm_or_ps(_mm_cmpeq_ps(lo, zero), _mm_cmpeq_ps(hi, zero)),
            );
            let det = _mm_add_ps(_mm_add_ps(u, v), w);
            let t_scaled = _mm_add_ps(
                _mm_add_ps(
                    _mm_mul_ps(u, _mm_mul_ps(sz, az)),
                    _mm_mul_ps(v, _mm_mul_ps(sz, bz)),
                ),
                _mm_mul_ps(w, _mm_mul_ps(sz, cz)),
            );
            let rcp = _mm_div_ps(_mm_set1_ps(1.0), det);
            let t = _mm_mul_ps(t_scaled, rcp);
            // Ordered compares: a NaN t (padding, det = 0) fails them.
            let in_range = _mm_and_ps(
                _mm_cmpge_ps(t, _mm_set1_ps(t_min)),
                _mm_cmple_ps(t, _mm_set1_ps(t_max)),
            );
            let ok = _mm_andnot_ps(
                scalar,
                _mm_and_ps(inside, _mm_and_ps(_mm_cmpneq_ps(det, zero), in_range)),
            );
            let hits = _mm_movemask_ps(ok) as u32;
            let scalar = _mm_movemask_ps(scalar) as u32;
            (hits, scalar, t, _mm_mul_ps(v, rcp), _mm_mul_ps(w, rcp))
        }
    }
}

/// Occlusion statistics of the Triangle4 leaf `r` (see
/// [`super::occlusion_order`]) from its blocks' miss probabilities (as
/// [`pack_triangle4_with_misses`] gives them): one unit of cost per block.
pub fn leaf_occlusion(block_misses: &[f32], r: u32) -> OcclusionStats {
    let (first, count) = decode_leaf(r);
    let miss: f32 = block_misses[first as usize..(first + count) as usize]
        .iter()
        .product();
    OcclusionStats::from_miss(miss, count as f32)
}

/// An 8-wide tree over a [`crate::MeshBvh`]'s leaf-order triangles whose
/// leaves are [`Triangle4`] blocks: the traversal layout of the flat BVH and
/// of every object BVH (the binary `MeshBvh` stays the build, re-braiding
/// and reference structure).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WideTriangleBvh {
    pub wide: WideBvh<8>,
    pub blocks: Vec<Triangle4>,
    /// Occlusion statistics of each wide node's subtree (indexed like
    /// `wide.nodes`), by which its slots are ordered; the top level orders
    /// its own slots by them too.
    pub occlusion: Vec<OcclusionStats>,
    /// Per block, the probability that a line entering its leaf's box
    /// misses its triangles (see [`pack_triangle4_with_misses`]).
    pub block_misses: Vec<f32>,
}

impl WideTriangleBvh {
    /// Closest (or, with `ANY`, some) hit of a valid ray on the whole
    /// tree (not empty), within the ray's interval, counting visited nodes:
    /// [`crate::bvh::query_subtree`] from the root. The one-ray query of the
    /// flat mode and of a top level walked directly.
    #[inline]
    pub fn query<const ANY: bool>(
        &self,
        kernel: crate::bvh::Kernel,
        ray: &crate::Ray,
        counters: &mut crate::bvh::TraversalCounters,
    ) -> Option<LeafHit> {
        crate::bvh::query_subtree::<ANY>(
            &self.wide.nodes,
            &self.blocks,
            kernel,
            0,
            ray,
            ray.t_max,
            counters,
        )
    }

    /// Embree's SAH statistic of the tree as a ray walks it alone (see
    /// [`crate::bvh::wide::wide_sah_sum`]); 0 for an empty tree or a root
    /// box without area.
    pub fn wide_sah_cost(&self) -> f64 {
        use crate::bvh::wide::{wide_root_area, wide_sah_sum};
        let root_area = wide_root_area(&self.wide);
        if self.wide.nodes.is_empty() || root_area <= 0.0 {
            return 0.0;
        }
        let area = |b: &crate::Aabb| b.half_area() as f64;
        let mut leaf = |c: u32, a: f64| a * decode_leaf(c).1 as f64;
        wide_sah_sum(&self.wide, 0, root_area, &area, &mut leaf) / root_area
    }

    /// Collapse the mesh's binary tree and pack its leaves; fails when a
    /// binary leaf is too large for the wide layout.
    pub fn from_mesh(mesh: &crate::MeshBvh) -> Result<Self, crate::Error> {
        Self::from_mesh_with(mesh, super::Collapse::default())
    }

    /// [`WideTriangleBvh::from_mesh`] by the collapse rule `collapse`.
    pub fn from_mesh_with(
        mesh: &crate::MeshBvh,
        collapse: super::Collapse,
    ) -> Result<Self, crate::Error> {
        Ok(Self::from_plan(
            mesh,
            WideBvh::from_bvh_with(&mesh.bvh, collapse)?,
        ))
    }

    /// The second half of [`WideTriangleBvh::from_mesh_with`]: the leaves
    /// of `wide` (collapsed from `mesh.bvh`, its leaves still naming binary
    /// ranges) packed into blocks, and every node's slots put in occlusion
    /// order. Separate so that a scene's commit can make it while the top
    /// level is built, which needs only the collapse (which binary nodes
    /// the wide nodes hold) of each object.
    pub fn from_plan(mesh: &crate::MeshBvh, mut wide: WideBvh<8>) -> Self {
        let (blocks, block_misses) =
            pack_triangle4_with_misses(&mut wide, &mesh.triangles, &mesh.bvh.prim_indices);
        let occlusion = order_for_occlusion(&mut wide, |r, _| leaf_occlusion(&block_misses, r));
        Self {
            wide,
            blocks,
            occlusion,
            block_misses,
        }
    }

    /// Bytes of the nodes, maps and blocks.
    pub fn bytes(&self) -> usize {
        self.wide.bytes() + std::mem::size_of_val(self.blocks.as_slice())
    }

    /// Check the blocks against the mesh's leaf-order triangles and
    /// primitive ids, the tree against the blocks' boxes, and the occlusion
    /// order: every node's slots by non-increasing `p / c` with the stats
    /// recorded for them.
    pub fn validate(&self, mesh: &crate::MeshBvh) -> Result<(), String> {
        let (triangles, prims) = (&mesh.triangles, &mesh.bvh.prim_indices);
        validate_blocks(&self.blocks, triangles, prims)?;
        self.wide
            .validate(&block_boxes(&self.blocks, triangles, prims))?;
        if self.occlusion.len() != self.wide.nodes.len()
            || self.block_misses.len() != self.blocks.len()
        {
            return Err("occlusion statistics do not cover the tree".into());
        }
        let mut copy = self.wide.clone();
        let stats = order_for_occlusion(&mut copy, |r, _| leaf_occlusion(&self.block_misses, r));
        if copy != self.wide || stats != self.occlusion {
            return Err("slots are not in occlusion order".into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::bvh::{BuildParams, WideBvh};
    use crate::{MeshBvh, TriangleMesh};

    /// Blocks of random triangles whose vertices sit on a coarse integer
    /// lattice, and rays through lattice points: many rays pass exactly
    /// through vertices and edges, where edge functions are exactly zero
    /// and the scalar `f64` path must take over.
    fn lattice_case(rng: &mut Pcg64) -> (Vec<Triangle4>, Vec<[Vec3; 3]>) {
        let p = |rng: &mut Pcg64| {
            Vec3::new(
                rng.gen_range(-3..=3) as f32,
                rng.gen_range(-3..=3) as f32,
                rng.gen_range(-3..=3) as f32,
            )
        };
        let n = rng.gen_range(1..=8);
        let mut tris: Vec<[Vec3; 3]> = (0..n).map(|_| [p(rng), p(rng), p(rng)]).collect();
        // Some collapsed (as MeshBvh stores degenerate triangles).
        if rng.gen_bool(0.2) {
            let a = tris[0][0];
            tris[0] = [a, a, a];
        }
        let mut blocks = Vec::new();
        for (bi, chunk) in tris.chunks(4).enumerate() {
            let mut b = Triangle4::EMPTY;
            for (lane, t) in chunk.iter().enumerate() {
                b.set(lane, (bi * 4 + lane) as u32, *t);
            }
            blocks.push(b);
        }
        (blocks, tris)
    }

    fn bits(h: Option<LeafHit>) -> Option<[u32; 4]> {
        h.map(|(t, u, v, k)| [t.to_bits(), u.to_bits(), v.to_bits(), k])
    }

    #[test]
    fn transformed_matches_transform_point3() {
        let mut rng = Pcg64::seed_from_u64(11);
        let mut f = |a: f32| rng.gen_range(-a..a);
        for _ in 0..2_000 {
            let xf = glam::Affine3A::from_scale_rotation_translation(
                Vec3::new(f(3.0) + 3.5, f(3.0) + 3.5, f(3.0) + 3.5),
                glam::Quat::from_euler(glam::EulerRot::XYZ, f(3.0), f(3.0), f(3.0)),
                Vec3::new(f(1e3), f(1e3), f(1e3)),
            ) * glam::Affine3A::from_cols_array(&std::array::from_fn(|_| f(2.0)));
            let mut b = Triangle4::EMPTY;
            // Three lanes of random triangles, the fourth padding (NaN).
            for lane in 0..3 {
                let tri = std::array::from_fn(|_| Vec3::new(f(1e4), f(1e4), f(1e4)));
                b.set(lane, lane as u32, tri);
            }
            let out = b.transformed(&xf);
            assert_eq!(out.prim, b.prim);
            for lane in 0..3 {
                for (p, q) in b.triangle(lane).iter().zip(out.triangle(lane)) {
                    let want = xf.transform_point3(*p);
                    assert_eq!(
                        want.to_array().map(f32::to_bits),
                        q.to_array().map(f32::to_bits)
                    );
                }
            }
            assert!(out.triangle(3).iter().all(|p| p.is_nan()));
        }
    }

    #[test]
    fn simd_lanes_match_the_scalar_loop_bit_for_bit() {
        let mut rng = Pcg64::seed_from_u64(7);
        let mut fallbacks_hit = 0;
        for _ in 0..20_000 {
            let (blocks, tris) = lattice_case(&mut rng);
            let o = Vec3::new(
                rng.gen_range(-4..=4) as f32,
                rng.gen_range(-4..=4) as f32,
                4.5,
            );
            let target = if rng.gen_bool(0.5) {
                tris[rng.gen_range(0..tris.len())][rng.gen_range(0..3)]
            } else {
                Vec3::new(
                    rng.gen_range(-3.0..3.0),
                    rng.gen_range(-3.0..3.0),
                    rng.gen_range(-3.0..3.0),
                )
            };
            let dir = target - o;
            if dir == Vec3::ZERO {
                continue;
            }
            let wray = WatertightRay::new(o, dir);
            let t_max = if rng.gen_bool(0.3) {
                rng.gen_range(0.2..1.5)
            } else {
                f32::INFINITY
            };
            let prior = rng
                .gen_bool(0.2)
                .then(|| (rng.gen_range(0.5..2.0), 0.0, 0.0, 99));
            let count = blocks.len() as u32;
            let run = |any: bool, simd: bool| {
                let mut tm = prior.map_or(t_max, |p: LeafHit| p.0.min(t_max));
                let mut best = prior;
                let stop = if any {
                    intersect_blocks::<true>(
                        &blocks, &wray, 0.0, 0, count, &mut tm, &mut best, simd,
                    )
                } else {
                    intersect_blocks::<false>(
                        &blocks, &wray, 0.0, 0, count, &mut tm, &mut best, simd,
                    )
                };
                (stop, tm.to_bits(), bits(best))
            };
            assert_eq!(run(false, true), run(false, false));
            assert_eq!(run(true, true), run(true, false));
            // The plain per-triangle loop agrees too.
            let mut best: Option<LeafHit> = prior;
            let mut tm = prior.map_or(t_max, |p| p.0.min(t_max));
            for (k, [a, b, c]) in tris.iter().enumerate() {
                let (a, b, c) = if a == b && b == c {
                    continue;
                } else {
                    (*a, *b, *c)
                };
                if let Some((t, u, v)) = intersect_triangle(&wray, a, b, c, 0.0, tm)
                    && best.is_none_or(|h| t < h.0)
                {
                    tm = t;
                    best = Some((t, u, v, k as u32));
                }
            }
            assert_eq!(run(false, true).2, bits(best));
            #[cfg(target_arch = "x86_64")]
            for b in &blocks {
                // SAFETY: SSE2 is part of x86-64.
                let (_, scalar, ..) = unsafe { x86::lanes(b, &wray, 0.0, f32::INFINITY) };
                fallbacks_hit += (scalar != 0) as u32;
            }
        }
        #[cfg(target_arch = "x86_64")]
        assert!(
            fallbacks_hit > 100,
            "the f64 fallback lanes were exercised {fallbacks_hit} times"
        );
    }

    #[test]
    fn packing_covers_every_triangle_once_and_validation_catches_damage() {
        let mut rng = Pcg64::seed_from_u64(3);
        let mut positions = Vec::new();
        let mut indices = Vec::new();
        for i in 0..500u32 {
            let c = Vec3::new(
                rng.gen_range(0.0..10.0),
                rng.gen_range(0.0..10.0),
                rng.gen_range(0.0..10.0),
            );
            positions.extend([c, c + Vec3::X * 0.3, c + Vec3::Y * 0.3]);
            indices.push([3 * i, 3 * i + 1, 3 * i + 2]);
        }
        let mesh = TriangleMesh { positions, indices };
        let bvh = MeshBvh::build(&mesh, &BuildParams::default()).unwrap();
        let w = WideTriangleBvh::from_mesh(&bvh).unwrap();
        w.validate(&bvh).unwrap();
        assert_eq!(w.wide.prim_count, w.blocks.len());
        // Leaves of up to 8 triangles: at most two blocks each, and no more
        // blocks than leaves * 2.
        let leaves = w.wide.stats().leaves;
        assert!(w.blocks.len() >= leaves && w.blocks.len() <= 2 * leaves);
        let mut bad = w.clone();
        bad.blocks[0].v[0][0][0] += 1.0;
        assert!(bad.validate(&bvh).is_err());
        let mut bad = w.clone();
        bad.blocks[0].prim[0] = bad.blocks[1].prim[0];
        assert!(bad.validate(&bvh).is_err());
        // A lane whose id names another triangle (ids swapped between two
        // blocks: each id still appears once).
        let mut bad = w.clone();
        let (p0, p1) = (bad.blocks[0].prim[0], bad.blocks[1].prim[0]);
        bad.blocks[0].prim[0] = p1;
        bad.blocks[1].prim[0] = p0;
        assert!(bad.validate(&bvh).is_err());
        // Slots are in occlusion order and their binary maps moved along.
        w.wide.validate_slot_maps(&bvh.bvh).unwrap();
        let (n, i) = (0..w.wide.nodes.len())
            .flat_map(|n| (1..w.wide.nodes[n].child_count()).map(move |i| (n, i)))
            .find(|&(n, i)| {
                let key = |s: usize| {
                    let r = w.wide.nodes[n].child[s];
                    let st = if is_leaf_ref(r) {
                        leaf_occlusion(&w.block_misses, r)
                    } else {
                        w.occlusion[r as usize]
                    };
                    st.hit_probability / st.cost
                };
                key(i - 1) > key(i)
            })
            .expect("some node orders two children by their keys");
        let mut bad = w.clone();
        let node = &mut bad.wide.nodes[n];
        let (a, b) = (node.child_bounds(i - 1), node.child_bounds(i));
        let (ra, rb) = (node.child[i - 1], node.child[i]);
        node.set_child(i - 1, &b, rb);
        node.set_child(i, &a, ra);
        bad.wide.slot_binary[n].swap(i - 1, i);
        bad.wide.validate_slot_maps(&bvh.bvh).unwrap();
        assert!(bad.validate(&bvh).is_err(), "order not checked");
        bad.wide.slot_binary[n].swap(i - 1, i);
        assert!(bad.wide.validate_slot_maps(&bvh.bvh).is_err());
        // An empty tree packs to nothing.
        let mut empty = WideBvh::<8>::default();
        assert!(pack_triangle4(&mut empty, &[], &[]).is_empty());
    }
}
