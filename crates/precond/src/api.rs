//! The HTTP API's bodies, typed: every request the server accepts and every response it sends,
//! as the server renders them and as a Rust client (the `precond experiment` harness) reads
//! them. These types define the wire: the schemas of `api/openapi.yaml` are generated from them
//! (`precond openapi`, with the prose and bounds of `api/schemas.yaml`), and a test fails when
//! the document and the types differ.
//!
//! Requests refuse unknown fields (a misspelt option is an error, not a silent default);
//! responses ignore unknown fields when read, so a client keeps working when the server adds
//! one.

use crate::domain::{Space, Transition};
use crate::gp::{Hyperparameters, NoiseMode, NoiseSummary};
use crate::mde::{BetaChoice, EstimatorKind, HeldOutTrust, KernelTrial, SelectionRecord};
use crate::planning::Strategy;
use crate::records::{IterationStats, ListOrder, ModelSummary, ProposalStatus, ProposalTerms};
use crate::settings::ExperimentSettings;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::Value;

pub use crate::mde::Judgement;
/// A fit the server did not attempt because its estimated peak memory exceeded the budget, as
/// stored.
pub use crate::records::FitRefusal as FitRefusalView;
/// Where a posted trajectory comes from, as posted, stored and shown.
pub use crate::records::Provenance as TrajectorySource;
/// A stored transition with its prediction and label.
pub use crate::records::StoredTransition as TransitionView;
/// A run as listed.
pub use crate::records::{Run as RunView, RunStatus};
pub use crate::settings::ExperimentRequest;

/// `GET /healthz` and `GET /readyz`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct HealthResponse {
    /// `ok` (alive) or `ready` (the database answers).
    pub status: String,
}

/// A state or action space as clients see it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct SpaceView {
    /// Component names.
    pub names: Vec<String>,
    /// Lower bounds.
    pub low: Vec<f64>,
    /// Upper bounds.
    pub high: Vec<f64>,
    /// Allowed values of a discrete space.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub values: Option<Vec<Vec<f64>>>,
}

impl From<&Space> for SpaceView {
    fn from(s: &Space) -> Self {
        Self {
            names: s.names.clone(),
            low: s.low.clone(),
            high: s.high.clone(),
            values: s.values.clone(),
        }
    }
}

/// An experiment with its resolved settings, spaces and progress (`POST /v1/experiments`,
/// `GET /v1/experiments/{id}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ExperimentResponse {
    /// Identifier.
    pub id: i64,
    /// The fully resolved settings (`name`, `domain`, `d_max`, `seed`, `mde`, `learning`).
    #[serde(flatten)]
    pub settings: ExperimentSettings,
    /// The state space: what `s` and `s_next` must look like.
    pub state_space: SpaceView,
    /// The action space: what `a` must look like.
    pub action_space: SpaceView,
    /// Names of the MDE's feature components.
    pub feature_names: Vec<String>,
    /// Creation time (RFC 3339).
    pub created_at: String,
    /// Executed trajectories stored.
    pub n_trajectories: i64,
    /// Transitions stored.
    pub n_transitions: i64,
    /// Current learning iteration (completed batches).
    pub iteration: i64,
    /// The latest MDE version (0: the prior).
    pub model_version: i64,
    /// Proposal requests refused (`no_plan`, or past the planning deadline; each is a `refused` run).
    #[serde(default)]
    pub n_refused: i64,
    /// The latest of its creation, its last trajectory, its last proposal and its last refused
    /// proposal request (RFC 3339).
    #[serde(default)]
    pub last_activity: String,
}

/// Query of `GET /v1/experiments`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ExperimentsQuery {
    /// `oldest` (ascending id, the default) or `newest` first.
    #[serde(default)]
    pub order: ListOrder,
    /// Experiments to skip. Default 0.
    #[serde(default)]
    pub offset: i64,
    /// Page size, 1 to 1000; every experiment when absent.
    pub limit: Option<i64>,
}

/// `GET /v1/experiments`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ExperimentList {
    /// The page's experiments, in the order asked (every experiment, oldest first, by default).
    pub items: Vec<ExperimentResponse>,
    /// Experiments stored in all.
    #[serde(default)]
    pub total: i64,
    /// The `offset` of the next page, or `null` on the last.
    #[serde(default)]
    pub next: Option<i64>,
}

/// Query of the offset-paginated lists (`GET …/runs`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PageQuery {
    /// Rows to skip. Default 0.
    #[serde(default)]
    pub offset: i64,
    /// Page size, 1 to 1000; default 100.
    pub limit: Option<i64>,
}

/// `GET /v1/experiments/{id}/runs`: proposals with the trajectories that executed them,
/// trajectories posted without a proposal and refused proposal requests, newest first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct RunPage {
    /// The page's runs.
    pub items: Vec<RunView>,
    /// Runs in all.
    pub total: i64,
    /// The `offset` of the next page, or `null` on the last.
    pub next: Option<i64>,
}

