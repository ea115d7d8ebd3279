//! Key-frame animation: meshes whose vertices are interpolated between key
//! frames ([`KeyframedMesh`]) and transforms interpolated between keys
//! ([`AnimatedTransform`]), and helpers that apply them to a [`Scene`] at a
//! time `t` (the scene then commits as usual, rebuilding or refitting the
//! moved objects by their [`crate::UpdatePolicy`]).
//!
//! Times are plain `f32`s in any unit; keys must be strictly increasing.
//! Sampling before the first key gives the first key, after the last the
//! last (clamped); between two keys the interpolation is linear (positions,
//! translation, scale) or spherical (rotation).

use glam::{Affine3A, Quat, Vec3};

use crate::transform::check_transform;
use crate::{Error, InstanceId, ObjectId, Scene, TriangleMesh};

/// Keys `i`, `i + 1` and the weight of `i + 1` for time `t` (clamped).
/// `times` must be non-empty and strictly increasing.
fn bracket(times: &[f32], t: f32) -> (usize, usize, f32) {
    let last = times.len() - 1;
    if t.is_nan() || t <= times[0] {
        return (0, 0, 0.0);
    }
    if t >= times[last] {
        return (last, last, 0.0);
    }
    // First key strictly after t (exists: t < times[last]).
    let j = times.partition_point(|&k| k <= t);
    let i = j - 1;
    let w = (t - times[i]) / (times[j] - times[i]);
    (i, j, w.clamp(0.0, 1.0))
}

fn check_times(times: &[f32]) -> Result<(), Error> {
    if times.is_empty() {
        return Err(Error::InvalidParameter("animation without keys".into()));
    }
    if times.iter().any(|t| !t.is_finite()) {
        return Err(Error::InvalidParameter(
            "animation key times must be finite".into(),
        ));
    }
    if times.windows(2).any(|w| w[0] >= w[1]) {
        return Err(Error::InvalidParameter(
            "animation key times must be strictly increasing".into(),
        ));
    }
    Ok(())
}

/// A mesh with fixed triangles whose vertex positions are given at key times.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct KeyframedMesh {
    pub indices: Vec<[u32; 3]>,
    /// Vertex positions per key frame, each of the same length.
    pub frames: Vec<Vec<Vec3>>,
    /// Time of each key frame, strictly increasing.
    pub times: Vec<f32>,
}

impl KeyframedMesh {
    /// A checked key-framed mesh (see [`KeyframedMesh::validate`]).
    pub fn new(
        indices: Vec<[u32; 3]>,
        frames: Vec<Vec<Vec3>>,
        times: Vec<f32>,
    ) -> Result<Self, Error> {
        let m = Self {
            indices,
            frames,
            times,
        };
        m.validate()?;
        Ok(m)
    }

    /// One key per time, as many frames as times, every frame the same
    /// vertex count, every vertex finite, every index in range.
    pub fn validate(&self) -> Result<(), Error> {
        check_times(&self.times)?;
        if self.frames.len() != self.times.len() {
            return Err(Error::InvalidParameter(format!(
                "{} key frames for {} key times",
                self.frames.len(),
                self.times.len()
            )));
        }
        let nv = self.frames[0].len();
        for f in &self.frames {
            if f.len() != nv {
                return Err(Error::VertexCountMismatch {
                    expected: nv,
                    got: f.len(),
                });
            }
            crate::mesh::check_positions(f)?;
        }
        for (t, tri) in self.indices.iter().enumerate() {
            if let Some(&v) = tri.iter().find(|&&v| v as usize >= nv) {
                return Err(Error::IndexOutOfRange {
                    triangle: t,
                    vertex: v,
                    vertex_count: nv,
                });
            }
        }
        Ok(())
    }

    /// Vertices per frame.
    pub fn vertex_count(&self) -> usize {
        self.frames.first().map_or(0, Vec::len)
    }

    /// Positions at time `t` into `out` (resized to the vertex count; no
    /// allocation once `out` is large enough). The mesh must be valid.
    pub fn positions_into(&self, t: f32, out: &mut Vec<Vec3>) {
        out.clear();
        if self.frames.is_empty() || self.times.len() != self.frames.len() {
            return;
        }
        let (i, j, w) = bracket(&self.times, t);
        let (a, b) = (&self.frames[i], &self.frames[j]);
        if i == j || w == 0.0 {
            out.extend_from_slice(a);
        } else if w == 1.0 {
            out.extend_from_slice(b);
        } else {
            out.extend(a.iter().zip(b).map(|(p, q)| p.lerp(*q, w)));
        }
    }

    /// Positions at time `t` (linear interpolation, clamped to the keys).
    pub fn positions_at(&self, t: f32) -> Vec<Vec3> {
        let mut v = Vec::with_capacity(self.vertex_count());
        self.positions_into(t, &mut v);
        v
    }

    /// The mesh at time `t`.
    pub fn mesh_at(&self, t: f32) -> Result<TriangleMesh, Error> {
        TriangleMesh::new(self.positions_at(t), self.indices.clone())
    }
}

/// An affine transform given at key times, interpolated by decomposing each
/// key into scale, rotation and translation (`to_scale_rotation_translation`;
/// shears are not represented): scale and translation are interpolated
/// linearly, rotation spherically along the shorter arc.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AnimatedTransform {
    /// (time, transform), times strictly increasing.
    pub keys: Vec<(f32, Affine3A)>,
}

