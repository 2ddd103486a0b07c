//! `/v1/experiments/{id}/model` and `/precondition`: the MDE version answering, a forced refit,
//! and "is this state-action trusted?".

use super::AppState;
use super::extract::{ApiJson, ApiPath, ApiQuery};
use crate::error::Error;
use crate::live::{FitTrigger, LiveExperiment};
use crate::mde::ServedModel;
use axum::Json;
use axum::extract::State;
use serde::Deserialize;
use serde_json::{Value, json};
use std::sync::Arc;

/// Most points in one precondition query.
pub const MAX_POINTS: usize = 100_000;
/// Batches larger than this are answered on the blocking pool.
const INLINE_POINTS: usize = 256;

fn model_body(live: &LiveExperiment, m: &ServedModel) -> Value {
    let h = m.hyperparameters();
    json!({
        "experiment_id": live.id,
        "version": m.version,
        "source": if m.fit.is_some() { "fit" } else { "prior" },
        "n_train": m.n_train(),
        "noise": m.noise_mode(),
        "feature_names": live.domain.feature_names(),
        "hyperparameters": {
            "length_scales": h.length_scales,
            "signal_variance": h.signal_variance,
            "noise_variance": h.noise_variance,
            "prior_mean": h.prior_mean,
        },
        "noise_model": m.noise_summary(),
        "log_marginal_likelihood": m.log_marginal_likelihood(),
        "fit_seconds": m.fit.as_ref().map(|f| f.fit_seconds),
        "fitted_at": m.fit.as_ref().map(|f| f.fitted_at.clone()),
        "n_trajectories": m.fit.as_ref().map_or(0, |f| f.n_trajectories),
    })
}

/// `GET /v1/experiments/{id}/model`.
pub async fn get_model(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
) -> Result<Json<Value>, Error> {
    let live = state.experiments.get(&state.store, id).await?;
    Ok(Json(model_body(&live, &live.model())))
}

/// `POST /v1/experiments/{id}/model/refit`: fit now on every stored transition (off the async
/// workers) and answer with the new version.
pub async fn refit_model(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
) -> Result<Json<Value>, Error> {
    let live = state.experiments.get(&state.store, id).await?;
    let model = live.refit(&state.store, FitTrigger::Forced).await?;
    Ok(Json(model_body(&live, &model)))
}

/// One point of a precondition query.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointRequest {
    /// State.
    pub s: Vec<f64>,
    /// Action.
    pub a: Vec<f64>,
}

/// `POST /v1/experiments/{id}/precondition` body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PreconditionRequest {
    /// The state-actions to judge.
    pub points: Vec<PointRequest>,
    /// Confidence multiplier β; default: the experiment's `learning.test_beta`.
    pub beta: Option<f64>,
}

/// Judges points against the current model: `upper = μ + βσ`, `inside = upper < d_max`.
async fn judge(
    live: &Arc<LiveExperiment>,
    points: &[PointRequest],
    beta: Option<f64>,
) -> Result<Value, Error> {
    if points.is_empty() {
        return Err(Error::validation("points", "must hold at least one point"));
    }
    if points.len() > MAX_POINTS {
        return Err(Error::validation(
            "points",
            format!("at most {MAX_POINTS} points"),
        ));
    }
    let beta = beta.unwrap_or(live.settings.learning.test_beta);
    if !beta.is_finite() {
        return Err(Error::validation("beta", "must be a finite number"));
    }
    let domain = live.domain.as_ref();
    let dim = domain.feature_dim();
    let mut features = Vec::with_capacity(points.len() * dim);
    for (i, p) in points.iter().enumerate() {
        let field = |name: &str| format!("points[{i}].{name}");
        domain
            .validate_state(&p.s)
            .map_err(|e| Error::validation(field("s"), e.0))?;
        domain
            .validate_action(&p.a)
            .map_err(|e| Error::validation(field("a"), e.0))?;
        domain
            .validate_step(&p.s, &p.a)
            .map_err(|e| Error::validation(field("a"), e.0))?;
        features.extend(domain.features(&p.s, &p.a));
    }
    let model = live.model();
    let answers = if points.len() > INLINE_POINTS {
        let model = model.clone();
        tokio::task::spawn_blocking(move || model.answer(&features, dim))
            .await
            .map_err(|e| Error::Internal(e.into()))?
    } else {
        model.answer(&features, dim)
    };
    let d_max = live.settings.d_max;
    let mut results = Vec::with_capacity(answers.len());
    for a in answers {
        let upper = a.mu + beta * a.sigma;
        if !upper.is_finite() {
            return Err(Error::Internal(anyhow::anyhow!(
                "the model answered a non-finite deviation (μ = {}, σ = {})",
                a.mu,
                a.sigma
            )));
        }
        results
            .push(json!({"mu": a.mu, "sigma": a.sigma, "upper": upper, "inside": upper < d_max}));
    }
    Ok(json!({
        "model_version": model.version,
        "source": if model.fit.is_some() { "fit" } else { "prior" },
        "beta": beta,
        "d_max": d_max,
        "results": results,
    }))
}

/// `POST /v1/experiments/{id}/precondition`.
pub async fn query_precondition(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiJson(request): ApiJson<PreconditionRequest>,
) -> Result<Json<Value>, Error> {
    let live = state.experiments.get(&state.store, id).await?;
    Ok(Json(judge(&live, &request.points, request.beta).await?))
}

/// Query of `GET /v1/experiments/{id}/precondition`: one point, comma-separated.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointQuery {
    /// State, e.g. `s=3,2`.
    pub s: String,
    /// Action, e.g. `a=1,0`.
    pub a: String,
    /// β; default `learning.test_beta`.
    pub beta: Option<f64>,
}

fn parse_vector(field: &str, text: &str) -> Result<Vec<f64>, Error> {
    text.split(',')
        .map(|x| {
            x.trim().parse::<f64>().map_err(|_| {
                Error::validation(
                    field,
                    format!("{x:?} is not a number (use e.g. {field}=1,0.5)"),
                )
            })
        })
        .collect()
}

/// `GET /v1/experiments/{id}/precondition?s=..&a=..&beta=..`.
pub async fn get_precondition(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiQuery(query): ApiQuery<PointQuery>,
) -> Result<Json<Value>, Error> {
    let live = state.experiments.get(&state.store, id).await?;
    let point = PointRequest {
        s: parse_vector("s", &query.s)?,
        a: parse_vector("a", &query.a)?,
    };
    let mut body = judge(&live, std::slice::from_ref(&point), query.beta)
        .await
        .map_err(|e| match e {
            Error::Validation { field, reason } => {
                Error::validation(field.trim_start_matches("points[0]."), reason)
            }
            other => other,
        })?;
    body["s"] = json!(point.s);
    body["a"] = json!(point.a);
    Ok(Json(body))
}