/// One learning iteration of `GET /v1/experiments/{id}/timeline`: what was executed in it and
/// how many proposal requests it refused.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct TimelineIteration {
    /// `β_j` of the learning schedule at this iteration.
    pub beta: f64,
    /// Its statistics, as the store counts them.
    #[serde(flatten)]
    pub stats: IterationStats,
}

/// One model version of `GET /v1/experiments/{id}/timeline` (no training data, no noise
/// model).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct TimelineModel {
    /// The learning iteration its training data reached (`n_trajectories / batch_size`).
    pub iteration: i64,
    /// The version, as stored.
    #[serde(flatten)]
    pub model: ModelSummary,
}

/// `GET /v1/experiments/{id}/labels`: each of the experiment's models of its robot with what
/// its labels of the executed transitions say — where each model was right, from the same
/// executions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ModelLabels {
    /// The experiment.
    pub experiment_id: i64,
    /// The experiment's tolerance.
    pub d_max: f64,
    /// The domain's own model (`domain`) first, then the further models in their order.
    pub items: Vec<ModelLabelStats>,
}

/// One model's labels of an experiment's executed transitions, summed up.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ModelLabelStats {
    /// The model's name; `domain` for the domain's own.
    pub model: String,
    /// Its cost per call, in calls of the domain's model (1 for the domain's).
    pub cost: f64,
    /// Where it lives: `remote`, `linear`, `client` or `built_in`.
    pub kind: String,
    /// Transitions it labelled.
    pub n_labelled: i64,
    /// Transitions whose label it left missing (it could not answer).
    pub n_missing: i64,
    /// Mean deviation label (`null` without labels).
    pub mean_deviation: Option<f64>,
    /// Largest deviation label (`null` without labels).
    pub max_deviation: Option<f64>,
    /// Share of its labels below `d_max`: how often it was right (`null` without labels).
    pub share_within_d_max: Option<f64>,
}

/// `GET /v1/experiments/{id}/timeline`: how learning went, iteration by iteration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Timeline {
    /// Its experiment.
    pub experiment_id: i64,
    /// Trajectories per iteration (`learning.batch_size`).
    pub batch_size: i64,
    /// Planned iterations `J` of the β schedule (`learning.iterations`).
    pub iterations_planned: i64,
    /// Iterations with executed trajectories, in order (at most 10 000).
    pub iterations: Vec<TimelineIteration>,
    /// Fitted model versions, oldest first (at most 10 000).
    pub models: Vec<TimelineModel>,
    /// Fits refused for the memory budget, oldest first (at most 10 000).
    pub fit_refusals: Vec<FitRefusalView>,
}

/// Query of `GET /v1/experiments/{id}/precondition/map`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MapQuery {
    /// The horizontal axis: a state component `s.<name>` or an action component `a.<name>`.
    pub x: String,
    /// The vertical axis, likewise; not the same as `x`.
    pub y: String,
    /// The state fixing the other components, comma-separated; default the state box's centre.
    pub s: Option<String>,
    /// The action fixing the other components; default the first allowed value of a discrete
    /// action space, else the action box's centre.
    pub a: Option<String>,
    /// Grid points along `x`, 2 to 200; default 41.
    pub nx: Option<usize>,
    /// Grid points along `y`, 2 to 200; default 41.
    pub ny: Option<usize>,
    /// The model version to evaluate; default the one answering now.
    pub version: Option<i64>,
    /// Whose precondition: a further model's name (see the experiment's `models`); default
    /// (or `domain`) the domain's own model's.
    pub model: Option<String>,
}

/// One axis of a precondition map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct MapAxis {
    /// `s.<name>` or `a.<name>`.
    pub name: String,
    /// The grid's coordinates along it: evenly spaced from the component's lower to its upper
    /// bound, both included.
    pub values: Vec<f64>,
}

/// A training transition drawn on a map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct MapPoint {
    /// State.
    pub s: Vec<f64>,
    /// Action.
    pub a: Vec<f64>,
    /// Its deviation label.
    pub deviation: f64,
}

