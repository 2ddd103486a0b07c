//! The most likely heteroscedastic GP (Kersting, Plagemann, Pfaff & Burgard, ICML 2007).
//!
//! 1. Fit a homoscedastic GP `G₁` (done by the caller).
//! 2. For each training point estimate the noise as the expected squared residual under the
//!    current model, `e_i = (y_i − μ_i)² + v_i` (`μ_i`, `v_i` the latent posterior mean and variance
//!    at `x_i`; both come from `α` and `diag(K⁻¹)`: `y_i − μ_i = D'_i α_i`, `v_i = D'_i − D'_i² (K⁻¹)_ii`).
//! 3. Fit a homoscedastic GP `G₂` (own bounds, constant prior mean = mean target) to
//!    `z_i = log e_i + b(ρ_i)`, which undoes the bias of log-residuals. For a bare Gaussian
//!    residual `E[log r²] = log σ² + ψ(½) + log 2 = log σ² − 1.2704`, hence DESIGN.md's `+1.27`.
//!    Here `e_i` is a Gaussian residual *plus* the deterministic latent variance: under the model
//!    `e_i = D'_i (1 − ρ_i + ρ_i u²)`, `u ~ N(0,1)`, `ρ_i = D'_i (K⁻¹)_ii ∈ [0, 1]` (the share of the
//!    noise that shows up in the residual), so the exact correction is
//!    `b(ρ) = −E[log(1 − ρ + ρu²)]` ([`log_residual_bias`]): `b(1) = 1.2704` (the DESIGN constant),
//!    `b(0.95) = 0.795`, `b(0.5) = 0.160`, `b(0) = 0`. With typical `ρ ≈ 0.95` the flat `+1.27`
//!    over-corrects by `e^0.48 ≈ 1.6×` in variance (measured: 0.032/0.39 recovered for true
//!    0.02/0.3 with `+1.27`, within 10 % with `b(ρ)`).
//! 4. Refit the main GP's length scales and signal variance (warm-started) with the per-point noise
//!    `D_i = exp(μ₂(x_i))`, clipped to the main GP's noise bounds.
//! 5. Repeat 2–4 from the new model while its LML improves by more than `hetero_tolerance`
//!    (relative), at most `hetero_rounds` times; keep the LML-best round.
//!
//! At a query point the noise variance is `exp(μ₂(x*))`, clipped the same way.

use super::core::{Core, Prior, mean};
use super::fit::{self, Starts, Warm, optimise};
use super::kernel::{Inputs, Kernel};
use super::lbfgs;
use super::lml::{Jitter, NoiseSpec};
use super::{GpError, GpParams, Hyperparameters, NoiseModelState};

/// `−(ψ(½) + log 2) ≈ 1.2704`: the bias of `log r²` for a Gaussian residual `r`
/// (= [`log_residual_bias`]`(1.0)`).
pub const LOG_RESIDUAL_BIAS: f64 = 1.270_362_845_461_478;

/// Quadrature nodes for [`log_residual_bias`]: `u = e^s`, `s ∈ [−36, 3.6]` step 0.1, weights
/// `2φ(u) u h` (trapezoid in `s`; the integrand decays exponentially at both ends, so the rule is
/// accurate to ~1e-13).
fn bias_nodes() -> &'static [(f64, f64)] {
    static NODES: std::sync::OnceLock<Vec<(f64, f64)>> = std::sync::OnceLock::new();
    NODES.get_or_init(|| {
        let h = 0.1;
        let norm = 2.0 / (2.0 * std::f64::consts::PI).sqrt();
        (0..=396)
            .map(|k| {
                let u = (-36.0 + h * k as f64).exp();
                (u * u, norm * (-0.5 * u * u).exp() * u * h)
            })
            .collect()
    })
}

/// `b(ρ) = −E[log(1 − ρ + ρu²)]` for `u ~ N(0, 1)` and `ρ ∈ [0, 1]` (clamped): the amount to add
/// to `log e` when `e = σ²(1 − ρ + ρu²)` to get an unbiased estimate of `log σ²`.
/// `b(1) =` [`LOG_RESIDUAL_BIAS`], `b(0) = 0`, increasing in between.
pub fn log_residual_bias(rho: f64) -> f64 {
    let rho = if rho.is_nan() {
        1.0
    } else {
        rho.clamp(0.0, 1.0)
    };
    -bias_nodes()
        .iter()
        .map(|&(u2, w)| w * (1.0 - rho + rho * u2).ln())
        .sum::<f64>()
}

/// Relative function tolerance floor for the noise GP's optimiser: its targets are log
/// residuals with a variance of several units, so optimising their LML to 1e-9 buys nothing.
pub(crate) const NOISE_MODEL_FTOL: f64 = 1e-6;

