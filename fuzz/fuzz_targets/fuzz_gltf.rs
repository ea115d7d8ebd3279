//! Feed arbitrary bytes to the glTF / GLB parser, in every mode that changes
//! what it builds: it must return a scene or an error, never panic.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use rebraid_cli::loaders::{LoadOptions, Split, gltf::parse_gltf};

fuzz_target!(|data: &[u8]| {
    for split in [Split::Object, Split::Material] {
        for flatten_instances in [false, true] {
            let opts = LoadOptions {
                split,
                flatten_instances,
                ..LoadOptions::default()
            };
            if let Ok(l) = parse_gltf(data, Path::new("fuzz.glb"), None, &opts) {
                assert!(l.scene.validate().is_ok());
            }
        }
    }
});
