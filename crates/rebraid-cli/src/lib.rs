//! The app layer of rebraid: scene loaders, the renderer and the benchmark
//! harness behind the `rebraid` binary.

pub mod animate;
pub mod bench;
pub mod camera;
#[cfg(feature = "embree")]
pub mod embree;
#[cfg(feature = "embree")]
pub mod embree_bench;
pub mod loaders;
pub mod raysets;
pub mod render;
pub mod scene_input;
