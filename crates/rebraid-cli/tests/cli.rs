//! End-to-end tests of the `rebraid` binary: `render`, `bench` and `stats`
//! on small scenes (the built-in `library` at scale 0.02, files written
//! here, and one real scene of `shared/scenes` when present), their output
//! files, the agreement of every mode on the benchmark rays, and the
//! one-line `error:` messages of bad arguments.

#[path = "../../rebraid/tests/support/scenes.rs"]
mod scenes;

use std::path::Path;
use std::process::{Command, Output};

use serde_json::Value;

const EXE: &str = env!("CARGO_BIN_EXE_rebraid");
const MODES: [&str; 3] = ["flat", "two-level", "rebraided"];
const SETS: [&str; 3] = ["primary", "shadow", "diffuse"];
/// A view down the aisle of `library --scale 0.02`: at this scale the
/// default camera's eye falls inside a book, where every ray hits at once.
const AISLE: &str = "0.4,1.6,2.0,5.0,1.0,2.0,60";

/// Run the tool in `cwd`.
fn run_in(cwd: &Path, args: &[&str]) -> Output {
    Command::new(EXE)
        .args(args)
        .current_dir(cwd)
        .output()
        .expect("running the rebraid binary")
}

/// Run the tool, require success, return stdout.
fn ok(cwd: &Path, args: &[&str]) -> String {
    let out = run_in(cwd, args);
    assert!(
        out.status.success(),
        "rebraid {args:?} failed ({}):\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8 stdout")
}

/// Run the tool, require failure with one line on stderr starting with
/// `error:`; return that line.
fn fails(cwd: &Path, args: &[&str]) -> String {
    let out = run_in(cwd, args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        !out.status.success(),
        "rebraid {args:?} should fail, stdout:\n{}",
        String::from_utf8_lossy(&out.stdout)
    );
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(
        lines.len(),
        1,
        "rebraid {args:?}: stderr not one line:\n{err}"
    );
    assert!(
        lines[0].starts_with("error: "),
        "rebraid {args:?}: stderr does not start with `error:`:\n{err}"
    );
    lines[0].to_string()
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 temp path")
}

/// A PNG's size, after decoding it in full.
fn png_size(p: &Path) -> (u32, u32, image::RgbImage) {
    let img = image::open(p)
        .unwrap_or_else(|e| panic!("decoding {}: {e}", p.display()))
        .to_rgb8();
    (img.width(), img.height(), img)
}

/// The number after `key` in the tool's output (`mean 12.3,`).
fn figure_after(text: &str, key: &str) -> f64 {
    let at = text
        .find(key)
        .unwrap_or_else(|| panic!("no '{key}' in:\n{text}"));
    text[at + key.len()..]
        .trim_start()
        .split(|c: char| !(c.is_ascii_digit() || c == '.'))
        .next()
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no number after '{key}' in:\n{text}"))
}

/// The rows of a `bench --json` file.
fn read_rows(p: &Path) -> Vec<Value> {
    let text = std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    text.lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("bad JSON line {l}: {e}")))
        .collect()
}

fn row<'a>(rows: &'a [Value], mode: &str, threads: u64) -> &'a Value {
    rows.iter()
        .find(|r| r["mode"] == mode && r["threads"] == threads)
        .unwrap_or_else(|| panic!("no row ({mode}, {threads} threads) in {rows:#?}"))
}

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a - b).abs() <= rel * a.abs().max(b.abs()).max(1e-30)
}

