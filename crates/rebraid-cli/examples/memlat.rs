//! Memory latency of this machine: a dependent chain of loads through a
//! random cycle over buffers from one that fits the L2 cache (2 MiB) through
//! the sizes of the shared scenes' BVHs (8-32 MiB, the L3's range) to one
//! far larger than the L3 (256 MiB). Incoherent rays are chains of such
//! loads, so figures measured on different days compare only when these
//! agree (see docs/performance.md, session 6).
//!
//! ```sh
//! cargo run --release -p rebraid-cli --example memlat
//! ```

use rand::{Rng, SeedableRng};
use std::time::Instant;

fn chase_ns(bytes: usize, steps: usize) -> f64 {
    let n = bytes / 8;
    // Sattolo's shuffle: one cycle through every slot.
    let mut next: Vec<usize> = (0..n).collect();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
    for i in (1..n).rev() {
        let j = rng.gen_range(0..i);
        next.swap(i, j);
    }
    let mut k = 0usize;
    let t = Instant::now();
    for _ in 0..steps {
        k = next[k];
    }
    let ns = t.elapsed().as_secs_f64() * 1e9 / steps as f64;
    std::hint::black_box(k);
    ns
}

fn main() {
    for (label, bytes) in [
        ("2 MiB", 2usize << 20),
        ("8 MiB", 8 << 20),
        ("16 MiB", 16 << 20),
        ("32 MiB", 32 << 20),
        ("256 MiB", 256 << 20),
    ] {
        let runs: Vec<f64> = (0..3).map(|_| chase_ns(bytes, 5_000_000)).collect();
        println!("{label:>8}: {runs:.1?} ns per dependent load");
    }
}