/// `GET /v1/experiments/{id}/precondition/map`: `μ` and `σ` of a model version on a grid over
/// two components of `(s, a)`, the others fixed; the precondition at any β is
/// `μ + βσ < d_max`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct PreconditionMap {
    /// The version evaluated.
    pub model_version: i64,
    /// Prior or fit.
    pub source: ModelSource,
    /// Its training transitions (the experiment's first `n_train`).
    pub n_train: usize,
    /// The experiment's tolerance.
    pub d_max: f64,
    /// The test β of the answering version (`learning.test_beta`, or the version's certified β
    /// with `learning.calibrate_test_beta`).
    pub test_beta: f64,
    /// The state fixing the components not on an axis.
    pub s: Vec<f64>,
    /// The action fixing the components not on an axis.
    pub a: Vec<f64>,
    /// The horizontal axis.
    pub x: MapAxis,
    /// The vertical axis.
    pub y: MapAxis,
    /// `μ` row-major: `mu[j * nx + i]` at `(x.values[i], y.values[j])`.
    pub mu: Vec<f64>,
    /// `σ` (noise included), laid out as `mu`.
    pub sigma: Vec<f64>,
    /// The version's training transitions, at most 2000 evenly spread over them (with a
    /// further model's map, those it labelled, with its labels).
    pub training: Vec<MapPoint>,
    /// The further model whose precondition this is; absent for the domain's own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
}

/// Query of `GET /v1/experiments/{id}/model/diagnostics`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DiagnosticsQuery {
    /// The model version to check; default the one answering now.
    pub version: Option<i64>,
    /// β of the precondition whose rates are reported; default the version's test β.
    pub beta: Option<f64>,
}

/// Query of `GET /v1/experiments/{id}/model/export`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ExportQuery {
    /// The model version to export (1 or more); default the one answering now.
    pub version: Option<i64>,
    /// Whose estimator: one of the experiment's further models by name, or `domain` (the
    /// default) for the domain's own model's.
    pub model: Option<String>,
}

/// `GET /v1/experiments/{id}/model/export`: a fitted version as a self-contained, versioned
/// document (`format: precond-model`, `format_version: 1`) — the same document a controller
/// saves and evaluates (`precond::mde::ExportedModel::evaluate`, the Python client's
/// `ExportedModel.evaluate`).
pub type ModelExport = crate::mde::ExportedModel;

/// The share of labels inside `μ ± zσ` against the nominal Gaussian share.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Coverage {
    /// The interval's half-width in σ.
    pub z: f64,
    /// `P(|N(0,1)| ≤ z)`.
    pub nominal: f64,
    /// The observed share.
    pub observed: f64,
}

/// How often the precondition agrees with the labels' truth `y < d_max`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct PreconditionRates {
    /// β used.
    pub beta: f64,
    /// The experiment's tolerance.
    pub d_max: f64,
    /// Labels below `d_max` (the model was right).
    pub positives: usize,
    /// Labels at or above `d_max`.
    pub negatives: usize,
    /// Positives judged inside the precondition.
    pub true_positives: usize,
    /// Negatives judged outside.
    pub true_negatives: usize,
    /// `true_positives / positives` (`null` without positives).
    pub tpr: Option<f64>,
    /// `true_negatives / negatives` (`null` without negatives).
    pub tnr: Option<f64>,
}

/// `GET /v1/experiments/{id}/model/diagnostics`: leave-one-out calibration of a fitted model
/// version and the rates of its precondition on its own training labels, each predicted by the
/// model conditioned on every other label.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Diagnostics {
    /// Its experiment.
    pub experiment_id: i64,
    /// The version checked.
    pub model_version: i64,
    /// `leave_one_out`.
    pub method: String,
    /// Labels checked (the version's training set).
    pub n: usize,
    /// Root mean squared leave-one-out error.
    pub rmse: f64,
    /// Mean leave-one-out log predictive density (Gaussian; higher is better).
    pub mean_log_density: f64,
    /// Observed against nominal shares for `z` = 0.5, 1, 1.5, 2, 2.5, 3.
    pub coverage: Vec<Coverage>,
    /// The precondition's true-positive and true-negative rates (leave-one-out).
    pub precondition: PreconditionRates,
    /// The same rates on the transitions posted after the version's training set (never seen
    /// by it; at most the first 10 000), judged by the version itself; `null` when there are
    /// none yet.
    pub later: Option<LaterRates>,
}

/// The precondition's rates on transitions a version never saw.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct LaterRates {
    /// Transitions judged.
    pub n: usize,
    /// Observed against nominal coverage of `μ ± zσ` on them.
    pub coverage: Vec<Coverage>,
    /// The rates.
    #[serde(flatten)]
    pub rates: PreconditionRates,
}

/// `POST /v1/experiments/{id}/trajectories` body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TrajectoryRequest {
    /// The proposal this trajectory executed; closes its lease.
    #[serde(default)]
    pub proposal_id: Option<i64>,
    /// The robot stopped before the end of what it meant to execute.
    #[serde(default)]
    pub partial: bool,
    /// Where it comes from (an imported log, a simulated environment).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<TrajectorySource>,
    /// The executed transitions, in order.
    #[schemars(length(min = 1, max = crate::limits::MAX_TRANSITIONS))]
    pub transitions: Vec<Transition>,
}

