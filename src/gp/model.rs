//! [`GpModel`]: a fitted GP with its factorisation cached, and batched prediction.

use faer::Par;
use nalgebra::{DMatrix, DVector};

use super::fit::{self, Optimum};
use super::hetero::{self, NoiseModel};
use super::kernel::{self, Inputs};
use super::linalg;
use super::lml::{self, Jitter, NoiseSpec};
use super::{
    FitStats, GpError, Hyperparameters, ModelState, NoiseMode, NoiseSummary, Prediction,
    ValidGpParams,
};

/// One conditioned GP: scaled training inputs, `L⁻¹` and `α = K⁻¹(y − m)`.
#[derive(Clone, Debug)]
pub(crate) struct Core {
    pub n: usize,
    pub d: usize,
    /// Training inputs divided by the length scales, column-major `n × d`.
    pub xs: Vec<f64>,
    pub length_scales: Vec<f64>,
    pub s2: f64,
    pub mean: f64,
    /// Per-point noise variances on the diagonal (without jitter).
    pub noise: Vec<f64>,
    /// Absolute jitter added to the diagonal.
    pub jitter: f64,
    /// `L⁻¹` stored row-major (`n × n`; row `i` is `linv[i*n ..= i*n + i]`), so a single point's
    /// `‖L⁻¹k‖²` is `n` contiguous dot products and batches use it as a transposed GEMM operand.
    pub linv: Vec<f64>,
    pub alpha: Vec<f64>,
    pub lml: f64,
}

impl Core {
    /// Factorises the covariance for the given hyperparameters. `jitter` is the ladder; `first_eps`
    /// the first absolute jitter tried (0 for a new fit, the stored value for a rebuild).
    #[allow(clippy::too_many_arguments)]
    pub fn build(
        x: &Inputs,
        y: &[f64],
        mean: f64,
        length_scales: &[f64],
        s2: f64,
        noise: Vec<f64>,
        jitter: Jitter,
        first_eps: f64,
    ) -> Result<Core, GpError> {
        let (n, d) = (x.n, x.d);
        let r: Vec<f64> = y.iter().map(|v| v - mean).collect();
        let xs = x.scaled(length_scales);
        let fac = lml::factorise(
            &xs,
            n,
            d,
            s2,
            &noise,
            &r,
            jitter,
            first_eps,
            vec![0.0; n * n],
            None,
        )
        .map_err(|(e, _)| e)?;
        let lml = fac.lml(&r);
        let mut linv = fac.l.clone();
        linalg::invert_lower_row_major(&fac.l, n, &mut linv);
        Ok(Core {
            n,
            d,
            xs,
            length_scales: length_scales.to_vec(),
            s2,
            mean,
            noise,
            jitter: fac.jitter,
            linv,
            alpha: fac.alpha,
            lml,
        })
    }

    /// Frees `L⁻¹` (n² floats) when only means will be asked for (the noise GP); variances
    /// are then reported as NaN.
    pub fn drop_inverse_factor(&mut self) {
        self.linv = Vec::new();
    }

    /// `(K⁻¹)_ii = Σ_{k≥i} (L⁻¹)_ki²` (a sweep over the rows of `L⁻¹`).
    pub fn kinv_diag(&self) -> Vec<f64> {
        let n = self.n;
        let mut out = vec![0.0; n];
        for k in 0..n {
            for (o, v) in out.iter_mut().zip(&self.linv[k * n..k * n + k + 1]) {
                *o += v * v;
            }
        }
        out
    }

    /// Posterior mean of the latent function at the training inputs: `y_i − D'_i α_i`.
    pub fn train_mean(&self, y: &[f64]) -> Vec<f64> {
        y.iter()
            .zip(&self.noise)
            .zip(&self.alpha)
            .map(|((yi, di), ai)| yi - (di + self.jitter) * ai)
            .collect()
    }

