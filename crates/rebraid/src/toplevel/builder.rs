//! The top-level builder with partial re-braiding.
//!
//! C. Benthin, S. Woop, I. Wald, A. Áfra, "Improved Two-Level BVHs using
//! Partial Re-Braiding", HPG 2017 (see `shared/docs/rebraiding.md`). The build
//! is a top-down binned SAH build over *build refs*, each a reference to an
//! object-BVH node. At every step, before partitioning a list, refs that are
//! large relative to the list (extent above `threshold` times the list's
//! extent) are *opened*: replaced by their children. Deeper levels open in
//! later steps, when the shrinking lists make the remaining refs large
//! relative to them. Refs name binary object-BVH nodes (the build, SAH and
//! statistics structure), but an opened ref yields the children of the
//! 8-wide node collapsed from its node (up to 8), so every top-level leaf
//! enters an object BVH at a node the SIMD traversal starts from.
//!
//! Memory: the ref array is allocated once with spare slots (Embree's sizing
//! by default). A list owns `list.len()` array slots, its refs first; after a
//! split the spare slots are divided in proportion to the two sides' ref
//! counts and the array is rearranged to `[left | left spare | right | right
//! spare]`. Top-level node slots follow the array: a list covering array
//! positions `b..e` owns node slots `2b+1 .. 2e-1` for its descendants, so the
//! recursion never allocates and the tree does not depend on the thread count.
//!
//! Departures from Embree's shipped builder, each a fix of a limitation
//! measured in `shared/docs/anchors.md`:
//! - opening is not all-or-nothing: when the marked refs do not all fit in the
//!   list's spare slots, the largest ones (by extent along the split axis) are
//!   opened, so a tight budget degrades gracefully instead of opening nothing;
//! - the pairwise-overlap test of short lists checks every pair;
//! - several opening rounds per step (`open_rounds`), and refs opened by their
//!   longest extent rather than their extent along the list's longest axis;
//! - refs weighted in the SAH by their subtree's expected cost rather than
//!   their primitive count;
//! - refs may carry an instance transform and be opened through it
//!   ([`RebraidParams::open_instances`]): the children's world boxes are their
//!   transformed object-space boxes (for leaves: the box of their transformed
//!   vertices);
//! - the pairwise-overlap termination test covers lists of up to 64 refs;
//! - after the build (`super::TopLevelAccel::new`) the entries left at small
//!   object subtrees are grafted into the top level
//!   ([`RebraidParams::graft_max_prims`]) and the object leaves it reaches
//!   through instances are copied into it in world space
//!   ([`RebraidParams::inline_instanced_leaves`]), so a re-braided ray
//!   rarely enters an object at all (Embree's two-level traversal enters an
//!   instance at every instance leaf);
//! - the binary top level is improved by reinsertion before it is laid out
//!   ([`RebraidParams::reinsert`], `crate::bvh::reinsert`): a top-down
//!   binned build over refs of very different sizes leaves subtrees that a
//!   search over the finished tree can place better.
//!
//! Tried and rejected (figures from `rebraid stats`, SAH cost, on the shared
//! scenes): an "SAH guard" that keeps an opening round only when the opened
//! list's best binned split is cheaper than the unopened list's. It looks one
//! step ahead only, and opening rarely pays within one step, so it undid the
//! useful openings too: nexuiz 110.9 (54.8 without), openarena 60.1 (28.8),
//! samurai 42.9 (30.5), cocoa temple 22.8 (18.9); it helped only on
//! 2CylinderEngine (100.1 against 105.8), where opening interpenetrating parts
//! hurts. Top-level leaves of up to 4 refs chosen by the SAH: nexuiz 56.1
//! against 54.8, no change elsewhere. (These figures predate opening by wide
//! nodes.)

use std::sync::atomic::{AtomicU64, Ordering};

use glam::Vec3A;
use rayon::prelude::*;

use super::{InstanceXf, LayoutBuffers, ObjectBvh, TopRef};
use crate::bvh::binning::{
    BinBox, BinMapping, BinRange, Bins, MAX_BINS, SplitCandidate, with_bins,
};
use crate::bvh::reinsert::{ReinsertParams, reinsert, reorder_depth_first};
use crate::bvh::wide::WIDE_EMPTY;
use crate::bvh::{Bvh, BvhNode, Collapse, MEDIAN_FROM_DEPTH, compact_slots, split_slots};
use crate::{Aabb, Error, INVALID_ID};

/// How many ref slots the build may use in all.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RefBudget {
    /// `max(min, per_initial_ref * initial refs, per_primitive * s *
    /// primitives)`, and never below the initial refs, with `s` the overlap
    /// scale below. Embree uses `(1000, 2.0, 0.001)` and no scale.
    ///
    /// `primitives` are those of the distinct objects the initial refs name:
    /// an object placed by many instances counts once. The budget bounds
    /// the top level's work relative to the object builds, which instancing
    /// does not multiply. Counting world primitives instead (each placement
    /// again) gave the cocoa temple (110,015 distinct triangles placed as
    /// 462,347) 13,871 slots, all used, and a top level of 9.4 ms beside
    /// 29 ms of object builds, for no ray speed: `rebraid bench
    /// stk_cocoa_temple.glb --modes rebraided --threads 1 --width 640
    /// --height 360 --reps 3`, world count (0.03 per primitive) against the
    /// distinct count (0.00714 per world primitive), twice alternating: top
    /// level 9.4 / 2.0-2.2 ms, primary 13.83-13.54 / 13.45-13.13 Mrays/s,
    /// shadow 10.35-10.20 / 10.52-10.29, diffuse 6.08-6.05 / 6.01-5.96. The
    /// same on 2CylinderEngine (top 2.8 / 1.9 ms; primary 5.47-6.00 /
    /// 6.17-6.23, shadow 9.04-9.21 / 9.27-9.36, diffuse 3.74-3.80 /
    /// 3.84-3.89) and stk_ravenbridge_mansion (top 4.7 / 2.4 ms; primary
    /// 6.09-6.04 / 6.05-6.06, shadow 7.63-7.66 / 7.77-7.69, diffuse
    /// 2.50-2.56 / 2.54-2.55).
    ///
    /// `overlap_unit` scales the primitive term with how much the placements
    /// overlap: it is multiplied by `max(1, overlap / overlap_unit)`, where
    /// `overlap` is the sum of the initial refs' box areas over the area of
    /// their union (about how many placement boxes cover a point; the
    /// "overlap" of `rebraid stats`). Opening pays where boxes of different
    /// objects overlap (the paper's motivation), and the more they overlap,
    /// the more refs it takes to separate them; where they hardly overlap
    /// more refs buy nothing but build time. 0 turns the scaling off (as
    /// Embree).
    ///
    /// The default, 0.03 per primitive and a unit of 15, scales only the
    /// two shared scenes whose placements overlap most: nexuiz (overlap
    /// 21.7: 0.0435 per primitive) and the library (24.9 at scale 3: 0.05).
    /// Measured (sessions 25 and 26, `docs/performance.md`): instructions
    /// per re-braided diffuse ray (callgrind) nexuiz 1,795.6 -> 1,714.8,
    /// library 1,141.5 -> about 1,015 (0.045-0.075 per primitive all gave
    /// 1,015-1,019); nexuiz shadow rays 952.7 -> 970.7. One thread, against
    /// `embree-flat` (session 26, the same binary with units 15 and 0):
    /// library diffuse 0.94 against 0.80, nexuiz 0.82 against 0.78. The
    /// top level's time grows with its refs (library: 155 -> 241 ms of
    /// about 1.05 s, one thread): session 25 turned the scaling off when
    /// the library's two-thread build fell to 0.92 of `embree-two-level`'s;
    /// with [`super::TopLevelAccel::new`] in parallel and its copied blocks
    /// on huge pages (session 26) it stands at 1.03 (one thread) and 1.29
    /// (two). Fixed budgets on the other scenes: 0.06 per primitive cut
    /// diffuse instructions by 2.5% on openarena, 1.1% on ravenbridge, 2.7%
    /// on cocoa, none on samurai or the engine; 0.2 cut them by 7-10% on
    /// the engine, cocoa and nexuiz for 3-5 times the top level's build
    /// time.
    Scaled {
        min: usize,
        per_initial_ref: f32,
        per_primitive: f32,
        overlap_unit: f32,
    },
    /// Exactly this many slots beyond the initial refs.
    Spare(usize),
}

