//! Feed arbitrary bytes to the PLY parser: it must return a scene or an
//! error, never panic.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use rebraid_cli::loaders::{LoadOptions, ply::parse_ply};

fuzz_target!(|data: &[u8]| {
    if let Ok(scene) = parse_ply(data, Path::new("fuzz.ply"), &LoadOptions::default()) {
        assert!(scene.validate().is_ok());
    }
});
