//! A tiny Wavefront OBJ reader for the real test scenes, plus where to find them.
//!
//! The scenes under `shared/scenes` hold only `o`, `v` and `f` lines, so this
//! reads positions and faces (fan-triangulating polygons, accepting `v/vt/vn`
//! tokens and negative indices) and ignores everything else. Shared by the
//! tests and the benches through `#[path]`, so it depends on nothing but the
//! crate.

use std::path::Path;

#[path = "../support/scenes.rs"]
mod scenes;
#[allow(unused_imports)] // not every test crate reads real scenes
pub use scenes::scene_path_or_skip;

use rebraid::TriangleMesh;
use rebraid::glam::Vec3;

/// Parse the positions and faces of an OBJ file into one mesh.
pub fn load_obj(path: &Path) -> TriangleMesh {
    let text =
        std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    parse_obj(&text).unwrap_or_else(|e| panic!("parsing {}: {e}", path.display()))
}

/// Parse OBJ text (see the module docs for what is understood).
pub fn parse_obj(text: &str) -> Result<TriangleMesh, String> {
    let mut positions = Vec::new();
    let mut indices = Vec::new();
    for (line_no, line) in text.lines().enumerate() {
        let mut tokens = line.split_whitespace();
        match tokens.next() {
            Some("v") => {
                let mut xyz = [0.0f32; 3];
                for c in &mut xyz {
                    *c = tokens
                        .next()
                        .and_then(|t| t.parse().ok())
                        .ok_or_else(|| format!("line {}: bad vertex", line_no + 1))?;
                }
                positions.push(Vec3::from_array(xyz));
            }
            Some("f") => {
                let face: Vec<u32> = tokens
                    .map(|t| {
                        let i: i64 = t
                            .split('/')
                            .next()
                            .and_then(|s| s.parse().ok())
                            .ok_or_else(|| format!("line {}: bad face index {t:?}", line_no + 1))?;
                        let i = if i < 0 {
                            positions.len() as i64 + i
                        } else {
                            i - 1
                        };
                        u32::try_from(i).map_err(|_| {
                            format!("line {}: face index {t} out of range", line_no + 1)
                        })
                    })
                    .collect::<Result<_, _>>()?;
                for k in 1..face.len().saturating_sub(1) {
                    indices.push([face[0], face[k], face[k + 1]]);
                }
            }
            _ => {}
        }
    }
    TriangleMesh::new(positions, indices).map_err(|e| e.to_string())
}
