//! The model deviation estimator as the service serves it: before any data the GP prior, after
//! that a fitted regressor, each under a version. Knows nothing of HTTP or SQL.
//!
//! - [`estimator`]: the seam — the [`Regressor`] trait every fitted estimator answers through
//!   (the exact GP, the sparse GP), [`fit`], the stored [`EstimatorState`], and the
//!   `mde.estimator` choice ([`EstimatorChoice`]).
//! - [`experts`]: the local experts estimator ([`LocalExperts`]), exact GPs on regions of the
//!   feature space.
//! - [`export`]: a fitted version as a self-contained document a controller evaluates itself
//!   ([`ExportedModel`]).
//! - [`margin`]: the locally calibrated trust margin ([`LocalMargin`]), the β each state-action
//!   is judged at from the held-out judgements of the training transitions near it.
//! - [`selection`]: model selection at every fit — the label cap (how deviations become training
//!   labels, [`capped_labels`]), the kernel and the certified test β, each chosen from held-out
//!   judgements of the training transitions ([`fit_choosing_label_cap`], [`HeldOutTrust`],
//!   [`best_kernel`]), and what the choice costs ([`selection_cost`]).

pub mod estimator;
pub mod experts;
pub mod export;
pub mod margin;
pub mod selection;

pub use estimator::{
    AUTO_EXACT_MAX_N, DEFAULT_SELECTION_SUBSET, EstimatorChoice, EstimatorKind, EstimatorParams,
    EstimatorPredictor, EstimatorState, Regressor, fit,
};
pub use experts::{DEFAULT_EXPERT_SIZE, ExpertsPredictor, LocalExperts};
pub use export::{EXPORT_FORMAT, EXPORT_FORMAT_VERSION, ExportedModel};
pub use margin::{LocalMargin, Margined};
pub use selection::{
    BetaChoice, CALIBRATED_FALSE_TRUST, CAP_GAIN_STANDARD_ERRORS, CapChoice, Carry, FitPhase,
    HeldOutTrust, KernelTrial, LIKELIHOOD_DROP, Previous, RefitPlan, SelectionRecord, Training,
    best_kernel, blocks, capped_labels, fit_choosing_label_cap, held_out_margins, identical_rows,
    normal_tail, refit_plan, refit_warm, selection_cost, trajectory_folds,
};

use crate::gp::{GpParams, Hyperparameters, Kernel, NoiseMode, NoiseSummary};
use crate::planning::{DeviationModel, Fantasy, Precondition};
use nalgebra::{DMatrix, DVector};

/// What answers queries.
#[derive(Debug)]
pub enum Estimator {
    /// No data yet: μ = prior mean, σ = prior standard deviation, everywhere.
    Prior(Hyperparameters),
    /// A fitted regressor.
    Fitted(Box<dyn Regressor>),
}

/// How a version was fitted.
#[derive(Debug, Clone)]
pub struct FitRecord {
    /// Seconds the fit took.
    pub fit_seconds: f64,
    /// When it finished (RFC 3339).
    pub fitted_at: String,
    /// Trajectories stored when the fit started (used to tell whether a batch is still unfitted).
    pub n_trajectories: i64,
    /// The label cap the training labels were clipped at (units of `d_max`; 0 = raw labels).
    pub label_cap: f64,
    /// Every candidate cap's held-out judgement of the training transitions (one entry for a
    /// fixed cap; none for versions fitted before caps were recorded).
    pub label_cap_trials: Vec<HeldOutTrust>,
    /// Trajectories taken in by online updates since the fit (sparse GP; 0 otherwise).
    pub online_trajectories: usize,
    /// Every candidate kernel's fit, when the kernel was chosen from the data.
    pub kernel_trials: Vec<KernelTrial>,
    /// The test β this version's held-out judgements certify (`None` where they could not be
    /// computed, and for versions fitted before it was recorded); used by test plans when
    /// `learning.calibrate_test_beta` is on.
    pub beta_choice: Option<BetaChoice>,
    /// How its kernel and label cap were chosen (anew, or kept from an earlier version by a
    /// warm refit) and what the fit spent its time on (`None` for versions fitted before it was
    /// recorded).
    pub selection: Option<SelectionRecord>,
    /// The locally calibrated margin of this version's held-out judgements (`None` where they
    /// could not be computed); used by test plans and default judgements when
    /// `learning.local_test_margin` is on. Not stored: rebuilt with the version.
    pub local_margin: Option<std::sync::Arc<LocalMargin>>,
    /// The exclusions (ids of the service's records) in effect when the fit read its
    /// training set: it was fitted on the first `n_train` transitions outside the trajectories
    /// they cover.
    pub exclusions: Vec<i64>,
}

