//! The log marginal likelihood (LML), its analytic gradient, and the jittered factorisation
//! shared by the optimiser and by fitted models.
//!
//! With centred targets `r = y − m`, `K = s² R + diag(D) + εI` (`D` the noise variances, `ε` the
//! jitter) and `α = K⁻¹ r`:
//!
//! `LML = −½ rᵀα − ½ log|K| − n/2 log 2π`,
//! `∂LML/∂θ = ½ tr((ααᵀ − K⁻¹) ∂K/∂θ)`.
//!
//! For the log signal variance `∂K/∂θ = K − diag(D) − εI`, which gives the closed form
//! `½[(rᵀα − Σ α_i² D'_i) − (n − Σ (K⁻¹)_ii D'_i)]` with `D' = D + ε`; for a homoscedastic log
//! noise variance `∂K/∂θ = σ² I`, giving `½ σ² Σ (α_i² − (K⁻¹)_ii)`; the log length scales use
//! [`length_scale_gradient`].

use super::GpError;
use super::kernel::{Inputs, Kernel, build_train, length_scale_gradient};
use super::linalg;

/// `½ log 2π`.
const HALF_LN_2PI: f64 = 0.918_938_533_204_672_8;

/// Smallest accepted squared Cholesky pivot relative to the mean diagonal. A numerically
/// singular matrix (e.g. duplicate inputs without noise) can factorise with pivots that are pure
/// rounding noise; those are treated as failures so the jitter ladder takes over. Within the
/// default bounds (noise ≥ 1e-6, signal ≤ 1e4) genuine pivots are ≥ 1e-10 of the mean diagonal.
const MIN_PIVOT: f64 = 1e-13;

/// How the diagonal noise of the covariance is given.
#[derive(Clone, Copy, Debug)]
pub(crate) enum NoiseSpec<'a> {
    /// One variance, the last entry of the parameter vector (in log).
    Homoscedastic,
    /// Fixed per-point variances (the heteroscedastic main GP); not optimised.
    Fixed(&'a [f64]),
}

impl NoiseSpec<'_> {
    /// Length of `θ` over `d` inputs: `d` log length scales, the log signal variance and, when
    /// homoscedastic, the log noise variance.
    #[cfg(test)]
    pub fn n_params(&self, d: usize) -> usize {
        match self {
            NoiseSpec::Homoscedastic => d + 2,
            NoiseSpec::Fixed(_) => d + 1,
        }
    }
}

/// The jitter ladder: none, then `initial · mean diag`, ×10 per attempt up to `max · mean diag`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Jitter {
    /// First relative jitter.
    pub initial: f64,
    /// Largest relative jitter.
    pub max: f64,
}

/// A successful factorisation: `L` (lower triangle of `l`), the absolute jitter used, `α`, `log|K|`.
pub(crate) struct Factor {
    /// Lower Cholesky factor, column-major `n × n` (upper triangle unspecified).
    pub l: Vec<f64>,
    /// Absolute jitter that was added to the diagonal (0 when none was needed).
    pub jitter: f64,
    /// `K⁻¹ r`.
    pub alpha: Vec<f64>,
    /// `log |K|`.
    pub log_det: f64,
}

impl Factor {
    /// The LML for centred targets `r`.
    pub fn lml(&self, r: &[f64]) -> f64 {
        let fit: f64 = r.iter().zip(&self.alpha).map(|(a, b)| a * b).sum();
        -0.5 * fit - 0.5 * self.log_det - r.len() as f64 * HALF_LN_2PI
    }
}

/// Builds `K` (and `G` when asked) for scaled inputs `xs`, factorises it with the jitter ladder and
/// solves for `α`. `l` (and `g`) must have `n²` elements; they are reused as workspaces.
///
/// The first attempt adds `first_eps` (0 when fitting; the stored jitter when rebuilding a model,
/// so the rebuilt matrix is bit-identical); each failure moves up the ladder.
#[allow(clippy::too_many_arguments)]
pub(crate) fn factorise(
    kernel: Kernel,
    xs: &[f64],
    n: usize,
    d: usize,
    s2: f64,
    noise: &[f64],
    r: &[f64],
    jitter: Jitter,
    first_eps: f64,
    mut l: Vec<f64>,
    mut g: Option<&mut [f64]>,
) -> Result<Factor, (GpError, Vec<f64>)> {
    let mean_diag = s2 + noise.iter().sum::<f64>() / n as f64;
    let mut eps = first_eps;
    let mut diag: Vec<f64> = if eps == 0.0 {
        noise.to_vec()
    } else {
        noise.iter().map(|v| v + eps).collect()
    };
    loop {
        build_train(kernel, xs, n, d, s2, &diag, &mut l, g.as_deref_mut());
        if linalg::cholesky_in_place(&mut l, n)
            && (0..n).all(|i| l[i * n + i] * l[i * n + i] >= MIN_PIVOT * mean_diag)
        {
            let mut alpha = r.to_vec();
            linalg::solve_lower_in_place(&l, n, &mut alpha, 1, faer::Par::Seq);
            linalg::solve_upper_transpose_in_place(&l, n, &mut alpha, 1, faer::Par::Seq);
            let log_det = 2.0 * (0..n).map(|i| l[i * n + i].ln()).sum::<f64>();
            if alpha.iter().all(|v| v.is_finite()) && log_det.is_finite() {
                return Ok(Factor {
                    l,
                    jitter: eps,
                    alpha,
                    log_det,
                });
            }
        }
        let next = if eps == 0.0 {
            jitter.initial * mean_diag
        } else {
            eps * 10.0
        };
        if !(next > eps && next.is_finite() && next <= jitter.max * mean_diag * (1.0 + 1e-9)) {
            return Err((GpError::NotPositiveDefinite { jitter: eps }, l));
        }
        eps = next;
        for (dv, nv) in diag.iter_mut().zip(noise) {
            *dv = nv + eps;
        }
    }
}

