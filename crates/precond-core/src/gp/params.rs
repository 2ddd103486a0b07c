//! Checked GP settings: [`GpParams`] → [`ValidGpParams`].

use serde::{Deserialize, Serialize};

use super::{GpError, Hyperparameters, Kernel};

/// How the observation noise is modelled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(rename_all = "lowercase")]
pub enum NoiseMode {
    /// One noise variance for the whole input space (optimised with the other hyperparameters).
    Homoscedastic,
    /// Input-dependent noise: the *most likely heteroscedastic GP* of Kersting et al. (2007).
    ///
    /// A second GP models `log σ²_noise(x)`; see [`hetero`](super::hetero) for the procedure.
    Heteroscedastic,
}

/// Box bounds on the three kinds of hyperparameter, in natural (not log) units.
///
/// The optimiser works on the logarithms, so each interval must satisfy `0 < low ≤ high < ∞`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Bounds {
    /// Range of every ARD length scale, in unit-box input units.
    pub length_scale: (f64, f64),
    /// Range of the signal variance `s²` (units of the targets squared).
    pub signal_variance: (f64, f64),
    /// Range of the (homoscedastic) noise variance `σ²_n` (units of the targets squared).
    pub noise_variance: (f64, f64),
}

impl Bounds {
    /// Defaults for the main GP on unit-box inputs:
    /// length scales `[1e-2, 1e2]`, signal variance `[1e-6, 1e4]`, noise variance `[1e-6, 1e2]`.
    pub const MAIN: Bounds = Bounds {
        length_scale: (1e-2, 1e2),
        signal_variance: (1e-6, 1e4),
        noise_variance: (1e-6, 1e2),
    };

    /// Defaults for the heteroscedastic noise GP, whose targets are log variances (so of
    /// order one, with a residual noise variance near `π²/2 ≈ 4.9`):
    /// length scales `[5e-2, 1e2]`, signal variance `[1e-4, 1e2]`, noise variance `[1e-2, 1e2]`.
    pub const NOISE_MODEL: Bounds = Bounds {
        length_scale: (5e-2, 1e2),
        signal_variance: (1e-4, 1e2),
        noise_variance: (1e-2, 1e2),
    };

    fn check(&self, prefix: &'static [&'static str; 3]) -> Result<(), GpError> {
        for (name, (lo, hi)) in
            prefix
                .iter()
                .zip([self.length_scale, self.signal_variance, self.noise_variance])
        {
            if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && lo <= hi) {
                return Err(GpError::InvalidParameter {
                    name,
                    reason: format!("bounds must satisfy 0 < low <= high < inf, got ({lo}, {hi})"),
                });
            }
        }
        Ok(())
    }
}

impl Default for Bounds {
    fn default() -> Self {
        Bounds::MAIN
    }
}

