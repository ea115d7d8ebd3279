//! A stable-toolchain stand-in for the cargo-fuzz targets in `fuzz/`: feed
//! thousands of random and mutated inputs to the OBJ, PLY and glTF entry
//! points and check that they never panic (and that whatever parses
//! validates).
//!
//! Seeded: `REBRAID_FUZZ_SEED` (default 1) and `REBRAID_FUZZ_ITERS` (default
//! 3000 per parser) make a longer or different run; a failure prints the
//! input so it can become a regression case.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;
use rebraid_cli::loaders::gltf::parse_gltf;
use rebraid_cli::loaders::obj::parse_obj;
use rebraid_cli::loaders::ply::parse_ply;
use rebraid_cli::loaders::{LoadOptions, Split};
use support::gltf::{QUAD, base64, glb, glb_buffer, glb_bytes, tiny_gltf_embedded, tiny_gltf_json};

mod support;

fn env_u64(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn run_obj(data: &[u8]) {
    for (split, keep_touching_apart) in [Split::Object, Split::Group, Split::Material, Split::None]
        .into_iter()
        .flat_map(|s| [(s, false), (s, true)])
    {
        let opts = LoadOptions {
            split,
            keep_touching_apart,
            ..LoadOptions::default()
        };
        if let Ok(s) = parse_obj(data, Path::new("fuzz.obj"), &opts) {
            s.validate().expect("a parsed OBJ scene validates");
        }
    }
}

fn run_ply(data: &[u8]) {
    if let Ok(s) = parse_ply(data, Path::new("fuzz.ply"), &LoadOptions::default()) {
        s.validate().expect("a parsed PLY scene validates");
    }
}

/// glTF or GLB bytes in every mode that changes what the loader builds:
/// one object per mesh or per primitive, instances or baked placements.
fn run_gltf(data: &[u8]) {
    for split in [Split::Object, Split::Material] {
        for flatten_instances in [false, true] {
            let opts = LoadOptions {
                split,
                flatten_instances,
                ..LoadOptions::default()
            };
            if let Ok(l) = parse_gltf(data, Path::new("fuzz.glb"), None, &opts) {
                l.scene.validate().expect("a parsed glTF scene validates");
            }
        }
    }
}

/// A (mutated) JSON document wrapped as a well-formed GLB around the tiny
/// buffer, so that mutations reach the document's meshes, accessors and
/// nodes instead of stopping at the container's lengths.
fn run_gltf_json_in_glb(json: &[u8]) {
    run_gltf(&glb_bytes(json, &glb_buffer(&QUAD, [0, 1, 2])));
}

/// Run `f` on `data`; on a panic, show the input before failing.
fn check(what: &str, f: fn(&[u8]), data: &[u8]) {
    if catch_unwind(AssertUnwindSafe(|| f(data))).is_err() {
        panic!(
            "{what} parser panicked on input {:?}",
            String::from_utf8_lossy(data)
        );
    }
}

/// One random mutation: flip, insert, delete, duplicate a slice, truncate,
/// or splice in a token the format cares about.
fn mutate(rng: &mut Pcg64Mcg, data: &mut Vec<u8>, tokens: &[&[u8]]) {
    let n = data.len();
    match rng.gen_range(0..6) {
        0 if n > 0 => {
            let i = rng.gen_range(0..n);
            data[i] ^= 1 << rng.gen_range(0..8);
        }
        1 => {
            let i = rng.gen_range(0..=n);
            data.insert(i, rng.r#gen());
        }
        2 if n > 0 => {
            let i = rng.gen_range(0..n);
            let j = (i + rng.gen_range(1..16)).min(n);
            data.drain(i..j);
        }
        3 if n > 0 => {
            let i = rng.gen_range(0..n);
            let j = (i + rng.gen_range(1..64)).min(n);
            let k = rng.gen_range(0..=n);
            let piece = data[i..j].to_vec();
            data.splice(k..k, piece);
        }
        4 if n > 0 => data.truncate(rng.gen_range(0..n)),
        _ => {
            let t = tokens[rng.gen_range(0..tokens.len())];
            let i = rng.gen_range(0..=n);
            data.splice(i..i, t.iter().copied());
        }
    }
}

const OBJ_TOKENS: &[&[u8]] = &[
    b"v ",
    b"f ",
    b"o a\n",
    b"g b\n",
    b"usemtl c\n",
    b"\n",
    b" ",
    b"/",
    b"//",
    b"-1",
    b"0",
    b"1",
    b"-9999999999",
    b"4294967296",
    b"1e39",
    b"nan",
    b"inf",
    b"#",
    b"\r\n",
    b"cstype",
    b"vt 0 0\n",
    b"fo ",
    b"\\\n",
];

const PLY_TOKENS: &[&[u8]] = &[
    b"element vertex 4294967295\n",
    b"element face 18446744073709551615\n",
    b"property list uchar int vertex_indices\n",
    b"property double x\n",
    b"255 ",
    b"4000000000 ",
    b"-1 ",
    b"end_header\n",
    b"format binary_little_endian 1.0\n",
    b"format binary_big_endian 1.0\n",
    b"\xff\xff\xff\xff",
    b"\n",
    b"1e400 ",
];

const GLTF_TOKENS: &[&[u8]] = &[
    b"-1",
    b"0",
    b"1",
    b"3",
    b"4294967295",
    b"18446744073709551616",
    b"1e39",
    b"-0",
    b"0.5",
    b"null",
    b"\"VEC2\"",
    b"\"MAT4\"",
    b"\"SCALAR\"",
    b"5120",
    b"5121",
    b"5125",
    b"5126",
    b", \"byteStride\": 4",
    b", \"byteStride\": 255",
    b", \"children\": [0]",
    b", \"sparse\": {}",
    b", \"matrix\": [0,0,0,0, 0,0,0,0, 0,0,0,0, 0,0,0,0]",
    b", \"scale\": [1e38, 1e38, 1e38]",
    b"[",
    b"]",
    b"{",
    b"}",
    b",",
    b"\"",
];

/// Interesting values for a number of a JSON document: indices past every
/// array, negative and huge counts, offsets and strides, component types
/// and modes glTF does or does not define.
const GLTF_NUMBERS: &[&str] = &[
    "0",
    "1",
    "2",
    "3",
    "4",
    "5",
    "6",
    "7",
    "8",
    "12",
    "47",
    "48",
    "55",
    "56",
    "57",
    "64",
    "255",
    "256",
    "-1",
    "65535",
    "2147483647",
    "4294967295",
    "4294967296",
    "9007199254740993",
    "1e20",
    "5120",
    "5121",
    "5122",
    "5123",
    "5125",
    "5126",
    "0.5",
    "1e39",
    "-1e39",
];

/// Replace one number of a JSON document with one of [`GLTF_NUMBERS`]: the
/// document stays JSON, so the mutation reaches the loader's checks
/// (accessor ranges, node graphs, transforms) instead of the JSON parser's.
fn mutate_json_number(rng: &mut Pcg64Mcg, data: &mut Vec<u8>) {
    let is_num = |b: u8| b.is_ascii_digit() || b == b'.' || b == b'-' || b == b'e';
    let mut spans = Vec::new();
    let mut i = 0;
    while i < data.len() {
        if data[i].is_ascii_digit() && (i == 0 || !data[i - 1].is_ascii_alphanumeric()) {
            let mut b = i;
            if b > 0 && data[b - 1] == b'-' {
                b -= 1;
            }
            let mut e = i;
            while e < data.len() && is_num(data[e]) {
                e += 1;
            }
            spans.push((b, e));
            i = e;
        } else {
            i += 1;
        }
    }
    if spans.is_empty() {
        return;
    }
    let (b, e) = spans[rng.gen_range(0..spans.len())];
    let v = GLTF_NUMBERS[rng.gen_range(0..GLTF_NUMBERS.len())];
    data.splice(b..e, v.bytes());
}

fn obj_seeds() -> Vec<Vec<u8>> {
    let mut seeds: Vec<Vec<u8>> = vec![
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\no a\ng g\nusemtl m\nf 1 2 3 4\nf -1 -2 -3\nf 1/1/1 2//2 3/3\n".to_vec(),
        b"o x\nv 1 2 3 1\nv 4 5 6\nv 7 8 9\nf 1 2 3\no y\nusemtl q\nf 3 2 1\n".to_vec(),
    ];
    let dir = std::env::var_os("REBRAID_SCENES")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| concat!(env!("CARGO_MANIFEST_DIR"), "/../../../shared/scenes").into());
    for f in ["openarena_oa_thor.obj", "samurai_monastery.obj"] {
        if let Ok(bytes) = std::fs::read(dir.join(f)) {
            // The start (vertices) and a slice with faces near the end.
            seeds.push(bytes[..bytes.len().min(3000)].to_vec());
            let tail = bytes.len().saturating_sub(3000);
            seeds.push(
                bytes[..600.min(bytes.len())]
                    .iter()
                    .chain(&bytes[tail..])
                    .copied()
                    .collect(),
            );
        }
    }
    seeds
}

fn ply_seeds() -> Vec<Vec<u8>> {
    let ascii = b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty double z\n\
        element face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n4 0 1 2 3\n"
        .to_vec();
    let mut seeds = vec![ascii];
    for big in [false, true] {
        let fmt = if big {
            "binary_big_endian"
        } else {
            "binary_little_endian"
        };
        let mut b = format!(
            "ply\nformat {fmt} 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
             element face 1\nproperty list uchar uint vertex_indices\nend_header\n"
        )
        .into_bytes();
        for v in [0.0f32, 0., 0., 1., 0., 0., 0., 1., 0.] {
            b.extend(if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            });
        }
        b.push(3);
        for i in [0u32, 1, 2] {
            b.extend(if big {
                i.to_be_bytes()
            } else {
                i.to_le_bytes()
            });
        }
        seeds.push(b);
    }
    seeds
}

