//! Random box sets and binary trees over them, shared by the unit tests of
//! the tree passes that work on built trees (reinsertion, the collapse).

use glam::Vec3;

use super::{BuildParams, Bvh, BvhNode, build_bvh};
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

/// One small tree, `((a, b), c)` over leaves of one primitive each, in two
/// layouts: children after their parents (root (1, 2), 1 = (3, 4)), and the
/// inner child after its own children (root (3, 4), 3 = (1, 2)).
pub(crate) fn two_layouts(a: Aabb, b: Aabb, c: Aabb) -> [[BvhNode; 5]; 2] {
    let ab = a.union(b);
    let all = ab.union(c);
    [
        [
            BvhNode::inner(all, 1),
            BvhNode::inner(ab, 3),
            BvhNode::leaf(c, 2, 1),
            BvhNode::leaf(a, 0, 1),
            BvhNode::leaf(b, 1, 1),
        ],
        [
            BvhNode::inner(all, 3),
            BvhNode::leaf(a, 0, 1),
            BvhNode::leaf(b, 1, 1),
            BvhNode::inner(ab, 1),
            BvhNode::leaf(c, 2, 1),
        ],
    ]
}

/// The twelve triangles of the faces of the box from `lo` to `lo + size`,
/// two per face.
pub(crate) fn box_faces(lo: Vec3, size: Vec3) -> Vec<[Vec3; 3]> {
    let corner =
        |i: usize| lo + Vec3::new((i & 1) as f32, (i >> 1 & 1) as f32, (i >> 2) as f32) * size;
    // Each face's four corners in a loop, as indices into `corner`.
    let faces = [
        [0, 1, 3, 2],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 3, 7, 6],
        [0, 2, 6, 4],
        [1, 3, 7, 5],
    ];
    faces
        .iter()
        .flat_map(|f| [[f[0], f[1], f[2]], [f[0], f[2], f[3]]])
        .map(|t| t.map(corner))
        .collect()
}

/// Per triangle, its box and the box's centre: a build's input.
pub(crate) fn boxes_and_centroids(tris: &[[Vec3; 3]]) -> (Vec<Aabb>, Vec<Vec3>) {
    tris.iter()
        .map(|t| {
            let b = t.iter().fold(Aabb::EMPTY, |b, &p| b.grow(p));
            (b, b.center())
        })
        .unzip()
}
