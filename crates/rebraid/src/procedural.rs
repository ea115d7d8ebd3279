//! Seeded procedural scenes (the project's own generated data).
//!
//! - [`library`]: the paper's "library incident" (Benthin et al. 2017,
//!   section 1): a reading room full of bookcases whose objects are grouped
//!   *by material*, so that every book-cover colour is one object spanning
//!   the whole room. A plain two-level BVH has nothing to separate at the top
//!   level; re-braiding has to open the objects.
//! - [`random_overlapping`]: objects whose triangles are scattered over one
//!   common box (worst case for a two-level BVH, no structure at all).
//! - [`random_instanced`]: a few prototypes placed by many random instances
//!   with rotations and non-uniform scales.
//!
//! Everything is a pure function of its parameters and seed: the same call
//! gives bit-identical scenes on every machine and thread count (the
//! parallel parts seed one generator per work item and concatenate results
//! in a fixed order). The generator is a small SplitMix64, kept here rather
//! than taken from `rand` so the core crate needs no extra dependency and
//! the output cannot change with a `rand` upgrade.

use glam::{Affine3A, Mat3, Quat, Vec3};
use rayon::prelude::*;

use crate::{InstanceDesc, ObjectDesc, SceneDesc, TriangleMesh};

/// Parameters of [`library`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LibraryParams {
    /// Number of books (and bookcases) relative to the reference scene:
    /// 1.0 gives about one million triangles, 0.01 about ten thousand,
    /// 100 about a hundred million. Clamped to `0..=1000`; NaN counts as 0,
    /// and the scene always has at least one book.
    pub scale: f32,
    pub seed: u64,
}

impl Default for LibraryParams {
    fn default() -> Self {
        LibraryParams {
            scale: 1.0,
            seed: 0,
        }
    }
}

/// Book-cover colours: one object each.
const COVERS: [&str; 24] = [
    "red", "crimson", "maroon", "orange", "ochre", "yellow", "olive", "green", "forest", "teal",
    "cyan", "sky", "blue", "navy", "indigo", "violet", "purple", "magenta", "pink", "brown", "tan",
    "beige", "grey", "black",
];

/// Books at scale 1: with 40 triangles per book this is about 1M triangles.
const BOOKS_AT_SCALE_1: f64 = 25_000.0;
/// Arc segments of a book's rounded spine (40 triangles per book).
const SPINE_SEGMENTS: usize = 8;

// Bookcase dimensions in metres.
const CASE_W: f32 = 2.0;
const CASE_D: f32 = 0.35;
const CASE_H: f32 = 2.2;
const PANEL: f32 = 0.02;
const SHELVES: usize = 5;
const SHELF_PITCH: f32 = 0.42;
const FIRST_SHELF: f32 = 0.08;
/// Rough number of books on one full bookcase, used only to decide how many
/// bookcases to build.
const BOOKS_PER_CASE: usize = 200;
/// Distance between two rows of bookcases (one bookcase deep plus an aisle).
const ROW_PITCH: f32 = 2.5;
const MARGIN: f32 = 0.6;
const MIN_CASES: usize = 4;
const ROOM_H: f32 = 2.8;

