//! `/v1/experiments/{id}/model` and `/precondition`: the MDE version answering, its export, a
//! forced refit, and "is this state-action trusted?".

use super::AppState;
use super::error::{ApiError, ApiResult};
use super::extract::{ApiJson, ApiPath, ApiQuery};
use super::render;
use super::stream;
use crate::api::{
    ExportQuery, ModelResponse, Point, PointQuery, PreconditionRequest, PreconditionResponse,
};
use crate::service::Error;
use axum::Json;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};

/// `GET /v1/experiments/{id}/model`.
pub async fn get_model(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
) -> ApiResult<Json<ModelResponse>> {
    Ok(Json(render::model(state.service.model(id).await?)))
}

/// `GET /v1/experiments/{id}/model/export?version=`: a fitted version as a document a
/// controller evaluates itself; `409` for the prior. Built and written on a blocking thread in
/// an export slot, a chunk at a time ([`stream`](super::stream)).
pub async fn export_model(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiQuery(query): ApiQuery<ExportQuery>,
) -> ApiResult<Response> {
    let export = state
        .service
        .prepare_model_export(id, query.version, query.model.as_deref())
        .await?;
    let body = stream::produced_body(export, "model export", |export, w| {
        let document = export.build().map_err(std::io::Error::other)?;
        serde_json::to_writer(w, &document).map_err(std::io::Error::other)
    });
    Ok(([(header::CONTENT_TYPE, "application/json")], body).into_response())
}

/// `POST /v1/experiments/{id}/model/refit`: fit now on every stored transition and answer with
/// the new version (`200`), or, when the fit outlasts the planning deadline, with the version
/// still answering (`202`: the fit goes on and is swapped in when done).
pub async fn refit_model(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
) -> ApiResult<(StatusCode, Json<ModelResponse>)> {
    let refit = state.service.refit(id).await?;
    let status = if refit.finished {
        StatusCode::OK
    } else {
        StatusCode::ACCEPTED
    };
    Ok((status, Json(render::model(refit.view))))
}

/// `POST /v1/experiments/{id}/precondition`.
pub async fn query_precondition(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiJson(request): ApiJson<PreconditionRequest>,
) -> ApiResult<Json<PreconditionResponse>> {
    let judged = state
        .service
        .judge(id, &request.points, request.beta, request.model.as_deref())
        .await?;
    Ok(Json(render::judged(judged)))
}

pub(super) fn parse_vector(field: &str, text: &str) -> ApiResult<Vec<f64>> {
    text.split(',')
        .map(|x| {
            x.trim().parse::<f64>().map_err(|_| {
                ApiError::validation(
                    field,
                    format!("{x:?} is not a number (use e.g. {field}=1,0.5)"),
                )
            })
        })
        .collect()
}

/// `GET /v1/experiments/{id}/precondition?s=..&a=..&beta=..`: one point, for curl.
pub async fn get_precondition(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiQuery(query): ApiQuery<PointQuery>,
) -> ApiResult<Json<PreconditionResponse>> {
    let point = Point {
        s: parse_vector("s", &query.s)?,
        a: parse_vector("a", &query.a)?,
        s_pred: query
            .s_pred
            .as_deref()
            .map(|v| parse_vector("s_pred", v))
            .transpose()?,
    };
    let judged = state
        .service
        .judge(
            id,
            std::slice::from_ref(&point),
            query.beta,
            query.model.as_deref(),
        )
        .await
        .map_err(|e| match e {
            // The query names its fields `s` and `a`, not `points[0].s`.
            Error::Validation { field, reason } => {
                Error::validation(field.trim_start_matches("points[0]."), reason)
            }
            other => other,
        })?;
    Ok(Json(PreconditionResponse {
        s: Some(point.s),
        a: Some(point.a),
        ..render::judged(judged)
    }))
}