/// Settings for fitting a GP. Build one (or start from [`Default`]), then call
/// [`GpParams::check`]; only the resulting [`ValidGpParams`] can fit a model.
///
/// Every field has a documented default and range; unknown combinations are rejected by `check`
/// with the field's name and the reason.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GpParams {
    /// Noise model. Default [`NoiseMode::Heteroscedastic`]; falls back to homoscedastic when there
    /// are fewer than [`hetero_min_points`](Self::hetero_min_points) training points.
    pub noise: NoiseMode,
    /// The main GP's kernel. Default [`Kernel::Matern52`] (the paper's). The heteroscedastic
    /// noise GP always uses ν = 5/2.
    pub kernel: Kernel,
    /// Constant prior mean `m` of the GP (finite). Default `0.0`: unexplored regions look
    /// trustworthy but uncertain, which drives exploration.
    pub prior_mean: f64,
    /// Extra seeded optimiser starts beyond the first (deterministic) one. Default `2`; range `0..=64`.
    pub restarts: usize,
    /// Seed of every random choice (restart points, screening subset). Same seed, same model.
    pub seed: u64,
    /// Box bounds of the main GP's hyperparameters. Default [`Bounds::MAIN`].
    pub bounds: Bounds,
    /// Box bounds of the heteroscedastic noise GP's hyperparameters. Default [`Bounds::NOISE_MODEL`].
    pub noise_model_bounds: Bounds,
    /// Maximum L-BFGS iterations per optimiser start. Default `200`; range `1..=10_000`.
    pub max_iterations: usize,
    /// Relative reduction of `−LML` below which an optimiser run stops:
    /// `(f_k − f_{k+1}) ≤ tol · max(|f_k|, |f_{k+1}|, 1)`. Default `1e-9`; range `(0, 1e-2]`.
    pub function_tolerance: f64,
    /// Infinity norm of the projected gradient of `−LML` (w.r.t. log-parameters) below which an
    /// optimiser run stops. Default `1e-5`; range `(0, 1]`.
    pub gradient_tolerance: f64,
    /// When `n` exceeds this (and `restarts > 0`), the random restarts are first optimised on a
    /// seeded random subset of this many points and only the best of them is refined on all the
    /// data (starting near its optimum, so that refinement needs few iterations). The
    /// deterministic default start always runs on all the data, because on a subset weakly
    /// relevant inputs look irrelevant. `0` disables screening (every start runs on all data).
    /// Default `512`; must be `0` or at least `64`.
    pub screen_subset: usize,
    /// First jitter tried when a Cholesky factorisation fails, relative to the mean diagonal of
    /// the covariance matrix (the first attempt always uses none). Default `1e-10`; range `(0, jitter_max]`.
    pub jitter_initial: f64,
    /// Largest relative jitter (grows ×10 per attempt); beyond it the fit fails with
    /// [`GpError::NotPositiveDefinite`]. Default `1e-4`; range `[jitter_initial, 1e-1]`.
    pub jitter_max: f64,
    /// Maximum number of heteroscedastic refinement rounds (each: estimate noise, fit the noise
    /// GP, refit the main GP); stops earlier once the LML stops improving. Default `4`; range `1..=20`.
    pub hetero_rounds: usize,
    /// Minimum relative LML improvement for another heteroscedastic round. Default `1e-4`; range `[0, 1)`.
    pub hetero_tolerance: f64,
    /// Below this many training points the heteroscedastic mode falls back to homoscedastic
    /// (a noise model cannot be learnt from a handful of residuals). Default `8`; range `>= 2`.
    pub hetero_min_points: usize,
    /// Where the optimisation starts when a related fit is known (a refit after one more batch):
    /// the previous optimum is then the only start — no restarts, no screening — and the
    /// heteroscedastic noise GP's first round starts from the previous noise GP. Default
    /// `None`: a new fit from the default start and `restarts` random ones. Not serialised: a
    /// fit's own business, never a setting.
    #[serde(skip)]
    pub warm: Option<WarmStart>,
}

/// A previous fit's optimum, to start a related fit from ([`GpParams::warm`]).
#[derive(Clone, Debug, PartialEq)]
pub struct WarmStart {
    /// The main GP's `[log ℓ.., log s², log σ²]` (homoscedastic form: for a heteroscedastic fit,
    /// its mean noise variance).
    pub main: Vec<f64>,
    /// The noise GP's `[log ℓ.., log s², log σ²]`, for a heteroscedastic fit.
    pub noise: Option<Vec<f64>>,
}

impl WarmStart {
    /// The optimum of a fit with hyperparameters `main` (and the noise GP's `noise`), in the
    /// optimiser's log form; a zero noise variance is floored at `1e-12`.
    pub fn of(main: &Hyperparameters, noise: Option<&Hyperparameters>) -> Self {
        let log = |h: &Hyperparameters| -> Vec<f64> {
            h.length_scales
                .iter()
                .map(|l| l.ln())
                .chain([h.signal_variance.ln(), h.noise_variance.max(1e-12).ln()])
                .collect()
        };
        Self {
            main: log(main),
            noise: noise.map(log),
        }
    }

    /// `theta` for `d` inputs clipped into the log-`bounds` (`None` when its length or values
    /// do not fit `d` inputs, so that a start from another problem is never used).
    pub(crate) fn within(theta: &[f64], d: usize, bounds: &Bounds) -> Option<Vec<f64>> {
        if theta.len() != d + 2 || !theta.iter().all(|v| v.is_finite()) {
            return None;
        }
        let (lo, hi) = super::fit::log_bounds(d, bounds, true);
        Some(
            theta
                .iter()
                .zip(lo.iter().zip(&hi))
                .map(|(v, (l, h))| v.clamp(*l, *h))
                .collect(),
        )
    }
}

impl Default for GpParams {
    fn default() -> Self {
        GpParams {
            noise: NoiseMode::Heteroscedastic,
            kernel: Kernel::Matern52,
            prior_mean: 0.0,
            restarts: 2,
            seed: 0,
            bounds: Bounds::MAIN,
            noise_model_bounds: Bounds::NOISE_MODEL,
            max_iterations: 200,
            function_tolerance: 1e-9,
            gradient_tolerance: 1e-5,
            screen_subset: 512,
            jitter_initial: 1e-10,
            jitter_max: 1e-4,
            hetero_rounds: 4,
            hetero_tolerance: 1e-4,
            hetero_min_points: 8,
            warm: None,
        }
    }
}