/// The "library incident" scene: a room (floor, walls, ceiling) with rows of
/// bookcases full of books, grouped by material: `floor`, `walls`,
/// `ceiling`, `wood` (every bookcase) and one `cover_<colour>` object per
/// book-cover colour (24), each spread over the whole room. Books are boxes
/// with a rounded spine (40 triangles), with slightly varied sizes, a small
/// random lean and twist, and now and then a stack of books lying flat.
/// Every object is `placed`; there are no instances. +Y is up.
pub fn library(params: &LibraryParams) -> SceneDesc {
    let scale = if params.scale.is_nan() {
        0.0
    } else {
        params.scale.clamp(0.0, 1000.0)
    };
    let books = ((scale as f64 * BOOKS_AT_SCALE_1).round() as usize).max(1);
    // At least a few bookcases, so that even a tiny library spreads its
    // books (and so every cover colour) over the room.
    let cases = books.div_ceil(BOOKS_PER_CASE).max(MIN_CASES);
    // Rows about three times as long as the room is deep: a reading hall.
    let rows = (((cases as f64) / 3.0).sqrt().round() as usize).max(2);
    let per_row = cases.div_ceil(rows);
    let room = Vec3::new(
        2.0 * MARGIN + per_row as f32 * CASE_W,
        ROOM_H,
        2.0 * MARGIN + (rows - 1) as f32 * ROW_PITCH + CASE_D + 0.1,
    );

    let parts: Vec<CaseParts> = (0..cases)
        .into_par_iter()
        .map(|i| {
            let origin = Vec3::new(
                MARGIN + (i % per_row) as f32 * CASE_W,
                0.0,
                MARGIN + (i / per_row) as f32 * ROW_PITCH,
            );
            // Books dealt evenly over the bookcases (a case may hold a few
            // less when its random books are thick).
            let limit = books * (i + 1) / cases - books * i / cases;
            build_case(origin, limit, Rng::new(params.seed, i as u64 + 1))
        })
        .collect();

    let mut floor = Part::default();
    floor.add_box(
        Vec3::new(-0.1, -0.1, -0.1),
        Vec3::new(room.x + 0.1, 0.0, room.z + 0.1),
        &Affine3A::IDENTITY,
    );
    let mut ceiling = Part::default();
    ceiling.add_box(
        Vec3::new(-0.1, room.y, -0.1),
        Vec3::new(room.x + 0.1, room.y + 0.1, room.z + 0.1),
        &Affine3A::IDENTITY,
    );
    let mut walls = Part::default();
    for (lo, hi) in [
        (
            Vec3::new(-0.1, 0.0, -0.1),
            Vec3::new(room.x + 0.1, room.y, 0.0),
        ),
        (
            Vec3::new(-0.1, 0.0, room.z),
            Vec3::new(room.x + 0.1, room.y, room.z + 0.1),
        ),
        (Vec3::new(-0.1, 0.0, 0.0), Vec3::new(0.0, room.y, room.z)),
        (
            Vec3::new(room.x, 0.0, 0.0),
            Vec3::new(room.x + 0.1, room.y, room.z),
        ),
    ] {
        walls.add_box(lo, hi, &Affine3A::IDENTITY);
    }

    let wood = Part::concat(parts.iter().map(|p| &p.wood));
    let mut named: Vec<(String, Part)> = vec![
        ("floor".into(), floor),
        ("walls".into(), walls),
        ("ceiling".into(), ceiling),
        ("wood".into(), wood),
    ];
    let covers: Vec<(String, Part)> = (0..COVERS.len())
        .into_par_iter()
        .map(|c| {
            (
                format!("cover_{}", COVERS[c]),
                Part::concat(parts.iter().map(|p| &p.covers[c])),
            )
        })
        .collect();
    named.extend(covers);
    SceneDesc {
        objects: named
            .into_iter()
            .filter(|(_, p)| !p.indices.is_empty())
            .map(|(name, p)| ObjectDesc {
                name,
                mesh: p.into_mesh(),
                placed: true,
            })
            .collect(),
        instances: Vec::new(),
    }
}

/// `objects` objects of `tris_per_object` small random triangles each, all
/// scattered uniformly over the box `[0, 100]^3`: every object's box is the
/// scene box. Triangles have edges of about 1 unit.
pub fn random_overlapping(objects: usize, tris_per_object: usize, seed: u64) -> SceneDesc {
    let objects = (0..objects)
        .into_par_iter()
        .map(|o| {
            let mut rng = Rng::new(seed, o as u64 + 1);
            let mut part = Part::default();
            for _ in 0..tris_per_object {
                let c = rng.vec3(Vec3::ZERO, Vec3::splat(100.0));
                part.add_triangle([
                    c + rng.vec3(Vec3::splat(-0.5), Vec3::splat(0.5)),
                    c + rng.vec3(Vec3::splat(-0.5), Vec3::splat(0.5)),
                    c + rng.vec3(Vec3::splat(-0.5), Vec3::splat(0.5)),
                ]);
            }
            ObjectDesc {
                name: format!("scatter_{o}"),
                mesh: part.into_mesh(),
                placed: true,
            }
        })
        .collect();
    SceneDesc {
        objects,
        instances: Vec::new(),
    }
}

