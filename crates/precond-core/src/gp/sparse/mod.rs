//! A sparse variational GP beside the exact one: SGPR / VFE (Titsias 2009) with `m` inducing
//! points, for training sets where the exact GP's O(n³) time and O(n²) memory do not fit.
//!
//! # The method
//!
//! With inducing inputs `Z` (`m` points), `K_mm = K(Z, Z) + εI` (`ε` a jitter relative to `s²`),
//! `K_mn = K(Z, X)`, `Q_nn = K_nm K_mm⁻¹ K_mn`, centred targets `r = y − m·1` (the same constant
//! prior mean as the exact GP) and noise `Λ = diag(λ_i)` (`λ_i = σ²` homoscedastic, or per-point
//! variances from a noise GP), the hyperparameters maximise the collapsed bound
//!
//! `F = log N(r | 0, Q_nn + Λ) − ½ tr(Λ⁻¹ (K_nn − Q_nn))  ≤  log p(y)`.
//!
//! It is computed as in GPflow's SGPR, generalised to a diagonal `Λ`: `L = chol(K_mm)`,
//! `A = L⁻¹ K_mn Λ^{-1/2}`, `B = I + A Aᵀ = L_B L_Bᵀ`, `c = L_B⁻¹ A Λ^{-1/2} r`,
//!
//! `F = −n/2 log 2π − Σ log (L_B)_ii − ½ Σ log λ_i − ½ rᵀΛ⁻¹r + ½ cᵀc − ½ Σ k_ii/λ_i + ½ tr(AAᵀ)`.
//!
//! The data enter only through `AAᵀ` (`m × m`), `A Λ^{-1/2} r` (`m`) and four scalars, which are
//! accumulated over chunks of points: a bound evaluation costs O(n m²) time and O(m² + m·chunk)
//! memory (no `m × n`, let alone `n × n`, matrix is ever held). The gradient with respect to the
//! log length scales, log signal variance and (homoscedastic) log noise is analytic: a second pass
//! over the chunks contracts `∂F/∂K_mn = 2 C K_mn Λ⁻¹ + β (Λ⁻¹ r)ᵀ` with the kernel derivatives,
//! where `C = L⁻ᵀ H L⁻¹`, `H = ½(I − B⁻¹ − γγᵀ)`, `γ = L_B⁻ᵀ c`, `β = L⁻ᵀ γ` (see `bound`).
//!
//! Prediction at `x*` with `k* = K(Z, x*)`: mean `m + k*ᵀ w` (`w = L⁻ᵀ L_B⁻ᵀ c`), latent variance
//! `s² − ‖L⁻¹k*‖² + ‖L_B⁻¹ L⁻¹ k*‖²` — O(m²) per point. It is computed as `s² − ‖H k*‖²` with
//! one lower-triangular `H` (`HᵀH = L⁻ᵀ (I − B⁻¹) L⁻¹`), formed once per conditioning: one
//! triangular product per batch instead of two triangular solves (see `core`).
//!
//! New data at fixed hyperparameters and inducing points update `L_B` by a rank-k Cholesky update
//! and `A Λ^{-1/2} r` by a sum ([`SparseGp::update`]): the result equals conditioning on all the
//! data at once ([`SparseGp::condition`]) to rounding.
//!
//! # Inducing points
//!
//! Chosen by greedy variance selection (a pivoted Cholesky of the kernel matrix, Burt et al.
//! 2020): each next point is the candidate whose variance conditioned on the points already chosen
//! is largest, so they spread over the data in the kernel's metric and `K_mm` stays well
//! conditioned. The candidates are a seeded random subset of the data
//! ([`SparseParams::selection_candidates`]); the first selection uses the default start's
//! hyperparameters, and each further round ([`SparseParams::inducing_rounds`]) reselects with the
//! fitted ones and refits from there (kept only if the bound improves). Inducing locations are not
//! optimised by gradient.
//!
//! Up to [`SparseParams::full_rank_up_to`] training points (default 1024) the fit is full rank
//! instead: every distinct training input is an inducing point, `Q_nn = K_nn`, the trace term
//! vanishes and the bound is the exact GP's log marginal likelihood. Its optimum is then found
//! by the exact GP's own fit (one Cholesky per evaluation rather than the chunked passes), and
//! written in sparse form ([`SparseGp::from_exact_state`]). At the MDE's sizes this matters:
//! its deviations are nearly noise-free, so a low-rank `Q_nn` is paid for by a larger fitted
//! noise (VFE's known overestimation), a larger σ everywhere and a precondition that trusts
//! less (see [`DEFAULT_FULL_RANK_UP_TO`]).
//!
//! # Heteroscedastic noise
//!
//! The procedure of [`hetero`](super::hetero) with sparse GPs throughout: the noise GP is a sparse
//! homoscedastic GP (Matérn 5/2, its own bounds) on `z_i = log e_i + b(ρ_i)` with inducing points
//! the first [`SparseParams::noise_inducing_points`] of the main GP's (greedy order, so they are
//! themselves a greedy selection). Under the bound's model `y ~ N(m, Q_nn + Λ)` the residual at a
//! training point is `y_i − μ_i = λ_i ((Q+Λ)⁻¹ r)_i`, with variance `λ_i ρ_i`, `ρ_i = 1 − k_iᵀΣ⁻¹k_i / λ_i`
//! (`Σ = K_mm + K_mn Λ⁻¹ K_nm`), so the expected squared residual is `e_i = (y_i − μ_i)² + k_iᵀΣ⁻¹k_i`
//! (with `Z = X` these are exactly the exact GP's quantities).
//!
//! # Cost
//!
//! [`super::cost`] estimates the peak memory and work of a fit before it allocates anything.

