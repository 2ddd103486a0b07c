//! Read-only views of an experiment's history for the dashboard: proposals and trajectories as
//! one list of runs, per-iteration statistics and the list of model versions.

use super::trajectories::provenance_from_row;
use super::{Backend, ExclusionSet, Store, decode_vec, flag};
use crate::records::{IterationStats, ModelSummary, RefusalReason, Run, RunStatus};
use sqlx::Row;
use sqlx::any::AnyRow;

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
        let rows = sqlx::query(
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
        .await?;
        rows.iter()
            .map(|row| {
                Ok(IterationStats {
                    iteration: row.try_get("iteration")?,
                    n_trajectories: row.try_get("n_trajectories")?,
                    n_transitions: row.try_get("n_transitions")?,
                    mean_deviation: row.try_get("mean_deviation")?,
                    max_deviation: row.try_get("max_deviation")?,
                    share_within_d_max: row.try_get("share_within_d_max")?,
                    n_refused: row.try_get("n_refused")?,
                })
            })
            .collect()
    }

    /// The first `limit` model versions of an experiment, oldest first.
    #[tracing::instrument(skip(self))]
    pub async fn model_summaries(
        &self,
        experiment_id: i64,
        limit: i64,
    ) -> Result<Vec<ModelSummary>, sqlx::Error> {
        let rows = sqlx::query(
            "SELECT version, n_train, n_trajectories, noise, log_marginal_likelihood,
                    fit_seconds, fitted_at, label_cap
             FROM models WHERE experiment_id = $1 ORDER BY version LIMIT $2",
        )
        .bind(experiment_id)
        .bind(limit)
        .fetch_all(&self.read)
        .await?;
        rows.iter()
            .map(|row| {
                Ok(ModelSummary {
                    version: row.try_get("version")?,
                    n_train: row.try_get("n_train")?,
                    n_trajectories: row.try_get("n_trajectories")?,
                    noise: row.try_get("noise")?,
                    log_marginal_likelihood: row.try_get("log_marginal_likelihood")?,
                    fit_seconds: row.try_get("fit_seconds")?,
                    fitted_at: row.try_get("fitted_at")?,
                    label_cap: row.try_get("label_cap")?,
                })
            })
            .collect()
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
    ) -> Result<Vec<crate::records::StoredTransition>, sqlx::Error> {
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
