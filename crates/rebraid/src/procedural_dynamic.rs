//! Procedural animated objects to move through a static scene (the project's
//! own generated data, deterministic like [`crate::procedural`]).
//!
//! - [`DynamicKind::Robot`]: an articulated robot-like figure, thirteen
//!   limbs (pelvis, torso, head, upper and lower arms, thighs, shins, feet),
//!   each a finely tessellated superellipsoid (boxy or cylindrical), posed by
//!   forward kinematics of a walk cycle and walking along a path. All limbs
//!   are one mesh whose vertices move every frame (the triangles stay), so a
//!   commit can refit its BVH.
//! - [`DynamicKind::Deforming`]: a wobbling tessellated torus gliding and
//!   spinning along the path: a [`KeyframedMesh`] (one wobble cycle in object
//!   space) placed by an [`AnimatedTransform`] (the glide), both interpolated
//!   per frame.
//!
//! Animation time `t` runs from 0 (start of the path) to 1 (end); outside,
//! the pose is clamped. [`DynamicParams::in_box`] places the path inside a
//! static scene's box.

use glam::{Affine3A, Quat, Vec3};
use rayon::prelude::*;

use crate::animation::{AnimatedTransform, KeyframedMesh};
use crate::{Aabb, Error, TriangleMesh};

/// Which animated object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DynamicKind {
    /// An articulated figure walking along the path.
    Robot,
    /// A wobbling torus gliding along the path.
    Deforming,
}

/// Where and how large the animated object is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DynamicParams {
    /// Path on the floor, from `start` (t = 0) to `end` (t = 1).
    pub start: Vec3,
    pub end: Vec3,
    /// Unit up vector (the object stands on the floor along it).
    pub up: Vec3,
    /// Height of the object in world units.
    pub height: f32,
    /// Approximate number of triangles.
    pub triangles: usize,
}

impl DynamicParams {
    /// A path inside a static scene's box: on the floor (the box's bottom
    /// plus 3.4% of its height, the top of the library's floor slab), along
    /// the longest horizontal axis from 25% to 80% of the box, at 21% across
    /// it, just beside the default camera of the tool (which sits at 20% of
    /// the box on every axis, looking at the centre), so the object walks
    /// away from the camera inside its view. Height: 60% of the box's up
    /// extent, at most 30% of its shorter horizontal extent.
    pub fn in_box(bounds: &Aabb, up: Vec3, triangles: usize) -> Self {
        let up = if up.length_squared() > 0.0 {
            up.normalize()
        } else {
            Vec3::Y
        };
        let a = up.abs();
        let u = if a.x >= a.y && a.x >= a.z {
            0
        } else if a.y >= a.z {
            1
        } else {
            2
        };
        let (a, b): (usize, usize) = ((u + 1) % 3, (u + 2) % 3);
        let e = bounds.extent();
        let (long, lat) = if e[a] >= e[b] { (a, b) } else { (b, a) };
        let at = |fl: f32, fa: f32| {
            let mut p = bounds.min;
            p[long] += fl * e[long];
            p[lat] += fa * e[lat];
            p[u] += 0.034 * e[u];
            p
        };
        let height = (0.6f32 * e[u]).min(0.3 * e[lat]).max(1e-3);
        Self {
            start: at(0.25, 0.21),
            end: at(0.8, 0.21),
            up,
            height,
            triangles,
        }
    }
}

/// An animated object: fixed triangles, positions as a function of time.
#[derive(Clone, Debug)]
pub struct DynamicObject {
    pub kind: DynamicKind,
    indices: Vec<[u32; 3]>,
    data: Data,
}

#[derive(Clone, Debug)]
enum Data {
    Robot(Robot),
    Deforming {
        shape: KeyframedMesh,
        glide: AnimatedTransform,
        /// Wobble cycles over the animation.
        cycles: f32,
    },
}