impl RefBudget {
    /// Total capacity of the ref array for a build over `initial_refs` refs
    /// naming `primitives` distinct primitives, whose boxes overlap by
    /// `overlap` (see [`RefBudget::Scaled`]; [`placement_overlap`]).
    pub fn capacity(&self, initial_refs: usize, primitives: u64, overlap: f64) -> usize {
        match *self {
            RefBudget::Scaled {
                min,
                per_initial_ref,
                per_primitive,
                overlap_unit,
            } => {
                let scale = if overlap_unit > 0.0 && overlap.is_finite() {
                    (overlap / overlap_unit as f64).max(1.0)
                } else {
                    1.0
                };
                let a = (per_initial_ref as f64 * initial_refs as f64).ceil() as usize;
                let b = (per_primitive as f64 * scale * primitives as f64).ceil() as usize;
                min.max(a).max(b).max(initial_refs)
            }
            RefBudget::Spare(s) => initial_refs + s,
        }
    }
}

/// How much the refs' boxes overlap ([`Aabb::overlap_ratio`]).
pub fn placement_overlap(refs: &[BuildRef]) -> f64 {
    Aabb::overlap_ratio(refs.iter().map(|r| r.bounds))
}

/// Parameters of the top-level build.
#[derive(Clone, Debug, PartialEq)]
pub struct RebraidParams {
    /// Open object BVHs at all. `false` gives the plain two-level BVH.
    pub open: bool,
    /// Also open refs that carry an instance transform (Embree never does).
    pub open_instances: bool,
    /// A ref is opened when its extent along the list's longest axis exceeds
    /// this fraction of the list's extent (the paper's 10%).
    pub threshold: f32,
    pub budget: RefBudget,
    /// SAH bins per axis.
    pub bins: usize,
    /// Lists of at most this many refs are opened only when two of their
    /// refs overlap (Embree: 4). 64 keeps separated
    /// objects closed in the small lists where they look large (the `grid`
    /// scene: 1,081 nodes opened and 0.80x the primary-ray speed of the
    /// two-level tree with 4; none opened, equal speed with 64) and changed
    /// nothing measurable on the shared scenes or the library; at most 2,016
    /// box tests per list.
    pub short_list: usize,
    /// Open only refs whose box shares an area with a ref of another object
    /// or instance (the paper tests overlap for lists of at most
    /// `short_list` refs only). Off by default: large refs that overlap
    /// nothing still spoil a list's split. Measured with `rebraid stats`
    /// (SAH cost, off / on): grid of separated objects 41.20 / 41.19 (7,609
    /// refs opened / none, traversal speed equal within noise), nexuiz 54.76 /
    /// 54.21, samurai 30.55 / 30.08, cocoa temple 18.77 / 20.16, ravenbridge
    /// 32.24 / 33.58, 2CylinderEngine 105.35 / 106.56.
    pub open_only_overlapping: bool,
    /// Opening rounds per build step: after each round the list's bounds are
    /// recomputed and refs still above the threshold are opened again. The
    /// paper opens one level per step (1); more rounds let the split of a
    /// list see a decomposition of its large subtrees fine enough to
    /// separate them (measured: lower SAH cost and faster traversal).
    pub open_rounds: usize,
    /// Largest number of refs in one top-level leaf (1 as in Embree). More
    /// lets the SAH put small subtrees of different objects in one leaf, as
    /// a flat BVH puts their triangles; tried with 4 and rejected as the
    /// default: SAH cost 56.1 against 54.8 on nexuiz_ons_reborn (the leaf
    /// cost estimate from subtree costs is too optimistic), no change on
    /// the other shared scenes.
    pub max_leaf_refs: usize,
    /// After the top level is collapsed to 8 wide, fill each top-level
    /// node's empty slots with the child slots of the object nodes its refs
    /// enter (see [`super::TopLevelAccel::new`]): a ray then tests those
    /// children in the top-level node it is already testing, instead of
    /// entering the object to test its node.
    pub pull_entry_nodes: bool,
    /// Copy the triangle blocks of object leaves that top-level leaves enter
    /// directly into the top level, so that traversal tests them without
    /// entering the object (see [`super::TopLevelAccel::new`]).
    pub inline_leaf_blocks: bool,
    /// With `inline_leaf_blocks`, copy the leaves that top-level leaves
    /// enter through an instance too, their vertices transformed into
    /// world space (see [`super::TopLevelAccel::new`]): a ray then tests
    /// them as it tests a directly placed leaf's copy, without the entry,
    /// the instance ray and its set-up. One copy per placement of each
    /// such leaf (ravenbridge: 16.1 -> 16.5 MB in all). Measured (session
    /// 28, `rebraid stats SCENE --visits 240x135` and callgrind over the
    /// timed batch): ravenbridge's entries per re-braided diffuse ray 2.95
    /// -> 0.40 and its instructions per ray 1,855.0 -> 1,665.2; wall time
    /// (`tools/ab-wall.sh`, one thread, 480x270, 8 rounds, control beside)
    /// diffuse 1.113 (control 1.036), primary 1.218 (1.050), shadow 1.275
    /// (1.046); the engine and cocoa within their controls. Traced in world
    /// space, a copied leaf's triangles are no longer watertight against the
    /// same instance's triangles tested in object space through an entry
    /// (within the instance each side is); hits report the entry path's
    /// normal length (`TopLevelAccel::block_normal_scale`).
    pub inline_instanced_leaves: bool,
    /// Graft the object subtrees of at most this many primitives that
    /// top-level leaves enter into the top level as copies of the object's
    /// own nodes (0: none; see [`super::TopLevelAccel::new`]), so that a ray
    /// reaching them walks on in the top level instead of entering.
    /// Ignored when `open` is off (the plain two-level mode stays plain).
    ///
    /// Measured (session 28, callgrind over the timed batch, instructions
    /// per re-braided diffuse ray at 0 / 16 / 32 / 64 / 256 / 1,024):
    /// nexuiz 1,718.9 / 1,702.9 / 1,687.6 / 1,658.3 / 1,641.8 / 1,638.9,
    /// the engine 1,331.9 / 1,330.3 / 1,319.8 / 1,295.0 / 1,243.0 / 1,212.5,
    /// cocoa 666.5 / 664.8 / 658.8 / 646.9 / 619.9 / 614.5; ravenbridge,
    /// samurai and openarena 0.4-0.8% at 64. The top level's time grows
    /// with the copies (one thread, `rebraid bench SCENE --modes rebraided
    /// --sets primary --reps 9 --graft-max-prims G`): at 64 by 0.3-1.6 ms,
    /// at 256 by 2-9 ms (of builds of 13-40 ms), which the build column
    /// against Embree cannot carry without a limit. On the library at
    /// scale 3 (3M triangles, most entries small) grafting every entry of
    /// up to 64 primitives copied 116 MB and took 90-100 ms, hence
    /// [`RebraidParams::graft_budget`] and, since session 29,
    /// [`RebraidParams::graft_share_per_prim`] (off by default), which
    /// wants a size of 512: the engine's dense entries lie in subtrees of
    /// 65-512 primitives.
    pub graft_max_prims: u32,
    /// How many primitives the grafts may copy in all, per primitive of
    /// the distinct objects (each object counted once): the entries a ray
    /// is likeliest to reach per primitive copied (slot area over subtree
    /// primitives) are grafted first. 0 grafts nothing.
    ///
    /// Measured (session 28, instructions per re-braided diffuse ray,
    /// callgrind, at budgets 0.05 / 0.1 / 0.25 and unlimited, sizes up to
    /// 64): nexuiz 1,692.5 / 1,683.6 / 1,658.4 / 1,658.4 (none: 1,718.9),
    /// the engine 1,315.0 / 1,308.7 / 1,295.1 / 1,295.1 (1,331.9), cocoa
    /// 651.7 / 648.7 / 647.0 / 647.0 (666.5); the library's copies 9.8 /
    /// 19.1 / 47.3 / 116 MB. The default, 0.1.
    pub graft_budget: f32,
    /// Entries whose top-level slot box has at least this share of the
    /// top level's root box area per primitive under the entry are grafted
    /// past [`RebraidParams::graft_budget`], up to the distinct primitives
    /// in all; 0 (the default) turns it off. At 1e-5 a 512-primitive
    /// subtree qualifies when its slot covers 0.5% of the scene box's area.
    ///
    /// Why: the budget is a share of the primitives, the same for every
    /// scene, while what a graft saves is the entries rays make, which is
    /// the slot's share of the scene's area (the chance that a ray through
    /// the scene box enters it). Entries that many rays make are worth
    /// copying whatever the budget. Their copies cost about 40 ns of build
    /// time per primitive on this machine (the engine's, one thread) and
    /// each entry they spare a ray about 100 instructions (some 35 ns), so
    /// at 1e-5 a graft pays for itself after about 40 / (1e-5 * 35), some
    /// 100,000 rays through the scene box: a tenth of one 1280x720
    /// frame's primary rays.
    ///
    /// Measured (session 29, callgrind over the timed batch, instructions
    /// per re-braided ray, diffuse and shadow, the defaults against 1e-5
    /// with a graft size of 512): the 2CylinderEngine 1,308.7 -> 1,213.0
    /// (-7.3%) and 791.0 -> 781.6, nexuiz 1,683.5 -> 1,649.8 (-2.0%) and
    /// 974.5 -> 971.2, openarena 859.6 -> 851.2, cocoa 648.7 -> 643.5,
    /// ravenbridge and samurai within 0.2%; build instructions (callgrind
    /// over `Scene::commit`, one thread) the engine +11.9%, openarena
    /// +2.2%, nexuiz +1.6%, ravenbridge +0.9%, cocoa +0.7%, samurai +0.2%
    /// (after 5-5.4% less from checking the object builds' inputs in their
    /// bounds pass, the same session). At 5e-6 cocoa and ravenbridge would
    /// gain 1.5-2% more for 4-5% more build everywhere.
    ///
    /// Why it is off: the instructions saved did not come out as time.
    /// The engine's diffuse rays in wall time (`tools/ab-wall.sh 6`, one
    /// thread, 480x270, the defaults as control) 1.013 against a control
    /// of 0.983, its first-level and last-level cache misses per ray the
    /// same (callgrind's model); in the sixteenth run of the figure, with
    /// it on, the engine's diffuse rays over `embree-flat` 0.97 (0.96 in
    /// the fifteenth, without) and its build over `embree-two-level` 1.05
    /// at one thread and 0.95 at two (the grafts run on one thread). For a
    /// scene traced with many rays per build and built on one thread it
    /// may still pay: `--graft-max-prims 512 --graft-share-per-prim 1e-5`.
    pub graft_share_per_prim: f32,
    /// Graft a scene's merged BVH (see
    /// [`crate::scene::SceneParams::merge_placed`]) of at most this many
    /// triangles whole into the top level, whatever `graft_max_prims` and
    /// `graft_budget` say (0: never): it stands for the many objects
    /// re-braiding would have opened, and its entries cost what theirs did.
    /// The price is a copy of its nodes and blocks, which pays on nexuiz
    /// (125,101 triangles merged: wall time 1.05 over the merged BVH behind
    /// entries, for 4-7 ms of build and 15.1 -> 23.7 MB) and not on the
    /// library at scale 1 (1M triangles: no measurable difference, for 74
    /// ms of build and 150 -> 199 MB); docs/performance.md, session 30.
    /// Default 2^18. A merged BVH that is the whole scene is walked alone
    /// ([`super::TopLevelAccel::direct`]) and never grafted.
    pub graft_merged_max_prims: u32,
    /// Lists longer than this are opened, binned and partitioned with
    /// data-parallel loops, and their halves built as parallel tasks.
    pub parallel_threshold: usize,
    /// Trace an object that exactly one instance places (and that is not
    /// placed itself) from a BVH over its transformed, world-space
    /// vertices, as a directly placed object, while that instance has
    /// never moved (see [`crate::Scene::commit`]). Scene formats place
    /// every mesh through a node (glTF), so most such "instances" are
    /// plain placements; traced directly they need no instance ray and
    /// their leaves can be copied into the top level. Measured (session
    /// 8, paired A/B, the loader baking them instead): re-braided
    /// 2CylinderEngine +11% / +29% / +9% (primary / shadow / diffuse),
    /// cocoa temple +6% / +9% / +5%, ravenbridge +5% / -1% / +6%.
    pub bake_single_instances: bool,
    /// Re-braided scenes: a placement that moved (an instance's transform,
    /// an object's vertices or mesh, after a commit took it in) is traced
    /// for this many commits, the one after its move included, from a
    /// second top level over the placements that moved, built at every
    /// commit, while the top level over the others is kept from the commit
    /// that last changed which placements move (see
    /// [`crate::scene::SplitAccel`]). 0: one top level over everything,
    /// rebuilt at every commit.
    ///
    /// A placement that stops moving joins the kept top level this many
    /// commits later (which rebuilds it), so an object moved now and then
    /// does not rebuild it at every move; one that starts moving rebuilds
    /// it once. Default 8.
    pub moving_hold_commits: u32,
    /// Split only while the moving placements' world triangles are at most
    /// this share of the others' (see `moving_hold_commits`). A ray that
    /// reaches the moving part's box walks both top levels, and walks the
    /// fixed one past a moving hit it would have stopped at; a moving part
    /// as large as the rest is reached by many rays, while the top level
    /// it saves rebuilding is small. `rebraid animate` with its 200K-
    /// triangle robot, two threads, medians of three alternations, split
    /// against one top level (session 35): the library at 2M and 3M
    /// triangles update 94.8 -> 13.5 and 127.1 -> 13.7 ms per frame,
    /// primary rays 1.03 and 0.90, diffuse 0.98 and 1.05; the cocoa
    /// temple (462K world triangles) 19.3 -> 11.1 ms, primary 0.75,
    /// diffuse 0.94; nexuiz (125K) 21.4 -> 14.7 ms, primary 0.83, diffuse
    /// 0.97. Default 0.25: the library splits, those two do not.
    pub moving_split_max_share: f32,
    /// Reinsertion over the top level's binary tree after its build
    /// ([`crate::bvh::reinsert`]; Bittner et al. 2013, Meister and Bittner
    /// 2018): subtrees the top-down binned build left in poor places (the
    /// greedy splits, refs opened deep in a list) move to where the summed
    /// area of the inner nodes is lowest. Ignored when `open` is off (the
    /// plain two-level mode stays plain). Default 0.3 x 3 passes, at most
    /// 4,096 nodes per pass.
    ///
    /// Measured (session 36). Embree's statistic of the traversed wide
    /// layout (`rebraid stats`), none / 0.1 x 4 / 0.3 x 3 / 1 x 16: nexuiz
    /// 18.65 / 17.89 / 17.83 / 17.16, samurai 11.26 / 11.04 / 10.71 /
    /// 10.38, the cocoa temple 6.26 / 6.01 / 6.02 / 5.95; the searches on
    /// one thread take 1.6 / 3.1 / 52 ms on nexuiz (10,731 top-level
    /// nodes), and 0.1 x 4 uncapped took 67 ms of the library's (3M
    /// triangles, 295,089 nodes) 215 ms top level, hence the cap. Wall
    /// time, default against none (`tools/ab-wall.sh 5`, one thread,
    /// 480x270, the control 0.98-1.03): diffuse rays +1.7% to +6.4% on the
    /// six shared scenes and +16% on the library at 0.25, primary +0.4%
    /// to +4.3% and +20%, shadow +2.7% to +14% but ravenbridge (0.995)
    /// and the library, **0.64**: all its shadow rays are occluded and the
    /// unmoved tree finds the occluder in the first leaf (1.00 leaves per
    /// ray), the reinserted one after 1.34 (`rebraid stats library
    /// --visits 240x135`); moving leaves only keeps that and loses the
    /// rest, moving nothing within four levels of the root or no move onto
    /// a large leaf changes neither. 0.1 x 4 cost nexuiz's primary rays 5%.
    pub reinsert: ReinsertParams,
    /// How the top level's binary tree becomes the 8-wide one traversal
    /// walks ([`crate::bvh::collapse`]); by default the SAH-optimal choice
    /// of wide nodes, as for the objects ([`crate::bvh::BuildParams::collapse`]).
    pub collapse: Collapse,
}

