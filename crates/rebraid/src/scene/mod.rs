//! Scenes of many objects and instances, and their acceleration modes.
//!
//! A [`Scene`] holds objects (triangle meshes) and instances (an object placed
//! by an affine transform). An object is either *placed* (it appears in the
//! world as given) or only a prototype seen through its instances. Edits mark
//! what changed; [`Scene::commit`] rebuilds the BVHs of changed objects only
//! (in parallel across objects, and in parallel within a large object), then
//! the top level, in the [`AccelMode`] the scene is set to. Queries answer
//! from the last commit; before the first commit they hit nothing.
//!
//! In the two-level modes an object that exactly one instance places, and
//! that instance has never moved, is *baked*: its BVH is built over its
//! transformed vertices and the top level treats it as directly placed,
//! while hits still name the instance
//! ([`crate::toplevel::RebraidParams::bake_single_instances`]). Scene files
//! place every mesh through a node, so most such instances are plain
//! placements, and traced directly they need no instance ray. The first move
//! of a baked instance makes the next commit build its object in object
//! space, once; from then on moves cost no object build, as for any
//! instance. [`CommitReport::instances_baked`] lists the baked instances.
//!
//! With [`SceneParams::merge_placed`] the two-level modes trace the objects
//! placed directly from one BVH over all their triangles (see there).
//!
//! A re-braided scene whose placements move (an instance's transform, an
//! object's vertices) traces those that moved within
//! [`RebraidParams::moving_hold_commits`] commits from a second top level,
//! built at every commit, and keeps the top level over the others from
//! the commit that last changed which placements move ([`Accel::Split`],
//! [`SplitAccel`]): a frame of one moving object costs its refit, not a
//! re-braiding of the whole scene.

mod flat;
mod split;

use std::sync::Arc;
use std::time::Instant;

use glam::Affine3A;
use rayon::prelude::*;

use flat::FlatPart;
pub use flat::{FlatAccel, PrimOrigin};
pub use split::SplitAccel;

use crate::bvh::{
    BuildParams, BvhStats, Kernel, SahCosts, SceneVolumeLeafLimit, TraversalCounters, WideBvh,
};
use crate::toplevel::builder::{RefSources, TopLevelScratch, build_top_level_with};
use crate::toplevel::{
    BuildRef, InstanceXf, MergedSlot, ObjectBvh, RebraidParams, TopLevelAccel, TopLevelBuildStats,
    TopLevelLayout,
};
use crate::transform::{check_transform, transform_box};
use crate::{Aabb, Error, Hit, INVALID_ID, MeshBvh, Ray, SceneDesc, TriangleMesh};

/// Id of an object of a scene (stable until the object is removed).
pub type ObjectId = u32;
/// Id of an instance of a scene (stable until the instance is removed).
pub type InstanceId = u32;

/// How a committed scene is accelerated. Every mode answers every query the
/// same way (same closest hit up to exact ties, same occlusion).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum AccelMode {
    /// One BVH over every world-space triangle: best traversal, slowest
    /// build, no sharing of instanced geometry.
    Flat,
    /// One BVH per object plus a top-level BVH over object and instance boxes.
    TwoLevel,
    /// Two-level with partial re-braiding: the top level opens object BVHs
    /// where they overlap (see [`crate::toplevel::builder`]).
    #[default]
    Rebraided,
}

impl AccelMode {
    pub const ALL: [AccelMode; 3] = [AccelMode::Flat, AccelMode::TwoLevel, AccelMode::Rebraided];

    /// The name used by the tool and in reports: `flat`, `two-level`, `rebraided`.
    pub fn name(&self) -> &'static str {
        match self {
            AccelMode::Flat => "flat",
            AccelMode::TwoLevel => "two-level",
            AccelMode::Rebraided => "rebraided",
        }
    }
}

impl std::str::FromStr for AccelMode {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        match s {
            "flat" => Ok(AccelMode::Flat),
            "two-level" | "twolevel" | "two_level" => Ok(AccelMode::TwoLevel),
            "rebraided" | "rebraid" => Ok(AccelMode::Rebraided),
            _ => Err(Error::InvalidParameter(format!(
                "unknown mode '{s}' (expected flat, two-level or rebraided)"
            ))),
        }
    }
}

/// Build parameters of a scene.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SceneParams {
    pub mode: AccelMode,
    /// Object BVHs (and the flat BVH).
    pub object_build: BuildParams,
    /// Top level of the re-braided mode (the two-level mode uses the same
    /// parameters with opening off).
    pub rebraid: RebraidParams,
    /// Traversal kernel; `None` picks the best this CPU runs
    /// ([`Kernel::best`]). Tests force each kernel to compare them.
    pub kernel: Option<Kernel>,
    /// Two-level modes: trace the objects placed directly from one BVH
    /// over all their triangles, as Embree traces a static scene, instead
    /// of one BVH each. Members are the live objects that are placed, not
    /// empty, have no instances and the [`UpdatePolicy::Rebuild`] policy,
    /// and have not been edited since a commit took them in, when there are
    /// at least two; instanced objects, objects with instances, refitted
    /// and edited objects keep their own BVHs, which the top level
    /// re-braids with the merged one as with any object. Hits name the
    /// object and its primitive as always.
    ///
    /// Why: a re-braided top level opens object BVHs but cannot mix two
    /// objects' triangles in one leaf, so where objects interleave at the
    /// triangle level (a level split by material, each material spanning
    /// the map) even every object opened to its leaves traces more nodes
    /// and leaves than one BVH over all of them (nexuiz, diffuse rays:
    /// 9.77 inner nodes and 3.44 leaves per ray against 8.42 and 3.07;
    /// docs/performance.md, sessions 29 and 30).
    ///
    /// The cost: the merged BVH is one build over all the members'
    /// triangles (about what the flat mode's build costs for them), made
    /// again whenever the members change. An object's first edit (its
    /// mesh or vertices, after a commit took it in) takes it out for good,
    /// as a baked instance's first move makes it an instance: that commit
    /// builds its own BVH and the merged one without it, later edits only
    /// its own. When the merged BVH is the whole scene (no other object, no
    /// instance) the top level is walked as that BVH alone
    /// ([`crate::toplevel::TopLevelAccel::direct`]).
    ///
    /// Off by default: the one large build takes more than the objects'
    /// small ones (commit instructions nexuiz +7.9%, openarena +14.7%,
    /// samurai +12.1%; nexuiz, one thread: 0.85-1.16 of
    /// `embree-two-level`'s build time with it over session 31's runs,
    /// 1.07-1.27 without), for diffuse rays 7-25% fewer instructions on
    /// those scenes (nexuiz 0.92-0.95 of `embree-flat`'s wall time with it,
    /// 0.78-0.85 without); and on the library scene, whose objects are all
    /// members, the flat walk it becomes is slower than the re-braided one
    /// (0.88 against 0.92 of `embree-flat`, session 30).
    /// `rebraid --merge-placed` turns it on.
    pub merge_placed: bool,
}

/// How a commit brings the BVH of an object whose vertices moved up to date.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum UpdatePolicy {
    /// Build a new BVH (best tree, slowest update).
    #[default]
    Rebuild,
    /// Keep the tree's topology and recompute its boxes from the new
    /// vertices ([`MeshBvh::refit`]): much faster, but the tree degrades as
    /// the geometry moves away from the pose it was built for. Applies only
    /// when the triangles are unchanged: a new mesh with other indices
    /// ([`Scene::set_mesh`]) and the object's first BVH are always built.
    Refit,
}

struct Object {
    mesh: TriangleMesh,
    placed: bool,
    /// The object-space BVH (`None` while the object is baked).
    bvh: Option<Arc<ObjectBvh>>,
    /// The world-space BVH of the one instance that places the object, while
    /// it is baked (see [`RebraidParams::bake_single_instances`]).
    baked: Option<Baked>,
    /// The box of the mesh's vertices, made at the first commit that needs
    /// it after the mesh changed (see `Scene::scene_volume`).
    vertex_bounds: Option<Aabb>,
    /// The mesh changed since `bvh` was built.
    dirty: bool,
    /// The triangles (indices) changed since `bvh` was built: rebuild.
    topology_changed: bool,
    policy: UpdatePolicy,
    /// Edited after a commit took it in: never merged again (see
    /// [`SceneParams::merge_placed`]).
    edited: bool,
    /// Commits made before it was added, and the commit its last move
    /// (vertices or mesh edited after a commit took it in) goes into, 0
    /// for none (see [`RebraidParams::moving_hold_commits`]).
    born: u64,
    moved: u64,
}

