//! `POST /v1/experiments/{id}/imports`: a file of logged transitions (CSV or Parquet, the
//! request's body) into the experiment, through the code `precond import` uses
//! ([`crate::import`]); one trajectory per episode, stored as posted ones are.
//!
//! The body is spooled to a temporary file (Parquet is read from its end) while it arrives,
//! under its own limit (`--max-import-bytes`, not the JSON body limit) and with
//! `--body-read-timeout-secs` as the longest wait for the next chunk; the import holds one of the
//! server's slots for large transfers (`--max-concurrent-exports`) from before the first byte
//! is read until the answer. The body must be declared as CSV (`text/csv`) or Parquet
//! (`application/vnd.apache.parquet`), or as `application/octet-stream` with `format`: no
//! web page can send such a request without the server's CORS consent.

use super::AppState;
use super::error::{ApiError, ApiResult};
use super::extract::{ApiPath, ApiQuery, BodyReadTimeout, DEFAULT_BODY_READ_TIMEOUT};
use crate::api::{ImportFormat, ImportQuery};
use crate::import::ImportReport;
use crate::import::mapping::Given;
use crate::import::table::Format;
use crate::limits::MAX_TRANSITIONS;
use crate::service::imports::{ImportFile, check_import};
use axum::Json;
use axum::extract::{Request, State};
use axum::http::header;
use futures_util::StreamExt;
use std::io::Write;

/// The format the request declares: its `format`, else its `Content-Type`.
fn format_of(query: Option<ImportFormat>, content_type: Option<&str>) -> ApiResult<Format> {
    let declared = content_type
        .map(|c| {
            c.split(';')
                .next()
                .unwrap_or("")
                .trim()
                .to_ascii_lowercase()
        })
        .unwrap_or_default();
    let from_type = match declared.as_str() {
        "text/csv" => Some(Format::Csv),
        "application/vnd.apache.parquet" | "application/x-parquet" => Some(Format::Parquet),
        "application/octet-stream" => None,
        _ => {
            return Err(ApiError::UnsupportedMediaType(format!(
                "an import's body is the file: declare it as text/csv, \
                 application/vnd.apache.parquet, or application/octet-stream with `format` \
                 (got {:?})",
                declared
            )));
        }
    };
    match (query, from_type) {
        (Some(ImportFormat::Csv), _) => Ok(Format::Csv),
        (Some(ImportFormat::Parquet), _) => Ok(Format::Parquet),
        (None, Some(f)) => Ok(f),
        (None, None) => Err(ApiError::validation(
            "format",
            "an application/octet-stream body needs `format` (csv or parquet)",
        )),
    }
}

/// A comma-separated column list (`None` when absent).
fn columns(list: Option<&str>) -> Option<Vec<String>> {
    list.map(|l| l.split(',').map(|c| c.trim().to_string()).collect())
}

/// `POST /v1/experiments/{id}/imports`.
pub async fn create_import(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiQuery(query): ApiQuery<ImportQuery>,
    request: Request,
) -> ApiResult<Json<ImportReport>> {
    let content_type = request
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(str::to_string);
    let format = format_of(query.format, content_type.as_deref())?;
    if let Some(n) = query.max_transitions
        && !(1..=MAX_TRANSITIONS).contains(&n)
    {
        return Err(ApiError::validation(
            "max_transitions",
            format!("must be 1 to {MAX_TRANSITIONS}, got {n}"),
        ));
    }
    let dataset_id = check_import(
        &query.dataset,
        query.label.as_deref(),
        query.dataset_id.as_deref(),
    )?;
    // The experiment first: nothing is read for one that does not exist.
    state.service.live(id).await?;
    let slot = state.service.transfer_slot().await?;
    let within = request
        .extensions()
        .get::<BodyReadTimeout>()
        .map_or(DEFAULT_BODY_READ_TIMEOUT, |t| t.0);
    let limit = state.config.max_import_bytes;
    let file = spool(request, limit, within).await?;
    let given = Given {
        as_query: true,
        state: columns(query.state.as_deref()),
        action: columns(query.action.as_deref()),
        next_state: columns(query.next_state.as_deref()),
        predicted: columns(query.predicted_state.as_deref()),
        episode: query.episode.clone(),
    };
    let report = state
        .service
        .import(
            id,
            ImportFile {
                path: file.path().to_path_buf(),
                format,
                given,
                dataset: query.dataset,
                dataset_id,
                label: query.label,
                max_body_bytes: state.config.max_body_bytes,
                max_transitions: query.max_transitions,
            },
            slot,
        )
        .await?;
    drop(file);
    Ok(Json(report))
}

/// The body, written to a temporary file as it arrives (removed when dropped); `413` past
/// `limit` bytes, `408` when no chunk arrives for `within`.
async fn spool(
    request: Request,
    limit: usize,
    within: std::time::Duration,
) -> ApiResult<tempfile::NamedTempFile> {
    let mut file = tokio::task::spawn_blocking(tempfile::NamedTempFile::new)
        .await
        .map_err(|e| ApiError::Service(crate::service::Error::Internal(e.into())))?
        .map_err(|e| {
            ApiError::Service(crate::service::Error::Internal(
                anyhow::Error::new(e).context("creating the import's temporary file"),
            ))
        })?;
    let mut stream = request.into_body().into_data_stream();
    let mut written = 0usize;
    loop {
        let next = tokio::time::timeout(within, stream.next())
            .await
            .map_err(|_| {
                ApiError::RequestTimeout(format!(
                    "no part of the file arrived for {} s",
                    within.as_secs_f64()
                ))
            })?;
        let Some(chunk) = next else { break };
        let chunk =
            chunk.map_err(|e| ApiError::BadRequest(format!("could not read the file: {e}")))?;
        written += chunk.len();
        if written > limit {
            return Err(ApiError::PayloadTooLarge { limit });
        }
        // Chunks are small (tens of KiB): a write to the page cache, not worth a thread.
        file.write_all(&chunk).map_err(|e| {
            ApiError::Service(crate::service::Error::from_io(
                e,
                "writing the import's temporary file",
            ))
        })?;
    }
    file.flush().map_err(|e| {
        ApiError::Service(crate::service::Error::from_io(
            e,
            "writing the import's temporary file",
        ))
    })?;
    Ok(file)
}