impl Default for RebraidParams {
    fn default() -> Self {
        Self {
            open: true,
            open_instances: true,
            threshold: 0.1,
            budget: RefBudget::Scaled {
                min: 1000,
                per_initial_ref: 2.0,
                per_primitive: 0.03,
                overlap_unit: 15.0,
            },
            bins: 32,
            short_list: 64,
            max_leaf_refs: 1,
            open_rounds: 4,
            open_only_overlapping: false,
            pull_entry_nodes: true,
            inline_leaf_blocks: true,
            inline_instanced_leaves: true,
            graft_max_prims: 64,
            graft_budget: 0.1,
            graft_share_per_prim: 0.0,
            graft_merged_max_prims: 1 << 18,
            parallel_threshold: 1024,
            bake_single_instances: true,
            moving_hold_commits: 8,
            moving_split_max_share: 0.25,
            reinsert: ReinsertParams {
                batch_ratio: 0.3,
                passes: 3,
                max_batch: 4096,
            },
            collapse: Collapse::default(),
        }
    }
}

impl RebraidParams {
    /// The plain two-level BVH: no opening.
    pub fn two_level() -> Self {
        Self {
            open: false,
            ..Self::default()
        }
    }

    pub fn check(&self) -> Result<(), Error> {
        if !(2..=MAX_BINS).contains(&self.bins) {
            return Err(Error::InvalidParameter(format!(
                "bins must be in 2..={MAX_BINS}"
            )));
        }
        self.reinsert.check()?;
        if self.max_leaf_refs == 0 {
            return Err(Error::InvalidParameter(
                "max_leaf_refs must be at least 1".into(),
            ));
        }
        if !(self.threshold >= 0.0 && self.threshold.is_finite()) {
            return Err(Error::InvalidParameter(
                "threshold must be finite and >= 0".into(),
            ));
        }
        if !(self.graft_budget >= 0.0 && self.graft_budget.is_finite()) {
            return Err(Error::InvalidParameter(
                "graft_budget must be finite and >= 0".into(),
            ));
        }
        if self.moving_split_max_share.is_nan() || self.moving_split_max_share < 0.0 {
            return Err(Error::InvalidParameter(
                "moving_split_max_share must be >= 0".into(),
            ));
        }
        if !(self.graft_share_per_prim >= 0.0 && self.graft_share_per_prim.is_finite()) {
            return Err(Error::InvalidParameter(
                "graft_share_per_prim must be finite and >= 0".into(),
            ));
        }
        if let RefBudget::Scaled {
            per_initial_ref,
            per_primitive,
            overlap_unit,
            ..
        } = self.budget
            && !(per_initial_ref >= 0.0 && per_primitive >= 0.0 && overlap_unit >= 0.0)
        {
            return Err(Error::InvalidParameter(
                "budget factors must be >= 0".into(),
            ));
        }
        Ok(())
    }
}

