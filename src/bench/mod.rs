//! Benchmarks that print figures: `precond bench gp` and `precond bench planning` (build with
//! `--release`).

pub mod gp;
pub mod planning;
