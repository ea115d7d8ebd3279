//! Top-down binned SAH builder over boxes and centroids.
//!
//! The builder knows nothing of triangles: it takes one box and one centroid
//! per primitive (as madmann91/bvh v2 does), so the object builder and the
//! top-level builders share it. Parallelism follows the usual recipe: the two
//! halves of a split are built as `rayon::join` tasks above a size threshold,
//! and large ranges are binned and partitioned in fixed-size chunks.
//!
//! Determinism: every split is a function of its primitive range only,
//! chunk sizes are constants, and merges are exact (box unions and integer
//! sums); each task returns its subtree already in depth-first pair order
//! (see [`Part`]) and one final pass lays them out. The tree and its node
//! order are therefore identical for any thread count.
//!
//! The top-level builder instead reserves a slot region per ref range (a
//! subtree over positions `b..e` owns slots `2b+1 .. 2e-1` for its
//! descendants) and compacts them afterwards ([`split_slots`],
//! [`compact_slots`]): its ranges are short and its buffers are reused
//! across builds, so the sparse slots cost nothing there.
//!
//! Tried and rejected: partitioning 40-byte primitive records (box,
//! centroid, id) instead of `u32` indices into the box and centroid arrays,
//! for sequential memory access as Embree's PrimRefs give. Single-thread
//! flat build of `library --scale 2` (2M triangles, `rebraid stats library
//! --scale 2 --modes flat`, alternating binaries): 2.1-2.3 s against
//! 1.93 s with indices; no change on the 125K-triangle nexuiz scene.

use glam::{BVec3A, Vec3, Vec3A};
use rayon::prelude::*;

use super::binning::{
    BinBox, BinMapping, BinRange, Bins, MAX_BINS, SplitCandidate, finite_lanes, with_bins,
};
use super::reinsert::ReinsertParams;
use super::{Bvh, BvhNode, Collapse};
use crate::{Aabb, Error};

/// Depth from which the builder stops using the SAH and splits at the object
/// median instead. Median splits halve the range, so no tree is deeper than
/// `MEDIAN_FROM_DEPTH + 32`, whatever the input (see [`MAX_DEPTH`]).
pub const MEDIAN_FROM_DEPTH: u32 = 32;

/// Upper bound on the depth (root = 1) of a tree built here; traversal stacks
/// are sized by it.
pub const MAX_DEPTH: u32 = MEDIAN_FROM_DEPTH + 32;

/// Ranges at least this long are binned in parallel chunks.
const PARALLEL_BINNING_MIN: usize = 1 << 15;
/// Chunk length of parallel binning and partitioning (a constant, so the
/// result does not depend on the number of threads).
const CHUNK: usize = 1 << 13;

/// Parameters of the binned SAH build. The defaults suit triangle BVHs traced
/// with the scalar kernels of this crate.
#[derive(Clone, Debug, PartialEq)]
pub struct BuildParams {
    /// SAH bins per axis (2 ..= 32).
    pub bins: usize,
    /// SAH cost of traversing an inner node.
    pub traversal_cost: f32,
    /// SAH cost of intersecting one primitive.
    pub intersection_cost: f32,
    /// Largest leaf; ranges above it are always split.
    pub max_leaf_size: u32,
    /// Primitives one intersection test handles (a power of two up to 16):
    /// the SAH prices a leaf of `n` primitives as `ceil(n / leaf_block_size)`
    /// tests, as Embree does for its `Triangle4` leaves. 4 matches the
    /// [`super::triangle4`] blocks traversal uses; 1 prices every primitive.
    pub leaf_block_size: u32,
    /// Subtrees over more primitives than this are built as parallel tasks.
    /// 1024 rather than 4096: two-thread object builds 3-6% faster
    /// (openarena 5.5-5.8 -> 5.2-5.3 ms, samurai 10.3 -> 10.0 ms), one
    /// thread equal within noise (`rebraid bench SCENES --modes two-level
    /// --threads 1` and `2`, alternating the binaries).
    pub parallel_threshold: usize,
    /// Reinsertion after the build ([`super::reinsert`]): off by default.
    /// It lowers the SAH cost of flat trees by 4-7% (Embree's statistic
    /// of the wide layout: samurai 10.73 -> 10.04, nexuiz 16.72 -> 15.97 at
    /// 0.05 x 3, the library at 3M triangles 24.13 -> 22.44, `embree-flat`
    /// 22.11) for 5-10% more build time; on object BVHs under a re-braided
    /// top level it changed the traversed statistic by -1% to +0.4%
    /// (docs/performance.md, session 36).
    pub reinsert: ReinsertParams,
    /// How the binary tree becomes the 8-wide one traversal walks
    /// ([`super::collapse`]): by default the SAH-optimal choice of wide
    /// nodes.
    pub collapse: Collapse,
    /// Large leaves of more than one block split where the SAH would keep
    /// them ([`LargeLeafSplit`]). On by default; the scene's object builds
    /// turn it off (it is for trees whose root is the scene: the flat
    /// mode's and the merged BVH of [`crate::scene::SceneParams::merge_placed`]).
    pub large_leaf_split: Option<LargeLeafSplit>,
    /// Nodes whose box holds much of the scene's volume become leaves of
    /// at most a quad ([`SceneVolumeLeafLimit`]). On by default, for object
    /// BVHs too ([`crate::Scene`] gives them the scene's volume).
    pub scene_volume_leaf_limit: Option<SceneVolumeLeafLimit>,
}

