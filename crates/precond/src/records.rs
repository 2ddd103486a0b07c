//! What precond keeps and shows as it is: executed transitions with their labels, where a
//! trajectory comes from, the runs list, refused fits and proposal requests, a proposal's
//! terms and status. The store reads and writes these values (its rows and queries are its
//! own, in [`crate::store`]); the service returns them; the API shows them as they are
//! ([`crate::api`] names them as the wire does: `TransitionView`, `TrajectorySource`, …).
//! Plain data: no SQL, no HTTP.

use crate::mde::EstimatorKind;
use crate::planning::Strategy;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
/// A stored transition with its prediction and label (`Transition` of the API, as stored).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct StoredTransition {
    /// Identifier; ascending in ingest order.
    pub id: i64,
    /// The trajectory it belongs to.
    pub trajectory_id: i64,
    /// Position in the trajectory, from 0.
    pub step: i64,
    /// State.
    pub s: Vec<f64>,
    /// Action.
    pub a: Vec<f64>,
    /// Observed next state.
    pub s_next: Vec<f64>,
    /// Predicted next state.
    pub s_pred: Vec<f64>,
    /// Deviation label.
    pub deviation: f64,
    /// The further models' labels (`settings.models`), in their order; left out when the
    /// experiment has none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub labels: Option<Vec<ModelLabel>>,
}

/// One further model's label of an executed transition: its prediction `f̂_m(s, a)` and
/// deviation `d(f̂_m(s, a), s_next)`, or — when the model could not answer — neither, and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ModelLabel {
    /// The model's name.
    pub model: String,
    /// Its prediction; `null` when missing.
    pub s_pred: Option<Vec<f64>>,
    /// Its deviation label; `null` when missing.
    pub deviation: Option<f64>,
    /// Why the label is missing (the model's error); `null` when labelled.
    pub missing: Option<String>,
}

impl ModelLabel {
    /// `model`'s label: its prediction and deviation.
    pub fn labelled(model: &str, s_pred: Vec<f64>, deviation: f64) -> Self {
        Self {
            model: model.to_string(),
            s_pred: Some(s_pred),
            deviation: Some(deviation),
            missing: None,
        }
    }

    /// `model` left the transition unlabelled because of `why`.
    pub fn missing(model: &str, why: impl Into<String>) -> Self {
        Self {
            model: model.to_string(),
            s_pred: None,
            deviation: None,
            missing: Some(why.into()),
        }
    }
}

/// Where a posted trajectory comes from: a logged dataset or file, a simulated environment.
/// Posted with the trajectory (`TrajectorySource` of the API, checked by
/// `service::ingest::check_source`), stored with it and shown with it and in the runs list.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Provenance {
    /// The dataset, file or environment, e.g. `lerobot:user/pusht` or `logs/run3.csv`
    /// (1 to 1000 characters).
    #[schemars(length(min = 1, max = crate::limits::MAX_SOURCE_TEXT_LEN))]
    pub dataset: String,
    /// The episode of the dataset (≥ 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub episode: Option<i64>,
    /// The step of the episode the trajectory's first transition was (≥ 0): an episode longer
    /// than one post allows is posted as several trajectories.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first_step: Option<i64>,
    /// A free-form label (at most 1000 characters).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = crate::limits::MAX_SOURCE_TEXT_LEN))]
    pub label: Option<String>,
}

/// Where a run stands: a proposal's lease status, or what its trajectory was.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum RunStatus {
    /// A proposal leased to its client, waiting for the executed trajectory.
    Open,
    /// A proposal whose trajectory was posted in full.
    Executed,
    /// A proposal its client gave up.
    Abandoned,
    /// A proposal whose lease ran out before a trajectory was posted.
    Expired,
    /// A proposal whose robot stopped early (`partial` trajectory).
    Partial,
    /// A trajectory posted without a proposal (teleoperation, logs, another planner).
    Unsolicited,
    /// A proposal request answered `no_plan`: no trajectory reached the goal inside the
    /// precondition at any β tried.
    Refused,
}

