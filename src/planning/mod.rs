//! The planner: candidate trajectories grown by an RRT inside the current model precondition,
//! the trajectory-level acquisition function, the β schedule, and the strategies that turn a
//! planning problem into a proposal (DESIGN.md §1).
//!
//! - [`planner`]: the front door — a [`Planner`] (domain, deviation model, checked
//!   [`PlanningSettings`], budget) that plans, proposes and judges for a checked
//!   [`Problem`](crate::domain::Problem) inside a [`Precondition`].
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
//! - [`synthetic`]: cheap deviation models with known answers, for tests, benchmarks and demos.
//!
//! The imports run one way: [`planner`] uses [`given`], [`strategy`] and [`rrt`](mod@rrt),
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
pub mod given;
pub mod planner;
pub mod precondition;
pub mod rrt;
pub mod schedule;
pub mod settings;
pub mod spread;
pub mod strategy;
pub mod synthetic;
pub mod trajectory;

#[cfg(test)]
mod tests;

pub use crate::budget::{Budget, Stop};
pub use acquisition::{
    AcquisitionKind, AcquisitionSettings, Aggregation, aggregate, alpha_step, within_probability,
};
pub use cache::ModelCache;
pub use given::{Path, Verdict, choose};
pub use planner::Planner;
pub use precondition::{Agreement, Precondition};
pub use rrt::{Rejections, RrtOutcome};
pub use schedule::{BetaSchedule, MAX_RELAXATION_STEPS, beta_schedule, relaxation_ladder};
pub use settings::{PlannerSettings, PlanningSettings};
pub use strategy::{CandidateScore, Proposal, Strategy};
pub use trajectory::Trajectory;

/// A model deviation estimator as the planner sees it: μ and σ (σ includes noise) of the
/// deviation for feature vectors φ(s,a).
pub trait DeviationModel: Sync {
    /// `features` is row-major, `n = features.len() / dim` points of dimension `dim`; returns
    /// (mu, sigma) per point.
    ///
    /// The planner asks for many points at once where it can, and never asks twice for the same
    /// feature vector within one proposal (see [`ModelCache`]).
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)>;

    /// (μ, σ) as if the state-actions `pending` (row-major, `dim` each: executions chosen or
    /// posted since the model was fitted) had been labelled as well, at the same
    /// hyperparameters: μ unchanged, σ what they would leave uncertain. The acquisition of
    /// `active` scores candidates with it, so a batch's trajectories do not all chase one
    /// uncertainty; which steps are trusted is still judged by [`predict`](Self::predict).
    /// The default ignores `pending` (a model that cannot fantasise).
    fn predict_fantasised(&self, features: &[f64], pending: &[f64], dim: usize) -> Vec<(f64, f64)> {
        let _ = pending;
        self.predict(features, dim)
    }

    /// [`predict_fantasised`](Self::predict_fantasised) at the same `features` for any number
    /// of alternative pending sets, asked in as many calls of the returned function as suit
    /// the caller: the `spread` acquisition asks it about every candidate of a proposal. A
    /// model may prepare `features` once for all of them and share work between the sets of
    /// one call (the exact GP does both); the default asks anew for each set.
    fn fantasy<'a>(&'a self, features: &'a [f64], dim: usize) -> Fantasy<'a> {
        Box::new(move |pendings| {
            pendings
                .iter()
                .map(|pending| self.predict_fantasised(features, pending, dim))
                .collect()
        })
    }
}

/// What [`DeviationModel::fantasy`] answers: `(μ, σ)` at its features after each of several
/// alternative pending sets (row-major, the features' dimension each), in order.
pub type Fantasy<'a> = Box<dyn Fn(&[&[f64]]) -> Vec<Vec<(f64, f64)>> + 'a>;

/// Why the planner could not answer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanningError {
    /// A planner, acquisition or schedule setting is out of range.
    #[error("{field}: {reason}")]
    InvalidSettings {
        /// The setting's name, e.g. `"goal_bias"`.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// An input of the planning problem (start, goal, β, d_max) is not acceptable.
    #[error("{field}: {reason}")]
    InvalidInput {
        /// `"start"`, `"goal"`, `"beta"` or `"d_max"`.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// No candidate reached the goal inside the precondition (for `random`: not even one step
    /// from the start was possible).
    #[error("no plan inside the model precondition within {extensions} extensions")]
    NoPlan {
        /// Extensions (attempted edges) spent before giving up.
        extensions: usize,
    },
    /// The search stopped before it concluded: its deadline passed or it was cancelled.
    #[error("the search stopped ({reason:?}) after {extensions} extensions")]
    Stopped {
        /// Why.
        reason: Stop,
        /// Extensions spent until then.
        extensions: usize,
    },
    /// The dynamics model `f̂` could not answer (a remote model that failed or timed out).
    #[error(transparent)]
    Dynamics(#[from] crate::domain::DynamicsError),
    /// The deviation model broke its contract (a bug in the model, not in the request).
    #[error("the deviation model returned {got} predictions for {expected} points")]
    ModelOutput {
        /// Points asked for.
        expected: usize,
        /// Predictions returned.
        got: usize,
    },
}

impl PlanningError {
    pub(crate) fn settings(field: &'static str, reason: impl Into<String>) -> Self {
        Self::InvalidSettings {
            field,
            reason: reason.into(),
        }
    }

    pub(crate) fn input(field: &'static str, reason: impl Into<String>) -> Self {
        Self::InvalidInput {
            field,
            reason: reason.into(),
        }
    }
}
