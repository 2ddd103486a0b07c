//! The HTTP/JSON API: one [`AppState`], one route table, one error shape.
//!
//! The router is built from [`routes`], the same table the contract test compares with
//! `api/openapi.yaml`, so a route cannot exist in one and not the other. The dashboard's pages
//! and assets (`/`, `/ui/...`) are merged beside it: they are not part of the JSON API.

mod activity;
pub mod auth;
pub mod error;
mod exclusions;
mod experiments;
pub mod extract;
pub mod guard;
mod health;
mod imports;
mod inspection;
pub mod metrics;
mod model;
mod proposals;
mod render;
pub mod server;
mod stream;
mod trajectories;
mod ui;

use crate::service::Service;
use crate::store::Store;
use axum::Router;
use axum::extract::{DefaultBodyLimit, Request};
use axum::http::HeaderName;
use axum::http::{HeaderValue, Method, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{MethodRouter, get, post};
use error::ApiError;
use extract::BodyLimit;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tower::util::option_layer;
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::cors::{AllowOrigin, CorsLayer};
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::TraceLayer;

/// Limits and knobs of the HTTP layer.
#[derive(Debug, Clone)]
pub struct HttpConfig {
    /// Largest accepted request body in bytes.
    pub max_body_bytes: usize,
    /// Largest file an import route accepts, in bytes (spooled to a temporary file).
    pub max_import_bytes: usize,
    /// Access tokens; `None` lets every request through (loopback or `--insecure-no-auth`).
    pub tokens: Option<Arc<auth::TokenTable>>,
    /// How long in-flight requests may run on after shutdown is requested before they are
    /// dropped (a dropped search stops at its next round).
    pub shutdown_grace: Duration,
    /// Longest wait for a request's complete headers, and the idle time after which a
    /// kept-alive connection is closed (see [`server`]).
    pub header_read_timeout: Duration,
    /// Longest time to receive a request's whole body; past it `408 request_timeout`.
    pub body_read_timeout: Duration,
    /// Origins (`scheme://host[:port]`) whose pages may call the API from a browser (CORS), e.g.
    /// a dashboard served by another precond; none by default.
    pub cors_allow_origins: Vec<String>,
    /// The address the server listens on, set by [`serve`] from its listener. With no tokens
    /// and a loopback address, requests must name this machine in `Host` and writes from web
    /// pages must come from its own origin (see [`guard`]).
    pub bound: Option<std::net::SocketAddr>,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            max_body_bytes: crate::limits::DEFAULT_MAX_BODY_BYTES,
            max_import_bytes: 256 * 1024 * 1024,
            tokens: None,
            shutdown_grace: Duration::from_secs(20),
            header_read_timeout: Duration::from_secs(30),
            body_read_timeout: extract::DEFAULT_BODY_READ_TIMEOUT,
            cors_allow_origins: Vec::new(),
            bound: None,
        }
    }
}

