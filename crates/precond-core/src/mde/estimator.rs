//! The estimator seam: every fitted regressor behind the MDE answers through [`Regressor`], is
//! fitted by [`fit`] and stored and restored as an [`EstimatorState`] — one match arm per
//! estimator in each. The service, the diagnostics, the label-cap choice and the stored model
//! rows see only these.
//!
//! - [`EstimatorKind::Exact`]: the exact GP ([`GpModel`]): `O(n³)` to fit, `O(n²)` memory, the
//!   better choice while it fits (closed-form leave-one-out, no approximation).
//! - [`EstimatorKind::Sparse`]: the sparse variational GP ([`SparseGp`], `m` inducing points):
//!   `O(n m²)` to fit, `O(n m)` memory, online updates at fixed hyperparameters. Up to
//!   [`DEFAULT_FULL_RANK_UP_TO`](crate::gp::DEFAULT_FULL_RANK_UP_TO) transitions every training
//!   input is an inducing point, and the fit is the exact GP's in sparse form.
//!
//! - [`EstimatorKind::LocalExperts`]: exact GPs, one per region of the feature space, each with
//!   its own hyperparameters ([`LocalExperts`]): for deviations that are flat in one place and
//!   jump in another; `k · O((n/k)³)` to fit, closed-form leave-out per expert.
//!
//! What an estimator can do beyond μ and σ it declares ([`EstimatorKind::judges_held_out`],
//! [`EstimatorKind::updates_online`], [`Regressor::hyperparameters`]); the service and model
//! selection ask these, not which estimator it is. A new estimator is a [`Regressor`]
//! implementation, an [`EstimatorKind`] and [`EstimatorState`] variant, an arm in [`fit`] and
//! [`EstimatorState::restore`], and its exported form ([`EstimatorPredictor`]).
//!
//! [`EstimatorChoice::Auto`] (the default) fits the exact GP up to [`AUTO_EXACT_MAX_N`]
//! transitions, and while its fit stays within the memory budget, and the sparse GP beyond.

use super::experts::{DEFAULT_EXPERT_SIZE, ExpertsPredictor, ExpertsState, LocalExperts};
use crate::gp::export::{PointPrediction, Scratch};
use crate::gp::{
    FitCost, Fold, GpError, GpModel, GpParams, Hyperparameters, Kernel, ModelState, NoiseMode,
    NoiseSummary, Prediction, Predictor, SparseGp, SparseParams, SparseState, ValidGpParams,
    ValidSparseParams, WarmStart, exact_fit_cost, sparse_fit_cost,
};
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// Which regressor a fitted version is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum EstimatorKind {
    /// The exact GP.
    #[default]
    Exact,
    /// The sparse variational GP.
    Sparse,
    /// Exact GPs, one per region of the feature space ([`LocalExperts`]).
    LocalExperts,
}

impl EstimatorKind {
    /// The setting's name.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Exact => "exact",
            Self::Sparse => "sparse",
            Self::LocalExperts => "local_experts",
        }
    }

    /// The kind named `name` ([`as_str`](Self::as_str)).
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Exact, Self::Sparse, Self::LocalExperts]
            .into_iter()
            .find(|k| k.as_str() == name)
    }

    /// Whether its fits judge their own training transitions held out in closed form
    /// ([`Regressor::leave_folds_out`] answers): model selection (label cap, kernel, certified
    /// β) then runs on the estimator itself; otherwise on exact GPs over a subset.
    pub fn judges_held_out(self) -> bool {
        match self {
            Self::Exact | Self::LocalExperts => true,
            Self::Sparse => false,
        }
    }

    /// Whether a fitted version takes new trajectories in by an online update at its
    /// hyperparameters ([`Regressor::update`]) rather than only by a refit.
    pub fn updates_online(self) -> bool {
        match self {
            Self::Sparse => true,
            Self::Exact | Self::LocalExperts => false,
        }
    }

    /// Whether its cost grows like the exact GP's, cubically in the training set: a batch's
    /// proposals in flight are then limited by the fit they will cause.
    pub fn fits_cubically(self) -> bool {
        match self {
            Self::Exact => true,
            Self::Sparse | Self::LocalExperts => false,
        }
    }
}

