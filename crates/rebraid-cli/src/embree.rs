//! The Embree 3.13 baseline (feature `embree`): a [`rebraid::SceneDesc`] built
//! into Embree scenes and queried with Embree's single-ray API
//! (`rtcIntersect1` / `rtcOccluded1`), as `shared/docs/anchors.md` measured it.
//!
//! Linking: through the `embree3` 0.4 crate, whose build script emits
//! `cargo:rustc-link-lib=embree3` (plus `-L $EMBREE_DIR/lib` when that
//! variable is set). Debian's `libembree-dev` puts `libembree3.so` in
//! `/usr/lib/x86_64-linux-gnu`, on the linker's and the loader's default
//! paths, so nothing needs to be set (`.ci/install-embree.sh` installs it).
//!
//! Two modes:
//! - [`EmbreeMode::Flat`]: every world triangle in one triangle geometry
//!   (instances flattened into transformed copies), scene build quality
//!   MEDIUM.
//! - [`EmbreeMode::TwoLevel`]: one triangle geometry per placed object in the
//!   top scene, and each instanced object in its own scene (build quality
//!   MEDIUM), placed by one `RTC_GEOMETRY_TYPE_INSTANCE` geometry per instance;
//!   top scene build quality LOW, which selects Embree's re-braiding two-level
//!   builder.
//!
//! Each [`EmbreeScene`] has its own device, configured with `threads=N` where
//! N is the current rayon pool's thread count, so that a single-threaded rayon
//! pool gives a single-threaded Embree build too.

use std::sync::Arc;
use std::sync::atomic::{AtomicIsize, Ordering};
use std::time::Instant;

use anyhow::{Context, bail};
use embree3::{
    BufferUsage, BuildQuality, Config, Device, Format, Geometry, GeometryKind, IntersectContext,
    Isa, RayHit, Scene,
};
use glam::{Affine3A, Mat4, Vec3};
use rebraid::{INVALID_ID, Ray, SceneDesc, TriangleMesh};

use crate::bench::{EmbreeFlags, EmbreeIsa};

/// How a [`SceneDesc`] is laid out in Embree.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum EmbreeMode {
    /// One geometry of all world triangles, build quality MEDIUM.
    Flat,
    /// Placed objects as geometries and instanced objects as instanced
    /// scenes, top scene build quality LOW (Embree's re-braiding builder).
    TwoLevel,
}

impl EmbreeMode {
    pub const ALL: [EmbreeMode; 2] = [EmbreeMode::Flat, EmbreeMode::TwoLevel];

    /// `embree-flat` or `embree-two-level`.
    pub fn name(&self) -> &'static str {
        match self {
            EmbreeMode::Flat => "embree-flat",
            EmbreeMode::TwoLevel => "embree-two-level",
        }
    }
}

/// The closest hit of a ray, in the ids of the [`SceneDesc`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EmbreeHit {
    pub t: f32,
    /// Barycentrics as in [`rebraid::Hit`]: `(1 - u - v) * v0 + u * v1 + v * v2`.
    pub u: f32,
    pub v: f32,
    /// Triangle index in its object's index buffer.
    pub prim_id: u32,
    /// Index into `desc.objects`.
    pub object_id: u32,
    /// Index into `desc.instances`, or [`INVALID_ID`] for a placed object.
    pub instance_id: u32,
}

/// Where a run of the flat geometry's triangles comes from.
#[derive(Clone, Copy, Debug)]
struct FlatRun {
    /// First triangle of the run in the flat geometry.
    first_prim: u32,
    object_id: u32,
    instance_id: u32,
}

#[derive(Debug)]
enum IdMap {
    /// Runs sorted by `first_prim`, one per placed object or instance.
    Flat(Vec<FlatRun>),
    /// Top-level geometry id -> (object id, instance id). Inside an instanced
    /// scene the object is the scene's only geometry (id 0).
    TwoLevel(Vec<(u32, u32)>),
}