/// A reference to an object-BVH node during the top-level build.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct BuildRef {
    /// World-space bounds of the node (transformed for instances).
    pub bounds: Aabb,
    pub object: u32,
    pub node: u32,
    /// Instance id, or [`INVALID_ID`] for an object placed directly.
    pub instance: u32,
    /// Primitives under the node.
    pub prims: u32,
    /// Expected cost of the node's subtree for a ray entering its box
    /// ([`ObjectBvh::subtree_cost`]): the ref's SAH weight.
    pub cost: f32,
}

const _: () = assert!(std::mem::size_of::<BuildRef>() == 44);

impl BuildRef {
    /// The SAH weight as the bins' integer (sixteenths of a cost unit).
    #[inline]
    fn weight(&self) -> u64 {
        // `+ 0.5` and truncation: `round` is a libm call on baseline x86-64
        // (no SSE4.1), once per ref per binning pass. Through `i64`: one
        // instruction, where `f32 as u64` is a branchy sequence (the same
        // value below 2^63; costs are far smaller).
        ((self.cost * 16.0 + 0.5) as i64).max(1) as u64
    }
}

/// What a top-level build did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TopLevelBuildStats {
    pub refs_initial: usize,
    pub refs_final: usize,
    /// Object-BVH nodes replaced by their children.
    pub nodes_opened: usize,
    /// Spare ref slots used: `refs_final - refs_initial` (an opened node
    /// takes one slot per child but the first; up to 7 with wide nodes).
    pub spare_used: usize,
    /// Size of the ref array (initial refs plus spare slots).
    pub capacity: usize,
    /// [`placement_overlap`] of the initial refs, which may scale the
    /// budget.
    pub overlap: f64,
    pub top_nodes: usize,
    /// The binned build with its opening, the reinsertion included.
    pub build_ms: f64,
    /// Of `build_ms`, the reinsertion (`RebraidParams::reinsert`) and the
    /// depth-first relayout after it.
    pub reinsert_ms: f64,
    /// The layout pass after the build (`TopLevelAccel::new`), by phase.
    pub layout: LayoutTimes,
}

/// Where the top level's layout pass (`TopLevelAccel::new`) spent its
/// time, in milliseconds: what, besides the build itself, the re-braided
/// top level costs (`rebraid stats` prints it). Measured with a clock
/// around each phase; the phases run one after the other.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LayoutTimes {
    /// The SAH-optimal (or greedy) collapse into 8-wide nodes.
    pub collapse_ms: f64,
    /// Entry records, and object wide nodes pulled into free slots.
    pub entries_ms: f64,
    /// Small object subtrees grafted into the top level.
    pub graft_ms: f64,
    /// The occlusion order of every node's slots.
    pub order_ms: f64,
    /// Object leaf blocks copied into the top level, and their placements.
    pub copy_ms: f64,
}

impl LayoutTimes {
    pub fn total_ms(&self) -> f64 {
        self.collapse_ms + self.entries_ms + self.graft_ms + self.order_ms + self.copy_ms
    }
}

/// Object BVHs and instance transforms the refs point into.
#[derive(Clone, Copy)]
pub struct RefSources<'a> {
    pub objects: &'a [Option<std::sync::Arc<ObjectBvh>>],
    pub instances: &'a [InstanceXf],
}