/// The `mde.estimator` setting: which regressor fits use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum EstimatorChoice {
    /// The exact GP while it is cheap and fits the memory budget, the sparse GP beyond.
    #[default]
    Auto,
    /// Always the exact GP (a fit too large for the memory budget is refused).
    Exact,
    /// Always the sparse GP.
    Sparse,
    /// Always local experts: exact GPs on regions of about `mde.expert_size` transitions each.
    LocalExperts,
}

/// [`EstimatorChoice::Auto`] fits the exact GP up to this many training transitions. At
/// n = 2000 (d = 6, 2 cores) the exact GP fits in 15 s and the sparse GP (m = 256) in 4 s with a
/// held-out negative log likelihood 1.6 % worse (`precond bench gp --sparse`); beyond a few
/// thousand the exact fit's cubic time dominates a batch's wall time.
pub const AUTO_EXACT_MAX_N: usize = 3000;

impl EstimatorChoice {
    /// The regressor a fit of `n` transitions of dimension `d` uses: for `Auto` the exact GP
    /// while `n ≤ AUTO_EXACT_MAX_N` and its estimated peak memory is within `memory_budget`
    /// bytes, else the sparse GP.
    pub fn kind_for(
        self,
        n: usize,
        d: usize,
        params: &EstimatorParams,
        memory_budget: u64,
    ) -> EstimatorKind {
        match self {
            Self::Exact => EstimatorKind::Exact,
            Self::Sparse => EstimatorKind::Sparse,
            Self::LocalExperts => EstimatorKind::LocalExperts,
            Self::Auto => {
                if n <= AUTO_EXACT_MAX_N
                    && params.cost(EstimatorKind::Exact, n, d).peak_bytes <= memory_budget as f64
                {
                    EstimatorKind::Exact
                } else {
                    EstimatorKind::Sparse
                }
            }
        }
    }
}

/// What [`Regressor::fantasy`] answers: the prediction at its rows after each of several
/// alternative sets of pending rows, in order.
pub type PreparedRows<'a> = Box<dyn Fn(&[DMatrix<f64>]) -> Vec<Prediction> + 'a>;