/// A format-aware mutation, applied instead of [`mutate`] half of the time.
type Mutation = fn(&mut Pcg64Mcg, &mut Vec<u8>);

fn fuzz(what: &str, f: fn(&[u8]), seeds: &[Vec<u8>], tokens: &[&[u8]], salt: u64) {
    fuzz_with(what, f, seeds, tokens, None, salt);
}

fn fuzz_with(
    what: &str,
    f: fn(&[u8]),
    seeds: &[Vec<u8>],
    tokens: &[&[u8]],
    aware: Option<Mutation>,
    salt: u64,
) {
    for s in seeds {
        check(what, f, s);
    }
    let iters = env_u64("REBRAID_FUZZ_ITERS", 3000);
    let mut rng = Pcg64Mcg::seed_from_u64(env_u64("REBRAID_FUZZ_SEED", 1) ^ salt);
    for it in 0..iters {
        let data: Vec<u8> = if it % 4 == 0 {
            // Pure noise, sometimes only from the format's own tokens.
            if rng.gen_bool(0.5) {
                (0..rng.gen_range(0..256)).map(|_| rng.r#gen()).collect()
            } else {
                (0..rng.gen_range(0..64))
                    .flat_map(|_| tokens[rng.gen_range(0..tokens.len())].to_vec())
                    .collect()
            }
        } else {
            let mut d = seeds[rng.gen_range(0..seeds.len())].clone();
            for _ in 0..rng.gen_range(1..6) {
                match aware {
                    Some(m) if rng.gen_bool(0.5) => m(&mut rng, &mut d),
                    _ => mutate(&mut rng, &mut d, tokens),
                }
            }
            d
        };
        check(what, f, &data);
    }
}

/// Regression: a binary element with no properties and a huge count used to
/// spin through the count without reading a byte.
#[test]
fn ply_huge_empty_binary_element_is_quick() {
    let t = std::time::Instant::now();
    let data = b"ply\nformat binary_little_endian 1.0\nelement junk 18446744073709551615\n\
        element vertex 0\nproperty float x\nproperty float y\nproperty float z\n\
        element face 0\nproperty list uchar int vertex_indices\nend_header\n";
    let _ = parse_ply(data, Path::new("empty.ply"), &LoadOptions::default());
    assert!(t.elapsed().as_secs() < 5);
}

#[test]
fn obj_parser_survives_random_and_mutated_input() {
    fuzz("OBJ", run_obj, &obj_seeds(), OBJ_TOKENS, 0x0b1);
}

#[test]
fn ply_parser_survives_random_and_mutated_input() {
    fuzz("PLY", run_ply, &ply_seeds(), PLY_TOKENS, 0x91e);
}

/// The glTF seeds load: the fuzz runs start from documents that reach the
/// meshes and the node graph, not from ones the container check rejects.
fn check_gltf_seed(data: &[u8]) {
    let l = parse_gltf(data, Path::new("seed.gltf"), None, &LoadOptions::default())
        .unwrap_or_else(|e| panic!("seed does not load: {e}"));
    assert_eq!(l.scene.objects.len(), 2, "both meshes");
    assert_eq!(l.scene.instances.len(), 2, "both placed nodes");
}

#[test]
fn base64_matches_known_encodings() {
    assert_eq!(base64(b""), "");
    assert_eq!(base64(b"f"), "Zg==");
    assert_eq!(base64(b"fo"), "Zm8=");
    assert_eq!(base64(b"foo"), "Zm9v");
    assert_eq!(base64(b"foobar"), "Zm9vYmFy");
}

#[test]
fn gltf_parser_survives_random_and_mutated_input() {
    let json = tiny_gltf_json(3, "", "[0, 0, 0]");
    let glb_seed = glb(&json, &glb_buffer(&QUAD, [0, 1, 2]));
    let embedded = tiny_gltf_embedded();
    check_gltf_seed(&glb_seed);
    check_gltf_seed(embedded.as_bytes());
    // The container and the embedded form as they come, and the document
    // mutated inside a well-formed container.
    let raw = [glb_seed, embedded.into_bytes()];
    fuzz_with(
        "glTF",
        run_gltf,
        &raw,
        GLTF_TOKENS,
        Some(mutate_json_number),
        0x91f,
    );
    fuzz_with(
        "glTF (JSON in GLB)",
        run_gltf_json_in_glb,
        &[json.into_bytes()],
        GLTF_TOKENS,
        Some(mutate_json_number),
        0x91b,
    );
}
