//! Where tests and benches find the shared real scenes: `$REBRAID_SCENES`,
//! else `shared/scenes` beside the workspace (the repository never holds the
//! scenes). One file, included with `#[path]` by the test crates of both
//! workspace crates, so the skip-or-fail rule is written once: a missing
//! scene prints a visible `SKIPPED:` line, except under `CI=true`, where it
//! fails, because CI must never pass by silently testing nothing.

#![allow(dead_code)] // each including crate uses its own part

use std::path::PathBuf;

/// The scenes directory (which may not exist).
pub fn scenes_dir() -> PathBuf {
    match std::env::var_os("REBRAID_SCENES") {
        Some(dir) => PathBuf::from(dir),
        None => PathBuf::from(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../../shared/scenes"
        )),
    }
}

fn missing(what: &str) {
    let ci = std::env::var("CI").is_ok_and(|v| v == "true");
    assert!(
        !ci,
        "{what} is missing and CI=true: CI must run the real-scene tests \
         (set REBRAID_SCENES to the scenes directory)"
    );
    eprintln!("SKIPPED: {what} not found (set REBRAID_SCENES to the scenes directory)");
}

/// The scenes directory, or `None` after the skip message (see the module docs).
pub fn scenes_dir_or_skip() -> Option<PathBuf> {
    let dir = scenes_dir();
    if dir.is_dir() {
        return Some(dir);
    }
    missing(&format!("scenes directory {}", dir.display()));
    None
}

/// One scene file, or `None` after the skip message (see the module docs).
pub fn scene_path_or_skip(file: &str) -> Option<PathBuf> {
    let path = scenes_dir().join(file);
    if path.is_file() {
        return Some(path);
    }
    missing(&format!("scene {}", path.display()));
    None
}