/// A fitted regressor as the MDE uses it. Inputs are feature rows scaled to the unit box.
pub trait Regressor: Send + Sync + std::fmt::Debug {
    /// Which one it is.
    fn kind(&self) -> EstimatorKind;
    /// Training points it is conditioned on.
    fn n_train(&self) -> usize;
    /// The hyperparameters, where one set answers everywhere (`None`: local experts, each
    /// with its own).
    fn hyperparameters(&self) -> Option<&Hyperparameters>;
    /// The fit's objective: the log marginal likelihood (exact; local experts: the sum of
    /// theirs) or its variational lower bound (sparse).
    fn log_marginal_likelihood(&self) -> f64;
    /// The noise model.
    fn noise_mode(&self) -> NoiseMode;
    /// The heteroscedastic noise model's summary, if there is one.
    fn noise_summary(&self) -> Option<NoiseSummary>;
    /// Batched predictions.
    fn predict(&self, x: &DMatrix<f64>) -> Prediction;
    /// Batched predictions as if the rows of `pending` had been observed too, at the same
    /// hyperparameters and noise (executions not yet fitted): the same mean, and the latent
    /// variance observing them would leave. Choosing the next execution of a batch with it
    /// keeps the batch from chasing one uncertainty.
    fn predict_fantasised(&self, x: &DMatrix<f64>, pending: &DMatrix<f64>) -> Prediction;
    /// [`predict_fantasised`](Self::predict_fantasised) at the rows of `x` for any number of
    /// alternative pending sets, asked in as many calls of the returned function as suit the
    /// caller. Both GPs prepare `x` once for all of them ([`GpModel::fantasy`],
    /// [`SparseGp::fantasy`]); the default asks anew for each set.
    fn fantasy(&self, x: DMatrix<f64>) -> PreparedRows<'_> {
        Box::new(move |pendings| {
            pendings
                .iter()
                .map(|pending| self.predict_fantasised(&x, pending))
                .collect()
        })
    }
    /// The fitted regressor as plain numbers, for evaluation outside the server
    /// ([`ExportedModel`](super::ExportedModel)).
    fn predictor(&self) -> EstimatorPredictor;
    /// `(y_i − μ₋ᵢ, σ₋ᵢ)` of each training point predicted from the others, where the
    /// regressor has it in closed form (`None` otherwise).
    fn leave_one_out(&self) -> Option<Vec<(f64, f64)>>;
    /// The same with each group of rows left out together.
    fn leave_groups_out(&self, groups: &[Vec<usize>]) -> Option<Vec<(f64, f64)>> {
        self.leave_folds_out(&Fold::whole(groups))
    }
    /// The same with each fold's rows left out together and its judged rows predicted
    /// ([`GpModel::leave_folds_out`]).
    fn leave_folds_out(&self, folds: &[Fold]) -> Option<Vec<(f64, f64)>>;
    /// The same regressor conditioned on more points `(x, y)` as well, at the same
    /// hyperparameters (an online update); an error for a regressor that only refits.
    fn update(&self, x: &DMatrix<f64>, y: &DVector<f64>) -> Result<Box<dyn Regressor>, GpError>;
    /// What restores it ([`EstimatorState::restore`]).
    fn state(&self) -> EstimatorState;
    /// Floats it keeps in memory (for the cache of older versions).
    fn floats(&self) -> usize;
    /// Forms what its predictions would otherwise form lazily on the first call (the sparse
    /// GP's variance factor), so the caller pays for it on a thread meant for long work rather
    /// than in the first query. Nothing to do by default.
    fn prepare(&self) {}
}

/// A fitted regressor's stored form, tagged `"estimator"`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "estimator", rename_all = "snake_case")]
pub enum EstimatorState {
    /// The exact GP's hyperparameters and noise model; restoring needs its training data.
    Exact(ModelState),
    /// The sparse GP's inducing points and factors; restoring needs no training data.
    Sparse(Box<SparseState>),
    /// The experts' centres and GP states; restoring needs the training data.
    LocalExperts(ExpertsState),
}

impl EstimatorState {
    /// Which regressor it restores.
    pub fn kind(&self) -> EstimatorKind {
        match self {
            Self::Exact(_) => EstimatorKind::Exact,
            Self::Sparse(_) => EstimatorKind::Sparse,
            Self::LocalExperts(_) => EstimatorKind::LocalExperts,
        }
    }

    /// Whether [`restore`](Self::restore) needs the training data.
    pub fn needs_training_data(&self) -> bool {
        matches!(self, Self::Exact(_) | Self::LocalExperts(_))
    }

    /// The hyperparameters of the stored fit, where one set answers everywhere.
    pub fn hyperparameters(&self) -> Option<&Hyperparameters> {
        match self {
            Self::Exact(s) => Some(&s.hyperparameters),
            Self::Sparse(s) => Some(&s.main.hyperparameters),
            Self::LocalExperts(_) => None,
        }
    }

    /// The noise mode of the stored fit (local experts: heteroscedastic if any expert is).
    pub fn noise(&self) -> NoiseMode {
        match self {
            Self::Exact(s) => s.noise,
            Self::Sparse(s) => s.noise,
            Self::LocalExperts(s) => {
                if s.experts
                    .iter()
                    .all(|e| e.noise == NoiseMode::Homoscedastic)
                {
                    NoiseMode::Homoscedastic
                } else {
                    NoiseMode::Heteroscedastic
                }
            }
        }
    }

