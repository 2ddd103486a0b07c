//! [`GpModel`]: a fitted GP with its factorisation cached, and batched prediction.

use nalgebra::{DMatrix, DVector};

use super::core::{Core, PreparedQueries, Prior, mean};
use super::export::{NoisePredictor, Predictor};
use super::fit::{self, Optimum};
use super::hetero::{self, NoiseModel};
use super::kernel::Inputs;
use super::lml::Jitter;
use super::{
    FitStats, GpError, Hyperparameters, ModelState, NoiseMode, NoiseSummary, Prediction,
    ValidGpParams,
};

/// Training rows left out together, of which the first `judged` are predicted from the rest
/// ([`GpModel::leave_folds_out`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Fold {
    /// The rows left out, the judged ones first.
    pub rows: Vec<usize>,
    /// How many of `rows`, from the first, are predicted.
    pub judged: usize,
}

impl Fold {
    /// The most work [`GpModel::leave_folds_out`] takes on for `n` training rows, as `Σ|rows|²`
    /// over the folds: what a partition of the rows costs at worst, `n²`.
    pub fn max_work(n: usize) -> usize {
        n.saturating_mul(n)
    }

    /// Each group left out and judged whole.
    pub fn whole(groups: &[Vec<usize>]) -> Vec<Fold> {
        groups
            .iter()
            .map(|g| Fold {
                rows: g.clone(),
                judged: g.len(),
            })
            .collect()
    }
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
pub(crate) fn check_data(x: &DMatrix<f64>, y: &DVector<f64>) -> Result<Inputs, GpError> {
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

pub(crate) fn check_finite_matrix(x: &DMatrix<f64>, what: &'static str) -> Result<(), GpError> {
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

/// The prediction at the rows of `x` for a model of input dimension `d`, `at` predicting at
/// converted inputs. Never panics: a wrong column count gives NaN everywhere, a row with a
/// non-finite coordinate NaN for that row (the exact and the sparse GP's `predict`).
pub(crate) fn predict_rows(
    x: &DMatrix<f64>,
    d: usize,
    at: impl FnOnce(&Inputs) -> Prediction,
) -> Prediction {
    if x.ncols() != d {
        let m = x.nrows();
        return Prediction {
            mean: vec![f64::NAN; m],
            latent_variance: vec![f64::NAN; m],
            noise_variance: vec![f64::NAN; m],
        };
    }
    let q = Inputs::from_matrix(x);
    let mut p = at(&q);
    mark_non_finite(&q, &mut p);
    p
}

/// NaN for every row of `p` whose query row in `q` has a non-finite coordinate.
fn mark_non_finite(q: &Inputs, p: &mut Prediction) {
    for i in 0..q.n {
        if (0..q.d).any(|k| !q.cols[k * q.n + i].is_finite()) {
            p.mean[i] = f64::NAN;
            p.latent_variance[i] = f64::NAN;
            p.noise_variance[i] = f64::NAN;
        }
    }
}

/// A query `try_predict` accepts: `d` columns, every coordinate finite.
pub(crate) fn check_query(x: &DMatrix<f64>, d: usize) -> Result<(), GpError> {
    if x.ncols() != d {
        return Err(GpError::DimensionMismatch {
            what: "columns of query x vs input dimension",
            expected: d,
            found: x.ncols(),
        });
    }
    check_finite_matrix(x, "query x")
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
        } = fit::optimise_homoscedastic(&x, &r, p)?;
        let prior = Prior::from_log(p.kernel, p.prior_mean, &theta[..=d]);
        let noise = theta[d + 1].exp();
        let homo = Core::build(&prior, &x, y, vec![noise; x.n], jitter, 0.0)?;
        let homo_lml = homo.lml;
        let hetero = p.noise == NoiseMode::Heteroscedastic && x.n >= p.hetero_min_points;
        if !hetero {
            let hyper = prior.with_noise(noise);
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
            kernel: p.kernel,
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
        let (noise, noise_model) = match (state.noise, &state.noise_model) {
            (NoiseMode::Homoscedastic, None) => (vec![h.noise_variance; x.n], None),
            (NoiseMode::Heteroscedastic, Some(ns)) => {
                let nm = NoiseModel::from_state(&x, ns)?;
                (nm.train_noise(), Some((nm, ns)))
            }
            _ => {
                return Err(GpError::InvalidState(
                    "noise mode and noise model disagree".into(),
                ));
            }
        };
        let main = Core::build(&Prior::of(h), &x, y, noise, fixed, state.jitter)?;
        let (homo_lml, rounds) = match &noise_model {
            Some((_, ns)) if ns.homoscedastic_lml.is_finite() => (ns.homoscedastic_lml, ns.rounds),
            Some((_, ns)) => (main.lml, ns.rounds),
            None => (main.lml, 0),
        };
        Ok(GpModel {
            x,
            mode: state.noise,
            main,
            noise_model: noise_model.map(|(nm, _)| nm),
            hyper: h.clone(),
            homo_lml,
            rounds,
            stats: None,
        })
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

    /// Leave-one-out predictions at the training points, in closed form (Rasmussen & Williams
    /// 2006, §5.4.2): for point `i`, the prediction of `y_i` by the model conditioned on every
    /// other point, with the same hyperparameters (and, in heteroscedastic mode, the same noise
    /// model). Returns `(residual_i, sd_i)` with `residual_i = y_i − μ₋ᵢ = α_i / (K⁻¹)_ii` and
    /// `sd_i = (K⁻¹)_ii^{-1/2}`, the standard deviation of an observation (noise included, as in
    /// [`Prediction::std`]). Costs O(n²) on the cached `L⁻¹`; `None` when the factor is absent.
    pub fn leave_one_out(&self) -> Option<Vec<(f64, f64)>> {
        let n = self.main.n;
        if self.main.linv.len() != n * n {
            return None;
        }
        Some(
            self.main
                .kinv_diag()
                .iter()
                .zip(&self.main.alpha)
                .map(|(k, a)| (a / k, 1.0 / k.sqrt()))
                .collect(),
        )
    }

    /// Leave-group-out predictions at the training points, in closed form: every point of a
    /// group is predicted by the model conditioned on the points outside its group, with the
    /// same hyperparameters (and noise model). For a group `G`, with `B = (K⁻¹)_GG`, the
    /// observations `y_G` given the rest have mean `y_G − B⁻¹ α_G` and covariance `B⁻¹`
    /// (the block form of [`leave_one_out`](Self::leave_one_out), to which singleton groups
    /// reduce). Returns `(residual_i, sd_i)` per training point in training order. A point in
    /// no group is left out alone; a point in several groups takes its last group's answer.
    ///
    /// Costs `O(n · Σ|G|²)` on the cached `L⁻¹`; `None` when the factor is absent, a group
    /// names a point that does not exist, or a block cannot be inverted.
    pub fn leave_groups_out(&self, groups: &[Vec<usize>]) -> Option<Vec<(f64, f64)>> {
        self.leave_folds_out(&Fold::whole(groups))
    }

    /// [`leave_groups_out`](Self::leave_groups_out) where what is left out and what is judged
    /// differ: for each fold, its first `judged` rows are predicted by the model conditioned on
    /// the points outside all of its `rows` (the marginal of the block form over the judged
    /// rows). Folds may overlap: a trajectory's rows judged with every copy of them left out
    /// too, where a copy belongs to another trajectory's fold. A point judged by no fold is left
    /// out alone; a point judged by several takes its last fold's answer.
    ///
    /// Costs `O(n · Σ|rows|²)` on the cached `L⁻¹`, and is refused (`None`) beyond the most a
    /// partition of the rows can cost, `Σ|rows|² ≤ n²` (on the order of the fit's own
    /// factorisation): overlapping folds could otherwise multiply it by their number — the same
    /// state-action posted in every trajectory puts all its copies in every fold. `None` also
    /// when the factor is absent, a fold names a point that does not exist, or a block cannot
    /// be inverted.
    pub fn leave_folds_out(&self, folds: &[Fold]) -> Option<Vec<(f64, f64)>> {
        let n = self.main.n;
        let linv = &self.main.linv;
        let work = folds
            .iter()
            .map(|f| f.rows.len().saturating_mul(f.rows.len()))
            .fold(0usize, usize::saturating_add);
        if work > Fold::max_work(n) {
            return None;
        }
        let mut out = self.leave_one_out()?;
        for fold in folds.iter().filter(|f| f.rows.len() > 1 && f.judged > 0) {
            let group = &fold.rows;
            if group.iter().any(|&i| i >= n) {
                return None;
            }
            let g = group.len();
            // (K⁻¹)_ab = Σ_{k ≥ max(a, b)} (L⁻¹)_ka (L⁻¹)_kb, with row k of L⁻¹ holding
            // columns 0..=k.
            let first = *group.iter().min()?;
            let mut b = DMatrix::<f64>::zeros(g, g);
            let mut v = vec![0.0; g];
            for k in first..n {
                let row = &linv[k * n..k * n + k + 1];
                for (va, &i) in v.iter_mut().zip(group) {
                    *va = if i <= k { row[i] } else { 0.0 };
                }
                for a in 0..g {
                    if v[a] == 0.0 {
                        continue;
                    }
                    for c in 0..=a {
                        b[(a, c)] += v[a] * v[c];
                    }
                }
            }
            b.fill_upper_triangle_with_lower_triangle();
            let cov = b.cholesky()?.inverse();
            let alpha = DVector::from_iterator(g, group.iter().map(|&i| self.main.alpha[i]));
            let residual = &cov * alpha;
            for (a, &i) in group.iter().enumerate().take(fold.judged) {
                let var = cov[(a, a)];
                if !(var.is_finite() && var > 0.0) {
                    return None;
                }
                out[i] = (residual[a], var.sqrt());
            }
        }
        Some(out)
    }

    /// The fitted GP as plain numbers ([`Predictor`]): the training inputs, `α`, the cached
    /// `L⁻¹` and the noise (the noise GP's inputs and `α` in heteroscedastic mode). `O(n²)`
    /// numbers.
    pub fn predictor(&self) -> Predictor {
        Predictor {
            main: self.main.predictor(&self.x, true),
            noise: NoisePredictor::new(
                self.hyper.noise_variance,
                self.noise_model
                    .as_ref()
                    .map(|nm| (nm.core.predictor(&self.x, false), nm.clip)),
            ),
        }
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
        predict_rows(x, self.x.d, |q| {
            let (mean, latent_variance) = self.main.predict(q, true);
            let noise_variance = self.noise_at(q);
            Prediction {
                mean,
                latent_variance,
                noise_variance,
            }
        })
    }

    /// Like [`predict`](Self::predict) but rejects a wrong column count or non-finite inputs.
    pub fn try_predict(&self, x: &DMatrix<f64>) -> Result<Prediction, GpError> {
        check_query(x, self.x.d)?;
        Ok(self.predict(x))
    }

    /// The observation-noise variance at each point of `q`.
    fn noise_at(&self, q: &Inputs) -> Vec<f64> {
        match &self.noise_model {
            Some(nm) => nm.predict_noise(q),
            None => vec![self.hyper.noise_variance; q.n],
        }
    }

    /// Like [`predict`](Self::predict), as if the rows of `pending` had been observed too at
    /// this model's hyperparameters and with its noise there (a batch executed but not yet
    /// fitted): the same mean, and the latent variance observing them would leave (see
    /// `Core::fantasy`; exact, since a GP's variance does not depend on the
    /// labels). `O(n² (k + m))` for `k` pending rows and `m` query rows. A `pending` with the
    /// wrong column count or a non-finite coordinate is ignored (the plain prediction).
    pub fn predict_fantasised(&self, x: &DMatrix<f64>, pending: &DMatrix<f64>) -> Prediction {
        self.fantasy(x.clone()).predict(pending)
    }

    /// The rows of `x` prepared for [`predict_fantasised`](Self::predict_fantasised) with
    /// many alternative `pending` sets ([`FantasyQueries::predict`]): the `O(n² m)` whitening
    /// of the `m` rows is done here, once, and each set then costs `O(n² k + n k m)` for its
    /// `k` rows. The `spread` acquisition asks this about every candidate of a proposal.
    pub fn fantasy(&self, x: DMatrix<f64>) -> FantasyQueries<'_> {
        let of_model = FantasyOf {
            dim: self.x.d,
            plain: Box::new(|x| self.predict(x)),
            noise_at: Box::new(|q| self.noise_at(q)),
        };
        FantasyQueries::new(of_model, x, |q| {
            let (mean, fantasy) = self.main.fantasy(q)?;
            Some((mean, Box::new(fantasy) as Box<dyn PreparedQueries>))
        })
    }
}

/// A GP's side of [`FantasyQueries`]: its input dimension, its plain prediction (what an empty
/// or invalid pending set answers) and its observation noise at pending points.
pub(crate) struct FantasyOf<'a> {
    pub dim: usize,
    pub plain: Box<PlainPrediction<'a>>,
    pub noise_at: Box<NoiseAt<'a>>,
}

/// A GP's plain prediction at query rows.
pub(crate) type PlainPrediction<'a> = dyn Fn(&DMatrix<f64>) -> Prediction + 'a;

/// A GP's observation-noise variances at points.
pub(crate) type NoiseAt<'a> = dyn Fn(&Inputs) -> Vec<f64> + 'a;

/// Query rows prepared for predictions as if different pending rows had been observed
/// ([`GpModel::fantasy`], [`SparseGp::fantasy`](super::SparseGp::fantasy)).
pub struct FantasyQueries<'a> {
    model: FantasyOf<'a>,
    x: DMatrix<f64>,
    /// The rows as inputs, the posterior mean there, their preparation and their noise; `None`
    /// where the plain prediction is every answer (wrong column count, no rows, or no factor
    /// to fantasise with).
    prepared: Option<Prepared<'a>>,
}

