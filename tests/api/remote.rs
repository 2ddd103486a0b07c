//! Remote models under hostile conditions, over real sockets: answers larger than asked, hung
//! models, searches and their deadlines, revoked and ambiguous URLs.

use crate::helpers::*;
use crate::model_server::{self, ModelServer};
use precond::remote_model::ModelCallLimits;
use precond::service::Limits;
use serde_json::{Value, json};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

fn plane(url: &str, timeout_ms: u64) -> Value {
    json!({"d_max": 0.05, "learning": {"batch_size": 1000},
           "domain": {"kind": "custom",
                      "state": {"low": [0, 0], "high": [1, 1]},
                      "action": {"low": [-0.1, -0.1], "high": [0.1, 0.1]},
                      "model": {"kind": "remote", "url": url, "timeout_ms": timeout_ms}}})
}

fn step() -> Value {
    json!({"transitions": [{"s": [0.2, 0.2], "a": [0.1, 0], "s_next": [0.3, 0.2]}]})
}

fn limits(slots: usize, timeout_ms: u64) -> Limits {
    Limits {
        max_concurrent_plans: slots,
        max_plans_per_experiment: slots,
        plan_timeout: Duration::from_millis(timeout_ms),
        ..Limits::default()
    }
}

async fn app(
    server: &ModelServer,
    limits: Limits,
    calls: ModelCallLimits,
) -> (tempfile::TempDir, TestApp) {
    let (dir, db) = temp_db();
    let app = spawn_app_with_models(&db, &[server.prefix()], limits, calls).await;
    (dir, app)
}

#[tokio::test]
async fn an_answer_longer_or_wider_than_asked_is_refused_while_it_is_parsed() {
    let server = model_server::start().await;
    let (_dir, app) = app(&server, limits(2, 30_000), ModelCallLimits::default()).await;
    for (endpoint, why) in [
        ("amplify", "more than 1 next states for 1 points"),
        ("wide", "more than 2 components"),
    ] {
        let id = app
            .create_experiment(plane(&server.url(endpoint), 5000))
            .await;
        let (status, body) = app.post_at(id, "trajectories", &step()).await;
        assert_eq!((status, code(&body)), (502, "model_unavailable"), "{body}");
        let reason = reason(&body);
        assert!(reason.contains(why), "{endpoint}: {reason}");
    }
}

/// A model whose handshake offers raw little-endian arrays is called in them, on ingest and
/// in planning, and its predictions arrive bit for bit; one that declares another state
/// dimension than the domain's is refused, naming both.
#[tokio::test]
async fn a_model_that_offers_binary_arrays_is_called_in_them() {
    let server = model_server::start().await;
    let (_dir, app) = app(&server, limits(2, 30_000), ModelCallLimits::default()).await;
    let id = app
        .create_experiment(plane(&server.url("binary"), 5000))
        .await;
    let odd = json!({"transitions": [{"s": [0.1, 1e-300], "a": [0.1, 0], "s_next": [0.3, 0.2]}]});
    let (status, body) = app.post_at(id, "trajectories", &odd).await;
    assert_eq!(status, 201, "{body}");
    let (_, page) = app.get(&format!("/v1/experiments/{id}/transitions")).await;
    let s_pred = &page["items"][0]["s_pred"];
    assert_eq!(s_pred, &json!([0.1 + 0.1, 1e-300]), "{page}");
    let (status, body) = app
        .post_at(
            id,
            "proposals",
            &json!({"start": [0.2, 0.2], "goal": [0.5, 0.2]}),
        )
        .await;
    assert_eq!(status, 201, "{body}");
    assert!(server.counts.binary_calls.load(Ordering::Relaxed) >= 2);
    assert_eq!(
        server.counts.calls.load(Ordering::Relaxed),
        0,
        "no JSON call"
    );

    let id = app
        .create_experiment(plane(&server.url("declares3"), 5000))
        .await;
    let (status, body) = app.post_at(id, "trajectories", &step()).await;
    assert_eq!((status, code(&body)), (502, "model_unavailable"), "{body}");
    let reason = reason(&body);
    assert!(
        reason.contains("declares states of 3 numbers; the domain's state has 2"),
        "{reason}"
    );
}