/// A rule for trees over a whole scene, whose rays mostly start inside the
/// root's box: a leaf of more than one [`BuildParams::leaf_block_size`]
/// block whose box is a large share of the root's is split when the best
/// binned split leaves most of its box empty, whatever the SAH says.
///
/// Why: the SAH prices a child by its surface area, the chance that a ray
/// crossing the parent's box from outside crosses the child's. For rays that
/// start inside the scene that chance is wrong for the largest boxes
/// (Fabianowski, Fowler and Dingliana, "A Cost Metric for Scene-Interior Ray
/// Origins", Eurographics 2009 short papers): the library scene's floor and
/// ceiling (a leaf of 8 triangles in two blocks, whose box is the whole
/// room) cost two blocks on every ray, since every ray starts inside that
/// box, while split they are two slabs that hold 3% of the room's volume
/// each, which a ray reaches only if it heads that way and nothing nearer
/// stops it. The SAH keeps them together because each slab has 0.79 of the
/// room's area. Embree's builder splits such leaves too, by another rule:
/// it fills a wide node by splitting its largest child of more than four
/// primitives whatever the SAH says (`docs/performance.md`, session 43).
///
/// Measured on the flat mode (`MODES=flat SETS=diffuse,primary,shadow
/// tools/ab-wall.sh 6 "SCENES" off on off`, `off` adding
/// `--no-large-leaf-split`; one thread, controls 0.99-1.01): the library at
/// 1M triangles 1.13-1.15 on all three ray sets; at 3M diffuse 1.025
/// (control 1.012), shadow 1.19, primary 0.95 (its floor and ceiling now
/// sit under an inner node of the room's box instead of in the root);
/// samurai diffuse 1.01; the other shared scenes 0.99-1.01. Without the
/// volume condition it also split leaves into two boxes each nearly the
/// leaf's (ravenbridge: 0.99 on primary rays). Object BVHs under a
/// two-level top level do not use it, their roots not being the scene:
/// with a candidate area of 5% of the scene's (and no volume condition),
/// re-braided diffuse rays lost 1.7% on samurai and 3.2% on the cocoa temple
/// (6.5% of its shadow rays) for 2.5-2.6% on nexuiz and openarena; with 5%
/// of each object's own area and the volume condition, they took 0.2-1.3%
/// more instructions on four of seven scenes (`docs/performance.md`,
/// session 43).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LargeLeafSplit {
    /// A leaf is a candidate when its box's surface area exceeds this share
    /// of the root's.
    pub min_area_share: f32,
    /// A candidate is split when the two boxes of the best split together
    /// hold less than this share of its box's volume.
    pub max_volume_share: f32,
}

impl LargeLeafSplit {
    /// 5% of the root's area, half the leaf's volume.
    pub const DEFAULT: Self = Self {
        min_area_share: 0.05,
        max_volume_share: 0.5,
    };
}

/// A rule for rays that start inside the scene: a node whose box holds at
/// least `min_volume_share` of the scene box's volume becomes a leaf only if
/// it has at most `max_primitives` primitives, whatever the SAH says.
///
/// Why: a ray whose origin lies inside a box enters it at distance 0, so
/// traversal tests that box's leaf before anything nearer can end the ray,
/// and nearly every ray of a closed scene (camera rays, shadow and bounce
/// rays from its surfaces) starts inside a box that holds most of the scene.
/// The SAH prices such a leaf by its area, the chance for a ray from outside
/// (the cost metric of Fabianowski, Fowler and Dingliana, Eurographics 2009,
/// adds the volume share for interior origins). Such boxes are a sky box's:
/// nexuiz keeps its sky in one material object of more than four triangles,
/// whose single leaf of two blocks spans the level, and openarena's flat
/// tree and objects both have one. Split down to quads, the sky's leaves
/// become slabs along the scene's faces, which a ray enters only where it
/// leaves the scene, after nearer hits have usually ended it.
///
/// Measured (session 48, `MODES=rebraided,flat SETS=primary,shadow,diffuse
/// tools/ab-wall.sh 5`, one thread, 480x270, against the commit before,
/// controls 0.99-1.04): re-braided diffuse / primary / shadow rays nexuiz
/// 1.082 / 1.038 / 1.016, openarena 1.152 / 1.036 / 1.200; the flat mode
/// nexuiz 1.063 / 0.980 / 1.062, openarena 1.147 / 1.060 / 1.154. On the
/// other shared scenes and the library (at 0.25 and 3) no node qualifies:
/// their trees are the same, at any share from 0.05 to 0.5. Builds are
/// unchanged (0.97-1.02, control 0.97-1.02). Measured against each tree's
/// own root instead of the scene, the rule also split the leaves of small
/// objects (samurai, ravenbridge and the library visited up to 37% more
/// leaves per ray); a quarter of the scene box's *area* instead of its
/// volume caught the cocoa temple's ground and the library's room, whose
/// re-braided rays then lost 2-3%.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneVolumeLeafLimit {
    /// Nodes whose box's volume is at least this share of the scene's.
    pub min_volume_share: f32,
    /// The most primitives such a node may keep as a leaf (at least 1).
    pub max_primitives: u32,
    /// The volume of the scene's box; `None`: the tree's own root box (a
    /// tree over the whole scene, as the flat mode's). [`crate::Scene`]
    /// sets it for the BVHs of objects placed in world space; a BVH kept
    /// from an earlier commit keeps the volume it was built with. A scene
    /// of no volume (flat) turns the rule off.
    pub scene_volume: Option<f32>,
}

impl SceneVolumeLeafLimit {
    /// A quarter of the scene's volume, one quad (two triangles) per leaf.
    pub const DEFAULT: Self = Self {
        min_volume_share: 0.25,
        max_primitives: 2,
        scene_volume: None,
    };
}

