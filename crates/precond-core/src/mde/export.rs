//! The exported model ([`ExportedModel`]): one fitted MDE version as a self-contained,
//! versioned document — the domain's feature map, the GP as plain numbers
//! ([`Predictor`](crate::gp::Predictor)) and the precondition's tolerance — that a robot's
//! controller evaluates itself, in microseconds and without a round trip to the server.
//!
//! [`ExportedModel::evaluate`] computes `φ(s, a)` by the [`FeatureMap`] and the GP's `μ` and
//! `σ = √(latent + noise)` from the exported numbers, as `POST /precondition` does: the same
//! features to the bit, `μ` and `σ` to rounding (about 1e-12 relative). The Python client's
//! `precond_client.export` reads the same document with numpy.

use serde::{Deserialize, Serialize};

use super::{Estimator, EstimatorKind, EstimatorPredictor, ServedModel};
use crate::domain::{Domain, FeatureMap};
use crate::gp::export::Scratch as GpScratch;

/// The document's `format`.
pub const EXPORT_FORMAT: &str = "precond-model";

/// The document's `format_version` for a GP (`predictor` holds one GP): 1.
pub const EXPORT_FORMAT_VERSION: u32 = 1;

/// The `format_version` of a document whose `predictor` holds local experts: 2 (a reader of
/// version 1 refuses it rather than misread it).
pub const EXPORT_FORMAT_VERSION_EXPERTS: u32 = 2;

/// One fitted MDE version, exported: everything `μ(s, a)`, `σ(s, a)` and the precondition
/// `μ + βσ < d_max` need.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
pub struct ExportedModel {
    /// Always `precond-model`.
    pub format: String,
    /// The format's version ([`EXPORT_FORMAT_VERSION`], or [`EXPORT_FORMAT_VERSION_EXPERTS`] for
    /// local experts); a reader refuses one it does not know.
    pub format_version: u32,
    /// The experiment the model belongs to.
    pub experiment_id: i64,
    /// The model version exported (1 or more: the prior is not exported).
    pub model_version: i64,
    /// Which regressor the version is.
    pub estimator: EstimatorKind,
    /// Training transitions the version was fitted on.
    pub n_train: usize,
    /// The experiment's deviation tolerance.
    pub d_max: f64,
    /// The test β of this version, the β the server judges with by default: `learning.test_beta`,
    /// or the version's certified β with `learning.calibrate_test_beta`.
    pub test_beta: f64,
    /// Components of a state.
    pub state_dim: usize,
    /// Components of an action.
    pub action_dim: usize,
    /// Names of the features, in order.
    pub feature_names: Vec<String>,
    /// How a state-action becomes the features the GP reads.
    pub feature_map: FeatureMap,
    /// The estimator on deviations and its noise, as plain numbers: one GP (`main`, `noise`),
    /// or local experts (`centres`, `experts`: each a GP; the expert of the nearest centre
    /// answers).
    pub predictor: EstimatorPredictor,
    /// The further model of the experiment's robot whose precondition this is (its feature
    /// map reads *that* model's prediction); absent for the domain's own model's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
}

/// Reusable buffers for [`ExportedModel::evaluate_with`].
#[derive(Debug, Clone, Default)]
pub struct Scratch {
    features: Vec<f64>,
    gp: GpScratch,
}

impl ExportedModel {
    /// The export of `model` of experiment `experiment_id` on `domain`, or `None` for the
    /// prior (which has nothing fitted to export).
    pub fn of(
        experiment_id: i64,
        model: &ServedModel,
        domain: &dyn Domain,
        d_max: f64,
        test_beta: f64,
    ) -> Option<Self> {
        Self::of_estimator(
            experiment_id,
            (model.version, &model.estimator, None),
            domain,
            d_max,
            test_beta,
        )
    }

    /// The export of the further model `further`'s estimator in `model`, or `None` when the
    /// version holds none of it; `test_beta` is the β it is judged at by default.
    pub fn of_further(
        experiment_id: i64,
        model: &ServedModel,
        further: &str,
        domain: &dyn Domain,
        d_max: f64,
        test_beta: f64,
    ) -> Option<Self> {
        let estimator = &model.further(further)?.estimator;
        Self::of_estimator(
            experiment_id,
            (model.version, estimator, Some(further)),
            domain,
            d_max,
            test_beta,
        )
    }