/// What every answer about one stored trajectory starts with: which it is, what it executed and
/// where it comes from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct TrajectoryHeader {
    /// Identifier of the stored trajectory.
    pub id: i64,
    /// Its experiment.
    pub experiment_id: i64,
    /// The proposal it executed, if any.
    pub proposal_id: Option<i64>,
    /// Whether the robot stopped before the end.
    pub partial: bool,
    /// Whether it departs from its proposal (other actions, longer, or another start; a
    /// prefix does not).
    #[serde(default)]
    pub deviating: bool,
    /// Where it comes from, when the client said.
    #[serde(default)]
    pub source: Option<TrajectorySource>,
}

/// `201` answer to a posted trajectory (replayed as it was for a retry with the same
/// `Idempotency-Key`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct TrajectoryCreated {
    /// The stored trajectory.
    #[serde(flatten)]
    pub trajectory: TrajectoryHeader,
    /// Transitions stored.
    pub n_transitions: usize,
    /// Each transition's deviation label `d(f̂(s, a), s_next)`, in order.
    pub deviations: Vec<f64>,
    /// Learning iteration after this trajectory.
    pub iteration: i64,
    /// The MDE version answering when it was stored.
    pub model_version: i64,
    /// Trajectories of the experiment, this one included.
    pub n_trajectories: i64,
    /// Ingest time (RFC 3339).
    pub created_at: String,
}

/// `GET /v1/experiments/{id}/trajectories/{tid}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct TrajectoryResponse {
    /// Which trajectory it is.
    #[serde(flatten)]
    pub trajectory: TrajectoryHeader,
    /// Ingest time (RFC 3339).
    pub created_at: String,
    /// Its transitions in order, with their predictions and labels.
    pub transitions: Vec<TransitionView>,
    /// Transitions stored.
    pub n_transitions: usize,
}

/// Query of `GET /v1/experiments/{id}/transitions`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TransitionsQuery {
    /// Return transitions with an id greater than this cursor. Default 0.
    #[serde(default)]
    pub after: i64,
    /// Page size: default 100 and at most 1000 for JSON; unlimited by default for CSV.
    pub limit: Option<i64>,
}

/// The format of an imported file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ImportFormat {
    /// Comma-separated values with a header row.
    Csv,
    /// Apache Parquet.
    Parquet,
}

/// Query of `POST /v1/experiments/{id}/imports` (the file is the body).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ImportQuery {
    /// The dataset's name, stored in every trajectory's `source.dataset`; with the episode it
    /// keys each trajectory, so importing the same dataset again stores nothing twice.
    #[schemars(length(min = 1, max = crate::limits::MAX_SOURCE_TEXT_LEN))]
    pub dataset: String,
    /// The dataset's identity in the keys instead of the SHA-256 of its name (letters, digits,
    /// `.`, `_`, `-`; at most 64).
    pub dataset_id: Option<String>,
    /// The file's format; default from `Content-Type` (`text/csv`,
    /// `application/vnd.apache.parquet`).
    pub format: Option<ImportFormat>,
    /// A label stored with every trajectory's source.
    #[schemars(length(max = crate::limits::MAX_SOURCE_TEXT_LEN))]
    pub label: Option<String>,
    /// The state's columns, comma-separated in the state's order, or one list column.
    pub state: Option<String>,
    /// The action's columns, likewise.
    pub action: Option<String>,
    /// The next state's columns; without them the next row's state within the episode.
    pub next_state: Option<String>,
    /// The client's predicted next state (an experiment whose model is the client's).
    pub predicted_state: Option<String>,
    /// The episode column (`none`: the whole file is one episode).
    pub episode: Option<String>,
    /// Transitions per stored trajectory, when fewer than the server's `--max-transitions`:
    /// a longer episode is stored as several trajectories (as `precond import
    /// --max-transitions`).
    #[schemars(range(min = 1, max = crate::limits::MAX_TRANSITIONS))]
    pub max_transitions: Option<usize>,
}

/// A page of `GET /v1/experiments/{id}/transitions`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct TransitionPage {
    /// Transitions in id order.
    pub items: Vec<TransitionView>,
    /// Cursor of the next page (`after=`), or `null` on the last.
    pub next: Option<i64>,
}

/// Whether a model version was fitted or is the prior.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ModelSource {
    /// No data yet: μ = prior mean, σ = prior standard deviation everywhere.
    Prior,
    /// A GP fitted on stored transitions.
    Fit,
}

