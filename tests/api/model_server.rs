//! A robot's dynamics model served over HTTP, as a lab would run it, on port 0 in the test:
//! `POST /predict {"states", "actions"} → {"next_states"}` with `ŝ' = s + a` — and endpoints
//! that misbehave in the ways a real model server can.

use axum::Json;
use axum::Router;
use axum::extract::State;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::Deserialize;
use serde_json::json;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

#[derive(Deserialize)]
struct Batch {
    states: Vec<Vec<f64>>,
    actions: Vec<Vec<f64>>,
}

fn step(b: &Batch) -> Vec<Vec<f64>> {
    b.states
        .iter()
        .zip(&b.actions)
        .map(|(s, a)| s.iter().zip(a).map(|(x, d)| x + d).collect())
        .collect()
}

/// Calls and points received, per endpoint.
#[derive(Debug, Default)]
pub struct Counts {
    /// Calls to `/predict` and `/valid`.
    pub calls: AtomicUsize,
    /// Points received by `/predict` and `/valid`.
    pub points: AtomicUsize,
    /// Calls to `/hang` still waiting, and the most there ever were at once.
    pub hanging: AtomicUsize,
    /// The most calls to `/hang` there ever were at once.
    pub most_hanging: AtomicUsize,
    /// Calls to `/hang`.
    pub hang_calls: AtomicUsize,
    /// Calls to `/binary` in raw little-endian arrays.
    pub binary_calls: AtomicUsize,
}

/// The running model server.
pub struct ModelServer {
    /// Its address.
    pub addr: SocketAddr,
    /// What `/predict` received.
    pub counts: Arc<Counts>,
}

impl ModelServer {
    /// The URL of one of its endpoints (`predict`, `slow`, `error`, `short`, `nan`,
    /// `valid`, `hang`, `amplify`, `wide`, `binary`, `declares3`).
    pub fn url(&self, endpoint: &str) -> String {
        format!("http://{}/{endpoint}", self.addr)
    }

    /// The prefix to allow.
    pub fn prefix(&self) -> String {
        format!("http://{}/", self.addr)
    }
}

async fn predict(State(counts): State<Arc<Counts>>, Json(b): Json<Batch>) -> Response {
    counts.calls.fetch_add(1, Ordering::Relaxed);
    counts.points.fetch_add(b.states.len(), Ordering::Relaxed);
    Json(json!({"next_states": step(&b)})).into_response()
}

/// `ŝ' = s + a`, but steps that end with `x` in `[0.48, 0.52]` are invalid (the robot's own
/// collision check).
async fn with_validity(State(counts): State<Arc<Counts>>, Json(b): Json<Batch>) -> Response {
    counts.calls.fetch_add(1, Ordering::Relaxed);
    counts.points.fetch_add(b.states.len(), Ordering::Relaxed);
    let next = step(&b);
    let valid: Vec<bool> = next
        .iter()
        .map(|s| !(0.48..=0.52).contains(&s[0]))
        .collect();
    Json(json!({"next_states": next, "valid": valid})).into_response()
}

async fn slow(Json(b): Json<Batch>) -> Response {
    tokio::time::sleep(std::time::Duration::from_millis(1500)).await;
    Json(json!({"next_states": step(&b)})).into_response()
}

/// Accepts the call and answers only after 30 s (longer than any test waits).
async fn hang(State(counts): State<Arc<Counts>>) -> Response {
    counts.hang_calls.fetch_add(1, Ordering::Relaxed);
    let now = counts.hanging.fetch_add(1, Ordering::Relaxed) + 1;
    counts.most_hanging.fetch_max(now, Ordering::Relaxed);
    struct Leave(Arc<Counts>);
    impl Drop for Leave {
        fn drop(&mut self) {
            self.0.hanging.fetch_sub(1, Ordering::Relaxed);
        }
    }
    let _leave = Leave(counts);
    tokio::time::sleep(std::time::Duration::from_secs(30)).await;
    (StatusCode::INTERNAL_SERVER_ERROR, "too late").into_response()
}