impl DynamicObject {
    pub fn new(kind: DynamicKind, p: &DynamicParams) -> Result<Self, Error> {
        let ok = p.start.is_finite()
            && p.end.is_finite()
            && p.up.is_finite()
            && p.up.length_squared() > 0.0
            && p.height.is_finite()
            && p.height > 0.0;
        if !ok {
            return Err(Error::InvalidParameter(
                "dynamic object: path, up and height must be finite, height positive".into(),
            ));
        }
        match kind {
            DynamicKind::Robot => {
                let (robot, indices) = Robot::new(p);
                Ok(Self {
                    kind,
                    indices,
                    data: Data::Robot(robot),
                })
            }
            DynamicKind::Deforming => {
                let (shape, glide, cycles) = deforming(p)?;
                Ok(Self {
                    kind,
                    indices: shape.indices.clone(),
                    data: Data::Deforming {
                        shape,
                        glide,
                        cycles,
                    },
                })
            }
        }
    }

    /// The triangles (the same at every time).
    pub fn indices(&self) -> &[[u32; 3]] {
        &self.indices
    }

    pub fn triangle_count(&self) -> usize {
        self.indices.len()
    }

    pub fn vertex_count(&self) -> usize {
        match &self.data {
            Data::Robot(r) => r.rest.len(),
            Data::Deforming { shape, .. } => shape.vertex_count(),
        }
    }

    /// World positions at animation time `t` (0..1, clamped) into `out`
    /// (no allocation once `out` is large enough).
    pub fn positions_into(&self, t: f32, out: &mut Vec<Vec3>) {
        let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
        match &self.data {
            Data::Robot(r) => r.pose(t, out),
            Data::Deforming {
                shape,
                glide,
                cycles,
            } => {
                // One wobble cycle of key frames, repeated.
                let phase = (t * cycles).fract();
                shape.positions_into(phase, out);
                let xf = glide.at(t);
                out.par_iter_mut()
                    .with_min_len(4096)
                    .for_each(|p| *p = xf.transform_point3(*p));
            }
        }
    }

    /// The mesh at time `t`.
    pub fn mesh_at(&self, t: f32) -> TriangleMesh {
        let mut positions = Vec::new();
        self.positions_into(t, &mut positions);
        TriangleMesh {
            positions,
            indices: self.indices.clone(),
        }
    }
}

/// `sign(x) * |x|^e`: the superellipsoid's rounding.
#[inline]
fn spow(x: f32, e: f32) -> f32 {
    x.signum() * x.abs().powf(e)
}

/// A closed superellipsoid around the local Y axis: `nu` segments around,
/// `nv` along; half-extents `half`, centre `c`; `e_around` 1 is round, small
/// is square; `e_along` likewise along Y.
#[allow(clippy::too_many_arguments)]
fn superellipsoid(
    nu: usize,
    nv: usize,
    c: Vec3,
    half: Vec3,
    e_around: f32,
    e_along: f32,
    base: u32,
    pos: &mut Vec<Vec3>,
    idx: &mut Vec<[u32; 3]>,
) {
    use std::f32::consts::{FRAC_PI_2, PI, TAU};
    for j in 0..=nv {
        let v = -FRAC_PI_2 + PI * j as f32 / nv as f32;
        let (cv, sv) = (spow(v.cos().max(0.0), e_along), spow(v.sin(), e_along));
        for i in 0..nu {
            let u = TAU * i as f32 / nu as f32;
            pos.push(
                c + half
                    * Vec3::new(
                        cv * spow(u.cos(), e_around),
                        sv,
                        cv * spow(u.sin(), e_around),
                    ),
            );
        }
    }
    let nu32 = nu as u32;
    for j in 0..nv as u32 {
        for i in 0..nu32 {
            let a = base + j * nu32 + i;
            let b = base + j * nu32 + (i + 1) % nu32;
            let c = b + nu32;
            let d = a + nu32;
            idx.push([a, c, b]);
            idx.push([a, d, c]);
        }
    }
}

