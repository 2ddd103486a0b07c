//! The planner: candidate trajectories grown by an RRT inside the current model precondition,
//! the trajectory-level acquisition function, the β schedule, and the strategies that turn a
//! planning problem into a proposal (DESIGN.md §1).
//!
//! - [`planner`]: the front door — a [`Planner`] (domain, deviation model, checked
//!   [`PlanningSettings`], budget) that plans, proposes and judges for a checked
//!   [`Problem`](crate::domain::Problem) inside a [`Precondition`].
//! - [`model`]: the [`DeviationModel`] the planner asks for μ and σ (and fantasised σ) — the
//!   seam the MDE plugs into from outside.
//! - [`error`]: [`PlanningError`], why the planner could not answer.
//! - [`precondition`]: `μ + β σ < d_max`, the one definition of "trusted".
//! - [`schedule`]: `β_j` over the learning iterations, and the ladder of lower βs a training
//!   problem with no plan at `β_j` tries ([`Planner::propose_relaxing`]).
//! - [`acquisition`]: `α_step = μ − c σ` and its discounted aggregation over a trajectory.
//! - [`bottleneck`]: the `bottleneck` acquisition's cross-problem value on a finite domain —
//!   the untrusted steps that would open the most sampled problems, and a probe to the best.
//! - [`spread`]: the `spread` acquisition's value — the σ near `d_max` a candidate would
//!   remove over a uniform sample of state-actions (targeted integrated variance).
//! - [`Budget`] (from [`crate::budget`]): the deadline and cancel flag a search checks between
//!   rounds (a planner's [`Planner::within`]).
//! - [`cache`]: batching and memoising the deviation model's predictions within one proposal.
//! - [`settings`]: the [`PlannerSettings`] and, checked once with the acquisition's, the
//!   [`PlanningSettings`].
//! - [`trajectory`]: the [`Trajectory`] every part passes on.
//! - [`rrt`](mod@rrt): one RRT run (behind [`Planner::rrt`] and the test-time
//!   [`Planner::plan`]).
//! - [`strategy`]: candidate generation and the `active` / `goal_conditioned` / `random`
//!   strategies behind [`Planner::propose`]; [`Strategy::choose`], the one choice among
//!   candidates.
//! - [`given`]: candidates posted by the client, judged step by step and chosen by the same
//!   strategies.
//! - `valuation`: how a proposal's candidates are compared, the planner's and a client's
//!   alike — the score, and under `active` the value an `Acquisition` (`bottleneck`,
//!   `spread`) puts on executing each.
//! - [`synthetic`]: cheap deviation models with known answers, for tests, benchmarks and demos.
//!
//! The imports run one way: [`planner`] uses [`given`], [`strategy`], `valuation` and [`rrt`](mod@rrt),
//! which are handed values (the settings, the problem, the model, the budget) and never the
//! [`Planner`].
//!
//! The module knows nothing of HTTP, SQL or JSON. The deviation model is reached only through
//! [`DeviationModel`], so the GP (or any stand-in) plugs in from outside. Every random choice
//! derives from a `u64` seed: the same inputs and seed give the same result.

/// Names a plain settings enum's variants as the settings spell them: an `ALL` list, `as_str`,
/// `Display`, and a `FromStr` whose error names the setting `field` and lists every accepted
/// name. One definition for every such enum, so that a name is written once.
macro_rules! setting_names {
    ($ty:ident, $field:literal, { $($variant:ident => $name:literal),+ $(,)? }) => {
        impl $ty {
            /// Every value, in the order the setting lists them.
            pub const ALL: &'static [$ty] = &[$($ty::$variant),+];

            /// The setting's name of this value.
            pub fn as_str(self) -> &'static str {
                match self {
                    $(Self::$variant => $name),+
                }
            }
        }

        impl std::fmt::Display for $ty {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.as_str())
            }
        }

        impl std::str::FromStr for $ty {
            type Err = $crate::planning::PlanningError;

            fn from_str(s: &str) -> Result<Self, Self::Err> {
                Self::ALL
                    .iter()
                    .copied()
                    .find(|v| v.as_str() == s)
                    .ok_or_else(|| {
                        let names: Vec<String> =
                            Self::ALL.iter().map(|v| format!("{:?}", v.as_str())).collect();
                        $crate::planning::PlanningError::settings(
                            $field,
                            format!("{s:?} is not one of {}", names.join(", ")),
                        )
                    })
            }
        }
    };
}

pub mod acquisition;
pub mod bottleneck;
pub mod cache;
pub mod error;
pub mod given;
pub mod model;
pub mod planner;
pub mod precondition;
pub mod rrt;
pub mod schedule;
pub mod settings;
pub mod spread;
pub mod strategy;
pub mod synthetic;
pub mod trajectory;
pub(crate) mod valuation;

#[cfg(test)]
mod tests;

pub use crate::budget::{Budget, Stop};
pub use acquisition::{
    AcquisitionKind, AcquisitionSettings, Aggregation, aggregate, alpha_step, within_probability,
};
pub use cache::ModelCache;
pub use error::PlanningError;
pub use given::{Path, Verdict, choose};
pub use model::{DeviationModel, Fantasy, PlanModel};
pub use planner::{GivenChoice, Planner};
pub use precondition::{Agreement, Precondition};
pub use rrt::{Rejections, RrtOutcome};
pub use schedule::{BetaSchedule, MAX_RELAXATION_STEPS, beta_schedule, relaxation_ladder};
pub use settings::{PlannerSettings, PlanningSettings};
pub use strategy::{CandidateScore, Proposal, Strategy};
pub use trajectory::Trajectory;
