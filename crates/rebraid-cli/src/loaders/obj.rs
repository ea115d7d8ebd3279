//! Wavefront OBJ: positions and polygon faces, split into objects by `o`,
//! `g` or `usemtl` (see [`Split`]).
//!
//! # Why a hand-written parser and not `tobj`
//!
//! The plan was `tobj::load_obj_buf`, but it cannot meet two requirements:
//!
//! - **Splitting.** tobj starts a new model at both `o` *and* `g` (they share
//!   one code path), and at every `usemtl`, so [`Split::Object`] and
//!   [`Split::Group`] cannot be told apart, and a material that comes back
//!   later becomes a second model. Regrouping its models afterwards would need
//!   the very statement stream tobj hides.
//! - **Error lines.** tobj reports neither the line nor, for bad indices, the
//!   face; recovering them needs a second pass over the text that repeats half
//!   of the parsing anyway.
//!
//! What is needed is tiny (`v`, `f`, `o`, `g`, `usemtl`), so this module is a
//! single streaming pass over the bytes that knows the line number of every
//! statement. It is also faster than tobj's per-line `String` allocations:
//! the shared 2-7 MB scenes load in a few tens of milliseconds in release.
//!
//! Accepted syntax: `v x y z [w]` (and the common `v x y z r g b` colour
//! extension; only x, y, z are kept), `f`/`fo` with `a`, `a/b`, `a//c` or
//! `a/b/c` vertices, positive (1-based) or negative (relative) indices,
//! polygons of any size (fan-triangulated), `#` comments, CRLF line ends.
//! Face indices must refer to vertices defined earlier in the file (as the
//! OBJ specification says). Normals, texture coordinates, smoothing groups,
//! lines, points and material libraries are ignored; free-form geometry
//! (`cstype`, `curv`, `surf`...) is rejected as unsupported, and so is a file
//! without a single triangle.

use std::collections::HashMap;
use std::path::Path;

use glam::Vec3;
use rebraid::{ObjectDesc, SceneDesc, TriangleMesh};

use super::{LoadError, LoadOptions, Location, Split, mesh_error};

/// Parse OBJ text. `file` only names the source in errors and gives the
/// fallback object name; nothing is read from disk (material libraries are
/// ignored).
pub fn parse_obj(bytes: &[u8], file: &Path, opts: &LoadOptions) -> Result<SceneDesc, LoadError> {
    let mut p = Parser::new(file, bytes);
    p.run()?;
    p.finish(opts.split, !opts.keep_touching_apart)
}

/// A run of consecutive triangles that share their object, group and material.
struct Run {
    first_tri: usize,
    keys: [u32; 3],
}

/// Interned names of one kind (objects, groups or materials); id 0 is the
/// name of faces that come before any statement of that kind.
struct Names {
    names: Vec<String>,
    ids: HashMap<String, u32>,
}

impl Names {
    fn new() -> Self {
        Names {
            names: vec![String::new()],
            ids: HashMap::new(),
        }
    }

    fn intern(&mut self, name: &str) -> u32 {
        if let Some(&id) = self.ids.get(name) {
            return id;
        }
        let id = self.names.len() as u32;
        self.names.push(name.to_owned());
        self.ids.insert(name.to_owned(), id);
        id
    }
}

#[derive(Clone, Copy)]
enum Kind {
    Syntax,
    BadIndex,
    NonFinite,
    OutOfRange,
    Unsupported,
}

const OBJECT: usize = 0;
const GROUP: usize = 1;
const MATERIAL: usize = 2;

struct Parser<'a> {
    file: &'a Path,
    bytes: &'a [u8],
    line: usize,
    positions: Vec<Vec3>,
    tris: Vec<[u32; 3]>,
    runs: Vec<Run>,
    names: [Names; 3],
    current: [u32; 3],
    object_statements: usize,
    poly: Vec<u32>,
}

/// Statements that are valid OBJ but carry nothing a triangle BVH needs.
const IGNORED: &[&[u8]] = &[
    b"vt",
    b"vn",
    b"vp",
    b"s",
    b"mtllib",
    b"l",
    b"p",
    b"lod",
    b"maplib",
    b"usemap",
    b"shadow_obj",
    b"trace_obj",
    b"bevel",
    b"c_interp",
    b"d_interp",
    b"mg",
    b"ctech",
    b"stech",
];

/// Free-form geometry statements: real content we cannot triangulate.
const FREE_FORM: &[&[u8]] = &[
    b"cstype", b"deg", b"bmat", b"step", b"curv", b"curv2", b"surf", b"parm", b"trim", b"hole",
    b"scrv", b"sp", b"end", b"con",
];

