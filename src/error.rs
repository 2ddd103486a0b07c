//! The one application error type and its one JSON shape:
//! `{"error": {"code": "...", "message": "...", "details": ...}}`.
//!
//! Handlers return `Result<_, Error>`; every failure a client can see goes through
//! [`Error::into_response`], including extractor rejections, unknown routes and panics. Internal
//! failures are logged once, here, with their cause; the client gets a generic message.

use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};

/// Everything that can go wrong in a request, by what the client should do about it.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The body is not well-formed JSON (400 `bad_request`).
    #[error("{0}")]
    BadRequest(String),
    /// A field has the wrong type, dimension, range or value (422 `validation_failed`).
    #[error("{field}: {reason}")]
    Validation {
        /// Path of the offending field, e.g. `transitions[3].s`.
        field: String,
        /// Why it is wrong.
        reason: String,
    },
    /// The resource does not exist (404 `not_found`).
    #[error("{0}")]
    NotFound(String),
    /// The request conflicts with what is stored, e.g. an idempotency key reused with another
    /// body (409 `conflict`).
    #[error("{0}")]
    Conflict(String),
    /// The body is larger than the configured limit (413 `payload_too_large`).
    #[error("request body larger than {limit} bytes")]
    PayloadTooLarge {
        /// The limit in bytes.
        limit: usize,
    },
    /// The route exists but not with this method (405 `method_not_allowed`).
    #[error("method not allowed on this route")]
    MethodNotAllowed,
    /// The planner found no goal-reaching trajectory (422 `no_plan`).
    #[error("no goal-reaching trajectory within {extensions} extensions")]
    NoPlan {
        /// Extensions used by the search.
        extensions: usize,
    },
    /// A dependency (the database) is not answering (503 `unavailable`).
    #[error("{0}")]
    Unavailable(String),
    /// Anything else: logged with its cause, reported as 500 `internal` without details.
    #[error(transparent)]
    Internal(#[from] anyhow::Error),
}

impl Error {
    /// A validation failure on `field`.
    pub fn validation(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Validation {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// The HTTP status that fits.
    pub fn status(&self) -> StatusCode {
        match self {
            Self::BadRequest(_) => StatusCode::BAD_REQUEST,
            Self::Validation { .. } | Self::NoPlan { .. } => StatusCode::UNPROCESSABLE_ENTITY,
            Self::NotFound(_) => StatusCode::NOT_FOUND,
            Self::Conflict(_) => StatusCode::CONFLICT,
            Self::PayloadTooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            Self::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            Self::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            Self::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    /// The stable machine-readable code.
    pub fn code(&self) -> &'static str {
        match self {
            Self::BadRequest(_) => "bad_request",
            Self::Validation { .. } => "validation_failed",
            Self::NotFound(_) => "not_found",
            Self::Conflict(_) => "conflict",
            Self::PayloadTooLarge { .. } => "payload_too_large",
            Self::MethodNotAllowed => "method_not_allowed",
            Self::NoPlan { .. } => "no_plan",
            Self::Unavailable(_) => "unavailable",
            Self::Internal(_) => "internal",
        }
    }

    fn details(&self) -> Value {
        match self {
            Self::Validation { field, reason } => json!({"field": field, "reason": reason}),
            Self::PayloadTooLarge { limit } => json!({"limit_bytes": limit}),
            Self::NoPlan { extensions } => json!({"extensions": extensions}),
            _ => Value::Null,
        }
    }

    /// The JSON body of this error.
    pub fn body(&self) -> Value {
        let message = match self {
            Self::Internal(_) => "internal server error".to_string(),
            other => other.to_string(),
        };
        json!({"error": {"code": self.code(), "message": message, "details": self.details()}})
    }
}

impl IntoResponse for Error {
    fn into_response(self) -> Response {
        match &self {
            Self::Internal(cause) => tracing::error!(error = ?cause, "request failed"),
            Self::Unavailable(reason) => tracing::warn!(%reason, "dependency unavailable"),
            _ => {}
        }
        (self.status(), Json(self.body())).into_response()
    }
}

impl From<sqlx::Error> for Error {
    fn from(e: sqlx::Error) -> Self {
        Self::Internal(anyhow::Error::new(e).context("database"))
    }
}

/// Result alias for handlers and the store.
pub type Result<T, E = Error> = std::result::Result<T, E>;