impl Object {
    /// A moved object whose BVH can be refitted rather than rebuilt.
    fn can_refit(&self) -> bool {
        self.policy == UpdatePolicy::Refit
            && !self.topology_changed
            && self
                .bvh
                .as_ref()
                .is_some_and(|b| b.mesh.len() == self.mesh.len())
    }
}

/// The objects placed directly that one BVH traces together (see
/// [`SceneParams::merge_placed`]).
struct Merged {
    /// The member objects, ascending.
    members: Vec<ObjectId>,
    bvh: Arc<ObjectBvh>,
    /// Per primitive of `bvh`, the (object, primitive) it is.
    origins: Arc<[(u32, u32)]>,
}

impl Merged {
    /// One BVH over the members' triangles, in member order.
    fn build(
        objects: &[Option<Object>],
        members: Vec<ObjectId>,
        params: &BuildParams,
    ) -> Result<Self, Error> {
        let meshes: Vec<_> = members
            .iter()
            .map(|&id| {
                let o = objects[id as usize].as_ref().expect("members are live");
                (&o.mesh, None)
            })
            .collect();
        let mesh = TriangleMesh::concat(&meshes)?;
        let mut origins = Vec::with_capacity(mesh.len());
        for (&id, (m, _)) in members.iter().zip(&meshes) {
            origins.extend((0..m.len() as u32).map(|p| (id, p)));
        }
        let bvh = MeshBvh::build(&mesh, params)?;
        Ok(Self {
            members,
            bvh: Arc::new(ObjectBvh::with_collapse(bvh, params.collapse)),
            origins: origins.into(),
        })
    }
}

/// A placement traced from a BVH over its object's transformed vertices.
struct Baked {
    instance: InstanceId,
    bvh: Arc<ObjectBvh>,
}

#[derive(Clone, Copy)]
struct Instance {
    object: ObjectId,
    xf: InstanceXf,
    /// May be baked: false once its transform changed (a moving instance
    /// stays an instance, whose moves cost nothing to rebuild) or once its
    /// transformed vertices were not finite.
    bakeable: bool,
    /// As [`Object`]'s: commits before it was added, and the commit its
    /// last move goes into (0: none).
    born: u64,
    moved: u64,
}

/// Per object slot and per instance slot, whether the placement moved
/// within [`RebraidParams::moving_hold_commits`] commits (an instance
/// moves with its object's vertices too).
#[derive(Clone, Debug, PartialEq)]
struct Moving {
    objects: Vec<bool>,
    instances: Vec<bool>,
}

/// What a kept top level over the placements that did not move was built
/// for: it serves a later commit only when all of this is the same (every
/// edit of a placement makes it move, so the others are as they were).
#[derive(Clone, Debug, PartialEq)]
struct FixedKey {
    /// [`Scene`]'s count of edits to what the scene holds (objects and
    /// instances added or removed, placed, their update policies).
    structure: u64,
    params: SceneParams,
    moving: Moving,
}

/// Where a pending object BVH (see `ObjectBvh::planned`) sits: an
/// object's own, or the world-space one of its baked placement.
#[derive(Clone, Copy)]
enum PendingAt {
    Object(usize),
    Baked(usize),
}

/// The placements a top level is built over.
#[derive(Clone, Copy)]
enum Part<'a> {
    All,
    /// Those that did not move.
    Fixed(&'a Moving),
    /// Those that did.
    Moving(&'a Moving),
}

impl Part<'_> {
    /// Whether the object placed directly (`instance` INVALID_ID) or the
    /// instance is in this part.
    fn takes(&self, object: ObjectId, instance: InstanceId) -> bool {
        let moved = |m: &Moving| {
            m.objects[object as usize] || (instance != INVALID_ID && m.instances[instance as usize])
        };
        match self {
            Part::All => true,
            Part::Fixed(m) => !moved(m),
            Part::Moving(m) => moved(m),
        }
    }
}

/// The committed acceleration structure.
#[derive(Clone, Debug, Default)]
#[allow(
    clippy::large_enum_variant,
    reason = "one per scene, built once per commit and never moved in a hot path; \
              boxing it would put a pointer between every trace call and its tables"
)]
pub enum Accel {
    /// Nothing committed yet, or an empty scene.
    #[default]
    Empty,
    Flat(FlatAccel),
    TopLevel(TopLevelAccel),
    /// A re-braided scene some of whose placements moved lately (see
    /// [`RebraidParams::moving_hold_commits`]).
    Split(SplitAccel),
}

/// What a commit did and how long each phase took.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CommitReport {
    pub mode: AccelMode,
    /// Objects whose BVH was (re)built by this commit.
    pub objects_rebuilt: Vec<ObjectId>,
    /// Objects whose BVH was refitted to moved vertices by this commit
    /// ([`UpdatePolicy::Refit`]); disjoint from `objects_rebuilt`.
    pub objects_refitted: Vec<ObjectId>,
    /// Objects whose BVH from an earlier commit was reused as it was (not
    /// counting the members of a merged BVH).
    pub objects_reused: usize,
    /// Objects traced from the merged BVH after this commit (see
    /// [`SceneParams::merge_placed`]); 0 when there is none.
    pub objects_merged: usize,
    /// This commit built the merged BVH (its triangles count in
    /// `triangles_rebuilt`, its time in `object_build_ms`).
    pub merged_rebuilt: bool,
    /// Triangles of the rebuilt objects.
    pub triangles_rebuilt: usize,
    /// Triangles of the refitted objects.
    pub triangles_refitted: usize,
    /// Instances traced from a BVH over their object's transformed
    /// vertices after this commit (two-level modes; see
    /// [`RebraidParams::bake_single_instances`]). Their objects' BVH
    /// builds count in `objects_rebuilt` like object-space ones.
    pub instances_baked: Vec<InstanceId>,
    /// Building the BVHs of `objects_rebuilt`. Their leaf blocks and
    /// occlusion order are made beside the top-level build (see
    /// `ObjectBvh::planned`): what that adds to the top level's own time
    /// (all of it on one thread) counts here, not in `top_build_ms`.
    pub object_build_ms: f64,
    /// Refitting the BVHs of `objects_refitted`.
    pub refit_ms: f64,
    /// Top-level build (two-level modes: both top levels of a split
    /// scene) or the whole flat build (flat mode).
    pub top_build_ms: f64,
    pub total_ms: f64,
    /// Top-level statistics (two-level modes, none for an empty scene; of a
    /// split scene, the top level over the placements that did not move,
    /// as it was built).
    pub top: Option<TopLevelBuildStats>,
    /// A split scene's top level over the placements that moved (see
    /// [`RebraidParams::moving_hold_commits`]), built by this commit.
    pub top_moving: Option<TopLevelBuildStats>,
    /// The placements traced from that top level (its initial refs).
    pub moving_placements: usize,
    /// The top level over the placements that did not move was kept from
    /// an earlier commit, not built.
    pub fixed_top_reused: bool,
}

/// A scene of objects and instances with a committed acceleration structure.
#[derive(Default)]
pub struct Scene {
    objects: Vec<Option<Object>>,
    instances: Vec<Option<Instance>>,
    pub params: SceneParams,
    accel: Accel,
    /// Some edit since the last commit.
    changed: bool,
    /// Buffers of the top-level build, kept between commits.
    top_scratch: TopLevelScratch,
    /// Initial refs of the top-level build, kept between commits.
    top_initial: Vec<BuildRef>,
    /// Do not keep `top_scratch` between commits (for measurements).
    no_buffer_reuse: bool,
    /// The merged BVH of the objects placed directly, when
    /// [`SceneParams::merge_placed`] is on and there are members.
    merged: Option<Merged>,
    /// Commits made (each call of [`Scene::commit`]).
    commits: u64,
    /// Edits to what the scene holds (see [`FixedKey::structure`]).
    structure: u64,
    /// What the fixed part of an [`Accel::Split`] was built for.
    fixed_key: Option<FixedKey>,
    /// The parameters of the last successful commit (`params` is a public
    /// field: its changes set no flag).
    committed_params: Option<SceneParams>,
}