mod bound;
mod core;
mod inducing;
mod model;
#[cfg(test)]
mod tests;

use serde::{Deserialize, Serialize};

pub use model::SparseGp;

use super::params::off_or_at_least;
use super::{GpError, GpParams, Hyperparameters, NoiseMode};

/// Default number of inducing points: 256. Measured on the benchmark's data (n = 100 000, d = 6,
/// homoscedastic, release build, 2 cores): m = 256 fits in 25 s, predicts 260 000 points/s and
/// one point in 0.014 ms; m = 512 fits in 81 s, predicts 90 000 points/s and one point in
/// 0.08 ms, for a held-out NLL better by 0.5 % (−0.410 vs −0.408).
pub const DEFAULT_INDUCING_POINTS: usize = 256;

/// Default [`SparseParams::full_rank_up_to`]: 1024 training points. The deviations the MDE
/// learns are nearly noise-free (fitted noise variances 1e-6–1e-4 against signal variances
/// around 5e-4 on the continuous worlds), so VFE's trace penalty `tr(K_nn − Q_nn) / 2σ²` stays
/// large until `m` is close to `n`, and the optimiser pays it by overestimating the noise: on
/// the base and pusher worlds' 400–600 training transitions, m = 256 gave bounds 100–170 nats
/// below the exact log marginal likelihood and noise variances 1.5–3× the exact GP's, and
/// only m ≈ n closed the gap (`precond bench mde`, docs/measurements/performance.md). Up to
/// 1024 points the exact fit takes seconds and its sparse form `O(n³)` work and `n²/2` stored
/// numbers, about what the default fit costs at n = 100 000.
pub const DEFAULT_FULL_RANK_UP_TO: usize = 1024;