    fn of_estimator(
        experiment_id: i64,
        (version, estimator, further): (i64, &Estimator, Option<&str>),
        domain: &dyn Domain,
        d_max: f64,
        test_beta: f64,
    ) -> Option<Self> {
        let Estimator::Fitted(gp) = estimator else {
            return None;
        };
        let predictor = gp.predictor();
        Some(Self {
            format: EXPORT_FORMAT.to_string(),
            format_version: format_version(&predictor),
            experiment_id,
            model_version: version,
            estimator: gp.kind(),
            n_train: gp.n_train(),
            d_max,
            test_beta,
            state_dim: domain.state_space().dim(),
            action_dim: domain.action_space().dim(),
            feature_names: domain.feature_names(),
            feature_map: domain.feature_map(),
            predictor,
            model: further.map(str::to_string),
        })
    }

    /// Checks the format and that the parts fit together (the feature map reads states and
    /// actions of the stated dimensions and yields the predictor's features), so that
    /// [`evaluate`](Self::evaluate) cannot index out of bounds.
    pub fn check(&self) -> Result<(), String> {
        if self.format != EXPORT_FORMAT {
            return Err(format!(
                "format: {:?} is not {EXPORT_FORMAT:?}",
                self.format
            ));
        }
        if self.format_version != format_version(&self.predictor) {
            return Err(format!(
                "format_version: {} is not supported for this predictor (this reader knows \
                 {EXPORT_FORMAT_VERSION} for one GP, {EXPORT_FORMAT_VERSION_EXPERTS} for local experts)",
                self.format_version
            ));
        }
        if !(self.d_max.is_finite() && self.d_max > 0.0 && self.test_beta.is_finite()) {
            return Err("d_max and test_beta: finite, d_max > 0".into());
        }
        self.feature_map
            .check(self.state_dim, self.action_dim)
            .map_err(|(field, reason)| format!("feature_map.{field}: {reason}"))?;
        if self.feature_map.dim() != self.predictor.dim() {
            return Err(format!(
                "predictor: reads {} features, the feature map makes {}",
                self.predictor.dim(),
                self.feature_map.dim()
            ));
        }
        self.predictor.check().map_err(|e| format!("predictor.{e}"))
    }

    /// `(μ, σ)` at `(s, a)` with reusable buffers (no allocation after the first call);
    /// `s_pred` is the model's prediction `f̂(s, a)`, which the caller supplies when the feature
    /// map reads it ([`uses_prediction`](Self::uses_prediction); ignored otherwise). NaN for a
    /// state, action or needed prediction of the wrong dimension. Like the server's features,
    /// the map does not clamp to the spaces' bounds, but unlike the server (which refuses such
    /// points) it answers outside them too.
    pub fn evaluate_with(
        &self,
        s: &[f64],
        a: &[f64],
        s_pred: &[f64],
        scratch: &mut Scratch,
    ) -> (f64, f64) {
        if s.len() != self.state_dim
            || a.len() != self.action_dim
            || (self.uses_prediction() && s_pred.len() != self.state_dim)
        {
            return (f64::NAN, f64::NAN);
        }
        self.feature_map
            .features_into(s, a, s_pred, &mut scratch.features);
        let p = self
            .predictor
            .predict_into(&scratch.features, &mut scratch.gp);
        (p.mean, p.std())
    }

    /// Whether the features read the model's prediction `f̂(s, a)` (a custom domain's
    /// `features.prediction`): the caller then passes it to [`evaluate_with`](Self::evaluate_with)
    /// or [`evaluate_predicted`](Self::evaluate_predicted), since the model lives with the robot.
    pub fn uses_prediction(&self) -> bool {
        self.feature_map.uses_prediction()
    }

    /// `(μ, σ)` at `(s, a)` for features that do not read the prediction (NaN for those that
    /// do: see [`evaluate_predicted`](Self::evaluate_predicted)).
    pub fn evaluate(&self, s: &[f64], a: &[f64]) -> (f64, f64) {
        self.evaluate_with(s, a, &[], &mut Scratch::default())
    }

    /// `(μ, σ)` at `(s, a)` whose model prediction is `s_pred`.
    pub fn evaluate_predicted(&self, s: &[f64], a: &[f64], s_pred: &[f64]) -> (f64, f64) {
        self.evaluate_with(s, a, s_pred, &mut Scratch::default())
    }

    /// Whether `(s, a)` (model prediction `s_pred`, when the features read it; else `&[]`)
    /// lies in the precondition `μ + βσ < d_max` (false for NaN).
    pub fn inside(&self, s: &[f64], a: &[f64], s_pred: &[f64], beta: f64) -> bool {
        let (mu, sigma) = self.evaluate_with(s, a, s_pred, &mut Scratch::default());
        mu + beta * sigma < self.d_max
    }
}

/// The `format_version` a document with `predictor` carries.
fn format_version(predictor: &EstimatorPredictor) -> u32 {
    match predictor {
        EstimatorPredictor::Gp(_) => EXPORT_FORMAT_VERSION,
        EstimatorPredictor::Experts(_) => EXPORT_FORMAT_VERSION_EXPERTS,
    }
}
