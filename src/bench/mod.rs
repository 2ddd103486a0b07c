//! Benchmarks that print figures: `precond bench gp` and `precond bench planning` (build with
//! `--release`). `planning` also times proposals with a model served over HTTP ([`remote`]).

pub mod gp;
pub mod planning;
pub mod remote;
