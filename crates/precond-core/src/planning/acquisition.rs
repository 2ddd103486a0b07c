//! The trajectory-level acquisition function. The `active` strategy executes the candidate
//! with the smallest value `α`. Two kinds ([`AcquisitionKind`]):
//!
//! - `lcb` (the paper's): a lower confidence bound per step, `α_step = μ − c σ`, aggregated
//!   with a discount (`max` or `sum`, see [`Aggregation`]): the trajectory whose steps are most
//!   plausibly within tolerance, uncertainty counting in their favour.
//! - `level_set`: the precondition is a level set (`deviation < d_max`), so what an execution
//!   teaches is how ambiguous each step's side of `d_max` is. With `p_t = Φ((d_max − μ_t)/σ_t)`
//!   the probability that step `t` is within tolerance, a step's ambiguity is
//!   `4 p_t (1 − p_t)` (1 on the level set, 0 far from it, as in the straddle/LSE family of
//!   level-set acquisitions), and it counts only as much as the robot is likely to reach that
//!   step where it was planned, `r_t = Π_{k<t} p_k` (steps after a likely failure are executed
//!   from elsewhere and teach little about the plan). `α_step = −r_t · 4 p_t (1 − p_t)` and
//!   `α = Σ_t γ^t α_step(t)`: the smallest `α` is the trajectory expected to settle the most
//!   doubtful steps. `aggregation` and `c` do not apply.
//! - `bottleneck`: in a domain with finitely many state-actions, of the candidates and a probe
//!   (a way to the most promising untrusted step, ending there), the one whose execution is
//!   expected to open the most problems of the domain's distribution at the test β
//!   ([`bottleneck`](super::bottleneck)); `lcb` where nothing crosses such a step, and in
//!   continuous domains.

use super::error::PlanningError;
use super::trajectory::Trajectory;
use serde::{Deserialize, Serialize};

/// How per-step utilities combine into a trajectory utility.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Aggregation {
    /// `h_max = max_t γ^t α_step(t)`: a trajectory scores its (discounted) step whose lower
    /// confidence bound on the deviation is highest, i.e. the step most surely out of tolerance.
    /// The default.
    #[default]
    Max,
    /// `h_sum = Σ_t γ^t α_step(t)`.
    Sum,
}

setting_names!(Aggregation, "aggregation", { Max => "max", Sum => "sum" });

/// Which acquisition function scores a trajectory (see the [module docs](self)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum AcquisitionKind {
    /// The paper's: `α = h(μ − c σ)`, discounted over the steps.
    #[default]
    Lcb,
    /// Reach-weighted ambiguity of each step's side of `d_max`, negated and summed.
    LevelSet,
    /// The steps that would open the most sampled problems (finite domains), else `lcb`.
    Bottleneck,
    /// The uncertainty about the precondition's boundary a candidate's execution would remove
    /// over a uniform sample of state-actions ([`spread`](super::spread)); `lcb` breaks ties.
    Spread,
}

setting_names!(AcquisitionKind, "acquisition", {
    Lcb => "lcb",
    LevelSet => "level_set",
    Bottleneck => "bottleneck",
    Spread => "spread",
});

/// The acquisition's parameters (experiment settings).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AcquisitionSettings {
    /// Which function: `lcb` (the paper's, the default) or `level_set`.
    pub kind: AcquisitionKind,
    /// Exploration weight `c` in `α_step = μ − c σ`. Default 1; finite, ≥ 0 (larger favours
    /// uncertain steps).
    pub c: f64,
    /// Discount `γ` over the steps of a trajectory (step `t` weighs `γ^t`, `t` from 0). Default
    /// 0.9; in `(0, 1]`.
    pub gamma: f64,
    /// `max` (default) or `sum`.
    pub aggregation: Aggregation,
    /// The β test plans are made at, which `bottleneck` values its steps against. Default 2.
    pub test_beta: f64,
}

impl Default for AcquisitionSettings {
    fn default() -> Self {
        Self {
            kind: AcquisitionKind::Lcb,
            c: 1.0,
            gamma: 0.9,
            aggregation: Aggregation::Max,
            test_beta: 2.0,
        }
    }
}

impl AcquisitionSettings {
    /// Checks the ranges; the error names the field.
    pub fn check(&self) -> Result<(), PlanningError> {
        if !(self.c.is_finite() && self.c >= 0.0) {
            return Err(PlanningError::settings("c", "must be a finite number ≥ 0"));
        }
        if !(self.gamma > 0.0 && self.gamma <= 1.0) {
            return Err(PlanningError::settings("gamma", "must lie in (0, 1]"));
        }
        if !self.test_beta.is_finite() {
            return Err(PlanningError::settings(
                "test_beta",
                "must be a finite number",
            ));
        }
        Ok(())
    }

