//! Fitted model versions.

use super::{ExclusionSet, Store};
use crate::mde::{
    BetaChoice, EstimatorKind, EstimatorState, HeldOutTrust, KernelTrial, SelectionRecord,
};
use crate::records::FitRefusal;
use sqlx::AnyConnection;

/// A stored model version.
#[derive(Debug, Clone)]
pub struct StoredModel {
    /// Version (1, 2, …).
    pub version: i64,
    /// Training transitions: the experiment's first `n_train` in id order outside the
    /// trajectories `exclusions` cover.
    pub n_train: i64,
    /// The exclusions in effect when the fit read its training set.
    pub exclusions: ExclusionSet,
    /// Trajectories stored when the fit started.
    pub n_trajectories: i64,
    /// Everything needed to rebuild the model (with its training data, for the exact GP).
    pub state: EstimatorState,
    /// The fit's objective: log marginal likelihood (exact) or its bound (sparse).
    pub log_marginal_likelihood: f64,
    /// Seconds the fit took.
    pub fit_seconds: f64,
    /// When it finished (RFC 3339).
    pub fitted_at: String,
    /// The label cap it was fitted with (units of `d_max`; 0 = raw labels).
    pub label_cap: f64,
    /// Every candidate cap's held-out judgement of the training transitions.
    pub label_cap_trials: Vec<HeldOutTrust>,
    /// Every candidate kernel's fit, when the kernel was chosen from the data.
    pub kernel_trials: Vec<KernelTrial>,
    /// The test β its held-out judgements certify, when they were made.
    pub beta_choice: Option<BetaChoice>,
    /// How its kernel and label cap were chosen and what its fit spent time on (`None` for
    /// versions fitted before it was recorded).
    pub selection: Option<SelectionRecord>,
    /// The estimators of the experiment's further models fitted with it.
    pub further: Vec<StoredFurther>,
}

/// A further model's estimator as a version stores it.
#[derive(Debug, Clone)]
pub struct StoredFurther {
    /// The further model's name.
    pub model: String,
    /// Training transitions: those among the version's that the model labelled, in id order.
    pub n_train: i64,
    /// The label cap its labels were clipped at (units of `d_max`; 0 = raw labels).
    pub label_cap: f64,
    /// Its fit's objective.
    pub log_marginal_likelihood: f64,
    /// Everything needed to rebuild it (with its training data, for the exact GP).
    pub state: EstimatorState,
}

fn json_err(e: serde_json::Error) -> sqlx::Error {
    sqlx::Error::Decode(Box::new(e))
}

/// Records a fitted version, inside the transaction that ends its fit
/// ([`Store::finish_fit`]).
pub(super) async fn insert_model_on(
    conn: &mut AnyConnection,
    experiment_id: i64,
    model: &StoredModel,
) -> Result<(), sqlx::Error> {
    let state = serde_json::to_string(&model.state).map_err(json_err)?;
    // `null` for an estimator without one set of hyperparameters (local experts).
    let hyper = serde_json::to_string(&model.state.hyperparameters()).map_err(json_err)?;
    let noise = serde_json::to_value(model.state.noise()).map_err(json_err)?;
    let trials = serde_json::to_string(&model.label_cap_trials).map_err(json_err)?;
    let kernel_trials = serde_json::to_string(&model.kernel_trials).map_err(json_err)?;
    let beta_choice = serde_json::to_string(&model.beta_choice).map_err(json_err)?;
    let selection = model
        .selection
        .as_ref()
        .map(serde_json::to_string)
        .transpose()
        .map_err(json_err)?;
    sqlx::query(
        "INSERT INTO models (experiment_id, version, n_train, n_trajectories, noise, state,
                             hyperparameters, log_marginal_likelihood, fit_seconds, fitted_at,
                             label_cap, label_cap_trials, kernel_trials, beta_choice, selection,
                             exclusions)
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15, $16)",
    )
    .bind(experiment_id)
    .bind(model.version)
    .bind(model.n_train)
    .bind(model.n_trajectories)
    .bind(noise.as_str().unwrap_or_default().to_string())
    .bind(state)
    .bind(hyper)
    .bind(model.log_marginal_likelihood)
    .bind(model.fit_seconds)
    .bind(&model.fitted_at)
    .bind(model.label_cap)
    .bind(trials)
    .bind(kernel_trials)
    .bind(beta_choice)
    .bind(selection)
    .bind(model.exclusions.encode())
    .execute(&mut *conn)
    .await?;
    for f in &model.further {
        sqlx::query(
            "INSERT INTO further_fits (experiment_id, version, model, n_train, label_cap,
                                       log_marginal_likelihood, state)
             VALUES ($1, $2, $3, $4, $5, $6, $7)",
        )
        .bind(experiment_id)
        .bind(model.version)
        .bind(f.model.as_str())
        .bind(f.n_train)
        .bind(f.label_cap)
        .bind(f.log_marginal_likelihood)
        .bind(serde_json::to_string(&f.state).map_err(json_err)?)
        .execute(&mut *conn)
        .await?;
    }
    Ok(())
}