impl Default for BuildParams {
    fn default() -> Self {
        Self {
            bins: 32,
            traversal_cost: 1.0,
            intersection_cost: 1.0,
            max_leaf_size: 8,
            leaf_block_size: 4,
            parallel_threshold: 1024,
            reinsert: ReinsertParams::OFF,
            collapse: Collapse::default(),
            large_leaf_split: Some(LargeLeafSplit::DEFAULT),
            scene_volume_leaf_limit: Some(SceneVolumeLeafLimit::DEFAULT),
        }
    }
}

impl BuildParams {
    pub fn check(&self) -> Result<(), Error> {
        if !(2..=MAX_BINS).contains(&self.bins) {
            return Err(Error::InvalidParameter(format!(
                "bins must be in 2..={MAX_BINS}, got {}",
                self.bins
            )));
        }
        if !self.leaf_block_size.is_power_of_two() || self.leaf_block_size > 16 {
            return Err(Error::InvalidParameter(format!(
                "leaf_block_size must be a power of two up to 16, got {}",
                self.leaf_block_size
            )));
        }
        if self.max_leaf_size == 0 {
            return Err(Error::InvalidParameter(
                "max_leaf_size must be at least 1".into(),
            ));
        }
        self.reinsert.check()?;
        if let Some(r) = self.large_leaf_split
            && !(r.min_area_share >= 0.0
                && r.min_area_share.is_finite()
                && r.max_volume_share >= 0.0
                && r.max_volume_share.is_finite())
        {
            return Err(Error::InvalidParameter(format!(
                "large_leaf_split shares must be finite and >= 0, got {r:?}"
            )));
        }
        if let Some(r) = self.scene_volume_leaf_limit
            && !(r.min_volume_share > 0.0
                && r.min_volume_share.is_finite()
                && r.max_primitives >= 1
                && r.scene_volume.is_none_or(|v| v >= 0.0 && v.is_finite()))
        {
            return Err(Error::InvalidParameter(format!(
                "scene_volume_leaf_limit needs a finite share > 0, max_primitives >= 1 and a \
                 finite scene volume >= 0, got {r:?}"
            )));
        }
        let costs_ok = self.traversal_cost >= 0.0
            && self.intersection_cost > 0.0
            && self.traversal_cost.is_finite()
            && self.intersection_cost.is_finite();
        if !costs_ok {
            return Err(Error::InvalidParameter(
                "costs must be finite, traversal >= 0 and intersection > 0".into(),
            ));
        }
        Ok(())
    }
}

struct Ctx<'a> {
    boxes: &'a [BinBox],
    centroids: &'a [Vec3A],
    params: &'a BuildParams,
    /// [`BuildParams::large_leaf_split`] for this tree: the area above which
    /// a leaf is a candidate, and the volume share.
    large_leaf: Option<(f32, f32)>,
    /// [`BuildParams::scene_volume_leaf_limit`] for this tree: the volume
    /// from which a node is limited, and the primitives it may keep.
    volume_leaf: Option<(f32, usize)>,
}

impl Ctx<'_> {
    /// True when [`LargeLeafSplit`] overrules the SAH's leaf of `blocks`
    /// blocks over `bounds` in favour of the split `s`.
    fn splits_large_leaf(&self, blocks: usize, bounds: &Aabb, s: &SplitCandidate) -> bool {
        let Some((min_area, volume_share)) = self.large_leaf else {
            return false;
        };
        blocks > 1
            && bounds.half_area() > min_area
            && s.left_bounds.volume() + s.right_bounds.volume() < volume_share * bounds.volume()
    }

    /// True when [`SceneVolumeLeafLimit`] forbids a leaf of `n` primitives
    /// over `bounds`.
    fn limits_leaf(&self, n: usize, bounds: &Aabb) -> bool {
        self.volume_leaf
            .is_some_and(|(min_volume, max)| n > max && bounds.volume() >= min_volume)
    }

    /// Box and centroid of primitive `p`, an element of the build's `prims`
    /// (unchecked: two compares and branches per primitive in the binning
    /// and partition loops, measured with callgrind in the commit that made
    /// it so).
    #[inline(always)]
    fn prim(&self, p: u32) -> (&BinBox, Vec3A) {
        debug_assert!((p as usize) < self.boxes.len() && (p as usize) < self.centroids.len());
        // SAFETY: `build_bvh_aligned` checks that `boxes` and `centroids`
        // have one element per primitive and starts `prims` as `0..n`; the
        // builder only ever permutes `prims` (partitions, median selection,
        // copies back from `scratch`), so every element stays below `n`.
        unsafe {
            (
                self.boxes.get_unchecked(p as usize),
                *self.centroids.get_unchecked(p as usize),
            )
        }
    }
}

/// Build a BVH over `boxes` (one per primitive) split by `centroids`.
///
/// Every box must be finite and non-empty. An empty input gives an empty BVH.
/// Converts to the 16-byte-aligned form [`build_bvh_aligned`] takes.
pub fn build_bvh(boxes: &[Aabb], centroids: &[Vec3], params: &BuildParams) -> Result<Bvh, Error> {
    let boxes: Vec<BinBox> = boxes.iter().map(BinBox::from_aabb).collect();
    let centroids: Vec<Vec3A> = centroids.iter().map(|&c| c.into()).collect();
    build_bvh_aligned(&boxes, &centroids, params)
}