impl ServedModel {
    /// What this version tells the next fit ([`refit_plan`]).
    pub fn as_previous(&self) -> Previous<'_> {
        Previous {
            version: self.version,
            fitted: match (&self.estimator, &self.fit) {
                (Estimator::Fitted(gp), Some(fit)) => Some((gp.as_ref(), fit.label_cap)),
                _ => None,
            },
            selection: self.fit.as_ref().and_then(|f| f.selection.as_ref()),
        }
    }
}

/// One version of an experiment's MDE.
#[derive(Debug)]
pub struct ServedModel {
    /// 0 for the prior, then 1, 2, … one per fit.
    pub version: i64,
    /// The estimator.
    pub estimator: Estimator,
    /// Absent for the prior.
    pub fit: Option<FitRecord>,
    /// The estimators of the experiment's further models of its robot, fitted with this
    /// version from their own labels (none for the prior, nor for a model without labels);
    /// shared by the versions an online update makes, which do not update them.
    pub further: std::sync::Arc<Vec<FurtherEstimator>>,
}

/// The deviation estimator of one of an experiment's further models: fitted with a version of
/// the domain model's, on the same training transitions that model labelled, with the domain
/// model's kernel and label cap.
#[derive(Debug)]
pub struct FurtherEstimator {
    /// The further model's name.
    pub model: String,
    /// Its estimator.
    pub estimator: Estimator,
    /// The label cap its labels were clipped at (units of `d_max`; 0 = raw labels).
    pub label_cap: f64,
}

impl Estimator {
    /// μ and σ for `n = features.len() / dim` row-major feature vectors (see
    /// [`ServedModel::answer`]).
    pub fn answer(&self, features: &[f64], dim: usize) -> Vec<Answer> {
        if dim == 0 {
            return Vec::new();
        }
        let n = features.len() / dim;
        match self {
            Estimator::Prior(h) => vec![
                Answer {
                    mu: h.prior_mean,
                    sigma: h.prior_std(),
                };
                n
            ],
            Estimator::Fitted(gp) => {
                let x = DMatrix::from_row_slice(n, dim, &features[..n * dim]);
                let p = gp.predict(&x);
                p.mean
                    .iter()
                    .zip(p.std())
                    .map(|(mu, sigma)| Answer { mu: *mu, sigma })
                    .collect()
            }
        }
    }

    /// Floats it keeps in memory.
    pub fn floats(&self) -> usize {
        match self {
            Estimator::Prior(_) => 0,
            Estimator::Fitted(gp) => gp.floats(),
        }
    }
}

/// The MDE's answer at one point.
#[derive(Debug, Clone, PartialEq)]
pub struct Answer {
    /// Mean deviation μ.
    pub mu: f64,
    /// Standard deviation σ (latent and noise).
    pub sigma: f64,
}

/// Whether one state-action lies in the model precondition `μ + βσ < d_max`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct Judgement {
    /// Mean deviation μ.
    pub mu: f64,
    /// Standard deviation σ (latent and noise).
    pub sigma: f64,
    /// `μ + βσ`.
    pub upper: f64,
    /// `upper < d_max`.
    pub inside: bool,
}

impl Judgement {
    /// The judgement of `answer` by `precondition`; `None` when the model answered a
    /// non-finite value (which must never reach a client).
    pub fn of(answer: &Answer, precondition: Precondition) -> Option<Self> {
        let upper = precondition.upper(answer.mu, answer.sigma);
        upper.is_finite().then_some(Self {
            mu: answer.mu,
            sigma: answer.sigma,
            upper,
            inside: precondition.inside(answer.mu, answer.sigma),
        })
    }
}

impl ServedModel {
    /// The prior, version 0, for features of dimension `dim`, under the kernel later fits use.
    pub fn prior(dim: usize, prior_mean: f64, kernel: Kernel) -> Self {
        Self {
            version: 0,
            estimator: Estimator::Prior(Hyperparameters {
                kernel,
                ..Hyperparameters::prior(dim, prior_mean)
            }),
            fit: None,
            further: Default::default(),
        }
    }

    /// The estimator of the further model `model` in this version, if it has one.
    pub fn further(&self, model: &str) -> Option<&FurtherEstimator> {
        self.further.iter().find(|f| f.model == model)
    }

    /// Which regressor answers (`None` for the prior).
    pub fn kind(&self) -> Option<EstimatorKind> {
        match &self.estimator {
            Estimator::Prior(_) => None,
            Estimator::Fitted(gp) => Some(gp.kind()),
        }
    }

