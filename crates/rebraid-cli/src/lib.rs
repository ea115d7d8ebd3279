//! The app layer of rebraid: scene loaders, the built-in procedural scenes,
//! the renderer and the benchmark harness behind the `rebraid` binary.
