//! A fitted GP as plain numbers ([`Predictor`]): what computing its mean, latent variance and
//! noise variance at a point needs, for a program that does not run this crate's fit — the
//! exported model (`mde::export`), and its numpy twin in the Python client.
//!
//! Both regressors reduce to the same form. With `k_i = k(x, p_i)` the kernel between the query
//! and the stored points (the training inputs of the exact GP, the inducing inputs of the sparse
//! GP), a GP's
//!
//! - mean is `m + Σ_i w_i k_i` (exact: `w = K⁻¹(y − m)`; sparse: `w = L⁻ᵀ L_B⁻ᵀ c`);
//! - latent variance is `s² − ‖F k‖² + ‖C k‖²`, clamped to `[0, s²]`, with `F` and `C` lower
//!   triangular (exact: `F = L⁻¹` of the noisy training covariance, no `C`; sparse:
//!   `F = chol(K_mm + εI)⁻¹` and `C = L_B⁻¹ F`);
//! - noise variance is a constant, or `clamp(exp(μ₂(x)), low, high)` with `μ₂` the mean of a
//!   second GP of the same form (without variance factors) on log noise variances.
//!
//! The server's `σ` is `√(latent + noise)`. The factors are the server's own (`F` of the exact GP
//! is the `L⁻¹` its predictions use) or the explicit inverses of the triangles its predictions
//! solve with (sparse), so evaluations agree with the server's to rounding.

use serde::{Deserialize, Serialize};

use super::kernel::{Inputs, Kernel};

/// One GP's mean (and optionally latent variance) as plain numbers; see the module
/// documentation for the formulas.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct GpPredictor {
    /// The Matérn kernel.
    pub kernel: Kernel,
    /// ARD length scales `ℓ_k`, one per feature; `r² = Σ_k ((x_k − p_k) / ℓ_k)²`, computed as
    /// `Σ_k (p_k/ℓ_k − x_k/ℓ_k)²` (each division a multiplication by `1/ℓ_k`).
    pub length_scales: Vec<f64>,
    /// Signal variance `s²`.
    pub signal_variance: f64,
    /// Constant prior mean `m`.
    pub prior_mean: f64,
    /// The points `p_i` the kernel is evaluated against, one row of features each.
    pub points: Vec<Vec<f64>>,
    /// The weights `w_i` of the mean, one per point.
    pub weights: Vec<f64>,
    /// `F`, lower triangular, packed by rows (row `i` holds columns `0..=i`: `n(n+1)/2`
    /// numbers); `null` for a GP asked only for its mean (the noise GP).
    pub factor: Option<Vec<f64>>,
    /// `C`, packed likewise (the sparse GP); `null` when the variance has no such term (exact).
    pub correction: Option<Vec<f64>>,
}

/// The observation noise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum NoisePredictor {
    /// One noise variance everywhere.
    Homoscedastic {
        /// The noise variance `σ²_n`.
        noise_variance: f64,
    },
    /// The noise variance `clamp(exp(μ₂(x)), noise_variance_min, noise_variance_max)`, `μ₂` the
    /// mean of a GP on log noise variances.
    Heteroscedastic {
        /// The GP on log noise variances (`factor` and `correction` null).
        log_noise: GpPredictor,
        /// The lower clip.
        noise_variance_min: f64,
        /// The upper clip.
        noise_variance_max: f64,
    },
}

impl NoisePredictor {
    /// One noise variance `noise_variance` without a noise GP, else the noise GP `log_noise`
    /// with its clip `(min, max)`: the noise of the exact and the sparse GP's [`Predictor`].
    pub(crate) fn new(noise_variance: f64, log_noise: Option<(GpPredictor, (f64, f64))>) -> Self {
        match log_noise {
            None => NoisePredictor::Homoscedastic { noise_variance },
            Some((log_noise, (noise_variance_min, noise_variance_max))) => {
                NoisePredictor::Heteroscedastic {
                    log_noise,
                    noise_variance_min,
                    noise_variance_max,
                }
            }
        }
    }
}

/// A fitted GP's predictions as plain numbers: the main GP and its noise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct Predictor {
    /// The GP on deviations.
    pub main: GpPredictor,
    /// Its noise.
    pub noise: NoisePredictor,
}

/// One point's prediction: mean, latent variance and noise variance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointPrediction {
    /// Mean μ.
    pub mean: f64,
    /// Latent variance.
    pub latent_variance: f64,
    /// Noise variance.
    pub noise_variance: f64,
}

impl PointPrediction {
    /// `√(latent + noise)`, the σ the server reports.
    pub fn std(&self) -> f64 {
        (self.latent_variance + self.noise_variance).sqrt()
    }
}

/// Reusable buffers for [`Predictor::predict_into`], so that a control loop's evaluations
/// allocate nothing after the first.
#[derive(Debug, Clone, Default)]
pub struct Scratch {
    scaled: Vec<f64>,
    k: Vec<f64>,
}

/// The row-major packing of the lower triangle of a column-major `n × n` matrix.
pub(crate) fn pack_lower_col_major(a: &[f64], n: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(n * (n + 1) / 2);
    for i in 0..n {
        out.extend((0..=i).map(|j| a[j * n + i]));
    }
    out
}