/// A valid answer with 200 000 rows, whatever was asked.
async fn amplify() -> Response {
    let rows = vec!["[0.5, 0.5]"; 200_000].join(",");
    (
        [("content-type", "application/json")],
        format!("{{\"next_states\": [{rows}]}}"),
    )
        .into_response()
}

/// One row per point, each a component too many.
async fn wide(Json(b): Json<Batch>) -> Response {
    let rows: Vec<Vec<f64>> = b.states.iter().map(|_| vec![0.5, 0.5, 0.5]).collect();
    Json(json!({"next_states": rows})).into_response()
}

async fn error() -> Response {
    (StatusCode::INTERNAL_SERVER_ERROR, "model crashed").into_response()
}

async fn short(Json(b): Json<Batch>) -> Response {
    let mut next = step(&b);
    next.pop();
    Json(json!({"next_states": next})).into_response()
}

async fn nan(Json(b): Json<Batch>) -> Response {
    // What Python's json.dumps writes for float('nan').
    let rows: Vec<String> = b.states.iter().map(|_| "[NaN, 0.5]".to_string()).collect();
    (
        [("content-type", "application/json")],
        format!("{{\"next_states\": [{}]}}", rows.join(", ")),
    )
        .into_response()
}

/// The handshake of a model that reads and answers raw little-endian arrays, declaring a
/// 2-D state and action.
async fn binary_hello() -> Response {
    Json(json!({"precond_model": 1, "encodings": ["f64le", "json"],
                "state_dim": 2, "action_dim": 2}))
    .into_response()
}

/// The handshake of a model that declares a 3-D state.
async fn declares3_hello() -> Response {
    Json(json!({"precond_model": 1, "encodings": ["f64le"], "state_dim": 3})).into_response()
}

/// `ŝ' = s + a` in raw little-endian arrays: `points × n` states then `points × m` actions
/// (shape in `x-precond-shape`), answering the next states the same way.
async fn binary(
    State(counts): State<Arc<Counts>>,
    headers: axum::http::HeaderMap,
    body: axum::body::Bytes,
) -> Response {
    let shape: Vec<usize> = headers
        .get("x-precond-shape")
        .and_then(|v| v.to_str().ok())
        .map(|v| v.split(',').filter_map(|x| x.parse().ok()).collect())
        .unwrap_or_default();
    let content_type = headers.get("content-type").and_then(|v| v.to_str().ok());
    let [points, n, m] = shape[..] else {
        return (StatusCode::BAD_REQUEST, "no x-precond-shape").into_response();
    };
    if content_type != Some(F64LE) || n != m || body.len() != 8 * points * (n + m) {
        return (StatusCode::BAD_REQUEST, "not the arrays announced").into_response();
    }
    counts.binary_calls.fetch_add(1, Ordering::Relaxed);
    counts.points.fetch_add(points, Ordering::Relaxed);
    let values: Vec<f64> = body
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
        .collect();
    let (states, actions) = values.split_at(points * n);
    let out: Vec<u8> = states
        .iter()
        .zip(actions)
        .flat_map(|(s, a)| (s + a).to_le_bytes())
        .collect();
    ([("content-type", F64LE)], out).into_response()
}

/// Content type of the binary encoding.
const F64LE: &str = "application/x-precond-f64le";

/// Starts the model server on `127.0.0.1:0` for the rest of the test's runtime.
pub async fn start() -> ModelServer {
    let counts = Arc::new(Counts::default());
    let app = Router::new()
        .route("/predict", post(predict))
        .route("/valid", post(with_validity))
        .route("/slow", post(slow))
        .route("/error", post(error))
        .route("/short", post(short))
        .route("/nan", post(nan))
        .route("/hang", post(hang))
        .route("/amplify", post(amplify))
        .route("/wide", post(wide))
        .route("/binary", get(binary_hello).post(binary))
        .route("/declares3", get(declares3_hello).post(binary))
        .with_state(counts.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move { axum::serve(listener, app).await });
    ModelServer { addr, counts }
}
