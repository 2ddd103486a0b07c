//! The HTTP error: every failure a client can see, with the status that fits and the one JSON
//! shape `{"error": {"code", "message", "details"}}` (`api::ErrorBody`).
//!
//! Handlers return `Result<_, ApiError>`; extractor rejections, unknown routes and panics go
//! through here too. Internal failures are logged once, here, with their cause; the client gets
//! a generic message.

use crate::api::{ErrorBody, ErrorDetail};
use crate::domain::DynamicsError;
use crate::service::Error;
use axum::Json;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};

/// `Retry-After` of a `507`: space is freed by an operator, not in a second.
const STORAGE_FULL_RETRY_SECS: u64 = 30;
/// `Retry-After` of a `503 unavailable`: a database restarting or a connection lost.
const UNAVAILABLE_RETRY_SECS: u64 = 2;

/// Everything that can go wrong in a request.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// The body is not well-formed JSON (400 `bad_request`).
    #[error("{0}")]
    BadRequest(String),
    /// The body is not declared as JSON (`Content-Type: application/json`) (415
    /// `unsupported_media_type`).
    #[error("{0}")]
    UnsupportedMediaType(String),
    /// The body did not arrive in time (408 `request_timeout`).
    #[error("{0}")]
    RequestTimeout(String),
    /// The body is larger than the configured limit (413 `payload_too_large`).
    #[error("request body larger than {limit} bytes")]
    PayloadTooLarge {
        /// The limit in bytes.
        limit: usize,
    },
    /// The route exists but not with this method (405 `method_not_allowed`).
    #[error("method not allowed on this route")]
    MethodNotAllowed,
    /// A dependency (the database) is not answering (503 `unavailable`).
    #[error("{0}")]
    Unavailable(String),
    /// No bearer token, or one the server does not know (401 `unauthorized`).
    #[error("a valid bearer token is required (Authorization: Bearer <token>)")]
    Unauthorized,
    /// The token lacks the route's role or does not reach the experiment (403 `forbidden`).
    #[error("{0}")]
    Forbidden(String),
    /// What the service answered instead of a result.
    #[error(transparent)]
    Service(#[from] Error),
}

impl ApiError {
    /// A validation failure of `field` (422 `validation_failed`).
    pub fn validation(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Service(Error::validation(field, reason))
    }

    /// A resource or route that does not exist (404 `not_found`).
    pub fn not_found(what: impl Into<String>) -> Self {
        Self::Service(Error::NotFound(what.into()))
    }

    /// The HTTP status that fits.
    pub fn status(&self) -> StatusCode {
        match self {
            Self::BadRequest(_) => StatusCode::BAD_REQUEST,
            Self::PayloadTooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            Self::UnsupportedMediaType(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            Self::RequestTimeout(_) => StatusCode::REQUEST_TIMEOUT,
            Self::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            Self::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            Self::Unauthorized => StatusCode::UNAUTHORIZED,
            Self::Forbidden(_) => StatusCode::FORBIDDEN,
            Self::Service(e) => service_status(e),
        }
    }

    /// The stable machine-readable code.
    pub fn code(&self) -> &'static str {
        match self {
            Self::BadRequest(_) => "bad_request",
            Self::PayloadTooLarge { .. } => "payload_too_large",
            Self::UnsupportedMediaType(_) => "unsupported_media_type",
            Self::RequestTimeout(_) => "request_timeout",
            Self::MethodNotAllowed => "method_not_allowed",
            Self::Unavailable(_) => "unavailable",
            Self::Unauthorized => "unauthorized",
            Self::Forbidden(_) => "forbidden",
            Self::Service(e) => service_code(e),
        }
    }

    fn details(&self) -> Value {
        match self {
            Self::PayloadTooLarge { limit } => json!({"limit_bytes": limit}),
            Self::Service(e) => service_details(e),
            _ => Value::Null,
        }
    }

    /// Seconds a client should wait before retrying, for the `Retry-After` header.
    pub fn retry_after_secs(&self) -> Option<u64> {
        match self {
            Self::Service(e) => service_retry_after(e),
            Self::Unavailable(_) => Some(UNAVAILABLE_RETRY_SECS),
            _ => None,
        }
    }

