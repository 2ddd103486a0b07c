//! Read-only views of an experiment's history for the dashboard: proposals and trajectories as
//! one list of runs, per-iteration statistics and the list of model versions.

use super::trajectories::provenance_from_row;
use super::{Backend, ExclusionSet, Provenance, RefusalReason, Store, decode_vec, flag};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use sqlx::any::AnyRow;
use sqlx::{FromRow, Row};

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

/// Executed trajectories and transitions of one learning iteration, and its refused proposal
/// requests (shown in the API's timeline).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema, FromRow)]
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
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema, FromRow)]
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

/// Proposals (with the trajectory that executed each), trajectories without a proposal and
/// refused proposal requests, as one relation (the first branch's NULLs typed: PostgreSQL
/// resolves a UNION's column types branch by branch); `$1` is the experiment, `$2` the current
/// Unix time (an open proposal whose lease has passed shows as expired without being written).
const RUNS: &str = "
    SELECT p.id AS proposal_id, t.id AS trajectory_id, CAST(NULL AS BIGINT) AS refusal_id,
           CASE WHEN p.status = 'open' AND p.expires_unix <= $2 THEN 'expired'
                ELSE p.status END AS proposal_status,
           p.client_id, p.iteration, p.beta, p.model_version, p.created_at,
           COALESCE(t.n_transitions, p.n_actions, 0) AS length,
           COALESCE(t.partial, FALSE) AS partial, COALESCE(t.deviating, FALSE) AS deviating,
           t.source_dataset, t.source_episode, t.source_first_step, t.source_label,
           p.extensions AS extensions, CAST(NULL AS TEXT) AS betas,
           CAST(NULL AS TEXT) AS refusal_reason
    FROM proposals p LEFT JOIN trajectories t ON t.proposal_id = p.id
    WHERE p.experiment_id = $1
    UNION ALL
    SELECT NULL, t.id, NULL, NULL, NULL, NULL, NULL, NULL, t.created_at, t.n_transitions,
           t.partial, t.deviating, t.source_dataset, t.source_episode, t.source_first_step,
           t.source_label, NULL, NULL, NULL
    FROM trajectories t
    WHERE t.experiment_id = $1 AND t.proposal_id IS NULL
    UNION ALL
    SELECT NULL, NULL, r.id, 'refused', r.client_id, r.iteration,
           r.first_beta, r.model_version, r.created_at, 0, FALSE, FALSE,
           NULL, NULL, NULL, NULL, r.extensions, r.betas, r.reason
    FROM refusals r
    WHERE r.experiment_id = $1";

fn unix_now() -> f64 {
    time::OffsetDateTime::now_utc().unix_timestamp_nanos() as f64 / 1e9
}

fn run_from_row(row: &AnyRow) -> Result<Run, sqlx::Error> {
    let proposal_id: Option<i64> = row.try_get("proposal_id")?;
    let partial = flag(row, "partial")?;
    let proposal_status: Option<String> = row.try_get("proposal_status")?;
    let status = match (proposal_status.as_deref(), partial) {
        (None, _) => RunStatus::Unsolicited,
        (Some("executed"), true) => RunStatus::Partial,
        (Some("executed"), false) => RunStatus::Executed,
        (Some("open"), _) => RunStatus::Open,
        (Some("abandoned"), _) => RunStatus::Abandoned,
        (Some("expired"), _) => RunStatus::Expired,
        (Some("refused"), _) => RunStatus::Refused,
        (Some(other), _) => {
            return Err(sqlx::Error::Decode(
                format!("unknown proposal status {other:?}").into(),
            ));
        }
    };
    let betas: Option<String> = row.try_get("betas")?;
    let refusal_reason = match row
        .try_get::<Option<String>, _>("refusal_reason")?
        .as_deref()
    {
        None => None,
        Some("deadline_exceeded") => Some(RefusalReason::DeadlineExceeded),
        Some(_) => Some(RefusalReason::NoPlan),
    };
    Ok(Run {
        proposal_id,
        trajectory_id: row.try_get("trajectory_id")?,
        refusal_id: row.try_get("refusal_id")?,
        status,
        client_id: row.try_get("client_id")?,
        iteration: row.try_get("iteration")?,
        beta: row.try_get("beta")?,
        betas_tried: betas.as_deref().map(decode_vec).transpose()?,
        refusal_reason,
        extensions: row.try_get("extensions")?,
        model_version: row.try_get("model_version")?,
        created_at: row.try_get("created_at")?,
        length: row.try_get("length")?,
        partial,
        deviating: flag(row, "deviating")?,
        source: provenance_from_row(row)?,
        max_deviation: row.try_get("max_deviation")?,
        excluded_by: row.try_get("excluded_by")?,
    })
}

