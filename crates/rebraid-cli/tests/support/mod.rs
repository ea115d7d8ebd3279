//! Helpers shared by the rebraid-cli test binaries (each uses a part).
#![allow(dead_code)]

pub mod gltf;