/// The opposite of the library: `side` x `side` objects on a grid in the
/// XZ plane, each a blob of `tris_per_object` triangles inside its own unit
/// cell with a gap of a fifth of a cell to its neighbours, so that no two
/// object boxes overlap. Re-braiding should find nothing to open here and
/// cost nearly nothing over the plain two-level BVH.
pub fn separated(side: usize, tris_per_object: usize, seed: u64) -> SceneDesc {
    let objects = (0..side * side)
        .into_par_iter()
        .map(|o| {
            let mut rng = Rng::new(seed, o as u64 + 1);
            let centre = Vec3::new((o % side) as f32 + 0.5, 0.5, (o / side) as f32 + 0.5);
            let mut part = Part::default();
            for _ in 0..tris_per_object {
                let c = rng.unit_vector() * rng.range(0.2, 0.38);
                let tri = [0, 1, 2].map(|_| {
                    centre
                        + (c + rng.vec3(Vec3::splat(-0.02), Vec3::splat(0.02)))
                            .clamp(Vec3::splat(-0.4), Vec3::splat(0.4))
                });
                part.add_triangle(tri);
            }
            ObjectDesc {
                name: format!("blob_{o}"),
                mesh: part.into_mesh(),
                placed: true,
            }
        })
        .collect();
    SceneDesc {
        objects,
        instances: Vec::new(),
    }
}

/// `prototypes` objects (`placed: false`) of `tris_per_prototype` triangles
/// each, a random closed-ish blob in `[-1, 1]^3`, placed by `instances`
/// instances with random prototype, rotation, non-uniform scale in
/// `[0.5, 2]` per axis and translation in `[0, 100]^3`. Every transform
/// passes [`crate::transform::check_transform`].
pub fn random_instanced(
    prototypes: usize,
    instances: usize,
    tris_per_prototype: usize,
    seed: u64,
) -> SceneDesc {
    let prototypes = prototypes.max(1);
    let objects: Vec<ObjectDesc> = (0..prototypes)
        .map(|p| {
            let mut rng = Rng::new(seed, p as u64 + 1);
            let mut part = Part::default();
            // Triangles with vertices on a bumpy sphere: a blob with a
            // sensible box and plenty of overlap between its triangles.
            for _ in 0..tris_per_prototype {
                let c = rng.unit_vector() * rng.range(0.6, 1.0);
                let tri = [0, 1, 2].map(|_| {
                    (c + rng.vec3(Vec3::splat(-0.15), Vec3::splat(0.15)))
                        .clamp(Vec3::NEG_ONE, Vec3::ONE)
                });
                part.add_triangle(tri);
            }
            ObjectDesc {
                name: format!("prototype_{p}"),
                mesh: part.into_mesh(),
                placed: false,
            }
        })
        .collect();
    let mut rng = Rng::new(seed, u64::MAX);
    let instances = (0..instances)
        .map(|i| {
            let object = (rng.next_u64() % prototypes as u64) as u32;
            let rotation =
                Quat::from_axis_angle(rng.unit_vector(), rng.range(0.0, std::f32::consts::TAU));
            let scale = rng.vec3(Vec3::splat(0.5), Vec3::splat(2.0));
            let translation = rng.vec3(Vec3::ZERO, Vec3::splat(100.0));
            InstanceDesc {
                name: format!("instance_{i}"),
                object,
                transform: Affine3A::from_scale_rotation_translation(scale, rotation, translation),
            }
        })
        .collect();
    SceneDesc { objects, instances }
}

/// Geometry of one bookcase, by material.
struct CaseParts {
    wood: Part,
    covers: Vec<Part>,
}