/// [`build_bvh`] over boxes and centroids in SSE-aligned vectors, which the
/// binning and partitioning loops load in one instruction each (object
/// builds 10-12% faster than over `Aabb`/`Vec3` arrays of 24 and 12 bytes;
/// measured in the commit that introduced it).
pub fn build_bvh_aligned(
    boxes: &[BinBox],
    centroids: &[Vec3A],
    params: &BuildParams,
) -> Result<Bvh, Error> {
    params.check()?;
    if boxes.len() != centroids.len() {
        return Err(Error::InvalidParameter(format!(
            "{} boxes but {} centroids",
            boxes.len(),
            centroids.len()
        )));
    }
    let n = boxes.len();
    if n >= (1usize << 31) {
        return Err(Error::TooManyPrimitives(n));
    }
    if n == 0 {
        return Ok(Bvh::default());
    }
    let (bounds, cbounds, valid) = range_bounds(boxes, centroids);
    if !valid {
        // The error path only: find the first bad primitive.
        let i = (0..n)
            .into_par_iter()
            .with_min_len(4096)
            .find_first(|&i| !boxes[i].is_valid() || !centroids[i].is_finite())
            .expect("range_bounds saw an invalid primitive");
        return Err(Error::InvalidBounds { index: i });
    }
    let mut prims: Vec<u32> = (0..n as u32).collect();
    let mut scratch = vec![0u32; n];
    let ctx = Ctx {
        boxes,
        centroids,
        params,
        large_leaf: params
            .large_leaf_split
            .map(|r| (r.min_area_share * bounds.half_area(), r.max_volume_share)),
        volume_leaf: params.scene_volume_leaf_limit.and_then(|r| {
            let scene = r.scene_volume.unwrap_or_else(|| bounds.volume());
            // No volume (a flat scene) or too much for an `f32`: off.
            let min_volume = r.min_volume_share * scene;
            (scene > 0.0 && min_volume.is_finite())
                .then_some((min_volume, r.max_primitives as usize))
        }),
    };
    let nodes = match build_part(&ctx, &mut prims, &mut scratch, 0, bounds, cbounds, 1) {
        // One task built it all: its vector is the tree (no copy).
        Part::Seq(mut nodes) => {
            nodes.shrink_to_fit();
            nodes
        }
        root => {
            let mut nodes = Vec::with_capacity(1 + root.descendants());
            nodes.push(BvhNode::zeroed_node());
            root.emit(0, &mut nodes);
            nodes
        }
    };
    let mut bvh = Bvh {
        nodes,
        prim_indices: prims,
    };
    bvh.reinsert(&params.reinsert);
    #[cfg(debug_assertions)]
    if let Err(e) = bvh.validate(&boxes.iter().map(|b| b.to_aabb()).collect::<Vec<_>>()) {
        panic!("BVH builder produced an invalid tree: {e}");
    }
    Ok(bvh)
}

/// A subtree as the builder's tasks return it, before the one pass that
/// lays every node out in depth-first pair order (each node's children pair
/// is placed when the node is visited; the left child's descendants follow,
/// then the right child's).
///
/// Why not write nodes into their final slots directly: the final position
/// of a node depends on how many nodes the subtrees to its left produce,
/// which parallel tasks learn only at the end. The builder used to reserve
/// a slot region per primitive range (`2n - 1` slots, the worst case), which
/// wrote and page-faulted 64 bytes per triangle for about 16 used: 20% of an
/// object build in the kernel's page-fault path (measured in the commit
/// that replaced it). Now each sequential task appends its subtree to its
/// own vector, already in final relative order, and only the few nodes split
/// by parallel tasks are kept as `Split`s.
enum Part {
    /// A subtree built by one task: its root first, then its descendants in
    /// depth-first pair order, child indices relative to the vector (so a
    /// tree built by one task is already the final node array).
    Seq(Vec<BvhNode>),
    /// A node whose halves were built by parallel tasks.
    Split(Aabb, Box<[Part; 2]>),
}

impl Part {
    /// Number of nodes below the root.
    fn descendants(&self) -> usize {
        match self {
            Part::Seq(nodes) => nodes.len() - 1,
            Part::Split(_, kids) => 2 + kids[0].descendants() + kids[1].descendants(),
        }
    }

    /// Write this subtree's root into `out[slot]` and append its descendants.
    fn emit(self, slot: usize, out: &mut Vec<BvhNode>) {
        match self {
            Part::Seq(nodes) => {
                // Relative index `i >= 1` lands at `out.len() + i - 1`.
                let base = out.len() as u32 - 1;
                let moved = |mut node: BvhNode| {
                    if !node.is_leaf() {
                        node.index += base;
                    }
                    node
                };
                let (root, desc) = nodes.split_first().expect("a part has a root");
                out[slot] = moved(*root);
                out.extend(desc.iter().copied().map(moved));
            }
            Part::Split(bounds, kids) => {
                let pair = out.len();
                out[slot] = BvhNode::inner(bounds, pair as u32);
                out.extend([BvhNode::zeroed_node(); 2]);
                let [left, right] = *kids;
                left.emit(pair, out);
                right.emit(pair + 1, out);
            }
        }
    }
}

impl BvhNode {
    fn zeroed_node() -> Self {
        bytemuck::Zeroable::zeroed()
    }
}

/// Bounds of the boxes and of the centroids, and whether every box is
/// valid ([`BinBox::is_valid`]) and every centroid finite: one pass, in
/// parallel for long inputs.
///
/// The check rides along as lane masks ANDed without a branch. It used to
/// be a separate `find_first` pass, whose per-element closure (glam's
/// `is_finite` called out of line) took 3-4% of a one-thread nexuiz
/// re-braided build in `perf` (session 29).
fn range_bounds(boxes: &[BinBox], centroids: &[Vec3A]) -> (Aabb, Aabb, bool) {
    let fold = |(b, c, ok): (BinBox, BinBox, BVec3A), (x, y): (&BinBox, &Vec3A)| {
        (
            b.union(*x),
            c.grow(*y),
            ok & x.valid_lanes() & finite_lanes(*y),
        )
    };
    let join = |(a, b, p): (BinBox, BinBox, BVec3A), (c, d, q): (BinBox, BinBox, BVec3A)| {
        (a.union(c), b.union(d), p & q)
    };
    let empty = (BinBox::EMPTY, BinBox::EMPTY, BVec3A::TRUE);
    let (b, c, ok) = if boxes.len() >= PARALLEL_BINNING_MIN {
        boxes
            .par_chunks(CHUNK)
            .zip(centroids.par_chunks(CHUNK))
            .map(|(b, c)| b.iter().zip(c).fold(empty, fold))
            .reduce(|| empty, join)
    } else {
        boxes.iter().zip(centroids).fold(empty, fold)
    };
    (b.to_aabb(), c.to_aabb(), ok.all())
}