/// A [`SceneDesc`] committed into Embree. Every Embree object it creates is
/// released when it drops.
pub struct EmbreeScene {
    // Field order is drop order: the top scene first, then the instanced
    // scenes, then the device (Embree reference-counts them anyway).
    top: Scene<'static>,
    /// Scenes of instanced objects (two-level mode), kept alive here too.
    _instanced: Vec<Scene<'static>>,
    ids: IdMap,
    mode: EmbreeMode,
    /// Bytes Embree reports as allocated on this scene's device.
    memory: Arc<AtomicIsize>,
    device: Device,
}

impl std::fmt::Debug for EmbreeScene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EmbreeScene")
            .field("mode", &self.mode)
            .field("bytes", &self.bytes())
            .finish_non_exhaustive()
    }
}

/// Embree's scene flags for `flags` (set before the scene's first commit).
fn set_flags(scene: &mut Scene<'_>, flags: EmbreeFlags) {
    if flags == EmbreeFlags::Robust {
        scene.set_flags(embree3::SceneFlags::ROBUST);
    }
}

/// A device whose thread count follows the current rayon pool, with a
/// memory monitor counting its allocations.
fn new_device(max_isa: EmbreeIsa) -> anyhow::Result<(Device, Arc<AtomicIsize>)> {
    let config = Config {
        threads: rayon::current_num_threads() as u32,
        max_isa: match max_isa {
            EmbreeIsa::Auto => Config::default().max_isa,
            EmbreeIsa::Avx2 => Isa::Avx2,
            EmbreeIsa::Sse42 => Isa::Sse4_2,
        },
        // Embree's own log level (2 prints each BVH's statistics after its
        // build: nodes, fill, SAH), for comparing its trees with ours.
        verbose: std::env::var("REBRAID_EMBREE_VERBOSE")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(0),
        ..Config::default()
    };
    let device =
        Device::with_config(config).map_err(|e| anyhow::anyhow!("rtcNewDevice failed: {e:?}"))?;
    let memory = Arc::new(AtomicIsize::new(0));
    let m = Arc::clone(&memory);
    // Embree calls this before each allocation (bytes > 0, post = false) and
    // after each deallocation (bytes < 0), and undoes a failed allocation with
    // a negative call: the running sum is the memory in use.
    device.set_memory_monitor_function(move |bytes, _post| {
        m.fetch_add(bytes, Ordering::Relaxed);
        true
    });
    Ok((device, memory))
}

/// Fail with Embree's pending error code, if any.
fn check(device: &Device, what: &str) -> anyhow::Result<()> {
    let e = device.get_error();
    if e != embree3::Error::NONE {
        bail!("Embree error after {what}: {e:?}");
    }
    Ok(())
}

/// A committed triangle geometry (Embree-owned buffers, copied from the
/// slices: the geometry borrows nothing).
fn triangle_geometry(
    device: &Device,
    positions: &[Vec3],
    indices: &[[u32; 3]],
) -> anyhow::Result<Geometry<'static>> {
    let mut g = device
        .create_geometry(GeometryKind::TRIANGLE)
        .map_err(|e| anyhow::anyhow!("rtcNewGeometry(TRIANGLE) failed: {e:?}"))?;
    g.set_new_buffer::<[f32; 3]>(BufferUsage::VERTEX, 0, Format::FLOAT3, 12, positions.len())
        .map_err(|e| anyhow::anyhow!("vertex buffer of {} vertices: {e:?}", positions.len()))?
        .iter_mut()
        .zip(positions)
        .for_each(|(d, p)| *d = p.to_array());
    g.set_new_buffer::<[u32; 3]>(BufferUsage::INDEX, 0, Format::UINT3, 12, indices.len())
        .map_err(|e| anyhow::anyhow!("index buffer of {} triangles: {e:?}", indices.len()))?
        .copy_from_slice(indices);
    Ok(g.commit())
}

/// Column-major 4x4 of an affine transform, as `rtcSetGeometryTransform` takes it.
fn column_major(xf: &Affine3A) -> [f32; 16] {
    Mat4::from(*xf).to_cols_array()
}

