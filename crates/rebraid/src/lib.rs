//! # rebraid
//!
//! Ray-tracing kernels built around two-level BVHs with *partial re-braiding*
//! (C. Benthin, S. Woop, I. Wald, A. Áfra, "Improved Two-Level BVHs using
//! Partial Re-Braiding", HPG 2017): one BVH per object, one top-level BVH over
//! them, and a top-level builder that opens the object BVHs where their bounds
//! overlap.
//!
//! This crate is the core: geometry, builders, layouts, traversal and the
//! scene. It does no file I/O; loaders and tools live in the `rebraid-cli`
//! crate.
//!
//! ```
//! use rebraid::{BuildParams, MeshBvh, Ray, TriangleMesh};
//! use glam::Vec3;
//!
//! // One quad made of two triangles in the z = 0 plane.
//! let mesh = TriangleMesh::new(
//!     vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)],
//!     vec![[0, 1, 2], [0, 2, 3]],
//! )?;
//! let bvh = MeshBvh::build(&mesh, &BuildParams::default())?;
//! let ray = Ray::new(Vec3::new(0.25, 0.75, 1.0), Vec3::new(0.0, 0.0, -1.0), 0.0, f32::INFINITY)?;
//! let hit = bvh.intersect(&ray).expect("the ray hits the quad");
//! assert_eq!(hit.prim_id, 1);
//! assert!((hit.t - 1.0).abs() < 1e-6);
//! # Ok::<(), rebraid::Error>(())
//! ```

pub mod aabb;
pub mod animation;
pub mod bvh;
pub mod desc;
pub mod error;
mod huge_pages;
pub mod mesh;
pub mod procedural;
pub mod procedural_dynamic;
pub mod ray;
pub mod scene;
pub mod toplevel;
pub mod transform;
pub mod triangle;

pub use aabb::Aabb;
pub use bvh::{BuildParams, Bvh, BvhNode, BvhStats};
pub use desc::{InstanceDesc, ObjectDesc, SceneDesc};
pub use error::Error;
pub use mesh::{MeshBvh, TriangleMesh};
pub use ray::{Hit, INVALID_ID, Ray};
pub use scene::{
    AccelMode, CommitReport, InstanceId, ObjectId, Scene, SceneParams, SceneStats, UpdatePolicy,
};
pub use toplevel::{RebraidParams, RefBudget};

pub use glam;

// Compile the README's example as a doc-test.
#[doc = include_str!("../../../README.md")]
#[cfg(doctest)]
pub struct ReadmeDoctests;
