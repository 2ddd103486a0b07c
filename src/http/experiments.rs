//! `/v1/experiments`: create, list, show.

use super::AppState;
use super::auth::Caller;
use super::error::ApiResult;
use super::extract::{ApiJson, ApiPath};
use super::render;
use crate::api::{ExperimentList, ExperimentRequest, ExperimentResponse};
use axum::extract::State;
use axum::http::StatusCode;
use axum::{Extension, Json};

/// `POST /v1/experiments`.
pub async fn create_experiment(
    State(state): State<AppState>,
    ApiJson(request): ApiJson<ExperimentRequest>,
) -> ApiResult<(StatusCode, Json<ExperimentResponse>)> {
    let created = state.service.create_experiment(request).await?;
    Ok((StatusCode::CREATED, Json(render::experiment(created))))
}

/// `GET /v1/experiments`: every experiment the caller's token reaches (all without tokens).
pub async fn list_experiments(
    State(state): State<AppState>,
    caller: Option<Extension<Caller>>,
) -> ApiResult<Json<ExperimentList>> {
    let items = state.service.experiments().await?;
    let visible = |id: i64| caller.as_ref().is_none_or(|c| c.scope.allows(id));
    Ok(Json(ExperimentList {
        items: items
            .into_iter()
            .filter(|e| visible(e.experiment.id))
            .map(render::experiment)
            .collect(),
    }))
}

/// `GET /v1/experiments/{id}`.
pub async fn get_experiment(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
) -> ApiResult<Json<ExperimentResponse>> {
    let e = state.service.experiment(id).await?;
    Ok(Json(render::experiment(e)))
}