impl EmbreeScene {
    /// Build the description in the given mode. Returns the scene and the
    /// build time in milliseconds: geometry set-up (buffer copies, flattening)
    /// plus every scene commit, not the device's creation.
    ///
    /// Flat: all triangles in one geometry (instances flattened: transformed
    /// copies), scene build quality MEDIUM.
    /// TwoLevel: one triangle geometry per placed object in the top scene,
    /// and each instanced object as its own scene instanced by an
    /// `RTC_GEOMETRY_TYPE_INSTANCE` geometry with its transform; top scene
    /// build quality LOW (Embree's own re-braiding two-level builder).
    ///
    /// Objects without triangles are skipped (they cannot be hit).
    pub fn build(desc: &SceneDesc, mode: EmbreeMode) -> anyhow::Result<(EmbreeScene, f64)> {
        Self::build_with_isa(desc, mode, EmbreeIsa::Auto)
    }

    /// [`EmbreeScene::build`] on a device whose kernels are capped at
    /// `max_isa`.
    pub fn build_with_isa(
        desc: &SceneDesc,
        mode: EmbreeMode,
        max_isa: EmbreeIsa,
    ) -> anyhow::Result<(EmbreeScene, f64)> {
        Self::build_with(desc, mode, max_isa, EmbreeFlags::Default)
    }

    /// [`EmbreeScene::build_with_isa`] with `flags` on every scene it makes
    /// (the top scene and, in the two-level mode, each instanced one).
    pub fn build_with(
        desc: &SceneDesc,
        mode: EmbreeMode,
        max_isa: EmbreeIsa,
        flags: EmbreeFlags,
    ) -> anyhow::Result<(EmbreeScene, f64)> {
        desc.validate().context("invalid scene description")?;
        let (device, memory) = new_device(max_isa)?;
        let start = Instant::now();
        let mut top = device
            .create_scene()
            .map_err(|e| anyhow::anyhow!("rtcNewScene failed: {e:?}"))?;
        set_flags(&mut top, flags);
        let mut instanced = Vec::new();
        let ids = match mode {
            EmbreeMode::Flat => {
                top.set_build_quality(BuildQuality::MEDIUM);
                IdMap::Flat(Self::build_flat(&device, &mut top, desc)?)
            }
            EmbreeMode::TwoLevel => {
                top.set_build_quality(BuildQuality::LOW);
                IdMap::TwoLevel(Self::build_two_level(
                    &device,
                    &mut top,
                    &mut instanced,
                    desc,
                    flags,
                )?)
            }
        };
        top.commit();
        check(&device, "rtcCommitScene")?;
        let ms = start.elapsed().as_secs_f64() * 1e3;
        Ok((
            EmbreeScene {
                top,
                _instanced: instanced,
                ids,
                mode,
                memory,
                device,
            },
            ms,
        ))
    }

    fn build_flat(
        device: &Device,
        top: &mut Scene<'static>,
        desc: &SceneDesc,
    ) -> anyhow::Result<Vec<FlatRun>> {
        // Placed objects first, then instances, each as one run of triangles.
        let mut sources: Vec<(u32, u32, Option<&Affine3A>)> = Vec::new();
        for (i, o) in desc.objects.iter().enumerate() {
            if o.placed && !o.mesh.is_empty() {
                sources.push((i as u32, INVALID_ID, None));
            }
        }
        for (i, inst) in desc.instances.iter().enumerate() {
            if !desc.objects[inst.object as usize].mesh.is_empty() {
                sources.push((inst.object, i as u32, Some(&inst.transform)));
            }
        }
        let mut runs = Vec::with_capacity(sources.len());
        let (mut nv, mut nt) = (0usize, 0usize);
        for &(o, inst, _) in &sources {
            let m = &desc.objects[o as usize].mesh;
            if nt + m.len() > u32::MAX as usize || nv + m.positions.len() > u32::MAX as usize {
                bail!("the flattened scene has more than 2^32 triangles or vertices");
            }
            runs.push(FlatRun {
                first_prim: nt as u32,
                object_id: o,
                instance_id: inst,
            });
            nv += m.positions.len();
            nt += m.len();
        }
        if nt == 0 {
            return Ok(runs);
        }
        let mut positions = Vec::with_capacity(nv);
        let mut indices = Vec::with_capacity(nt);
        for &(o, _, xf) in &sources {
            let m: &TriangleMesh = &desc.objects[o as usize].mesh;
            let base = positions.len() as u32;
            match xf {
                None => positions.extend_from_slice(&m.positions),
                Some(xf) => positions.extend(m.positions.iter().map(|&p| xf.transform_point3(p))),
            }
            indices.extend(m.indices.iter().map(|t| t.map(|v| v + base)));
        }
        let g = triangle_geometry(device, &positions, &indices)?;
        top.attach_geometry(&g);
        check(device, "building the flat geometry")?;
        Ok(runs)
    }