    /// The JSON body of this error.
    pub fn body(&self) -> ErrorBody {
        let message = match self {
            Self::Service(e) => service_message(e),
            other => other.to_string(),
        };
        ErrorBody {
            error: ErrorDetail {
                code: self.code().to_string(),
                message,
                details: self.details(),
            },
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        match &self {
            Self::Service(e) => log_service_failure(e.answered()),
            Self::Unavailable(reason) => tracing::warn!(%reason, "dependency unavailable"),
            _ => {}
        }
        let mut response = (self.status(), Json(self.body())).into_response();
        if let Some(secs) = self.retry_after_secs() {
            response
                .headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(secs));
        }
        if matches!(self, Self::RequestTimeout(_)) {
            // The rest of a late body is not worth waiting for.
            response
                .headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
        }
        if matches!(self, Self::Unauthorized) {
            response
                .headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        response
    }
}

/// The status of a service answer.
fn service_status(e: &Error) -> StatusCode {
    match e {
        Error::PrefixStored { error, .. } | Error::ImportStopped { error, .. } => {
            service_status(error)
        }
        Error::Validation { .. } | Error::NoPlan { .. } => StatusCode::UNPROCESSABLE_ENTITY,
        Error::NotFound(_) => StatusCode::NOT_FOUND,
        Error::Conflict(_) | Error::LeaseHeld { .. } | Error::KeyReused { .. } => {
            StatusCode::CONFLICT
        }
        Error::Dynamics(DynamicsError::Timeout { .. }) => StatusCode::GATEWAY_TIMEOUT,
        Error::Dynamics(DynamicsError::Unavailable { .. }) => StatusCode::BAD_GATEWAY,
        Error::Dynamics(DynamicsError::Busy { .. }) => StatusCode::SERVICE_UNAVAILABLE,
        Error::Dynamics(DynamicsError::NotAllowed { .. }) => StatusCode::CONFLICT,
        Error::Dynamics(DynamicsError::ClientSide) => StatusCode::UNPROCESSABLE_ENTITY,
        Error::Overloaded { .. } | Error::ExportsBusy { .. } => StatusCode::TOO_MANY_REQUESTS,
        Error::DeadlineExceeded { .. } | Error::Cancelled => StatusCode::SERVICE_UNAVAILABLE,
        Error::LimitReached(_) => StatusCode::CONFLICT,
        Error::StorageFull(_) => StatusCode::INSUFFICIENT_STORAGE,
        Error::DatabaseUnavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
        Error::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

/// The code of a service answer.
fn service_code(e: &Error) -> &'static str {
    match e {
        Error::PrefixStored { error, .. } | Error::ImportStopped { error, .. } => {
            service_code(error)
        }
        Error::Validation { .. } | Error::Dynamics(DynamicsError::ClientSide) => {
            "validation_failed"
        }
        Error::NotFound(_) => "not_found",
        Error::Conflict(_) | Error::LeaseHeld { .. } | Error::KeyReused { .. } => "conflict",
        Error::NoPlan { .. } => "no_plan",
        Error::Dynamics(DynamicsError::Timeout { .. }) => "model_timeout",
        Error::Dynamics(DynamicsError::Unavailable { .. }) => "model_unavailable",
        Error::Dynamics(DynamicsError::Busy { .. }) => "model_busy",
        Error::Dynamics(DynamicsError::NotAllowed { .. }) => "model_not_allowed",
        Error::Overloaded { .. } | Error::ExportsBusy { .. } => "overloaded",
        Error::DeadlineExceeded { .. } => "deadline_exceeded",
        Error::Cancelled => "cancelled",
        Error::LimitReached(_) => "limit_reached",
        Error::StorageFull(_) => "insufficient_storage",
        Error::DatabaseUnavailable(_) => "unavailable",
        Error::Internal(_) => "internal",
    }
}

/// The details of a service answer.
fn service_details(e: &Error) -> Value {
    match e {
        Error::PrefixStored {
            trajectory_id,
            error,
        } => {
            let mut details = match service_details(error) {
                Value::Object(map) => map,
                _ => serde_json::Map::new(),
            };
            details.insert("stored_trajectory_id".into(), json!(trajectory_id));
            Value::Object(details)
        }
        Error::ImportStopped { stop, error } => {
            let mut details = match service_details(error) {
                Value::Object(map) => map,
                _ => serde_json::Map::new(),
            };
            details.insert("import".into(), json!(stop));
            Value::Object(details)
        }
        Error::Validation { field, reason } => json!({"field": field, "reason": reason}),
        Error::KeyReused { field, difference } => {
            json!({"field": field, "reason": difference})
        }
        Error::LeaseHeld {
            proposal_id,
            client_id,
            start,
            goal,
        } => json!({"proposal_id": proposal_id, "client_id": client_id,
                    "start": start, "goal": goal}),
        Error::NoPlan {
            extensions,
            candidates,
        } if candidates.is_empty() => json!({"extensions": extensions}),
        Error::NoPlan {
            extensions,
            candidates,
        } => json!({"extensions": extensions, "candidates": candidates}),
        Error::Dynamics(DynamicsError::Timeout { model, timeout_ms }) => {
            json!({"model": model, "timeout_ms": timeout_ms})
        }
        Error::Dynamics(
            DynamicsError::Unavailable { model, reason }
            | DynamicsError::Busy { model, reason }
            | DynamicsError::NotAllowed { model, reason },
        ) => json!({"model": model, "reason": reason}),
        Error::Dynamics(DynamicsError::ClientSide) => {
            json!({"field": "domain.model", "reason": e.to_string()})
        }
        Error::Overloaded { retry_after_secs }
        | Error::ExportsBusy {
            retry_after_secs, ..
        } => {
            json!({"retry_after_seconds": retry_after_secs})
        }
        Error::DeadlineExceeded {
            extensions,
            timeout_ms,
            retry_after_secs,
        } => json!({"extensions": extensions, "timeout_ms": timeout_ms,
                    "retry_after_seconds": retry_after_secs}),
        _ => Value::Null,
    }
}

/// Logs what the operator should see of a service answer (once, here).
fn log_service_failure(e: &Error) {
    match e {
        Error::Internal(cause) => tracing::error!(error = ?cause, "request failed"),
        Error::Dynamics(e) => tracing::warn!(error = %e, "dynamics model failed"),
        Error::DatabaseUnavailable(reason) => tracing::warn!(%reason, "database unavailable"),
        Error::StorageFull(reason) => {
            tracing::error!(%reason, "the database's disk is full: writes are refused")
        }
        _ => {}
    }
}

/// `Retry-After` of a service answer.
fn service_retry_after(e: &Error) -> Option<u64> {
    match e.answered() {
        Error::Overloaded { retry_after_secs }
        | Error::ExportsBusy {
            retry_after_secs, ..
        }
        | Error::DeadlineExceeded {
            retry_after_secs, ..
        } => Some(*retry_after_secs),
        Error::Dynamics(DynamicsError::Busy { .. }) => Some(1),
        Error::StorageFull(_) => Some(STORAGE_FULL_RETRY_SECS),
        Error::DatabaseUnavailable(_) => Some(UNAVAILABLE_RETRY_SECS),
        _ => None,
    }
}

/// The message of a service answer: never an internal failure's cause.
fn service_message(e: &Error) -> String {
    match e {
        Error::Internal(_) => "internal server error".to_string(),
        Error::PrefixStored {
            trajectory_id,
            error,
        } => format!(
            "{} (the executed prefix is stored as trajectory {trajectory_id})",
            service_message(error)
        ),
        Error::ImportStopped { stop, error } => format!(
            "{} (the import stopped at {stop}; {} of its trajectories were stored before: \
             importing again skips them)",
            service_message(error),
            stop.stored_before.trajectories
        ),
        other => other.to_string(),
    }
}

/// Result alias for handlers.
pub type ApiResult<T> = std::result::Result<T, ApiError>;