/// Every row has the documented keys and sane ray counts.
fn check_row_keys(r: &Value, pixels: u64) {
    for k in [
        "scene",
        "mode",
        "threads",
        "triangles",
        "objects",
        "instances",
        "build_ms_objects",
        "build_ms_top",
        "build_ms_total",
        "sah_cost",
        "bytes",
        "refs_opened",
    ] {
        assert!(r.get(k).is_some(), "row lacks '{k}': {r}");
    }
    assert!(r["triangles"].as_u64().unwrap() > 0, "{r}");
    if !r["mode"].as_str().unwrap().starts_with("embree") {
        assert!(r["sah_cost"].as_f64().unwrap() > 0.0, "{r}");
    }
    for set in SETS {
        let v = &r[set];
        for k in ["rays", "hits", "t_sum", "mrays_per_s"] {
            assert!(v.get(k).is_some(), "row's {set} lacks '{k}': {r}");
        }
        assert!(
            v["hits"].as_u64().unwrap() <= v["rays"].as_u64().unwrap(),
            "{r}"
        );
        assert!(v["mrays_per_s"].as_f64().unwrap() > 0.0, "{r}");
    }
    assert_eq!(r["primary"]["rays"].as_u64(), Some(pixels), "{r}");
    let hits = r["primary"]["hits"].as_u64().unwrap();
    assert_eq!(r["shadow"]["rays"].as_u64(), Some(hits), "{r}");
    assert_eq!(r["diffuse"]["rays"].as_u64(), Some(hits), "{r}");
}

/// Every row gives the same answers as `reference`: hits exactly, distance
/// sums within `rel`.
fn check_agreement(rows: &[Value], reference: &Value, rel: f64) {
    for r in rows {
        for set in SETS {
            let (a, b) = (&r[set], &reference[set]);
            assert_eq!(
                a["hits"], b["hits"],
                "{set} hits differ between {} ({} thr) and {} ({} thr)",
                r["mode"], r["threads"], reference["mode"], reference["threads"]
            );
            let (ta, tb) = (a["t_sum"].as_f64().unwrap(), b["t_sum"].as_f64().unwrap());
            assert!(
                close(ta, tb, rel),
                "{set} t_sum {ta} of {} ({} thr) vs {tb} of {} ({} thr)",
                r["mode"],
                r["threads"],
                reference["mode"],
                reference["threads"]
            );
        }
    }
}

#[test]
fn help_lists_the_commands() {
    let dir = tempfile::tempdir().unwrap();
    let out = ok(dir.path(), &["--help"]);
    for c in ["render", "bench", "stats"] {
        assert!(out.contains(c), "--help lacks '{c}':\n{out}");
    }
    assert!(
        !out.contains("embree-worker"),
        "hidden command listed:\n{out}"
    );
    for c in ["render", "bench", "stats"] {
        let out = ok(dir.path(), &[c, "--help"]);
        assert!(out.contains("--scale"), "{c} --help:\n{out}");
    }
}

/// The main job: no arguments renders the default scene to `render.png`.
#[test]
fn no_arguments_renders_the_default_scene() {
    let dir = tempfile::tempdir().unwrap();
    let out = ok(dir.path(), &[]);
    assert!(out.contains("scene library@0.25"), "{out}");
    let (w, h, img) = png_size(&dir.path().join("render.png"));
    assert_eq!((w, h), (960, 540));
    // Lit, not a black picture (the default light once sat in a bookcase).
    let mean = img
        .pixels()
        .map(|p| p.0.iter().map(|&c| c as f64).sum::<f64>() / 3.0)
        .sum::<f64>()
        / (w * h) as f64;
    assert!(
        mean > 60.0,
        "default render too dark: mean {mean:.1} of 255"
    );
}

#[test]
fn render_every_mode_writes_image_and_heat_map() {
    let dir = tempfile::tempdir().unwrap();
    let mut heat_means = Vec::new();
    for mode in MODES {
        let img = dir.path().join(format!("{mode}.png"));
        let heat = dir.path().join(format!("{mode}-heat.png"));
        let out = ok(
            dir.path(),
            &[
                "render",
                "library",
                "--scale",
                "0.02",
                "--width",
                "64",
                "--height",
                "36",
                "--spp",
                "1",
                "--mode",
                mode,
                "--camera",
                AISLE,
                "-o",
                s(&img),
                "--heatmap",
                s(&heat),
            ],
        );
        assert!(out.contains(&format!("mode {mode}:")), "{out}");
        let (w, h, pixels) = png_size(&img);
        assert_eq!((w, h), (64, 36), "{mode}");
        let lit = pixels
            .pixels()
            .filter(|p| p.0.iter().any(|&c| c > 40))
            .count();
        assert!(lit * 2 > pixels.len() / 3, "{mode}: only {lit} lit pixels");
        // The heat map has a colour bar of max(height / 24, 4) rows below.
        let (w, h, heat_img) = png_size(&heat);
        assert_eq!((w, h), (64, 40), "{mode} heat map");
        // The bar runs from black (0 nodes) to white (--heat-max nodes).
        assert_eq!(heat_img.get_pixel(0, 39).0, [0, 0, 0]);
        assert_eq!(heat_img.get_pixel(63, 39).0, [255, 255, 255]);
        let mean = figure_after(&out, "mean");
        assert!(mean > 0.0, "{mode}: {out}");
        heat_means.push(mean);
    }
    // The point of re-braiding: fewer nodes per ray than the plain two-level BVH.
    assert!(
        heat_means[2] < heat_means[1],
        "rebraided visits {} nodes per ray, two-level {}",
        heat_means[2],
        heat_means[1]
    );
}