/// Settings for fitting a [`SparseGp`]. Build one (or start from [`Default`]), then call
/// [`SparseParams::check`]; only the resulting [`ValidSparseParams`] can fit a model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SparseParams {
    /// The settings shared with the exact GP: noise mode, kernel, prior mean, restarts, seed,
    /// bounds, optimiser tolerances, the jitter ceiling (`jitter_max`, relative to `s²` here) and
    /// the heteroscedastic rounds. `gp.screen_subset` and `gp.jitter_initial` are not used (see
    /// [`screen_subset`](Self::screen_subset) and [`jitter`](Self::jitter)).
    pub gp: GpParams,
    /// Number of inducing points `m` (capped by the number of distinct training inputs).
    /// Default [`DEFAULT_INDUCING_POINTS`]; range `1..=4096`.
    pub inducing_points: usize,
    /// Inducing points of the heteroscedastic noise GP: the first this many of the main GP's.
    /// Default 128; range `1..=4096`.
    pub noise_inducing_points: usize,
    /// Rounds of inducing-point selection: the first at the default start's hyperparameters, each
    /// further one at the fitted hyperparameters followed by a warm-started refit. Default 2;
    /// range `1..=5`.
    pub inducing_rounds: usize,
    /// Greedy selection considers a seeded random subset of this many training points (all of
    /// them when there are fewer). Its cost is O(candidates · m²). Default 8192; at least 1 (and
    /// raised to `4 m`).
    pub selection_candidates: usize,
    /// When `n` exceeds this (and `gp.restarts > 0`), the random restarts are optimised on a
    /// seeded subset of this many points and only the best is refined on all data, as in the
    /// exact GP (whose own `gp.screen_subset` is smaller). `0` disables screening. Default 4096;
    /// must be `0` or at least 64.
    pub screen_subset: usize,
    /// When `n` exceeds twice this, the whole procedure (selection rounds, restarts,
    /// heteroscedastic rounds) runs on a seeded subset of this many points, and is then refined
    /// once on all the data with the subset's inducing points: the homoscedastic optimum
    /// warm-started from the subset's (its L-BFGS pairs rescaled by `n / subset`), and in
    /// heteroscedastic mode one round whose noise and main GPs start from the subset's optima.
    /// Full-data evaluations, the expensive ones, are then few (about 30 at n = 100 000 instead of
    /// about 75). `0` disables it. Default 16384; must be `0` or at least 256.
    pub presolve_subset: usize,
    /// Jitter added to `K_mm`'s diagonal, relative to the signal variance (the first rung of a
    /// ladder that grows ×10 up to `gp.jitter_max`). Default `1e-6`; range `(0, 1e-2]`.
    pub jitter: f64,
    /// With at most this many training points the fit is full rank: every distinct training
    /// input is an inducing point of the main GP and of the noise GP, whatever
    /// [`inducing_points`](Self::inducing_points) says. The collapsed bound is then the exact
    /// log marginal likelihood, so its optimum is the exact GP's: the exact GP is fitted (with
    /// `gp`, the same procedure and seeds) and written in sparse form
    /// ([`SparseGp::from_exact_state`]), which predicts as it does. Costs `O(n³)` time and
    /// `n²/2` stored numbers. Default [`DEFAULT_FULL_RANK_UP_TO`]; range `0..=4096`, `0` turns
    /// it off.
    pub full_rank_up_to: usize,
}

impl Default for SparseParams {
    fn default() -> Self {
        SparseParams {
            gp: GpParams::default(),
            inducing_points: DEFAULT_INDUCING_POINTS,
            noise_inducing_points: 128,
            inducing_rounds: 2,
            selection_candidates: 8192,
            screen_subset: 4096,
            presolve_subset: 16384,
            jitter: 1e-6,
            full_rank_up_to: DEFAULT_FULL_RANK_UP_TO,
        }
    }
}

/// [`SparseParams`] that passed [`SparseParams::check`]; the only way to fit a [`SparseGp`].
pub type ValidSparseParams = super::params::Checked<SparseParams>;

fn invalid(name: &'static str, reason: String) -> GpError {
    GpError::InvalidParameter { name, reason }
}

