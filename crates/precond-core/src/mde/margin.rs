//! A locally calibrated trust margin ([`LocalMargin`]): the β a state-action is judged at,
//! chosen from how the fitted model judged its own training transitions held out *near it*,
//! rather than one β for the whole space.
//!
//! A certified test β ([`BetaChoice`](super::BetaChoice)) is one number for the whole space:
//! where the model is honest it throws trust away, where it is over-confident it trusts too
//! much. On the robot bench (`bench/robots/README.md`) `μ` ranks safe before unsafe well on
//! every robot while β = 2 trusts 1–26 % of the safe moves, and a smaller global β lets more
//! unsafe steps into plans where the model is wrong. The local margin asks, at each
//! state-action `x` and β: of the training transitions near `x` that the model, with their
//! whole trajectory held out, trusted at β *by less than [`BAND_STEPS`] grid steps* (trusted at
//! β, not at β + 0.5), how many were unsafe? It takes the smallest β at which that share —
//! weighted by closeness to `x` — is at most the certified β's false-trust rate (2 %), counting one
//! pessimistic pseudo-transition of weight [`PRIOR_WEIGHT`] that is unsafe whenever β is below
//! the experiment's test β. Far from every training transition the pseudo-transition decides
//! and the answer is the test β itself. So the margin never trusts less than the test β
//! would, and trusts more only where held-out transitions nearby show it safe.
//!
//! Why the band: a plan's steps sit at the edge of what is trusted (the search takes any
//! trusted step that gets it closer), so their risk is that of transitions trusted by a
//! little, not of all trusted ones — most of which lie deep inside. Counting all trusted ones
//! (the first form measured) planned 5.6–7.8 % unsafe steps on the robot bench's base, pusher
//! and 7-joint arm (`bench/robots/README.md`, which also says how little the band changes
//! there: it lowers β only where held-out transitions sit at the edge nearby). It is a local form of
//! conformal calibration (as LUCCa calibrates a dynamics model's prediction regions locally)
//! of the decision the planner makes rather than a coverage of the deviation, which measured
//! worse: a deviation far above `d_max` says no more than "unsafe", yet it widens a coverage
//! quantile for every state-action near it.

use crate::planning::DeviationModel;

/// The weight of the pessimistic pseudo-transition: the closeness-weighted trusted mass the
/// training transitions near a state-action must reach, all of them safe, before it is judged
/// below the test β (`PRIOR_WEIGHT` over the false-trust rate: 5 transitions at distance 0
/// for 2 %).
pub const PRIOR_WEIGHT: f64 = 0.1;

/// The closeness kernel's bandwidth per feature, in the unit box the features live in: a
/// transition at distance `BANDWIDTH · √dim` weighs `e^{-1/2}`.
pub const BANDWIDTH: f64 = 0.1;

/// The spacing of the β grid the local margin is chosen on (as the certified β's).
const GRID_STEP: f64 = 0.1;

/// The band of β (in grid steps) a transition must be trusted within to count at β: trusted
/// at β but not at `β + BAND_STEPS · GRID_STEP`.
pub const BAND_STEPS: usize = 5;

/// How each training transition was judged held out, and where it lies: what a local margin
/// needs to judge any state-action ([`LocalMargin::beta_at`]).
#[derive(Debug, Clone, PartialEq)]
pub struct LocalMargin {
    dim: usize,
    /// The training features, row-major.
    x: Vec<f64>,
    /// Per training row, how many β of the grid (from 0, up to `BAND_STEPS` above its top)
    /// it was trusted at, held out.
    trusted_steps: Vec<u32>,
    /// Per training row, whether its deviation reached `d_max`.
    unsafe_rows: Vec<bool>,
    /// Grid points `0, GRID_STEP, …` below `max_beta`.
    steps: usize,
    /// `1 / (2 h²)` with `h = BANDWIDTH · √dim`.
    inverse_width: f64,
    /// The share of unsafe transitions at the edge of trust it accepts.
    false_trust: f64,
}

/// What a [`LocalMargin`] is calibrated against: the tolerance, the test β it never exceeds,
/// and the share of unsafe transitions at the edge of trust it accepts (the certified β's, 2 %).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    /// `d_max`: a transition deviating by this much or more is unsafe.
    pub d_max: f64,
    /// The largest β the margin takes (the experiment's test β).
    pub max_beta: f64,
    /// The accepted false-trust rate.
    pub false_trust: f64,
}