/// One bookcase with its origin at the floor, left, back corner; its books'
/// spines face +Z (the aisle). Places at most `limit` books.
fn build_case(origin: Vec3, limit: usize, mut rng: Rng) -> CaseParts {
    let at = Affine3A::from_translation(origin);
    let mut wood = Part::default();
    wood.add_box(Vec3::ZERO, Vec3::new(PANEL, CASE_H, CASE_D), &at);
    wood.add_box(
        Vec3::new(CASE_W - PANEL, 0.0, 0.0),
        Vec3::new(CASE_W, CASE_H, CASE_D),
        &at,
    );
    wood.add_box(
        Vec3::new(PANEL, 0.0, 0.0),
        Vec3::new(CASE_W - PANEL, CASE_H, PANEL),
        &at,
    );
    wood.add_box(
        Vec3::new(PANEL, CASE_H - PANEL, 0.0),
        Vec3::new(CASE_W - PANEL, CASE_H, CASE_D),
        &at,
    );
    let mut covers: Vec<Part> = (0..COVERS.len()).map(|_| Part::default()).collect();
    let mut placed = 0usize;
    for s in 0..SHELVES {
        let y = FIRST_SHELF + s as f32 * SHELF_PITCH;
        wood.add_box(
            Vec3::new(PANEL, y - PANEL, PANEL),
            Vec3::new(CASE_W - PANEL, y, CASE_D),
            &at,
        );
        let mut x = PANEL + 0.005;
        let end = CASE_W - PANEL - 0.005;
        loop {
            if placed >= limit {
                break;
            }
            let h = rng.range(0.18, 0.34);
            let d = rng.range(0.13, 0.23).min(CASE_D - PANEL - 0.01);
            let colour = (rng.next_u64() % COVERS.len() as u64) as usize;
            if rng.f32() < 0.04 {
                // A stack of books lying flat, spines out.
                let n = 2 + (rng.next_u64() % 3) as usize;
                let w = h + 0.01;
                if x + w > end {
                    break;
                }
                let mut top = y;
                for _ in 0..n.min(limit - placed) {
                    let t = rng.range(0.02, 0.05);
                    let c = (rng.next_u64() % COVERS.len() as u64) as usize;
                    // Local book: thickness along x, height along y. Lying
                    // flat: height along +x, thickness along +y.
                    let lie = Affine3A::from_mat3_translation(
                        Mat3::from_cols(Vec3::Y, Vec3::NEG_X, Vec3::Z),
                        Vec3::new(x + h, top, CASE_D - d),
                    );
                    covers[c].add_book(t, h, d, &(at * lie));
                    top += t;
                    placed += 1;
                }
                x += w;
                continue;
            }
            let t = rng.range(0.018, 0.06);
            if x + t > end {
                break;
            }
            // Small lean about the spine axis and twist about the vertical,
            // pivoting on the book's bottom centre so it stays on the shelf.
            let lean = rng.range(-0.03, 0.03);
            let twist = rng.range(-0.05, 0.05);
            let pivot = Vec3::new(t * 0.5, 0.0, d * 0.5);
            let place = Affine3A::from_translation(Vec3::new(x, y, CASE_D - d) + pivot)
                * Affine3A::from_rotation_z(lean)
                * Affine3A::from_rotation_y(twist)
                * Affine3A::from_translation(-pivot);
            covers[colour].add_book(t, h, d, &(at * place));
            placed += 1;
            x += t + rng.range(0.001, 0.006);
        }
    }
    CaseParts { wood, covers }
}

/// Growing vertex and triangle arrays of one material.
#[derive(Default)]
struct Part {
    positions: Vec<Vec3>,
    indices: Vec<[u32; 3]>,
}

