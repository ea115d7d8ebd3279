//! `rebraid animate` end to end: a tiny library with a small robot,
//! three frames in every mode, PNGs and JSON written, every ray set traced.

use std::path::Path;
use std::process::Command;

/// Command-line words.
fn words(line: &str) -> Vec<String> {
    line.split_whitespace().map(String::from).collect()
}

/// Run the tool with `args` and `--json json`; its stdout, once it has
/// exited successfully.
fn run_animate(args: Vec<String>, json: &Path) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_rebraid"))
        .args(args)
        .arg("--json")
        .arg(json)
        .output()
        .expect("run rebraid");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "exit {:?}\nstdout:\n{stdout}\nstderr:\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

#[test]
fn animate_writes_frames_and_json() {
    let dir = tempfile::tempdir().expect("tempdir");
    let frames = dir.path().join("frames");
    let json = dir.path().join("animate.json");
    // A robot small beside the library: the re-braided scene splits it off
    // (`RebraidParams::moving_split_max_share`).
    let mut args = words(
        "animate library --scale 0.02 --frames 3 --dynamic-triangles 3000 --width 64 --height 36",
    );
    args.extend(["-o".into(), frames.display().to_string()]);
    let stdout = run_animate(args, &json);
    assert!(stdout.contains("summary"), "{stdout}");
    let modes = ["flat", "two-level", "rebraided"];
    for mode in modes {
        for f in 0..3 {
            let png = frames.join(mode).join(format!("frame_{f:04}.png"));
            let bytes = std::fs::read(&png).unwrap_or_else(|e| panic!("{}: {e}", png.display()));
            assert!(bytes.starts_with(b"\x89PNG"), "{}", png.display());
        }
        assert_eq!(
            std::fs::read_dir(frames.join(mode)).unwrap().count(),
            3,
            "{mode}: three PNGs"
        );
    }
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).expect("JSON");
    let rows = v["frames"].as_array().expect("frames array");
    assert_eq!(rows.len(), 9, "one row per frame and mode");
    for (k, r) in rows.iter().enumerate() {
        assert_eq!(r["mode"], modes[k / 3]);
        assert_eq!(r["frame"], (k % 3) as u64);
        assert!(r["mrays_per_s"].as_f64().unwrap() > 0.0);
        assert!(r["shadow_mrays_per_s"].as_f64().unwrap() > 0.0);
        assert!(r["diffuse_mrays_per_s"].as_f64().unwrap() > 0.0);
        if r["mode"] == "rebraided" {
            // The robot moves every frame: it is traced from a top level of
            // its own, and the one over the library, built at the first
            // frame, is kept.
            assert!(r["moving_refs"].as_u64().unwrap() >= 1, "{r}");
            assert_eq!(r["fixed_kept"], r["frame"] != 0, "{r}");
        } else {
            assert_eq!(r["moving_refs"], 0, "{r}");
        }
        assert!(r["commit_ms"].as_f64().unwrap() >= 0.0);
        assert_eq!(r["primary_rays"], 64 * 36);
        assert!(r["render_ms"].as_f64().is_some());
        if r["mode"] != "flat" {
            // The robot's BVH is refitted every frame (policy refit).
            assert_eq!(r["objects_refitted"], 1, "{r}");
            assert_eq!(r["objects_rebuilt"], 0, "{r}");
        }
    }
    assert_eq!(v["summary"].as_array().unwrap().len(), 3);
    let tris = v["dynamic_triangles"].as_u64().unwrap();
    assert!((1000..10_000).contains(&tris), "{tris}");
}

/// The swarm: rigid instances moved by their transforms. From the first
/// move on, the re-braided scene traces them from a top level of their
/// own, and from the second keeps the library's.
#[test]
fn animate_swarm_moves_instances() {
    let dir = tempfile::tempdir().expect("tempdir");
    let json = dir.path().join("swarm.json");
    let args = words(
        "animate library --scale 0.05 --frames 4 --dynamic swarm --dynamic-triangles 3000 \
         --mode two-level,rebraided --width 48 --height 32",
    );
    run_animate(args, &json);
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).expect("JSON");
    assert_eq!(v["dynamic"], "swarm");
    let rows = v["frames"].as_array().expect("frames array");
    assert_eq!(rows.len(), 8);
    for r in rows {
        // Nothing but transforms moves.
        assert_eq!(r["objects_refitted"], 0, "{r}");
        assert_eq!(r["objects_rebuilt"], 0, "{r}");
        assert!(r["diffuse_mrays_per_s"].as_f64().unwrap() > 0.0);
        if r["mode"] == "rebraided" {
            // Frame 0 sets the transforms the instances have: no move.
            let f = r["frame"].as_u64().unwrap();
            assert_eq!(r["moving_refs"].as_u64().unwrap() >= 64, f >= 1, "{r}");
            assert_eq!(r["fixed_kept"], f >= 2, "{r}");
        }
    }
}