#[derive(Clone, Copy, Debug)]
enum Joint {
    Pelvis,
    Torso,
    Head,
    Shoulder(f32),
    Elbow(f32),
    Hip(f32),
    Knee(f32),
    Ankle(f32),
}

/// One limb: parent limb, joint offset in the parent's frame, the joint's
/// motion, and its shape in its own frame.
struct LimbDef {
    parent: Option<usize>,
    offset: Vec3,
    joint: Joint,
    centre: Vec3,
    half: Vec3,
    e_around: f32,
    e_along: f32,
}

fn limb_defs() -> Vec<LimbDef> {
    let l = |parent: Option<usize>,
             offset: [f32; 3],
             joint: Joint,
             centre: [f32; 3],
             half: [f32; 3],
             e_around: f32,
             e_along: f32| LimbDef {
        parent,
        offset: Vec3::from_array(offset),
        joint,
        centre: Vec3::from_array(centre),
        half: Vec3::from_array(half),
        e_around,
        e_along,
    };
    let mut v = vec![
        // 0 pelvis, 1 torso, 2 head.
        l(
            None,
            [0.0, 0.565, 0.0],
            Joint::Pelvis,
            [0.0; 3],
            [0.12, 0.06, 0.08],
            0.3,
            0.3,
        ),
        l(
            Some(0),
            [0.0, 0.05, 0.0],
            Joint::Torso,
            [0.0, 0.17, 0.0],
            [0.15, 0.17, 0.09],
            0.3,
            0.3,
        ),
        l(
            Some(1),
            [0.0, 0.38, 0.0],
            Joint::Head,
            [0.0, 0.07, 0.01],
            [0.075, 0.085, 0.08],
            0.5,
            0.5,
        ),
    ];
    for s in [-1.0f32, 1.0] {
        let i = v.len();
        // Upper arm, forearm.
        v.push(l(
            Some(1),
            [0.2 * s, 0.31, 0.0],
            Joint::Shoulder(s),
            [0.0, -0.13, 0.0],
            [0.04, 0.145, 0.04],
            1.0,
            0.3,
        ));
        v.push(l(
            Some(i),
            [0.0, -0.27, 0.0],
            Joint::Elbow(s),
            [0.0, -0.12, 0.0],
            [0.035, 0.13, 0.035],
            1.0,
            0.3,
        ));
    }
    for s in [-1.0f32, 1.0] {
        let i = v.len();
        // Thigh, shin, foot.
        v.push(l(
            Some(0),
            [0.075 * s, -0.04, 0.0],
            Joint::Hip(s),
            [0.0, -0.125, 0.0],
            [0.055, 0.135, 0.055],
            1.0,
            0.3,
        ));
        v.push(l(
            Some(i),
            [0.0, -0.25, 0.0],
            Joint::Knee(s),
            [0.0, -0.115, 0.0],
            [0.045, 0.125, 0.045],
            1.0,
            0.3,
        ));
        v.push(l(
            Some(i + 1),
            [0.0, -0.23, 0.0],
            Joint::Ankle(s),
            [0.0, -0.025, 0.04],
            [0.045, 0.025, 0.085],
            0.3,
            0.3,
        ));
    }
    v
}

/// The robot: rest vertices per limb (limb frame), equal counts per limb.
#[derive(Clone, Debug)]
struct Robot {
    rest: Vec<Vec3>,
    per_limb: usize,
    /// Limb parent, joint offset and motion (shape already in `rest`).
    joints: Vec<(Option<usize>, Vec3, Joint)>,
    path: AnimatedTransform,
    /// Steps (half cycles) over the path.
    cycles: f32,
}

/// Height of the robot's model (head top) in model units.
const ROBOT_MODEL_HEIGHT: f32 = 1.16;