/// A proposal and the trajectory that executed it, a trajectory posted without a proposal, or a
/// refused proposal request: a row of the runs list, shown as listed (`Run` of the API).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Run {
    /// The proposal, if there was one.
    pub proposal_id: Option<i64>,
    /// The executed trajectory, if one was posted.
    pub trajectory_id: Option<i64>,
    /// The refusal, for a refused proposal request (`status` `refused`).
    #[serde(default)]
    pub refusal_id: Option<i64>,
    /// Where it stands.
    pub status: RunStatus,
    /// The client the proposal was leased to (or that was refused).
    pub client_id: Option<String>,
    /// The learning iteration the proposal was made (or refused) in (`null` without a
    /// proposal).
    pub iteration: Option<i64>,
    /// β the proposal was planned with; for a refusal, the first β tried (the iteration's
    /// `β_j`) (`null` without a proposal).
    pub beta: Option<f64>,
    /// Every β a refused request tried, in order (`null` unless refused).
    #[serde(default)]
    pub betas_tried: Option<Vec<f64>>,
    /// Why a refused request was refused: `no_plan` or `deadline_exceeded` (`null` unless
    /// refused).
    #[serde(default)]
    pub refusal_reason: Option<RefusalReason>,
    /// RRT extensions the proposal's or the refusal's search spent (`null` without a proposal).
    #[serde(default)]
    pub extensions: Option<i64>,
    /// The MDE version that scored the proposal (`null` without a proposal).
    pub model_version: Option<i64>,
    /// When the proposal was made, or the trajectory posted if there was no proposal (RFC 3339).
    pub created_at: String,
    /// Actions: executed transitions when a trajectory was posted, else the proposal's planned
    /// actions.
    pub length: i64,
    /// Whether the posted trajectory stopped early.
    pub partial: bool,
    /// Whether the posted trajectory departs from its proposal (other actions, longer, or
    /// another start; a prefix does not).
    #[serde(default)]
    pub deviating: bool,
    /// Where the posted trajectory comes from, when its client said.
    #[serde(default)]
    pub source: Option<Provenance>,
    /// The largest deviation label of the executed trajectory (`null` before one was posted).
    pub max_deviation: Option<f64>,
    /// The exclusion (the oldest in effect) that keeps the posted trajectory out of the
    /// experiment's model (`null` when none does).
    #[serde(default)]
    pub excluded_by: Option<i64>,
}

/// A fit the server did not attempt because its estimated peak memory or time exceeded the
/// budget; the version before it kept answering. Shown as stored (`FitRefusal` of the API).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct FitRefusal {
    /// Transitions the fit would have been trained on.
    pub n_train: i64,
    /// Trajectories stored then.
    pub n_trajectories: i64,
    /// The regressor it would have fitted: `exact` or `sparse`.
    pub estimator: EstimatorKind,
    /// Its estimated peak memory (bytes).
    pub needed_bytes: f64,
    /// The server's budget (bytes, `--max-fit-memory-mib`).
    pub budget_bytes: f64,
    /// Why, in words.
    pub reason: String,
    /// When (RFC 3339).
    pub refused_at: String,
    /// For a refusal over time: its estimated seconds (model selection included, at the cost
    /// model's assumed rate); `null` for one over memory.
    pub needed_seconds: Option<f64>,
    /// For a refusal over time: the server's budget (seconds, `--max-fit-seconds`).
    pub budget_seconds: Option<f64>,
}

impl FitRefusal {
    /// A refusal now over time: the fit (within the memory budget: `(needed, budget)` bytes)
    /// would take about `needed_seconds`, beyond `budget_seconds`.
    pub fn over_time(
        n_train: i64,
        n_trajectories: i64,
        estimator: EstimatorKind,
        (needed_bytes, budget_bytes): (f64, f64),
        (needed_seconds, budget_seconds): (f64, f64),
    ) -> Self {
        Self {
            n_train,
            n_trajectories,
            estimator,
            needed_bytes,
            budget_bytes,
            reason: format!(
                "the {} GP's fit on {n_train} transitions would take about {needed_seconds:.0} s \
                 (model selection included), beyond the server's fit time budget of \
                 {budget_seconds:.0} s (--max-fit-seconds); the previous version keeps answering",
                estimator.as_str(),
            ),
            refused_at: now(),
            needed_seconds: Some(needed_seconds),
            budget_seconds: Some(budget_seconds),
        }
    }

    /// A refusal now over memory.
    pub fn now(
        n_train: i64,
        n_trajectories: i64,
        estimator: EstimatorKind,
        needed_bytes: f64,
        budget_bytes: f64,
    ) -> Self {
        let gib = |b: f64| b / (1u64 << 30) as f64;
        Self {
            n_train,
            n_trajectories,
            estimator,
            needed_bytes,
            budget_bytes,
            reason: format!(
                "the {} GP's fit on {n_train} transitions needs about {:.2} GiB, beyond the \
                 server's fit memory budget of {:.2} GiB (--max-fit-memory-mib); the previous \
                 version keeps answering",
                estimator.as_str(),
                gib(needed_bytes),
                gib(budget_bytes)
            ),
            refused_at: now(),
            needed_seconds: None,
            budget_seconds: None,
        }
    }
}

