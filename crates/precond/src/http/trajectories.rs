//! `/v1/experiments/{id}/trajectories` and `/transitions`: ingest executed trajectories, read
//! them back (JSON pages or CSV).

use super::AppState;
use super::error::{ApiError, ApiResult};
use super::extract::{ApiJson, ApiPath, ApiQuery};
use super::render;
use super::stream;
use crate::api::{TrajectoryRequest, TrajectoryResponse, TransitionPage, TransitionsQuery};
use crate::domain::Domain;
use crate::limits::{DEFAULT_PAGE, MAX_CSV_ROWS, MAX_PAGE};
use crate::records::StoredTransition;
use axum::Json;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, header};
use axum::response::{IntoResponse, Response};
use std::io::Write;

/// `POST /v1/experiments/{id}/trajectories`: validate, label and store one trajectory
/// atomically; a retry with the same `Idempotency-Key` replays the first answer.
pub async fn create_trajectory(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    headers: HeaderMap,
    ApiJson(request): ApiJson<TrajectoryRequest>,
) -> ApiResult<Response> {
    let key = headers.get("idempotency-key").map(|v| v.as_bytes());
    let ingested = state.service.ingest(id, request, key).await?;
    Ok(render::created(
        render::trajectory_created(&ingested),
        ingested.replayed,
    ))
}

/// `GET /v1/experiments/{id}/trajectories/{tid}`.
pub async fn get_trajectory(
    State(state): State<AppState>,
    ApiPath((id, tid)): ApiPath<(i64, i64)>,
) -> ApiResult<Json<TrajectoryResponse>> {
    let t = state.service.trajectory(id, tid).await?;
    Ok(Json(render::trajectory(t)))
}

/// CSV when the client accepts `text/csv` and not JSON (a client that accepts both gets JSON).
fn wants_csv(headers: &HeaderMap) -> bool {
    headers
        .get_all(header::ACCEPT)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .fold((false, false), |(csv, json), v| {
            (
                csv || v.contains("text/csv"),
                json || v.contains("application/json"),
            )
        })
        == (true, false)
}

/// `GET /v1/experiments/{id}/transitions`: a page of transitions as JSON, or CSV when the client
/// sends `Accept: text/csv`.
pub async fn list_transitions(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiQuery(query): ApiQuery<TransitionsQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let csv = wants_csv(&headers);
    let max = if csv { MAX_CSV_ROWS } else { MAX_PAGE };
    if query.limit.is_some_and(|l| !(1..=max).contains(&l)) {
        return Err(ApiError::validation(
            "limit",
            format!("must be between 1 and {max}"),
        ));
    }
    if !csv {
        let limit = query.limit.unwrap_or(DEFAULT_PAGE);
        let (items, next) = state
            .service
            .transitions(id, query.after, Some(limit))
            .await?;
        return Ok(Json(TransitionPage { items, next }).into_response());
    }
    // Every transition by default: written page by page from the database, never whole.
    let export = state
        .service
        .prepare_transitions_export(id, query.after, query.limit)
        .await?;
    let next = export.next;
    let body = stream::produced_body(export, "transitions CSV", |export, w| {
        w.write_all(csv_header(export.domain.as_ref(), &export.models).as_bytes())?;
        loop {
            let page = w
                .block_on(export.next_page())
                .map_err(std::io::Error::other)?;
            if page.is_empty() {
                return Ok(());
            }
            w.write_all(csv_rows(&page, &export.models).as_bytes())?;
        }
    });
    let mut response = ([(header::CONTENT_TYPE, "text/csv; charset=utf-8")], body).into_response();
    if let Some(next) = next {
        response
            .headers_mut()
            .insert("x-next-cursor", HeaderValue::from(next));
    }
    Ok(response)
}

/// The CSV's header line: `id`, `trajectory_id`, `step`, then the state, action, next state
/// and predicted next state by the domain's names, `deviation`, then each further model's
/// deviation (`deviation.<model>`, empty where its label is missing).
fn csv_header(domain: &dyn Domain, models: &[String]) -> String {
    let state_names = &domain.state_space().names;
    let action_names = &domain.action_space().names;
    let mut header = vec!["id".to_string(), "trajectory_id".into(), "step".into()];
    header.extend(state_names.iter().map(|n| format!("s.{n}")));
    header.extend(action_names.iter().map(|n| format!("a.{n}")));
    header.extend(state_names.iter().map(|n| format!("s_next.{n}")));
    header.extend(state_names.iter().map(|n| format!("s_pred.{n}")));
    header.push("deviation".into());
    header.extend(models.iter().map(|m| format!("deviation.{m}")));
    let mut out = header.join(",");
    out.push('\n');
    out
}

/// One CSV line per transition.
fn csv_rows(items: &[StoredTransition], models: &[String]) -> String {
    let mut out = String::new();
    for t in items {
        let mut row = vec![
            t.id.to_string(),
            t.trajectory_id.to_string(),
            t.step.to_string(),
        ];
        for v in [&t.s, &t.a, &t.s_next, &t.s_pred] {
            row.extend(v.iter().map(|x| x.to_string()));
        }
        row.push(t.deviation.to_string());
        for m in models {
            let label = t.labels.iter().flatten().find(|l| l.model == *m);
            row.push(
                label
                    .and_then(|l| l.deviation)
                    .map(|d| d.to_string())
                    .unwrap_or_default(),
            );
        }
        out.push_str(&row.join(","));
        out.push('\n');
    }
    out
}