/// The row-major packing of the lower triangle of a row-major `n × n` matrix.
pub(crate) fn pack_lower_row_major(a: &[f64], n: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(n * (n + 1) / 2);
    for i in 0..n {
        out.extend_from_slice(&a[i * n..i * n + i + 1]);
    }
    out
}

/// The rows of a column-major `n × d` point set.
pub(crate) fn rows(x: &Inputs) -> Vec<Vec<f64>> {
    (0..x.n)
        .map(|i| (0..x.d).map(|k| x.cols[k * x.n + i]).collect())
        .collect()
}

/// `‖P k‖²` for `P` lower triangular packed by rows.
fn packed_quad(p: &[f64], k: &[f64]) -> f64 {
    let mut sum = 0.0;
    let mut start = 0;
    for i in 0..k.len() {
        let row = &p[start..start + i + 1];
        let t: f64 = row.iter().zip(&k[..=i]).map(|(a, b)| a * b).sum();
        sum += t * t;
        start += i + 1;
    }
    sum
}

impl GpPredictor {
    /// Input dimension.
    pub fn dim(&self) -> usize {
        self.length_scales.len()
    }

    /// Checks that the numbers fit together (lengths, finiteness, positivity), so that
    /// [`mean_and_variance`](Self::mean_and_variance) cannot index out of bounds. The error
    /// names the field.
    pub fn check(&self, what: &str) -> Result<(), String> {
        let d = self.dim();
        let n = self.points.len();
        let fail = |field: &str, reason: String| Err(format!("{what}.{field}: {reason}"));
        if d == 0 {
            return fail("length_scales", "at least one".into());
        }
        if !self.length_scales.iter().all(|l| l.is_finite() && *l > 0.0) {
            return fail("length_scales", "finite and positive".into());
        }
        if !(self.signal_variance.is_finite() && self.signal_variance > 0.0) {
            return fail("signal_variance", "finite and positive".into());
        }
        if !self.prior_mean.is_finite() {
            return fail("prior_mean", "finite".into());
        }
        if n == 0 {
            return fail("points", "at least one".into());
        }
        if let Some(i) = self
            .points
            .iter()
            .position(|p| p.len() != d || p.iter().any(|v| !v.is_finite()))
        {
            return fail(&format!("points[{i}]"), format!("{d} finite numbers"));
        }
        if self.weights.len() != n || self.weights.iter().any(|v| !v.is_finite()) {
            return fail("weights", format!("{n} finite numbers"));
        }
        for (name, f) in [("factor", &self.factor), ("correction", &self.correction)] {
            if let Some(f) = f
                && (f.len() != n * (n + 1) / 2 || f.iter().any(|v| !v.is_finite()))
            {
                return fail(name, format!("{} finite numbers", n * (n + 1) / 2));
            }
        }
        if self.correction.is_some() && self.factor.is_none() {
            return fail("correction", "needs a factor".into());
        }
        Ok(())
    }

    /// Mean and latent variance at `x` (`NaN` variance without a factor). `x` must have
    /// [`dim`](Self::dim) components and the predictor must have passed
    /// [`check`](Self::check).
    pub fn mean_and_variance(&self, x: &[f64], scratch: &mut Scratch) -> (f64, f64) {
        let d = self.dim();
        scratch.scaled.clear();
        scratch
            .scaled
            .extend(self.length_scales.iter().zip(x).map(|(l, v)| v * (1.0 / l)));
        scratch.k.clear();
        let s2 = self.signal_variance;
        let q = &scratch.scaled;
        scratch.k.extend(self.points.iter().map(|p| {
            let r2: f64 = (0..d)
                .map(|k| {
                    let t = p[k] * (1.0 / self.length_scales[k]) - q[k];
                    t * t
                })
                .sum();
            self.kernel.value(r2, s2)
        }));
        let k = &scratch.k;
        let mean = self.prior_mean + k.iter().zip(&self.weights).map(|(a, b)| a * b).sum::<f64>();
        let var = match &self.factor {
            None => f64::NAN,
            Some(f) => {
                let c = self
                    .correction
                    .as_deref()
                    .map_or(0.0, |c| packed_quad(c, k));
                (s2 - packed_quad(f, k) + c).clamp(0.0, s2)
            }
        };
        (mean, var)
    }
}

impl NoisePredictor {
    /// The noise variance at `x`.
    pub fn at(&self, x: &[f64], scratch: &mut Scratch) -> f64 {
        match self {
            Self::Homoscedastic { noise_variance } => *noise_variance,
            Self::Heteroscedastic {
                log_noise,
                noise_variance_min,
                noise_variance_max,
            } => log_noise
                .mean_and_variance(x, scratch)
                .0
                .exp()
                .clamp(*noise_variance_min, *noise_variance_max),
        }
    }
}

impl Predictor {
    /// Input dimension.
    pub fn dim(&self) -> usize {
        self.main.dim()
    }