impl<'a> Parser<'a> {
    fn new(file: &'a Path, bytes: &'a [u8]) -> Self {
        // About 30 bytes per vertex line and as many per face line in
        // typical files: reserve so the vectors rarely grow.
        let guess = (bytes.len() / 64).min(1 << 24);
        Parser {
            file,
            bytes,
            line: 0,
            positions: Vec::with_capacity(guess),
            tris: Vec::with_capacity(guess),
            runs: Vec::new(),
            names: [Names::new(), Names::new(), Names::new()],
            current: [0; 3],
            object_statements: 0,
            poly: Vec::with_capacity(8),
        }
    }

    /// An error at the current line. A syntax error on the last line of a
    /// file that does not end with a newline is most likely a cut-off file,
    /// so it is reported as truncated.
    fn err(&self, kind: Kind, detail: String) -> LoadError {
        let file = self.file.to_path_buf();
        let at = Location::Line(self.line);
        match kind {
            Kind::Syntax
                if !self.bytes.ends_with(b"\n")
                    && self.bytes.iter().filter(|&&b| b == b'\n').count() + 1 == self.line =>
            {
                LoadError::Truncated { file, at, detail }
            }
            Kind::Syntax => LoadError::Syntax { file, at, detail },
            Kind::BadIndex => LoadError::BadIndex { file, at, detail },
            Kind::NonFinite => LoadError::NonFinite { file, at, detail },
            Kind::OutOfRange => LoadError::OutOfRange { file, at, detail },
            Kind::Unsupported => LoadError::Unsupported { file, at, detail },
        }
    }