    /// The regressor again, without re-optimising: the exact GP refactorised on its training
    /// data `(x, y)` (the stored `n_train` rows), the sparse GP from its factors (`x`, `y`
    /// unused).
    pub fn restore(
        &self,
        x: &DMatrix<f64>,
        y: &DVector<f64>,
    ) -> Result<Box<dyn Regressor>, GpError> {
        Ok(match self {
            Self::Exact(s) => Box::new(GpModel::from_state(x, y, s)?),
            Self::Sparse(s) => Box::new(SparseGp::from_state(s)?),
            Self::LocalExperts(s) => Box::new(LocalExperts::from_state(x, y, s)?),
        })
    }
}

/// With the sparse GP, the kernel and the label cap are chosen on at most this many
/// transitions by default (`mde.selection_subset`, see
/// [`fit_choosing_label_cap`](super::fit_choosing_label_cap)). On 100,000 transitions through
/// the API the choice on 2,000 (five exact fits) took 131 s of a 162 s first fit, on 1,000 it
/// took 44 s of 74 s, with the same kernel, cap and held-out judgement of the fitted model
/// (`docs/measurements/performance.md`, "Through the API").
pub const DEFAULT_SELECTION_SUBSET: usize = 1000;

/// Checked parameters of a fit, for either regressor.
#[derive(Debug, Clone)]
pub struct EstimatorParams {
    gp: ValidGpParams,
    sparse: ValidSparseParams,
    expert_size: usize,
    selection_subset: usize,
}

impl EstimatorParams {
    /// The exact GP's parameters `gp`, and the sparse GP's: the same plus `inducing_points`.
    pub fn new(gp: GpParams, inducing_points: usize) -> Result<Self, GpError> {
        let sparse = SparseParams {
            gp: gp.clone(),
            inducing_points,
            ..SparseParams::default()
        }
        .check()?;
        Ok(Self {
            gp: gp.check()?,
            sparse,
            expert_size: DEFAULT_EXPERT_SIZE,
            selection_subset: DEFAULT_SELECTION_SUBSET,
        })
    }

    /// The same parameters with local experts of about `expert_size` transitions each.
    pub fn with_expert_size(mut self, expert_size: usize) -> Self {
        self.expert_size = expert_size.max(1);
        self
    }

    /// The same parameters choosing the sparse GP's kernel and label cap on at most
    /// `selection_subset` transitions ([`super::fit_choosing_label_cap`]).
    pub fn with_selection_subset(mut self, selection_subset: usize) -> Self {
        self.selection_subset = selection_subset.max(1);
        self
    }

    /// How many transitions, at most, the sparse GP's kernel and label cap are chosen on.
    pub fn selection_subset(&self) -> usize {
        self.selection_subset
    }

    /// The shared GP parameters.
    pub fn gp(&self) -> &GpParams {
        self.gp.params()
    }

    /// The same parameters with `kernel`.
    pub fn with_kernel(&self, kernel: Kernel) -> Result<Self, GpError> {
        Ok(Self::new(
            GpParams {
                kernel,
                ..self.gp.params().clone()
            },
            self.sparse.params().inducing_points,
        )?
        .with_expert_size(self.expert_size)
        .with_selection_subset(self.selection_subset))
    }

    /// The same parameters starting from `warm` (a warm refit; `None`: a new fit).
    pub fn with_warm(&self, warm: Option<WarmStart>) -> Result<Self, GpError> {
        Ok(Self::new(
            GpParams {
                warm,
                ..self.gp.params().clone()
            },
            self.sparse.params().inducing_points,
        )?
        .with_expert_size(self.expert_size)
        .with_selection_subset(self.selection_subset))
    }

    /// The estimated peak memory and work of a fit of `n` points of dimension `d`.
    pub fn cost(&self, kind: EstimatorKind, n: usize, d: usize) -> FitCost {
        let g = self.gp.params();
        match kind {
            EstimatorKind::Exact => exact_fit_cost(n, d, g.restarts, g.noise, g.hetero_rounds),
            EstimatorKind::Sparse => sparse_fit_cost(n, d, self.sparse.params()),
            EstimatorKind::LocalExperts => {
                // Regions of about `expert_size` rows; the smallest are merged, so at worst
                // one region holds twice as many.
                let size = self.expert_size.min(n).max(1);
                let k = n.div_ceil(size).max(1) as f64;
                let cost =
                    |rows: usize| exact_fit_cost(rows, d, g.restarts, g.noise, g.hetero_rounds);
                let (each, largest) = (cost(size), cost((2 * size).min(n)));
                FitCost {
                    peak_bytes: largest.peak_bytes,
                    flops: (each.flops * k).max(largest.flops),
                    seconds: (each.seconds * k).max(largest.seconds),
                }
            }
        }
    }
}