/// `GET /v1/experiments/{id}/model` and `POST .../model/refit`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ModelResponse {
    /// Its experiment.
    pub experiment_id: i64,
    /// Version (0: the prior).
    pub version: i64,
    /// Prior or fit.
    pub source: ModelSource,
    /// Training transitions.
    pub n_train: usize,
    /// Noise mode of the fit (`null` for the prior).
    pub noise: Option<NoiseMode>,
    /// Names of the feature components, in the order of `length_scales`.
    pub feature_names: Vec<String>,
    /// Hyperparameters (length scales in the unit-box feature space); `null` for local
    /// experts, each of which has its own (see the export).
    pub hyperparameters: Option<Hyperparameters>,
    /// The heteroscedastic noise model's summary, when there is one.
    pub noise_model: Option<NoiseSummary>,
    /// Log marginal likelihood of the fit.
    pub log_marginal_likelihood: Option<f64>,
    /// Seconds the fit took.
    pub fit_seconds: Option<f64>,
    /// When the fit finished (RFC 3339).
    pub fitted_at: Option<String>,
    /// Trajectories the fit covers.
    pub n_trajectories: i64,
    /// The label cap the fit clipped deviations at (units of `d_max`; 0 = raw labels; `null`
    /// for the prior).
    pub label_cap: Option<f64>,
    /// Each candidate cap's model judging its own training transitions, each state-action held
    /// out in turn with all its copies (trust at `learning.test_beta`, and the log probability
    /// given to the right side of `d_max`): with `mde.label_cap: "auto"` the fit keeps the best-scoring one, but replaces
    /// raw labels only when a cap scores clearly better (see
    /// [`crate::mde::fit_choosing_label_cap`]).
    pub label_cap_trials: Vec<HeldOutTrust>,
    /// The regressor of the fit: `exact` (the exact GP) or `sparse` (the sparse GP; `null` for
    /// the prior).
    pub estimator: Option<EstimatorKind>,
    /// Trajectories taken in since the fit by online updates at its hyperparameters (the
    /// sparse GP takes each posted trajectory in at once; the exact GP waits for its batch's
    /// refit, so 0).
    pub online_trajectories: usize,
    /// The latest fit refused since this version because it would not fit the server's memory
    /// budget (`null` if none): this version kept answering.
    pub last_fit_refusal: Option<FitRefusalView>,
    /// With `mde.kernel: "auto"`, every candidate kernel's fit on the first candidate cap's
    /// labels; the one with the highest log marginal likelihood was kept unless another was
    /// clearly better held out (empty otherwise).
    pub kernel_trials: Vec<KernelTrial>,
    /// The test β the fit's judgement of its own training transitions, each executed trajectory
    /// held out whole with every copy of its state-actions, certifies: the smallest β (grid of 0.1, at most
    /// `learning.test_beta`) at which at most 2 % of the unsafe ones are trusted, estimated as
    /// `(trusted unsafe + 1) / (unsafe + 2)`; `learning.test_beta` when none smaller is
    /// certified (`null` for the prior, where it could not be computed, and for versions
    /// fitted before it was recorded).
    pub beta_choice: Option<BetaChoice>,
    /// The β test plans and the precondition's default judgements use with this version:
    /// `beta_choice.beta` with `learning.calibrate_test_beta`, else `learning.test_beta`.
    pub test_beta: f64,
    /// How this version's kernel and label cap were chosen — anew, or kept from an earlier
    /// version by a warm refit (`mde.reselect_every`) — and what its fit spent its time on;
    /// `null` for the prior and for versions fitted before it was recorded.
    pub selection: Option<SelectionRecord>,
    /// The exclusions in effect when this version was fitted (ids, ascending; see
    /// `…/exclusions`): it was fitted on the first `n_train` transitions outside the
    /// trajectories they cover. Empty for the prior and a version fitted without any.
    pub exclusions: Vec<i64>,
}

/// `POST /v1/experiments/{id}/exclusions`: leave one trajectory, or every trajectory stored in a
/// time range, out of the experiment's model. Give `trajectory_id`, or `from` and `to`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ExclusionRequest {
    /// The trajectory to leave out.
    #[serde(default)]
    pub trajectory_id: Option<i64>,
    /// The first ingest time the range covers (RFC 3339, inclusive).
    #[serde(default)]
    pub since: Option<String>,
    /// The end of the range (RFC 3339, exclusive). A range covers the trajectories stored
    /// when the exclusion is made, never one stored later.
    #[serde(default)]
    pub until: Option<String>,
    /// Why (1 to 1000 characters), kept with the exclusion and shown with it.
    #[schemars(length(min = 1, max = crate::limits::MAX_SOURCE_TEXT_LEN))]
    pub reason: String,
}

/// Whether an exclusion keeps its trajectories out of the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ExclusionStatus {
    /// Made and not restored: the next fit (and every one after) leaves its trajectories out.
    InEffect,
    /// Restored: the next fit takes its trajectories in again.
    Restored,
}

