//! Fitted model versions.

use super::Store;
use crate::gp::{Hyperparameters, ModelState};
use crate::mde::HeldOutTrust;

/// A stored model version.
#[derive(Debug, Clone)]
pub struct StoredModel {
    /// Version (1, 2, …).
    pub version: i64,
    /// Training transitions: the experiment's first `n_train` in id order.
    pub n_train: i64,
    /// Trajectories stored when the fit started.
    pub n_trajectories: i64,
    /// Everything needed to rebuild the model from its training data.
    pub state: ModelState,
    /// Seconds the fit took.
    pub fit_seconds: f64,
    /// When it finished (RFC 3339).
    pub fitted_at: String,
    /// The label cap it was fitted with (units of `d_max`; 0 = raw labels).
    pub label_cap: f64,
    /// Every candidate cap's held-out judgement of the training transitions.
    pub label_cap_trials: Vec<HeldOutTrust>,
}

fn json_err(e: serde_json::Error) -> sqlx::Error {
    sqlx::Error::Decode(Box::new(e))
}

impl Store {
    /// Records a fitted version.
    #[tracing::instrument(skip(self, model), fields(version = model.version))]
    pub async fn insert_model(
        &self,
        experiment_id: i64,
        model: &StoredModel,
        hyperparameters: &Hyperparameters,
    ) -> Result<(), sqlx::Error> {
        let state = serde_json::to_string(&model.state).map_err(json_err)?;
        let hyper = serde_json::to_string(hyperparameters).map_err(json_err)?;
        let noise = serde_json::to_value(model.state.noise).map_err(json_err)?;
        let trials = serde_json::to_string(&model.label_cap_trials).map_err(json_err)?;
        sqlx::query(
            "INSERT INTO models (experiment_id, version, n_train, n_trajectories, noise, state,
                                 hyperparameters, log_marginal_likelihood, fit_seconds, fitted_at,
                                 label_cap, label_cap_trials)
             VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(experiment_id)
        .bind(model.version)
        .bind(model.n_train)
        .bind(model.n_trajectories)
        .bind(noise.as_str().unwrap_or_default())
        .bind(state)
        .bind(hyper)
        .bind(model.state.log_marginal_likelihood)
        .bind(model.fit_seconds)
        .bind(&model.fitted_at)
        .bind(model.label_cap)
        .bind(trials)
        .execute(&self.write)
        .await?;
        Ok(())
    }

    /// The latest version of an experiment's model, if any was fitted.
    #[tracing::instrument(skip(self))]
    pub async fn latest_model(
        &self,
        experiment_id: i64,
    ) -> Result<Option<StoredModel>, sqlx::Error> {
        self.model_where(experiment_id, "ORDER BY version DESC LIMIT 1", None)
            .await
    }

    /// Version `version` of an experiment's model, if it was fitted.
    #[tracing::instrument(skip(self))]
    pub async fn model_version(
        &self,
        experiment_id: i64,
        version: i64,
    ) -> Result<Option<StoredModel>, sqlx::Error> {
        self.model_where(experiment_id, "AND version = ?", Some(version))
            .await
    }

    async fn model_where(
        &self,
        experiment_id: i64,
        clause: &str,
        version: Option<i64>,
    ) -> Result<Option<StoredModel>, sqlx::Error> {
        let sql = format!(
            "SELECT version, n_train, n_trajectories, state, fit_seconds, fitted_at, label_cap,
                    label_cap_trials
             FROM models WHERE experiment_id = ? {clause}"
        );
        type Row = (i64, i64, i64, String, f64, String, f64, String);
        let mut query = sqlx::query_as::<_, Row>(&sql).bind(experiment_id);
        if let Some(v) = version {
            query = query.bind(v);
        }
        let Some(row) = query.fetch_optional(&self.read).await? else {
            return Ok(None);
        };
        let (version, n_train, n_trajectories, state, fit_seconds, fitted_at, label_cap, trials) =
            row;
        Ok(Some(StoredModel {
            version,
            n_train,
            n_trajectories,
            state: serde_json::from_str(&state).map_err(json_err)?,
            fit_seconds,
            fitted_at,
            label_cap,
            label_cap_trials: serde_json::from_str(&trials).map_err(json_err)?,
        }))
    }
}