fn bounds_of(ctx: &Ctx, prims: &[u32]) -> (Aabb, Aabb) {
    let (b, c) = prims
        .iter()
        .fold((BinBox::EMPTY, BinBox::EMPTY), |(b, c), &p| {
            (
                b.union(ctx.boxes[p as usize]),
                c.grow(ctx.centroids[p as usize]),
            )
        });
    (b.to_aabb(), c.to_aabb())
}

/// Bins the primitives of a range (in parallel chunks when long).
struct RangeBinner<'a, 'b> {
    ctx: &'a Ctx<'b>,
    prims: &'a [u32],
}

impl BinRange for RangeBinner<'_, '_> {
    fn run<const N: usize>(&self, map: &BinMapping) -> Option<SplitCandidate> {
        let ctx = self.ctx;
        // Bins are filled in place: returning them by value copied up to
        // 3.8 KB per node (7% of a build in `memmove`).
        let fill = |bins: &mut Bins<N>, chunk: &[u32]| {
            bins.fill(
                map,
                chunk.iter().map(|&p| {
                    let (b, c) = ctx.prim(p);
                    (*b, c, 1)
                }),
            );
        };
        let mut all = Bins::<N>::default();
        if self.prims.len() >= PARALLEL_BINNING_MIN {
            let parts: Vec<Bins<N>> = self
                .prims
                .par_chunks(CHUNK)
                .map(|chunk| {
                    let mut bins = Bins::<N>::default();
                    fill(&mut bins, chunk);
                    bins
                })
                .collect();
            for p in &parts {
                all.merge(p, map.bins);
            }
        } else {
            fill(&mut all, self.prims);
        }
        all.best_split_blocks(map, ctx.params.leaf_block_size.trailing_zeros())
    }
}

/// Partition `prims` so that those for which `is_left` holds come first.
/// Returns the left count and the centroid bounds of both sides.
fn partition<F>(
    ctx: &Ctx,
    prims: &mut [u32],
    scratch: &mut [u32],
    is_left: F,
) -> (usize, Aabb, Aabb)
where
    F: Fn(Vec3A) -> bool + Sync,
{
    let c = ctx.centroids;
    if prims.len() < PARALLEL_BINNING_MIN {
        // Tried and rejected: a branch-free Lomuto partition (swap always,
        // advance on "left"; same sets, identical SAH). Re-braided builds of
        // samurai 26.2-27.1 ms against 27.1-28.1 here, shadow rays 1-3%
        // slower (it scrambles the order inside leaves, hence which
        // triangles share a Triangle4 block); `rebraid bench
        // samurai_monastery.obj 2CylinderEngine.glb nexuiz_ons_reborn.obj
        // --modes rebraided --threads 1 --width 640 --height 360`,
        // alternating the binaries.
        let (mut i, mut j) = (0, prims.len());
        let (mut cl, mut cr) = (BinBox::EMPTY, BinBox::EMPTY);
        while i < j {
            let p = ctx.prim(prims[i]).1;
            if is_left(p) {
                cl = cl.grow(p);
                i += 1;
            } else {
                cr = cr.grow(p);
                j -= 1;
                prims.swap(i, j);
            }
        }
        return (i, cl.to_aabb(), cr.to_aabb());
    }
    // Chunked stable partition through `scratch`.
    let counts: Vec<(usize, BinBox, BinBox)> = prims
        .par_chunks(CHUNK)
        .map(|chunk| {
            let (mut n, mut cl, mut cr) = (0, BinBox::EMPTY, BinBox::EMPTY);
            for &q in chunk {
                let p = c[q as usize];
                if is_left(p) {
                    n += 1;
                    cl = cl.grow(p);
                } else {
                    cr = cr.grow(p);
                }
            }
            (n, cl, cr)
        })
        .collect();
    let left: usize = counts.iter().map(|x| x.0).sum();
    let (mut rest_l, mut rest_r) = scratch.split_at_mut(left);
    let mut dests = Vec::with_capacity(counts.len());
    for (k, &(nl, _, _)) in counts.iter().enumerate() {
        let len = CHUNK.min(prims.len() - k * CHUNK);
        let (a, tail_l) = std::mem::take(&mut rest_l).split_at_mut(nl);
        let (b, tail_r) = std::mem::take(&mut rest_r).split_at_mut(len - nl);
        rest_l = tail_l;
        rest_r = tail_r;
        dests.push((a, b));
    }
    prims
        .par_chunks(CHUNK)
        .zip(dests.into_par_iter())
        .for_each(|(chunk, (dl, dr))| {
            let (mut i, mut j) = (0, 0);
            for &q in chunk {
                if is_left(c[q as usize]) {
                    dl[i] = q;
                    i += 1;
                } else {
                    dr[j] = q;
                    j += 1;
                }
            }
        });
    prims
        .par_chunks_mut(CHUNK)
        .zip(scratch.par_chunks(CHUNK))
        .for_each(|(d, s)| d.copy_from_slice(s));
    let (cl, cr) = counts
        .iter()
        .fold((BinBox::EMPTY, BinBox::EMPTY), |(a, b), x| {
            (a.union(x.1), b.union(x.2))
        });
    (left, cl.to_aabb(), cr.to_aabb())
}

