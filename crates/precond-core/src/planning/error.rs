//! Why the planner could not answer.

use crate::budget::Stop;

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
