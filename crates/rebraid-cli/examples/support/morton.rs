//! Morton codes of points in a box, shared by the examples that order
//! triangles along a space-filling curve (`interleave`, `chunks`).

use glam::Vec3;

/// The low 21 bits of `v` spread to every third bit.
pub fn spread(v: u32) -> u64 {
    let mut x = v as u64 & 0x1f_ffff;
    x = (x | x << 32) & 0x1f_0000_0000_ffff;
    x = (x | x << 16) & 0x1f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    x = (x | x << 2) & 0x1249_2492_4924_9249;
    x
}

/// The 63-bit Morton code of `p` in the box `lo .. lo + extent` (21 bits
/// per axis; `extent` must be positive on every axis).
pub fn code(p: Vec3, lo: Vec3, extent: Vec3) -> u64 {
    let q = ((p - lo) / extent * 2_097_151.0).as_uvec3();
    spread(q.x) | spread(q.y) << 1 | spread(q.z) << 2
}