/// Fits a regressor of `kind` on `(x, y)`.
pub fn fit(
    kind: EstimatorKind,
    x: &DMatrix<f64>,
    y: &DVector<f64>,
    params: &EstimatorParams,
) -> Result<Box<dyn Regressor>, GpError> {
    Ok(match kind {
        EstimatorKind::Exact => Box::new(GpModel::fit(x, y, &params.gp)?),
        EstimatorKind::Sparse => Box::new(SparseGp::fit(x, y, &params.sparse)?),
        EstimatorKind::LocalExperts => {
            Box::new(LocalExperts::fit(x, y, &params.gp, params.expert_size)?)
        }
    })
}

/// A fitted estimator as plain numbers, for evaluation outside the server (the exported
/// model's `predictor`): one GP (the exact and the sparse GP), or local experts. Serialised
/// untagged, so a GP's document is the same as before local experts existed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(untagged)]
pub enum EstimatorPredictor {
    /// One GP.
    Gp(Box<Predictor>),
    /// Local experts: the expert of the nearest centre answers.
    Experts(ExpertsPredictor),
}

impl EstimatorPredictor {
    /// Input dimension.
    pub fn dim(&self) -> usize {
        match self {
            Self::Gp(p) => p.dim(),
            Self::Experts(p) => p.dim(),
        }
    }

    /// Checks that the numbers fit together; the error names the field.
    pub fn check(&self) -> Result<(), String> {
        match self {
            Self::Gp(p) => p.check(),
            Self::Experts(p) => p.check(),
        }
    }

    /// The GP answering at features `x` (the one GP, or the expert of the nearest centre).
    pub fn answering(&self, x: &[f64]) -> &Predictor {
        match self {
            Self::Gp(p) => p,
            Self::Experts(p) => p.expert_at(x),
        }
    }

    /// The points the GPs' kernels are evaluated against, over all of them.
    pub fn points(&self) -> usize {
        match self {
            Self::Gp(p) => p.main.points.len(),
            Self::Experts(p) => p.experts.iter().map(|e| e.main.points.len()).sum(),
        }
    }

    /// The prediction at features `x` with reusable buffers.
    pub fn predict_into(&self, x: &[f64], scratch: &mut Scratch) -> PointPrediction {
        self.answering(x).predict_into(x, scratch)
    }
}

/// The [`Regressor`] methods both GPs answer with their inherent method of the same name.
macro_rules! inherent_methods {
    ($gp:ident) => {
        fn n_train(&self) -> usize {
            $gp::n_train(self)
        }
        fn hyperparameters(&self) -> Option<&Hyperparameters> {
            Some($gp::hyperparameters(self))
        }
        fn noise_mode(&self) -> NoiseMode {
            $gp::noise_mode(self)
        }
        fn noise_summary(&self) -> Option<NoiseSummary> {
            $gp::noise_summary(self)
        }
        fn predict(&self, x: &DMatrix<f64>) -> Prediction {
            $gp::predict(self, x)
        }
        fn predict_fantasised(&self, x: &DMatrix<f64>, pending: &DMatrix<f64>) -> Prediction {
            $gp::predict_fantasised(self, x, pending)
        }
        fn predictor(&self) -> EstimatorPredictor {
            EstimatorPredictor::Gp(Box::new($gp::predictor(self)))
        }
        fn fantasy(&self, x: DMatrix<f64>) -> PreparedRows<'_> {
            let prepared = $gp::fantasy(self, x);
            Box::new(move |pendings| prepared.predict_each(pendings))
        }
    };
}