struct Ctx<'a> {
    src: RefSources<'a>,
    params: &'a RebraidParams,
    opened: AtomicU64,
}

/// Chunk length of data-parallel loops (a constant: thread-count independence).
const CHUNK: usize = 512;

/// Build the top level over `initial` refs (each an object-BVH node, usually
/// a root). Returns the tree (leaves of exactly one ref, indexing the returned
/// refs) and statistics.
pub fn build_top_level(
    initial: &[BuildRef],
    src: RefSources,
    params: &RebraidParams,
) -> Result<(Bvh, Vec<TopRef>, TopLevelBuildStats), Error> {
    build_top_level_with(initial, src, params, &mut TopLevelScratch::default())
}

/// The large buffers of a top-level build, kept between builds so that a
/// scene committed every frame does not allocate (nor page in) them anew:
/// the ref array with its spare slots, the partition scratch, the node slots,
/// and the previous build's output node and ref arrays handed back by
/// [`TopLevelScratch::recycle`].
///
/// The buffers only grow; [`TopLevelScratch::bytes`] tells how much they hold
/// and [`TopLevelScratch::clear`] frees them.
#[derive(Clone, Debug, Default)]
pub struct TopLevelScratch {
    refs: Vec<BuildRef>,
    scratch: Vec<BuildRef>,
    slots: Vec<BvhNode>,
    nodes: Vec<BvhNode>,
    out_refs: Vec<TopRef>,
    /// The previous top level's layout arrays (its collapsed nodes,
    /// entries, copied leaf blocks), for the next one's.
    layout: LayoutBuffers,
}

impl TopLevelScratch {
    /// Hand back the node and ref arrays of a previous build's output for
    /// the next one.
    pub fn recycle(&mut self, nodes: Vec<BvhNode>, refs: Vec<TopRef>) {
        if nodes.capacity() > self.nodes.capacity() {
            self.nodes = nodes;
        }
        if refs.capacity() > self.out_refs.capacity() {
            self.out_refs = refs;
        }
    }

    /// Hand back a previous top level's layout arrays
    /// ([`super::TopLevelAccel::take_layout_buffers`]); of two handed back
    /// (a split scene's), the larger are kept.
    pub fn recycle_layout(&mut self, layout: LayoutBuffers) {
        if layout.bytes() > self.layout.bytes() {
            self.layout = layout;
        }
    }

    /// The layout arrays for the next top level (the scratch keeps none
    /// until some are handed back).
    pub fn take_layout(&mut self) -> LayoutBuffers {
        std::mem::take(&mut self.layout)
    }

    /// Bytes held by the buffers.
    pub fn bytes(&self) -> usize {
        use std::mem::size_of;
        (self.refs.capacity() + self.scratch.capacity()) * size_of::<BuildRef>()
            + (self.slots.capacity() + self.nodes.capacity()) * size_of::<BvhNode>()
            + self.out_refs.capacity() * size_of::<TopRef>()
            + self.layout.bytes()
    }

    /// Free every buffer.
    pub fn clear(&mut self) {
        *self = Self::default();
    }
}

/// `buf[..len]`, growing `buf` with `fill` only when it is too short. The
/// stale contents of a reused buffer are never read: the builder writes
/// every ref, scratch entry and node slot before reading it.
fn reuse<T: Copy>(buf: &mut Vec<T>, len: usize, fill: T) -> &mut [T] {
    if buf.len() < len {
        buf.resize(len, fill);
    }
    &mut buf[..len]
}

/// [`build_top_level`] with buffers reused from earlier builds.
pub fn build_top_level_with(
    initial: &[BuildRef],
    src: RefSources,
    params: &RebraidParams,
    buffers: &mut TopLevelScratch,
) -> Result<(Bvh, Vec<TopRef>, TopLevelBuildStats), Error> {
    params.check()?;
    let start = std::time::Instant::now();
    let n = initial.len();
    for (i, r) in initial.iter().enumerate() {
        let ok = src
            .objects
            .get(r.object as usize)
            .and_then(|o| o.as_deref())
            .is_some_and(|o| (r.node as usize) < o.nodes().len())
            && (r.instance == INVALID_ID || (r.instance as usize) < src.instances.len())
            && r.bounds.is_finite()
            && !r.bounds.is_empty();
        if !ok {
            return Err(Error::InvalidBounds { index: i });
        }
    }
    if n == 0 {
        return Ok((Bvh::default(), Vec::new(), TopLevelBuildStats::default()));
    }
    let prims = distinct_object_prims(initial, &src);
    let overlap = placement_overlap(initial);
    let capacity = if params.open {
        params.budget.capacity(n, prims, overlap)
    } else {
        n
    };
    if capacity >= (1usize << 31) {
        return Err(Error::TooManyPrimitives(capacity));
    }
    // The only buffers of the build: ref array, scratch, node slots (reused
    // from earlier builds when `buffers` holds them).
    let refs = reuse(&mut buffers.refs, capacity, initial[0]);
    refs[..n].copy_from_slice(initial);
    let scratch = reuse(&mut buffers.scratch, capacity, initial[0]);
    let slots = reuse(
        &mut buffers.slots,
        2 * capacity - 1,
        bytemuck::Zeroable::zeroed(),
    );
    let ctx = Ctx {
        src,
        params,
        opened: AtomicU64::new(0),
    };
    let (root, desc) = slots.split_at_mut(1);
    root[0] = build_list(&ctx, refs, scratch, n, desc, 1, 0, 1);

    // Compact the slots into depth-first order, refs into leaf order.
    let mut out_refs: Vec<TopRef> = std::mem::take(&mut buffers.out_refs);
    out_refs.clear();
    out_refs.reserve(capacity);
    let mut nodes = std::mem::take(&mut buffers.nodes);
    compact_slots(slots, &mut nodes, |leaf| {
        let first = out_refs.len() as u32;
        out_refs.extend(refs[leaf.prim_range()].iter().map(|r| TopRef {
            object: r.object,
            node: r.node,
            instance: r.instance,
            prims: r.prims,
        }));
        leaf.index = first;
    });
    let reinsert_start = std::time::Instant::now();
    if params.open && reinsert(&mut nodes, &params.reinsert) {
        // Depth-first again, the refs in the new leaf order.
        let map = reorder_depth_first(&mut nodes);
        let old = out_refs.clone();
        for (r, &m) in out_refs.iter_mut().zip(&map) {
            *r = old[m as usize];
        }
    }
    let reinsert_ms = reinsert_start.elapsed().as_secs_f64() * 1e3;
    let stats = TopLevelBuildStats {
        refs_initial: n,
        refs_final: out_refs.len(),
        spare_used: out_refs.len() - n,
        nodes_opened: ctx.opened.load(Ordering::Relaxed) as usize,
        capacity,
        overlap,
        top_nodes: nodes.len(),
        build_ms: start.elapsed().as_secs_f64() * 1e3,
        reinsert_ms,
        layout: LayoutTimes::default(),
    };
    let tree = Bvh {
        nodes,
        prim_indices: Vec::new(),
    };
    Ok((tree, out_refs, stats))
}

/// Primitives of the distinct objects `refs` name, each object counted once
/// however many refs (instances, subtrees) name it (see [`RefBudget`]).
fn distinct_object_prims(refs: &[BuildRef], src: &RefSources) -> u64 {
    let mut seen = vec![false; src.objects.len()];
    let mut prims = 0u64;
    for r in refs {
        let Some(o) = src
            .objects
            .get(r.object as usize)
            .and_then(|o| o.as_deref())
        else {
            continue;
        };
        if !std::mem::replace(&mut seen[r.object as usize], true) {
            prims += o.mesh.triangles.len() as u64;
        }
    }
    prims
}