    /// Floats the version keeps in memory (its further models' estimators too).
    pub fn floats(&self) -> usize {
        self.estimator.floats()
            + self
                .further
                .iter()
                .map(|f| f.estimator.floats())
                .sum::<usize>()
    }

    /// Training-set size (0 for the prior).
    pub fn n_train(&self) -> usize {
        match &self.estimator {
            Estimator::Prior(_) => 0,
            Estimator::Fitted(gp) => gp.n_train(),
        }
    }

    /// The hyperparameters answering queries, where one set answers everywhere (the prior's;
    /// a fitted GP's; `None` for local experts).
    pub fn hyperparameters(&self) -> Option<&Hyperparameters> {
        match &self.estimator {
            Estimator::Prior(h) => Some(h),
            Estimator::Fitted(gp) => gp.hyperparameters(),
        }
    }

    /// Log marginal likelihood of the fitted model (`None` for the prior).
    pub fn log_marginal_likelihood(&self) -> Option<f64> {
        match &self.estimator {
            Estimator::Prior(_) => None,
            Estimator::Fitted(gp) => Some(gp.log_marginal_likelihood()),
        }
    }

    /// Noise mode used (`None` for the prior).
    pub fn noise_mode(&self) -> Option<NoiseMode> {
        match &self.estimator {
            Estimator::Prior(_) => None,
            Estimator::Fitted(gp) => Some(gp.noise_mode()),
        }
    }

    /// Heteroscedastic noise model summary, when there is one.
    pub fn noise_summary(&self) -> Option<NoiseSummary> {
        match &self.estimator {
            Estimator::Prior(_) => None,
            Estimator::Fitted(gp) => gp.noise_summary(),
        }
    }

    /// μ and σ for `n = features.len() / dim` row-major feature vectors. A GP that cannot
    /// answer (which the service's validation should make impossible) answers NaN, which
    /// every caller checks before it leaves the process.
    pub fn answer(&self, features: &[f64], dim: usize) -> Vec<Answer> {
        self.estimator.answer(features, dim)
    }
}

/// A further model's estimator as the planner asks it (its `μ` and `σ`, no fantasies).
impl DeviationModel for Estimator {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        self.answer(features, dim)
            .into_iter()
            .map(|a| (a.mu, a.sigma))
            .collect()
    }
}

impl DeviationModel for ServedModel {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        self.estimator.predict(features, dim)
    }

    /// A fitted regressor's [`Regressor::predict_fantasised`]; the prior does not fantasise
    /// (its σ is the same everywhere, and stays so).
    fn predict_fantasised(&self, features: &[f64], pending: &[f64], dim: usize) -> Vec<(f64, f64)> {
        self.fantasy(features, dim)(&[pending]).swap_remove(0)
    }

    /// The fitted regressor's [`Regressor::fantasy`] of `features`, asked about each pending
    /// set; the prior's plain answer.
    fn fantasy<'a>(&'a self, features: &'a [f64], dim: usize) -> Fantasy<'a> {
        let plain = move |pendings: &[&[f64]]| vec![self.predict(features, dim); pendings.len()];
        let Estimator::Fitted(gp) = &self.estimator else {
            return Box::new(plain);
        };
        if dim == 0 {
            return Box::new(plain);
        }
        let rows =
            move |v: &[f64]| DMatrix::from_row_slice(v.len() / dim, dim, &v[..v.len() / dim * dim]);
        let prepared = gp.fantasy(rows(features));
        // A set shorter than one row is nothing pending: zero rows, the plain prediction.
        Box::new(move |pendings| {
            let sets: Vec<DMatrix<f64>> = pendings.iter().map(|p| rows(p)).collect();
            prepared(&sets)
                .iter()
                .map(|answer| answer.mean.iter().copied().zip(answer.std()).collect())
                .collect()
        })
    }
}

/// Row-major features and labels as the GP wants them.
pub fn training_data(
    features: Vec<f64>,
    labels: Vec<f64>,
    dim: usize,
) -> (DMatrix<f64>, DVector<f64>) {
    let n = labels.len();
    (
        DMatrix::from_row_slice(n, dim, &features),
        DVector::from_vec(labels),
    )
}

/// The GP parameters for an experiment's MDE settings and a fit's seed.
pub fn gp_params(
    noise: NoiseMode,
    kernel: Kernel,
    prior_mean: f64,
    restarts: usize,
    seed: u64,
) -> GpParams {
    GpParams {
        noise,
        kernel,
        prior_mean,
        restarts,
        seed,
        ..GpParams::default()
    }
}
