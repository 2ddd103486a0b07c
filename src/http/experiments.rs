//! `/v1/experiments`: create, list, show.

use super::AppState;
use super::extract::{ApiJson, ApiPath};
use crate::domain::Space;
use crate::error::Error;
use crate::live::LiveExperiment;
use crate::settings::{ExperimentRequest, ExperimentSettings};
use crate::store::Experiment;
use axum::Json;
use axum::extract::State;
use axum::http::StatusCode;
use serde::Serialize;

/// A space as clients see it.
#[derive(Debug, Serialize)]
pub struct SpaceBody {
    /// Component names.
    pub names: Vec<String>,
    /// Lower bounds.
    pub low: Vec<f64>,
    /// Upper bounds.
    pub high: Vec<f64>,
    /// Allowed values of a discrete space.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub values: Option<Vec<Vec<f64>>>,
}

impl From<&Space> for SpaceBody {
    fn from(s: &Space) -> Self {
        Self {
            names: s.names.clone(),
            low: s.low.clone(),
            high: s.high.clone(),
            values: s.values.clone(),
        }
    }
}

/// An experiment with its resolved settings, spaces and progress.
#[derive(Debug, Serialize)]
pub struct ExperimentResponse {
    /// Identifier.
    pub id: i64,
    /// The fully resolved settings (`name`, `domain`, `d_max`, `seed`, `mde`, `learning`).
    #[serde(flatten)]
    pub settings: ExperimentSettings,
    /// The state space: what `s` and `s_next` must look like.
    pub state_space: SpaceBody,
    /// The action space: what `a` must look like.
    pub action_space: SpaceBody,
    /// Names of the MDE's feature components.
    pub feature_names: Vec<String>,
    /// Creation time.
    pub created_at: String,
    /// Executed trajectories stored.
    pub n_trajectories: i64,
    /// Transitions stored.
    pub n_transitions: i64,
    /// Current learning iteration (completed batches).
    pub iteration: i64,
    /// The MDE version answering queries (0: the prior).
    pub model_version: i64,
}

impl ExperimentResponse {
    fn new(e: Experiment, live: &LiveExperiment) -> Self {
        let domain = live.domain.as_ref();
        let model_version = live.model().version;
        Self {
            id: e.id,
            iteration: live.iteration(e.n_trajectories),
            settings: e.settings,
            state_space: domain.state_space().into(),
            action_space: domain.action_space().into(),
            feature_names: domain.feature_names(),
            created_at: e.created_at,
            n_trajectories: e.n_trajectories,
            n_transitions: e.n_transitions,
            model_version,
        }
    }
}

/// `POST /v1/experiments`.
pub async fn create_experiment(
    State(state): State<AppState>,
    ApiJson(request): ApiJson<ExperimentRequest>,
) -> Result<(StatusCode, Json<ExperimentResponse>), Error> {
    let (settings, domain) = request.resolve()?;
    let stored = state.store.insert_experiment(&settings).await?;
    let live = state
        .experiments
        .insert(LiveExperiment::new(stored.id, settings, domain.clone()));
    tracing::info!(
        experiment = stored.id,
        kind = domain.kind(),
        "experiment created"
    );
    Ok((
        StatusCode::CREATED,
        Json(ExperimentResponse::new(stored, &live)),
    ))
}

/// `GET /v1/experiments`.
pub async fn list_experiments(
    State(state): State<AppState>,
) -> Result<Json<serde_json::Value>, Error> {
    let mut items = Vec::new();
    for e in state.store.experiments().await? {
        let live = state.experiments.get(&state.store, e.id).await?;
        items.push(ExperimentResponse::new(e, &live));
    }
    Ok(Json(serde_json::json!({ "items": items })))
}

/// `GET /v1/experiments/{id}`.
pub async fn get_experiment(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
) -> Result<Json<ExperimentResponse>, Error> {
    let live = state.experiments.get(&state.store, id).await?;
    let e = state
        .store
        .experiment(id)
        .await?
        .ok_or_else(|| Error::NotFound(format!("no experiment {id}")))?;
    Ok(Json(ExperimentResponse::new(e, &live)))
}
