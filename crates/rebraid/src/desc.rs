//! Plain descriptions of scenes: what loaders and procedural generators
//! produce, and what a [`crate::Scene`] is built from. No acceleration data.

use glam::Affine3A;

use crate::{Aabb, TriangleMesh};

/// One object (triangle mesh) of a scene description.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ObjectDesc {
    pub name: String,
    pub mesh: TriangleMesh,
    /// True when the object appears in the world as given (identity
    /// placement); false when it is seen only through instances.
    pub placed: bool,
}

/// One placement of an object with an affine transform (object to world).
#[derive(Clone, Debug, PartialEq)]
pub struct InstanceDesc {
    pub name: String,
    /// Index into [`SceneDesc::objects`].
    pub object: u32,
    pub transform: Affine3A,
}

/// A scene as a list of objects and instances.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SceneDesc {
    pub objects: Vec<ObjectDesc>,
    pub instances: Vec<InstanceDesc>,
}

impl SceneDesc {
    /// Triangles in the world: placed objects plus one copy per instance.
    pub fn world_triangles(&self) -> usize {
        let placed: usize = self
            .objects
            .iter()
            .filter(|o| o.placed)
            .map(|o| o.mesh.len())
            .sum();
        let inst: usize = self
            .instances
            .iter()
            .map(|i| {
                self.objects
                    .get(i.object as usize)
                    .map_or(0, |o| o.mesh.len())
            })
            .sum();
        placed + inst
    }

    /// Triangles stored once per object.
    pub fn unique_triangles(&self) -> usize {
        self.objects.iter().map(|o| o.mesh.len()).sum()
    }

    /// World boxes of every placement (placed objects, then instances), and
    /// the box of the whole scene.
    pub fn world_boxes(&self) -> (Vec<Aabb>, Aabb) {
        let mut boxes: Vec<Aabb> = self
            .objects
            .iter()
            .filter(|o| o.placed && !o.mesh.is_empty())
            .map(|o| o.mesh.bounds())
            .collect();
        for inst in &self.instances {
            if let Some(o) = self.objects.get(inst.object as usize)
                && !o.mesh.is_empty()
            {
                let b = o.mesh.bounds();
                boxes.push(crate::transform::transform_box(&inst.transform, &b));
            }
        }
        let all = boxes.iter().fold(Aabb::EMPTY, |a, b| a.union(*b));
        (boxes, all)
    }

    /// Sum of the placements' box surface areas over the scene box's: the
    /// "overlap" of `shared/scenes/README.md`. 1 or below means little overlap.
    pub fn overlap_ratio(&self) -> f64 {
        Aabb::overlap_ratio(self.world_boxes().0)
    }

    /// Every instance transform world-to-object invertible and finite, every
    /// object id in range, every mesh valid.
    pub fn validate(&self) -> Result<(), crate::Error> {
        for o in &self.objects {
            o.mesh.validate()?;
        }
        for i in &self.instances {
            if i.object as usize >= self.objects.len() {
                return Err(crate::Error::UnknownObject(i.object));
            }
            crate::transform::check_transform(&i.transform)?;
        }
        Ok(())
    }
}