    /// Mean and (optionally) latent variance at query points `q`.
    pub fn predict(&self, q: &Inputs, want_var: bool) -> (Vec<f64>, Vec<f64>) {
        let (n, m, d) = (self.n, q.n, self.d);
        let without_factor = want_var && self.linv.len() != n * n;
        let want_var = want_var && !without_factor;
        let qs = q.scaled(&self.length_scales);
        let mut mean = Vec::with_capacity(m);
        let mut var = Vec::with_capacity(if want_var { m } else { 0 });
        // Chunks of about 16 MB of cross covariances keep memory bounded and GEMMs efficient.
        let chunk = ((1usize << 21) / n.max(1)).clamp(16, 4096);
        let mut ks = Vec::new();
        let mut v = Vec::new();
        let mut j0 = 0;
        while j0 < m {
            let mc = chunk.min(m - j0);
            let mut qc = Vec::with_capacity(mc * d);
            for k in 0..d {
                qc.extend_from_slice(&qs[k * m + j0..k * m + j0 + mc]);
            }
            ks.resize(n * mc, 0.0);
            kernel::build_cross(&self.xs, n, &qc, mc, d, self.s2, &mut ks);
            for col in ks.chunks_exact(n) {
                mean.push(self.mean + col.iter().zip(&self.alpha).map(|(a, b)| a * b).sum::<f64>());
            }
            if want_var {
                if mc == 1 {
                    var.push((self.s2 - self.quad_single(&ks)).max(0.0));
                } else {
                    v.resize(n * mc, 0.0);
                    let par = if n * n * mc >= 50_000_000 {
                        Par::rayon(0)
                    } else {
                        Par::Seq
                    };
                    linalg::lower_matmul(&self.linv, n, &ks, mc, &mut v, par);
                    for col in v.chunks_exact(n) {
                        var.push((self.s2 - col.iter().map(|t| t * t).sum::<f64>()).max(0.0));
                    }
                }
            }
            j0 += mc;
        }
        if without_factor {
            var = vec![f64::NAN; m];
        }
        (mean, var)
    }

    /// `‖L⁻¹ k‖²` for one point: one dot product per row of `L⁻¹` (memory-bound: reads the
    /// triangle once, contiguously). Large models split the rows between two threads.
    fn quad_single(&self, k: &[f64]) -> f64 {
        let n = self.n;
        let rows = |r0: usize, r1: usize| -> f64 {
            (r0..r1)
                .map(|i| {
                    let t = dot(&self.linv[i * n..i * n + i + 1], &k[..i + 1]);
                    t * t
                })
                .sum()
        };
        if n < 1500 || kernel::threads_for(usize::MAX) < 2 {
            return rows(0, n);
        }
        // Rows [split, n) hold as many entries as rows [0, split). A scoped thread (≈30 µs to
        // spawn) measured faster here than faer's pool (`join_raw`) for this memory-bound sweep.
        let split = ((n as f64) * std::f64::consts::FRAC_1_SQRT_2) as usize;
        std::thread::scope(|s| {
            let h = s.spawn(|| rows(split, n));
            let a = rows(0, split);
            // The closure cannot panic; fall back to computing the half here if it somehow did.
            a + h.join().unwrap_or_else(|_| rows(split, n))
        })
    }
}

/// Dot product with eight independent accumulators (vectorises; fixed summation order).
#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for t in 0..8 {
            acc[t] += x[t] * y[t];
        }
    }
    acc.iter().sum::<f64>() + tail
}

/// A fitted GP model deviation estimator.
///
/// Holds the training inputs, the inverse Cholesky factor `L⁻¹` and `α = K⁻¹(y − m)` of the main
/// GP (and of the noise GP in heteroscedastic mode), so predictions need no refactorisation.
/// `Send + Sync`: share it behind an `Arc` and swap in a new one after a refit.
#[derive(Clone, Debug)]
pub struct GpModel {
    x: Inputs,
    mode: NoiseMode,
    main: Core,
    noise_model: Option<NoiseModel>,
    hyper: Hyperparameters,
    homo_lml: f64,
    rounds: usize,
    stats: Option<FitStats>,
}

/// Checks the training data and converts it.
fn check_data(x: &DMatrix<f64>, y: &DVector<f64>) -> Result<Inputs, GpError> {
    if x.nrows() == 0 {
        return Err(GpError::EmptyData("no training points"));
    }
    if x.ncols() == 0 {
        return Err(GpError::EmptyData("inputs have no columns"));
    }
    if y.len() != x.nrows() {
        return Err(GpError::DimensionMismatch {
            what: "length of y vs rows of x",
            expected: x.nrows(),
            found: y.len(),
        });
    }
    check_finite_matrix(x, "x")?;
    if let Some(i) = y.iter().position(|v| !v.is_finite()) {
        return Err(GpError::NonFinite {
            what: "y",
            index: i,
        });
    }
    Ok(Inputs::from_matrix(x))
}

fn check_finite_matrix(x: &DMatrix<f64>, what: &'static str) -> Result<(), GpError> {
    for i in 0..x.nrows() {
        for j in 0..x.ncols() {
            if !x[(i, j)].is_finite() {
                return Err(GpError::NonFinite {
                    what,
                    index: i * x.ncols() + j,
                });
            }
        }
    }
    Ok(())
}