impl Regressor for GpModel {
    inherent_methods!(GpModel);
    fn kind(&self) -> EstimatorKind {
        EstimatorKind::Exact
    }
    fn log_marginal_likelihood(&self) -> f64 {
        GpModel::log_marginal_likelihood(self)
    }
    fn leave_one_out(&self) -> Option<Vec<(f64, f64)>> {
        GpModel::leave_one_out(self)
    }
    fn leave_folds_out(&self, folds: &[Fold]) -> Option<Vec<(f64, f64)>> {
        GpModel::leave_folds_out(self, folds)
    }
    /// The exact GP is refitted after each batch, not updated: an error.
    fn update(&self, _x: &DMatrix<f64>, _y: &DVector<f64>) -> Result<Box<dyn Regressor>, GpError> {
        Err(GpError::InvalidState(
            "the exact GP takes new data by a refit, not an online update".into(),
        ))
    }
    fn state(&self) -> EstimatorState {
        EstimatorState::Exact(GpModel::state(self))
    }
    fn floats(&self) -> usize {
        let n = GpModel::n_train(self);
        n * n
    }
}

impl Regressor for SparseGp {
    inherent_methods!(SparseGp);
    fn kind(&self) -> EstimatorKind {
        EstimatorKind::Sparse
    }
    fn log_marginal_likelihood(&self) -> f64 {
        self.bound()
    }
    fn leave_one_out(&self) -> Option<Vec<(f64, f64)>> {
        None
    }
    fn leave_folds_out(&self, _folds: &[Fold]) -> Option<Vec<(f64, f64)>> {
        None
    }
    fn update(&self, x: &DMatrix<f64>, y: &DVector<f64>) -> Result<Box<dyn Regressor>, GpError> {
        let mut next = self.clone();
        SparseGp::update(&mut next, x, y)?;
        Ok(Box::new(next))
    }
    fn state(&self) -> EstimatorState {
        EstimatorState::Sparse(Box::new(SparseGp::state(self)))
    }
    fn floats(&self) -> usize {
        SparseGp::floats(self)
    }
    fn prepare(&self) {
        SparseGp::prepare(self)
    }
}

impl Regressor for LocalExperts {
    fn kind(&self) -> EstimatorKind {
        EstimatorKind::LocalExperts
    }
    fn n_train(&self) -> usize {
        LocalExperts::n_train(self)
    }
    /// Each expert has its own.
    fn hyperparameters(&self) -> Option<&Hyperparameters> {
        None
    }
    fn log_marginal_likelihood(&self) -> f64 {
        LocalExperts::log_marginal_likelihood(self)
    }
    fn noise_mode(&self) -> NoiseMode {
        LocalExperts::noise_mode(self)
    }
    fn noise_summary(&self) -> Option<NoiseSummary> {
        None
    }
    fn predict(&self, x: &DMatrix<f64>) -> Prediction {
        LocalExperts::predict(self, x)
    }
    fn predict_fantasised(&self, x: &DMatrix<f64>, pending: &DMatrix<f64>) -> Prediction {
        LocalExperts::predict_fantasised(self, x, pending)
    }
    fn predictor(&self) -> EstimatorPredictor {
        EstimatorPredictor::Experts(LocalExperts::predictor(self))
    }
    fn leave_one_out(&self) -> Option<Vec<(f64, f64)>> {
        LocalExperts::leave_one_out(self)
    }
    fn leave_folds_out(&self, folds: &[Fold]) -> Option<Vec<(f64, f64)>> {
        LocalExperts::leave_folds_out(self, folds)
    }
    /// Local experts take new data by a refit: an error.
    fn update(&self, _x: &DMatrix<f64>, _y: &DVector<f64>) -> Result<Box<dyn Regressor>, GpError> {
        Err(GpError::InvalidState(
            "local experts take new data by a refit, not an online update".into(),
        ))
    }
    fn state(&self) -> EstimatorState {
        EstimatorState::LocalExperts(LocalExperts::state(self))
    }
    fn floats(&self) -> usize {
        LocalExperts::floats(self)
    }
}