impl Robot {
    fn new(p: &DynamicParams) -> (Self, Vec<[u32; 3]>) {
        let defs = limb_defs();
        let per_limb_tris = (p.triangles.max(13 * 32) / defs.len()).max(32);
        // 2 nu nv triangles, nu = 2 nv around.
        let nv = ((per_limb_tris as f32 / 4.0).sqrt().round() as usize).max(4);
        let nu = 2 * nv;
        let per_limb = nu * (nv + 1);
        let mut rest = Vec::with_capacity(per_limb * defs.len());
        let mut idx = Vec::with_capacity(2 * nu * nv * defs.len());
        for d in &defs {
            let base = rest.len() as u32;
            superellipsoid(
                nu, nv, d.centre, d.half, d.e_around, d.e_along, base, &mut rest, &mut idx,
            );
        }
        let scale = p.height / ROBOT_MODEL_HEIGHT;
        let dir = p.end - p.start;
        let path = walk_path(p, scale);
        // A stride of about 0.9 model units per cycle.
        let cycles = (dir.length() / (0.9 * scale)).max(1.0);
        let joints = defs.iter().map(|d| (d.parent, d.offset, d.joint)).collect();
        (
            Self {
                rest,
                per_limb,
                joints,
                path,
                cycles,
            },
            idx,
        )
    }

    /// Limb frames at phase `ph` (radians), in model space.
    fn limb_frames(&self, ph: f32) -> Vec<Affine3A> {
        let (s, c) = ph.sin_cos();
        let mut frames: Vec<Affine3A> = Vec::with_capacity(self.joints.len());
        for &(parent, offset, joint) in &self.joints {
            let rx = Affine3A::from_rotation_x;
            let local = match joint {
                Joint::Pelvis => {
                    Affine3A::from_translation(Vec3::Y * 0.025 * (2.0 * ph).cos().abs())
                        * Affine3A::from_rotation_y(0.12 * s)
                }
                Joint::Torso => Affine3A::from_rotation_y(-0.2 * s) * rx(-0.06),
                Joint::Head => rx(0.08 * (2.0 * ph).sin()),
                // Arms swing against the legs on the same side.
                Joint::Shoulder(side) => {
                    rx(0.5 * s * side) * Affine3A::from_rotation_z(0.08 * side)
                }
                Joint::Elbow(side) => rx(-0.35 - 0.25 * (0.5 + 0.5 * s * side)),
                Joint::Hip(side) => rx(-0.45 * s * side),
                Joint::Knee(side) => rx(0.55 * (0.5 + 0.5 * (ph + side * 1.2).sin()).powi(2)),
                Joint::Ankle(side) => rx(0.2 * c * side),
            };
            let parent = parent.map_or(Affine3A::IDENTITY, |i| frames[i]);
            frames.push(parent * Affine3A::from_translation(offset) * local);
        }
        frames
    }

    fn pose(&self, t: f32, out: &mut Vec<Vec3>) {
        let root = self.path.at(t);
        let frames: Vec<Affine3A> = self
            .limb_frames(std::f32::consts::TAU * self.cycles * t)
            .into_iter()
            .map(|f| root * f)
            .collect();
        out.clear();
        out.resize(self.rest.len(), Vec3::ZERO);
        out.par_chunks_mut(self.per_limb)
            .zip(self.rest.par_chunks(self.per_limb))
            .zip(frames.par_iter())
            .for_each(|((o, r), f)| {
                for (o, r) in o.iter_mut().zip(r) {
                    *o = f.transform_point3(*r);
                }
            });
    }
}

/// The root transform along the path: model +Y to `up`, model +Z along the
/// path, uniform `scale`; keys at start and end.
fn walk_path(p: &DynamicParams, scale: f32) -> AnimatedTransform {
    let up = p.up.normalize();
    let mut fwd = (p.end - p.start).reject_from(up);
    if fwd.length_squared() <= 1e-12 {
        fwd = up.any_orthonormal_vector();
    }
    let fwd = fwd.normalize();
    let right = up.cross(fwd);
    let rot = Quat::from_mat3(&glam::Mat3::from_cols(right, up, fwd));
    let key = |pos: Vec3| Affine3A::from_scale_rotation_translation(Vec3::splat(scale), rot, pos);
    AnimatedTransform {
        keys: vec![(0.0, key(p.start)), (1.0, key(p.end))],
    }
}

