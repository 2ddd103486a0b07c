//! The planner's settings: those of the RRT and candidate generation ([`PlannerSettings`]) and,
//! checked together with the acquisition's once, the [`PlanningSettings`] a
//! [`Planner`](super::Planner) plans under.

use super::acquisition::AcquisitionSettings;
use super::error::PlanningError;
use crate::limits::{MAX_CANDIDATES, MAX_EXTENSIONS};

/// The planner's parameters (experiment settings).
#[derive(Debug, Clone, PartialEq)]
pub struct PlannerSettings {
    /// Budget of one RRT run, in extensions (attempted edges). Default 5000 (paper);
    /// 1 ..= [`MAX_EXTENSIONS`].
    pub max_extensions: usize,
    /// Number of seeded RRT runs per proposal, hence the largest number of candidates.
    /// Default 20; 1 ..= [`MAX_CANDIDATES`].
    pub n_candidates: usize,
    /// Probability that an extension grows towards the goal rather than a uniform state.
    /// Default 0.2 (a common choice: enough pull to reach the goal quickly in open space,
    /// enough spread to get around regions outside the precondition); in `[0, 1]`.
    pub goal_bias: f64,
    /// Largest number of edges proposed per round and sent to the deviation model together
    /// (see [`rrt`](mod@super::rrt)). Default 1, the classic one-edge-at-a-time RRT; 1 ..= 4096.
    pub extension_batch: usize,
    /// Candidate generation gives up (no plan) after this many runs have failed before any run
    /// reached the goal. Default 1: a run that spends its whole budget without reaching the
    /// goal is strong evidence that the goal is not reachable inside the precondition, and the
    /// answer "no plan within `max_extensions`" then costs one run, not `n_candidates`. Runs
    /// that fail after a success only contribute no candidate. 1 ..= `n_candidates`.
    pub max_failed_runs: usize,
    /// `random` strategy: actions sampled per step before the rollout stops early because none
    /// satisfies the constraints and the precondition. Default 20; 1 ..= 10 000.
    pub random_action_tries: usize,
}

impl Default for PlannerSettings {
    fn default() -> Self {
        Self {
            max_extensions: 5000,
            n_candidates: 20,
            goal_bias: 0.2,
            extension_batch: 1,
            max_failed_runs: 1,
            random_action_tries: 20,
        }
    }
}

impl PlannerSettings {
    /// Checks the ranges; the error names the field.
    pub fn check(&self) -> Result<(), PlanningError> {
        let in_range = |field, v: usize, lo: usize, hi: usize| {
            if v < lo || v > hi {
                Err(PlanningError::settings(
                    field,
                    format!("must lie in {lo} ..= {hi}, got {v}"),
                ))
            } else {
                Ok(())
            }
        };
        in_range(
            "max_extensions",
            self.max_extensions,
            1,
            MAX_EXTENSIONS as usize,
        )?;
        in_range(
            "n_candidates",
            self.n_candidates,
            1,
            MAX_CANDIDATES as usize,
        )?;
        in_range("extension_batch", self.extension_batch, 1, 4096)?;
        in_range(
            "max_failed_runs",
            self.max_failed_runs,
            1,
            self.n_candidates.max(1),
        )?;
        in_range("random_action_tries", self.random_action_tries, 1, 10_000)?;
        if !(0.0..=1.0).contains(&self.goal_bias) {
            return Err(PlanningError::settings(
                "goal_bias",
                format!("must lie in [0, 1], got {}", self.goal_bias),
            ));
        }
        Ok(())
    }
}

/// The planner's and the acquisition's settings, checked together once: only valid settings
/// can plan ([`PlanningSettings::new`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PlanningSettings {
    planner: PlannerSettings,
    acquisition: AcquisitionSettings,
}

impl Default for PlanningSettings {
    /// The defaults of both (valid by construction).
    fn default() -> Self {
        Self {
            planner: PlannerSettings::default(),
            acquisition: AcquisitionSettings::default(),
        }
    }
}

impl PlanningSettings {
    /// Checks both; the error names the field.
    pub fn new(
        planner: PlannerSettings,
        acquisition: AcquisitionSettings,
    ) -> Result<Self, PlanningError> {
        planner.check()?;
        acquisition.check()?;
        Ok(Self {
            planner,
            acquisition,
        })
    }

    /// The planner's settings.
    pub fn planner(&self) -> &PlannerSettings {
        &self.planner
    }

    /// The acquisition's settings.
    pub fn acquisition(&self) -> &AcquisitionSettings {
        &self.acquisition
    }

    /// The same settings with a search budget of `max_extensions` (at least 1) per RRT run:
    /// one test-time plan that searches longer or shorter than the experiment's default.
    pub fn with_max_extensions(&self, max_extensions: usize) -> Self {
        let mut planner = self.planner.clone();
        planner.max_extensions = max_extensions.max(1);
        Self {
            planner,
            acquisition: self.acquisition,
        }
    }
}