/// The bounds of a list's refs and of their centres, folded in four-lane
/// vectors ([`BinBox`]): with the scalar `Aabb`
/// operations this was 16% of the top-level build's instructions
/// (callgrind, nexuiz). Same values: minima, maxima and centres are exact.
fn list_bounds(list: &[BuildRef], parallel: bool) -> (Aabb, Aabb) {
    let empty = (BinBox::EMPTY, BinBox::EMPTY);
    let fold = |(b, c): (BinBox, BinBox), r: &BuildRef| {
        let rb = BinBox::from_aabb(&r.bounds);
        (b.union(rb), c.grow(rb.center()))
    };
    let (b, c) = if parallel {
        list.par_chunks(CHUNK)
            .map(|ch| ch.iter().fold(empty, fold))
            .reduce(|| empty, |(a, b), (c, d)| (a.union(c), b.union(d)))
    } else {
        list.iter().fold(empty, fold)
    };
    (b.to_aabb(), c.to_aabb())
}

/// Does this list still benefit from opening? (The paper's termination rules.)
fn may_open(ctx: &Ctx, list: &[BuildRef], spare: usize) -> bool {
    if spare == 0 {
        return false;
    }
    let first = (list[0].object, list[0].instance);
    if list.iter().all(|r| (r.object, r.instance) == first) {
        return false;
    }
    if list.len() <= ctx.params.short_list {
        // Open only if some pair shares an area or volume (touching at an
        // edge or corner is no overlap).
        for i in 0..list.len() {
            for j in i + 1..list.len() {
                if share_area(&list[i].bounds, &list[j].bounds) {
                    return true;
                }
            }
        }
        return false;
    }
    true
}

#[inline]
fn openable(ctx: &Ctx, r: &BuildRef) -> bool {
    if r.instance != INVALID_ID && !ctx.params.open_instances {
        return false;
    }
    ctx.src.objects[r.object as usize]
        .as_deref()
        .is_some_and(|o| !o.nodes()[r.node as usize].is_leaf())
}

#[inline]
fn is_object_leaf(ctx: &Ctx, r: &BuildRef) -> bool {
    ctx.src.objects[r.object as usize]
        .as_deref()
        .is_some_and(|o| o.nodes()[r.node as usize].is_leaf())
}

/// Child nodes (binary node ids) of an opened ref: the slots of the wide
/// node collapsed from its node when the object has the wide layout or its
/// collapse pending (up to 8: the top level then reaches exactly the nodes
/// traversal starts from), else the binary node's two children. Returns
/// the ids and their count.
#[inline]
fn child_nodes(ctx: &Ctx, r: &BuildRef) -> ([u32; 8], usize) {
    let obj = ctx.src.objects[r.object as usize]
        .as_deref()
        .expect("validated");
    let mut ids = [0u32; 8];
    if let Some(slots) = obj.wide_node(r.node).and_then(|w| obj.wide_slots(w)) {
        let mut k = 0;
        for &b in slots.iter().take_while(|&&b| b != WIDE_EMPTY) {
            ids[k] = b;
            k += 1;
        }
        // In binary node order, not the slots' (which the occlusion order
        // sets, and which a pending layout does not have yet): the same
        // refs in the same order whether the object was built in this
        // commit or an earlier one.
        ids[..k].sort_unstable();
        return (ids, k);
    }
    let c = obj.nodes()[r.node as usize].index;
    ids[0] = c;
    ids[1] = c + 1;
    (ids, 2)
}

/// The ref of child node `i` of an opened ref `r`.
#[inline]
fn child_ref(ctx: &Ctx, r: &BuildRef, i: u32) -> BuildRef {
    let obj = ctx.src.objects[r.object as usize]
        .as_deref()
        .expect("validated");
    let xf = (r.instance != INVALID_ID).then(|| &ctx.src.instances[r.instance as usize]);
    BuildRef {
        bounds: placed_bounds(obj, xf, i, obj.nodes()[i as usize].bounds(), &r.bounds),
        object: r.object,
        node: i,
        instance: r.instance,
        prims: obj.subtree_prims[i as usize],
        cost: obj.subtree_cost[i as usize],
    }
}

/// World box of binary node `node` of `obj`, whose object-space box is
/// `local`, placed by `xf` (directly when `None`) as a child of a ref whose
/// world box is `parent`.
///
/// An instanced leaf's world box is that of its transformed vertices (a
/// handful): much tighter than the transformed local box under rotation.
/// Inner nodes get the transformed local box. Both are clipped to the
/// parent's world box, which holds them up to rounding, so that the
/// top-level nodes nest exactly.
pub(crate) fn placed_bounds(
    obj: &ObjectBvh,
    xf: Option<&InstanceXf>,
    node: u32,
    local: Aabb,
    parent: &Aabb,
) -> Aabb {
    let Some(xf) = xf else { return local };
    let node = &obj.nodes()[node as usize];
    if node.is_leaf() {
        obj.mesh.triangles[node.prim_range()]
            .iter()
            .flatten()
            .fold(Aabb::EMPTY, |b, v| {
                b.grow(xf.object_to_world.transform_point3(*v))
            })
            .intersection(*parent)
    } else {
        xf.world_box(&local).intersection(*parent)
    }
}

/// Spare slots opening `r` takes: its children but one (which takes its place).
#[inline]
fn extra_refs(ctx: &Ctx, r: &BuildRef) -> usize {
    child_nodes(ctx, r).1 - 1
}

/// Replace every ref of `head` by its first child and write the other
/// children, in order, to `tail` (exactly as long as they need). Halves
/// `head` recursively in parallel when it is long; allocation-free.
fn open_all(ctx: &Ctx, head: &mut [BuildRef], tail: &mut [BuildRef]) {
    if head.len() <= ctx.params.parallel_threshold.max(64) {
        let mut cursor = 0;
        for r in head.iter_mut() {
            let (ids, k) = child_nodes(ctx, r);
            let parent = *r;
            *r = child_ref(ctx, &parent, ids[0]);
            for &i in &ids[1..k] {
                tail[cursor] = child_ref(ctx, &parent, i);
                cursor += 1;
            }
        }
        return;
    }
    let mid = head.len() / 2;
    let extra: usize = head[..mid].iter().map(|r| extra_refs(ctx, r)).sum();
    let (h1, h2) = head.split_at_mut(mid);
    let (t1, t2) = tail.split_at_mut(extra);
    rayon::join(|| open_all(ctx, h1, t1), || open_all(ctx, h2, t2));
}

/// Move the refs for which `pred` holds to the front; returns their count.
///
/// Scans from both ends and swaps only misplaced pairs. The one-sided form
/// (swap every "no" with the end, then test the slot again) rewrote and
/// re-read the same 44-byte ref on each step, a store-forwarding stall per
/// ref and the hottest instructions of the builder's own loop: the cocoa
/// temple's re-braided top level took 9.8-11.4 ms with it, 8.4-9.1 ms
/// without (`rebraid bench stk_cocoa_temple.glb --modes rebraided`,
/// alternating the binaries).
fn partition_in_place(list: &mut [BuildRef], pred: impl Fn(&BuildRef) -> bool) -> usize {
    let (mut i, mut j) = (0, list.len());
    loop {
        while i < j && pred(&list[i]) {
            i += 1;
        }
        while i < j && !pred(&list[j - 1]) {
            j -= 1;
        }
        if j - i < 2 {
            return i;
        }
        list.swap(i, j - 1);
        i += 1;
        j -= 1;
    }
}

/// True when two boxes share an area or volume (touching at an edge or a
/// corner is no overlap).
#[inline]
fn share_area(a: &Aabb, b: &Aabb) -> bool {
    let i = a.intersection(*b);
    !i.is_empty() && i.half_area() > 0.0
}