impl Scene {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn with_params(params: SceneParams) -> Self {
        Self {
            params,
            ..Self::default()
        }
    }

    /// A scene holding everything a description lists (not yet committed).
    pub fn from_desc(desc: &SceneDesc, params: SceneParams) -> Result<Self, Error> {
        let mut s = Self::with_params(params);
        for o in &desc.objects {
            let id = s.add_object(o.mesh.clone())?;
            s.set_object_placed(id, o.placed)?;
        }
        for i in &desc.instances {
            s.add_instance(i.object, i.transform)?;
        }
        Ok(s)
    }

    /// Set the mode the next commit builds.
    pub fn set_mode(&mut self, mode: AccelMode) {
        if self.params.mode != mode {
            self.params.mode = mode;
            self.changed = true;
        }
    }

    pub fn mode(&self) -> AccelMode {
        self.params.mode
    }

    /// Add a mesh that appears in the world as given. Its id is returned.
    pub fn add_object(&mut self, mesh: TriangleMesh) -> Result<ObjectId, Error> {
        mesh.validate()?;
        if self.objects.len() >= INVALID_ID as usize {
            return Err(Error::TooManyPrimitives(self.objects.len()));
        }
        self.objects.push(Some(Object {
            mesh,
            placed: true,
            bvh: None,
            baked: None,
            vertex_bounds: None,
            dirty: true,
            topology_changed: true,
            policy: UpdatePolicy::default(),
            edited: false,
            born: self.commits,
            moved: 0,
        }));
        self.changed = true;
        self.structure += 1;
        Ok(self.objects.len() as u32 - 1)
    }

    /// Add a mesh seen only through its instances (a prototype).
    pub fn add_prototype(&mut self, mesh: TriangleMesh) -> Result<ObjectId, Error> {
        let id = self.add_object(mesh)?;
        self.set_object_placed(id, false)?;
        Ok(id)
    }

    fn object_mut(&mut self, id: ObjectId) -> Result<&mut Object, Error> {
        self.objects
            .get_mut(id as usize)
            .and_then(|o| o.as_mut())
            .ok_or(Error::UnknownObject(id))
    }

    fn object(&self, id: ObjectId) -> Result<&Object, Error> {
        self.objects
            .get(id as usize)
            .and_then(|o| o.as_ref())
            .ok_or(Error::UnknownObject(id))
    }

    /// Whether the object appears in the world itself (besides its instances).
    pub fn set_object_placed(&mut self, id: ObjectId, placed: bool) -> Result<(), Error> {
        let o = self.object_mut(id)?;
        if o.placed != placed {
            o.placed = placed;
            self.changed = true;
            self.structure += 1;
        }
        Ok(())
    }

    /// The object's mesh.
    pub fn mesh(&self, id: ObjectId) -> Result<&TriangleMesh, Error> {
        Ok(&self.object(id)?.mesh)
    }

    /// Replace the object's mesh. Rebuilt at commit, unless the new mesh has
    /// the same triangles (indices) and the object's policy is
    /// [`UpdatePolicy::Refit`].
    pub fn set_mesh(&mut self, id: ObjectId, mesh: TriangleMesh) -> Result<(), Error> {
        mesh.validate()?;
        let commits = self.commits;
        let o = self.object_mut(id)?;
        if mesh.indices != o.mesh.indices {
            o.topology_changed = true;
        }
        o.mesh = mesh;
        o.vertex_bounds = None;
        o.edited |= !o.dirty;
        o.dirty = true;
        if commits > o.born {
            o.moved = commits + 1;
        }
        self.changed = true;
        Ok(())
    }

    /// How commits update the object's BVH after its vertices moved.
    pub fn set_update_policy(&mut self, id: ObjectId, policy: UpdatePolicy) -> Result<(), Error> {
        let o = self.object_mut(id)?;
        if o.policy != policy {
            o.policy = policy;
            // It may join or leave the merged BVH, and be baked or not
            // (a refitted object never is).
            self.changed = true;
            self.structure += 1;
        }
        Ok(())
    }

    pub fn update_policy(&self, id: ObjectId) -> Result<UpdatePolicy, Error> {
        Ok(self.object(id)?.policy)
    }

    /// Keep the top-level build's large buffers (ref array, scratch, node
    /// slots, output arrays) between commits (the default), or allocate them
    /// anew for every commit (`false`, for measurements).
    pub fn set_reuse_top_level_buffers(&mut self, reuse: bool) {
        self.no_buffer_reuse = !reuse;
        if !reuse {
            self.top_scratch.clear();
        }
    }

    /// Bytes held between commits for the top-level build.
    pub fn top_level_buffer_bytes(&self) -> usize {
        self.top_scratch.bytes() + self.top_initial.capacity() * std::mem::size_of::<BuildRef>()
    }

    /// Move the object's vertices (same count, same triangles); rebuilt or
    /// refitted at commit, by the object's [`UpdatePolicy`].
    pub fn set_vertices(&mut self, id: ObjectId, positions: &[glam::Vec3]) -> Result<(), Error> {
        let commits = self.commits;
        let o = self.object_mut(id)?;
        if positions.len() != o.mesh.positions.len() {
            return Err(Error::VertexCountMismatch {
                expected: o.mesh.positions.len(),
                got: positions.len(),
            });
        }
        crate::mesh::check_positions(positions)?;
        o.mesh.positions.copy_from_slice(positions);
        o.vertex_bounds = None;
        o.edited |= !o.dirty;
        o.dirty = true;
        if commits > o.born {
            o.moved = commits + 1;
        }
        self.changed = true;
        Ok(())
    }

    /// Remove an object and every instance of it. Returns the removed instances.
    pub fn remove_object(&mut self, id: ObjectId) -> Result<Vec<InstanceId>, Error> {
        self.object(id)?;
        self.objects[id as usize] = None;
        let mut removed = Vec::new();
        for (i, inst) in self.instances.iter_mut().enumerate() {
            if inst.is_some_and(|x| x.object == id) {
                *inst = None;
                removed.push(i as u32);
            }
        }
        self.changed = true;
        self.structure += 1;
        Ok(removed)
    }

    /// Place an object by an affine object-to-world transform (non-uniform
    /// scale allowed; singular or non-finite transforms are rejected).
    pub fn add_instance(
        &mut self,
        object: ObjectId,
        transform: Affine3A,
    ) -> Result<InstanceId, Error> {
        self.object(object)?;
        check_transform(&transform)?;
        if self.instances.len() >= INVALID_ID as usize {
            return Err(Error::TooManyPrimitives(self.instances.len()));
        }
        self.instances.push(Some(Instance {
            object,
            xf: InstanceXf::new(transform),
            bakeable: true,
            born: self.commits,
            moved: 0,
        }));
        self.changed = true;
        self.structure += 1;
        Ok(self.instances.len() as u32 - 1)
    }

    /// Move an instance. An instance that moves is never baked again (see
    /// [`RebraidParams::bake_single_instances`]): if it was, the next commit
    /// builds its object's BVH in object space, once, and later moves cost
    /// no object build. Setting the transform it has changes nothing.
    pub fn set_instance_transform(
        &mut self,
        id: InstanceId,
        transform: Affine3A,
    ) -> Result<(), Error> {
        check_transform(&transform)?;
        let inst = self
            .instances
            .get_mut(id as usize)
            .and_then(|i| i.as_mut())
            .ok_or(Error::UnknownInstance(id))?;
        if inst.xf.object_to_world == transform {
            return Ok(());
        }
        inst.bakeable = false;
        inst.xf = InstanceXf::new(transform);
        if self.commits > inst.born {
            inst.moved = self.commits + 1;
        }
        self.changed = true;
        Ok(())
    }

    pub fn instance_transform(&self, id: InstanceId) -> Result<Affine3A, Error> {
        self.instances
            .get(id as usize)
            .and_then(|i| i.as_ref())
            .map(|i| i.xf.object_to_world)
            .ok_or(Error::UnknownInstance(id))
    }

