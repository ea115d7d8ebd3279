//! Watertight ray/triangle intersection.
//!
//! Implements S. Woop, C. Benthin, I. Wald, "Watertight Ray/Triangle
//! Intersection", JCGT 2(1), 2013. The ray is sheared and scaled so that it
//! points along +z from the origin; the triangle's 2D edge functions are then
//! evaluated in that space. Two triangles sharing an edge evaluate that edge
//! function from the same two (bit-identical) transformed vertices, so a ray
//! through the edge sees zero on both sides and hits at least one of them:
//! no ray slips through a closed mesh. Edge functions that round to exactly
//! zero are recomputed in `f64`, as the paper recommends, so that rays through
//! vertices and edges are decided consistently.

use glam::Vec3;

/// Per-ray constants of the watertight test, computed once per ray.
#[derive(Clone, Copy, Debug)]
pub struct WatertightRay {
    pub origin: Vec3,
    /// Permuted axes: `kz` is the dominant axis of the direction.
    pub kx: usize,
    pub ky: usize,
    pub kz: usize,
    /// Shear constants.
    pub sx: f32,
    pub sy: f32,
    pub sz: f32,
    /// The origin's coordinates in the permuted order `(kx, ky, kz)`: the
    /// four-triangle test broadcasts them per block, and indexing `origin`
    /// by the axes there compiled to a chain of branches per block
    /// (about 50 instructions per nexuiz diffuse ray, callgrind).
    pub origin_k: [f32; 3],
}

/// The axis along which `dir` is largest in magnitude (the lowest on
/// ties): the watertight test's `kz`. Rays of one direction octant and one
/// dominant axis share the whole permutation `(kx, ky, kz)`.
#[inline(always)]
pub fn dominant_axis(dir: Vec3) -> usize {
    let a = dir.abs();
    axis_of_magnitudes(a.x >= a.y, a.y >= a.z, a.x >= a.z)
}

/// [`dominant_axis`]'s rule on the three comparisons of the magnitudes
/// (false for NaN): `kz = 0` when x is the largest, else 1 when y is, else
/// 2. Shared with the table of [`WatertightRay::new_avx`].
#[inline(always)]
const fn axis_of_magnitudes(ge_xy: bool, ge_yz: bool, ge_xz: bool) -> usize {
    let x_max = ge_xy & ge_xz;
    let y_max = !x_max & ge_yz;
    const KZ: [usize; 4] = [2, 1, 0, 0];
    KZ[(x_max as usize) << 1 | y_max as usize]
}

/// The shear's other two axes for dominant axis `kz`: `(kz + 1) % 3` and
/// `(kz + 2) % 3`, swapped when the ray points down `kz` (`negative`) to
/// preserve the triangle's winding.
#[inline(always)]
const fn shear_axes(kz: usize, negative: bool) -> (usize, usize) {
    const NEXT: [usize; 4] = [1, 2, 0, 1];
    let (k1, k2) = (NEXT[kz & 3], NEXT[NEXT[kz & 3] & 3]);
    if negative { (k2, k1) } else { (k1, k2) }
}

/// The lane-permute control `[kx, ky, kz, 3]` of
/// [`WatertightRay::new_avx`] for each 3-bit mask `[|x| >= |y|, |y| >= |z|,
/// |x| >= |z|]` of a direction (bit 0 first) and 3-bit mask of its
/// negative components, indexed by `mask | negative << 3`: the axis choice
/// and the sign test of [`WatertightRay::new`] (the same two functions) in
/// one lookup.
#[cfg(target_arch = "x86_64")]
const PERMUTATIONS: [[i32; 4]; 64] = {
    let mut t = [[0; 4]; 64];
    let mut i = 0;
    while i < 64 {
        let kz = axis_of_magnitudes(i & 1 != 0, i & 2 != 0, i & 4 != 0);
        let (kx, ky) = shear_axes(kz, (i >> 3) >> kz & 1 != 0);
        t[i] = [kx as i32, ky as i32, kz as i32, 3];
        i += 1;
    }
    t
};