/// The CORS layer for the configured origins; an origin that is not a valid header value is an
/// error at start-up.
fn cors(origins: &[String]) -> anyhow::Result<Option<CorsLayer>> {
    if origins.is_empty() {
        return Ok(None);
    }
    let origins = origins
        .iter()
        .map(|o| {
            HeaderValue::from_str(o.trim_end_matches('/'))
                .map_err(|_| anyhow::anyhow!("invalid CORS origin {o:?}"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok(Some(
        CorsLayer::new()
            .allow_origin(AllowOrigin::list(origins))
            .allow_methods([Method::GET, Method::HEAD, Method::POST])
            // The dashboard sends its token (`Authorization`) to a server with tokens; a robot
            // in a browser may send its own request id and idempotency key.
            .allow_headers([
                header::CONTENT_TYPE,
                header::AUTHORIZATION,
                HeaderName::from_static("idempotency-key"),
                REQUEST_ID,
            ])
            .expose_headers([REQUEST_ID, header::RETRY_AFTER]),
    ))
}

/// What every handler can reach.
#[derive(Debug, Clone)]
pub struct AppState {
    /// The service.
    pub service: Service,
    /// HTTP settings.
    pub config: Arc<HttpConfig>,
}

impl AppState {
    /// State over an opened store, with the service's default policies.
    pub fn new(store: Store, config: HttpConfig) -> Self {
        Self::with_service(Service::new(store), config)
    }

    /// State over a configured service.
    pub fn with_service(service: Service, config: HttpConfig) -> Self {
        Self {
            service,
            config: Arc::new(config),
        }
    }
}

/// The header carrying a request's id, in logs and responses.
pub const REQUEST_ID: HeaderName = HeaderName::from_static("x-request-id");

/// One row of the route table.
pub struct Route {
    /// HTTP method.
    pub method: Method,
    /// Path in axum's syntax (`{id}` parameters), the same as in the OpenAPI document.
    pub path: &'static str,
    /// The handler.
    pub handler: MethodRouter<AppState>,
}

fn route(method: Method, path: &'static str, handler: MethodRouter<AppState>) -> Route {
    Route {
        method,
        path,
        handler,
    }
}

/// Every route the service answers.
pub fn routes() -> Vec<Route> {
    use Method as M;
    vec![
        route(M::GET, "/healthz", get(health::get_health)),
        route(M::GET, "/readyz", get(health::get_readiness)),
        route(M::GET, "/metrics", get(metrics::get_metrics)),
        route(
            M::POST,
            "/v1/experiments",
            post(experiments::create_experiment),
        ),
        route(
            M::GET,
            "/v1/experiments",
            get(experiments::list_experiments),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}",
            get(experiments::get_experiment),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/trajectories",
            post(trajectories::create_trajectory),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/imports",
            post(imports::create_import),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/trajectories/{tid}",
            get(trajectories::get_trajectory),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/transitions",
            get(trajectories::list_transitions),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/runs",
            get(activity::list_runs),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/timeline",
            get(activity::get_timeline),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/labels",
            get(activity::get_labels),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/exclusions",
            post(exclusions::create_exclusion),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/exclusions",
            get(exclusions::list_exclusions),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/exclusions/{eid}/restore",
            post(exclusions::restore_exclusion),
        ),
        route(M::GET, "/v1/experiments/{id}/model", get(model::get_model)),
        route(
            M::GET,
            "/v1/experiments/{id}/model/export",
            get(model::export_model),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/model/diagnostics",
            get(inspection::get_model_diagnostics),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/model/refit",
            post(model::refit_model),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/precondition",
            post(model::query_precondition),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/precondition",
            get(model::get_precondition),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/precondition/map",
            get(inspection::get_precondition_map),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/proposals",
            post(proposals::create_proposal),
        ),
        route(
            M::GET,
            "/v1/experiments/{id}/proposals/{pid}",
            get(proposals::get_proposal),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/proposals/{pid}/abandon",
            post(proposals::abandon_proposal),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/proposals/{pid}/continue",
            post(proposals::continue_proposal),
        ),
        route(
            M::POST,
            "/v1/experiments/{id}/plans",
            post(proposals::create_plan),
        ),
    ]
}

/// The application: routes (the dashboard's pages among them), access tokens, fallbacks, body
/// limit, CORS (when configured), tracing, request ids and the panic net. Fails only on an
/// invalid CORS origin.
pub fn app(state: AppState) -> anyhow::Result<Router> {
    let limit = state.config.max_body_bytes;
    let body_timeout = extract::BodyReadTimeout(state.config.body_read_timeout);
    let tokens = state.config.tokens.clone();
    let cors = cors(&state.config.cors_allow_origins)?;
    let loopback_guard =
        (tokens.is_none() && state.config.bound.is_some_and(|a| a.ip().is_loopback())).then(|| {
            Arc::new(guard::LoopbackGuard {
                allowed_origins: state
                    .config
                    .cors_allow_origins
                    .iter()
                    .map(|o| o.trim_end_matches('/').to_ascii_lowercase())
                    .collect(),
            })
        });
    metrics::handle();
    let mut router = Router::new();
    for r in routes() {
        router = router.route(r.path, r.handler);
    }
    Ok(router
        // A route layer, so that the middleware sees the matched route's template.
        .route_layer(middleware::from_fn(move |req: Request, next: Next| {
            auth::authorize(tokens.clone(), req, next)
        }))
        .route_layer(middleware::from_fn(metrics::track))
        // The dashboard's static pages: open (a browser cannot send a bearer token with a page
        // load); the API calls they make carry the token the user gives the page.
        .merge(ui::router())
        .fallback(route_not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(middleware::from_fn(
            move |mut req: Request, next: Next| async move {
                req.extensions_mut().insert(BodyLimit(limit));
                req.extensions_mut().insert(body_timeout);
                next.run(req).await
            },
        ))
        .layer(DefaultBodyLimit::max(limit))
        .layer(option_layer(loopback_guard.map(|g| {
            middleware::from_fn(move |req: Request, next: Next| guard::guard(g.clone(), req, next))
        })))
        .layer(option_layer(cors))
        .layer(CatchPanicLayer::custom(panic_response))
        .layer(TraceLayer::new_for_http().make_span_with(|req: &Request| {
            let id = req
                .headers()
                .get(REQUEST_ID)
                .and_then(|v| v.to_str().ok())
                .unwrap_or("-");
            tracing::info_span!("request", method = %req.method(), uri = %req.uri().path(),
                    request_id = %id)
        }))
        // An `x-request-id` on every request (the client's, or a new UUID) and response.
        .layer(PropagateRequestIdLayer::new(REQUEST_ID))
        .layer(SetRequestIdLayer::new(REQUEST_ID, MakeRequestUuid))
        .with_state(state))
}

async fn route_not_found(method: Method, uri: axum::http::Uri) -> ApiError {
    ApiError::not_found(format!("no route for {method} {}", uri.path()))
}

async fn method_not_allowed() -> ApiError {
    ApiError::MethodNotAllowed
}

fn panic_response(_: Box<dyn std::any::Any + Send + 'static>) -> Response {
    tracing::error!("a handler panicked");
    let e = ApiError::from(crate::service::Error::Internal(anyhow::anyhow!(
        "handler panicked"
    )));
    (StatusCode::INTERNAL_SERVER_ERROR, axum::Json(e.body())).into_response()
}

/// Serves the API on `listener` until `shutdown` resolves, then lets in-flight requests finish
/// and closes the store.
pub async fn serve(
    listener: TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let store = state.service.store().clone();
    let stopping = state.service.clone();
    let grace = state.config.shutdown_grace;
    let addr = listener.local_addr()?;
    let state = AppState {
        config: Arc::new(HttpConfig {
            bound: Some(addr),
            ..(*state.config).clone()
        }),
        ..state
    };
    tracing::info!(%addr, backend = store.backend().as_str(), "serving");
    let background = state.service.start_background().await;
    let service = state.service.clone();
    tokio::spawn(async move {
        match service.resume_refits().await {
            Ok(0) => {}
            Ok(n) => tracing::info!(experiments = n, "refitting batches left unfitted"),
            Err(e) => tracing::error!(error = %e, "could not look for unfitted batches"),
        }
    });
    let (requested_tx, requested_rx) = tokio::sync::oneshot::channel::<()>();
    let signal = async move {
        shutdown.await;
        let _ = requested_tx.send(());
    };
    let limits = server::ConnLimits {
        header_read: state.config.header_read_timeout,
    };
    let server = server::run(listener, app(state)?, limits, signal);
    let grace_over = async move {
        if requested_rx.await.is_ok() {
            tokio::time::sleep(grace).await;
        } else {
            std::future::pending::<()>().await;
        }
    };
    tokio::select! {
        () = server => {},
        () = grace_over => tracing::warn!(
            seconds = grace.as_secs_f64(),
            "grace period over: dropping the requests still in flight"
        ),
    }
    drop(background);
    stopping.release_fits().await;
    if tokio::time::timeout(Duration::from_secs(5), store.close())
        .await
        .is_err()
    {
        tracing::warn!("the database did not close within 5 s");
    }
    tracing::info!("stopped");
    Ok(())
}