    /// The per-step utilities of a trajectory and their aggregate `α`, for the tolerance
    /// `d_max` (which only `level_set` uses).
    pub fn score(&self, trajectory: &Trajectory, d_max: f64) -> (Vec<f64>, f64) {
        let pairs = trajectory.mu.iter().zip(&trajectory.sigma);
        match self.kind {
            AcquisitionKind::Lcb | AcquisitionKind::Bottleneck | AcquisitionKind::Spread => {
                let steps: Vec<f64> = pairs.map(|(m, s)| alpha_step(*m, *s, self.c)).collect();
                let alpha = aggregate(&steps, self.gamma, self.aggregation);
                (steps, alpha)
            }
            AcquisitionKind::LevelSet => {
                let mut reach = 1.0;
                let steps: Vec<f64> = pairs
                    .map(|(m, s)| {
                        let p = within_probability(*m, *s, d_max);
                        let u = -reach * 4.0 * p * (1.0 - p);
                        reach *= p;
                        u
                    })
                    .collect();
                let alpha = aggregate(&steps, self.gamma, Aggregation::Sum);
                (steps, alpha)
            }
        }
    }
}

/// `P(deviation < d_max) = Φ((d_max − μ)/σ)` under the model's Gaussian; for `σ = 0`, 1 or 0
/// by the side of `μ`.
pub fn within_probability(mu: f64, sigma: f64, d_max: f64) -> f64 {
    if sigma > 0.0 {
        0.5 * libm::erfc(-(d_max - mu) / (sigma * std::f64::consts::SQRT_2))
    } else if mu < d_max {
        1.0
    } else {
        0.0
    }
}

/// The step utility `α_step = μ − c σ` (a lower confidence bound on the deviation).
pub fn alpha_step(mu: f64, sigma: f64, c: f64) -> f64 {
    mu - c * sigma
}