/// The noise GP's starts in hetero round `seed`'s fit: from the previous round's optimum
/// `theta` (with its L-BFGS `memory`) when there is one, else the default start and
/// `restarts` random ones, all screened, to [`NOISE_MODEL_FTOL`]. Shared by the exact and the
/// sparse GP.
pub(crate) fn noise_gp_starts<'a>(
    theta: Option<&'a [f64]>,
    memory: &lbfgs::Memory,
    restarts: usize,
    seed: u64,
) -> Starts<'a> {
    Starts::warm_or_new(
        theta.map(|theta| Warm {
            theta,
            memory: memory.clone(),
        }),
        restarts,
        seed,
    )
    .ftol_floor(NOISE_MODEL_FTOL)
    .default_screened()
}

/// The noise GP's kernel, whatever the main GP's: the log noise level is a smooth summary of
/// where the residuals are large, not a function that jumps.
pub(crate) const NOISE_MODEL_KERNEL: Kernel = Kernel::Matern52;

/// The fitted noise GP.
#[derive(Clone, Debug)]
pub(crate) struct NoiseModel {
    pub core: Core,
    pub hyper: Hyperparameters,
    pub targets: Vec<f64>,
    pub clip: (f64, f64),
}

impl NoiseModel {
    /// Per-point noise variances at the training inputs: `exp(μ₂(x_i))`, clipped.
    pub fn train_noise(&self) -> Vec<f64> {
        self.core
            .train_mean(&self.targets)
            .iter()
            .map(|z| z.exp().clamp(self.clip.0, self.clip.1))
            .collect()
    }

    /// Noise variances at query inputs.
    pub fn predict_noise(&self, q: &Inputs) -> Vec<f64> {
        self.core
            .predict(q, false)
            .0
            .iter()
            .map(|z| z.exp().clamp(self.clip.0, self.clip.1))
            .collect()
    }

    pub fn state(&self, rounds: usize, homoscedastic_lml: f64) -> NoiseModelState {
        NoiseModelState {
            hyperparameters: self.hyper.clone(),
            log_noise_targets: self.targets.clone(),
            noise_variance_clip: self.clip,
            jitter: self.core.jitter,
            rounds,
            homoscedastic_lml,
        }
    }

    pub fn from_state(x: &Inputs, s: &NoiseModelState) -> Result<NoiseModel, GpError> {
        s.hyperparameters
            .check(x.d, "noise model hyperparameters")?;
        if s.log_noise_targets.len() != x.n {
            return Err(GpError::DimensionMismatch {
                what: "noise model targets vs rows of x",
                expected: x.n,
                found: s.log_noise_targets.len(),
            });
        }
        if let Some(i) = s.log_noise_targets.iter().position(|v| !v.is_finite()) {
            return Err(GpError::NonFinite {
                what: "noise model targets",
                index: i,
            });
        }
        let (lo, hi) = s.noise_variance_clip;
        if !(lo.is_finite()
            && hi.is_finite()
            && lo > 0.0
            && lo <= hi
            && s.jitter.is_finite()
            && s.jitter >= 0.0)
        {
            return Err(GpError::InvalidState(
                "noise model clip or jitter out of range".into(),
            ));
        }
        let h = &s.hyperparameters;
        let core = Core::build(
            &Prior::of(h),
            x,
            &s.log_noise_targets,
            vec![h.noise_variance; x.n],
            Jitter {
                initial: 0.0,
                max: 0.0,
            },
            s.jitter,
        )?;
        let mut core = core;
        core.drop_inverse_factor();
        Ok(NoiseModel {
            core,
            hyper: h.clone(),
            targets: s.log_noise_targets.clone(),
            clip: s.noise_variance_clip,
        })
    }
}

/// The outcome of [`fit()`].
pub(crate) struct Fitted {
    pub main: Core,
    pub noise_model: NoiseModel,
    pub rounds: usize,
    /// Objective evaluations over all rounds (noise GP and main GP).
    pub evaluations: usize,
    /// Whether every optimiser run of the kept rounds converged.
    pub converged: bool,
}

/// Log-noise targets `z_i = log((y_i − μ_i)² + v_i) + b(ρ_i)` from a conditioned model.
fn log_noise_targets(core: &Core) -> Vec<f64> {
    let kd = core.kinv_diag();
    (0..core.n)
        .map(|i| {
            let dp = core.noise[i] + core.jitter;
            let res = dp * core.alpha[i];
            let rho = (dp * kd[i]).clamp(0.0, 1.0);
            let v = dp * (1.0 - rho);
            (res * res + v).max(1e-300).ln() + log_residual_bias(rho)
        })
        .collect()
}

