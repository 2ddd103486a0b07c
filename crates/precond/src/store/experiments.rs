//! Experiment rows.

use super::{Store, lock_experiment_list, now};
use crate::records::ListOrder;
use crate::settings::ExperimentSettings;
use sqlx::Row;
use sqlx::any::AnyRow;

/// A stored experiment with its counters.
#[derive(Debug, Clone)]
pub struct Experiment {
    /// Identifier.
    pub id: i64,
    /// Resolved settings.
    pub settings: ExperimentSettings,
    /// Creation time (RFC 3339).
    pub created_at: String,
    /// Executed trajectories stored.
    pub n_trajectories: i64,
    /// Transitions stored.
    pub n_transitions: i64,
    /// The latest fitted model version (0: none, the prior answers).
    pub model_version: i64,
    /// Proposal requests refused (`no_plan`).
    pub n_refused: i64,
    /// The latest of its creation, its last trajectory, its last proposal and its last refused
    /// proposal request (RFC 3339).
    pub last_activity: String,
}

const SELECT: &str = "SELECT e.id, e.settings, e.created_at,
        (SELECT COUNT(*) FROM trajectories t WHERE t.experiment_id = e.id) AS n_trajectories,
        (SELECT COUNT(*) FROM transitions x WHERE x.experiment_id = e.id) AS n_transitions,
        (SELECT COALESCE(MAX(version), 0) FROM models m WHERE m.experiment_id = e.id)
            AS model_version,
        (SELECT created_at FROM trajectories t WHERE t.experiment_id = e.id
            ORDER BY t.id DESC LIMIT 1) AS last_trajectory_at,
        (SELECT created_at FROM proposals p WHERE p.experiment_id = e.id
            ORDER BY p.id DESC LIMIT 1) AS last_proposal_at,
        (SELECT COUNT(*) FROM refusals r WHERE r.experiment_id = e.id) AS n_refused,
        (SELECT created_at FROM refusals r WHERE r.experiment_id = e.id
            ORDER BY r.id DESC LIMIT 1) AS last_refusal_at
     FROM experiments e";

/// The latest of RFC 3339 times (compared as instants, not as strings: fractional seconds may
/// have any number of digits).
fn latest(times: &[&str]) -> String {
    let parse = |t: &str| {
        time::OffsetDateTime::parse(t, &time::format_description::well_known::Rfc3339).ok()
    };
    times
        .iter()
        .filter_map(|t| parse(t).map(|at| (at, *t)))
        .max_by_key(|(at, _)| *at)
        .map(|(_, t)| t.to_string())
        .unwrap_or_else(|| times.first().copied().unwrap_or_default().to_string())
}

fn from_row(row: &AnyRow) -> Result<Experiment, sqlx::Error> {
    let settings: String = row.try_get("settings")?;
    let created_at: String = row.try_get("created_at")?;
    let mut times = vec![created_at.as_str()];
    let trajectory: Option<String> = row.try_get("last_trajectory_at")?;
    let proposal: Option<String> = row.try_get("last_proposal_at")?;
    let refusal: Option<String> = row.try_get("last_refusal_at")?;
    times.extend(trajectory.as_deref());
    times.extend(proposal.as_deref());
    times.extend(refusal.as_deref());
    let last_activity = latest(&times);
    Ok(Experiment {
        id: row.try_get("id")?,
        settings: serde_json::from_str(&settings).map_err(|e| sqlx::Error::Decode(Box::new(e)))?,
        last_activity,
        created_at,
        n_trajectories: row.try_get("n_trajectories")?,
        n_transitions: row.try_get("n_transitions")?,
        model_version: row.try_get("model_version")?,
        n_refused: row.try_get("n_refused")?,
    })
}

impl Store {
    /// Stores a new experiment and returns it, unless `limit` experiments are stored already
    /// (`None`). Counting and storing are one transaction under the experiment list's lock, so
    /// the limit holds across replicas.
    #[tracing::instrument(skip_all)]
    pub async fn insert_experiment(
        &self,
        settings: &ExperimentSettings,
        limit: i64,
    ) -> Result<Option<Experiment>, sqlx::Error> {
        self.noted(async {
            let json = serde_json::to_string(settings).map_err(|e| sqlx::Error::Encode(Box::new(e)))?;
            let created_at = now();
            let mut tx = self.begin_write().await?;
            lock_experiment_list(&mut tx, self.backend).await?;
            let count: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM experiments")
                .fetch_one(&mut *tx)
                .await?;
            if count >= limit {
                tx.rollback().await?;
                return Ok(None);
            }
            let id: i64 = sqlx::query_scalar(
                "INSERT INTO experiments (name, settings, created_at) VALUES ($1, $2, $3) RETURNING id",
            )
            .bind(&settings.name)
            .bind(json)
            .bind(&created_at)
            .fetch_one(&mut *tx)
            .await?;
            tx.commit().await?;
            Ok(Some(Experiment {
                id,
                settings: settings.clone(),
                n_trajectories: 0,
                n_transitions: 0,
                model_version: 0,
                n_refused: 0,
                last_activity: created_at.clone(),
                created_at,
            }))
        })
        .await
    }

    /// One experiment, or `None`.
    #[tracing::instrument(skip(self))]
    pub async fn experiment(&self, id: i64) -> Result<Option<Experiment>, sqlx::Error> {
        sqlx::query(&format!("{SELECT} WHERE e.id = $1"))
            .bind(id)
            .fetch_optional(&self.read)
            .await?
            .as_ref()
            .map(from_row)
            .transpose()
    }

    /// A page of experiments in `order`: skipping `offset`, at most `limit` (all when `None`).
    #[tracing::instrument(skip(self))]
    pub async fn experiments(
        &self,
        order: ListOrder,
        offset: i64,
        limit: Option<i64>,
    ) -> Result<Vec<Experiment>, sqlx::Error> {
        let direction = match order {
            ListOrder::Oldest => "ASC",
            ListOrder::Newest => "DESC",
        };
        sqlx::query(&format!(
            "{SELECT} ORDER BY e.id {direction} LIMIT $1 OFFSET $2"
        ))
        .bind(limit.unwrap_or(i64::MAX))
        .bind(offset)
        .fetch_all(&self.read)
        .await?
        .iter()
        .map(from_row)
        .collect()
    }

    /// How many experiments there are.
    #[tracing::instrument(skip(self))]
    pub async fn count_experiments(&self) -> Result<i64, sqlx::Error> {
        sqlx::query_scalar("SELECT COUNT(*) FROM experiments")
            .fetch_one(&self.read)
            .await
    }
}
