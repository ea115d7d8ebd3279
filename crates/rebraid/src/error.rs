//! The library's typed errors.

use thiserror::Error;

/// Everything that can go wrong when building or querying acceleration structures.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum Error {
    #[error("vertex {index} has a non-finite coordinate ({value:?})")]
    NonFiniteVertex { index: usize, value: [f32; 3] },
    #[error(
        "vertex {index} has a coordinate beyond +-{} ({value:?}), where box areas overflow",
        crate::mesh::MAX_COORDINATE
    )]
    VertexOutOfRange { index: usize, value: [f32; 3] },
    #[error(
        "triangle {triangle} references vertex {vertex}, but there are only {vertex_count} vertices"
    )]
    IndexOutOfRange {
        triangle: usize,
        vertex: u32,
        vertex_count: usize,
    },
    #[error("too many primitives: {0} (at most 2^31 - 1 per BVH)")]
    TooManyPrimitives(usize),
    #[error("primitive {index} has an invalid bounding box")]
    InvalidBounds { index: usize },
    #[error("invalid ray: {0}")]
    InvalidRay(&'static str),
    #[error("invalid transform: {0}")]
    InvalidTransform(&'static str),
    #[error("unknown object id {0}")]
    UnknownObject(u32),
    #[error("unknown instance id {0}")]
    UnknownInstance(u32),
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
    #[error("vertex count changed: object has {expected} vertices, got {got}")]
    VertexCountMismatch { expected: usize, got: usize },
}