impl GpModel {
    /// Fits a GP to training inputs `x` (rows are points, already scaled to the unit box) and
    /// targets `y`, maximising the LML over the hyperparameters (see [`GpParams`](super::GpParams)).
    ///
    /// Heteroscedastic mode falls back to homoscedastic when `n < params.hetero_min_points`
    /// ([`noise_mode`](Self::noise_mode) reports what was used). Same data and seed, same model.
    ///
    /// # Errors
    /// [`GpError::EmptyData`], [`GpError::DimensionMismatch`], [`GpError::NonFinite`] for bad data;
    /// [`GpError::NotPositiveDefinite`] / [`GpError::OptimisationFailed`] when the covariance cannot
    /// be factorised even with the maximum jitter.
    pub fn fit(
        x: &DMatrix<f64>,
        y: &DVector<f64>,
        params: &ValidGpParams,
    ) -> Result<GpModel, GpError> {
        let x = check_data(x, y)?;
        let p = params.params();
        let y = y.as_slice();
        let d = x.d;
        let r: Vec<f64> = y.iter().map(|v| v - p.prior_mean).collect();
        let jitter = fit::jitter(p);
        let Optimum {
            theta,
            evaluations,
            converged,
            ..
        } = fit::optimise(
            &x,
            &r,
            NoiseSpec::Homoscedastic,
            &p.bounds,
            p,
            p.restarts,
            None,
            p.seed,
            0.0,
            true,
        )?;
        let ls: Vec<f64> = theta[..d].iter().map(|v| v.exp()).collect();
        let s2 = theta[d].exp();
        let noise = theta[d + 1].exp();
        let homo = Core::build(&x, y, p.prior_mean, &ls, s2, vec![noise; x.n], jitter, 0.0)?;
        let homo_lml = homo.lml;
        let hetero = p.noise == NoiseMode::Heteroscedastic && x.n >= p.hetero_min_points;
        if !hetero {
            let hyper = Hyperparameters {
                length_scales: ls,
                signal_variance: s2,
                noise_variance: noise,
                prior_mean: p.prior_mean,
            };
            let stats = Some(FitStats {
                evaluations,
                converged,
            });
            return Ok(GpModel {
                x,
                mode: NoiseMode::Homoscedastic,
                main: homo,
                noise_model: None,
                hyper,
                homo_lml,
                rounds: 0,
                stats,
            });
        }
        let fitted = hetero::fit(&x, y, p, homo, &theta[..d + 1])?;
        let hyper = Hyperparameters {
            length_scales: fitted.main.length_scales.clone(),
            signal_variance: fitted.main.s2,
            noise_variance: mean(&fitted.main.noise),
            prior_mean: p.prior_mean,
        };
        Ok(GpModel {
            x,
            mode: NoiseMode::Heteroscedastic,
            main: fitted.main,
            noise_model: Some(fitted.noise_model),
            hyper,
            homo_lml,
            rounds: fitted.rounds,
            stats: Some(FitStats {
                evaluations: evaluations + fitted.evaluations,
                converged: converged && fitted.converged,
            }),
        })
    }

    /// Rebuilds a fitted model from its [`ModelState`] and the same training data, without
    /// re-optimising. Predictions equal the original model's (to rounding of stored floats).
    ///
    /// # Errors
    /// Data errors as for [`fit`](Self::fit); [`GpError::InvalidState`] / [`GpError::DimensionMismatch`]
    /// when the state does not match the data or is malformed; [`GpError::NotPositiveDefinite`]
    /// if the stored configuration no longer factorises.
    pub fn from_state(
        x: &DMatrix<f64>,
        y: &DVector<f64>,
        state: &ModelState,
    ) -> Result<GpModel, GpError> {
        let x = check_data(x, y)?;
        let y = y.as_slice();
        if state.format != 1 {
            return Err(GpError::InvalidState(format!(
                "unsupported format {}",
                state.format
            )));
        }
        if state.n_train != x.n {
            return Err(GpError::DimensionMismatch {
                what: "state n_train vs rows of x",
                expected: state.n_train,
                found: x.n,
            });
        }
        let h = &state.hyperparameters;
        h.check(x.d, "hyperparameters")?;
        if !(state.jitter.is_finite() && state.jitter >= 0.0) {
            return Err(GpError::InvalidState(
                "jitter must be finite and >= 0".into(),
            ));
        }
        // A rebuild uses exactly the stored jitter (no ladder): the matrix must be the one fitted.
        let fixed = Jitter {
            initial: 0.0,
            max: 0.0,
        };
        match (state.noise, &state.noise_model) {
            (NoiseMode::Homoscedastic, None) => {
                let main = Core::build(
                    &x,
                    y,
                    h.prior_mean,
                    &h.length_scales,
                    h.signal_variance,
                    vec![h.noise_variance; x.n],
                    fixed,
                    state.jitter,
                )?;
                Ok(GpModel {
                    x,
                    mode: NoiseMode::Homoscedastic,
                    homo_lml: main.lml,
                    main,
                    noise_model: None,
                    hyper: h.clone(),
                    rounds: 0,
                    stats: None,
                })
            }
            (NoiseMode::Heteroscedastic, Some(ns)) => {
                let nm = NoiseModel::from_state(&x, ns)?;
                let noise = nm.train_noise();
                let main = Core::build(
                    &x,
                    y,
                    h.prior_mean,
                    &h.length_scales,
                    h.signal_variance,
                    noise,
                    fixed,
                    state.jitter,
                )?;
                let homo_lml = if ns.homoscedastic_lml.is_finite() {
                    ns.homoscedastic_lml
                } else {
                    main.lml
                };
                Ok(GpModel {
                    x,
                    mode: NoiseMode::Heteroscedastic,
                    main,
                    noise_model: Some(nm),
                    hyper: h.clone(),
                    homo_lml,
                    rounds: ns.rounds,
                    stats: None,
                })
            }
            _ => Err(GpError::InvalidState(
                "noise mode and noise model disagree".into(),
            )),
        }
    }