/// How a range is to be built: as one leaf, or split at `mid` into two
/// halves with their bounds and centroid bounds.
enum Decision {
    Leaf,
    Split {
        mid: usize,
        left: (Aabb, Aabb),
        right: (Aabb, Aabb),
    },
}

/// Choose between a leaf and the best binned SAH split of `prims`; a split
/// is applied (the range partitioned) before returning.
fn decide(
    ctx: &Ctx,
    prims: &mut [u32],
    scratch: &mut [u32],
    bounds: Aabb,
    cbounds: Aabb,
    depth: u32,
) -> Decision {
    let n = prims.len();
    let p = ctx.params;
    if n == 1 {
        return Decision::Leaf;
    }
    let fits_leaf = n <= p.max_leaf_size as usize && !ctx.limits_leaf(n, &bounds);
    // One block: a split's cost (traversal plus at least one block per
    // side) can never undercut the leaf's single block when traversal
    // costs at least an intersection, so skip the binning.
    if fits_leaf && n <= p.leaf_block_size as usize && p.traversal_cost >= p.intersection_cost {
        return Decision::Leaf;
    }
    let use_sah = depth < MEDIAN_FROM_DEPTH && cbounds.extent().max_element() > 0.0;

    let split = if use_sah {
        // Small ranges get fewer bins: 4 + n / 20, Embree's count
        // (`BinMapping` in its `heuristic_binning.h`).
        let map = BinMapping::new(&cbounds, p.bins.min(4 + n / 20));
        with_bins(&map, &RangeBinner { ctx, prims }).map(|s| (map, s))
    } else {
        None
    };

    match split {
        Some((map, s)) => {
            // Compare costs multiplied through by the node's area, which also
            // handles nodes of zero area.
            let area = bounds.half_area();
            let split_cost = p.traversal_cost * area + p.intersection_cost * s.cost;
            let blocks = n.div_ceil(p.leaf_block_size as usize);
            let leaf_cost = p.intersection_cost * blocks as f32 * area;
            if fits_leaf && leaf_cost <= split_cost && !ctx.splits_large_leaf(blocks, &bounds, &s) {
                return Decision::Leaf;
            }
            let axis = s.axis;
            let (mid, lcb, rcb) = match axis {
                0 => partition(ctx, prims, scratch, |c| map.goes_left::<0>(c, s.bin)),
                1 => partition(ctx, prims, scratch, |c| map.goes_left::<1>(c, s.bin)),
                _ => partition(ctx, prims, scratch, |c| map.goes_left::<2>(c, s.bin)),
            };
            debug_assert_eq!(mid as u64, s.left_weight);
            Decision::Split {
                mid,
                left: (s.left_bounds, lcb),
                right: (s.right_bounds, rcb),
            }
        }
        None => {
            if fits_leaf {
                return Decision::Leaf;
            }
            // Object median along the longest centroid axis, or an index
            // median when all centroids coincide.
            let mid = n / 2;
            if cbounds.extent().max_element() > 0.0 {
                let axis = cbounds.largest_axis();
                let c = ctx.centroids;
                prims.select_nth_unstable_by(mid, |&a, &b| {
                    c[a as usize][axis]
                        .total_cmp(&c[b as usize][axis])
                        .then(a.cmp(&b))
                });
            }
            let (l, r) = prims.split_at(mid);
            Decision::Split {
                mid,
                left: bounds_of(ctx, l),
                right: bounds_of(ctx, r),
            }
        }
    }
}

/// Build the subtree over `prims` (global offset `first`), splitting the
/// work into parallel tasks while ranges are longer than the parallel
/// threshold.
fn build_part(
    ctx: &Ctx,
    prims: &mut [u32],
    scratch: &mut [u32],
    first: u32,
    bounds: Aabb,
    cbounds: Aabb,
    depth: u32,
) -> Part {
    let n = prims.len();
    if n <= ctx.params.parallel_threshold {
        // Typical trees have about one node per two primitives; the root's
        // slot first.
        let mut nodes = Vec::with_capacity(n);
        nodes.push(BvhNode::zeroed_node());
        nodes[0] = build_seq(
            ctx, prims, scratch, first, bounds, cbounds, depth, &mut nodes,
        );
        return Part::Seq(nodes);
    }
    match decide(ctx, prims, scratch, bounds, cbounds, depth) {
        Decision::Leaf => Part::Seq(vec![BvhNode::leaf(bounds, first, n as u32)]),
        Decision::Split { mid, left, right } => {
            let (lp, rp) = prims.split_at_mut(mid);
            let (ls, rs) = scratch.split_at_mut(mid);
            let right_first = first + mid as u32;
            let (l, r) = rayon::join(
                || build_part(ctx, lp, ls, first, left.0, left.1, depth + 1),
                || build_part(ctx, rp, rs, right_first, right.0, right.1, depth + 1),
            );
            Part::Split(bounds, Box::new([l, r]))
        }
    }
}

