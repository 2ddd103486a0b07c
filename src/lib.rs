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
//! - [`domain`]: the [`domain::Domain`] trait (spaces, distance, features, constraints,
//!   samplers), the dynamics-model seam [`domain::DynamicsModel`] (`f̂`, batched and fallible)
//!   and the built-in worlds' models: icy gridworld, kinematic, water plant.
//! - [`sim`]: the built-in worlds' true dynamics (simulators), for experiments and tests; the
//!   planner never sees them.
//! - [`gp`]: the Gaussian-process regressor behind the MDE: Matérn ARD kernels (ν = 1/2, 3/2, 5/2),
//!   homoscedastic or most-likely heteroscedastic noise, LML-maximising fits, batched prediction.
//! - [`planning`]: RRT candidates inside the precondition, the trajectory acquisition function,
//!   the β schedule (and its relaxation ladder for training problems with no plan) and the
//!   `active` / `goal_conditioned` / `random` strategies.
//! - [`mde`]: the model deviation estimator as served: the prior before any data, then a fitted
//!   GP, under a version; precondition judgements; the label cap chosen from held-out
//!   judgements of the training transitions.
//! - [`seed`]: seeds derived from seeds (one hashing helper for every seeded choice).
//! - [`limits`]: the range of everything a client can set, in one place.
//! - [`budget`]: how long a search or a remote model call may run (a deadline and a cancel
//!   flag), below the planner and the domains that both honour it.
//!
//! The service around it:
//! - [`settings`]: an experiment's settings, their defaults and their validation.
//! - [`remote_model`]: a dynamics model served by a robot over HTTP, and the operator's list of
//!   allowed model URLs.
//! - [`store`]: SQLite or PostgreSQL (sqlx): every query, rows ↔ values, atomic idempotent
//!   ingest, and what replicas over one database agree on (locks, fit claims, versions).
//! - [`service`]: what precond does, whoever asks: experiments in memory, labelling and ingest,
//!   refits, judgements, proposals with leases, plans. Returns domain values and its own error.
//! - [`api`]: the typed request and response bodies of the HTTP API, shared by the server and
//!   the Rust client in [`experiment`].
//! - [`http`]: the axum router; handlers parse, call the service and render; the one HTTP error
//!   type and its JSON shape; access tokens, `/metrics`, request ids; serving with graceful
//!   shutdown; the web dashboard (`ui/`, embedded in the binary, reading only the JSON API).
//! - [`cli`]: the command line (`precond serve`, `precond backup`, `precond bench`,
//!   `precond experiment`, `precond import`).
//! - [`bench`](mod@bench): benchmarks that print figures (`precond bench ...`).
//! - [`experiment`]: `precond experiment`, the paper's evaluation run end to end as an HTTP
//!   client of the service (simulators, CSV/JSON results, SVG plots).
//! - [`import`](mod@import): `precond import`, logged transitions (CSV, Parquet) into an
//!   experiment as an HTTP client, one trajectory per episode, resumable and idempotent.
//!
//! ## Layers, and what plugs in
//!
//! ```text
//! cli ─▶ http ─▶ service ─▶ store (SQLite or PostgreSQL)
//!          │        │
//!          ▼        ▼
//!         api    settings ─▶ domain, planning, gp, mde (the numeric core)
//! ```
//!
//! - **A new world**: implement [`domain::Domain`] (and [`domain::LocalModel`] if its model runs
//!   in-process), add a variant to [`settings::DomainSpec`]; the planner, the service and the
//!   API need nothing else.
//! - **A new dynamics model** (e.g. one served by a robot over the network): implement
//!   [`domain::DynamicsModel`] and return it from [`domain::Domain::dynamics`]; the planner and
//!   the labeller call it in batches and turn its [`domain::DynamicsError`] into `502`/`504`.
//!
//! - **A new regressor for the MDE**: implement [`mde::Regressor`] and add an
//!   [`mde::EstimatorKind`]; the exact GP ([`gp::GpModel`]) and the sparse GP ([`gp::sparse`])
//!   are the two there. The planner sees the MDE only through [`planning::DeviationModel`].
//! - **Another database engine**: [`store::Store`] runs its queries through sqlx's `Any`
//!   driver; an engine needs its migrations, a [`store::Backend`] variant and its own text
//!   where the SQL differs. SQLite (one process) and PostgreSQL (replicas) are there.

pub mod api;
pub mod bench;
pub mod cli;
pub mod experiment;
pub mod http;
pub mod import;
pub mod remote_model;
pub mod service;
pub mod settings;
pub mod store;

// The numeric core, under the paths the server and its users always named it by.
pub use precond_core::{budget, domain, gp, limits, mde, planning, seed, sim};
