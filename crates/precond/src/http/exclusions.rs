//! `/v1/experiments/{id}/exclusions`: leave trajectories out of an experiment's model, list what
//! was left out, and restore it (the operator's `admin` role).

use super::AppState;
use super::auth::Fingerprint;
use super::error::ApiResult;
use super::extract::{ApiJson, ApiPath, ApiQuery};
use super::render;
use crate::api::{ExclusionPage, ExclusionRequest, ExclusionView, PageQuery};
use axum::Json;
use axum::extract::{Extension, State};
use axum::response::Response;

/// `POST /v1/experiments/{id}/exclusions`: `201` once the exclusion and the refit it requests
/// are stored; the refit runs in the background.
pub async fn create_exclusion(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    by: Option<Extension<Fingerprint>>,
    ApiJson(request): ApiJson<ExclusionRequest>,
) -> ApiResult<Response> {
    let by = by.map(|Extension(f)| f.0);
    let made = state.service.exclude(id, &request, by.as_deref()).await?;
    Ok(render::created(render::exclusion(id, made), false))
}

/// `GET /v1/experiments/{id}/exclusions?offset=&limit=`: newest first.
pub async fn list_exclusions(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiQuery(query): ApiQuery<PageQuery>,
) -> ApiResult<Json<ExclusionPage>> {
    let page = state
        .service
        .exclusions(id, query.offset, query.limit)
        .await?;
    Ok(Json(render::exclusions(id, page)))
}

/// `POST /v1/experiments/{id}/exclusions/{eid}/restore`: the next fit, requested here, takes
/// the trajectories in again; restoring twice changes nothing.
pub async fn restore_exclusion(
    State(state): State<AppState>,
    ApiPath((id, eid)): ApiPath<(i64, i64)>,
    by: Option<Extension<Fingerprint>>,
) -> ApiResult<Json<ExclusionView>> {
    let by = by.map(|Extension(f)| f.0);
    let restored = state
        .service
        .restore_exclusion(id, eid, by.as_deref())
        .await?;
    Ok(Json(render::exclusion(id, restored)))
}