    /// Checks the main GP, that it has a variance factor, and the noise (see
    /// [`GpPredictor::check`]).
    pub fn check(&self) -> Result<(), String> {
        self.main.check("main")?;
        if self.main.factor.is_none() {
            return Err("main.factor: the main GP needs its variance factor".into());
        }
        match &self.noise {
            NoisePredictor::Homoscedastic { noise_variance } => {
                if !(noise_variance.is_finite() && *noise_variance >= 0.0) {
                    return Err("noise.noise_variance: finite and >= 0".into());
                }
            }
            NoisePredictor::Heteroscedastic {
                log_noise,
                noise_variance_min: lo,
                noise_variance_max: hi,
            } => {
                log_noise.check("noise.log_noise")?;
                if log_noise.dim() != self.dim() {
                    return Err(format!(
                        "noise.log_noise.length_scales: {} features, as the main GP",
                        self.dim()
                    ));
                }
                if !(lo.is_finite() && hi.is_finite() && *lo >= 0.0 && lo <= hi) {
                    return Err("noise: 0 <= noise_variance_min <= noise_variance_max".into());
                }
            }
        }
        Ok(())
    }

    /// The prediction at features `x` (a checked predictor, `x` of its dimension).
    pub fn predict_into(&self, x: &[f64], scratch: &mut Scratch) -> PointPrediction {
        let (mean, latent_variance) = self.main.mean_and_variance(x, scratch);
        let noise_variance = self.noise.at(x, scratch);
        PointPrediction {
            mean,
            latent_variance,
            noise_variance,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{GpModel, GpParams, NoiseMode, SparseGp, SparseParams};
    use super::*;
    use nalgebra::{DMatrix, DVector};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Noisy data on `[0, 1]³` whose noise grows with the first feature.
    fn data(n: usize, seed: u64) -> (DMatrix<f64>, DVector<f64>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let x = DMatrix::from_fn(n, 3, |_, _| rng.random::<f64>());
        let y = DVector::from_fn(n, |i, _| {
            let noise = 0.02 + 0.3 * x[(i, 0)];
            (4.0 * x[(i, 0)]).sin() + x[(i, 1)] * x[(i, 2)] + noise * (rng.random::<f64>() - 0.5)
        });
        (x, y)
    }

    /// The predictor's answers at random points (inside and a little outside the unit box)
    /// against the model's batched `predict`; the largest relative differences of μ and σ.
    fn worst(p: &Predictor, predict: impl Fn(&DMatrix<f64>) -> super::super::Prediction) -> f64 {
        p.check().expect("the predictor checks");
        let json = serde_json::to_string(p).unwrap();
        let back: Predictor = serde_json::from_str(&json).unwrap();
        assert_eq!(&back, p, "JSON round-trips the numbers exactly");
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let q = DMatrix::from_fn(300, p.dim(), |_, _| rng.random::<f64>() * 1.2 - 0.1);
        let want = predict(&q);
        let (mu, sd) = (want.mean.clone(), want.std());
        let mut scratch = Scratch::default();
        let mut worst = 0.0f64;
        for i in 0..q.nrows() {
            let x: Vec<f64> = q.row(i).iter().copied().collect();
            let got = p.predict_into(&x, &mut scratch);
            let rel = |a: f64, b: f64| (a - b).abs() / (1.0 + b.abs());
            worst = worst.max(rel(got.mean, mu[i])).max(rel(got.std(), sd[i]));
        }
        worst
    }

    #[test]
    fn an_exact_gps_predictor_answers_as_the_gp() {
        let (x, y) = data(120, 1);
        for noise in [NoiseMode::Homoscedastic, NoiseMode::Heteroscedastic] {
            for kernel in Kernel::ALL {
                let params = GpParams {
                    noise,
                    kernel,
                    restarts: 0,
                    ..GpParams::default()
                };
                let gp = GpModel::fit(&x, &y, &params.check().unwrap()).unwrap();
                assert_eq!(gp.noise_mode(), noise);
                let w = worst(&gp.predictor(), |q| gp.predict(q));
                assert!(w < 1e-11, "{noise:?} {kernel}: {w:e}");
            }
        }
    }

    #[test]
    fn a_sparse_gps_predictor_answers_as_the_gp() {
        let (x, y) = data(400, 2);
        for noise in [NoiseMode::Homoscedastic, NoiseMode::Heteroscedastic] {
            for kernel in [Kernel::Matern12, Kernel::Matern52] {
                // Low rank (40 inducing points), and full rank (all 400 inputs).
                for full_rank_up_to in [0, 400] {
                    let params = SparseParams {
                        gp: GpParams {
                            noise,
                            kernel,
                            restarts: 0,
                            ..GpParams::default()
                        },
                        inducing_points: 40,
                        noise_inducing_points: 20,
                        inducing_rounds: 1,
                        full_rank_up_to,
                        ..SparseParams::default()
                    };
                    let gp = SparseGp::fit(&x, &y, &params.check().unwrap()).unwrap();
                    let w = worst(&gp.predictor(), |q| gp.predict(q));
                    assert!(w < 1e-10, "{noise:?} {kernel} {full_rank_up_to}: {w:e}");
                }
            }
        }
    }
}