/// The discounted aggregate of step utilities, `t` counted from 0:
/// `h_max = max_t γ^t α_t` or `h_sum = Σ_t γ^t α_t`.
///
/// For an empty trajectory `h_max` is `−∞` and `h_sum` is 0; the planner never scores one.
pub fn aggregate(alpha_steps: &[f64], gamma: f64, aggregation: Aggregation) -> f64 {
    let discounted = alpha_steps.iter().scan(1.0, |w, a| {
        let v = *w * a;
        *w *= gamma;
        Some(v)
    });
    match aggregation {
        Aggregation::Max => discounted.fold(f64::NEG_INFINITY, f64::max),
        Aggregation::Sum => discounted.sum(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_abs_diff_eq;

    #[test]
    fn step_utility_is_a_lower_confidence_bound() {
        assert_abs_diff_eq!(alpha_step(0.5, 0.2, 1.0), 0.3, epsilon = 1e-12);
        assert_abs_diff_eq!(alpha_step(0.5, 0.2, 2.5), 0.0, epsilon = 1e-12);
        assert_abs_diff_eq!(alpha_step(0.5, 0.2, 0.0), 0.5, epsilon = 1e-12);
    }

    #[test]
    fn h_max_by_hand() {
        // γ = 1: the plain maximum.
        assert_abs_diff_eq!(aggregate(&[1.0, 3.0, 2.0], 1.0, Aggregation::Max), 3.0);
        // γ = 0.5: 1, 0.5·3 = 1.5, 0.25·2 = 0.5 → 1.5.
        assert_abs_diff_eq!(aggregate(&[1.0, 3.0, 2.0], 0.5, Aggregation::Max), 1.5);
        // γ = 0.1: 1, 0.3, 0.02 → the first step wins.
        assert_abs_diff_eq!(aggregate(&[1.0, 3.0, 2.0], 0.1, Aggregation::Max), 1.0);
        // Negative utilities are discounted towards 0, so later ones are larger.
        assert_abs_diff_eq!(aggregate(&[-1.0, -1.0], 0.5, Aggregation::Max), -0.5);
        assert_abs_diff_eq!(aggregate(&[-0.2], 0.9, Aggregation::Max), -0.2);
    }

    #[test]
    fn h_sum_by_hand() {
        assert_abs_diff_eq!(aggregate(&[1.0, 3.0, 2.0], 1.0, Aggregation::Sum), 6.0);
        // 1 + 0.5·3 + 0.25·2 = 3.
        assert_abs_diff_eq!(aggregate(&[1.0, 3.0, 2.0], 0.5, Aggregation::Sum), 3.0);
        // 0.9^0·(−1) + 0.9·0.5 + 0.81·2 = −1 + 0.45 + 1.62 = 1.07.
        assert_abs_diff_eq!(
            aggregate(&[-1.0, 0.5, 2.0], 0.9, Aggregation::Sum),
            1.07,
            epsilon = 1e-12
        );
    }

    #[test]
    fn empty_trajectories_have_neutral_aggregates() {
        assert_eq!(aggregate(&[], 0.9, Aggregation::Max), f64::NEG_INFINITY);
        assert_eq!(aggregate(&[], 0.9, Aggregation::Sum), 0.0);
    }

    #[test]
    fn score_combines_steps_of_a_trajectory() {
        let t = Trajectory {
            states: vec![vec![0.0], vec![1.0], vec![2.0]],
            actions: vec![vec![1.0], vec![1.0]],
            mu: vec![0.4, 1.0],
            sigma: vec![0.1, 0.5],
        };
        let settings = AcquisitionSettings {
            kind: AcquisitionKind::Lcb,
            c: 2.0,
            gamma: 0.5,
            aggregation: Aggregation::Sum,
            ..AcquisitionSettings::default()
        };
        let (steps, alpha) = settings.score(&t, 0.1);
        assert_abs_diff_eq!(steps[0], 0.2, epsilon = 1e-12);
        assert_abs_diff_eq!(steps[1], 0.0, epsilon = 1e-12);
        assert_abs_diff_eq!(alpha, 0.2, epsilon = 1e-12);
    }

    #[test]
    fn level_set_prefers_reachable_doubt() {
        let traj = |mu: Vec<f64>, sigma: Vec<f64>| Trajectory {
            states: vec![vec![0.0]; mu.len() + 1],
            actions: vec![vec![1.0]; mu.len()],
            mu,
            sigma,
        };
        let acq = AcquisitionSettings {
            kind: AcquisitionKind::LevelSet,
            gamma: 1.0,
            ..Default::default()
        };
        let d = 0.1;
        // A step on the level set (μ = d_max) is fully ambiguous: p = 1/2, utility −1.
        let (steps, alpha) = acq.score(&traj(vec![0.1], vec![0.05]), d);
        assert_abs_diff_eq!(steps[0], -1.0, epsilon = 1e-12);
        assert_abs_diff_eq!(alpha, -1.0, epsilon = 1e-12);
        // A step surely inside teaches nothing, and lets the next step count fully.
        let (steps, _) = acq.score(&traj(vec![0.0, 0.1], vec![1e-3, 0.05]), d);
        assert!(steps[0].abs() < 1e-12);
        assert_abs_diff_eq!(steps[1], -1.0, epsilon = 1e-9);
        // After a step that surely fails, doubt counts for nothing: the robot is elsewhere.
        let (steps, _) = acq.score(&traj(vec![1.0, 0.1], vec![1e-3, 0.05]), d);
        assert!(steps[1].abs() < 1e-12);
        // So a trajectory with its doubtful step after a likely failure loses to one with it first.
        let late = acq.score(&traj(vec![0.2, 0.1], vec![0.05, 0.05]), d).1;
        let early = acq.score(&traj(vec![0.1, 0.2], vec![0.05, 0.05]), d).1;
        assert!(early < late, "{early} < {late}");
        // The paper's kind ignores d_max.
        let lcb = AcquisitionSettings::default();
        let t = traj(vec![0.3], vec![0.1]);
        assert_eq!(lcb.score(&t, 0.1), lcb.score(&t, 5.0));
    }

    #[test]
    fn within_probability_is_the_gaussian_cdf() {
        assert_abs_diff_eq!(within_probability(0.1, 0.05, 0.1), 0.5, epsilon = 1e-15);
        // Φ(1) ≈ 0.841345.
        assert_abs_diff_eq!(
            within_probability(0.05, 0.05, 0.1),
            0.841_344_746,
            epsilon = 1e-8
        );
        assert_eq!(within_probability(0.05, 0.0, 0.1), 1.0);
        assert_eq!(within_probability(0.15, 0.0, 0.1), 0.0);
    }

    #[test]
    fn settings_are_checked_by_field() {
        assert!(AcquisitionSettings::default().check().is_ok());
        let bad = AcquisitionSettings {
            gamma: 0.0,
            ..Default::default()
        };
        assert!(matches!(
            bad.check(),
            Err(PlanningError::InvalidSettings { field: "gamma", .. })
        ));
        let bad = AcquisitionSettings {
            c: -1.0,
            ..Default::default()
        };
        assert!(matches!(
            bad.check(),
            Err(PlanningError::InvalidSettings { field: "c", .. })
        ));
        assert_eq!("sum".parse::<Aggregation>(), Ok(Aggregation::Sum));
        assert!("mean".parse::<Aggregation>().is_err());
        assert_eq!(
            "level_set".parse::<AcquisitionKind>(),
            Ok(AcquisitionKind::LevelSet)
        );
        assert!("ucb".parse::<AcquisitionKind>().is_err());
    }
}
