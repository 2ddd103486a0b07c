//! The model precondition at one β: the state-actions whose deviation the MDE bounds below the
//! tolerance, `μ + β σ < d_max` (DESIGN.md §1). The one place this predicate is written.

use super::error::PlanningError;

/// `pre(f̂) = {(s, a) : μ(s, a) + β σ(s, a) < d_max}` for one `β` and `d_max`, checked: `β` is
/// finite and `d_max` a positive finite number, so only a usable precondition exists.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Precondition {
    beta: f64,
    d_max: f64,
}

impl Precondition {
    /// The precondition at confidence `beta` (finite; `β = Φ⁻¹(1 − δ)`, negative during early
    /// learning) and tolerance `d_max` (positive, finite). The error names `beta` or `d_max`.
    pub fn new(beta: f64, d_max: f64) -> Result<Self, PlanningError> {
        if !beta.is_finite() {
            return Err(PlanningError::input("beta", "must be a finite number"));
        }
        if !(d_max.is_finite() && d_max > 0.0) {
            return Err(PlanningError::input("d_max", "must be a positive number"));
        }
        Ok(Self { beta, d_max })
    }

    /// The same tolerance at another `beta` (checked as in [`Precondition::new`]).
    pub fn at_beta(self, beta: f64) -> Result<Self, PlanningError> {
        Self::new(beta, self.d_max)
    }

    /// `β`.
    pub fn beta(self) -> f64 {
        self.beta
    }

    /// `d_max`.
    pub fn d_max(self) -> f64 {
        self.d_max
    }

    /// The upper confidence bound `μ + β σ` on the deviation.
    pub fn upper(self, mu: f64, sigma: f64) -> f64 {
        mu + self.beta * sigma
    }

    /// Whether a state-action with deviation estimate `(μ, σ)` lies in the precondition,
    /// `μ + β σ < d_max`. Written so that a NaN from the model keeps it out.
    pub fn inside(self, mu: f64, sigma: f64) -> bool {
        self.upper(mu, sigma) < self.d_max
    }
}

/// How a precondition's verdicts agree with the true deviations of judged transitions: the
/// positives (true deviation below `d_max`) it judged inside, the negatives it judged outside.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Agreement {
    /// Transitions whose true deviation is below `d_max`.
    pub positives: usize,
    /// Transitions whose true deviation is at least `d_max`.
    pub negatives: usize,
    /// Positives judged inside.
    pub true_positives: usize,
    /// Negatives judged outside.
    pub true_negatives: usize,
}

impl Agreement {
    /// Counts one transition of true `deviation` that the precondition judged `inside` or not.
    pub fn count(&mut self, deviation: f64, d_max: f64, inside: bool) {
        if deviation < d_max {
            self.positives += 1;
            self.true_positives += usize::from(inside);
        } else {
            self.negatives += 1;
            self.true_negatives += usize::from(!inside);
        }
    }

    /// `true_positives / positives` (`None` without positives).
    pub fn tpr(&self) -> Option<f64> {
        (self.positives > 0).then(|| self.true_positives as f64 / self.positives as f64)
    }

    /// `true_negatives / negatives` (`None` without negatives).
    pub fn tnr(&self) -> Option<f64> {
        (self.negatives > 0).then(|| self.true_negatives as f64 / self.negatives as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inside_is_a_strict_upper_bound_and_nan_is_outside() {
        let p = Precondition::new(2.0, 0.1).unwrap();
        assert!(p.inside(0.0, 0.04));
        assert!(!p.inside(0.02, 0.04), "0.02 + 0.08 = d_max is not inside");
        assert!(!p.inside(f64::NAN, 0.0));
        assert!(!p.inside(0.0, f64::NAN));
        // A negative β widens the precondition.
        assert!(p.at_beta(-1.0).unwrap().inside(0.12, 0.05));
        assert_eq!(p.upper(0.01, 0.02), 0.05);
    }

    #[test]
    fn unusable_values_are_refused_by_name() {
        assert!(matches!(
            Precondition::new(f64::INFINITY, 0.1),
            Err(PlanningError::InvalidInput { field, .. }) if field == "beta"
        ));
        for d_max in [0.0, -1.0, f64::NAN] {
            assert!(matches!(
                Precondition::new(1.0, d_max),
                Err(PlanningError::InvalidInput { field, .. }) if field == "d_max"
            ));
        }
    }
}
