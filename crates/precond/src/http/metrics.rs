//! `GET /metrics`: counters and histograms in the Prometheus text format.
//!
//! Instrumentation uses the `metrics` facade (so the service layer counts fits and proposals
//! without knowing about HTTP); `metrics-exporter-prometheus` renders it. The recorder is
//! process-wide and installed once, the first time an app is built.
//!
//! Exposed:
//! - `http_requests_total{method, route, status}` and `http_request_duration_seconds{method,
//!   route}` (histogram): every request to a route, by its template
//!   (`/v1/experiments/{id}/model`), 401 and 403 answers included;
//! - `precond_fits_total{trigger, result}` and `precond_fit_seconds` (histogram);
//! - `precond_proposals_total{outcome}`: `created`, `lease_returned`, `no_plan`, `lease_held`,
//!   `deadline_exceeded`, `overloaded`, `cancelled`, `invalid`, `failed`;
//! - `precond_planning_queue_depth` and `precond_planning_running`: requests waiting for a
//!   planning slot and searches or fits running;
//! - `precond_store_bytes`, `precond_store_experiments`, `precond_store_trajectories`,
//!   `precond_store_transitions`: read from the store at each scrape.

use super::AppState;
use super::error::{ApiError, ApiResult};
use axum::extract::{MatchedPath, Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};
use std::sync::OnceLock;
use std::time::Instant;

/// Histogram buckets in seconds: from a cheap read (1 ms) to a long search or fit (2 min).
const SECONDS_BUCKETS: &[f64] = &[
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0,
];

static HANDLE: OnceLock<Option<PrometheusHandle>> = OnceLock::new();

/// The process's Prometheus handle, installing the recorder on first use. `None` if another
/// recorder was installed first (then `/metrics` answers 503).
pub fn handle() -> Option<&'static PrometheusHandle> {
    HANDLE
        .get_or_init(|| {
            let recorder = PrometheusBuilder::new()
                .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), SECONDS_BUCKETS)
                .ok()?
                .build_recorder();
            let handle = recorder.handle();
            metrics::set_global_recorder(recorder).ok()?;
            describe();
            Some(handle)
        })
        .as_ref()
}

fn describe() {
    use metrics::{describe_counter, describe_gauge, describe_histogram};
    describe_counter!("http_requests_total", "HTTP requests by route and status");
    describe_histogram!(
        "http_request_duration_seconds",
        metrics::Unit::Seconds,
        "HTTP request latency by route"
    );
    describe_counter!("precond_fits_total", "MDE fits by trigger and result");
    describe_histogram!(
        "precond_fit_seconds",
        metrics::Unit::Seconds,
        "MDE fit duration"
    );
    describe_counter!("precond_proposals_total", "proposal requests by outcome");
    describe_gauge!(
        "precond_planning_queue_depth",
        "requests waiting for a planning slot"
    );
    describe_gauge!("precond_planning_running", "searches and fits running");
    describe_gauge!("precond_store_bytes", "bytes of the SQLite database file");
    describe_gauge!("precond_store_experiments", "experiments stored");
    describe_gauge!("precond_store_trajectories", "trajectories stored");
    describe_gauge!("precond_store_transitions", "transitions stored");
}

/// Middleware: counts every request and records its latency by route template.
pub async fn track(req: Request, next: Next) -> Response {
    let started = Instant::now();
    let method = req.method().as_str().to_owned();
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| "unmatched".to_owned(), |m| m.as_str().to_owned());
    let response = next.run(req).await;
    let status = response.status().as_u16().to_string();
    metrics::counter!("http_requests_total", "method" => method.clone(),
        "route" => route.clone(), "status" => status)
    .increment(1);
    metrics::histogram!("http_request_duration_seconds", "method" => method, "route" => route)
        .record(started.elapsed().as_secs_f64());
    response
}

/// `GET /metrics`: the Prometheus text exposition.
pub async fn get_metrics(State(state): State<AppState>) -> ApiResult<Response> {
    let handle = handle().ok_or_else(|| {
        ApiError::Unavailable("another metrics recorder is installed in this process".into())
    })?;
    let store = state.service.store();
    let size = store.size().await.map_err(crate::service::Error::from)?;
    metrics::gauge!("precond_store_bytes").set(size.bytes as f64);
    metrics::gauge!("precond_store_experiments").set(size.experiments as f64);
    metrics::gauge!("precond_store_trajectories").set(size.trajectories as f64);
    metrics::gauge!("precond_store_transitions").set(size.transitions as f64);
    metrics::gauge!("precond_planning_queue_depth").set(state.service.work().queue_depth() as f64);
    // Fit requests over every replica of the database, and those this replica holds.
    let jobs = store
        .fit_jobs()
        .await
        .map_err(crate::service::Error::from)?;
    let replica = state.service.fits().replica();
    let held = |mine: bool| {
        jobs.iter()
            .filter(|j| {
                j.claimed_by
                    .as_deref()
                    .is_some_and(|r| (r == replica) == mine)
            })
            .count() as f64
    };
    let waiting = jobs.iter().filter(|j| j.claimed_by.is_none()).count() as f64;
    metrics::gauge!("precond_fit_requests", "state" => "waiting").set(waiting);
    metrics::gauge!("precond_fit_requests", "state" => "fitting_here").set(held(true));
    metrics::gauge!("precond_fit_requests", "state" => "fitting_elsewhere").set(held(false));
    handle.run_upkeep();
    Ok((
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        handle.render(),
    )
        .into_response())
}
