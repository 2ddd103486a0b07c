//! `/v1/experiments/{id}/trajectories` and `/transitions`: ingest executed trajectories, read
//! them back.

use super::AppState;
use super::extract::{ApiJson, ApiPath, ApiQuery};
use crate::error::Error;
use crate::live::LiveExperiment;
use crate::store::{IdempotencyKey, IngestOutcome, NewTransition, StoredTrajectory, Transition};
use axum::Json;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

/// Most transitions in one posted trajectory.
pub const MAX_TRANSITIONS: usize = 10_000;
/// Longest accepted `Idempotency-Key`.
pub const MAX_IDEMPOTENCY_KEY_LEN: usize = 200;

/// One executed transition as a client posts it.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransitionRequest {
    /// State before the action.
    pub s: Vec<f64>,
    /// Action executed.
    pub a: Vec<f64>,
    /// State observed after it.
    pub s_next: Vec<f64>,
}

/// `POST /v1/experiments/{id}/trajectories` body.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrajectoryRequest {
    /// The proposal this trajectory executed; closes its lease.
    #[serde(default)]
    pub proposal_id: Option<i64>,
    /// The robot stopped before the end of what it meant to execute.
    #[serde(default)]
    pub partial: bool,
    /// The executed transitions, in order.
    pub transitions: Vec<TransitionRequest>,
}

/// Validates every transition against the domain and labels it.
pub fn label_transitions(
    live: &LiveExperiment,
    transitions: &[TransitionRequest],
) -> Result<Vec<NewTransition>, Error> {
    if transitions.is_empty() {
        return Err(Error::validation(
            "transitions",
            "must hold at least one transition",
        ));
    }
    if transitions.len() > MAX_TRANSITIONS {
        return Err(Error::validation(
            "transitions",
            format!("at most {MAX_TRANSITIONS} transitions per trajectory"),
        ));
    }
    let domain = live.domain.as_ref();
    transitions
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let field = |name: &str| format!("transitions[{i}].{name}");
            domain
                .validate_state(&t.s)
                .map_err(|e| Error::validation(field("s"), e.0))?;
            domain
                .validate_action(&t.a)
                .map_err(|e| Error::validation(field("a"), e.0))?;
            domain
                .validate_step(&t.s, &t.a)
                .map_err(|e| Error::validation(field("a"), e.0))?;
            domain
                .validate_observed_state(&t.s_next)
                .map_err(|e| Error::validation(field("s_next"), e.0))?;
            let s_pred = domain.predict(&t.s, &t.a);
            let deviation = domain.distance(&s_pred, &t.s_next);
            if !deviation.is_finite() {
                return Err(Error::validation(
                    field("s_next"),
                    "the deviation from the prediction is not a finite number",
                ));
            }
            Ok(NewTransition {
                s: t.s.clone(),
                a: t.a.clone(),
                s_next: t.s_next.clone(),
                s_pred,
                deviation,
            })
        })
        .collect()
}

fn idempotency_key(headers: &HeaderMap) -> Result<Option<String>, Error> {
    let Some(value) = headers.get("idempotency-key") else {
        return Ok(None);
    };
    let key = value
        .to_str()
        .ok()
        .filter(|k| !k.is_empty() && k.len() <= MAX_IDEMPOTENCY_KEY_LEN)
        .ok_or_else(|| {
            Error::validation(
                "Idempotency-Key",
                format!("must be 1 to {MAX_IDEMPOTENCY_KEY_LEN} visible ASCII characters"),
            )
        })?;
    Ok(Some(key.to_string()))
}