impl WatertightRay {
    /// Precompute the shear for a ray. The direction must be non-zero for any
    /// triangle to be hit; a zero direction yields non-finite constants and
    /// every test then fails.
    #[inline]
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        // Branch-free: the axes depend on the direction, so on incoherent
        // rays the branches of a plain `if` chain (and of indexing a `Vec3`
        // by them) mispredict. Callgrind's branch model, samurai monastery
        // diffuse rays, flat mode: 9.6 -> 8.7 mispredicted branches per
        // ray, with this and `Ray::is_valid` without short-circuits.
        let kz = dominant_axis(dir);
        let d = [dir.x, dir.y, dir.z, 0.0];
        let dz = d[kz & 3];
        let (kx, ky) = shear_axes(kz, dz < 0.0);
        let sz = 1.0 / dz;
        Self {
            origin,
            kx,
            ky,
            kz,
            // One division per ray: the shear's own rounding is irrelevant
            // to watertightness (every triangle of the ray sees the same
            // constants), and three divisions were a measurable part of a
            // coherent ray's cost.
            sx: d[kx & 3] * sz,
            sy: d[ky & 3] * sz,
            sz,
            origin_k: {
                let o = [origin.x, origin.y, origin.z, 0.0];
                [o[kx & 3], o[ky & 3], o[kz & 3]]
            },
        }
    }

    /// [`WatertightRay::new`] for `ray`, bit for bit (the same dominant
    /// axis, the same division and products; a permutation only moves
    /// values), with the axis choice made by one compare of the magnitudes
    /// and one table lookup ([`PERMUTATIONS`]), and the permutation applied by two AVX lane
    /// permutes (`vpermilps`), instead of the portable path's scalar
    /// compares and arrays indexed by the axes (stored, then read back one
    /// lane at a computed offset): 39 instructions against 68 in
    /// openarena's re-braided walk (callgrind; with the leaner AVX2 box
    /// tester of the same session, 2-6% fewer instructions per diffuse
    /// ray: `docs/performance.md`, session 20). The AVX2 kernel's tester
    /// factory calls it ([`crate::bvh::TesterFactory::watertight`]).
    ///
    /// # Safety
    /// The CPU must have AVX. Not a target-feature function, so that it
    /// always inlines into the AVX2 kernels (as `#[target_feature]` with
    /// `#[inline]` it stayed a call in the re-braided packet lanes: 2.6%
    /// more instructions per primary ray on openarena, callgrind). The
    /// price: where LLVM compiles a caller out of line without AVX (a
    /// closure given to a generic such as `std::array::from_fn`), each
    /// intrinsic becomes a call, correct on an AVX CPU but slow (a
    /// packet's eight made through `std::array::from_fn` cost flat primary
    /// rays 13% more instructions: `packet_constants` loops instead).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub unsafe fn new_avx(ray: &crate::Ray) -> Self {
        use core::arch::x86_64::*;
        // SAFETY: AVX (the caller's promise). The loads read 16 bytes of a
        // 32-byte `repr(C)` `Ray` at offsets 0 and 16: `origin` then
        // `t_min`, `dir` then `t_max`. Lane 3 (`t_min`, `t_max`) is never
        // read: the permutations fill lanes 0..=2 from lanes 0..=2 and lane
        // 3 from lane 3, which is dropped, and both masks keep bits 0..=2.
        unsafe {
            let base = (ray as *const crate::Ray).cast::<f32>();
            let o = _mm_loadu_ps(base);
            let d = _mm_loadu_ps(base.add(4));
            // `dominant_axis`'s three comparisons of the magnitudes (false
            // for NaN, as there) and each component's `< 0.0` (false for
            // -0.0 and NaN, as `new`'s test of `dir[kz]`), one mask each.
            let a = _mm_andnot_ps(_mm_set1_ps(-0.0), d);
            let ge = _mm_cmpge_ps(
                _mm_permute_ps::<0b11_00_01_00>(a),
                _mm_permute_ps::<0b11_10_10_01>(a),
            );
            let ge = _mm_movemask_ps(ge) & 7;
            let negative = _mm_movemask_ps(_mm_cmplt_ps(d, _mm_setzero_ps())) & 7;
            let p = PERMUTATIONS[(ge | negative << 3) as usize];
            let control = _mm_loadu_si128(p.as_ptr().cast());
            let dk: [f32; 4] = bytemuck::cast(_mm_permutevar_ps(d, control));
            let ok: [f32; 4] = bytemuck::cast(_mm_permutevar_ps(o, control));
            let sz = 1.0 / dk[2];
            Self {
                origin: ray.origin,
                kx: p[0] as usize,
                ky: p[1] as usize,
                kz: p[2] as usize,
                sx: dk[0] * sz,
                sy: dk[1] * sz,
                sz,
                origin_k: [ok[0], ok[1], ok[2]],
            }
        }
    }
}