/// Settings that passed their `check` ([`GpParams::check`], [`SparseParams::check`]); the only
/// way to fit a model with them. Only those checks make one.
///
/// [`SparseParams::check`]: super::SparseParams::check
#[derive(Clone, Debug, PartialEq)]
pub struct Checked<T>(T);

impl<T> Checked<T> {
    /// Settings the caller has just checked (the checks of the `gp` module alone call it).
    pub(in crate::gp) fn new(params: T) -> Self {
        Checked(params)
    }

    /// The checked settings.
    pub fn params(&self) -> &T {
        &self.0
    }
}

impl<T> std::ops::Deref for Checked<T> {
    type Target = T;
    fn deref(&self) -> &T {
        &self.0
    }
}

/// [`GpParams`] that passed [`GpParams::check`]; the only way to fit a model.
pub type ValidGpParams = Checked<GpParams>;

/// Checks a subset size that is 0 (off) or at least `min`; the error names the field `name`.
pub(super) fn off_or_at_least(name: &'static str, value: usize, min: usize) -> Result<(), GpError> {
    if value != 0 && value < min {
        return Err(invalid(
            name,
            format!("must be 0 (off) or at least {min}, got {value}"),
        ));
    }
    Ok(())
}

fn invalid(name: &'static str, reason: impl Into<String>) -> GpError {
    GpError::InvalidParameter {
        name,
        reason: reason.into(),
    }
}

impl GpParams {
    /// Validates every field against its documented range.
    pub fn check(&self) -> Result<ValidGpParams, GpError> {
        if !self.prior_mean.is_finite() {
            return Err(invalid("prior_mean", "must be finite"));
        }
        if self.restarts > 64 {
            return Err(invalid(
                "restarts",
                format!("must be at most 64, got {}", self.restarts),
            ));
        }
        self.bounds.check(&[
            "bounds.length_scale",
            "bounds.signal_variance",
            "bounds.noise_variance",
        ])?;
        self.noise_model_bounds.check(&[
            "noise_model_bounds.length_scale",
            "noise_model_bounds.signal_variance",
            "noise_model_bounds.noise_variance",
        ])?;
        if !(1..=10_000).contains(&self.max_iterations) {
            return Err(invalid(
                "max_iterations",
                format!("must be in 1..=10000, got {}", self.max_iterations),
            ));
        }
        if !(self.function_tolerance > 0.0 && self.function_tolerance <= 1e-2) {
            return Err(invalid(
                "function_tolerance",
                format!("must be in (0, 1e-2], got {}", self.function_tolerance),
            ));
        }
        if !(self.gradient_tolerance > 0.0 && self.gradient_tolerance <= 1.0) {
            return Err(invalid(
                "gradient_tolerance",
                format!("must be in (0, 1], got {}", self.gradient_tolerance),
            ));
        }
        off_or_at_least("screen_subset", self.screen_subset, 64)?;
        if !(self.jitter_max.is_finite() && self.jitter_max > 0.0 && self.jitter_max <= 0.1) {
            return Err(invalid(
                "jitter_max",
                format!("must be in (0, 0.1], got {}", self.jitter_max),
            ));
        }
        if !(self.jitter_initial > 0.0 && self.jitter_initial <= self.jitter_max) {
            return Err(invalid(
                "jitter_initial",
                format!(
                    "must be in (0, jitter_max = {}], got {}",
                    self.jitter_max, self.jitter_initial
                ),
            ));
        }
        if !(1..=20).contains(&self.hetero_rounds) {
            return Err(invalid(
                "hetero_rounds",
                format!("must be in 1..=20, got {}", self.hetero_rounds),
            ));
        }
        if !(self.hetero_tolerance >= 0.0 && self.hetero_tolerance < 1.0) {
            return Err(invalid(
                "hetero_tolerance",
                format!("must be in [0, 1), got {}", self.hetero_tolerance),
            ));
        }
        if self.hetero_min_points < 2 {
            return Err(invalid(
                "hetero_min_points",
                format!("must be at least 2, got {}", self.hetero_min_points),
            ));
        }
        Ok(Checked::new(self.clone()))
    }
}