/// Why a proposal request was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum RefusalReason {
    /// No trajectory reached the goal inside the precondition, at every β tried.
    NoPlan,
    /// The search did not finish within the planning deadline (`--plan-timeout-ms`).
    DeadlineExceeded,
}

impl RefusalReason {
    /// The stored (and shown) name.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::NoPlan => "no_plan",
            Self::DeadlineExceeded => "deadline_exceeded",
        }
    }
}

/// Where a proposal's lease stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ProposalStatus {
    /// Leased to its client, waiting for the executed trajectory.
    Open,
    /// Its trajectory was posted.
    Executed,
    /// The client gave it up.
    Abandoned,
    /// The lease ran out before a trajectory was posted.
    Expired,
}

impl ProposalStatus {
    /// The stored name.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Open => "open",
            Self::Executed => "executed",
            Self::Abandoned => "abandoned",
            Self::Expired => "expired",
        }
    }

    /// The status of a stored name.
    pub fn from_name(s: &str) -> Option<Self> {
        Some(match s {
            "open" => Self::Open,
            "executed" => Self::Executed,
            "abandoned" => Self::Abandoned,
            "expired" => Self::Expired,
            _ => return None,
        })
    }
}

/// What a proposal answered and under which conditions: the problem, the client it is leased
/// to, and the learning state that shaped it. Shown as stored, in the API's proposal.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ProposalTerms {
    /// The client it is leased to.
    pub client_id: Option<String>,
    /// The learning iteration it was made in.
    pub iteration: i64,
    /// β it was planned with.
    pub beta: f64,
    /// The strategy that chose it.
    pub strategy: Strategy,
    /// The MDE version that scored it.
    pub model_version: i64,
    /// Start state.
    pub start: Vec<f64>,
    /// Goal.
    pub goal: Vec<f64>,
}

/// Which end of the experiment list comes first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ListOrder {
    /// Ascending id (creation order).
    #[default]
    Oldest,
    /// Descending id: the newest experiment first.
    Newest,
}

/// The current time as an RFC 3339 UTC string, the time format of everything precond keeps.
pub fn now() -> String {
    timestamp(time::OffsetDateTime::now_utc())
}

/// `t` as the store writes times: RFC 3339 in UTC with exactly nine fractional digits, so that
/// comparing two as text compares them in time (SQLite's date functions keep milliseconds only,
/// and rows stored within one millisecond must still sort in the order they were made).
pub fn timestamp(t: time::OffsetDateTime) -> String {
    const FORMAT: &[time::format_description::BorrowedFormatItem<'_>] = time::macros::format_description!(
        "[year]-[month]-[day]T[hour]:[minute]:[second].[subsecond digits:9]Z"
    );
    t.to_offset(time::UtcOffset::UTC)
        .format(FORMAT)
        .unwrap_or_default()
}

/// Executed trajectories and transitions of one learning iteration, and its refused proposal
/// requests (shown in the API's timeline).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct IterationStats {
    /// The iteration (its trajectories are the experiment's `iteration × batch_size`-th to the
    /// next batch's first, in ingest order).
    pub iteration: i64,
    /// Trajectories posted in it (0 when it only refused proposal requests so far).
    pub n_trajectories: i64,
    /// Their transitions.
    pub n_transitions: i64,
    /// Mean deviation label of those transitions (`null` without any).
    pub mean_deviation: Option<f64>,
    /// Largest deviation label (`null` without any).
    pub max_deviation: Option<f64>,
    /// Share of the transitions with a deviation below `d_max` (the model was right there;
    /// `null` without any).
    pub share_within_d_max: Option<f64>,
    /// Proposal requests refused in it (`no_plan`, or past the planning deadline).
    #[serde(default)]
    pub n_refused: i64,
}

/// A stored model version's summary (no training data, no noise model; shown in the API's
/// timeline).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ModelSummary {
    /// Version (1, 2, …).
    pub version: i64,
    /// Training transitions (the experiment's first `n_train`).
    pub n_train: i64,
    /// Trajectories stored when the fit started.
    pub n_trajectories: i64,
    /// Noise mode of the fit.
    pub noise: String,
    /// Log marginal likelihood of the fit.
    pub log_marginal_likelihood: f64,
    /// Seconds the fit took.
    pub fit_seconds: f64,
    /// When it finished (RFC 3339).
    pub fitted_at: String,
    /// The label cap it was fitted with (units of `d_max`; 0 = raw labels; migration 0007
    /// recorded one for every version fitted before caps were).
    pub label_cap: f64,
}
