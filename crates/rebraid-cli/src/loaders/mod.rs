//! Scene loaders: Wavefront OBJ, glTF 2.0 / GLB and PLY files into a
//! [`rebraid::SceneDesc`].
//!
//! [`load_scene`] reads a file and dispatches on its extension; each format
//! module also has an entry point that parses from memory
//! ([`obj::parse_obj`], [`ply::parse_ply`], [`gltf::parse_gltf`]) so that
//! tests and fuzzers can feed them bytes without touching the file system.
//!
//! Every failure is a [`LoadError`] that names the file and, where the format
//! has them, the line (OBJ, ASCII PLY) or the element (glTF mesh / primitive /
//! node, PLY element index) at fault. The loaders never panic on their input:
//! the fuzz targets in `fuzz/` and the smoke test `tests/loader_fuzz.rs` check
//! that.

use std::fmt;
use std::path::{Path, PathBuf};

use rebraid::SceneDesc;

pub mod gltf;
pub mod obj;
pub mod ply;

/// What becomes one object of the scene.
///
/// OBJ honours all four, and then joins the objects that share a vertex
/// position (pieces of one surface; [`LoadOptions::keep_touching_apart`]
/// keeps them apart); glTF uses [`Split::Material`] for "one object per
/// primitive" and one object per mesh otherwise; PLY always gives one object.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Split {
    /// One object per `o` statement (OBJ). When the file has at most one
    /// `o`, the OBJ loader falls back to [`Split::Material`]: a single `o`
    /// says nothing about the structure, materials usually do.
    #[default]
    Object,
    /// One object per `g` statement (OBJ).
    Group,
    /// One object per material (`usemtl` in OBJ, primitive in glTF).
    Material,
    /// Everything in one object.
    None,
}

/// Options shared by every loader.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LoadOptions {
    pub split: Split,
    /// glTF only: bake every placement of a mesh into its own `placed`
    /// object instead of emitting instances (for comparing against a flat
    /// BVH over the same world geometry).
    pub flatten_instances: bool,
    /// OBJ only: keep every object of the split apart, even those whose
    /// triangles share a vertex position (by default such objects are joined
    /// into one: see [`obj`]).
    pub keep_touching_apart: bool,
}

/// Where in a file something went wrong.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Location {
    /// Nowhere in particular (the whole file).
    File,
    /// A 1-based line number (OBJ, ASCII PLY).
    Line(usize),
    /// An element of a binary or structured format, described in words,
    /// e.g. `mesh 3 ("door") primitive 1` or `face 1234`.
    Element(String),
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Location::File => Ok(()),
            Location::Line(l) => write!(f, ", line {l}"),
            Location::Element(e) => write!(f, ", {e}"),
        }
    }
}

/// Why a scene could not be loaded. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("{}: unknown scene file extension {ext:?} (expected .obj, .gltf, .glb or .ply)", file.display())]
    UnknownExtension { file: PathBuf, ext: String },
    #[error("{}: cannot read: {source}", file.display())]
    Io {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}{at}: file ends too early: {detail}", file.display())]
    Truncated {
        file: PathBuf,
        at: Location,
        detail: String,
    },
    #[error("{}{at}: {detail}", file.display())]
    Syntax {
        file: PathBuf,
        at: Location,
        detail: String,
    },
    #[error("{}{at}: bad index: {detail}", file.display())]
    BadIndex {
        file: PathBuf,
        at: Location,
        detail: String,
    },
    #[error("{}{at}: non-finite number: {detail}", file.display())]
    NonFinite {
        file: PathBuf,
        at: Location,
        detail: String,
    },
    /// A coordinate beyond `rebraid::mesh::MAX_COORDINATE`.
    #[error("{}{at}: number out of range: {detail}", file.display())]
    OutOfRange {
        file: PathBuf,
        at: Location,
        detail: String,
    },
    #[error("{}{at}: unsupported content: {detail}", file.display())]
    Unsupported {
        file: PathBuf,
        at: Location,
        detail: String,
    },
}

impl LoadError {
    /// The file the error is about.
    pub fn file(&self) -> &Path {
        match self {
            LoadError::UnknownExtension { file, .. }
            | LoadError::Io { file, .. }
            | LoadError::Truncated { file, .. }
            | LoadError::Syntax { file, .. }
            | LoadError::BadIndex { file, .. }
            | LoadError::NonFinite { file, .. }
            | LoadError::OutOfRange { file, .. }
            | LoadError::Unsupported { file, .. } => file,
        }
    }

    /// The line or element at fault, when there is one.
    pub fn location(&self) -> Option<&Location> {
        match self {
            LoadError::Truncated { at, .. }
            | LoadError::Syntax { at, .. }
            | LoadError::BadIndex { at, .. }
            | LoadError::NonFinite { at, .. }
            | LoadError::OutOfRange { at, .. }
            | LoadError::Unsupported { at, .. } => Some(at),
            _ => None,
        }
    }
}

/// A loaded scene plus the things the loader skipped or fixed up on the way
/// (non-triangle glTF primitives, degenerate placements...), one sentence each.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Loaded {
    pub scene: SceneDesc,
    pub warnings: Vec<String>,
}

/// Load a scene file, choosing the format by extension (case-insensitive:
/// `obj`, `gltf`, `glb`, `ply`). Warnings are dropped; see
/// [`load_scene_with_warnings`] to get them.
pub fn load_scene(path: &Path, opts: &LoadOptions) -> Result<SceneDesc, LoadError> {
    load_scene_with_warnings(path, opts).map(|l| l.scene)
}

/// [`load_scene`], also returning the loader's warnings.
pub fn load_scene_with_warnings(path: &Path, opts: &LoadOptions) -> Result<Loaded, LoadError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    // Check the extension before touching the file so that a typo in the
    // extension is reported as such rather than as a parse error.
    if !matches!(ext.as_str(), "obj" | "gltf" | "glb" | "ply") {
        return Err(LoadError::UnknownExtension {
            file: path.to_path_buf(),
            ext,
        });
    }
    let bytes = std::fs::read(path).map_err(|source| LoadError::Io {
        file: path.to_path_buf(),
        source,
    })?;
    match ext.as_str() {
        "obj" => obj::parse_obj(&bytes, path, opts).map(|scene| Loaded {
            scene,
            warnings: Vec::new(),
        }),
        "ply" => ply::parse_ply(&bytes, path, opts).map(|scene| Loaded {
            scene,
            warnings: Vec::new(),
        }),
        _ => gltf::parse_gltf(&bytes, path, path.parent(), opts),
    }
}

/// Turn the core's mesh validation error into a load error for `file` at `at`.
pub(crate) fn mesh_error(file: &Path, at: Location, e: rebraid::Error) -> LoadError {
    let detail = e.to_string();
    let file = file.to_path_buf();
    match e {
        rebraid::Error::NonFiniteVertex { .. } | rebraid::Error::InvalidTransform(_) => {
            LoadError::NonFinite { file, at, detail }
        }
        rebraid::Error::VertexOutOfRange { .. } => LoadError::OutOfRange { file, at, detail },
        rebraid::Error::IndexOutOfRange { .. } => LoadError::BadIndex { file, at, detail },
        _ => LoadError::Unsupported { file, at, detail },
    }
}