impl AnimatedTransform {
    /// Checked keys: times finite and strictly increasing, every transform
    /// valid as an instance transform.
    pub fn new(keys: Vec<(f32, Affine3A)>) -> Result<Self, Error> {
        let a = Self { keys };
        a.validate()?;
        Ok(a)
    }

    pub fn validate(&self) -> Result<(), Error> {
        let times: Vec<f32> = self.keys.iter().map(|k| k.0).collect();
        check_times(&times)?;
        for (_, xf) in &self.keys {
            check_transform(xf)?;
        }
        Ok(())
    }

    /// The transform at time `t` (the identity when there are no keys).
    /// Exact at the keys and beyond the ends (the key itself is returned).
    pub fn at(&self, t: f32) -> Affine3A {
        let Some(first) = self.keys.first() else {
            return Affine3A::IDENTITY;
        };
        if t.is_nan() || t <= first.0 {
            return first.1;
        }
        let last = self.keys[self.keys.len() - 1];
        if t >= last.0 {
            return last.1;
        }
        let j = self.keys.partition_point(|k| k.0 <= t);
        let (ta, a) = self.keys[j - 1];
        let (tb, b) = self.keys[j];
        let w = ((t - ta) / (tb - ta)).clamp(0.0, 1.0);
        if w == 0.0 {
            return a;
        }
        let (sa, ra, pa) = a.to_scale_rotation_translation();
        let (sb, rb, pb) = b.to_scale_rotation_translation();
        let r: Quat = ra.normalize().slerp(rb.normalize(), w).normalize();
        Affine3A::from_scale_rotation_translation(sa.lerp(sb, w), r, pa.lerp(pb, w))
    }
}

/// Move object `id`'s vertices to `anim`'s positions at time `t`, using
/// `buf` as the interpolation buffer (no allocation once it is large enough).
pub fn apply_keyframed_mesh(
    scene: &mut Scene,
    id: ObjectId,
    anim: &KeyframedMesh,
    t: f32,
    buf: &mut Vec<Vec3>,
) -> Result<(), Error> {
    anim.positions_into(t, buf);
    scene.set_vertices(id, buf)
}

/// Set instance `id`'s transform to `anim`'s at time `t`.
pub fn apply_animated_transform(
    scene: &mut Scene,
    id: InstanceId,
    anim: &AnimatedTransform,
    t: f32,
) -> Result<(), Error> {
    scene.set_instance_transform(id, anim.at(t))
}

/// A set of animated objects and instances of one scene, applied together.
#[derive(Clone, Debug, Default)]
pub struct SceneAnimation {
    pub meshes: Vec<(ObjectId, KeyframedMesh)>,
    pub transforms: Vec<(InstanceId, AnimatedTransform)>,
    buf: Vec<Vec3>,
}

impl SceneAnimation {
    pub fn new() -> Self {
        Self::default()
    }

    /// Animate object `id`'s vertices (the object must have the key frames'
    /// vertex count when applied).
    pub fn add_mesh(&mut self, id: ObjectId, anim: KeyframedMesh) -> Result<(), Error> {
        anim.validate()?;
        self.meshes.push((id, anim));
        Ok(())
    }

    /// Animate instance `id`'s transform.
    pub fn add_transform(&mut self, id: InstanceId, anim: AnimatedTransform) -> Result<(), Error> {
        anim.validate()?;
        self.transforms.push((id, anim));
        Ok(())
    }

    /// Pose the scene at time `t` (edits only; commit afterwards).
    pub fn apply(&mut self, scene: &mut Scene, t: f32) -> Result<(), Error> {
        for (id, m) in &self.meshes {
            apply_keyframed_mesh(scene, *id, m, t, &mut self.buf)?;
        }
        for (id, x) in &self.transforms {
            apply_animated_transform(scene, *id, x, t)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bracket_clamps_and_finds_keys() {
        let t = [0.0, 1.0, 3.0];
        assert_eq!(bracket(&t, -1.0), (0, 0, 0.0));
        assert_eq!(bracket(&t, 0.0), (0, 0, 0.0));
        assert_eq!(bracket(&t, 0.5), (0, 1, 0.5));
        assert_eq!(bracket(&t, 1.0), (1, 2, 0.0));
        assert_eq!(bracket(&t, 2.0), (1, 2, 0.5));
        assert_eq!(bracket(&t, 3.0), (2, 2, 0.0));
        assert_eq!(bracket(&t, 9.0), (2, 2, 0.0));
        assert_eq!(bracket(&t, f32::NAN), (0, 0, 0.0));
    }

    #[test]
    fn bad_keys_are_rejected() {
        let f = vec![vec![Vec3::ZERO; 3]; 2];
        assert!(KeyframedMesh::new(vec![[0, 1, 2]], f.clone(), vec![1.0, 1.0]).is_err());
        assert!(KeyframedMesh::new(vec![[0, 1, 3]], f.clone(), vec![0.0, 1.0]).is_err());
        assert!(KeyframedMesh::new(vec![[0, 1, 2]], f.clone(), vec![0.0]).is_err());
        assert!(KeyframedMesh::new(vec![[0, 1, 2]], vec![], vec![]).is_err());
        assert!(KeyframedMesh::new(vec![[0, 1, 2]], f, vec![0.0, 1.0]).is_ok());
        assert!(AnimatedTransform::new(vec![(0.0, Affine3A::from_scale(Vec3::ZERO))]).is_err());
        assert!(
            AnimatedTransform::new(vec![(1.0, Affine3A::IDENTITY), (0.0, Affine3A::IDENTITY)])
                .is_err()
        );
    }
}