/// `POST /v1/experiments/{id}/trajectories`: validate, label and store one trajectory atomically.
pub async fn create_trajectory(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    headers: HeaderMap,
    ApiJson(request): ApiJson<TrajectoryRequest>,
) -> Result<Response, Error> {
    let live = state.experiments.get(&state.store, id).await?;
    let key = idempotency_key(&headers)?;
    let labelled = label_transitions(&live, &request.transitions)?;
    let canonical = serde_json::to_string(&request).map_err(anyhow::Error::from)?;
    let batch_size = i64::from(live.settings.learning.batch_size);
    let model_version = live.model().version;
    let outcome = state
        .store
        .ingest_trajectory(
            id,
            request.proposal_id,
            request.partial,
            &labelled,
            key.as_deref().map(|key| IdempotencyKey {
                key,
                request: &canonical,
            }),
            |t: &StoredTrajectory, n_trajectories| {
                json!({
                    "id": t.id,
                    "experiment_id": t.experiment_id,
                    "proposal_id": t.proposal_id,
                    "partial": t.partial,
                    "n_transitions": t.transitions.len(),
                    "deviations": t.transitions.iter().map(|x| x.deviation).collect::<Vec<_>>(),
                    "iteration": n_trajectories / batch_size,
                    "model_version": model_version,
                    "n_trajectories": n_trajectories,
                    "created_at": t.created_at,
                })
            },
        )
        .await?;
    match outcome {
        IngestOutcome::Created(body) => {
            tracing::info!(experiment = id, n = labelled.len(), "trajectory stored");
            let n_trajectories = body["n_trajectories"].as_i64().unwrap_or(0);
            if n_trajectories % batch_size == 0 {
                live.schedule_refit(&state.store);
            }
            Ok((StatusCode::CREATED, Json(body)).into_response())
        }
        IngestOutcome::Replayed { status, body } => {
            let status = StatusCode::from_u16(status).unwrap_or(StatusCode::CREATED);
            let mut response = (status, Json(body)).into_response();
            response
                .headers_mut()
                .insert("idempotent-replayed", HeaderValue::from_static("true"));
            Ok(response)
        }
        IngestOutcome::KeyReused => Err(Error::Conflict(
            "this Idempotency-Key was already used with a different request".into(),
        )),
        IngestOutcome::ProposalNotFound => Err(Error::validation(
            "proposal_id",
            format!(
                "no proposal {} in experiment {id}",
                request.proposal_id.unwrap_or_default()
            ),
        )),
        IngestOutcome::ProposalAlreadyExecuted => Err(Error::Conflict(format!(
            "proposal {} was already executed: its trajectory is stored",
            request.proposal_id.unwrap_or_default()
        ))),
    }
}

/// `GET /v1/experiments/{id}/trajectories/{tid}`.
pub async fn get_trajectory(
    State(state): State<AppState>,
    ApiPath((id, tid)): ApiPath<(i64, i64)>,
) -> Result<Json<Value>, Error> {
    state.experiments.get(&state.store, id).await?;
    let t = state
        .store
        .trajectory(id, tid)
        .await?
        .ok_or_else(|| Error::NotFound(format!("no trajectory {tid} in experiment {id}")))?;
    Ok(Json(json!({
        "id": t.id,
        "experiment_id": t.experiment_id,
        "proposal_id": t.proposal_id,
        "partial": t.partial,
        "created_at": t.created_at,
        "n_transitions": t.transitions.len(),
        "transitions": t.transitions,
    })))
}

/// Query of `GET /v1/experiments/{id}/transitions`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransitionsQuery {
    /// Return transitions with an id greater than this cursor. Default 0.
    #[serde(default)]
    pub after: i64,
    /// Page size: default 100 and at most 1000 for JSON; unlimited by default for CSV.
    pub limit: Option<i64>,
}

/// Default JSON page size.
pub const DEFAULT_PAGE: i64 = 100;
/// Largest JSON page size.
pub const MAX_PAGE: i64 = 1000;
/// Largest explicit CSV page size.
pub const MAX_CSV_ROWS: i64 = 1_000_000_000;

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
) -> Result<Response, Error> {
    let live = state.experiments.get(&state.store, id).await?;
    let csv = wants_csv(&headers);
    if let Some(limit) = query.limit {
        let max = if csv { MAX_CSV_ROWS } else { MAX_PAGE };
        if limit < 1 || limit > max {
            return Err(Error::validation(
                "limit",
                format!("must be between 1 and {max}"),
            ));
        }
    }
    let limit = query.limit.or(if csv { None } else { Some(DEFAULT_PAGE) });
    let mut items = state
        .store
        .transitions(id, query.after, limit.map(|l| l + 1))
        .await?;
    let next = match limit {
        Some(l) if items.len() as i64 > l => {
            items.truncate(l as usize);
            items.last().map(|t| t.id)
        }
        _ => None,
    };
    if csv {
        let mut response = (
            [(header::CONTENT_TYPE, "text/csv; charset=utf-8")],
            transitions_csv(&live, &items),
        )
            .into_response();
        if let Some(next) = next {
            response
                .headers_mut()
                .insert("x-next-cursor", HeaderValue::from(next));
        }
        return Ok(response);
    }
    Ok(Json(json!({
        "items": items,
        "next": next,
    }))
    .into_response())
}

fn transitions_csv(live: &LiveExperiment, items: &[Transition]) -> String {
    let state_names = &live.domain.state_space().names;
    let action_names = &live.domain.action_space().names;
    let mut header = vec!["id".to_string(), "trajectory_id".into(), "step".into()];
    header.extend(state_names.iter().map(|n| format!("s.{n}")));
    header.extend(action_names.iter().map(|n| format!("a.{n}")));
    header.extend(state_names.iter().map(|n| format!("s_next.{n}")));
    header.extend(state_names.iter().map(|n| format!("s_pred.{n}")));
    header.push("deviation".into());
    let mut out = header.join(",");
    out.push('\n');
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
        out.push_str(&row.join(","));
        out.push('\n');
    }
    out
}
