//! `/v1/experiments/{id}/proposals` (ask: which trajectory should the robot try next?) and
//! `/plans` (test time: is there a trustworthy plan?).

use super::AppState;
use super::error::ApiResult;
use super::extract::{ApiJson, ApiPath};
use super::render;
use crate::api::{
    ContinueRequest, ContinueResponse, PlanRequest, PlanResponse, ProposalRequest, ProposalResponse,
};
use axum::Json;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use axum::response::Response;

/// `POST /v1/experiments/{id}/proposals`: `201` with a new proposal leased to the client, or
/// `200` with the client's open one for the same problem.
pub async fn create_proposal(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiJson(request): ApiJson<ProposalRequest>,
) -> ApiResult<(StatusCode, Json<ProposalResponse>)> {
    let (proposal, created) = state.service.propose(id, request).await?;
    let status = if created {
        StatusCode::CREATED
    } else {
        StatusCode::OK
    };
    Ok((status, Json(render::proposal(proposal))))
}

/// `GET /v1/experiments/{id}/proposals/{pid}`.
pub async fn get_proposal(
    State(state): State<AppState>,
    ApiPath((id, pid)): ApiPath<(i64, i64)>,
) -> ApiResult<Json<ProposalResponse>> {
    Ok(Json(render::proposal(
        state.service.proposal(id, pid).await?,
    )))
}

/// `POST /v1/experiments/{id}/proposals/{pid}/abandon`: the client will not execute it.
pub async fn abandon_proposal(
    State(state): State<AppState>,
    ApiPath((id, pid)): ApiPath<(i64, i64)>,
) -> ApiResult<Json<ProposalResponse>> {
    Ok(Json(render::proposal(
        state.service.abandon(id, pid).await?,
    )))
}

/// `POST /v1/experiments/{id}/proposals/{pid}/continue`: store the executed prefix of an open
/// proposal and propose again from where the robot is (closed loop). `201`; a retry with the
/// same `Idempotency-Key` stores nothing twice and answers the same proposal.
pub async fn continue_proposal(
    State(state): State<AppState>,
    ApiPath((id, pid)): ApiPath<(i64, i64)>,
    headers: HeaderMap,
    ApiJson(request): ApiJson<ContinueRequest>,
) -> ApiResult<Response> {
    let key = headers.get("idempotency-key").map(|v| v.as_bytes());
    let (ingested, proposal) = state
        .service
        .continue_proposal(id, pid, request, key)
        .await?;
    Ok(render::created(
        ContinueResponse {
            trajectory: render::trajectory_created(&ingested),
            proposal: render::proposal(proposal),
        },
        ingested.replayed,
    ))
}

/// `POST /v1/experiments/{id}/plans`: a test-time plan with the conservative β. Nothing is
/// stored.
pub async fn create_plan(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiJson(request): ApiJson<PlanRequest>,
) -> ApiResult<Json<PlanResponse>> {
    let planned = state.service.plan(id, request).await?;
    Ok(Json(render::plan(planned)))
}