    fn build_two_level(
        device: &Device,
        top: &mut Scene<'static>,
        instanced: &mut Vec<Scene<'static>>,
        desc: &SceneDesc,
        flags: EmbreeFlags,
    ) -> anyhow::Result<Vec<(u32, u32)>> {
        let mut ids = Vec::new();
        for (i, o) in desc.objects.iter().enumerate() {
            if o.placed && !o.mesh.is_empty() {
                let g = triangle_geometry(device, &o.mesh.positions, &o.mesh.indices)?;
                let id = top.attach_geometry(&g) as usize;
                debug_assert_eq!(id, ids.len(), "Embree assigns geometry ids in order");
                ids.push((i as u32, INVALID_ID));
            }
        }
        // One scene per instanced object, shared by all its instances.
        let mut object_scene: Vec<Option<usize>> = vec![None; desc.objects.len()];
        for (i, inst) in desc.instances.iter().enumerate() {
            let o = inst.object as usize;
            let mesh = &desc.objects[o].mesh;
            if mesh.is_empty() {
                continue;
            }
            let s = match object_scene[o] {
                Some(s) => s,
                None => {
                    let mut scene = device
                        .create_scene()
                        .map_err(|e| anyhow::anyhow!("rtcNewScene failed: {e:?}"))?;
                    scene.set_build_quality(BuildQuality::MEDIUM);
                    set_flags(&mut scene, flags);
                    let g = triangle_geometry(device, &mesh.positions, &mesh.indices)?;
                    scene.attach_geometry(&g);
                    scene.commit();
                    check(device, "committing an instanced scene")?;
                    instanced.push(scene);
                    object_scene[o] = Some(instanced.len() - 1);
                    instanced.len() - 1
                }
            };
            let mut g = device
                .create_geometry(GeometryKind::INSTANCE)
                .map_err(|e| anyhow::anyhow!("rtcNewGeometry(INSTANCE) failed: {e:?}"))?;
            g.set_instanced_scene(&instanced[s]);
            g.set_transform(0, &column_major(&inst.transform));
            let g = g.commit();
            let id = top.attach_geometry(&g) as usize;
            debug_assert_eq!(id, ids.len(), "Embree assigns geometry ids in order");
            ids.push((inst.object, i as u32));
        }
        check(device, "building the two-level scene")?;
        Ok(ids)
    }

    pub fn mode(&self) -> EmbreeMode {
        self.mode
    }

    /// Embree's ray for ours, or `None` for a ray that hits nothing (see
    /// [`rebraid::Ray`]). Embree wants `0 <= tnear`: a negative `t_min` is
    /// clamped to 0.
    #[inline]
    fn embree_ray(ray: &Ray) -> Option<embree3::Ray> {
        if !ray.is_valid() {
            return None;
        }
        Some(embree3::Ray::segment(
            ray.origin.to_array(),
            ray.dir.to_array(),
            ray.t_min.max(0.0),
            ray.t_max,
        ))
    }

    /// Closest hit (`rtcIntersect1`).
    pub fn intersect(&self, ray: &Ray) -> Option<EmbreeHit> {
        let r = Self::embree_ray(ray)?;
        let mut ctx = IntersectContext::incoherent();
        let mut rh = RayHit::from_ray(r);
        self.top.intersect(&mut ctx, &mut rh);
        self.hit_of(&rh)
    }

    /// Our hit record of Embree's answer (`None` for a miss).
    fn hit_of(&self, rh: &RayHit) -> Option<EmbreeHit> {
        if !rh.hit.is_valid() {
            return None;
        }
        let (prim_id, object_id, instance_id) = match &self.ids {
            IdMap::Flat(runs) => {
                let p = rh.hit.primID;
                let k = runs.partition_point(|r| r.first_prim <= p) - 1;
                let run = runs[k];
                (p - run.first_prim, run.object_id, run.instance_id)
            }
            IdMap::TwoLevel(ids) => {
                let inst = rh.hit.instID[0];
                let top_id = if inst != embree3::INVALID_ID {
                    inst
                } else {
                    rh.hit.geomID
                };
                let (o, i) = ids[top_id as usize];
                (rh.hit.primID, o, i)
            }
        };
        Some(EmbreeHit {
            t: rh.ray.tfar,
            u: rh.hit.u,
            v: rh.hit.v,
            prim_id,
            object_id,
            instance_id,
        })
    }

