//! `/v1/experiments/{id}/precondition/map` and `/model/diagnostics`: a model version on a grid,
//! and its leave-one-out calibration.

use super::AppState;
use super::error::ApiResult;
use super::extract::{ApiPath, ApiQuery};
use super::model::parse_vector;
use super::render;
use crate::api::{Diagnostics, DiagnosticsQuery, MapQuery, PreconditionMap};
use crate::service::MapRequest;
use axum::Json;
use axum::extract::State;

/// `GET /v1/experiments/{id}/precondition/map?x=&y=&s=&a=&nx=&ny=&version=`.
pub async fn get_precondition_map(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiQuery(query): ApiQuery<MapQuery>,
) -> ApiResult<Json<PreconditionMap>> {
    let request = MapRequest {
        s: query
            .s
            .as_deref()
            .map(|s| parse_vector("s", s))
            .transpose()?,
        a: query
            .a
            .as_deref()
            .map(|a| parse_vector("a", a))
            .transpose()?,
        x: query.x,
        y: query.y,
        nx: query.nx,
        ny: query.ny,
        version: query.version,
        model: query.model,
    };
    let grid = state.service.precondition_map(id, request).await?;
    Ok(Json(render::map(grid)))
}

/// `GET /v1/experiments/{id}/model/diagnostics?version=&beta=`.
pub async fn get_model_diagnostics(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiQuery(query): ApiQuery<DiagnosticsQuery>,
) -> ApiResult<Json<Diagnostics>> {
    let d = state
        .service
        .diagnostics(id, query.version, query.beta)
        .await?;
    Ok(Json(render::diagnostics(id, d)))
}
