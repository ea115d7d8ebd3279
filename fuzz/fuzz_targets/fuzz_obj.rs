//! Feed arbitrary bytes to the OBJ parser, with every split mode and with
//! touching objects joined and kept apart: it must return a scene or an
//! error, never panic.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use rebraid_cli::loaders::{LoadOptions, Split, obj::parse_obj};

fuzz_target!(|data: &[u8]| {
    for (split, keep_touching_apart) in [Split::Object, Split::Group, Split::Material, Split::None]
        .into_iter()
        .flat_map(|s| [(s, false), (s, true)])
    {
        let opts = LoadOptions {
            split,
            keep_touching_apart,
            ..LoadOptions::default()
        };
        if let Ok(scene) = parse_obj(data, Path::new("fuzz.obj"), &opts) {
            // Whatever parses must be a valid scene.
            assert!(scene.validate().is_ok());
        }
    }
});