impl Store {
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
        self.model_where(experiment_id, "AND version = $2", Some(version))
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
                    label_cap_trials, log_marginal_likelihood, kernel_trials, beta_choice,
                    selection, exclusions
             FROM models WHERE experiment_id = $1 {clause}"
        );
        type Row = (
            i64,
            i64,
            i64,
            String,
            f64,
            String,
            f64,
            String,
            f64,
            String,
            String,
            Option<String>,
            Option<String>,
        );
        let mut query = sqlx::query_as::<_, Row>(&sql).bind(experiment_id);
        if let Some(v) = version {
            query = query.bind(v);
        }
        let Some(row) = query.fetch_optional(&self.read).await? else {
            return Ok(None);
        };
        let (
            version,
            n_train,
            n_trajectories,
            state,
            fit_seconds,
            fitted_at,
            label_cap,
            trials,
            lml,
            kernel_trials,
            beta_choice,
            selection,
            exclusions,
        ) = row;
        let further = sqlx::query_as::<_, (String, i64, f64, f64, String)>(
            "SELECT model, n_train, label_cap, log_marginal_likelihood, state FROM further_fits
             WHERE experiment_id = $1 AND version = $2 ORDER BY model",
        )
        .bind(experiment_id)
        .bind(version)
        .fetch_all(&self.read)
        .await?
        .into_iter()
        .map(|(model, n_train, label_cap, lml, state)| {
            Ok(StoredFurther {
                model,
                n_train,
                label_cap,
                log_marginal_likelihood: lml,
                state: serde_json::from_str(&state).map_err(json_err)?,
            })
        })
        .collect::<Result<Vec<_>, sqlx::Error>>()?;
        Ok(Some(StoredModel {
            further,
            version,
            n_train,
            exclusions: ExclusionSet::decode(exclusions.as_deref())?,
            n_trajectories,
            state: serde_json::from_str(&state).map_err(json_err)?,
            log_marginal_likelihood: lml,
            fit_seconds,
            fitted_at,
            label_cap,
            label_cap_trials: serde_json::from_str(&trials).map_err(json_err)?,
            kernel_trials: serde_json::from_str(&kernel_trials).map_err(json_err)?,
            beta_choice: serde_json::from_str(&beta_choice).map_err(json_err)?,
            selection: selection
                .as_deref()
                .map(serde_json::from_str)
                .transpose()
                .map_err(json_err)?,
        }))
    }

    /// Records a fit that was not attempted (see [`FitRefusal`]).
    #[tracing::instrument(skip(self))]
    pub async fn insert_fit_refusal(
        &self,
        experiment_id: i64,
        r: &FitRefusal,
    ) -> Result<(), sqlx::Error> {
        self.noted(async {
            sqlx::query(
                "INSERT INTO fit_refusals (experiment_id, n_train, n_trajectories, estimator,
                                           needed_bytes, budget_bytes, reason, refused_at,
                                           needed_seconds, budget_seconds)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10)",
            )
            .bind(experiment_id)
            .bind(r.n_train)
            .bind(r.n_trajectories)
            .bind(r.estimator.as_str())
            .bind(r.needed_bytes)
            .bind(r.budget_bytes)
            .bind(&r.reason)
            .bind(&r.refused_at)
            .bind(r.needed_seconds)
            .bind(r.budget_seconds)
            .execute(&self.write)
            .await?;
            Ok(())
        })
        .await
    }

    /// The experiment's latest refused fit, if any.
    #[tracing::instrument(skip(self))]
    pub async fn latest_fit_refusal(
        &self,
        experiment_id: i64,
    ) -> Result<Option<FitRefusal>, sqlx::Error> {
        let count = self.fit_refusal_count(experiment_id).await?;
        Ok(self
            .fit_refusals_from(experiment_id, (count - 1).max(0), 1)
            .await?
            .pop())
    }

    /// How many fits of the experiment were refused so far.
    #[tracing::instrument(skip(self))]
    pub async fn fit_refusal_count(&self, experiment_id: i64) -> Result<i64, sqlx::Error> {
        sqlx::query_scalar("SELECT COUNT(*) FROM fit_refusals WHERE experiment_id = $1")
            .bind(experiment_id)
            .fetch_one(&self.read)
            .await
    }

    /// The experiment's refused fits, oldest first, at most `limit`.
    #[tracing::instrument(skip(self))]
    pub async fn fit_refusals(
        &self,
        experiment_id: i64,
        limit: i64,
    ) -> Result<Vec<FitRefusal>, sqlx::Error> {
        self.fit_refusals_from(experiment_id, 0, limit).await
    }

    async fn fit_refusals_from(
        &self,
        experiment_id: i64,
        offset: i64,
        limit: i64,
    ) -> Result<Vec<FitRefusal>, sqlx::Error> {
        type Row = (
            i64,
            i64,
            String,
            f64,
            f64,
            String,
            String,
            Option<f64>,
            Option<f64>,
        );
        let rows = sqlx::query_as::<_, Row>(
            "SELECT n_train, n_trajectories, estimator, needed_bytes, budget_bytes, reason,
                    refused_at, needed_seconds, budget_seconds
             FROM fit_refusals WHERE experiment_id = $1 ORDER BY id LIMIT $2 OFFSET $3",
        )
        .bind(experiment_id)
        .bind(limit)
        .bind(offset)
        .fetch_all(&self.read)
        .await?;
        rows.into_iter()
            .map(
                |(n_train, n_trajectories, estimator, needed, budget, reason, at, secs, limit)| {
                    Ok(FitRefusal {
                        n_train,
                        n_trajectories,
                        estimator: EstimatorKind::from_name(&estimator)
                            .unwrap_or(EstimatorKind::Exact),
                        needed_bytes: needed,
                        budget_bytes: budget,
                        reason,
                        refused_at: at,
                        needed_seconds: secs,
                        budget_seconds: limit,
                    })
                },
            )
            .collect()
    }
}