/// Build the subtree over `prims` (global offset `first`) in this task:
/// returns its root and appends its descendants to `out` in depth-first
/// pair order, child indices relative to `out`'s start (where the caller
/// keeps the root's slot).
#[allow(clippy::too_many_arguments)]
fn build_seq(
    ctx: &Ctx,
    prims: &mut [u32],
    scratch: &mut [u32],
    first: u32,
    bounds: Aabb,
    cbounds: Aabb,
    depth: u32,
    out: &mut Vec<BvhNode>,
) -> BvhNode {
    let n = prims.len();
    match decide(ctx, prims, scratch, bounds, cbounds, depth) {
        Decision::Leaf => BvhNode::leaf(bounds, first, n as u32),
        Decision::Split { mid, left, right } => {
            let pair = out.len();
            out.extend([BvhNode::zeroed_node(); 2]);
            let (lp, rp) = prims.split_at_mut(mid);
            let (ls, rs) = scratch.split_at_mut(mid);
            out[pair] = build_seq(ctx, lp, ls, first, left.0, left.1, depth + 1, out);
            let right_first = first + mid as u32;
            out[pair + 1] = build_seq(ctx, rp, rs, right_first, right.0, right.1, depth + 1, out);
            BvhNode::inner(bounds, pair as u32)
        }
    }
}

/// Split the descendant slots of a node whose left child covers `left_len`
/// primitive (or ref array) positions: the children pair, then the left
/// subtree's `2 * left_len - 2` descendant slots, then the right subtree's;
/// each region with its global first slot. The one place that states the
/// slot layout both builders rely on (see the module docs).
#[allow(clippy::type_complexity)]
pub(crate) fn split_slots(
    desc: &mut [BvhNode],
    desc_first: u32,
    left_len: usize,
) -> (&mut [BvhNode], (&mut [BvhNode], u32), (&mut [BvhNode], u32)) {
    let (pair, rest) = desc.split_at_mut(2);
    let (left, right) = rest.split_at_mut(2 * left_len - 2);
    (
        pair,
        (left, desc_first + 2),
        (right, desc_first + 2 * left_len as u32),
    )
}