/// True when `list[i]`'s box shares an area or volume with the box of a ref
/// of another object or instance.
fn overlaps_another_placement(list: &[BuildRef], i: usize) -> bool {
    let r = &list[i];
    list.iter().any(|o| {
        (o.object, o.instance) != (r.object, r.instance) && share_area(&r.bounds, &o.bounds)
    })
}

/// Open the refs of `list[..n]` that are large relative to `bounds`, writing
/// new refs into the spare slots `list[n..]`. Returns the new ref count.
fn open_refs(ctx: &Ctx, list: &mut [BuildRef], n: usize, bounds: &Aabb) -> usize {
    let axis = bounds.largest_axis();
    let limit = ctx.params.threshold * bounds.extent()[axis];
    // The paper compares extents along the list's longest axis only, which
    // never opens a planar subtree lying across that axis (a floor in a tall
    // list); comparing the ref's longest extent fixes that (measured: lower
    // SAH cost on all three shared OBJ scenes).
    let marked = |r: &BuildRef| r.bounds.extent().max_element() > limit && openable(ctx, r);
    // Marked refs to the front.
    let m = partition_in_place(&mut list[..n], marked);
    // Optionally keep only those that overlap a ref of another placement
    // (see `RebraidParams::open_only_overlapping`).
    let m = if ctx.params.open_only_overlapping {
        let (mut kept, mut j) = (0, m);
        while kept < j {
            if overlaps_another_placement(&list[..n], kept) {
                kept += 1;
            } else {
                j -= 1;
                list.swap(kept, j);
            }
        }
        kept
    } else {
        m
    };
    let spare = list.len() - n;
    let mut extra: usize = list[..m].iter().map(|r| extra_refs(ctx, r)).sum();
    let mut k = m;
    if extra > spare {
        // Not all fit: open the largest that do, in order of size.
        list[..m]
            .sort_unstable_by(|a, b| b.bounds.extent()[axis].total_cmp(&a.bounds.extent()[axis]));
        (k, extra) = (0, 0);
        while k < m {
            let e = extra_refs(ctx, &list[k]);
            if extra + e > spare {
                break;
            }
            extra += e;
            k += 1;
        }
    }
    if k == 0 {
        return n;
    }
    let (head, tail) = list.split_at_mut(n);
    open_all(ctx, &mut head[..k], &mut tail[..extra]);
    ctx.opened.fetch_add(k as u64, Ordering::Relaxed);
    n + extra
}

/// Bins a list of refs by their SAH weights (in parallel chunks when long).
struct ListBinner<'a> {
    list: &'a [BuildRef],
    parallel: bool,
}

impl BinRange for ListBinner<'_> {
    fn run<const N: usize>(&self, map: &BinMapping) -> Option<SplitCandidate> {
        let item = |r: &BuildRef| {
            (
                BinBox::from_aabb(&r.bounds),
                Vec3A::from(r.bounds.center()),
                r.weight(),
            )
        };
        let bin_chunk = |chunk: &[BuildRef]| {
            let mut bins = Bins::<N>::default();
            bins.fill(map, chunk.iter().map(item));
            bins
        };
        if self.parallel {
            // Reduced in place (no buffer of partial bins): merges are exact,
            // so the result does not depend on how rayon pairs the chunks.
            self.list
                .par_chunks(CHUNK * 4)
                .map(bin_chunk)
                .reduce(Bins::<N>::default, |mut a, b| {
                    a.merge(&b, map.bins);
                    a
                })
                .best_split(map)
        } else {
            // Filled in place (a returned `Bins` would be copied).
            let mut bins = Bins::<N>::default();
            bins.fill(map, self.list.iter().map(item));
            bins.best_split(map)
        }
    }
}

/// Partition `list` so that refs for which `is_left` holds come first;
/// stable through `scratch` when parallel. Returns the left count. Does not
/// allocate: the parallel path halves the list recursively (`rayon::join`),
/// counting each left half to place both halves' outputs.
fn partition_refs<F>(
    list: &mut [BuildRef],
    scratch: &mut [BuildRef],
    parallel: bool,
    is_left: F,
) -> usize
where
    F: Fn(&BuildRef) -> bool + Sync,
{
    if !parallel {
        return partition_in_place(list, is_left);
    }
    let n = list.len();
    let left = count_left(list, &is_left);
    let (lo, hi) = scratch[..n].split_at_mut(left);
    scatter(list, lo, hi, &is_left);
    list.par_chunks_mut(CHUNK * 4)
        .zip(scratch[..n].par_chunks(CHUNK * 4))
        .for_each(|(d, s)| d.copy_from_slice(s));
    left
}

/// Number of refs of `list` for which `is_left` holds (parallel by halving).
fn count_left<F: Fn(&BuildRef) -> bool + Sync>(list: &[BuildRef], is_left: &F) -> usize {
    if list.len() <= 4 * CHUNK {
        return list.iter().filter(|r| is_left(r)).count();
    }
    let (a, b) = list.split_at(list.len() / 2);
    let (x, y) = rayon::join(|| count_left(a, is_left), || count_left(b, is_left));
    x + y
}

/// Copy the refs of `list` for which `is_left` holds to `left` and the others
/// to `right`, both in order; the outputs are exactly as long as needed.
fn scatter<F: Fn(&BuildRef) -> bool + Sync>(
    list: &[BuildRef],
    left: &mut [BuildRef],
    right: &mut [BuildRef],
    is_left: &F,
) {
    if list.len() <= 4 * CHUNK {
        let (mut i, mut j) = (0, 0);
        for r in list {
            if is_left(r) {
                left[i] = *r;
                i += 1;
            } else {
                right[j] = *r;
                j += 1;
            }
        }
        return;
    }
    let mid = list.len() / 2;
    let (a, b) = list.split_at(mid);
    let nl = count_left(a, is_left);
    let (l1, l2) = left.split_at_mut(nl);
    let (r1, r2) = right.split_at_mut(mid - nl);
    rayon::join(
        || scatter(a, l1, r1, is_left),
        || scatter(b, l2, r2, is_left),
    );
}

/// Binned SAH split of a list weighted by the refs' subtree costs; `None`
/// when the centroids coincide or the tree is too deep (median split then).
fn find_split(
    ctx: &Ctx,
    list: &[BuildRef],
    cbounds: &Aabb,
    depth: u32,
) -> Option<(BinMapping, SplitCandidate)> {
    if depth >= MEDIAN_FROM_DEPTH || cbounds.extent().max_element() <= 0.0 {
        return None;
    }
    let map = BinMapping::new(cbounds, ctx.params.bins.min(list.len().max(4)));
    let parallel = list.len() > ctx.params.parallel_threshold;
    with_bins(&map, &ListBinner { list, parallel }).map(|s| (map, s))
}