    /// True when anything is hit within the ray's interval (`rtcOccluded1`).
    pub fn occluded(&self, ray: &Ray) -> bool {
        let Some(mut r) = Self::embree_ray(ray) else {
            return false;
        };
        let mut ctx = IntersectContext::incoherent();
        self.top.occluded(&mut ctx, &mut r)
    }

    /// An Embree ray for a run of a stream: `ray` converted, or an inactive
    /// ray (`tnear > tfar`, which Embree skips) for a ray that hits nothing.
    fn stream_ray(ray: &Ray) -> embree3::Ray {
        Self::embree_ray(ray)
            .unwrap_or_else(|| embree3::Ray::segment([0.0; 3], [1.0, 0.0, 0.0], 1.0, 0.0))
    }

    /// Closest hits of many rays, in parallel on the rayon pool: one
    /// `rtcIntersect1` per ray, or with `stream` one `rtcIntersect1M` per
    /// run of rays (Embree's stream API, which pays its API entry once per
    /// run, as our batch queries pay their kernel dispatch).
    ///
    /// Never inlined, as `Scene::intersect_batch` is not: the timed region
    /// of each side is one function that `tools/callgrind-compare.sh`
    /// counts, ray and answer arrays included on both sides.
    #[inline(never)]
    pub fn intersect_batch_with(&self, rays: &[Ray], out: &mut [Option<EmbreeHit>], stream: bool) {
        if !stream {
            return rebraid::ray::par_query(rays, out, |r| self.intersect(r));
        }
        rebraid::ray::par_query_runs(rays, out, |rays, out| {
            let mut ctx = IntersectContext::incoherent();
            let mut rh: Vec<RayHit> = rays
                .iter()
                .map(|r| RayHit::from_ray(Self::stream_ray(r)))
                .collect();
            self.top.intersect_stream_aos(&mut ctx, &mut rh);
            for (o, h) in out.iter_mut().zip(&rh) {
                *o = self.hit_of(h);
            }
        });
    }

    /// Occlusion of many rays, in parallel on the rayon pool (see
    /// [`EmbreeScene::intersect_batch_with`]; `rtcOccluded1M` with
    /// `stream`). Never inlined (see `intersect_batch_with`).
    #[inline(never)]
    pub fn occluded_batch_with(&self, rays: &[Ray], out: &mut [bool], stream: bool) {
        if !stream {
            return rebraid::ray::par_query(rays, out, |r| self.occluded(r));
        }
        rebraid::ray::par_query_runs(rays, out, |rays, out| {
            let mut ctx = IntersectContext::incoherent();
            let mut er: Vec<embree3::Ray> = rays.iter().map(Self::stream_ray).collect();
            self.top.occluded_stream_aos(&mut ctx, &mut er);
            // An occluded ray comes back with `tfar = -inf`.
            for (o, r) in out.iter_mut().zip(&er) {
                *o = r.tfar == f32::NEG_INFINITY;
            }
        });
    }

    /// Closest hits of many rays, one `rtcIntersect1` per ray.
    pub fn intersect_batch(&self, rays: &[Ray], out: &mut [Option<EmbreeHit>]) {
        self.intersect_batch_with(rays, out, false)
    }

    /// Occlusion of many rays, one `rtcOccluded1` per ray.
    pub fn occluded_batch(&self, rays: &[Ray], out: &mut [bool]) {
        self.occluded_batch_with(rays, out, false)
    }

    /// Bytes Embree has allocated on this scene's device and not freed
    /// (geometry buffers and BVHs), as its memory monitor reports them.
    pub fn bytes(&self) -> usize {
        self.memory.load(Ordering::Relaxed).max(0) as usize
    }

    /// The Embree device of this scene.
    pub fn device(&self) -> &Device {
        &self.device
    }
}