#[test]
fn bench_library_writes_json_and_modes_agree() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("out.json");
    let out = ok(
        dir.path(),
        &[
            "bench",
            "library",
            "--scale",
            "0.02",
            "--width",
            "64",
            "--height",
            "36",
            "--reps",
            "1",
            "--threads",
            "1,2",
            "--camera",
            AISLE,
            "--json",
            s(&json),
        ],
    );
    assert!(out.contains("scene") && out.contains("Mtri/s"), "{out}");
    for m in MODES {
        assert!(out.contains(m), "table lacks {m}:\n{out}");
    }
    // The re-braided structure against our flat BVH, with no Embree row
    // to set our flat BVH against.
    assert!(out.contains("rebraided / flat "), "{out}");
    assert!(!out.contains("flat / embree"), "{out}");
    let rows = read_rows(&json);
    assert_eq!(rows.len(), 6, "one row per (mode, threads): {rows:#?}");
    // Every row names the CPU it ran on, as the output's first line does.
    let machine = out
        .lines()
        .find_map(|l| l.strip_prefix("machine: "))
        .unwrap_or_else(|| panic!("no machine line:\n{out}"));
    assert!(machine.contains("logical CPUs"), "{machine}");
    for r in &rows {
        assert_eq!(r["scene"], "library@0.02");
        assert_eq!(r["machine"], machine);
        check_row_keys(r, 64 * 36);
    }
    for t in [1, 2] {
        for m in MODES {
            row(&rows, m, t);
        }
    }
    assert_eq!(row(&rows, "flat", 1)["refs_opened"], 0);
    // A real workload: some shadow rays blocked, some reaching the light.
    let shadow = &row(&rows, "flat", 1)["shadow"];
    let blocked = shadow["hits"].as_u64().unwrap();
    assert!(
        blocked > 0 && blocked < shadow["rays"].as_u64().unwrap(),
        "{shadow}"
    );
    check_agreement(&rows, row(&rows, "flat", 1), 1e-6);
}

/// An OBJ file of `objects` objects, each a few boxes spread over the
/// whole scene (so their boxes overlap), on a floor.
fn overlapping_obj(objects: usize) -> String {
    let mut text = String::from("# written by tests/cli.rs\n");
    let mut base = 1;
    let mut add_box = |text: &mut String, lo: [f32; 3], hi: [f32; 3]| {
        for k in 0..8 {
            let c = |i: usize| if k >> i & 1 == 0 { lo[i] } else { hi[i] };
            text.push_str(&format!("v {} {} {}\n", c(0), c(1), c(2)));
        }
        // Corner k has x = bit 0, y = bit 1, z = bit 2.
        for [a, b, c, d] in [
            [0, 2, 3, 1],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 6, 7, 3],
            [0, 4, 6, 2],
            [1, 3, 7, 5],
        ] {
            let f = |i: usize| base + i;
            text.push_str(&format!("f {} {} {}\n", f(a), f(b), f(c)));
            text.push_str(&format!("f {} {} {}\n", f(a), f(c), f(d)));
        }
        base += 8;
    };
    text.push_str("o floor\n");
    add_box(&mut text, [-1.0, -0.1, -1.0], [11.0, 0.0, 11.0]);
    for o in 0..objects {
        text.push_str(&format!("o part{o}\n"));
        for b in 0..4 {
            let x = ((o * 7 + b * 3) % 10) as f32;
            let z = ((o * 3 + b * 5) % 10) as f32;
            let y = 0.2 * (b as f32);
            add_box(
                &mut text,
                [x, y, z],
                [x + 0.6, y + 0.5 + 0.1 * o as f32, z + 0.4],
            );
        }
    }
    text
}