/// Build the subtree over the `n` refs at the front of `list` (`list.len()`
/// slots in all, the rest spare). `list[0]` is array position `first`; the
/// subtree's descendants go to `desc`, whose first slot is `desc_first`.
#[allow(clippy::too_many_arguments)]
fn build_list(
    ctx: &Ctx,
    list: &mut [BuildRef],
    scratch: &mut [BuildRef],
    n: usize,
    desc: &mut [BvhNode],
    desc_first: u32,
    first: u32,
    depth: u32,
) -> BvhNode {
    let parallel = n > ctx.params.parallel_threshold;
    let (mut bounds, mut cbounds) = list_bounds(&list[..n], parallel);
    if n == 1 {
        return BvhNode::leaf(bounds, first, 1);
    }
    let mut n = n;
    for _ in 0..ctx.params.open_rounds {
        if !(ctx.params.open
            && depth < MEDIAN_FROM_DEPTH
            && may_open(ctx, &list[..n], list.len() - n))
        {
            break;
        }
        let opened = open_refs(ctx, list, n, &bounds);
        if opened == n {
            break;
        }
        n = opened;
        (bounds, cbounds) = list_bounds(&list[..n], n > ctx.params.parallel_threshold);
    }
    // What the binned sweep below decides for two refs, without it: on
    // every usable axis each side holds one ref at the same cost (a sum of
    // the same two terms), so the sweep keeps the lowest usable axis, and
    // the ref of lower centroid goes left. Half of a top-level tree's inner
    // nodes hold two refs.
    if n == 2
        && ctx.params.max_leaf_refs == 1
        && depth < MEDIAN_FROM_DEPTH
        && let Some(axis) = first_usable_axis(&cbounds)
    {
        if list[1].bounds.center()[axis] < list[0].bounds.center()[axis] {
            list.swap(0, 1);
        }
        return split_and_recurse(
            ctx, list, scratch, 2, 1, desc, desc_first, first, depth, bounds,
        );
    }
    let split = find_split(ctx, &list[..n], &cbounds, depth);
    // A leaf of several refs when the SAH prefers it: the refs' costs as seen
    // from this node's box against one traversal step plus the split.
    if n <= ctx.params.max_leaf_refs {
        let area = bounds.half_area();
        let leaf_cost: f32 = list[..n]
            .iter()
            .map(|r| {
                if is_object_leaf(ctx, r) {
                    area * r.cost
                } else {
                    area + r.bounds.half_area() * (r.cost - 1.0)
                }
            })
            .sum();
        let split_cost = match &split {
            Some((_, s)) => area + s.cost / 16.0,
            None => f32::INFINITY,
        };
        if leaf_cost <= split_cost {
            return BvhNode::leaf(bounds, first, n as u32);
        }
    }
    let nl = match split {
        // `goes_left` is `bin(..) < s.bin` by one float compare (the
        // saturating float-to-integer cast of `bin` is a branchy sequence).
        Some((map, s)) => {
            let centre = |r: &BuildRef| -> Vec3A { r.bounds.center().into() };
            let (list, scratch) = (&mut list[..n], &mut scratch[..n]);
            match s.axis {
                0 => partition_refs(list, scratch, parallel, |r| {
                    map.goes_left::<0>(centre(r), s.bin)
                }),
                1 => partition_refs(list, scratch, parallel, |r| {
                    map.goes_left::<1>(centre(r), s.bin)
                }),
                _ => partition_refs(list, scratch, parallel, |r| {
                    map.goes_left::<2>(centre(r), s.bin)
                }),
            }
        }
        None => {
            let mid = n / 2;
            if cbounds.extent().max_element() > 0.0 {
                let axis = cbounds.largest_axis();
                list[..n].select_nth_unstable_by(mid, |a, b| {
                    a.bounds.center()[axis]
                        .total_cmp(&b.bounds.center()[axis])
                        .then((a.object, a.instance, a.node).cmp(&(b.object, b.instance, b.node)))
                });
            }
            mid
        }
    };
    split_and_recurse(
        ctx, list, scratch, n, nl, desc, desc_first, first, depth, bounds,
    )
}

/// The lowest axis along which the binning of [`find_split`] can split
/// centroids of these bounds ([`BinMapping::axis_usable`]).
fn first_usable_axis(cbounds: &Aabb) -> Option<usize> {
    let map = BinMapping::new(cbounds, 4);
    (0..3).find(|&a| map.axis_usable(a))
}

/// Build the two sides of a list partitioned at `nl` (of its `n` refs) and
/// return their parent.
#[allow(clippy::too_many_arguments)]
fn split_and_recurse(
    ctx: &Ctx,
    list: &mut [BuildRef],
    scratch: &mut [BuildRef],
    n: usize,
    nl: usize,
    desc: &mut [BvhNode],
    desc_first: u32,
    first: u32,
    depth: u32,
    bounds: Aabb,
) -> BvhNode {
    debug_assert!(nl > 0 && nl < n);
    let parallel = n > ctx.params.parallel_threshold;

    // Divide the spare slots in proportion to the sides' ref counts:
    // [left | left spare | right | right spare].
    let spare = list.len() - n;
    let left_spare = (spare as u64 * nl as u64 / n as u64) as usize;
    // Only when the right side moves: the root's opening rounds usually
    // spend the whole budget, below which the copy would be onto itself
    // (a `memmove` of every right-side ref at every level, for nothing).
    if left_spare > 0 {
        list.copy_within(nl..n, nl + left_spare);
    }
    let left_len = nl + left_spare;

    let (pair, (left_desc, left_desc_first), (right_desc, right_desc_first)) =
        split_slots(desc, desc_first, left_len);
    let (left_list, right_list) = list.split_at_mut(left_len);
    let (left_scratch, right_scratch) = scratch.split_at_mut(left_len);
    let nr = n - nl;
    let right_first = first + left_len as u32;
    let mut build_left = move || {
        build_list(
            ctx,
            left_list,
            left_scratch,
            nl,
            left_desc,
            left_desc_first,
            first,
            depth + 1,
        )
    };
    let mut build_right = move || {
        build_list(
            ctx,
            right_list,
            right_scratch,
            nr,
            right_desc,
            right_desc_first,
            right_first,
            depth + 1,
        )
    };
    let (l, r) = if n > 64 || parallel {
        rayon::join(build_left, build_right)
    } else {
        (build_left(), build_right())
    };
    pair[0] = l;
    pair[1] = r;
    BvhNode::inner(bounds, desc_first)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn cube_ref(lo: Vec3, size: f32) -> BuildRef {
        BuildRef {
            bounds: Aabb::new(lo, lo + Vec3::splat(size)),
            object: 0,
            node: 0,
            instance: INVALID_ID,
            prims: 1,
            cost: 1.0,
        }
    }

    #[test]
    fn placement_overlap_counts_covering_boxes() {
        let a = cube_ref(Vec3::ZERO, 1.0);
        // The same box twice: every point covered twice.
        assert_eq!(placement_overlap(&[a, a]), 2.0);
        // Side by side: 2 x 3 over the 2x1x1 union's 5.
        let b = cube_ref(Vec3::X, 1.0);
        assert_eq!(placement_overlap(&[a, b]), 6.0 / 5.0);
        // A small box inside a large one.
        let big = cube_ref(Vec3::ZERO, 2.0);
        assert_eq!(placement_overlap(&[big, a]), (12.0 + 3.0) / 12.0);
        // Nothing with an area: 0.
        assert_eq!(placement_overlap(&[]), 0.0);
        let flat = BuildRef {
            bounds: Aabb::new(Vec3::ZERO, Vec3::ZERO),
            ..a
        };
        assert_eq!(placement_overlap(&[flat]), 0.0);
    }

    #[test]
    fn budget_grows_with_overlap_above_the_unit_only() {
        let scaled = |overlap_unit| RefBudget::Scaled {
            min: 10,
            per_initial_ref: 2.0,
            per_primitive: 0.01,
            overlap_unit,
        };
        let budget = scaled(10.0);
        // At or below the unit: the unscaled primitive term.
        assert_eq!(budget.capacity(5, 100_000, 0.0), 1000);
        assert_eq!(budget.capacity(5, 100_000, 10.0), 1000);
        // Above it: in proportion.
        assert_eq!(budget.capacity(5, 100_000, 25.0), 2500);
        // Not finite: unscaled.
        assert_eq!(budget.capacity(5, 100_000, f64::INFINITY), 1000);
        assert_eq!(budget.capacity(5, 100_000, f64::NAN), 1000);
        // Off.
        assert_eq!(scaled(0.0).capacity(5, 100_000, 25.0), 1000);
        // The other terms still bound it from below.
        assert_eq!(budget.capacity(5, 10, 25.0), 10);
        assert_eq!(budget.capacity(700, 10, 25.0), 1400);
    }
}