/// Intersect one triangle. Returns `(t, u, v)` with `t` in `[t_min, t_max]`,
/// where the hit point is `(1 - u - v) * v0 + u * v1 + v * v2`.
///
/// Degenerate triangles (zero determinant) are never hit. Both faces are hit.
#[inline(always)]
pub fn intersect_triangle(
    r: &WatertightRay,
    v0: Vec3,
    v1: Vec3,
    v2: Vec3,
    t_min: f32,
    t_max: f32,
) -> Option<(f32, f32, f32)> {
    let a = v0 - r.origin;
    let b = v1 - r.origin;
    let c = v2 - r.origin;
    let (kx, ky, kz) = (r.kx, r.ky, r.kz);
    let ax = a[kx] - r.sx * a[kz];
    let ay = a[ky] - r.sy * a[kz];
    let bx = b[kx] - r.sx * b[kz];
    let by = b[ky] - r.sy * b[kz];
    let cx = c[kx] - r.sx * c[kz];
    let cy = c[ky] - r.sy * c[kz];

    let mut u = cx * by - cy * bx;
    let mut v = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        let (ax, ay, bx, by, cx, cy) = (
            ax as f64, ay as f64, bx as f64, by as f64, cx as f64, cy as f64,
        );
        u = (cx * by - cy * bx) as f32;
        v = (ax * cy - ay * cx) as f32;
        w = (bx * ay - by * ax) as f32;
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    let az = r.sz * a[kz];
    let bz = r.sz * b[kz];
    let cz = r.sz * c[kz];
    let t_scaled = u * az + v * bz + w * cz;
    let rcp = 1.0 / det;
    let t = t_scaled * rcp;
    // Written so that NaN fails.
    if !(t >= t_min && t <= t_max) {
        return None;
    }
    Some((t, v * rcp, w * rcp))
}

/// The unnormalised geometric normal `(v1 - v0) x (v2 - v0)`.
#[inline]
pub fn geometric_normal(v0: Vec3, v1: Vec3, v2: Vec3) -> Vec3 {
    (v1 - v0).cross(v2 - v0)
}

