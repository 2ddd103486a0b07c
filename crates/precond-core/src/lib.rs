//! # precond-core
//!
//! precond's numeric core: what learns where an inaccurate dynamics model can be trusted (its
//! *model precondition*) and plans inside it, with no HTTP, SQL or JSON — the method of
//! LaGrassa, Lee, Kroemer, *Task-Oriented Active Learning of Model Preconditions for Inaccurate
//! Dynamics Models*. The `precond` server wraps it in a service with a store; a Rust robot stack
//! (a dora-rs or ROS 2 node) can link it directly for an in-process precondition and planner:
//! `examples/in_process.rs` fits on transitions, queries the precondition and plans
//! (`cargo run -p precond-core --release --example in_process`).
//!
//! ## Module map
//!
//! - [`domain`]: the [`domain::Domain`] trait (spaces, distance, features, constraints,
//!   samplers), the dynamics-model seam [`domain::DynamicsModel`] (`f̂`, batched and fallible)
//!   and the built-in worlds' models: icy gridworld, kinematic, water plant, and custom domains
//!   declared by their spaces and features.
//! - [`sim`]: the built-in worlds' true dynamics (simulators), for experiments and tests; the
//!   planner never sees them.
//! - [`gp`]: the Gaussian-process regressor behind the MDE: Matérn ARD kernels (ν = 1/2, 3/2, 5/2),
//!   homoscedastic or most-likely heteroscedastic noise, LML-maximising fits, batched prediction;
//!   the sparse GP for large data.
//! - [`planning`]: RRT candidates inside the precondition, the trajectory acquisition function,
//!   the β schedule (and its relaxation ladder for training problems with no plan) and the
//!   `active` / `goal_conditioned` / `random` strategies.
//! - [`mde`]: the model deviation estimator: the prior before any data, then a fitted regressor;
//!   precondition judgements; the label cap chosen from held-out judgements; the exported,
//!   self-contained precondition.
//! - [`seed`]: seeds derived from seeds (one hashing helper for every seeded choice).
//! - [`limits`]: the range of everything a client can set, in one place.
//! - [`budget`]: how long a search or a model call may run (a deadline and a cancel flag),
//!   below the planner and the domains that both honour it.
//!
//! ## What plugs in
//!
//! - **A new world**: implement [`domain::Domain`] (and [`domain::LocalModel`] if its model runs
//!   in-process); the planner needs nothing else.
//! - **A new dynamics model**: implement [`domain::DynamicsModel`] and return it from
//!   [`domain::Domain::dynamics`]; the planner and the labeller call it in batches.
//! - **A new regressor for the MDE**: implement [`mde::Regressor`] and add an
//!   [`mde::EstimatorKind`]; the exact GP ([`gp::GpModel`]) and the sparse GP ([`gp::sparse`])
//!   are the two there. The planner sees the MDE only through [`planning::DeviationModel`].

pub mod budget;
pub mod domain;
pub mod gp;
pub mod limits;
pub mod mde;
pub mod planning;
pub mod seed;
pub mod sim;
