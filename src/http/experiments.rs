//! `/v1/experiments`: create, list, show.

use super::AppState;
use super::error::ApiResult;
use super::extract::{ApiJson, ApiPath, ApiQuery};
use super::render;
use crate::api::{ExperimentList, ExperimentRequest, ExperimentResponse, ExperimentsQuery};
use crate::service::experiments::next_offset;
use axum::Json;
use axum::extract::State;
use axum::http::StatusCode;

/// `POST /v1/experiments`.
pub async fn create_experiment(
    State(state): State<AppState>,
    ApiJson(request): ApiJson<ExperimentRequest>,
) -> ApiResult<(StatusCode, Json<ExperimentResponse>)> {
    let created = state.service.create_experiment(request).await?;
    Ok((StatusCode::CREATED, Json(render::experiment(created))))
}

/// `GET /v1/experiments?order=&offset=&limit=`: every experiment (oldest first) by default,
/// or one page.
pub async fn list_experiments(
    State(state): State<AppState>,
    ApiQuery(query): ApiQuery<ExperimentsQuery>,
) -> ApiResult<Json<ExperimentList>> {
    let (items, total) = state
        .service
        .experiments(query.order, query.offset, query.limit)
        .await?;
    let next = next_offset(query.offset, items.len(), total);
    Ok(Json(ExperimentList {
        items: items.into_iter().map(render::experiment).collect(),
        total,
        next,
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