/// Renumber the used node slots of a slot-layout build into depth-first
/// order (each node's children pair allocated when the node is visited),
/// dropping the unused slots, into `out` (cleared first; its capacity is
/// reused). `on_leaf` sees every leaf in that order and may
/// rewrite its primitive range (the top-level builder compacts its refs so).
pub(crate) fn compact_slots(
    slots: &[BvhNode],
    out: &mut Vec<BvhNode>,
    mut on_leaf: impl FnMut(&mut BvhNode),
) {
    out.clear();
    out.push(slots[0]);
    let mut stack = vec![0usize];
    while let Some(i) = stack.pop() {
        let node = out[i];
        if node.is_leaf() {
            on_leaf(&mut out[i]);
            continue;
        }
        let old = node.index as usize;
        let new = out.len();
        out.push(slots[old]);
        out.push(slots[old + 1]);
        out[i].index = new as u32;
        stack.push(new + 1);
        stack.push(new);
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::bvh::test_trees::{box_faces, boxes_and_centroids};

    /// A closed room (floor and ceiling slabs, two triangles per face) around
    /// small triangles scattered inside it: the case [`LargeLeafSplit`] is
    /// for. Returns the boxes and centroids of its triangles.
    fn room() -> (Vec<Aabb>, Vec<Vec3>) {
        let mut tris: Vec<[Vec3; 3]> = Vec::new();
        for y in [-0.1f32, 0.0, 5.0, 5.1] {
            let (a, b, c, d) = (
                Vec3::new(0.0, y, 0.0),
                Vec3::new(100.0, y, 0.0),
                Vec3::new(100.0, y, 50.0),
                Vec3::new(0.0, y, 50.0),
            );
            tris.push([a, b, c]);
            tris.push([a, c, d]);
        }
        let mut rng = Pcg64::seed_from_u64(43);
        let mut next = move || rng.gen_range(0.0f32..1.0);
        for _ in 0..4000 {
            let c = Vec3::new(100.0 * next(), 0.2 + 4.3 * next(), 50.0 * next());
            let mut corner = || c + Vec3::new(next(), next(), next()) * 0.5;
            tris.push([corner(), corner(), corner()]);
        }
        boxes_and_centroids(&tris)
    }

    /// A sky: the twelve triangles of the faces of a 100 x 40 x 60 box,
    /// and `contents` small triangles inside it.
    fn sky(contents: usize) -> (Vec<Aabb>, Vec<Vec3>) {
        let size = Vec3::new(100.0, 40.0, 60.0);
        let mut tris = box_faces(Vec3::ZERO, size);
        let mut rng = Pcg64::seed_from_u64(48);
        let mut next = move || rng.gen_range(0.0f32..1.0);
        for _ in 0..contents {
            let c = Vec3::new(next(), next(), next()) * (size - 1.0);
            let mut corner = || c + Vec3::new(next(), next(), next());
            tris.push([corner(), corner(), corner()]);
        }
        boxes_and_centroids(&tris)
    }

    /// The most primitives in a leaf whose box holds at least `share` of
    /// `volume`.
    fn fullest_voluminous_leaf(bvh: &Bvh, share: f32, volume: f32) -> u32 {
        bvh.nodes
            .iter()
            .filter(|n| n.is_leaf() && n.bounds().volume() >= share * volume)
            .map(|n| n.count)
            .max()
            .unwrap_or(0)
    }

    #[test]
    fn scene_volume_leaf_limit_splits_the_sky() {
        let limit = SceneVolumeLeafLimit::DEFAULT;
        let off = BuildParams {
            scene_volume_leaf_limit: None,
            ..BuildParams::default()
        };
        for contents in [0, 3000] {
            let (boxes, centroids) = sky(contents);
            let volume = 100.0 * 40.0 * 60.0;
            // The SAH alone keeps leaves of several sky triangles whose
            // boxes hold most of the scene...
            let b = build_bvh(&boxes, &centroids, &off).unwrap();
            b.validate(&boxes).unwrap();
            let fullest = fullest_voluminous_leaf(&b, limit.min_volume_share, volume);
            assert!(fullest > limit.max_primitives, "{contents}: {fullest}");
            // ...which the rule splits down to quads.
            let a = build_bvh(&boxes, &centroids, &BuildParams::default()).unwrap();
            a.validate(&boxes).unwrap();
            let fullest = fullest_voluminous_leaf(&a, limit.min_volume_share, volume);
            assert!(fullest <= limit.max_primitives, "{contents}: {fullest}");
        }
    }

    #[test]
    fn scene_volume_leaf_limit_measures_against_the_scene() {
        let (boxes, centroids) = sky(0);
        let with = |scene_volume| BuildParams {
            scene_volume_leaf_limit: Some(SceneVolumeLeafLimit {
                scene_volume,
                ..SceneVolumeLeafLimit::DEFAULT
            }),
            ..BuildParams::default()
        };
        let off = BuildParams {
            scene_volume_leaf_limit: None,
            ..BuildParams::default()
        };
        let plain = build_bvh(&boxes, &centroids, &off).unwrap();
        // A sky object in a scene 8 times its volume, or in a flat scene:
        // the SAH's tree.
        for v in [8.0 * 100.0 * 40.0 * 60.0, 0.0] {
            let t = build_bvh(&boxes, &centroids, &with(Some(v))).unwrap();
            assert_eq!(t.nodes, plain.nodes, "{v}");
        }
        // In a scene of its own size: split.
        let t = build_bvh(&boxes, &centroids, &with(Some(100.0 * 40.0 * 60.0))).unwrap();
        assert_eq!(
            t,
            build_bvh(&boxes, &centroids, &BuildParams::default()).unwrap()
        );
        assert_ne!(t.nodes, plain.nodes);
    }

    #[test]
    fn scene_volume_leaf_limit_is_checked() {
        let bad = [
            SceneVolumeLeafLimit {
                min_volume_share: 0.0,
                ..SceneVolumeLeafLimit::DEFAULT
            },
            SceneVolumeLeafLimit {
                min_volume_share: f32::NAN,
                ..SceneVolumeLeafLimit::DEFAULT
            },
            SceneVolumeLeafLimit {
                max_primitives: 0,
                ..SceneVolumeLeafLimit::DEFAULT
            },
            SceneVolumeLeafLimit {
                scene_volume: Some(-1.0),
                ..SceneVolumeLeafLimit::DEFAULT
            },
            SceneVolumeLeafLimit {
                scene_volume: Some(f32::INFINITY),
                ..SceneVolumeLeafLimit::DEFAULT
            },
        ];
        for r in bad {
            let p = BuildParams {
                scene_volume_leaf_limit: Some(r),
                ..BuildParams::default()
            };
            assert!(
                matches!(p.check(), Err(Error::InvalidParameter(_))),
                "{r:?}"
            );
        }
    }

    /// The largest half area of a leaf of more than one block, over the
    /// root's.
    fn largest_multi_block_leaf(bvh: &Bvh, block: u32) -> f32 {
        let root = bvh.nodes[0].bounds().half_area();
        bvh.nodes
            .iter()
            .filter(|n| n.is_leaf() && n.count > block)
            .map(|n| n.bounds().half_area() / root)
            .fold(0.0, f32::max)
    }

    #[test]
    fn large_leaf_split_takes_the_room_apart() {
        let (boxes, centroids) = room();
        // The rule alone: the room's floor and ceiling leaf also holds the
        // room's volume, which `SceneVolumeLeafLimit` would split too.
        let with = BuildParams {
            scene_volume_leaf_limit: None,
            ..BuildParams::default()
        };
        let without = BuildParams {
            large_leaf_split: None,
            ..with.clone()
        };
        let a = build_bvh(&boxes, &centroids, &with).unwrap();
        let b = build_bvh(&boxes, &centroids, &without).unwrap();
        a.validate(&boxes).unwrap();
        b.validate(&boxes).unwrap();
        // The SAH alone keeps floor and ceiling in one leaf of two blocks
        // whose box is the room's...
        let largest = largest_multi_block_leaf(&b, with.leaf_block_size);
        assert!(largest > 0.9, "{largest}");
        // ...which the rule splits into slabs: no leaf of two blocks is left
        // above its area threshold.
        let limit = LargeLeafSplit::DEFAULT.min_area_share;
        assert!(largest_multi_block_leaf(&a, with.leaf_block_size) <= limit);
    }

    #[test]
    fn large_leaf_split_leaves_overlapping_splits_alone() {
        // Two triangles of the same large box in each of three places: any
        // split of a leaf over them keeps nearly all of its volume, so the
        // rule keeps the SAH's choice.
        let mut boxes = Vec::new();
        for i in 0..6 {
            let o = (i % 3) as f32 * 0.01;
            boxes.push(Aabb {
                min: Vec3::splat(o),
                max: Vec3::splat(10.0 + o),
            });
        }
        let centroids: Vec<Vec3> = boxes.iter().map(|b| b.center()).collect();
        let with = build_bvh(&boxes, &centroids, &BuildParams::default()).unwrap();
        let without = build_bvh(
            &boxes,
            &centroids,
            &BuildParams {
                large_leaf_split: None,
                ..BuildParams::default()
            },
        )
        .unwrap();
        assert_eq!(with.nodes, without.nodes);
    }

    #[test]
    fn large_leaf_split_shares_are_checked() {
        for bad in [-1.0, f32::NAN, f32::INFINITY] {
            for r in [
                LargeLeafSplit {
                    min_area_share: bad,
                    ..LargeLeafSplit::DEFAULT
                },
                LargeLeafSplit {
                    max_volume_share: bad,
                    ..LargeLeafSplit::DEFAULT
                },
            ] {
                let p = BuildParams {
                    large_leaf_split: Some(r),
                    ..BuildParams::default()
                };
                assert!(p.check().is_err(), "{r:?}");
            }
        }
    }
}