/// Two experiments: one whose remote model hangs (declaring a 10-minute timeout) and a local
/// kinematic one.
async fn hung_and_local(app: &TestApp, server: &ModelServer) -> (i64, i64) {
    let hung = app
        .create_experiment(plane(&server.url("hang"), 600_000))
        .await;
    let local = app
        .create_experiment(json!({"domain": {"kind": "kinematic"}}))
        .await;
    (hung, local)
}

/// A hung model holds only its own calls: at most `--max-model-calls-per-url` at once, each
/// ended by `--max-model-timeout-ms` whatever its experiment declared, the others refused as
/// busy when their time is up; another experiment's ingest does not wait for any of it.
#[tokio::test]
async fn a_hung_model_holds_only_its_own_calls_for_at_most_the_operators_timeout() {
    let server = model_server::start().await;
    let calls = ModelCallLimits {
        max_calls: 4,
        max_calls_per_url: 2,
        max_timeout: Duration::from_millis(800),
    };
    let (_dir, app) = app(&server, limits(2, 30_000), calls).await;
    let (hung, local) = hung_and_local(&app, &server).await;
    let started = Instant::now();
    let hung_ingests: Vec<_> = (0..6)
        .map(|_| {
            let (client, url) = (
                app.client.clone(),
                app.url(&format!("/v1/experiments/{hung}/trajectories")),
            );
            tokio::spawn(async move {
                let r = client.post(url).json(&step()).send().await.unwrap();
                let retry = r.headers().get("retry-after").is_some();
                let body: Value = r.json().await.unwrap();
                (code(&body).to_string(), retry, started.elapsed())
            })
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let asked = Instant::now();
    app.store_trajectory(
        local,
        &json!({"transitions": [{"s": [0.1, 0.1], "a": [0.05, 0], "s_next": [0.15, 0.1]}]}),
    )
    .await;
    assert_within(asked, Duration::from_millis(500));
    let mut codes = Vec::new();
    for h in hung_ingests {
        let (code, retry, took) = h.await.unwrap();
        assert!(took < Duration::from_secs(3), "{code} after {took:?}");
        if code == "model_busy" {
            assert!(retry, "model_busy carries Retry-After");
        }
        codes.push(code);
    }
    codes.sort();
    let timeouts = codes.iter().filter(|c| *c == "model_timeout").count();
    let busy = codes.iter().filter(|c| *c == "model_busy").count();
    assert_eq!(timeouts + busy, 6, "{codes:?}");
    assert!(timeouts >= 2 && busy >= 1, "{codes:?}");
    assert!(
        server.counts.most_hanging.load(Ordering::Relaxed) <= 2,
        "at most 2 calls to the model at once"
    );
    assert_eq!(server.counts.hang_calls.load(Ordering::Relaxed), timeouts);
}

/// A search calling a hung model stops at its own deadline, not the model's 600 s; a client
/// that goes away frees its planning slot at once.
#[tokio::test]
async fn a_search_waits_for_a_hung_model_no_longer_than_its_budget() {
    let server = model_server::start().await;
    let calls = ModelCallLimits {
        max_timeout: Duration::from_secs(600),
        ..ModelCallLimits::default()
    };
    let (_dir, app) = app(&server, limits(1, 1000), calls.clone()).await;
    let hung = app
        .create_experiment(plane(&server.url("hang"), 600_000))
        .await;
    let ask = json!({"start": [0.1, 0.1], "goal": [0.9, 0.9], "client_id": "r"});
    let started = Instant::now();
    let (status, body) = app.propose(hung, &ask).await;
    assert_eq!((status, code(&body)), (503, "deadline_exceeded"), "{body}");
    assert_within(started, Duration::from_secs(3));

    // One slot and a long deadline: only the client's going away can free the slot early.
    let (_dir2, app) = app_long(&server, calls).await;
    let (hung, local) = hung_and_local(&app, &server).await;
    let gone = app
        .post_and_go_away(&format!("/v1/experiments/{hung}/proposals"), &ask)
        .await;
    assert!(gone.unwrap_err().is_timeout());
    app.assert_proposes_within(local, Duration::from_secs(2))
        .await;
}

async fn app_long(server: &ModelServer, calls: ModelCallLimits) -> (tempfile::TempDir, TestApp) {
    app(server, limits(1, 60_000), calls).await
}

/// A model URL the operator no longer allows is never called again: ingests and searches get
/// `409 model_not_allowed`, reads still work.
#[tokio::test]
async fn a_revoked_model_url_is_refused_at_every_call() {
    let server = model_server::start().await;
    let (_dir, db) = temp_db();
    let allowed = spawn_app_allowing_models(&db, &[server.prefix()]).await;
    let id = allowed
        .create_experiment(plane(&server.url("predict"), 2000))
        .await;
    allowed.store_trajectory(id, &step()).await;
    let calls = server.counts.calls.load(Ordering::Relaxed);
    // Restarted without --allow-model-url.
    let revoked = allowed.restart().await;
    let (status, body) = revoked.post_at(id, "trajectories", &step()).await;
    assert_eq!((status, code(&body)), (409, "model_not_allowed"), "{body}");
    assert_eq!(body["error"]["details"]["model"], server.url("predict"));
    assert!(reason(&body).contains("--allow-model-url"));
    for (path, ask) in [
        (
            "proposals",
            json!({"start": [0.1, 0.1], "goal": [0.3, 0.1], "client_id": "r"}),
        ),
        ("plans", json!({"start": [0.1, 0.1], "goal": [0.3, 0.1]})),
    ] {
        let (status, body) = revoked
            .post(&format!("/v1/experiments/{id}/{path}"), &ask)
            .await;
        assert_eq!(
            (status, code(&body)),
            (409, "model_not_allowed"),
            "{path}: {body}"
        );
    }
    assert_eq!(
        server.counts.calls.load(Ordering::Relaxed),
        calls,
        "no call after revocation"
    );
    let (status, body) = revoked.get_at(id, "").await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["n_trajectories"], 1);
}

/// The URL stored is the normalised one that was checked, and that is the one called; URLs
/// two parsers could read differently are refused.
#[tokio::test]
async fn model_urls_are_stored_as_checked_and_ambiguous_ones_refused() {
    let server = model_server::start().await;
    let (_dir, app) = app(&server, limits(2, 30_000), ModelCallLimits::default()).await;
    let port = server.addr.port();
    let messy = format!("HTTP://127.0.0.1:{port}/./sub/../predict");
    let (status, body) = app.post("/v1/experiments", &plane(&messy, 2000)).await;
    assert_eq!(status, 201, "{body}");
    assert_eq!(body["domain"]["model"]["url"], server.url("predict"));
    let id = body["id"].as_i64().unwrap();
    app.store_trajectory(id, &step()).await;
    for url in [
        format!("http://127.0.0.1:{port}/pre dict"),
        format!("http://127.0.0.1:{port}/predict\r\nX-Injected: 1"),
        format!(" http://127.0.0.1:{port}/predict"),
        format!("http://127.0.0.1:{port}/ok/..%2fpredict"),
        format!("http://127.0.0.1:{port}/{}", "a".repeat(3000)),
    ] {
        let (status, body) = app.post("/v1/experiments", &plane(&url, 2000)).await;
        assert_eq!(
            (status, code(&body)),
            (422, "validation_failed"),
            "{url:?}: {body}"
        );
        assert_eq!(body["error"]["details"]["field"], "domain.model.url");
    }
}