/// An exclusion: what it covers, why, who made it and when, and whether it was restored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ExclusionView {
    /// Identifier (ascending in the order exclusions were made).
    pub id: i64,
    /// Its experiment.
    pub experiment_id: i64,
    /// In effect or restored.
    pub status: ExclusionStatus,
    /// The trajectory it names (`null` for a time range).
    pub trajectory_id: Option<i64>,
    /// The range's first instant (`null` for one trajectory).
    pub since: Option<String>,
    /// The range's end, exclusive (`null` for one trajectory).
    pub until: Option<String>,
    /// Why it was made.
    pub reason: String,
    /// The trajectories it covers, ascending (resolved when it was made).
    pub trajectory_ids: Vec<i64>,
    /// Their transitions.
    pub n_transitions: i64,
    /// When it was made (RFC 3339).
    pub created_at: String,
    /// Who made it: the first 12 hex digits of the SHA-256 of the caller's access token
    /// (`printf %s "$TOKEN" | sha256sum | cut -c1-12`); `null` on a server without tokens.
    pub created_by: Option<String>,
    /// When it was restored (`null` while in effect).
    pub restored_at: Option<String>,
    /// Who restored it, as `created_by`.
    pub restored_by: Option<String>,
    /// Whether the model answering now was fitted under this exclusion as it stands: `false`
    /// until the refit its making (or restoring) requested is swapped in.
    pub applied: bool,
}

/// `GET /v1/experiments/{id}/exclusions`: an experiment's exclusions, newest first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ExclusionPage {
    /// The page's exclusions.
    pub items: Vec<ExclusionView>,
    /// Exclusions in all.
    pub total: i64,
    /// The `offset` of the next page, or `null` on the last.
    pub next: Option<i64>,
}

/// One state-action to judge.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Point {
    /// State.
    pub s: Vec<f64>,
    /// Action.
    pub a: Vec<f64>,
    /// The model's prediction `f̂(s, a)`: required only when the experiment's features read
    /// it and its model is the client's (the service asks any other model itself); refused
    /// otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub s_pred: Option<Vec<f64>>,
}

/// `POST /v1/experiments/{id}/precondition` body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PreconditionRequest {
    /// The state-actions to judge.
    #[schemars(length(min = 1, max = crate::limits::MAX_POINTS))]
    pub points: Vec<Point>,
    /// Confidence multiplier β; default: the version's test β (`learning.test_beta`, or its
    /// certified β; for a further model, `learning.test_beta`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub beta: Option<f64>,
    /// Whose precondition: one of the experiment's further models by name, or `domain` (the
    /// default) for the domain's own model.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
}

/// Query of `GET /v1/experiments/{id}/precondition`: one point, comma-separated.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PointQuery {
    /// State, e.g. `s=3,2`.
    pub s: String,
    /// Action, e.g. `a=1,0`.
    pub a: String,
    /// The client-side model's prediction, e.g. `s_pred=4,2` (see [`Point::s_pred`]).
    pub s_pred: Option<String>,
    /// β; default the version's test β (`learning.test_beta`, or its certified β).
    pub beta: Option<f64>,
    /// Whose precondition (see [`PreconditionRequest::model`]).
    pub model: Option<String>,
}

/// The answer to a precondition query.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct PreconditionResponse {
    /// The MDE version that answered.
    pub model_version: i64,
    /// Prior or fit.
    pub source: ModelSource,
    /// β used.
    pub beta: f64,
    /// The experiment's tolerance.
    pub d_max: f64,
    /// One judgement per point, in order.
    pub results: Vec<Judgement>,
    /// The further model whose precondition this is; absent for the domain's own model's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    /// The state of a `GET` query.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub s: Option<Vec<f64>>,
    /// The action of a `GET` query.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub a: Option<Vec<f64>>,
}

/// `POST /v1/experiments/{id}/proposals` body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ProposalRequest {
    /// Start state.
    pub start: Vec<f64>,
    /// Goal (the domain's goal vector: a cell, a state, a target volume).
    pub goal: Vec<f64>,
    /// The client the proposal is leased to; asking again while it is open returns it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = crate::limits::MAX_CLIENT_ID_LEN))]
    pub client_id: Option<String>,
    /// Overrides the experiment's strategy for this proposal.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strategy: Option<Strategy>,
    /// The client's own candidate trajectories: the service scores them instead of planning
    /// (required when the experiment's model is the client's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = crate::limits::MAX_CLIENT_CANDIDATES))]
    pub candidates: Option<Vec<CandidateTrajectory>>,
    /// The models the service's candidates may step with, by name (`"domain"` for the
    /// domain's own), each step relying on the cheapest whose precondition trusts it, as in a
    /// plan; under `spread` the candidates are then valued by what their execution teaches
    /// every named model's precondition (every posted transition labels them all). Omitted:
    /// the domain's model alone, as in a single-model experiment (the other models learn from
    /// the same executions). Not with `candidates`, nor with the `random` strategy (a rollout
    /// steps with the domain's model alone).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = crate::settings::models::MAX_MODELS + 1), inner(length(min = 1, max = crate::settings::models::MAX_MODEL_NAME_LEN)))]
    pub models: Option<Vec<String>>,
}

