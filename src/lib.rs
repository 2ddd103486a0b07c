//! # precond
//!
//! A long-running HTTP/JSON service that learns the *model precondition* of an inaccurate
//! dynamics model — the region of state-action space where its predictions stay within a
//! tolerance — by active learning (LaGrassa, Lee, Kroemer: *Task-Oriented Active Learning of
//! Model Preconditions for Inaccurate Dynamics Models*).
//!
//! ## Module map
//!
//! The numeric core knows nothing of HTTP, SQL or JSON:
//! - [`domain`]: the [`domain::Domain`] trait (spaces, model `f̂`, distance, features,
//!   constraints, samplers) and the built-in worlds' models: icy gridworld, kinematic, water
//!   plant.
//! - [`sim`]: the built-in worlds' true dynamics (simulators), for experiments and tests; the
//!   planner never sees them.
//! - [`gp`]: the Gaussian-process regressor behind the MDE: Matérn 5/2 ARD kernel,
//!   homoscedastic or most-likely heteroscedastic noise, LML-maximising fits, batched prediction.
//! - [`planning`]: RRT candidates inside the precondition, the trajectory acquisition function,
//!   the β schedule and the `active` / `goal_conditioned` / `random` strategies.
//! - [`mde`]: the model deviation estimator as served: the prior before any data, then a fitted
//!   GP, under a version.
//!
//! The service around it:
//! - [`settings`]: an experiment's settings, their defaults and their validation.
//! - [`store`]: SQLite (sqlx): every query, rows ↔ values, atomic idempotent ingest.
//! - [`live`]: live experiments in memory (built domain, current model), background refits.
//! - [`http`]: the axum router, handlers per resource, extractors, serving with graceful shutdown.
//! - [`error`]: the one error type and its JSON shape.
//! - [`cli`]: the command line (`precond serve`, `precond bench`, `precond experiment`).
//! - [`bench`]: benchmarks that print figures (`precond bench ...`).
//! - [`experiment`]: `precond experiment`, the paper's evaluation run end to end as an HTTP
//!   client of the service (simulators, CSV/JSON results, SVG plots).

pub mod bench;
pub mod cli;
pub mod domain;
pub mod error;
pub mod experiment;
pub mod gp;
pub mod http;
pub mod live;
pub mod mde;
pub mod planning;
pub mod settings;
pub mod sim;
pub mod store;
