//! Scene arguments of the commands: a file path or `library`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use rebraid::SceneDesc;
use rebraid::procedural::{LibraryParams, library, separated};

use crate::loaders::{LoadOptions, load_scene};

/// A scene named on the command line.
#[derive(Clone, Debug, PartialEq)]
pub enum SceneInput {
    /// The built-in procedural library (the paper's "library incident").
    Library {
        scale: f32,
        seed: u64,
    },
    /// 256 separated objects on a grid, no two boxes overlapping (the case
    /// where re-braiding must cost nearly nothing); `scale` 1.0 is about a
    /// million triangles.
    Grid {
        scale: f32,
        seed: u64,
    },
    File(PathBuf),
}

impl SceneInput {
    /// `library` or a path; paths must exist.
    pub fn parse(arg: &str, scale: f32, seed: u64) -> anyhow::Result<Self> {
        if arg == "library" || arg == "grid" {
            if !(scale.is_finite() && scale > 0.0) {
                bail!("--scale must be a positive number, got {scale}");
            }
            return Ok(if arg == "grid" {
                SceneInput::Grid { scale, seed }
            } else {
                SceneInput::Library { scale, seed }
            });
        }
        let p = Path::new(arg);
        if !p.exists() {
            bail!("scene '{arg}' is neither `library`, `grid` nor an existing file");
        }
        Ok(SceneInput::File(p.to_path_buf()))
    }

    /// A short name for tables and JSON.
    pub fn name(&self) -> String {
        match self {
            SceneInput::Library { scale, .. } => format!("library@{scale}"),
            SceneInput::Grid { scale, .. } => format!("grid@{scale}"),
            SceneInput::File(p) => p
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| p.display().to_string()),
        }
    }

    /// Load or generate the scene; returns it with the milliseconds it took.
    pub fn load(&self, opts: &LoadOptions) -> anyhow::Result<(SceneDesc, f64)> {
        let t = Instant::now();
        let desc = match self {
            SceneInput::Grid { scale, seed } => {
                separated(16, ((4096.0 * scale) as usize).clamp(1, 1 << 20), *seed)
            }
            SceneInput::Library { scale, seed } => library(&LibraryParams {
                scale: *scale,
                seed: *seed,
            }),
            SceneInput::File(p) => {
                load_scene(p, opts).with_context(|| format!("loading {}", p.display()))?
            }
        };
        if desc.world_triangles() == 0 {
            bail!("scene '{}' has no triangles", self.name());
        }
        Ok((desc, t.elapsed().as_secs_f64() * 1e3))
    }
}
