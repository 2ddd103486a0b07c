//! Extractors whose rejections speak the one error shape.
//!
//! [`ApiJson`] reads the body itself so that it can tell apart an oversized body (413), malformed
//! JSON (400) and well-formed JSON with a wrong field (422, naming the field's path, e.g.
//! `transitions[3].s`). A body must be declared as JSON (`Content-Type: application/json`,
//! parameters such as `charset` allowed): anything else is `415 unsupported_media_type`, so a
//! page on another site cannot make a browser post JSON disguised as a form or as text (a
//! "simple" request needs no CORS preflight, and would otherwise be parsed as JSON whatever its
//! type). With curl: `-H 'Content-Type: application/json'` (or `--json`).

use super::error::ApiError;
use axum::body::Bytes;
use axum::extract::rejection::{PathRejection, QueryRejection};
use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::{HeaderMap, StatusCode, header};
use serde::de::DeserializeOwned;

/// A JSON body deserialised with field paths in its errors.
#[derive(Debug)]
pub struct ApiJson<T>(pub T);

impl<S, T> FromRequest<S> for ApiJson<T>
where
    S: Send + Sync,
    T: DeserializeOwned,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        check_json_content_type(req.headers())?;
        let limit = req
            .extensions()
            .get::<BodyLimit>()
            .map(|l| l.0)
            .unwrap_or(0);
        let within = req
            .extensions()
            .get::<BodyReadTimeout>()
            .map_or(DEFAULT_BODY_READ_TIMEOUT, |t| t.0);
        let read = tokio::time::timeout(within, Bytes::from_request(req, state))
            .await
            .map_err(|_| {
                ApiError::RequestTimeout(format!(
                    "the request body did not arrive within {} s",
                    within.as_secs_f64()
                ))
            })?;
        let bytes = read.map_err(|r| {
            if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
                ApiError::PayloadTooLarge { limit }
            } else {
                ApiError::BadRequest(format!("could not read the request body: {r}"))
            }
        })?;
        parse_json(&bytes).map(ApiJson)
    }
}

/// Whether the headers declare a JSON body: `Content-Type` `application/json` (any case, any
/// parameters). A request without a body (no `Content-Type`, and `Content-Length: 0` or no
/// length at all) passes: its empty body is then refused as malformed JSON. Otherwise `415`
/// naming what was sent.
pub fn check_json_content_type(headers: &HeaderMap) -> Result<(), ApiError> {
    let declared = headers
        .get(header::CONTENT_TYPE)
        .map(|v| String::from_utf8_lossy(v.as_bytes()).into_owned());
    let empty = !headers.contains_key(header::TRANSFER_ENCODING)
        && headers
            .get(header::CONTENT_LENGTH)
            .is_none_or(|v| v.as_bytes() == b"0");
    match declared {
        None if empty => Ok(()),
        Some(ct)
            if ct
                .split(';')
                .next()
                .is_some_and(|essence| essence.trim().eq_ignore_ascii_case("application/json")) =>
        {
            Ok(())
        }
        declared => Err(ApiError::UnsupportedMediaType(format!(
            "the body must be JSON sent with `Content-Type: application/json` (got {}); with \
             curl: -H 'Content-Type: application/json'",
            declared.map_or("no Content-Type".to_string(), |ct| format!("{ct:?}"))
        ))),
    }
}

/// The longest time to receive a request body, put in the request extensions by the app
/// ([`HttpConfig::body_read_timeout`](super::HttpConfig::body_read_timeout)).
#[derive(Debug, Clone, Copy)]
pub struct BodyReadTimeout(pub std::time::Duration);

/// The body deadline when the app did not set one (and [`super::HttpConfig`]'s default).
pub(crate) const DEFAULT_BODY_READ_TIMEOUT: std::time::Duration =
    std::time::Duration::from_secs(60);

/// The configured body limit, put in the request extensions so errors can state it.
#[derive(Debug, Clone, Copy)]
pub struct BodyLimit(pub usize);

/// Parses JSON, mapping syntax errors to 400 and data errors to 422 with the field path.
///
/// The body must be a JSON object: serde would otherwise read a struct from an array in field
/// order, which no client means.
pub fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, ApiError> {
    if bytes.iter().find(|b| !b.is_ascii_whitespace()) != Some(&b'{') {
        return Err(
            match serde_json::from_slice::<serde::de::IgnoredAny>(bytes) {
                Ok(_) => ApiError::validation("body", "must be a JSON object"),
                Err(e) => ApiError::BadRequest(format!("malformed JSON: {e}")),
            },
        );
    }
    let mut de = serde_json::Deserializer::from_slice(bytes);
    let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let path = e.path().to_string();
        let part = part_at(bytes, e.path());
        let inner = e.into_inner();
        match inner.classify() {
            serde_json::error::Category::Data => {
                if let Some((field, reason)) = part
                    .as_ref()
                    .and_then(|p| crate::settings::locate_in_tagged(&path, p))
                {
                    return ApiError::validation(field, strip_position(&reason));
                }
                let field = if path == "." {
                    "body".to_string()
                } else {
                    path
                };
                ApiError::validation(field, strip_position(&inner.to_string()))
            }
            _ => ApiError::BadRequest(format!("malformed JSON: {inner}")),
        }
    })?;
    de.end()
        .map_err(|e| ApiError::BadRequest(format!("malformed JSON: {e}")))?;
    Ok(value)
}

/// The JSON value at `path` in `bytes` (`None` when the body does not parse or has no such
/// part): where a data error stopped, to be read again by the settings' own types.
fn part_at(bytes: &[u8], path: &serde_path_to_error::Path) -> Option<serde_json::Value> {
    use serde_path_to_error::Segment;
    let mut value: serde_json::Value = serde_json::from_slice(bytes).ok()?;
    for segment in path.iter() {
        value = match segment {
            Segment::Map { key } => value.get_mut(key.as_str())?.take(),
            Segment::Seq { index } => value.get_mut(*index)?.take(),
            Segment::Enum { .. } | Segment::Unknown => return None,
        };
    }
    Some(value)
}

/// serde_json appends " at line L column C"; the field path says more, so drop it.
fn strip_position(message: &str) -> String {
    match message.rfind(" at line ") {
        Some(i) => message[..i].to_string(),
        None => message.to_string(),
    }
}

/// Path parameters; a parameter that does not parse names no existing resource (404).
#[derive(Debug, FromRequestParts)]
#[from_request(via(axum::extract::Path), rejection(ApiError))]
pub struct ApiPath<T>(pub T);

impl From<PathRejection> for ApiError {
    fn from(r: PathRejection) -> Self {
        ApiError::not_found(format!("no such resource: {}", r.body_text()))
    }
}

/// Query parameters; a bad one is a 422 naming it.
#[derive(Debug, FromRequestParts)]
#[from_request(via(axum::extract::Query), rejection(ApiError))]
pub struct ApiQuery<T>(pub T);

impl From<QueryRejection> for ApiError {
    fn from(r: QueryRejection) -> Self {
        ApiError::validation("query", r.body_text())
    }
}
