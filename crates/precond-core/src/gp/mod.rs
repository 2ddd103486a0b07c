#![warn(missing_docs)]
//! The Gaussian-process model deviation estimator (MDE): a Matérn ARD GP (ν = 5/2, the paper's,
//! or the rougher 3/2 and 1/2) with a constant prior mean and homoscedastic or *most likely
//! heteroscedastic* noise (Kersting et al. 2007).
//!
//! - [`params`]: checked settings ([`GpParams`] → [`ValidGpParams`]); only valid ones can fit.
//! - `kernel` (private): the kernels ([`Kernel`]) and the dense matrices built from them.
//! - `lml` / `lbfgs` / `fit` (private): the log marginal likelihood with analytic gradients and
//!   its maximisation over log-parameters by projected L-BFGS under box bounds, from seeded starts.
//! - [`hetero`]: the heteroscedastic noise procedure.
//! - [`model`]: [`GpModel`] — fit, rebuild from a [`ModelState`], batched prediction.
//! - [`export`]: a fitted GP as plain numbers ([`Predictor`]) that a program outside this
//!   crate evaluates itself.
//! - [`cost`]: a fit's peak memory and work, estimated before it allocates ([`exact_fit_cost`],
//!   [`sparse_fit_cost`]), so a server can refuse an exact fit over its budget.
//! - [`sparse`]: [`SparseGp`] — the sparse variational GP (SGPR/VFE, `m` inducing points) for
//!   large `n`: O(n m²) fits, O(m²) predictions, online updates, save/restore without the data.
//!
//! The API speaks nalgebra (`DMatrix` rows are points, already scaled to the unit box); the
//! O(n²)/O(n³) work runs on faer's blocked kernels. Numerical failure is a [`GpError`], never a panic.
//!
//! ```
//! use nalgebra::{DMatrix, DVector};
//! use precond_core::gp::{GpModel, GpParams, NoiseMode};
//!
//! let x = DMatrix::from_fn(30, 2, |i, j| ((i * 7 + j * 3) % 30) as f64 / 30.0);
//! let y = DVector::from_fn(30, |i, _| (3.0 * x[(i, 0)]).sin() + 0.5 * x[(i, 1)]);
//! let params = GpParams { noise: NoiseMode::Homoscedastic, ..GpParams::default() }.check()?;
//! let model = GpModel::fit(&x, &y, &params)?;
//! let pred = model.predict(&DMatrix::from_row_slice(1, 2, &[0.5, 0.5]));
//! assert!(pred.std()[0] > 0.0);
//! # Ok::<(), precond_core::gp::GpError>(())
//! ```

mod core;
pub mod cost;
mod error;
pub mod export;
mod fit;
pub mod hetero;
mod kernel;
mod lbfgs;
mod linalg;
mod lml;
pub mod model;
pub mod params;
pub mod sparse;
pub mod synthetic;
#[cfg(test)]
mod tests;

use serde::{Deserialize, Serialize};

pub use cost::{FitCost, exact_fit_cost, sparse_fit_cost};
pub use error::GpError;
pub use export::{GpPredictor, NoisePredictor, PointPrediction, Predictor};
pub use kernel::Kernel;
pub use model::{Fold, GpModel};
pub use params::{Bounds, Checked, GpParams, NoiseMode, ValidGpParams, WarmStart};
pub use sparse::{
    DEFAULT_FULL_RANK_UP_TO, DEFAULT_INDUCING_POINTS, SparseGp, SparseParams, SparseState,
    ValidSparseParams,
};

/// Signal variance of the prior before any data ([`Hyperparameters::prior`]): `1.0`, i.e. a prior
/// standard deviation of 1 in target units — large next to typical deviation thresholds, so an
/// unexplored model is honestly uncertain.
pub const DEFAULT_PRIOR_SIGNAL_VARIANCE: f64 = 1.0;

/// Length scale of the prior before any data ([`Hyperparameters::prior`]): `0.5` (unit-box units).
pub const DEFAULT_PRIOR_LENGTH_SCALE: f64 = 0.5;

/// The GP's hyperparameters in natural units.
///
/// Covariance: the Matérn [`Kernel`] of smoothness `ν` at `r² = Σ_k ((x_k − x'_k)/ℓ_k)²` times `s²`
/// (for ν = 5/2, `s² (1 + √5 r + 5/3 r²) exp(−√5 r)`), plus noise on the diagonal; prior mean
/// constant `m`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct Hyperparameters {
    /// ARD length scales `ℓ_k`, one per input dimension, in unit-box units (> 0).
    pub length_scales: Vec<f64>,
    /// Signal variance `s²` (> 0), target units squared.
    pub signal_variance: f64,
    /// Noise variance `σ²_n` (≥ 0), target units squared. Heteroscedastic models report the mean
    /// of the per-point training noise variances here (see [`NoiseSummary`] for the rest).
    pub noise_variance: f64,
    /// Constant prior mean `m` (not optimised).
    pub prior_mean: f64,
    /// The Matérn kernel's smoothness (not optimised by the LML: chosen by the settings, or
    /// among several fits).
    pub kernel: Kernel,
}

