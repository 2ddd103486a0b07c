//! Liveness and readiness.

use super::AppState;
use crate::error::Error;
use axum::Json;
use axum::extract::State;
use serde_json::{Value, json};

/// `GET /healthz`: the process is alive.
pub async fn get_health() -> Json<Value> {
    Json(json!({"status": "ok"}))
}

/// `GET /readyz`: the database answers.
pub async fn get_readiness(State(state): State<AppState>) -> Result<Json<Value>, Error> {
    state
        .store
        .ping()
        .await
        .map_err(|e| Error::Unavailable(format!("database not answering: {e}")))?;
    Ok(Json(json!({"status": "ready"})))
}