/// True when the triangle has zero area, judged in `f64` so that nearly
/// degenerate but valid triangles are kept.
pub fn is_degenerate(v0: Vec3, v1: Vec3, v2: Vec3) -> bool {
    let e1 = (v1 - v0).as_dvec3();
    let e2 = (v2 - v0).as_dvec3();
    e1.cross(e2) == glam::DVec3::ZERO
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The branch-free axis choice of [`WatertightRay::new`] is the
    /// reference's `if` chain (ties, zeros, signs and NaN included).
    #[test]
    fn axis_choice_matches_the_if_chain() {
        let vals = [0.0, -0.0, 1.0, -1.0, 2.0, -3.0, f32::NAN, 1e-30, -1e30];
        for &x in &vals {
            for &y in &vals {
                for &z in &vals {
                    let dir = Vec3::new(x, y, z);
                    let a = dir.abs();
                    let kz = if a.x >= a.y && a.x >= a.z {
                        0
                    } else if a.y >= a.z {
                        1
                    } else {
                        2
                    };
                    let mut kx = (kz + 1) % 3;
                    let mut ky = (kx + 1) % 3;
                    if dir[kz] < 0.0 {
                        std::mem::swap(&mut kx, &mut ky);
                    }
                    let r = WatertightRay::new(Vec3::ONE, dir);
                    assert_eq!((r.kx, r.ky, r.kz), (kx, ky, kz), "{dir:?}");
                    let sz = 1.0 / dir[kz];
                    let same =
                        |a: f32, b: f32| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
                    assert!(same(r.sz, sz), "{dir:?}");
                    assert!(
                        same(r.sx, dir[kx] * sz) && same(r.sy, dir[ky] * sz),
                        "{dir:?}"
                    );
                }
            }
        }
    }

    /// The AVX construction is the portable one bit for bit: the same
    /// axes, shear and permuted origin for directions with ties, zeros of
    /// either sign, NaN, infinities and subnormals.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx_construction_matches_the_portable_one() {
        if !std::arch::is_x86_feature_detected!("avx") {
            eprintln!("skipped: no AVX on this CPU");
            return;
        }
        let vals = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            2.0,
            -3.0,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            1e-40,
            -1e-30,
            1e30,
        ];
        let bits = |r: &WatertightRay| {
            (
                r.origin.to_array().map(f32::to_bits),
                (r.kx, r.ky, r.kz),
                [r.sx, r.sy, r.sz].map(f32::to_bits),
                r.origin_k.map(f32::to_bits),
            )
        };
        let mut checked = 0;
        for &x in &vals {
            for &y in &vals {
                for &z in &vals {
                    let dir = Vec3::new(x, y, z);
                    let origin = Vec3::new(z, -x, 0.5 * y + 1.0);
                    let ray = crate::Ray {
                        origin,
                        t_min: f32::NAN,
                        dir,
                        t_max: -7.0,
                    };
                    // SAFETY: AVX is available (checked above).
                    let fast = unsafe { WatertightRay::new_avx(&ray) };
                    assert_eq!(
                        bits(&fast),
                        bits(&WatertightRay::new(origin, dir)),
                        "{dir:?}"
                    );
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, vals.len().pow(3));
    }

    fn tri() -> [Vec3; 3] {
        [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ]
    }

    #[test]
    fn hits_inside_and_reports_barycentrics() {
        let [a, b, c] = tri();
        let o = Vec3::new(0.25, 0.5, 1.0);
        let r = WatertightRay::new(o, Vec3::new(0.0, 0.0, -2.0));
        let (t, u, v) = intersect_triangle(&r, a, b, c, 0.0, f32::INFINITY).unwrap();
        assert!((t - 0.5).abs() < 1e-6);
        let p = a * (1.0 - u - v) + b * u + c * v;
        assert!((p - Vec3::new(0.25, 0.5, 0.0)).length() < 1e-6);
        // both faces
        let r = WatertightRay::new(Vec3::new(0.25, 0.25, -1.0), Vec3::Z);
        assert!(intersect_triangle(&r, a, b, c, 0.0, f32::INFINITY).is_some());
    }

    #[test]
    fn misses_outside_and_outside_interval() {
        let [a, b, c] = tri();
        let r = WatertightRay::new(Vec3::new(0.75, 0.75, 1.0), -Vec3::Z);
        assert!(intersect_triangle(&r, a, b, c, 0.0, f32::INFINITY).is_none());
        let r = WatertightRay::new(Vec3::new(0.25, 0.25, 1.0), -Vec3::Z);
        assert!(intersect_triangle(&r, a, b, c, 0.0, 0.5).is_none());
        assert!(intersect_triangle(&r, a, b, c, 1.5, 3.0).is_none());
    }

    #[test]
    fn shared_edge_never_slips_through() {
        // Two triangles sharing the diagonal of the unit square; rays exactly
        // through the diagonal must hit one of them.
        let p = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ];
        for i in 0..=64 {
            let s = i as f32 / 64.0;
            let r = WatertightRay::new(Vec3::new(s, s, 3.0), Vec3::new(0.0, 0.0, -1.0));
            let h1 = intersect_triangle(&r, p[0], p[1], p[2], 0.0, f32::INFINITY);
            let h2 = intersect_triangle(&r, p[0], p[2], p[3], 0.0, f32::INFINITY);
            assert!(h1.is_some() || h2.is_some(), "slipped through at {s}");
        }
    }

    #[test]
    fn degenerate_never_hit() {
        let a = Vec3::new(0.0, 0.0, 0.0);
        let b = Vec3::new(1.0, 1.0, 0.0);
        let r = WatertightRay::new(Vec3::new(0.5, 0.5, 1.0), -Vec3::Z);
        assert!(intersect_triangle(&r, a, a, b, 0.0, f32::INFINITY).is_none());
        assert!(intersect_triangle(&r, a, a, a, 0.0, f32::INFINITY).is_none());
        assert!(is_degenerate(a, b, b * 2.0));
        assert!(!is_degenerate(a, b, Vec3::X));
    }
}
