//! `/v1/experiments/{id}/runs`, `/timeline` and `/labels`: an experiment's history, read-only.

use super::AppState;
use super::error::ApiResult;
use super::extract::{ApiPath, ApiQuery};
use super::render;
use crate::api::{ModelLabels, PageQuery, RunPage, Timeline};
use axum::Json;
use axum::extract::State;

/// `GET /v1/experiments/{id}/runs?offset=&limit=`: proposals with the trajectories that
/// executed them, and trajectories posted without a proposal, newest first.
pub async fn list_runs(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiQuery(query): ApiQuery<PageQuery>,
) -> ApiResult<Json<RunPage>> {
    let runs = state.service.runs(id, query.offset, query.limit).await?;
    Ok(Json(render::runs(runs)))
}

/// `GET /v1/experiments/{id}/timeline`: per-iteration statistics with `β_j`, and the model
/// versions.
pub async fn get_timeline(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
) -> ApiResult<Json<Timeline>> {
    let timeline = state.service.timeline(id).await?;
    Ok(Json(render::timeline(id, timeline)))
}

/// `GET /v1/experiments/{id}/labels`: each of the experiment's models of its robot with what
/// its labels of the executed transitions say.
pub async fn get_labels(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
) -> ApiResult<Json<ModelLabels>> {
    let (d_max, reports) = state.service.model_labels(id).await?;
    Ok(Json(render::model_labels(id, d_max, reports)))
}