/// A binary glTF of a cube mesh placed by three nodes and a square mesh by
/// one: two meshes, four instances.
fn tiny_glb() -> Vec<u8> {
    let mut bin = Vec::new();
    for k in 0..8u32 {
        for i in 0..3 {
            bin.extend_from_slice(&((k >> i & 1) as f32).to_le_bytes());
        }
    }
    let cube: [u16; 36] = [
        0, 2, 3, 0, 3, 1, 4, 5, 7, 4, 7, 6, 0, 1, 5, 0, 5, 4, 2, 6, 7, 2, 7, 3, 0, 4, 6, 0, 6, 2,
        1, 3, 7, 1, 7, 5,
    ];
    for i in cube {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    for [x, z] in [[0.0f32, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]] {
        for c in [x, 0.0, z] {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for i in [0u16, 2, 1, 0, 3, 2] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    assert_eq!(bin.len(), 96 + 72 + 48 + 12);
    let json = format!(
        r#"{{
  "asset": {{"version": "2.0"}},
  "buffers": [{{"byteLength": {len}}}],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": 96}},
    {{"buffer": 0, "byteOffset": 96, "byteLength": 72}},
    {{"buffer": 0, "byteOffset": 168, "byteLength": 48}},
    {{"buffer": 0, "byteOffset": 216, "byteLength": 12}}
  ],
  "accessors": [
    {{"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 1]}},
    {{"bufferView": 1, "componentType": 5123, "count": 36, "type": "SCALAR"}},
    {{"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [1, 0, 1]}},
    {{"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}}
  ],
  "meshes": [
    {{"name": "cube", "primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1}}]}},
    {{"name": "square", "primitives": [{{"attributes": {{"POSITION": 2}}, "indices": 3}}]}}
  ],
  "nodes": [
    {{"name": "ground", "scale": [8, 1, 8], "translation": [-4, 0, -4], "mesh": 1}},
    {{"name": "a", "translation": [0, 0, 0], "mesh": 0}},
    {{"name": "b", "translation": [0.5, 0.5, 0.2], "scale": [2, 1, 1], "mesh": 0}},
    {{"name": "c", "rotation": [0, 0.38268343, 0, 0.9238795], "translation": [-1, 0, 1], "mesh": 0}}
  ],
  "scenes": [{{"nodes": [0, 1, 2, 3]}}],
  "scene": 0
}}"#,
        len = bin.len()
    );
    let mut json = json.into_bytes();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

/// `bench` of one file in `flat` and `rebraided`; returns the two rows after
/// checking their keys and agreement.
fn bench_file(cwd: &Path, file: &Path) -> Vec<Value> {
    let json = cwd.join(format!(
        "{}.json",
        file.file_stem().unwrap().to_string_lossy()
    ));
    ok(
        cwd,
        &[
            "bench",
            s(file),
            "--modes",
            "flat,rebraided",
            "--width",
            "64",
            "--height",
            "36",
            "--reps",
            "1",
            "--threads",
            "1",
            "--json",
            s(&json),
        ],
    );
    let rows = read_rows(&json);
    assert_eq!(rows.len(), 2, "{rows:#?}");
    for r in &rows {
        check_row_keys(r, 64 * 36);
    }
    let flat = row(&rows, "flat", 1);
    assert!(
        flat["primary"]["hits"].as_u64().unwrap() > 0,
        "the default camera sees nothing of {}: {flat}",
        file.display()
    );
    check_agreement(&rows, flat, 1e-6);
    rows
}

#[test]
fn bench_small_obj_and_glb_files() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("parts.obj");
    std::fs::write(&obj, overlapping_obj(6)).unwrap();
    let rows = bench_file(dir.path(), &obj);
    let r = row(&rows, "rebraided", 1);
    assert_eq!(r["scene"], "parts");
    assert_eq!(r["objects"], 7);
    assert_eq!(r["triangles"], 12 * (1 + 6 * 4));

    let glb = dir.path().join("tiny.glb");
    std::fs::write(&glb, tiny_glb()).unwrap();
    let rows = bench_file(dir.path(), &glb);
    let r = row(&rows, "rebraided", 1);
    assert_eq!(r["objects"], 2, "{r}");
    assert_eq!(r["instances"], 4, "{r}");
    assert_eq!(r["triangles"], 2 + 3 * 12, "{r}");
}

#[test]
fn bench_real_glb_scene() {
    let Some(scenes) = scenes::scenes_dir_or_skip() else {
        return;
    };
    let glb = scenes.join("2CylinderEngine.glb");
    if !glb.is_file() {
        if std::env::var("CI").is_ok_and(|v| v == "true") {
            panic!("{} is missing and CI=true", glb.display());
        }
        eprintln!("SKIPPED: {} not found", glb.display());
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let rows = bench_file(dir.path(), &glb);
    let r = row(&rows, "flat", 1);
    assert_eq!(r["scene"], "2CylinderEngine");
    assert_eq!(r["triangles"], 121_496, "{r}");
}

#[test]
fn stats_library_json() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("s.json");
    let out = ok(
        dir.path(),
        &["stats", "library", "--scale", "0.02", "--json", s(&json)],
    );
    assert!(out.contains("library@0.02"), "{out}");
    let text = std::fs::read_to_string(&json).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 1, "one line per scene:\n{text}");
    let v: Value = serde_json::from_str(lines[0]).unwrap();
    assert_eq!(v["scene"], "library@0.02");
    assert_eq!(v["objects"], 28, "{v}");
    assert!(v["triangles"].as_u64().unwrap() > 0);
    assert!(v["overlap"].as_f64().unwrap() > 1.0, "{v}");
    let modes = v["modes"].as_array().expect("modes array");
    let names: Vec<&str> = modes.iter().map(|m| m["mode"].as_str().unwrap()).collect();
    assert_eq!(names, MODES);
    for m in modes {
        for k in [
            "build_ms",
            "sah_cost",
            "bytes",
            "top_nodes",
            "refs_initial",
            "refs_final",
            "refs_opened",
        ] {
            assert!(m.get(k).is_some(), "mode lacks '{k}': {m}");
        }
        assert!(m["sah_cost"].as_f64().unwrap() > 0.0, "{m}");
        assert!(m["bytes"].as_u64().unwrap() > 0, "{m}");
        // Embree's statistic counts the root once, then every leaf too.
        assert!(m["wide_sah_cost"].as_f64().unwrap() > 1.0, "{m}");
    }
    let sah = |i: usize| modes[i]["sah_cost"].as_f64().unwrap();
    assert!(sah(2) < sah(1), "re-braiding lowers the SAH cost: {v}");
    // The same by Embree's statistic of the wide layouts as traversed.
    let wide_sah = |i: usize| modes[i]["wide_sah_cost"].as_f64().unwrap();
    assert!(wide_sah(2) < wide_sah(1), "{v}");
    assert!(modes[2]["refs_opened"].as_u64().unwrap() > 0, "{v}");
    // The reinsertion options reach the trees: the re-braided top level
    // without it, the flat tree with it.
    let with = |extra: &[&str]| {
        let json = dir.path().join("r.json");
        let mut a = vec!["stats", "library", "--scale", "0.02", "--json", s(&json)];
        a.extend_from_slice(extra);
        ok(dir.path(), &a);
        let v: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        let m = v["modes"].as_array().unwrap().clone();
        [0, 2].map(|i| m[i]["sah_cost"].as_f64().unwrap())
    };
    let [_, top_off] = with(&["--reinsert", "off"]);
    assert!(top_off > sah(2), "{top_off} without, {} with", sah(2));
    let [flat_on, _] = with(&["--reinsert-objects", "0.2,3"]);
    assert!(flat_on < sah(0), "{flat_on} with, {} without", sah(0));
    // Embree's greedy collapse: wide trees of a higher statistic (the
    // default is the SAH-optimal collapse); the flat binary tree is the
    // same, the re-braided one not (opening follows the objects' wide nodes).
    let json = dir.path().join("g.json");
    let a = [
        "stats",
        "library",
        "--scale",
        "0.02",
        "--collapse",
        "greedy",
        "--json",
        s(&json),
    ];
    ok(dir.path(), &a);
    let g: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let greedy = g["modes"].as_array().unwrap();
    for i in [0, 2] {
        let (gw, ow) = (greedy[i]["wide_sah_cost"].as_f64().unwrap(), wide_sah(i));
        assert!(gw > ow, "mode {i}: greedy {gw}, optimal {ow}");
    }
    assert_eq!(greedy[0]["sah_cost"].as_f64().unwrap(), sah(0));
}

#[test]
fn stats_visits_per_ray() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("s.json");
    let out = ok(
        dir.path(),
        &[
            "stats",
            "library",
            "--scale",
            "0.02",
            "--visits",
            "48x27",
            "--json",
            s(&json),
        ],
    );
    assert!(out.contains("visits per ray"), "{out}");
    let v: Value = serde_json::from_str(std::fs::read_to_string(&json).unwrap().trim()).unwrap();
    let modes = v["modes"].as_array().expect("modes array");
    let visits = |i: usize, set: &str| -> (f64, f64, f64) {
        let p = &modes[i]["visits_per_ray"][set];
        let x = |k: usize| p[k].as_f64().unwrap();
        (x(0), x(1), x(2))
    };
    for (i, m) in modes.iter().enumerate() {
        for set in ["primary", "shadow", "diffuse"] {
            let (inner, leaves, entries) = visits(i, set);
            assert!(inner >= 1.0 && leaves > 0.0, "{set}: {m}");
            // Entries are leaves too; the flat mode has none.
            assert!((0.0..=leaves).contains(&entries), "{set}: {m}");
            if m["mode"] == "flat" {
                assert_eq!(entries, 0.0, "{set}: {m}");
            }
        }
    }
    // The two-level mode enters an object BVH for every hit it finds.
    assert!(visits(1, "primary").2 > 0.0, "{v}");
    // The library's objects overlap: a two-level walk enters many more of
    // them than the re-braided one, which opens the overlapping objects.
    assert!(visits(1, "primary").0 > visits(2, "primary").0, "{v}");
    let err = fails(dir.path(), &["stats", "library", "--visits", "48"]);
    assert!(err.contains("WIDTHxHEIGHT"), "{err}");
}

/// A reader that stops early (`rebraid stats library | head -1`) ends the
/// tool quietly: no panic about a broken pipe on stderr.
#[cfg(unix)]
#[test]
fn closed_stdout_ends_quietly() {
    use std::io::{BufRead, BufReader};
    use std::process::Stdio;
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(EXE)
        .args(["stats", "library", "--scale", "0.02"])
        .current_dir(dir.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("running the rebraid binary");
    let mut first = String::new();
    BufReader::new(child.stdout.take().expect("piped stdout"))
        .read_line(&mut first)
        .expect("reading the first line");
    // The reader is dropped here: the pipe is closed with output pending.
    let out = child.wait_with_output().expect("waiting for rebraid");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(first.starts_with("library"), "first line: {first:?}");
    assert!(!err.contains("panicked"), "stderr:\n{err}");
}

#[test]
fn bad_arguments_exit_with_one_error_line() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let small = ["--scale", "0.02", "--width", "8", "--height", "8"];
    let bench = |extra: &[&str]| {
        let mut a = vec!["bench", "--reps", "1", "--threads", "1"];
        a.extend_from_slice(&small);
        a.extend_from_slice(extra);
        fails(d, &a)
    };
    let e = fails(d, &["render", "--mode", "sideways"]);
    assert!(e.contains("sideways"), "{e}");
    let e = bench(&["--modes", "flat,sideways"]);
    assert!(e.contains("sideways"), "{e}");
    let e = bench(&["missing.obj"]);
    assert!(e.contains("missing.obj"), "{e}");
    let e = fails(d, &["render", "--camera", "1,2,3", "-o", "x.png"]);
    assert!(e.contains("--camera"), "{e}");
    let e = fails(d, &["render", "--threads", "0", "-o", "x.png"]);
    assert!(e.contains("--threads"), "{e}");
    let e = fails(d, &["bench", "--threads", "0"]);
    assert!(e.contains("--threads"), "{e}");
    let e = fails(d, &["bench", "--reps", "0"]);
    assert!(e.contains("--reps"), "{e}");
    let e = fails(d, &["render", "--scale", "-1", "-o", "x.png"]);
    assert!(e.contains("--scale"), "{e}");
    let e = fails(d, &["stats", "--scale", "0"]);
    assert!(e.contains("--scale"), "{e}");
    let e = fails(d, &["stats", "--reinsert", "0.1"]);
    assert!(
        e.contains("--reinsert") && e.contains("RATIO,PASSES"),
        "{e}"
    );
    let e = fails(d, &["stats", "--reinsert", "0.1,2,x"]);
    assert!(e.contains("RATIO,PASSES[,MAX]"), "{e}");
    // A value clap rejects: its own message, which lists the values.
    let out = run_in(d, &["stats", "--collapse", "best"]);
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{e}");
    assert!(
        e.starts_with("error: ") && e.contains("--collapse") && e.contains("greedy"),
        "{e}"
    );
    let e = fails(d, &["stats", "--reinsert-objects", "1.5,2"]);
    assert!(
        e.contains("--reinsert-objects") && e.contains("ratio"),
        "{e}"
    );
    std::fs::write(d.join("scene.stl"), "solid x\n").unwrap();
    let e = fails(d, &["stats", "scene.stl"]);
    assert!(e.contains("scene.stl") && e.contains("extension"), "{e}");
    std::fs::write(
        d.join("bad.obj"),
        "o a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 x7\n",
    )
    .unwrap();
    let e = bench(&["bad.obj"]);
    assert!(e.contains("bad.obj") && e.contains("line 6"), "{e}");
    // No image is left behind by a failed render.
    assert!(!d.join("x.png").exists());
    #[cfg(not(feature = "embree"))]
    {
        let e = bench(&["--embree"]);
        assert!(e.contains("embree"), "{e}");
    }
}

#[cfg(feature = "embree")]
#[test]
fn embree_rows_agree_with_ours() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("embree.json");
    let args = [
        "bench",
        "library",
        "--scale",
        "0.02",
        "--reps",
        "1",
        "--threads",
        "1",
        "--width",
        "64",
        "--height",
        "36",
        "--camera",
        AISLE,
        // Not the default: the worker processes must be given it.
        "--max-leaf",
        "4",
        "--json",
    ];
    let with_embree = [
        "--embree",
        "--embree-api",
        "single,stream",
        "--embree-flags",
        "default,robust",
    ];
    let out = ok(
        dir.path(),
        &[&args[..], &[s(&json)], &with_embree[..]].concat(),
    );
    assert!(out.contains("embree-flat"), "{out}");
    assert!(out.contains("rebraided / embree-two-level-stream"), "{out}");
    assert!(out.contains("rebraided / embree-flat-robust "), "{out}");
    // The gap to Embree's flat BVH split into structure and base.
    assert!(out.contains("rebraided / flat "), "{out}");
    assert!(out.contains("flat / embree-flat-robust-stream "), "{out}");
    let rows = read_rows(&json);
    assert_eq!(rows.len(), 11, "{rows:#?}");
    let embree = [
        "embree-flat",
        "embree-two-level",
        "embree-flat-stream",
        "embree-two-level-stream",
        "embree-flat-robust",
        "embree-two-level-robust",
        "embree-flat-robust-stream",
        "embree-two-level-robust-stream",
    ];
    for m in MODES.iter().chain(&embree) {
        check_row_keys(row(&rows, m, 1), 64 * 36);
    }
    check_agreement(&rows, row(&rows, "flat", 1), 1e-4);
    // With Embree our modes run in worker processes: the same trees as in
    // this process (the scene options reached them).
    let alone = dir.path().join("alone.json");
    ok(dir.path(), &[&args[..], &[s(&alone)]].concat());
    let alone = read_rows(&alone);
    for m in MODES {
        let (a, b) = (row(&rows, m, 1), row(&alone, m, 1));
        for key in ["sah_cost", "bytes", "refs_opened", "triangles"] {
            assert_eq!(a[key], b[key], "{m} {key}");
        }
    }
}
