//! Random box sets and binary trees over them, shared by the unit tests of
//! the tree passes that work on built trees (reinsertion, the collapse).

use glam::Vec3;

use super::{BuildParams, Bvh, build_bvh};
use crate::Aabb;

/// `n` boxes of random size scattered in a cube, every 37th large (what a
/// top level over opened refs looks like); xorshift from `seed`.
pub(crate) fn scattered_boxes(seed: u32, n: usize) -> Vec<Aabb> {
    let mut rng = seed | 1;
    let mut next = || {
        rng ^= rng << 13;
        rng ^= rng >> 17;
        rng ^= rng << 5;
        rng as f32 / u32::MAX as f32
    };
    (0..n)
        .map(|i| {
            let c = Vec3::new(next(), next(), next()) * 100.0;
            let size = if i % 37 == 0 { 40.0 } else { 3.0 };
            Aabb::new(c, c + Vec3::new(next(), next(), next()) * size)
        })
        .collect()
}

/// The binned SAH tree over `boxes` with leaves of at most `max_leaf`.
pub(crate) fn build_over(boxes: &[Aabb], max_leaf: u32) -> Bvh {
    let centroids: Vec<Vec3> = boxes.iter().map(|b| b.center()).collect();
    let params = BuildParams {
        max_leaf_size: max_leaf,
        ..BuildParams::default()
    };
    build_bvh(boxes, &centroids, &params).unwrap()
}
