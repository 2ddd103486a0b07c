//! `/v1/experiments`: create, list, show.

use super::AppState;
use super::auth::Caller;
use super::auth::Scope;
use super::error::ApiResult;
use super::extract::{ApiJson, ApiPath, ApiQuery};
use super::render;
use crate::api::{ExperimentList, ExperimentRequest, ExperimentResponse, ExperimentsQuery};
use crate::service::experiments::next_offset;
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

/// `GET /v1/experiments?order=&offset=&limit=`: every experiment the caller's token reaches
/// (all without tokens), oldest first by default, or one page of them.
pub async fn list_experiments(
    State(state): State<AppState>,
    caller: Option<Extension<Caller>>,
    ApiQuery(query): ApiQuery<ExperimentsQuery>,
) -> ApiResult<Json<ExperimentList>> {
    let (items, total) = match caller.as_ref().map(|c| &c.scope) {
        // A token scoped to some experiments pages through those alone.
        Some(scope @ Scope::Only(_)) => {
            let (all, _) = state.service.experiments(query.order, 0, None).await?;
            let visible: Vec<_> = all
                .into_iter()
                .filter(|e| scope.allows(e.experiment.id))
                .collect();
            let total = visible.len() as i64;
            let page = visible
                .into_iter()
                .skip(query.offset.max(0) as usize)
                .take(query.limit.map_or(usize::MAX, |l| l.max(0) as usize))
                .collect();
            (page, total)
        }
        _ => {
            state
                .service
                .experiments(query.order, query.offset, query.limit)
                .await?
        }
    };
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