    /// The state to store so that [`from_state`](Self::from_state) can rebuild this model.
    pub fn state(&self) -> ModelState {
        ModelState {
            format: 1,
            noise: self.mode,
            n_train: self.x.n,
            hyperparameters: self.hyper.clone(),
            jitter: self.main.jitter,
            log_marginal_likelihood: self.main.lml,
            noise_model: self
                .noise_model
                .as_ref()
                .map(|nm| nm.state(self.rounds, self.homo_lml)),
        }
    }

    /// The main GP's hyperparameters (for heteroscedastic models `noise_variance` is the mean
    /// per-point training noise variance).
    pub fn hyperparameters(&self) -> &Hyperparameters {
        &self.hyper
    }

    /// Log marginal likelihood of the training targets under the fitted model (natural log).
    pub fn log_marginal_likelihood(&self) -> f64 {
        self.main.lml
    }

    /// The noise model actually used (heteroscedastic requests fall back to homoscedastic when
    /// `n < hetero_min_points`).
    pub fn noise_mode(&self) -> NoiseMode {
        self.mode
    }

    /// How the hyperparameter optimisation went; `None` for a model rebuilt from a state.
    pub fn fit_stats(&self) -> Option<&FitStats> {
        self.stats.as_ref()
    }

    /// Absolute jitter the main factorisation needed (0 unless the covariance was near-singular).
    pub fn jitter(&self) -> f64 {
        self.main.jitter
    }

    /// For heteroscedastic models: the per-point training noise variances' min/mean/max, the
    /// noise GP's hyperparameters and the round count. `None` for homoscedastic models.
    pub fn noise_summary(&self) -> Option<NoiseSummary> {
        let nm = self.noise_model.as_ref()?;
        let noise = &self.main.noise;
        Some(NoiseSummary {
            min_noise_variance: noise.iter().copied().fold(f64::INFINITY, f64::min),
            mean_noise_variance: mean(noise),
            max_noise_variance: noise.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            noise_model: nm.hyper.clone(),
            rounds: self.rounds,
            homoscedastic_lml: self.homo_lml,
        })
    }

    /// Number of training points.
    pub fn n_train(&self) -> usize {
        self.x.n
    }

    /// Input dimension.
    pub fn input_dim(&self) -> usize {
        self.x.d
    }

    /// Predicts at the rows of `x`: mean, latent variance and noise variance per point.
    ///
    /// Never panics: if `x` has the wrong number of columns every output is NaN, and a row with
    /// a non-finite coordinate gives NaN for that row. Use [`try_predict`](Self::try_predict) to
    /// get an error instead.
    pub fn predict(&self, x: &DMatrix<f64>) -> Prediction {
        if x.ncols() != self.x.d {
            let m = x.nrows();
            return Prediction {
                mean: vec![f64::NAN; m],
                latent_variance: vec![f64::NAN; m],
                noise_variance: vec![f64::NAN; m],
            };
        }
        let q = Inputs::from_matrix(x);
        let (mean, latent_variance) = self.main.predict(&q, true);
        let noise_variance = match &self.noise_model {
            Some(nm) => nm.predict_noise(&q),
            None => vec![self.hyper.noise_variance; q.n],
        };
        let mut p = Prediction {
            mean,
            latent_variance,
            noise_variance,
        };
        for i in 0..q.n {
            if (0..q.d).any(|k| !q.cols[k * q.n + i].is_finite()) {
                p.mean[i] = f64::NAN;
                p.latent_variance[i] = f64::NAN;
                p.noise_variance[i] = f64::NAN;
            }
        }
        p
    }

    /// Like [`predict`](Self::predict) but rejects a wrong column count or non-finite inputs.
    pub fn try_predict(&self, x: &DMatrix<f64>) -> Result<Prediction, GpError> {
        if x.ncols() != self.x.d {
            return Err(GpError::DimensionMismatch {
                what: "columns of query x vs input dimension",
                expected: self.x.d,
                found: x.ncols(),
            });
        }
        check_finite_matrix(x, "query x")?;
        Ok(self.predict(x))
    }
}

pub(crate) fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}