impl LocalMargin {
    /// The margin from training features `x` (row-major, `dim` each), their deviations, and
    /// their held-out predictions `(label − μ₋ᵢ, σ₋ᵢ)` of `labels` (each trajectory left out
    /// whole, [`trajectory_folds`](super::trajectory_folds)), for β on the grid below
    /// `calibration.max_beta`. `None` when the lengths disagree or `dim` is 0.
    pub fn from_held_out(
        x: &[f64],
        dim: usize,
        held_out: &[(f64, f64)],
        labels: &[f64],
        deviations: &[f64],
        calibration: Calibration,
    ) -> Option<Self> {
        let Calibration {
            d_max,
            max_beta,
            false_trust,
        } = calibration;
        let n = deviations.len();
        if dim == 0 || x.len() != n * dim || held_out.len() != n || labels.len() != n {
            return None;
        }
        let steps = if max_beta > 0.0 {
            (max_beta / GRID_STEP - 1e-9).ceil() as usize
        } else {
            0
        };
        let trusted_steps = held_out
            .iter()
            .zip(labels)
            .map(|(&(residual, sd), &label)| {
                let mu = label - residual;
                // Counted up to a band above the grid, so that at its top a transition
                // trusted far beyond `max_beta` is not taken for one trusted by a little.
                (0..steps + BAND_STEPS)
                    .take_while(|&g| mu + g as f64 * GRID_STEP * sd < d_max)
                    .count() as u32
            })
            .collect();
        let h = BANDWIDTH * (dim as f64).sqrt();
        Some(Self {
            dim,
            x: x.to_vec(),
            trusted_steps,
            unsafe_rows: deviations.iter().map(|&d| d >= d_max).collect(),
            steps,
            inverse_width: 1.0 / (2.0 * h * h),
            false_trust,
        })
    }

    /// The feature dimension it judges.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Training transitions it was calibrated on.
    pub fn n_train(&self) -> usize {
        self.unsafe_rows.len()
    }

    /// The β to judge the state-action with features `row` at: the smallest β on the grid
    /// below `prior` at which the closeness-weighted share of unsafe transitions among those
    /// trusted held out at β, with the pessimistic pseudo-transition, is at most
    /// its false-trust rate; `prior` when there is none (and whenever `prior` ≤ 0).
    pub fn beta_at(&self, row: &[f64], prior: f64) -> f64 {
        if prior <= 0.0 || row.len() != self.dim {
            return prior;
        }
        // Trusted mass by how many grid steps a row was trusted at; suffix sums give the mass
        // trusted at each β.
        let top = self.steps + BAND_STEPS;
        let mut trusted = vec![0.0; top + 1];
        let mut unsafe_trusted = vec![0.0; top + 1];
        for (i, xi) in self.x.chunks_exact(self.dim).enumerate() {
            let d2: f64 = xi.iter().zip(row).map(|(a, b)| (a - b) * (a - b)).sum();
            let w = (-d2 * self.inverse_width).exp();
            let k = self.trusted_steps[i] as usize;
            trusted[k] += w;
            if self.unsafe_rows[i] {
                unsafe_trusted[k] += w;
            }
        }
        let (mut mass, mut unsafe_mass) = (0.0, 0.0);
        let mut at = vec![(0.0, 0.0); top];
        // Rows with k > g are trusted at step g.
        for g in (0..top).rev() {
            mass += trusted[g + 1];
            unsafe_mass += unsafe_trusted[g + 1];
            at[g] = (mass, unsafe_mass);
        }
        for (g, &(mass, unsafe_mass)) in at.iter().enumerate().take(self.steps) {
            let beta = g as f64 * GRID_STEP;
            if beta >= prior {
                break;
            }
            // Only the transitions trusted at β by less than BAND: a planned step sits at the
            // edge of what is trusted, and its risk is theirs, not that of the ones deep inside.
            let (above, unsafe_above) = at.get(g + BAND_STEPS).copied().unwrap_or((0.0, 0.0));
            let (band, unsafe_band) = (mass - above, unsafe_mass - unsafe_above);
            if (unsafe_band + PRIOR_WEIGHT) / (band + PRIOR_WEIGHT) <= self.false_trust {
                return beta;
            }
        }
        prior
    }

    /// [`beta_at`](Self::beta_at) for every row of `features` (row-major, [`dim`](Self::dim)
    /// each).
    pub fn betas(&self, features: &[f64], prior: f64) -> Vec<f64> {
        features
            .chunks_exact(self.dim.max(1))
            .map(|row| self.beta_at(row, prior))
            .collect()
    }
}

/// A deviation model judged at a local margin, for the planner: `σ` scaled by `β(x) / β`, so
/// that a precondition at `β` trusts exactly where `μ + β(x) σ < d_max`. Only the search sees
/// the scaled `σ`; what a plan reports is the model's own (see the service's test plans).
pub struct Margined<'a> {
    model: &'a dyn DeviationModel,
    margin: &'a LocalMargin,
    beta: f64,
}

