//! The β schedule of active learning: optimistic early (β < 0 widens the precondition, so the
//! planner tries what the model is unsure of), conservative late (β > 0).

use super::error::PlanningError;

/// `β_j = 2 k1 / (1 + exp(−k2 (j − J/2))) − k1`: a logistic curve from about `−k1` (at `j = 0`
/// for large `k2 J`) through `0` at `j = J/2` to about `k1`.
///
/// `j` is the current iteration (it may exceed `total_iterations`; β keeps approaching `k1`),
/// `total_iterations` is `J`, the number of planned iterations.
pub fn beta_schedule(j: usize, total_iterations: usize, k1: f64, k2: f64) -> f64 {
    let x = -k2 * (j as f64 - total_iterations as f64 / 2.0);
    2.0 * k1 / (1.0 + x.exp()) - k1
}

/// Most βs a relaxed training proposal tries (see [`relaxation_ladder`]).
pub const MAX_RELAXATION_STEPS: usize = 5;

/// The βs a training proposal tries in turn when no trajectory reaches the goal inside the
/// precondition at the iteration's `β_j` (`beta`): `β_j` itself, then lower values, evenly
/// spaced by at least 1 and ending at `floor` (the schedule's most optimistic β, `−k1`), at most
/// [`MAX_RELAXATION_STEPS`] in all. The first β with a plan is the smallest relaxation that
/// lets the robot try to reach the goal; a `β_j` at or below `floor` is tried alone.
pub fn relaxation_ladder(beta: f64, floor: f64) -> Vec<f64> {
    if beta.is_nan() || floor.is_nan() || beta <= floor {
        return vec![beta];
    }
    let steps = ((beta - floor).ceil() as usize).clamp(1, MAX_RELAXATION_STEPS - 1);
    let step = (beta - floor) / steps as f64;
    (0..steps)
        .map(|i| beta - step * i as f64)
        .chain([floor])
        .collect()
}

/// The schedule's parameters as an experiment setting.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BetaSchedule {
    /// Half the range of β: β goes from about `−k1` to about `k1`. Default 2 (paper); ≥ 0.
    pub k1: f64,
    /// Steepness of the logistic curve, per iteration. Default 0.5 (paper); ≥ 0.
    pub k2: f64,
    /// `J`, the number of planned iterations. Default 20; ≥ 1.
    pub iterations: usize,
}

impl Default for BetaSchedule {
    fn default() -> Self {
        Self {
            k1: 2.0,
            k2: 0.5,
            iterations: 20,
        }
    }
}

impl BetaSchedule {
    /// Checks the ranges; the error names the field.
    pub fn check(&self) -> Result<(), PlanningError> {
        if !(self.k1.is_finite() && self.k1 >= 0.0) {
            return Err(PlanningError::settings("k1", "must be a finite number ≥ 0"));
        }
        if !(self.k2.is_finite() && self.k2 >= 0.0) {
            return Err(PlanningError::settings("k2", "must be a finite number ≥ 0"));
        }
        if self.iterations == 0 {
            return Err(PlanningError::settings("iterations", "must be at least 1"));
        }
        Ok(())
    }

    /// β at iteration `j` (see [`beta_schedule`]).
    pub fn beta(&self, j: usize) -> f64 {
        beta_schedule(j, self.iterations, self.k1, self.k2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_abs_diff_eq;

    #[test]
    fn beta_is_zero_half_way() {
        assert_abs_diff_eq!(beta_schedule(10, 20, 2.0, 0.5), 0.0, epsilon = 1e-12);
        assert_abs_diff_eq!(beta_schedule(5, 10, 3.0, 1.7), 0.0, epsilon = 1e-12);
    }

    #[test]
    fn beta_approaches_plus_minus_k1() {
        assert_abs_diff_eq!(beta_schedule(0, 200, 2.0, 0.5), -2.0, epsilon = 1e-12);
        assert_abs_diff_eq!(beta_schedule(200, 200, 2.0, 0.5), 2.0, epsilon = 1e-12);
        assert_abs_diff_eq!(beta_schedule(10_000, 20, 2.0, 0.5), 2.0, epsilon = 1e-12);
    }

    #[test]
    fn beta_matches_a_hand_computed_value() {
        // j = 0, J = 20, k1 = 2, k2 = 0.5: 4 / (1 + e^5) − 2 = 4 / 149.4131591… − 2 = −1.9732286…
        assert_abs_diff_eq!(
            beta_schedule(0, 20, 2.0, 0.5),
            -1.973_228_596,
            epsilon = 1e-8
        );
        // j = 12: 4 / (1 + e^−1) − 2 = 2 tanh(1/2).
        assert_abs_diff_eq!(
            beta_schedule(12, 20, 2.0, 0.5),
            2.0 * 0.5f64.tanh(),
            epsilon = 1e-12
        );
    }

    #[test]
    fn beta_is_antisymmetric_about_the_middle() {
        for j in 0..=20 {
            assert_abs_diff_eq!(
                beta_schedule(j, 20, 2.0, 0.5),
                -beta_schedule(20 - j, 20, 2.0, 0.5),
                epsilon = 1e-12
            );
        }
    }

    #[test]
    fn the_relaxation_ladder_steps_down_to_the_floor() {
        let ladder = relaxation_ladder(1.5, -2.0);
        assert_eq!(ladder.len(), 5);
        assert_abs_diff_eq!(ladder[0], 1.5);
        assert_abs_diff_eq!(ladder[1], 0.625, epsilon = 1e-12);
        assert_abs_diff_eq!(ladder[4], -2.0);
        assert!(ladder.windows(2).all(|w| w[1] < w[0]));
        // Close to the floor: β_j then the floor.
        assert_eq!(relaxation_ladder(-1.7, -2.0), vec![-1.7, -2.0]);
        // At or below the floor, or with the schedule off (k1 = 0 at β_j = 0): β_j alone.
        assert_eq!(relaxation_ladder(-2.0, -2.0), vec![-2.0]);
        assert_eq!(relaxation_ladder(0.0, 0.0), vec![0.0]);
        // A wide range is still at most MAX_RELAXATION_STEPS βs.
        let wide = relaxation_ladder(100.0, -100.0);
        assert_eq!(wide.len(), MAX_RELAXATION_STEPS);
        assert_abs_diff_eq!(wide[1], 50.0, epsilon = 1e-9);
    }

    #[test]
    fn settings_are_checked_by_field() {
        assert!(BetaSchedule::default().check().is_ok());
        let bad = BetaSchedule {
            k2: f64::NAN,
            ..Default::default()
        };
        assert!(matches!(
            bad.check(),
            Err(PlanningError::InvalidSettings { field: "k2", .. })
        ));
    }
}