/// `−LML` and its gradient as a function of the log-parameters
/// `θ = [log ℓ_1 … log ℓ_d, log s², (log σ²_n if homoscedastic)]`.
///
/// Owns its `n × n` workspaces (three of them) so repeated evaluations do not allocate.
pub(crate) struct Objective<'a> {
    x: &'a Inputs,
    r: &'a [f64],
    noise: NoiseSpec<'a>,
    kernel: Kernel,
    jitter: Jitter,
    a: Vec<f64>,
    g: Vec<f64>,
    linv: Vec<f64>,
    /// Number of evaluations so far.
    pub evaluations: usize,
}

impl<'a> Objective<'a> {
    /// A new objective for inputs `x`, centred targets `r`.
    pub fn new(
        x: &'a Inputs,
        r: &'a [f64],
        noise: NoiseSpec<'a>,
        kernel: Kernel,
        jitter: Jitter,
    ) -> Self {
        let nn = x.n * x.n;
        Objective {
            x,
            r,
            noise,
            kernel,
            jitter,
            a: vec![0.0; nn],
            g: vec![0.0; nn],
            linv: vec![0.0; nn],
            evaluations: 0,
        }
    }

    /// `−LML(θ)`, writing `−∇LML` into `grad`. Returns `+∞` when the covariance cannot be
    /// factorised (the line search then backs off).
    pub fn eval(&mut self, theta: &[f64], grad: &mut [f64]) -> f64 {
        self.evaluations += 1;
        let (n, d) = (self.x.n, self.x.d);
        let ls: Vec<f64> = theta[..d].iter().map(|v| v.exp()).collect();
        let s2 = theta[d].exp();
        let homo_noise;
        let noise: &[f64] = match self.noise {
            NoiseSpec::Homoscedastic => {
                homo_noise = vec![theta[d + 1].exp(); n];
                &homo_noise
            }
            NoiseSpec::Fixed(v) => v,
        };
        let xs = self.x.scaled(&ls);
        let a = std::mem::take(&mut self.a);
        let fac = match factorise(
            self.kernel,
            &xs,
            n,
            d,
            s2,
            noise,
            self.r,
            self.jitter,
            0.0,
            a,
            Some(&mut self.g),
        ) {
            Ok(f) => f,
            Err((_, a)) => {
                self.a = a;
                grad.iter_mut().for_each(|v| *v = 0.0);
                return f64::INFINITY;
            }
        };
        let lml = fac.lml(self.r);
        let Factor {
            l, jitter, alpha, ..
        } = fac;
        let mut a = l;
        // K⁻¹ = L⁻ᵀ L⁻¹, written over L (no longer needed).
        linalg::invert_lower(&a, n, &mut self.linv);
        linalg::inverse_from_inverse_factor(&self.linv, n, &mut a);
        let kinv = &a;
        let gl = length_scale_gradient(&xs, n, d, &alpha, kinv, &self.g);
        for k in 0..d {
            grad[k] = -gl[k];
        }
        let mut fit = 0.0;
        let mut a2d = 0.0;
        let mut kd = 0.0;
        let mut a2 = 0.0;
        let mut kdiag = 0.0;
        for i in 0..n {
            let dprime = noise[i] + jitter;
            let ai = alpha[i];
            let ki = kinv[i * n + i];
            fit += ai * self.r[i];
            a2d += ai * ai * dprime;
            kd += ki * dprime;
            a2 += ai * ai;
            kdiag += ki;
        }
        grad[d] = -0.5 * ((fit - a2d) - (n as f64 - kd));
        if let NoiseSpec::Homoscedastic = self.noise {
            grad[d + 1] = -0.5 * noise[0] * (a2 - kdiag);
        }
        self.a = a;
        if !lml.is_finite() || grad.iter().any(|v| !v.is_finite()) {
            return f64::INFINITY;
        }
        -lml
    }
}