/// Key frames of the wobbling torus (one cycle, 8 keys) and its glide.
fn deforming(p: &DynamicParams) -> Result<(KeyframedMesh, AnimatedTransform, f32), Error> {
    use std::f32::consts::TAU;
    // 2 nu nv triangles with nu = 2 nv.
    let nv = ((p.triangles.max(64) as f32 / 4.0).sqrt().round() as usize).max(4);
    let nu = 2 * nv;
    let (big_r, small_r) = (0.32f32, 0.14f32);
    let keys = 8;
    let frames: Vec<Vec<Vec3>> = (0..=keys)
        .map(|k| {
            let ph = TAU * k as f32 / keys as f32;
            (0..nv)
                .flat_map(|j| (0..nu).map(move |i| (i, j)))
                .map(|(i, j)| {
                    let u = TAU * i as f32 / nu as f32;
                    let v = TAU * j as f32 / nv as f32;
                    let wobble = 1.0 + 0.3 * (3.0 * u + 2.0 * v + ph).sin() * (ph + u).cos();
                    let ring = big_r * (1.0 + 0.15 * (2.0 * u - ph).sin());
                    let r = small_r * wobble;
                    // Ring in the model's XY plane (standing up), centre at
                    // half height.
                    Vec3::new(
                        (ring + r * v.cos()) * u.cos(),
                        0.5 + (ring + r * v.cos()) * u.sin(),
                        r * v.sin(),
                    )
                })
                .collect()
        })
        .collect();
    let (nu32, nv32) = (nu as u32, nv as u32);
    let mut idx = Vec::with_capacity(2 * nu * nv);
    for j in 0..nv32 {
        for i in 0..nu32 {
            let at = |i: u32, j: u32| (j % nv32) * nu32 + (i % nu32);
            let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
            idx.push([a, b, c]);
            idx.push([a, c, d]);
        }
    }
    let times = (0..=keys).map(|k| k as f32 / keys as f32).collect();
    let shape = KeyframedMesh::new(idx, frames, times)?;
    // Model height about 1 (0.5 +- (0.32 * 1.15 + 0.14 * 1.3)), scaled to
    // the requested height; spins a full turn about `up` while gliding.
    let scale = p.height / 1.1;
    let base = walk_path(p, scale);
    let spin_keys = 8;
    let keys: Vec<(f32, Affine3A)> = (0..=spin_keys)
        .map(|k| {
            let t = k as f32 / spin_keys as f32;
            let spin = Affine3A::from_rotation_y(TAU * t);
            (t, base.at(t) * spin)
        })
        .collect();
    let glide = AnimatedTransform::new(keys)?;
    let cycles = 3.0;
    Ok((shape, glide, cycles))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(n: usize) -> DynamicParams {
        DynamicParams::in_box(
            &Aabb::new(Vec3::new(-0.1, -0.1, -0.1), Vec3::new(30.0, 2.9, 12.0)),
            Vec3::Y,
            n,
        )
    }

    #[test]
    fn sizes_and_placement() {
        for kind in [DynamicKind::Robot, DynamicKind::Deforming] {
            let p = params(200_000);
            let o = DynamicObject::new(kind, &p).unwrap();
            let n = o.triangle_count();
            assert!((180_000..=220_000).contains(&n), "{kind:?}: {n}");
            for t in [0.0, 0.37, 1.0] {
                let m = o.mesh_at(t);
                m.validate().unwrap();
                let b = m.bounds();
                let h = b.extent().y;
                assert!(
                    (0.8 * p.height..=1.25 * p.height).contains(&h),
                    "{kind:?} {h}"
                );
                assert!(b.min.y > -0.2 && b.max.y < 2.9, "{kind:?} {b:?}");
            }
            // It moves.
            let (a, b) = (o.mesh_at(0.0).bounds(), o.mesh_at(1.0).bounds());
            assert!((a.center() - b.center()).length() > 5.0);
        }
    }
}