    fn run(&mut self) -> Result<(), LoadError> {
        let bytes = self.bytes;
        for raw in bytes.split(|&b| b == b'\n') {
            self.line += 1;
            let mut line = raw;
            if let Some(i) = line.iter().position(|&b| b == b'#') {
                line = &line[..i];
            }
            let mut tokens = line
                .split(|&b| b == b' ' || b == b'\t' || b == b'\r' || b == 0x0c)
                .filter(|t| !t.is_empty());
            let Some(keyword) = tokens.next() else {
                continue;
            };
            // What follows the keyword (which indentation may put anywhere).
            let rest = &line[keyword.as_ptr() as usize - line.as_ptr() as usize + keyword.len()..];
            match keyword {
                b"v" => self.vertex(tokens)?,
                b"f" | b"fo" => self.face(tokens)?,
                b"o" => {
                    self.object_statements += 1;
                    self.current[OBJECT] = self.name_statement(OBJECT, rest);
                }
                b"g" => self.current[GROUP] = self.name_statement(GROUP, rest),
                b"usemtl" => self.current[MATERIAL] = self.name_statement(MATERIAL, rest),
                k if IGNORED.contains(&k) => {}
                k if FREE_FORM.contains(&k) => {
                    return Err(self.err(
                        Kind::Unsupported,
                        format!(
                            "free-form geometry (`{}`) is not supported",
                            String::from_utf8_lossy(k)
                        ),
                    ));
                }
                // Other all-letter keywords are vendor extensions: skip them.
                // Anything else means this is not OBJ text at all.
                k if k.iter().all(|b| b.is_ascii_alphanumeric() || *b == b'_') => {}
                k => {
                    return Err(self.err(
                        Kind::Syntax,
                        format!(
                            "not an OBJ statement: {:?}",
                            String::from_utf8_lossy(&k[..k.len().min(32)])
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The name after `o`, `g` or `usemtl`: the rest of the line, trimmed.
    fn name_statement(&mut self, kind: usize, rest: &[u8]) -> u32 {
        let rest = String::from_utf8_lossy(rest);
        let name = rest.trim();
        if name.is_empty() {
            return 0;
        }
        self.names[kind].intern(name)
    }

    fn vertex<'t>(&mut self, tokens: impl Iterator<Item = &'t [u8]>) -> Result<(), LoadError> {
        let mut xyz = [0.0f32; 3];
        let mut n = 0;
        for t in tokens {
            if n >= 7 {
                return Err(self.err(
                    Kind::Syntax,
                    "a vertex has at most 7 numbers (x y z [w] or x y z r g b)".into(),
                ));
            }
            let v = std::str::from_utf8(t)
                .ok()
                .and_then(|s| s.parse::<f32>().ok())
                .ok_or_else(|| {
                    self.err(
                        Kind::Syntax,
                        format!(
                            "not a number: {:?}",
                            String::from_utf8_lossy(&t[..t.len().min(32)])
                        ),
                    )
                })?;
            if n < 3 {
                if !v.is_finite() {
                    return Err(self.err(
                        Kind::NonFinite,
                        format!(
                            "vertex {} coordinate {:?}",
                            self.positions.len() + 1,
                            String::from_utf8_lossy(t)
                        ),
                    ));
                }
                if v.abs() > rebraid::mesh::MAX_COORDINATE {
                    return Err(self.err(
                        Kind::OutOfRange,
                        format!(
                            "vertex {} coordinate {} is beyond +-{}",
                            self.positions.len() + 1,
                            String::from_utf8_lossy(t),
                            rebraid::mesh::MAX_COORDINATE
                        ),
                    ));
                }
                xyz[n] = v;
            }
            n += 1;
        }
        if n < 3 {
            return Err(self.err(
                Kind::Syntax,
                format!("a vertex needs x, y and z, got {n} numbers"),
            ));
        }
        if self.positions.len() >= u32::MAX as usize {
            return Err(self.err(Kind::Unsupported, "more than 2^32 - 1 vertices".into()));
        }
        self.positions.push(Vec3::from_array(xyz));
        Ok(())
    }

    fn face<'t>(&mut self, tokens: impl Iterator<Item = &'t [u8]>) -> Result<(), LoadError> {
        let nv = self.positions.len() as i64;
        let mut poly = std::mem::take(&mut self.poly);
        poly.clear();
        for t in tokens {
            let first = t.split(|&b| b == b'/').next().unwrap_or(t);
            let idx = std::str::from_utf8(first)
                .ok()
                .and_then(|s| s.parse::<i64>().ok())
                .ok_or_else(|| {
                    self.err(
                        Kind::Syntax,
                        format!(
                            "not a vertex index: {:?}",
                            String::from_utf8_lossy(&t[..t.len().min(32)])
                        ),
                    )
                })?;
            let resolved = match idx {
                0 => None,
                i if i > 0 => Some(i - 1),
                i => nv.checked_add(i),
            };
            match resolved {
                Some(r) if (0..nv).contains(&r) => poly.push(r as u32),
                _ => {
                    return Err(self.err(
                        Kind::BadIndex,
                        format!(
                            "vertex index {idx} is out of range: {nv} vertices defined so far (1..={nv} or -{nv}..=-1)"
                        ),
                    ));
                }
            }
        }
        if poly.len() < 3 {
            return Err(self.err(
                Kind::Syntax,
                format!("a face needs at least 3 vertices, got {}", poly.len()),
            ));
        }
        if self.runs.last().is_none_or(|r| r.keys != self.current) {
            self.runs.push(Run {
                first_tri: self.tris.len(),
                keys: self.current,
            });
        }
        for w in 1..poly.len() - 1 {
            self.tris.push([poly[0], poly[w], poly[w + 1]]);
        }
        self.poly = poly;
        Ok(())
    }

    /// Gather the runs into objects (in order of first appearance, runs of
    /// the same name merged) and give each its own compact vertex array.
    fn finish(self, split: Split, join_touching: bool) -> Result<SceneDesc, LoadError> {
        if self.tris.is_empty() {
            return Err(LoadError::Unsupported {
                file: self.file.to_path_buf(),
                at: Location::File,
                detail: "no triangle faces".into(),
            });
        }
        let split = match split {
            Split::Object if self.object_statements <= 1 => Split::Material,
            s => s,
        };
        let kind = match split {
            Split::Object => Some(OBJECT),
            Split::Group => Some(GROUP),
            Split::Material => Some(MATERIAL),
            Split::None => None,
        };
        let stem = self
            .file
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let key_name = |key: u32| -> String {
            match kind {
                Some(k) if key != 0 => self.names[k].names[key as usize].clone(),
                _ => stem.clone(),
            }
        };

        // Object slot per key, and each object's triangle ranges.
        let mut slot_of: HashMap<u32, usize> = HashMap::new();
        let mut ranges: Vec<(String, Vec<(usize, usize)>)> = Vec::new();
        for (i, run) in self.runs.iter().enumerate() {
            let key = kind.map_or(0, |k| run.keys[k]);
            let end = self
                .runs
                .get(i + 1)
                .map_or(self.tris.len(), |r| r.first_tri);
            let slot = *slot_of.entry(key).or_insert_with(|| {
                ranges.push((key_name(key), Vec::new()));
                ranges.len() - 1
            });
            ranges[slot].1.push((run.first_tri, end));
        }

        let ranges = if join_touching {
            self.join_touching(ranges)
        } else {
            ranges
        };

        let mut remap = vec![u32::MAX; self.positions.len()];
        let mut objects = Vec::with_capacity(ranges.len());
        for (name, rs) in ranges {
            let ntris: usize = rs.iter().map(|(a, b)| b - a).sum();
            let mut positions = Vec::new();
            let mut globals = Vec::new();
            let mut indices = Vec::with_capacity(ntris);
            for (a, b) in rs {
                for tri in &self.tris[a..b] {
                    indices.push(tri.map(|g| {
                        let slot = &mut remap[g as usize];
                        if *slot == u32::MAX {
                            *slot = positions.len() as u32;
                            positions.push(self.positions[g as usize]);
                            globals.push(g);
                        }
                        *slot
                    }));
                }
            }
            // Reset only the entries this object touched.
            for &g in &globals {
                remap[g as usize] = u32::MAX;
            }
            let mesh = TriangleMesh::new(positions, indices).map_err(|e| {
                mesh_error(self.file, Location::Element(format!("object {name:?}")), e)
            })?;
            objects.push(ObjectDesc {
                name,
                mesh,
                placed: true,
            });
        }
        Ok(SceneDesc {
            objects,
            instances: Vec::new(),
        })
    }

    /// The objects of `ranges` (name, triangle ranges) with every set of
    /// objects that share a vertex position (the same `f32` coordinates,
    /// `-0.0` as `0.0`) joined into one, in the order of each set's first
    /// object; a joined object keeps its first member's name.
    ///
    /// Why: an OBJ often cuts one surface into several `o` statements, one
    /// per material (a level's terrain as one object per blend of its
    /// textures; a building as `mesh_material` pieces), each with its own
    /// copies of the vertices along the cuts. A BVH per piece cannot put
    /// triangles of both sides of a cut in one leaf, and every ray that
    /// leaves the surface near a cut starts inside the boxes of both pieces:
    /// re-braiding pays at every cut (docs/performance.md, session 49). The
    /// glTF loader's objects are whole meshes, whatever their materials; this
    /// gives OBJ files the same unit. Objects that only come near each other
    /// stay apart.
    fn join_touching(
        &self,
        ranges: Vec<(String, Vec<(usize, usize)>)>,
    ) -> Vec<(String, Vec<(usize, usize)>)> {
        if ranges.len() < 2 {
            return ranges;
        }
        fn root(parent: &mut [u32], mut x: u32) -> u32 {
            while parent[x as usize] != x {
                let up = parent[parent[x as usize] as usize];
                parent[x as usize] = up;
                x = up;
            }
            x
        }
        let mut parent: Vec<u32> = (0..ranges.len() as u32).collect();
        // The first object to use each position, and per vertex the last
        // object that looked it up (each object looks a vertex up once).
        // (aHash: with the default SipHash the join took about twice as
        // long, nexuiz loading in 42-47 ms against 33-38 ms, 28-34 without
        // the join, by run.)
        let mut first_user: ahash::AHashMap<[u32; 3], u32> =
            ahash::AHashMap::with_capacity(self.positions.len());
        let mut seen_by = vec![u32::MAX; self.positions.len()];
        for (slot, (_, rs)) in ranges.iter().enumerate() {
            let slot = slot as u32;
            for &(a, b) in rs {
                for &g in self.tris[a..b].iter().flatten() {
                    if std::mem::replace(&mut seen_by[g as usize], slot) == slot {
                        continue;
                    }
                    let key = (self.positions[g as usize] + Vec3::ZERO)
                        .to_array()
                        .map(f32::to_bits);
                    let other = *first_user.entry(key).or_insert(slot);
                    if other != slot {
                        let (r1, r2) = (root(&mut parent, other), root(&mut parent, slot));
                        // The smaller slot stays the root: sets keep the
                        // order of their first objects.
                        parent[r1.max(r2) as usize] = r1.min(r2);
                    }
                }
            }
        }
        // Each set's place in `joined`, by its root (a slot).
        let mut at = vec![usize::MAX; ranges.len()];
        let mut joined: Vec<(String, Vec<(usize, usize)>)> = Vec::new();
        for (slot, (name, rs)) in ranges.into_iter().enumerate() {
            let r = root(&mut parent, slot as u32) as usize;
            if at[r] == usize::MAX {
                at[r] = joined.len();
                joined.push((name, rs));
            } else {
                joined[at[r]].1.extend(rs);
            }
        }
        joined
    }
}