impl<'a> Margined<'a> {
    /// `model` judged at `margin` under the test β `beta`; `None` unless `beta` is positive
    /// (a scale needs one).
    pub fn new(model: &'a dyn DeviationModel, margin: &'a LocalMargin, beta: f64) -> Option<Self> {
        (beta > 0.0 && beta.is_finite()).then_some(Self {
            model,
            margin,
            beta,
        })
    }
}

impl DeviationModel for Margined<'_> {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        let plain = self.model.predict(features, dim);
        if dim != self.margin.dim() {
            return plain;
        }
        plain
            .into_iter()
            .zip(features.chunks_exact(dim))
            .map(|((mu, sd), row)| (mu, sd * self.margin.beta_at(row, self.beta) / self.beta))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `d_max` 0.1, the test β 2, 2 % false trust.
    const AT: Calibration = Calibration {
        d_max: 0.1,
        max_beta: 2.0,
        false_trust: 0.02,
    };

    fn margin(parts: &[(usize, f64, f64, f64, f64)]) -> LocalMargin {
        let (mut x, mut held, mut labels, mut dev) = (vec![], vec![], vec![], vec![]);
        // `n` rows at `at` (1-D), each held out at μ = `mu` (its label, residual 0), σ = `sd`,
        // with deviation `d`.
        for &(n, at, mu, sd, d) in parts {
            x.extend(std::iter::repeat_n(at, n));
            held.extend(std::iter::repeat_n((0.0, sd), n));
            labels.extend(std::iter::repeat_n(mu, n));
            dev.extend(std::iter::repeat_n(d, n));
        }
        LocalMargin::from_held_out(&x, 1, &held, &labels, &dev, AT).unwrap()
    }

    #[test]
    fn far_from_every_transition_the_test_beta_stands() {
        // Honest safe transitions at 0.2; a query at 0.9 is ~7 bandwidths away.
        let m = margin(&[(40, 0.2, 0.02, 0.05, 0.02)]);
        assert_eq!(m.beta_at(&[0.9], 2.0), 2.0);
    }

    #[test]
    fn near_many_safe_transitions_trusted_held_out_the_margin_shrinks() {
        // μ 0.02, σ 0.05: trusted held out while 0.02 + β·0.05 < 0.1, i.e. below β 1.6; all
        // safe. From β 1.1 they are trusted by less than the band (0.5): the margin there,
        // under which a state-action like them (μ + 1.1σ = 0.075) is trusted, as at β 2
        // (0.12) it is not.
        let m = margin(&[(40, 0.2, 0.02, 0.05, 0.02)]);
        assert!((m.beta_at(&[0.2], 2.0) - 1.1).abs() < 1e-9);
        // Too few to outweigh the pseudo-transition (mass 4 < 5): the test β.
        let few = margin(&[(4, 0.2, 0.02, 0.05, 0.02)]);
        assert_eq!(few.beta_at(&[0.2], 2.0), 2.0);
    }

    #[test]
    fn unsafe_transitions_trusted_held_out_push_the_margin_up_locally() {
        // At 0.5: 60 safe ones trusted below β 1.6, and 10 unsafe ones (deviation 0.3) the
        // model held out put at μ 0.025, σ 0.05 — trusted below β 1.5. The margin must rise
        // until the unsafe ones are no longer trusted (1.5), and stay at 1.1 at 0.2, where
        // all are safe.
        let m = margin(&[
            (60, 0.5, 0.02, 0.05, 0.02),
            (10, 0.5, 0.025, 0.05, 0.3),
            (40, 0.2, 0.02, 0.05, 0.02),
        ]);
        let near_unsafe = m.beta_at(&[0.5], 2.0);
        assert!((near_unsafe - 1.5).abs() < 1e-9, "{near_unsafe}");
        assert!((m.beta_at(&[0.2], 2.0) - 1.1).abs() < 1e-9);
        // Never above the test β, and a test β of 0 or less is kept as it is.
        assert_eq!(m.beta_at(&[0.5], 1.0), 1.0);
        assert_eq!(m.beta_at(&[0.5], -0.5), -0.5);
    }

    #[test]
    fn transitions_trusted_far_beyond_the_test_beta_are_not_at_the_edge() {
        // μ 0, σ 0.01: trusted held out up to β 9.9, far above the band at any β below 2 —
        // no evidence about the edge of trust, so the test β stands (β 2 trusts a
        // state-action like them anyway: 0.02 < 0.1).
        let m = margin(&[(40, 0.2, 0.0, 0.01, 0.0)]);
        assert_eq!(m.beta_at(&[0.2], 2.0), 2.0);
    }

    #[test]
    fn mismatched_inputs_are_refused() {
        assert!(
            LocalMargin::from_held_out(&[0.1, 0.2], 1, &[(0.0, 0.1)], &[0.0], &[0.0], AT).is_none()
        );
        assert!(LocalMargin::from_held_out(&[], 0, &[], &[], &[], AT).is_none());
    }
}