impl Store {
    /// A page of an experiment's runs, newest first: skipping `offset`, at most `limit`. The
    /// maximum deviation is computed for the page's trajectories only.
    #[tracing::instrument(skip(self))]
    pub async fn runs(
        &self,
        experiment_id: i64,
        offset: i64,
        limit: i64,
    ) -> Result<Vec<Run>, sqlx::Error> {
        // Times written by older SQLite versions of precond may have fewer fractional digits:
        // SQLite orders by the instant first. PostgreSQL databases only hold today's format,
        // which sorts as text.
        let instant = match self.backend {
            Backend::Sqlite => "julianday(r.created_at) DESC,",
            Backend::Postgres => "",
        };
        sqlx::query(&format!(
            "SELECT r.*, (SELECT MAX(x.deviation) FROM transitions x
                          WHERE x.trajectory_id = r.trajectory_id) AS max_deviation,
                         (SELECT MIN(e.exclusion_id) FROM excluded_trajectories e
                          JOIN exclusions z ON z.id = e.exclusion_id
                          WHERE e.trajectory_id = r.trajectory_id AND z.restored_at IS NULL)
                          AS excluded_by
             FROM ({RUNS}) r
             ORDER BY {instant} r.created_at DESC, r.proposal_id DESC,
                      r.trajectory_id DESC, r.refusal_id DESC
             LIMIT $3 OFFSET $4"
        ))
        .bind(experiment_id)
        .bind(unix_now())
        .bind(limit)
        .bind(offset)
        .fetch_all(&self.read)
        .await?
        .iter()
        .map(run_from_row)
        .collect()
    }

    /// How many runs an experiment has.
    #[tracing::instrument(skip(self))]
    pub async fn count_runs(&self, experiment_id: i64) -> Result<i64, sqlx::Error> {
        sqlx::query_scalar(
            "SELECT (SELECT COUNT(*) FROM proposals WHERE experiment_id = $1)
                  + (SELECT COUNT(*) FROM trajectories
                     WHERE experiment_id = $1 AND proposal_id IS NULL)
                  + (SELECT COUNT(*) FROM refusals WHERE experiment_id = $1)",
        )
        .bind(experiment_id)
        .fetch_one(&self.read)
        .await
    }

    /// Per-iteration statistics of the first `limit` iterations with executed trajectories or
    /// refused proposal requests: trajectory `k` (0-based, in ingest order) belongs to
    /// iteration `k / batch_size`, a refusal to the iteration it was asked in.
    #[tracing::instrument(skip(self))]
    pub async fn iteration_stats(
        &self,
        experiment_id: i64,
        batch_size: i64,
        d_max: f64,
        limit: i64,
    ) -> Result<Vec<IterationStats>, sqlx::Error> {
        sqlx::query_as(
            "WITH t AS (
                 SELECT id, (ROW_NUMBER() OVER (ORDER BY id) - 1) / $2 AS iteration
                 FROM trajectories WHERE experiment_id = $1
             ),
             executed AS (
                 SELECT t.iteration, COUNT(DISTINCT t.id) AS n_trajectories,
                        COUNT(*) AS n_transitions, AVG(x.deviation) AS mean_deviation,
                        MAX(x.deviation) AS max_deviation,
                        CAST(AVG(CASE WHEN x.deviation < $3 THEN 1.0 ELSE 0.0 END)
                             AS DOUBLE PRECISION) AS share_within_d_max
                 FROM t JOIN transitions x ON x.trajectory_id = t.id
                 GROUP BY t.iteration
             ),
             refused AS (
                 SELECT iteration, COUNT(*) AS n_refused FROM refusals
                 WHERE experiment_id = $1 GROUP BY iteration
             ),
             iterations AS (
                 SELECT iteration FROM executed UNION SELECT iteration FROM refused
             )
             SELECT i.iteration, COALESCE(e.n_trajectories, 0) AS n_trajectories,
                    COALESCE(e.n_transitions, 0) AS n_transitions, e.mean_deviation,
                    e.max_deviation, e.share_within_d_max, COALESCE(r.n_refused, 0) AS n_refused
             FROM iterations i
             LEFT JOIN executed e ON e.iteration = i.iteration
             LEFT JOIN refused r ON r.iteration = i.iteration
             ORDER BY i.iteration LIMIT $4",
        )
        .bind(experiment_id)
        .bind(batch_size.max(1))
        .bind(d_max)
        .bind(limit)
        .fetch_all(&self.read)
        .await
    }

    /// The first `limit` model versions of an experiment, oldest first.
    #[tracing::instrument(skip(self))]
    pub async fn model_summaries(
        &self,
        experiment_id: i64,
        limit: i64,
    ) -> Result<Vec<ModelSummary>, sqlx::Error> {
        sqlx::query_as(
            "SELECT version, n_train, n_trajectories, noise, log_marginal_likelihood,
                    fit_seconds, fitted_at, label_cap
             FROM models WHERE experiment_id = $1 ORDER BY version LIMIT $2",
        )
        .bind(experiment_id)
        .bind(limit)
        .fetch_all(&self.read)
        .await
    }

    /// The first `n` deviation labels of an experiment outside the trajectories `outside`
    /// covers, in id order (a model version's training labels).
    #[tracing::instrument(skip(self))]
    pub async fn first_deviations(
        &self,
        experiment_id: i64,
        outside: &ExclusionSet,
        n: i64,
    ) -> Result<Vec<f64>, sqlx::Error> {
        sqlx::query_scalar(&format!(
            "SELECT deviation FROM transitions WHERE experiment_id = $1{} ORDER BY id LIMIT $2",
            outside.sql("trajectory_id")
        ))
        .bind(experiment_id)
        .bind(n)
        .fetch_all(&self.read)
        .await
    }

    /// Transitions of an experiment outside the trajectories `outside` covers, after the
    /// first `skip` of them in id order (those a model version fitted on the first `skip`
    /// under those exclusions never saw), at most `limit`.
    #[tracing::instrument(skip(self))]
    pub async fn transitions_after_first(
        &self,
        experiment_id: i64,
        outside: &ExclusionSet,
        skip: i64,
        limit: i64,
    ) -> Result<Vec<super::StoredTransition>, sqlx::Error> {
        let first_unseen: Option<i64> = sqlx::query_scalar(&format!(
            "SELECT id FROM transitions WHERE experiment_id = $1{} ORDER BY id LIMIT 1 OFFSET $2",
            outside.sql("trajectory_id")
        ))
        .bind(experiment_id)
        .bind(skip)
        .fetch_optional(&self.read)
        .await?;
        match first_unseen {
            Some(id) => {
                self.transitions_outside(experiment_id, outside, id - 1, Some(limit))
                    .await
            }
            None => Ok(Vec::new()),
        }
    }
}