/// The range the noise variances of a heteroscedastic GP with labels `y` are clipped to: the
/// noise variance `bounds`, the upper one lowered to the labels' variance.
///
/// A point's noise variance cannot exceed the labels' total variance: otherwise the noise GP
/// can absorb structure (a large-label cluster explained as noise around a flat mean), and the
/// main GP, refitted under that fixed noise, has no reason to model it (a self-reinforcing
/// fixed point of the alternation; seen on the water plant, where it left some fits with the
/// signal variance at its floor and nothing trusted).
pub(crate) fn noise_clip(y: &[f64], (lo, hi): (f64, f64)) -> (f64, f64) {
    let my = mean(y);
    let var_y = y.iter().map(|v| (v - my) * (v - my)).sum::<f64>() / y.len().max(1) as f64;
    (lo, hi.min(var_y).max(lo))
}

/// The seed of the noise GP's fit in heteroscedastic round `round` of a fit seeded `seed`.
pub(crate) fn round_seed(seed: u64, round: usize) -> u64 {
    seed.wrapping_add(0x9E37_79B9_7F4A_7C15u64.wrapping_mul(round as u64 + 1))
}

/// Runs steps 2–5 starting from the homoscedastic model `homo` whose `[log ℓ, log s²]` are `theta_main`.
pub(crate) fn fit(
    x: &Inputs,
    y: &[f64],
    p: &GpParams,
    homo: Core,
    theta_main: &[f64],
) -> Result<Fitted, GpError> {
    let d = x.d;
    let r: Vec<f64> = y.iter().map(|v| v - p.prior_mean).collect();
    let jitter = fit::jitter(p);
    let clip = noise_clip(y, p.bounds.noise_variance);
    let mut best: Option<Fitted> = None;
    let mut current_theta = theta_main.to_vec();
    let mut main_memory = Vec::new();
    // A warm refit starts the noise GP where the previous fit's ended.
    let mut noise_theta: Option<Vec<f64>> = p
        .warm
        .as_ref()
        .and_then(|w| w.noise.as_deref())
        .and_then(|t| super::WarmStart::within(t, d, &p.noise_model_bounds));
    let mut noise_memory = Vec::new();
    let mut evaluations = 0;
    let mut converged = true;
    for round in 0..p.hetero_rounds {
        let z = log_noise_targets(best.as_ref().map_or(&homo, |b| &b.main));
        let mz = mean(&z);
        let rz: Vec<f64> = z.iter().map(|v| v - mz).collect();
        let seed = round_seed(p.seed, round);
        let g = optimise(
            x,
            &rz,
            NoiseSpec::Homoscedastic,
            &p.noise_model_bounds,
            NOISE_MODEL_KERNEL,
            p,
            noise_gp_starts(noise_theta.as_deref(), &noise_memory, p.restarts, seed),
        )?;
        let prior = Prior::from_log(NOISE_MODEL_KERNEL, mz, &g.theta[..=d]);
        let gn = g.theta[d + 1].exp();
        let core = Core::build(&prior, x, &z, vec![gn; x.n], jitter, 0.0)?;
        let hyper = prior.with_noise(gn);
        let nm = NoiseModel {
            core,
            hyper,
            targets: z,
            clip,
        };
        let noise = nm.train_noise();
        let mut nm = nm;
        nm.core.drop_inverse_factor();
        let f = optimise(
            x,
            &r,
            NoiseSpec::Fixed(&noise),
            &p.bounds,
            p.kernel,
            p,
            Starts::warm(
                Warm {
                    theta: &current_theta,
                    memory: main_memory.clone(),
                },
                p.seed,
            ),
        )?;
        let prior = Prior::from_log(p.kernel, p.prior_mean, &f.theta[..=d]);
        let main = Core::build(&prior, x, y, noise, jitter, 0.0)?;
        evaluations += g.evaluations + f.evaluations;
        let improved = match &best {
            None => true,
            Some(b) => main.lml > b.main.lml + p.hetero_tolerance * b.main.lml.abs(),
        };
        if !improved {
            break;
        }
        noise_theta = Some(g.theta);
        noise_memory = g.memory;
        current_theta = f.theta;
        main_memory = f.memory;
        converged &= g.converged && f.converged;
        best = Some(Fitted {
            main,
            noise_model: nm,
            rounds: round + 1,
            evaluations: 0,
            converged,
        });
    }
    let mut best = best
        .ok_or_else(|| GpError::OptimisationFailed("no heteroscedastic round succeeded".into()))?;
    best.evaluations = evaluations;
    Ok(best)
}
