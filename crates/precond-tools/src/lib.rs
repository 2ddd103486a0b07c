//! # precond-tools
//!
//! The `precond` command line and the tools around the server: what runs the server
//! (`precond serve`, `precond backup`, from the `precond` crate) and what drives it or measures
//! it from outside, as a lab would.
//!
//! ## Module map
//!
//! - [`cli`]: the command line (`precond serve`, `precond backup`, `precond bench`,
//!   `precond experiment`, `precond import`); `src/main.rs` is the `precond` binary.
//! - [`bench`](mod@bench): benchmarks that print figures (`precond bench ...`), each beside its
//!   reference in the same run.
//! - [`experiment`]: `precond experiment`, the paper's evaluation run end to end as an HTTP
//!   client of the service (simulators, CSV/JSON results, SVG plots).
//! - [`import`](mod@import): `precond import`, logged transitions (CSV, Parquet) into an
//!   experiment as an HTTP client, one trajectory per episode, resumable and idempotent.
//! - [`openapi`]: `precond openapi`, the schemas of `api/openapi.yaml` generated from the wire
//!   types of the `precond` crate and the annotations of `api/schemas.yaml`.
//!
//! ## Layers
//!
//! ```text
//! precond-tools (cli, experiment, bench, import, openapi)
//!     │
//!     ▼
//! precond (api, http, service, store, settings, remote_model)
//!     │
//!     ▼
//! precond-core (domain, planning, gp, mde, sim, seed, limits, budget)
//! ```

pub mod bench;
pub mod cli;
pub mod experiment;
pub mod import;
pub mod openapi;
