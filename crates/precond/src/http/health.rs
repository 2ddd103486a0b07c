//! Liveness and readiness.

use super::AppState;
use super::error::{ApiError, ApiResult};
use crate::api::HealthResponse;
use axum::Json;
use axum::extract::State;

/// `GET /healthz`: the process is alive.
pub async fn get_health() -> Json<HealthResponse> {
    Json(HealthResponse {
        status: "ok".into(),
    })
}

/// `GET /readyz`: the database answers, within a second, and writes are not failing for lack
/// of space.
pub async fn get_readiness(State(state): State<AppState>) -> ApiResult<Json<HealthResponse>> {
    state
        .service
        .ready()
        .await
        .map_err(|e| ApiError::Unavailable(e.to_string()))?;
    Ok(Json(HealthResponse {
        status: "ready".into(),
    }))
}
