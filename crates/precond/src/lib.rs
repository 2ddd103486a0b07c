//! # precond
//!
//! A long-running HTTP/JSON service that learns the *model precondition* of an inaccurate
//! dynamics model — the region of state-action space where its predictions stay within a
//! tolerance — by active learning (LaGrassa, Lee, Kroemer: *Task-Oriented Active Learning of
//! Model Preconditions for Inaccurate Dynamics Models*).
//!
//! ## The workspace
//!
//! - `precond-core` (`crates/precond-core`): the numeric core — domains, the GP and the model
//!   deviation estimators, planning, simulators. No HTTP, SQL or JSON; a Rust robot stack can
//!   link it alone. Re-exported here under the paths the server always used
//!   ([`domain`], [`planning`], [`gp`], [`mde`], [`sim`], [`seed`], [`limits`], [`budget`]).
//! - `precond` (this crate): the server — settings, the store, the service, the HTTP API.
//! - `precond-tools` (`crates/precond-tools`): the `precond` binary's command line and the tools
//!   that drive the server from outside (`experiment`, `bench`, `import`).
//!
//! ## Module map
//!
//! - [`settings`]: an experiment's settings, their defaults and their validation.
//! - [`remote_model`]: a dynamics model served by a robot over HTTP, and the operator's list of
//!   allowed model URLs.
//! - [`records`]: what precond keeps and shows as it is — executed transitions with their
//!   labels, where a trajectory comes from, runs, refusals, a proposal's terms — plain values
//!   the store reads and writes and the API shows; the store's rows and queries stay its own.
//! - [`store`]: SQLite or PostgreSQL (sqlx): every query, rows ↔ values, atomic idempotent
//!   ingest, and what replicas over one database agree on (locks, fit claims, versions).
//! - [`service`]: what precond does, whoever asks: experiments in memory, labelling and ingest,
//!   refits, judgements, proposals with leases, plans. Returns domain values and its own error.
//! - [`import`]: logged transitions (CSV, Parquet) into keyed trajectories — the one
//!   implementation of an import, run by `POST /v1/experiments/{id}/imports` and by
//!   `precond import`.
//! - [`api`]: the typed request and response bodies of the HTTP API, shared by the server and
//!   the Rust client in `precond-tools`; the OpenAPI document's schemas are generated from them.
//! - [`http`]: the axum router; handlers parse, call the service and render; the one HTTP error
//!   type and its JSON shape; access tokens, `/metrics`, request ids; serving with graceful
//!   shutdown; the web dashboard (`ui/`, embedded in the binary, reading only the JSON API).
//!
//! ## Layers, and what plugs in
//!
//! ```text
//! precond-tools (cli, experiment, bench, import)
//!    │
//!    ▼
//! http ─▶ service ─▶ store (SQLite or PostgreSQL)
//!  │        │
//!  ▼        ▼
//! api    settings ─▶ precond-core: domain, planning, gp, mde
//! ```
//!
//! - **A new world**: implement [`domain::Domain`] (and [`domain::LocalModel`] if its model runs
//!   in-process), add a variant to [`settings::DomainSpec`]; the planner, the service and the
//!   API need nothing else.
//! - **A new dynamics model** (e.g. one served by a robot over the network): implement
//!   [`domain::DynamicsModel`] and return it from [`domain::Domain::dynamics`]; the planner and
//!   the labeller call it in batches and turn its [`domain::DynamicsError`] into `502`/`504`.
//! - **A new regressor for the MDE**: implement [`mde::Regressor`] and add an
//!   [`mde::EstimatorKind`]; the exact GP ([`gp::GpModel`]) and the sparse GP ([`gp::sparse`])
//!   are the two there. The planner sees the MDE only through [`planning::DeviationModel`].
//! - **Another database engine**: [`store::Store`] runs its queries through sqlx's `Any`
//!   driver; an engine needs its migrations, a [`store::Backend`] variant and its own text
//!   where the SQL differs. SQLite (one process) and PostgreSQL (replicas) are there.

pub mod api;
pub mod http;
pub mod import;
pub mod records;
pub mod remote_model;
pub mod service;
pub mod settings;
pub mod store;

// The numeric core, under the paths the server and its users always named it by.
pub use precond_core::{budget, domain, gp, limits, mde, planning, seed, sim};
