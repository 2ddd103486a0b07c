//! Benchmarks that print figures: `precond bench gp` (with `--sparse`: [`sparse`]) and
//! `precond bench planning` (build with `--release`). `planning` also times proposals with a
//! model served over HTTP ([`remote`]); `saturation` measures health checks and cheap reads
//! while the planner is saturated; `worlds` characterises the continuous worlds (share of safe
//! state-actions, the oracle and the baseline on random problems); `mde` refits a run's
//! training data under each MDE setting and judges a continuous world's true deviations;
//! `export` times the exported model's evaluator against the server's prediction path;
//! `refit` times a refit after one more batch from scratch and warm, with their held-out
//! quality ([`refit`]);
//! `replicas` measures proposals per second with 1, 2, 4 … replicas over one PostgreSQL
//! database.

pub mod export;
pub mod gp;
pub mod mde;
pub mod planning;
pub mod refit;
pub mod remote;
pub mod replicas;
pub mod saturation;
pub mod sparse;
pub mod worlds;