    pub fn remove_instance(&mut self, id: InstanceId) -> Result<(), Error> {
        let slot = self
            .instances
            .get_mut(id as usize)
            .filter(|i| i.is_some())
            .ok_or(Error::UnknownInstance(id))?;
        *slot = None;
        self.changed = true;
        self.structure += 1;
        Ok(())
    }

    /// Ids of live objects.
    pub fn object_ids(&self) -> impl Iterator<Item = ObjectId> + '_ {
        self.objects
            .iter()
            .enumerate()
            .filter(|(_, o)| o.is_some())
            .map(|(i, _)| i as u32)
    }

    /// Live instances as (id, object, transform).
    pub fn instances(&self) -> impl Iterator<Item = (InstanceId, ObjectId, Affine3A)> + '_ {
        self.instances
            .iter()
            .enumerate()
            .filter_map(|(i, x)| x.map(|x| (i as u32, x.object, x.xf.object_to_world)))
    }

    pub fn object_count(&self) -> usize {
        self.objects.iter().flatten().count()
    }

    pub fn instance_count(&self) -> usize {
        self.instances.iter().flatten().count()
    }

    /// Triangles in the world: placed objects plus one copy per instance.
    pub fn world_triangles(&self) -> usize {
        let placed: usize = self
            .objects
            .iter()
            .flatten()
            .filter(|o| o.placed)
            .map(|o| o.mesh.len())
            .sum();
        let inst: usize = self
            .instances
            .iter()
            .flatten()
            .map(|i| {
                self.objects[i.object as usize]
                    .as_ref()
                    .map_or(0, |o| o.mesh.len())
            })
            .sum();
        placed + inst
    }

    /// True when there are edits the last commit does not include.
    pub fn needs_commit(&self) -> bool {
        // Every edit sets `changed`; `dirty` only says an object's BVH is
        // stale, which a flat commit leaves so (it builds no object BVHs).
        self.changed
    }

    /// The committed acceleration structure.
    pub fn accel(&self) -> &Accel {
        &self.accel
    }

    /// Bring the acceleration structure up to date with every edit.
    pub fn commit(&mut self) -> Result<CommitReport, Error> {
        let start = Instant::now();
        self.params.object_build.check()?;
        self.params.rebraid.check()?;
        let mode = self.params.mode;
        let mut report = CommitReport {
            mode,
            ..Default::default()
        };
        self.commits += 1;
        if self.is_up_to_date() {
            return Ok(self.up_to_date_report(report, start));
        }
        self.committed_params = None;
        if mode == AccelMode::Flat {
            let t = Instant::now();
            let mut parts = Vec::new();
            for (id, o) in self.objects.iter().enumerate() {
                if let Some(o) = o
                    && o.placed
                {
                    parts.push(FlatPart {
                        mesh: &o.mesh,
                        transform: None,
                        object: id as u32,
                        instance: INVALID_ID,
                    });
                }
            }
            for (id, inst) in self.instances.iter().enumerate() {
                if let Some(inst) = inst
                    && let Some(o) = &self.objects[inst.object as usize]
                {
                    parts.push(FlatPart {
                        mesh: &o.mesh,
                        transform: Some(inst.xf.object_to_world),
                        object: inst.object,
                        instance: id as u32,
                    });
                }
            }
            let flat = FlatAccel::build(
                &parts,
                &self.params.object_build,
                self.params.kernel.unwrap_or_else(Kernel::best),
            )?;
            report.top_build_ms = t.elapsed().as_secs_f64() * 1e3;
            self.fixed_key = None;
            self.accel = if flat.bvh.is_empty() {
                Accel::Empty
            } else {
                Accel::Flat(flat)
            };
        } else {
            // Take the previous structure apart: its output arrays go back
            // to the top-level buffers, and its references to the object
            // BVHs are dropped, so that the refits below update the BVHs in
            // place (`Arc::make_mut` copies one only while someone else,
            // e.g. a caller's clone of the old structure, still holds it).
            // Should this commit fail from here on, queries hit nothing
            // until the next successful commit.
            //
            // A re-braided scene some of whose placements moved lately is
            // split (see `RebraidParams::moving_hold_commits`): the top
            // level over the others is kept when it was built for the
            // same placements.
            let moving = self.moving_placements();
            let key = moving.as_ref().map(|m| FixedKey {
                structure: self.structure,
                params: self.params.clone(),
                moving: m.clone(),
            });
            let mut kept_fixed = None;
            let mut bufs = Vec::new();
            match std::mem::take(&mut self.accel) {
                Accel::TopLevel(old) => bufs.push(self.take_apart(old)),
                Accel::Split(SplitAccel { fixed, moving }) => {
                    bufs.push(self.take_apart(moving));
                    if key.is_some() && self.fixed_key == key {
                        kept_fixed = Some(fixed);
                    } else {
                        bufs.push(self.take_apart(fixed));
                    }
                }
                Accel::Empty | Accel::Flat(_) => {}
            }
            self.fixed_key = None;
            report.fixed_top_reused = kept_fixed.is_some();

            // Object BVHs of changed objects, in parallel across objects:
            // in world space for an object baked with its one instance
            // (built when it becomes baked or its mesh changed), else in
            // object space (built when changed or when it stops being
            // baked).
            let t = Instant::now();
            let bake_for = self.bake_targets();
            // The merged BVH's members (see `SceneParams::merge_placed`),
            // rebuilt when they or any of their meshes changed.
            let members = self.merge_members();
            let mut is_member = vec![false; self.objects.len()];
            for &m in &members {
                is_member[m as usize] = true;
            }
            let merge_stale = !members.is_empty()
                && self.merged.as_ref().is_none_or(|m| {
                    m.members != members
                        || members
                            .iter()
                            .any(|&i| self.objects[i as usize].as_ref().is_some_and(|o| o.dirty))
                });
            if members.is_empty() {
                self.merged = None;
            }
            let mut todo: Vec<(usize, Option<InstanceId>)> = Vec::new();
            for (i, o) in self.objects.iter_mut().enumerate() {
                let Some(o) = o else { continue };
                if is_member[i] {
                    o.baked = None;
                    continue;
                }
                match bake_for[i] {
                    Some(inst) => {
                        let current = o.baked.as_ref().is_some_and(|b| b.instance == inst);
                        if o.dirty || !current {
                            todo.push((i, Some(inst)));
                        }
                    }
                    None => {
                        o.baked = None;
                        if (o.dirty || o.bvh.is_none()) && !o.can_refit() {
                            todo.push((i, None));
                        }
                    }
                }
            }
            // The scene's volume, for the leaf limit of the BVHs built in
            // world space: those of objects placed directly, baked ones and
            // the merged one (`SceneVolumeLeafLimit`).
            let scene_volume = self.scene_volume();
            let object_build = &self.params.object_build;
            let params = &BuildParams {
                scene_volume_leaf_limit: object_build.scene_volume_leaf_limit.map(|r| {
                    SceneVolumeLeafLimit {
                        scene_volume: Some(scene_volume),
                        ..r
                    }
                }),
                ..object_build.clone()
            };
            // An object's root is not the scene: the large-leaf rule is for
            // the merged BVH (and the flat mode's), not for objects.
            let world_params = &BuildParams {
                large_leaf_split: None,
                ..params.clone()
            };
            // An object BVH in object space: the scene's volume does not
            // measure its boxes.
            let local_params = &BuildParams {
                scene_volume_leaf_limit: None,
                ..world_params.clone()
            };
            // The object structure up to its wide collapse (binary build,
            // counts and costs, collapse) per task: the collapse and
            // packing were a serial 17% of `library --scale 1`'s object
            // builds when they ran after all the binary builds. The packing
            // and occlusion order (`ObjectBvh::planned`) follow in
            // `build_top`, beside the top level's build: at two threads
            // builds 2-10% faster on five shared scenes (session 47).
            // One object per task (`with_max_len(1)`): rayon's adaptive
            // split otherwise left a thread running a run of the largest
            // objects in sequence while the other, done with its share of
            // small ones, found nothing to steal but their inner joins
            // (openarena, 51 objects, two threads: 6.7-6.8 -> 5.0-5.3 ms,
            // nexuiz 13.9-14.4 -> 12.6-13.2 ms; one thread equal).
            // Largest first (longest-processing-time-first scheduling):
            // a large object started late is the critical path, its
            // serial phases (the wide collapse, the packing) exposed while
            // the other threads have nothing left to do. Ravenbridge
            // mansion at two threads (a timed trace, since removed): in
            // index order its 105k-triangle object (of 138k) started after
            // 6 ms of small ones and ended the phase at 45.5 ms, the other
            // thread idle from 19 ms on; largest first it starts at 0 and
            // the phase ends with it at 31.4 ms. Worker-process builds
            // (`bench --embree --threads 2`, 6 alternations): 29.1 -> 25.7
            // ms median. The results are taken back in `todo` order.
            // (object, instance asked to bake, instance baked, BVH).
            type Built = (
                usize,
                Option<InstanceId>,
                Option<InstanceId>,
                Result<ObjectBvh, Error>,
            );
            let mut order: Vec<usize> = (0..todo.len()).collect();
            order.sort_by_key(|&k| {
                let tris = self.objects[todo[k].0].as_ref().map_or(0, |o| o.mesh.len());
                std::cmp::Reverse(tris)
            });
            let objects = &self.objects;
            let (merged, mut built): (_, Vec<(usize, Built)>) = rayon::join(
                || merge_stale.then(|| Merged::build(objects, members.clone(), params)),
                || {
                    order
                        .par_iter()
                        .with_max_len(1)
                        .map(|&k| {
                            let (i, bake) = todo[k];
                            let o = self.objects[i].as_ref().expect("listed above");
                            let baked = bake.and_then(|inst| {
                                let xf = &self.instances[inst as usize]
                                    .as_ref()
                                    .expect("bake targets are live")
                                    .xf
                                    .object_to_world;
                                // A failure (vertices moved to infinity by a huge
                                // scale): the instance stays one.
                                let bvh =
                                    MeshBvh::build_transformed(&o.mesh, xf, world_params).ok()?;
                                Some((inst, ObjectBvh::planned(bvh, params.collapse)))
                            });
                            let b: Built = match baked {
                                Some((inst, bvh)) => (i, bake, Some(inst), Ok(bvh)),
                                None => {
                                    // Placed directly, object space is world space.
                                    let p = if o.placed { world_params } else { local_params };
                                    let r = MeshBvh::build(&o.mesh, p)
                                        .map(|b| ObjectBvh::planned(b, params.collapse));
                                    (i, bake, None, r)
                                }
                            };
                            (k, b)
                        })
                        .collect()
                },
            );
            built.sort_unstable_by_key(|&(k, _)| k);
            for (_, (i, asked, baked, r)) in built {
                let bvh = Arc::new(r?);
                if let Some(inst) = asked
                    && baked.is_none()
                    && let Some(x) = self.instances[inst as usize].as_mut()
                {
                    x.bakeable = false;
                }
                let o = self.objects[i].as_mut().expect("listed above");
                report.triangles_rebuilt += o.mesh.len();
                match baked {
                    Some(instance) => {
                        o.baked = Some(Baked { instance, bvh });
                        o.bvh = None;
                    }
                    None => {
                        o.baked = None;
                        o.bvh = Some(bvh);
                    }
                }
                o.dirty = false;
                o.topology_changed = false;
                report.objects_rebuilt.push(i as u32);
            }
            if let Some(merged) = merged {
                let merged = merged?;
                report.triangles_rebuilt += merged.bvh.mesh.len();
                report.merged_rebuilt = true;
                for &id in &merged.members {
                    // Traced from the merged BVH: its own is not kept (built
                    // again should it leave).
                    let o = self.objects[id as usize]
                        .as_mut()
                        .expect("members are live");
                    o.bvh = None;
                    o.dirty = false;
                    o.topology_changed = false;
                }
                self.merged = Some(merged);
            }
            report.objects_merged = members.len();
            report.object_build_ms = t.elapsed().as_secs_f64() * 1e3;

            // Refits of moved objects, in place, in parallel across objects
            // (and within each large one).
            let t = Instant::now();
            let refitted: Vec<(usize, Result<(), Error>)> = self
                .objects
                .par_iter_mut()
                .enumerate()
                .filter_map(|(i, o)| {
                    let o = o.as_mut()?;
                    if !(o.dirty && o.baked.is_none() && o.can_refit()) {
                        return None;
                    }
                    let bvh = Arc::make_mut(o.bvh.as_mut()?);
                    Some((i, bvh.refit(&o.mesh)))
                })
                .collect();
            for (i, r) in refitted {
                r?;
                let o = self.objects[i].as_mut().expect("refitted above");
                report.triangles_refitted += o.mesh.len();
                o.dirty = false;
                report.objects_refitted.push(i as u32);
            }
            report.refit_ms = t.elapsed().as_secs_f64() * 1e3;
            report.objects_reused = self.object_count()
                - report.objects_rebuilt.len()
                - report.objects_refitted.len()
                - members.len();

            let t = Instant::now();
            let mut next_bufs = || bufs.pop().unwrap_or_default();
            // What the objects' pending layouts added to the top levels'
            // time (see `build_top`): counted with the objects.
            let mut finish_ms = 0.0;
            let mut top = |part| {
                self.build_top(mode, next_bufs(), part).map(|(accel, ms)| {
                    finish_ms += ms;
                    accel
                })
            };
            let (fixed, moving_top) = match &moving {
                None => (top(Part::All)?, None),
                Some(m) => {
                    let fixed = match kept_fixed {
                        Some(f) => f,
                        None => top(Part::Fixed(m))?,
                    };
                    let moving = top(Part::Moving(m))?;
                    (fixed, Some(moving))
                }
            };
            report.top_build_ms = t.elapsed().as_secs_f64() * 1e3 - finish_ms;
            report.object_build_ms += finish_ms;
            // One part empty: the other alone, not kept.
            let (top, split) = match moving_top {
                Some(m) if fixed.tree.is_empty() => (m, None),
                Some(m) if m.tree.is_empty() => (fixed, None),
                Some(m) => (fixed, Some(m)),
                None => (fixed, None),
            };
            self.accel = match split {
                Some(moving) => {
                    self.fixed_key = key;
                    Accel::Split(SplitAccel { fixed: top, moving })
                }
                None if top.tree.is_empty() => Accel::Empty,
                None => Accel::TopLevel(top),
            };
            self.report_structure(&mut report);
        }
        self.changed = false;
        self.committed_params = Some(self.params.clone());
        report.total_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(report)
    }

    /// The last commit's structure serves this one as it is: no edit and no
    /// parameter change since it succeeded, and the placements that moved
    /// within the hold are those it was split by (none, if not split).
    /// Why: a caller that commits every frame would otherwise rebuild the
    /// top level of a scene where nothing happened (91 ms for the library
    /// at 2M triangles, session 35).
    fn is_up_to_date(&self) -> bool {
        if self.changed || self.committed_params.as_ref() != Some(&self.params) {
            return false;
        }
        let moving = self.moving_placements();
        match &self.accel {
            Accel::Split(_) => {
                moving.is_some() && self.fixed_key.as_ref().map(|k| &k.moving) == moving.as_ref()
            }
            _ => moving.is_none(),
        }
    }

    /// The report of a commit that found the structure up to date: every
    /// object reused, the top level's statistics as built.
    fn up_to_date_report(&self, mut report: CommitReport, start: Instant) -> CommitReport {
        if report.mode != AccelMode::Flat {
            report.objects_merged = self.merged.as_ref().map_or(0, |m| m.members.len());
            report.objects_reused = self.object_count() - report.objects_merged;
            report.fixed_top_reused = matches!(self.accel, Accel::Split(_));
            self.report_structure(&mut report);
        }
        report.total_ms = start.elapsed().as_secs_f64() * 1e3;
        report
    }

    /// What a report says of the committed two-level structure: the baked
    /// instances, the top level's statistics, and a split scene's moving
    /// part.
    fn report_structure(&self, report: &mut CommitReport) {
        report.instances_baked = self
            .objects
            .iter()
            .filter_map(|o| Some(o.as_ref()?.baked.as_ref()?.instance))
            .collect();
        let (top, moving) = match &self.accel {
            Accel::TopLevel(t) => (t, None),
            Accel::Split(s) => (&s.fixed, Some(&s.moving)),
            Accel::Empty | Accel::Flat(_) => return,
        };
        report.top = Some(top.build_stats.clone());
        if let Some(m) = moving {
            report.top_moving = Some(m.build_stats.clone());
            report.moving_placements = m.build_stats.refs_initial;
        }
    }

    /// A previous commit's top level taken apart: its layout and build
    /// arrays go back to the top-level buffers (unless buffer reuse is
    /// off), its object and instance arrays are returned emptied for the
    /// next top level, and its references to the object BVHs are dropped.
    fn take_apart(
        &mut self,
        mut old: TopLevelAccel,
    ) -> (Vec<Option<Arc<ObjectBvh>>>, Vec<InstanceXf>) {
        if self.no_buffer_reuse {
            return Default::default();
        }
        self.top_scratch.recycle_layout(old.take_layout_buffers());
        self.top_scratch.recycle(old.tree.nodes, old.refs);
        let (mut objects, mut instances) = (old.objects, old.instances);
        objects.clear();
        instances.clear();
        (objects, instances)
    }

    /// The placements that moved within
    /// [`RebraidParams::moving_hold_commits`] commits of this one, when the
    /// scene is re-braided, splitting is on, any did, and their world
    /// triangles are at most [`RebraidParams::moving_split_max_share`] of
    /// the others'.
    fn moving_placements(&self) -> Option<Moving> {
        let hold = self.params.rebraid.moving_hold_commits as u64;
        if self.params.mode != AccelMode::Rebraided || hold == 0 {
            return None;
        }
        let now = self.commits;
        let recent = |moved: u64| moved > 0 && now < moved + hold;
        let objects: Vec<bool> = self
            .objects
            .iter()
            .map(|o| o.as_ref().is_some_and(|o| recent(o.moved)))
            .collect();
        let instances: Vec<bool> = self
            .instances
            .iter()
            .map(|i| {
                i.as_ref()
                    .is_some_and(|i| recent(i.moved) || objects[i.object as usize])
            })
            .collect();
        // World triangles of the moving placements and of the others.
        let (mut moving, mut fixed) = (0u64, 0u64);
        let mut count = |is_moving: bool, o: &Object| {
            let n = o.mesh.len() as u64;
            if is_moving { moving += n } else { fixed += n }
        };
        for (id, o) in self.objects.iter().enumerate() {
            if let Some(o) = o.as_ref().filter(|o| o.placed) {
                count(objects[id], o);
            }
        }
        for (id, i) in self.instances.iter().enumerate() {
            if let Some(o) = i
                .as_ref()
                .and_then(|i| self.objects[i.object as usize].as_ref())
            {
                count(instances[id], o);
            }
        }
        let share = self.params.rebraid.moving_split_max_share as f64;
        (moving > 0 && moving as f64 <= share * fixed as f64)
            .then_some(Moving { objects, instances })
    }

    /// The objects the merged BVH traces (see [`SceneParams::merge_placed`]),
    /// ascending: none unless merging is on and at least two qualify.
    fn merge_members(&self) -> Vec<ObjectId> {
        if !self.params.merge_placed {
            return Vec::new();
        }
        let mut instanced = vec![false; self.objects.len()];
        for inst in self.instances.iter().flatten() {
            instanced[inst.object as usize] = true;
        }
        let members: Vec<ObjectId> = (0..self.objects.len())
            .filter(|&i| {
                self.objects[i].as_ref().is_some_and(|o| {
                    o.placed
                        && !o.mesh.is_empty()
                        && o.policy == UpdatePolicy::Rebuild
                        && !o.edited
                        && !instanced[i]
                })
            })
            .map(|i| i as ObjectId)
            .collect();
        if members.len() < 2 {
            Vec::new()
        } else {
            members
        }
    }

    /// The volume of the scene's box, for [`SceneVolumeLeafLimit`]: the
    /// box of the vertices of every object placed directly and of every
    /// instance's transformed object box. Each object's vertex box is kept
    /// until its mesh changes, so a commit that rebuilds one object reads
    /// the vertices of that one only.
    fn scene_volume(&mut self) -> f32 {
        self.objects
            .par_iter_mut()
            .flatten()
            .filter(|o| o.vertex_bounds.is_none())
            .for_each(|o| {
                // `Aabb::from_points` folds in `Vec3`, three scalar min and
                // max per point: in its place here, 1.1% (nexuiz) and 1.9%
                // (the engine) more instructions per commit (callgrind over
                // `Scene::commit`, `bench --reps 3`); in `Vec3A` for it,
                // its 3-point callers (block boxes) took the engine 1.3%
                // more instead. So this one fold is its own.
                let b = o.mesh.positions.iter().fold(
                    (
                        glam::Vec3A::splat(f32::INFINITY),
                        glam::Vec3A::splat(f32::NEG_INFINITY),
                    ),
                    |(lo, hi), &p| (lo.min(p.into()), hi.max(p.into())),
                );
                o.vertex_bounds = Some(Aabb::new(b.0.into(), b.1.into()));
            });
        let bounds = |id: ObjectId| {
            self.objects[id as usize]
                .as_ref()
                .and_then(|o| o.vertex_bounds)
                .unwrap_or(Aabb::EMPTY)
        };
        let mut scene = Aabb::EMPTY;
        for (i, o) in self.objects.iter().enumerate() {
            if let Some(o) = o
                && o.placed
            {
                scene = scene.union(bounds(i as ObjectId));
            }
        }
        for inst in self.instances.iter().flatten() {
            scene = scene.union(transform_box(
                &inst.xf.object_to_world,
                &bounds(inst.object),
            ));
        }
        // A box too large for an `f32` volume (coordinates near
        // `MAX_COORDINATE`) turns the limit off, as a flat scene does.
        let volume = if scene.is_empty() {
            0.0
        } else {
            scene.volume()
        };
        if volume.is_finite() { volume } else { 0.0 }
    }

    /// Per object slot, the instance to bake it with, if any: the object is
    /// live, not placed itself, has a non-empty mesh and the
    /// [`UpdatePolicy::Rebuild`] policy (a refitted object deforms; its
    /// refits stay in object space), and exactly one live instance places
    /// it, which has never moved (see
    /// [`RebraidParams::bake_single_instances`]).
    fn bake_targets(&self) -> Vec<Option<InstanceId>> {
        let mut target = vec![None; self.objects.len()];
        if !self.params.rebraid.bake_single_instances {
            return target;
        }
        let mut count = vec![0u32; self.objects.len()];
        for (id, inst) in self.instances.iter().enumerate() {
            if let Some(inst) = inst {
                count[inst.object as usize] += 1;
                target[inst.object as usize] = inst.bakeable.then_some(id as u32);
            }
        }
        for (t, (o, n)) in target.iter_mut().zip(self.objects.iter().zip(count)) {
            let eligible = o.as_ref().is_some_and(|o| {
                !o.placed && !o.mesh.is_empty() && o.policy == UpdatePolicy::Rebuild
            });
            if n != 1 || !eligible {
                *t = None;
            }
        }
        target
    }

    /// Initial refs (object roots and instance roots) and the top-level
    /// build, into the given (cleared) arrays and the kept buffers.
    fn build_top(
        &mut self,
        mode: AccelMode,
        (mut objects, mut instances): (Vec<Option<Arc<ObjectBvh>>>, Vec<InstanceXf>),
        part: Part,
    ) -> Result<(TopLevelAccel, f64), Error> {
        // Every object BVH whose wide layout is pending (built in this
        // commit, see `ObjectBvh::planned`; or in an earlier one that
        // failed before its top level), whichever part it belongs to: its
        // collapse taken out to be finished beside the top-level build.
        // (`make_mut` copies only a BVH someone else still holds.)
        let mut pending: Vec<(PendingAt, Arc<ObjectBvh>, WideBvh<8>)> = Vec::new();
        for (id, o) in self.objects.iter_mut().enumerate() {
            let Some(o) = o else { continue };
            let at = [
                (PendingAt::Object(id), o.bvh.as_mut()),
                (PendingAt::Baked(id), o.baked.as_mut().map(|b| &mut b.bvh)),
            ];
            for (at, bvh) in at {
                if let Some(bvh) = bvh
                    && bvh.is_pending()
                    && let Some(plan) = Arc::make_mut(bvh).take_plan()
                {
                    pending.push((at, bvh.clone(), plan));
                }
            }
        }
        // The fixed part holds no object that moved, so that it can be
        // kept while their BVHs are refitted in place.
        objects.extend(self.objects.iter().enumerate().map(|(id, o)| {
            o.as_ref()
                .and_then(|o| o.bvh.clone())
                .filter(|b| !b.mesh.is_empty())
                .filter(|_| !matches!(part, Part::Fixed(m) if m.objects[id]))
        }));
        // The merged BVH in the slot after the objects' (its members never
        // moved: an edit takes an object out), then the baked placements'
        // world-space BVHs, those of this part.
        let merged = self
            .merged
            .as_ref()
            .filter(|_| !matches!(part, Part::Moving(_)))
            .map(|m| {
                objects.push(Some(m.bvh.clone()));
                MergedSlot {
                    slot: (objects.len() - 1) as u32,
                    origins: m.origins.clone(),
                }
            });
        let baked_base = objects.len();
        let mut baked = Vec::new();
        for (id, o) in self.objects.iter().enumerate() {
            if let Some(b) = o.as_ref().and_then(|o| o.baked.as_ref())
                && part.takes(id as u32, b.instance)
            {
                objects.push(Some(b.bvh.clone()));
                baked.push((id as u32, b.instance));
            }
        }
        if objects.len() >= INVALID_ID as usize {
            return Err(Error::TooManyPrimitives(objects.len()));
        }
        instances.extend(
            self.instances
                .iter()
                .map(|i| i.map_or(InstanceXf::new(Affine3A::IDENTITY), |i| i.xf)),
        );
        let mut refs = std::mem::take(&mut self.top_initial);
        refs.clear();
        // The root of the BVH in object slot `slot`, placed as it is.
        let direct_root = |bvh: &ObjectBvh, slot: usize| BuildRef {
            bounds: bvh.mesh.bvh.bounds(),
            object: slot as u32,
            node: 0,
            instance: INVALID_ID,
            prims: bvh.mesh.len() as u32,
            cost: bvh.subtree_cost[0],
        };
        for (id, o) in self.objects.iter().enumerate() {
            if let (Some(o), Some(bvh)) = (o, &objects[id])
                && o.placed
                && part.takes(id as u32, INVALID_ID)
            {
                refs.push(direct_root(bvh, id));
            }
        }
        if let Some(m) = &merged {
            let slot = m.slot as usize;
            refs.push(direct_root(
                objects[slot].as_ref().expect("pushed above"),
                slot,
            ));
        }
        for (k, &(_, instance)) in baked.iter().enumerate() {
            let slot = baked_base + k;
            refs.push(direct_root(
                objects[slot].as_ref().expect("pushed above"),
                slot,
            ));
            debug_assert!(self.instances[instance as usize].is_some());
        }
        for (id, inst) in self.instances.iter().enumerate() {
            let is_baked = |inst: &Instance| {
                self.objects[inst.object as usize]
                    .as_ref()
                    .and_then(|o| o.baked.as_ref())
                    .is_some_and(|b| b.instance == id as u32)
            };
            if let Some(inst) = inst
                && !is_baked(inst)
                && part.takes(inst.object, id as u32)
                && let Some(bvh) = &objects[inst.object as usize]
            {
                refs.push(BuildRef {
                    bounds: inst.xf.world_box(&bvh.mesh.bvh.bounds()),
                    object: inst.object,
                    node: 0,
                    instance: id as u32,
                    prims: bvh.mesh.len() as u32,
                    cost: bvh.subtree_cost[0],
                });
            }
        }
        let params = match mode {
            AccelMode::Rebraided => self.params.rebraid.clone(),
            _ => RebraidParams {
                open: false,
                ..self.params.rebraid.clone()
            },
        };
        let src = RefSources {
            objects: &objects,
            instances: &instances,
        };
        let mut fresh = TopLevelScratch::default();
        let buffers = if self.no_buffer_reuse {
            &mut fresh
        } else {
            &mut self.top_scratch
        };
        // The top level and the pending layouts side by side: the top
        // level's build is mostly serial (its binned build splits in
        // parallel only above `parallel_threshold` refs, its reinsertion
        // applies moves in order), and the packing and occlusion order of
        // the objects fill the threads it leaves idle.
        let join_start = Instant::now();
        let ((built, top_ms), finished) = rayon::join(
            || {
                let t = Instant::now();
                let built = build_top_level_with(&refs, src, &params, buffers);
                (built, t.elapsed().as_secs_f64() * 1e3)
            },
            || {
                pending
                    .into_par_iter()
                    .with_max_len(1)
                    .map(|(at, bvh, plan)| (at, ObjectBvh::finish_plan(&bvh.mesh, plan)))
                    .collect::<Vec<_>>()
            },
        );
        // What the layouts added to the top level's own time (the whole
        // of them at one thread): the objects' share of the commit.
        let finish_ms = (join_start.elapsed().as_secs_f64() * 1e3 - top_ms).max(0.0);
        // Put the layouts in: the slots of this part's `objects` let go of
        // their BVHs first, so that each is held once and changed in place.
        for (at, layout) in finished {
            let (id, slot) = match at {
                PendingAt::Object(id) => (id, Some(id)),
                PendingAt::Baked(id) => {
                    let k = baked.iter().position(|&(o, _)| o as usize == id);
                    (id, k.map(|k| baked_base + k))
                }
            };
            let held = slot.and_then(|k| objects[k].take()).is_some();
            let o = self.objects[id].as_mut().expect("pending BVHs are live");
            let bvh = match at {
                PendingAt::Object(_) => o.bvh.as_mut(),
                PendingAt::Baked(_) => o.baked.as_mut().map(|b| &mut b.bvh),
            }
            .expect("pending BVHs are in place");
            Arc::make_mut(bvh).install(layout);
            if let (Some(k), true) = (slot, held) {
                objects[k] = Some(bvh.clone());
            }
        }
        let layout_buffers = buffers.take_layout();
        if !self.no_buffer_reuse {
            self.top_initial = refs;
        }
        let (tree, top_refs, build_stats) = built?;
        // The merged BVH grafted whole up to its size limit.
        let graft_whole = merged
            .as_ref()
            .filter(|m| {
                let prims = objects[m.slot as usize]
                    .as_ref()
                    .map_or(0, |o| o.mesh.len());
                params.open && prims <= params.graft_merged_max_prims as usize
            })
            .map(|m| m.slot);
        let accel = TopLevelAccel::new(
            tree,
            top_refs,
            objects,
            instances,
            build_stats,
            TopLevelLayout {
                kernel: self.params.kernel.unwrap_or_else(Kernel::best),
                pull_entry_nodes: params.open && params.pull_entry_nodes,
                inline_leaf_blocks: params.inline_leaf_blocks,
                inline_instanced_leaves: params.inline_instanced_leaves,
                graft_max_prims: if params.open {
                    params.graft_max_prims
                } else {
                    0
                },
                graft_budget: params.graft_budget,
                collapse: params.collapse,
                graft_share_per_prim: params.graft_share_per_prim,
                graft_whole,
            },
            layout_buffers,
        )
        .with_baked(baked)?
        .with_merged(merged)?;
        #[cfg(debug_assertions)]
        if let Err(e) = accel.validate() {
            panic!("top-level builder produced an invalid tree: {e}");
        }
        Ok((accel, finish_ms))
    }

    /// Closest hit along the ray (no hit before the first commit).
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        self.intersect_counted(ray, &mut TraversalCounters::default())
    }

    /// Closest hit, counting the nodes visited (for heat maps).
    pub fn intersect_counted(&self, ray: &Ray, counters: &mut TraversalCounters) -> Option<Hit> {
        match &self.accel {
            Accel::Empty => None,
            Accel::Flat(f) => f.intersect_counted(ray, counters),
            Accel::TopLevel(t) => t.intersect_counted(ray, counters),
            Accel::Split(s) => s.intersect_counted(ray, counters),
        }
    }

    /// True when anything is hit within the ray's interval.
    pub fn occluded(&self, ray: &Ray) -> bool {
        self.occluded_counted(ray, &mut TraversalCounters::default())
    }

    /// Occlusion, counting the nodes and leaves visited (see
    /// [`Scene::intersect_counted`]).
    pub fn occluded_counted(&self, ray: &Ray, counters: &mut TraversalCounters) -> bool {
        match &self.accel {
            Accel::Empty => false,
            Accel::Flat(f) => f.occluded_counted(ray, counters),
            Accel::TopLevel(t) => t.occluded_counted(ray, counters),
            Accel::Split(s) => s.occluded_counted(ray, counters),
        }
    }

    /// Closest hits of many rays, in parallel: `out[i]` is what
    /// [`Scene::intersect`] answers for `rays[i]`, exact ties included.
    ///
    /// With the AVX2 kernel, runs of neighbouring rays with close
    /// directions (camera rays in pixel order) are traced in packets of
    /// eight, which is faster; the answers do not depend on it. Panics when
    /// the lengths differ.
    pub fn intersect_batch(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        crate::ray::par_query_runs(rays, out, |rays, out| match &self.accel {
            Accel::Empty => out.fill(None),
            Accel::Flat(f) => f.intersect_many(rays, out),
            Accel::TopLevel(t) => t.intersect_many(rays, out),
            Accel::Split(s) => s.intersect_many(rays, out),
        });
    }

    /// Occlusion of many rays, in parallel: `out[i]` is what
    /// [`Scene::occluded`] answers for `rays[i]`. With the AVX2 kernel,
    /// rays of one direction octant are traced in packets of eight
    /// (coherent ones, such as shadow rays towards one light, gain most).
    /// Panics when the lengths differ.
    pub fn occluded_batch(&self, rays: &[Ray], out: &mut [bool]) {
        crate::ray::par_query_runs(rays, out, |rays, out| match &self.accel {
            Accel::Empty => out.fill(false),
            Accel::Flat(f) => f.occluded_many(rays, out),
            Accel::TopLevel(t) => t.occluded_many(rays, out),
            Accel::Split(s) => s.occluded_many(rays, out),
        });
    }

    /// Statistics of the committed structure.
    pub fn stats(&self) -> SceneStats {
        let mut s = SceneStats {
            mode: self.params.mode,
            objects: self.object_count(),
            instances: self.instance_count(),
            world_triangles: self.world_triangles(),
            ..Default::default()
        };
        match &self.accel {
            Accel::Empty => {}
            Accel::Flat(f) => {
                let st = f.bvh.stats();
                s.sah_cost = st.sah_cost;
                s.wide_sah_cost = f.wide_sah_cost();
                s.bytes = st.bytes
                    + std::mem::size_of_val(f.origins.as_slice())
                    + f.wide.as_ref().map_or(0, |w| w.bytes());
                s.flat = Some(st);
            }
            Accel::TopLevel(t) => {
                s.sah_cost = t.sah_cost(SahCosts::default());
                s.wide_sah_cost = t.wide_sah_cost();
                s.bytes = object_bytes(&[t]) + top_bytes(t);
                s.top_nodes = t.tree.nodes.len();
                s.top_depth = t.tree.stats(SahCosts::default()).max_depth;
                s.top = Some(t.build_stats.clone());
            }
            Accel::Split(sp) => {
                // The SAH figures of the two walks a ray makes, each
                // weighted by the chance that a ray through the scene's
                // box enters its part's box.
                let (f, m) = (&sp.fixed, &sp.moving);
                let area = |t: &TopLevelAccel| t.tree.nodes.first().map(|n| n.bounds());
                let (fa, ma) = (area(f).unwrap_or_default(), area(m).unwrap_or_default());
                let (fa, ma, all) = (
                    fa.half_area() as f64,
                    ma.half_area() as f64,
                    fa.union(ma).half_area() as f64,
                );
                let weigh = |x: f64, a: f64| if all > 0.0 { x * a / all } else { 0.0 };
                s.sah_cost = weigh(f.sah_cost(SahCosts::default()), fa)
                    + weigh(m.sah_cost(SahCosts::default()), ma);
                s.wide_sah_cost = weigh(f.wide_sah_cost(), fa) + weigh(m.wide_sah_cost(), ma);
                s.bytes = object_bytes(&[f, m]) + top_bytes(f) + top_bytes(m);
                s.top_nodes = f.tree.nodes.len() + m.tree.nodes.len();
                s.top_depth = f
                    .tree
                    .stats(SahCosts::default())
                    .max_depth
                    .max(m.tree.stats(SahCosts::default()).max_depth);
                s.top = Some(f.build_stats.clone());
            }
        }
        s
    }
}

