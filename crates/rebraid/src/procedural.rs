//! Seeded procedural scenes (the project's own generated data).
