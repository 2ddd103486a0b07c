//! The trajectory-level acquisition function: a lower confidence bound per step, aggregated
//! with a discount. The `active` strategy executes the candidate with the smallest value.

use super::PlanningError;
use super::trajectory::Trajectory;
use std::fmt;
use std::str::FromStr;

/// How per-step utilities combine into a trajectory utility.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
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

impl Aggregation {
    /// The setting's name: `"max"` or `"sum"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Max => "max",
            Self::Sum => "sum",
        }
    }
}

impl fmt::Display for Aggregation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Aggregation {
    type Err = PlanningError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "max" => Ok(Self::Max),
            "sum" => Ok(Self::Sum),
            other => Err(PlanningError::settings(
                "aggregation",
                format!("{other:?} is not one of \"max\", \"sum\""),
            )),
        }
    }
}

/// The acquisition's parameters (experiment settings).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AcquisitionSettings {
    /// Exploration weight `c` in `α_step = μ − c σ`. Default 1; finite, ≥ 0 (larger favours
    /// uncertain steps).
    pub c: f64,
    /// Discount `γ` over the steps of a trajectory (step `t` weighs `γ^t`, `t` from 0). Default
    /// 0.9; in `(0, 1]`.
    pub gamma: f64,
    /// `max` (default) or `sum`.
    pub aggregation: Aggregation,
}

impl Default for AcquisitionSettings {
    fn default() -> Self {
        Self {
            c: 1.0,
            gamma: 0.9,
            aggregation: Aggregation::Max,
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
        Ok(())
    }

    /// The per-step utilities of a trajectory and their aggregate `α`.
    pub fn score(&self, trajectory: &Trajectory) -> (Vec<f64>, f64) {
        let steps: Vec<f64> = trajectory
            .mu
            .iter()
            .zip(&trajectory.sigma)
            .map(|(m, s)| alpha_step(*m, *s, self.c))
            .collect();
        let alpha = aggregate(&steps, self.gamma, self.aggregation);
        (steps, alpha)
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
            c: 2.0,
            gamma: 0.5,
            aggregation: Aggregation::Sum,
        };
        let (steps, alpha) = settings.score(&t);
        assert_abs_diff_eq!(steps[0], 0.2, epsilon = 1e-12);
        assert_abs_diff_eq!(steps[1], 0.0, epsilon = 1e-12);
        assert_abs_diff_eq!(alpha, 0.2, epsilon = 1e-12);
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
    }
}