/// `POST /v1/experiments/{id}/proposals/{pid}/continue` body: the part of an open proposal
/// the robot executed before it re-plans from where it actually is.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ContinueRequest {
    /// The executed transitions, from the proposal's start; the last `s_next` is where the
    /// robot is now, the start of the proposal that continues it.
    #[schemars(length(min = 1, max = crate::limits::MAX_TRANSITIONS))]
    pub transitions: Vec<Transition>,
    /// With a client-side model: the trajectories the client planned from where the robot is
    /// (see [`ProposalRequest::candidates`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = crate::limits::MAX_CLIENT_CANDIDATES))]
    pub candidates: Option<Vec<CandidateTrajectory>>,
}

/// `201` answer to a continued proposal: the executed prefix, stored (a partial trajectory of
/// the proposal), and the new proposal from where the robot is to the same goal, leased to the
/// same client.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ContinueResponse {
    /// The stored prefix.
    pub trajectory: TrajectoryCreated,
    /// The proposal that continues it.
    pub proposal: ProposalResponse,
}

/// A trajectory the client planned: its predicted states (starting with the start state) and
/// the actions between them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct CandidateTrajectory {
    /// Predicted states `s_0 = start, s_1, …`; one more than `actions`.
    pub states: Vec<Vec<f64>>,
    /// Actions.
    pub actions: Vec<Vec<f64>>,
}

/// A planned trajectory with the MDE's answer at each step (and, for proposals, the
/// acquisition).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct PlannedTrajectory {
    /// Predicted states `s_0 = start, s_{t+1} = f̂(s_t, a_t)`; one more than `actions`.
    pub states: Vec<Vec<f64>>,
    /// Actions.
    pub actions: Vec<Vec<f64>>,
    /// `μ` per action.
    pub mu: Vec<f64>,
    /// `σ` per action (noise included).
    pub sigma: Vec<f64>,
    /// `α_step = μ − cσ` per action (proposals only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_step: Option<Vec<f64>>,
    /// The trajectory's acquisition value `α` (proposals only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha: Option<f64>,
}

/// A scored candidate of a proposal or plan. Candidates the service planned itself lie inside
/// the precondition and reach the goal by construction and carry `alpha` and `length` only; a
/// client's candidates also carry their verdict and per-step answers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct CandidateView {
    /// Its acquisition value `α` (the aggregated `α_step = μ − cσ`).
    pub alpha: f64,
    /// Its number of actions.
    pub length: usize,
    /// Whether every step lies in the precondition at the β used.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inside: Option<bool>,
    /// The first step outside the precondition (`null` when inside).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first_outside: Option<usize>,
    /// Whether its last state satisfies the goal test.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reaches_goal: Option<bool>,
    /// `μ` per step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mu: Option<Vec<f64>>,
    /// `σ` per step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma: Option<Vec<f64>>,
}

impl CandidateView {
    /// A candidate the service planned itself.
    pub fn planned(alpha: f64, length: usize) -> Self {
        Self {
            alpha,
            length,
            inside: None,
            first_outside: None,
            reaches_goal: None,
            mu: None,
            sigma: None,
        }
    }

    /// A client's candidate with its verdict.
    pub fn judged(v: &crate::planning::Verdict) -> Self {
        Self {
            alpha: v.alpha,
            length: v.trajectory.len(),
            inside: Some(v.inside),
            first_outside: v.first_outside,
            reaches_goal: Some(v.reaches_goal),
            mu: Some(v.trajectory.mu.clone()),
            sigma: Some(v.trajectory.sigma.clone()),
        }
    }
}

/// What a proposal chose and from what: stored with the proposal exactly as shown.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ProposalContent {
    /// The trajectory to execute.
    pub trajectory: PlannedTrajectory,
    /// Every candidate, in the order found.
    pub candidates: Vec<CandidateView>,
    /// Index of the chosen one in `candidates`.
    pub chosen_index: usize,
    /// RRT extensions spent (for `random`, actions tried), over every β tried.
    pub extensions: usize,
    /// The iteration's `β_j`, present when no trajectory reached the goal inside the
    /// precondition at it and the proposal's `beta` is a lower one (`learning.relax_beta`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relaxed_from_beta: Option<f64>,
    /// The acquisition whose `α` the candidates were compared by — the service's own candidates
    /// and a client's alike: the experiment's `learning.acquisition`, or `lcb` where a
    /// value-based one (`bottleneck`, `spread`) valued no candidate above 0 (no graph to
    /// value on, the budget spent, nothing to gain) or the strategy is not `active`. Absent for
    /// proposals stored before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub valued_by: Option<crate::planning::AcquisitionKind>,
    /// The models the candidates stepped with (cheapest first), present when the request named
    /// more than the domain's model; a continuation of it steps with the same.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub models: Option<Vec<String>>,
    /// The model each step of the trajectory relied on, present with `models`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_models: Option<Vec<String>>,
}