impl Part {
    fn concat<'a>(parts: impl Iterator<Item = &'a Part> + Clone) -> Part {
        let nv = parts.clone().map(|p| p.positions.len()).sum();
        let nt = parts.clone().map(|p| p.indices.len()).sum();
        let mut out = Part {
            positions: Vec::with_capacity(nv),
            indices: Vec::with_capacity(nt),
        };
        for p in parts {
            let base = out.positions.len() as u32;
            out.positions.extend_from_slice(&p.positions);
            out.indices
                .extend(p.indices.iter().map(|t| t.map(|v| v + base)));
        }
        out
    }

    fn into_mesh(self) -> TriangleMesh {
        TriangleMesh {
            positions: self.positions,
            indices: self.indices,
        }
    }

    fn add_triangle(&mut self, tri: [Vec3; 3]) {
        let b = self.positions.len() as u32;
        self.positions.extend_from_slice(&tri);
        self.indices.push([b, b + 1, b + 2]);
    }

    /// A prism: the convex polygon `profile` (in the XZ plane,
    /// counter-clockwise seen from +Y) extruded from y = 0 to y = `h`.
    fn add_prism(&mut self, profile: &[Vec3], h: f32, to_world: &Affine3A) {
        let n = profile.len() as u32;
        let b = self.positions.len() as u32;
        self.positions
            .extend(profile.iter().map(|&p| to_world.transform_point3(p)));
        self.positions.extend(
            profile
                .iter()
                .map(|&p| to_world.transform_point3(p + Vec3::new(0.0, h, 0.0))),
        );
        for i in 0..n {
            let j = (i + 1) % n;
            self.indices.push([b + i, b + n + i, b + j]);
            self.indices.push([b + j, b + n + i, b + n + j]);
        }
        for i in 1..n - 1 {
            self.indices.push([b, b + i + 1, b + i]);
            self.indices.push([b + n, b + n + i, b + n + i + 1]);
        }
    }

    fn add_box(&mut self, lo: Vec3, hi: Vec3, to_world: &Affine3A) {
        let profile = [
            Vec3::new(lo.x, lo.y, lo.z),
            Vec3::new(lo.x, lo.y, hi.z),
            Vec3::new(hi.x, lo.y, hi.z),
            Vec3::new(hi.x, lo.y, lo.z),
        ];
        self.add_prism(&profile, hi.y - lo.y, to_world);
    }

    /// A book of thickness `t` (x), height `h` (y) and depth `d` (z) with
    /// its back at z = 0 and a rounded spine bulging past z = d:
    /// `4 * (SPINE_SEGMENTS + 3) - 4` = 40 triangles.
    fn add_book(&mut self, t: f32, h: f32, d: f32, to_world: &Affine3A) {
        let bulge = 0.25 * t;
        let mut poly = [Vec3::ZERO; SPINE_SEGMENTS + 3];
        for k in 0..=SPINE_SEGMENTS {
            // From (0, d) over the bulge to (t, d).
            let a = std::f32::consts::PI * (1.0 - k as f32 / SPINE_SEGMENTS as f32);
            poly[1 + k] = Vec3::new(0.5 * t + 0.5 * t * a.cos(), 0.0, d + bulge * a.sin());
        }
        poly[SPINE_SEGMENTS + 2] = Vec3::new(t, 0.0, 0.0);
        self.add_prism(&poly, h, to_world);
    }
}

/// SplitMix64: tiny, fast, and good enough for scene layout.
#[derive(Clone)]
struct Rng(u64);

impl Rng {
    /// One independent stream per (seed, stream) pair.
    fn new(seed: u64, stream: u64) -> Self {
        let mut r = Rng(seed ^ stream.wrapping_mul(0xD1B5_4A32_D192_ED03));
        r.next_u64();
        r
    }

    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }

    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f32()
    }

    fn vec3(&mut self, lo: Vec3, hi: Vec3) -> Vec3 {
        Vec3::new(
            self.range(lo.x, hi.x),
            self.range(lo.y, hi.y),
            self.range(lo.z, hi.z),
        )
    }

    fn unit_vector(&mut self) -> Vec3 {
        loop {
            let v = self.vec3(Vec3::NEG_ONE, Vec3::ONE);
            let l = v.length_squared();
            if l > 1e-4 && l <= 1.0 {
                return v / l.sqrt();
            }
        }
    }
}

#[cfg(test)]
mod separated_tests {
    use super::*;