/// [`FantasyQueries`]' rows once prepared.
struct Prepared<'a> {
    q: Inputs,
    mean: Vec<f64>,
    variances: Box<dyn PreparedQueries + 'a>,
    noise: Vec<f64>,
}

impl<'a> FantasyQueries<'a> {
    /// The rows of `x` prepared by `prepare` (given them as inputs; it answers the posterior
    /// mean there beside the preparation) for the GP `model` describes.
    pub(crate) fn new(
        model: FantasyOf<'a>,
        x: DMatrix<f64>,
        prepare: impl FnOnce(&Inputs) -> Option<(Vec<f64>, Box<dyn PreparedQueries + 'a>)>,
    ) -> Self {
        let prepared = (x.ncols() == model.dim).then(|| {
            let q = Inputs::from_matrix(&x);
            let (mean, variances) = prepare(&q)?;
            let noise = (model.noise_at)(&q);
            Some(Prepared {
                q,
                mean,
                variances,
                noise,
            })
        });
        FantasyQueries {
            model,
            x,
            prepared: prepared.flatten(),
        }
    }

    /// [`GpModel::predict_fantasised`] of the prepared rows with these `pending` rows.
    pub fn predict(&self, pending: &DMatrix<f64>) -> Prediction {
        self.predict_each(std::slice::from_ref(pending))
            .swap_remove(0)
    }

    /// [`predict`](Self::predict) with each of several alternative `pending` sets, in order;
    /// their whitening is one product with `L⁻¹` for all of them.
    pub fn predict_each(&self, pendings: &[DMatrix<f64>]) -> Vec<Prediction> {
        let model = &self.model;
        let Some(prepared) = &self.prepared else {
            return pendings.iter().map(|_| (model.plain)(&self.x)).collect();
        };
        // A set that is empty or not a query answers the plain prediction.
        let sets: Vec<Option<(Inputs, Vec<f64>)>> = pendings
            .iter()
            .map(|pending| {
                let valid = pending.nrows() > 0 && check_query(pending, model.dim).is_ok();
                valid.then(|| {
                    let p = Inputs::from_matrix(pending);
                    let noise_p = (model.noise_at)(&p);
                    (p, noise_p)
                })
            })
            .collect();
        let valid: Vec<(&Inputs, &[f64])> = sets
            .iter()
            .flatten()
            .map(|(p, noise_p)| (p, noise_p.as_slice()))
            .collect();
        let mut variances = prepared.variances.variances_each(&valid).into_iter();
        sets.iter()
            .map(|set| match set {
                None => (model.plain)(&self.x),
                Some(_) => {
                    let mut prediction = Prediction {
                        mean: prepared.mean.clone(),
                        latent_variance: variances.next().unwrap_or_default(),
                        noise_variance: prepared.noise.clone(),
                    };
                    mark_non_finite(&prepared.q, &mut prediction);
                    prediction
                }
            })
            .collect()
    }
}