impl Hyperparameters {
    /// The prior used before any data: every length scale [`DEFAULT_PRIOR_LENGTH_SCALE`], signal
    /// variance [`DEFAULT_PRIOR_SIGNAL_VARIANCE`], no noise, the given prior mean. Without data the
    /// posterior is the prior: μ = `prior_mean`, σ = [`prior_std`](Self::prior_std) everywhere.
    pub fn prior(dim: usize, prior_mean: f64) -> Self {
        Hyperparameters {
            length_scales: vec![DEFAULT_PRIOR_LENGTH_SCALE; dim],
            signal_variance: DEFAULT_PRIOR_SIGNAL_VARIANCE,
            noise_variance: 0.0,
            prior_mean,
            kernel: Kernel::default(),
        }
    }

    /// Prior standard deviation of an observation, `√(s² + σ²_n)` (what an unfitted model reports as σ).
    pub fn prior_std(&self) -> f64 {
        (self.signal_variance + self.noise_variance).sqrt()
    }

    /// The prior's prediction at `m` points: mean `prior_mean`, latent variance `s²`, noise `σ²_n`.
    pub fn prior_prediction(&self, m: usize) -> Prediction {
        Prediction {
            mean: vec![self.prior_mean; m],
            latent_variance: vec![self.signal_variance; m],
            noise_variance: vec![self.noise_variance; m],
        }
    }

    /// Checks that the values are usable for `dim` inputs (finite, positive, right length).
    pub fn check(&self, dim: usize, what: &'static str) -> Result<(), GpError> {
        if self.length_scales.len() != dim {
            return Err(GpError::DimensionMismatch {
                what,
                expected: dim,
                found: self.length_scales.len(),
            });
        }
        let ok = self.length_scales.iter().all(|l| l.is_finite() && *l > 0.0)
            && self.signal_variance.is_finite()
            && self.signal_variance > 0.0
            && self.noise_variance.is_finite()
            && self.noise_variance >= 0.0
            && self.prior_mean.is_finite();
        if ok {
            Ok(())
        } else {
            Err(GpError::InvalidState(format!(
                "{what}: hyperparameters must be finite and positive"
            )))
        }
    }
}

/// The heteroscedastic noise model's stored state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NoiseModelState {
    /// Hyperparameters of the GP on log noise variances; its `prior_mean` is the mean log target.
    pub hyperparameters: Hyperparameters,
    /// The log-noise targets `z_i` (one per training point) the noise GP was conditioned on.
    pub log_noise_targets: Vec<f64>,
    /// Predicted noise variances are clipped to this interval (the main GP's noise bounds).
    pub noise_variance_clip: (f64, f64),
    /// Absolute jitter that the noise GP's factorisation needed (usually 0).
    pub jitter: f64,
    /// Heteroscedastic rounds kept (informational).
    pub rounds: usize,
    /// LML of the initial homoscedastic fit (informational).
    pub homoscedastic_lml: f64,
}

/// Everything needed to rebuild a fitted [`GpModel`] without re-optimising, given the same
/// training data. Serialise it with serde; [`GpModel::from_state`] reproduces the model's
/// predictions exactly (to rounding of the serialised floats).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelState {
    /// Format version of this structure (currently 1).
    pub format: u32,
    /// The noise model actually used.
    pub noise: NoiseMode,
    /// Number of training points the model was fitted on (checked on rebuild).
    pub n_train: usize,
    /// The main GP's hyperparameters.
    pub hyperparameters: Hyperparameters,
    /// Absolute jitter that the main GP's factorisation needed (usually 0).
    pub jitter: f64,
    /// The LML of the fitted model (informational; recomputed on rebuild).
    pub log_marginal_likelihood: f64,
    /// The noise GP (heteroscedastic mode only).
    pub noise_model: Option<NoiseModelState>,
}

/// A heteroscedastic model's noise, summarised.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct NoiseSummary {
    /// Smallest per-point noise variance over the training inputs.
    pub min_noise_variance: f64,
    /// Mean per-point noise variance over the training inputs.
    pub mean_noise_variance: f64,
    /// Largest per-point noise variance over the training inputs.
    pub max_noise_variance: f64,
    /// Hyperparameters of the GP on log noise variances.
    pub noise_model: Hyperparameters,
    /// Heteroscedastic rounds kept (the LML-best round).
    pub rounds: usize,
    /// LML of the initial homoscedastic fit, for comparison with the model's LML.
    pub homoscedastic_lml: f64,
}

/// How a fit's hyperparameter optimisation went.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FitStats {
    /// LML evaluations (each one Cholesky, plus an inverse for the gradient), over all starts,
    /// subset screening and heteroscedastic rounds.
    pub evaluations: usize,
    /// Whether every final optimiser run stopped on a convergence test rather than the
    /// iteration cap or a failed line search.
    pub converged: bool,
}

/// Batched predictions; entry `j` of each vector belongs to query row `j`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Prediction {
    /// Predictive mean μ.
    pub mean: Vec<f64>,
    /// Latent (epistemic) variance of the function value, ≥ 0.
    pub latent_variance: Vec<f64>,
    /// Predicted observation-noise (aleatoric) variance, ≥ 0.
    pub noise_variance: Vec<f64>,
}

impl Prediction {
    /// Predictive variance of an observation, `latent + noise`.
    pub fn variance(&self) -> Vec<f64> {
        self.latent_variance
            .iter()
            .zip(&self.noise_variance)
            .map(|(a, b)| a + b)
            .collect()
    }

    /// Predictive standard deviation of an observation, `√(latent + noise)` — the σ reported to users.
    pub fn std(&self) -> Vec<f64> {
        self.variance().into_iter().map(f64::sqrt).collect()
    }

    /// Number of predicted points.
    pub fn len(&self) -> usize {
        self.mean.len()
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.mean.is_empty()
    }
}