/// Bytes of the object BVHs the top levels hold, each counted once.
fn object_bytes(tops: &[&TopLevelAccel]) -> usize {
    let mut seen = std::collections::HashSet::new();
    tops.iter()
        .flat_map(|t| t.objects.iter().flatten())
        .filter(|o| seen.insert(Arc::as_ptr(o)))
        .map(|o| {
            o.mesh.stats().bytes
                + std::mem::size_of_val(o.subtree_prims.as_slice())
                + std::mem::size_of_val(o.subtree_cost.as_slice())
                + std::mem::size_of_val(o.wide_of.as_slice())
                + o.wide.as_ref().map_or(0, |w| w.bytes())
        })
        .sum()
}

/// Bytes of a top level's own arrays and its wide layout.
fn top_bytes(t: &TopLevelAccel) -> usize {
    t.top_bytes() + t.wide.as_ref().map_or(0, |w| w.bytes())
}

/// Statistics of a committed scene.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SceneStats {
    pub mode: AccelMode,
    pub objects: usize,
    pub instances: usize,
    pub world_triangles: usize,
    /// SAH cost of the tree as traversed (see `rebraiding.md`).
    pub sah_cost: f64,
    /// Embree's SAH statistic of the wide layout as traversed (nodes'
    /// half areas plus leaves' times their `Triangle4` blocks, over the
    /// root's; Embree prints its own with `verbose=2`); 0 without one.
    pub wide_sah_cost: f64,
    /// Bytes of every node, index and triangle array of the structure.
    pub bytes: usize,
    pub top_nodes: usize,
    /// Depth of the top-level tree (root = 1).
    pub top_depth: u32,
    pub top: Option<TopLevelBuildStats>,
    pub flat: Option<BvhStats>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// The twelve triangles of the unit cube moved by `at`.
    fn cube(at: Vec3) -> TriangleMesh {
        let tris = crate::bvh::test_trees::box_faces(at, Vec3::ONE);
        TriangleMesh::from_triangles(&tris).unwrap()
    }

    #[test]
    fn scene_volume_covers_placed_objects_and_instances() {
        let mut scene = Scene::new();
        assert_eq!(scene.scene_volume(), 0.0);
        let placed = scene.add_object(cube(Vec3::ZERO)).unwrap();
        assert_eq!(scene.scene_volume(), 1.0);
        // A prototype counts through its instances only.
        let proto = scene.add_prototype(cube(Vec3::ZERO)).unwrap();
        assert_eq!(scene.scene_volume(), 1.0);
        let inst = scene
            .add_instance(proto, Affine3A::from_translation(Vec3::new(9.0, 0.0, 0.0)))
            .unwrap();
        assert!((scene.scene_volume() - 10.0).abs() < 1e-4);
        // Moved vertices and transforms are seen at the next call.
        let moved: Vec<Vec3> = cube(Vec3::new(0.0, 3.0, 0.0)).positions;
        scene.set_vertices(placed, &moved).unwrap();
        assert!((scene.scene_volume() - 40.0).abs() < 1e-3);
        scene
            .set_instance_transform(inst, Affine3A::from_translation(Vec3::new(4.0, 0.0, 0.0)))
            .unwrap();
        assert!((scene.scene_volume() - 20.0).abs() < 1e-3);
        scene.remove_instance(inst).unwrap();
        assert_eq!(scene.scene_volume(), 1.0);
        // Beyond an `f32` volume: off, and the scene still commits.
        let far = crate::mesh::MAX_COORDINATE * 0.9;
        scene.add_object(cube(Vec3::splat(far))).unwrap();
        scene.add_object(cube(Vec3::splat(-far))).unwrap();
        assert_eq!(scene.scene_volume(), 0.0);
        for mode in AccelMode::ALL {
            scene.set_mode(mode);
            scene.commit().unwrap();
        }
    }
}
