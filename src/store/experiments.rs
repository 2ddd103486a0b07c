//! Experiment rows.

use super::{Store, now};
use crate::settings::ExperimentSettings;
use sqlx::Row;
use sqlx::sqlite::SqliteRow;

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
}

const SELECT: &str = "SELECT e.id, e.settings, e.created_at,
        (SELECT COUNT(*) FROM trajectories t WHERE t.experiment_id = e.id) AS n_trajectories,
        (SELECT COUNT(*) FROM transitions x WHERE x.experiment_id = e.id) AS n_transitions,
        (SELECT COALESCE(MAX(version), 0) FROM models m WHERE m.experiment_id = e.id)
            AS model_version
     FROM experiments e";

fn from_row(row: &SqliteRow) -> Result<Experiment, sqlx::Error> {
    let settings: String = row.try_get("settings")?;
    Ok(Experiment {
        id: row.try_get("id")?,
        settings: serde_json::from_str(&settings).map_err(|e| sqlx::Error::Decode(Box::new(e)))?,
        created_at: row.try_get("created_at")?,
        n_trajectories: row.try_get("n_trajectories")?,
        n_transitions: row.try_get("n_transitions")?,
        model_version: row.try_get("model_version")?,
    })
}

impl Store {
    /// Stores a new experiment and returns it.
    #[tracing::instrument(skip_all)]
    pub async fn insert_experiment(
        &self,
        settings: &ExperimentSettings,
    ) -> Result<Experiment, sqlx::Error> {
        let json = serde_json::to_string(settings).map_err(|e| sqlx::Error::Encode(Box::new(e)))?;
        let created_at = now();
        let id: i64 = sqlx::query_scalar(
            "INSERT INTO experiments (name, settings, created_at) VALUES (?, ?, ?) RETURNING id",
        )
        .bind(&settings.name)
        .bind(json)
        .bind(&created_at)
        .fetch_one(&self.write)
        .await?;
        Ok(Experiment {
            id,
            settings: settings.clone(),
            created_at,
            n_trajectories: 0,
            n_transitions: 0,
            model_version: 0,
        })
    }

    /// One experiment, or `None`.
    #[tracing::instrument(skip(self))]
    pub async fn experiment(&self, id: i64) -> Result<Option<Experiment>, sqlx::Error> {
        sqlx::query(&format!("{SELECT} WHERE e.id = ?"))
            .bind(id)
            .fetch_optional(&self.read)
            .await?
            .as_ref()
            .map(from_row)
            .transpose()
    }

    /// Every experiment, oldest first.
    #[tracing::instrument(skip(self))]
    pub async fn experiments(&self) -> Result<Vec<Experiment>, sqlx::Error> {
        sqlx::query(&format!("{SELECT} ORDER BY e.id"))
            .fetch_all(&self.read)
            .await?
            .iter()
            .map(from_row)
            .collect()
    }

    /// Number of experiments.
    #[tracing::instrument(skip(self))]
    pub async fn count_experiments(&self) -> Result<i64, sqlx::Error> {
        sqlx::query_scalar("SELECT COUNT(*) FROM experiments")
            .fetch_one(&self.read)
            .await
    }
}