/// A proposal (`POST /proposals`, `GET /proposals/{pid}`, `POST .../abandon`): its lease,
/// the terms it answered under, and what it chose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ProposalResponse {
    /// Identifier.
    pub id: i64,
    /// Where its lease stands: `open`, `executed`, `abandoned` or `expired`.
    pub status: ProposalStatus,
    /// Whether the trajectory that executed it departs from it (other actions, longer, or
    /// another start; a prefix does not); `false` until executed.
    #[serde(default)]
    pub deviating: bool,
    /// The problem, the client it is leased to and the learning state that shaped it.
    #[serde(flatten)]
    pub terms: ProposalTerms,
    /// Creation time (RFC 3339).
    pub created_at: String,
    /// End of the lease (RFC 3339).
    pub expires_at: String,
    /// The chosen trajectory and the candidates.
    #[serde(flatten)]
    pub content: ProposalContent,
}

/// `POST /v1/experiments/{id}/plans` body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PlanRequest {
    /// Start state.
    pub start: Vec<f64>,
    /// Goal.
    pub goal: Vec<f64>,
    /// β; default the version's test β (`learning.test_beta`, or its certified β).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub beta: Option<f64>,
    /// The client's own candidate trajectories: the plan is the one with the smallest `α` among
    /// those inside the precondition that reach the goal (required when the experiment's model
    /// is the client's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = crate::limits::MAX_CLIENT_CANDIDATES))]
    pub candidates: Option<Vec<CandidateTrajectory>>,
    /// The search's extension budget for this plan, 1 to 200 000; default
    /// `learning.max_extensions`. A longer search tells "no plan inside the precondition" from
    /// "none found in time"; it still ends at the planning deadline. Not with `candidates`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 1, max = crate::limits::MAX_EXTENSIONS))]
    pub max_extensions: Option<u32>,
    /// The models the search may step with, by name (`domain` for the domain's own), each step
    /// relying on the cheapest whose precondition trusts it; default every model of the
    /// experiment with an estimator in the answering version. Not with `candidates`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = crate::settings::models::MAX_MODELS + 1), inner(length(min = 1, max = crate::settings::models::MAX_MODEL_NAME_LEN)))]
    pub models: Option<Vec<String>>,
}

/// What a plan's search spent on one model: its calls and their cost.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ModelCalls {
    /// The model's name (`domain` for the domain's own).
    pub model: String,
    /// Calls the search made to it (each with a batch of state-actions).
    pub calls: usize,
    /// What one call costs, in calls of the domain's own model.
    pub cost: f64,
}

/// A test-time plan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct PlanResponse {
    /// Whether a plan was found within the extension budget.
    pub found: bool,
    /// Extensions spent.
    pub extensions: usize,
    /// Why extensions added nothing to the search tree (0 for the client's candidates).
    pub rejections: RejectionCounts,
    /// β used.
    pub beta: f64,
    /// The experiment's tolerance.
    pub d_max: f64,
    /// The MDE version that answered.
    pub model_version: i64,
    /// The plan, when found.
    pub trajectory: Option<PlannedTrajectory>,
    /// The client's candidates with their verdicts, when it posted some.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub candidates: Option<Vec<CandidateView>>,
    /// Which model each step of the plan relied on (predicted by it, trusted by its
    /// precondition), when the experiment has several models; empty without a plan.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_models: Option<Vec<String>>,
    /// What the search spent on each model it could step with, when the experiment has
    /// several models.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_calls: Option<Vec<ModelCalls>>,
}

/// Why a search's extensions added nothing to its tree.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct RejectionCounts {
    /// No steered action was allowed by the domain's constraints (bounds, obstacles, the
    /// action's form) and new: the search could not reach further there.
    pub constraints: usize,
    /// Some were, but none lay inside the precondition: the model is not trusted there.
    pub precondition: usize,
}

/// Every error's body: `{"error": {"code", "message", "details"}}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ErrorBody {
    /// The error.
    pub error: ErrorDetail,
}

/// What went wrong, for machines (`code`, `details`) and people (`message`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ErrorDetail {
    /// Stable machine-readable code, e.g. `validation_failed`.
    pub code: String,
    /// Human-readable message.
    pub message: String,
    /// Code-specific details (e.g. `{"field", "reason"}`), or `null`.
    pub details: Value,
}

impl From<&crate::planning::Trajectory> for PlannedTrajectory {
    /// The trajectory with its per-step μ and σ, without acquisition values.
    fn from(t: &crate::planning::Trajectory) -> Self {
        Self {
            states: t.states.clone(),
            actions: t.actions.clone(),
            mu: t.mu.clone(),
            sigma: t.sigma.clone(),
            alpha_step: None,
            alpha: None,
        }
    }
}