    #[test]
    fn separated_objects_do_not_overlap() {
        let d = separated(4, 50, 3);
        assert_eq!(d.objects.len(), 16);
        assert_eq!(d.world_triangles(), 16 * 50);
        let (boxes, _) = d.world_boxes();
        for i in 0..boxes.len() {
            for j in i + 1..boxes.len() {
                assert!(!boxes[i].overlaps(&boxes[j]), "{i} {j}");
            }
        }
        assert!(d.validate().is_ok());
        assert_eq!(separated(4, 50, 3), d);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lib(scale: f32) -> SceneDesc {
        library(&LibraryParams { scale, seed: 7 })
    }

    #[test]
    fn library_is_deterministic_and_seeded() {
        let a = lib(0.05);
        assert_eq!(a, lib(0.05));
        let b = library(&LibraryParams {
            scale: 0.05,
            seed: 8,
        });
        assert_ne!(a, b);
    }

    #[test]
    fn library_meshes_validate_and_group_by_material() {
        let s = lib(0.1);
        s.validate().unwrap();
        assert!(
            (16..=40).contains(&s.objects.len()),
            "{} objects",
            s.objects.len()
        );
        for name in ["floor", "walls", "ceiling", "wood", "cover_red"] {
            assert!(s.objects.iter().any(|o| o.name == name), "no object {name}");
        }
        assert!(s.objects.iter().all(|o| o.placed && !o.mesh.is_empty()));
        assert!(s.instances.is_empty());
    }

    #[test]
    fn library_overlap_is_high() {
        for (scale, min) in [(0.01, 6.0), (0.1, 15.0), (1.0, 20.0)] {
            let r = lib(scale).overlap_ratio();
            assert!(r > min, "overlap {r} at scale {scale}");
        }
    }

    #[test]
    fn library_triangles_scale_linearly() {
        let t1 = lib(0.1).world_triangles() as f64;
        let t2 = lib(0.4).world_triangles() as f64;
        let t3 = lib(1.0).world_triangles() as f64;
        assert!((t2 / t1 - 4.0).abs() < 0.4, "{t1} -> {t2}");
        assert!((t3 / t1 - 10.0).abs() < 1.0, "{t1} -> {t3}");
        assert!((0.8e6..1.3e6).contains(&t3), "{t3} triangles at scale 1");
        let small = lib(0.01).world_triangles();
        assert!(
            (2_000..20_000).contains(&small),
            "{small} triangles at scale 0.01"
        );
        assert!(lib(0.0).world_triangles() > 0);
        assert!(
            library(&LibraryParams {
                scale: f32::NAN,
                seed: 0
            })
            .world_triangles()
                > 0
        );
    }

    #[test]
    fn random_overlapping_spans_the_box() {
        let s = random_overlapping(8, 500, 3);
        s.validate().unwrap();
        assert_eq!(s.objects.len(), 8);
        assert_eq!(s.world_triangles(), 4000);
        assert!(s.overlap_ratio() > 6.0);
        assert_eq!(s, random_overlapping(8, 500, 3));
    }

    #[test]
    fn random_instanced_transforms_are_valid() {
        let s = random_instanced(3, 200, 100, 5);
        s.validate().unwrap();
        assert_eq!(s.objects.len(), 3);
        assert_eq!(s.instances.len(), 200);
        assert_eq!(s.world_triangles(), 200 * 100);
        assert!(s.objects.iter().all(|o| !o.placed));
        assert_eq!(s, random_instanced(3, 200, 100, 5));
    }

    /// `cargo test -p rebraid --release procedural -- --ignored --nocapture`
    #[test]
    #[ignore = "prints sizes and timings"]
    fn print_library_stats() {
        for scale in [0.01f32, 0.1, 1.0, 10.0] {
            let t = std::time::Instant::now();
            let s = library(&LibraryParams { scale, seed: 1 });
            let ms = t.elapsed().as_secs_f64() * 1e3;
            println!(
                "scale {scale}: {} objects, {} triangles, overlap {:.1}, {ms:.0} ms",
                s.objects.len(),
                s.world_triangles(),
                s.overlap_ratio()
            );
        }
    }
}