impl SparseParams {
    /// Validates every field against its documented range (including `gp`'s, via
    /// [`GpParams::check`]).
    pub fn check(&self) -> Result<ValidSparseParams, GpError> {
        self.gp.check()?;
        if !(1..=4096).contains(&self.inducing_points) {
            return Err(invalid(
                "inducing_points",
                format!("must be in 1..=4096, got {}", self.inducing_points),
            ));
        }
        if !(1..=4096).contains(&self.noise_inducing_points) {
            return Err(invalid(
                "noise_inducing_points",
                format!("must be in 1..=4096, got {}", self.noise_inducing_points),
            ));
        }
        if !(1..=5).contains(&self.inducing_rounds) {
            return Err(invalid(
                "inducing_rounds",
                format!("must be in 1..=5, got {}", self.inducing_rounds),
            ));
        }
        if self.selection_candidates == 0 {
            return Err(invalid(
                "selection_candidates",
                "must be at least 1".to_string(),
            ));
        }
        off_or_at_least("screen_subset", self.screen_subset, 64)?;
        off_or_at_least("presolve_subset", self.presolve_subset, 256)?;
        if self.full_rank_up_to > 4096 {
            return Err(invalid(
                "full_rank_up_to",
                format!("must be in 0..=4096, got {}", self.full_rank_up_to),
            ));
        }
        if !(self.jitter > 0.0 && self.jitter <= 1e-2) {
            return Err(invalid(
                "jitter",
                format!("must be in (0, 1e-2], got {}", self.jitter),
            ));
        }
        Ok(ValidSparseParams::new(self.clone()))
    }
}

/// One conditioned sparse GP, stored: everything needed to predict and to take online updates,
/// without the training data.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SparseCoreState {
    /// Hyperparameters. `noise_variance` is the homoscedastic `σ²`, or for per-point noise the
    /// mean of the training points' `λ_i` (informational).
    pub hyperparameters: Hyperparameters,
    /// Inducing inputs `Z`, row-major `m × d` (point `i` is `inducing_points[i*d .. (i+1)*d]`),
    /// in the unit-box input space.
    pub inducing_points: Vec<f64>,
    /// Absolute jitter added to `K_mm`'s diagonal (reused exactly on rebuild).
    pub jitter: f64,
    /// The lower Cholesky factor `L_B` of `B = I + AAᵀ`, packed by rows: row `i` holds columns
    /// `0..=i` (`m(m+1)/2` numbers).
    pub factor_b: Vec<f64>,
    /// `A Λ^{-1/2} r` (`m` numbers).
    pub projected_targets: Vec<f64>,
    /// Training points absorbed so far.
    pub n_train: usize,
    /// `Σ log λ_i` over the training points.
    pub sum_log_noise: f64,
    /// `Σ r_i² / λ_i`.
    pub sum_sq_residual_over_noise: f64,
    /// `Σ 1 / λ_i`.
    pub sum_inv_noise: f64,
    /// `tr(AAᵀ) = Σ_i q_ii / λ_i` (the Nyström part of the trace term).
    pub trace_aat: f64,
}

/// The sparse heteroscedastic noise model, stored.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SparseNoiseState {
    /// The sparse GP on log noise variances (its `prior_mean` is the mean log target).
    pub core: SparseCoreState,
    /// Predicted noise variances are clipped to this interval.
    pub noise_variance_clip: (f64, f64),
    /// Heteroscedastic rounds kept (informational).
    pub rounds: usize,
    /// Bound of the initial homoscedastic fit (informational).
    pub homoscedastic_bound: f64,
    /// Min, mean and max of the training points' noise variances at fit time (informational).
    pub train_noise_variance: (f64, f64, f64),
}

/// Everything needed to rebuild a [`SparseGp`] exactly ([`SparseGp::from_state`]), without the
/// training data: hyperparameters, inducing points, the factor and the sufficient statistics.
/// About `m²/2 + m·d` numbers (≈ 33 000 at m = 256).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SparseState {
    /// Format version of this structure (currently 1).
    pub format: u32,
    /// The noise model actually used.
    pub noise: NoiseMode,
    /// The main GP.
    pub main: SparseCoreState,
    /// The noise GP (heteroscedastic mode only).
    pub noise_model: Option<SparseNoiseState>,
}
