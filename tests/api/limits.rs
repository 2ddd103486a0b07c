//! Bounded work over HTTP: deadlines, the queue, cancellation, the operator's limits, metrics
//! and request ids.

use crate::helpers::*;
use precond::service::Limits;
use serde_json::{Value, json};
use std::time::{Duration, Instant};

/// A kinematic world cut in two by a wall: no search reaches the goal, so every search runs
/// until its budget or deadline.
fn walled() -> Value {
    json!({
        "domain": {"kind": "kinematic",
                   "obstacles": [{"low": [0.45, 0.0], "high": [0.55, 1.0]}]},
        "learning": {"max_extensions": 200000}
    })
}

fn blocked_ask(client: &str) -> Value {
    json!({"start": [0.1, 0.5], "goal": [0.9, 0.5], "client_id": client})
}

fn limits(slots: usize, queue: usize, timeout_ms: u64) -> Limits {
    Limits {
        max_concurrent_plans: slots,
        max_queued_plans: queue,
        plan_timeout: Duration::from_millis(timeout_ms),
        ..Limits::default()
    }
}

#[tokio::test]
async fn a_search_past_its_deadline_is_503_with_retry_after() {
    let (_dir, app) = fresh_app_with_limits(limits(2, 4, 300)).await;
    let id = app.create_experiment(walled()).await;
    let started = Instant::now();
    let r = app
        .client
        .post(app.url(&format!("/v1/experiments/{id}/proposals")))
        .json(&blocked_ask("a"))
        .send()
        .await
        .unwrap();
    let took = started.elapsed();
    assert_eq!(r.status().as_u16(), 503);
    assert_eq!(r.headers()["retry-after"], "1");
    let body: Value = r.json().await.unwrap();
    assert_eq!(code(&body), "deadline_exceeded", "{body}");
    assert!(body["error"]["details"]["extensions"].as_u64().unwrap() > 0);
    assert_eq!(body["error"]["details"]["timeout_ms"], 300);
    assert!(took < Duration::from_secs(3), "{took:?}");
    // The refused request is a run, saying why.
    let (_, runs) = app.get_at(id, "runs").await;
    let refused = &runs["items"][0];
    assert_eq!(
        (
            refused["status"].as_str(),
            refused["refusal_reason"].as_str(),
            refused["client_id"].as_str()
        ),
        (Some("refused"), Some("deadline_exceeded"), Some("a")),
        "{runs}"
    );
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["n_refused"], 1, "{e}");
    // A test-time plan has the same deadline; nothing was stored for either. (At the test β
    // the prior trusts nothing, so the tree cannot grow and the search ends in about the
    // deadline's time; at β = −2, as in the proposal above, it grows a large tree and cannot.)
    let (status, body) = app
        .post_at(
            id,
            "plans",
            &json!({"start": [0.1, 0.5], "goal": [0.9, 0.5], "beta": -2.0}),
        )
        .await;
    assert_eq!((status, code(&body)), (503, "deadline_exceeded"));
}

#[tokio::test]
async fn a_saturated_planner_queues_then_refuses_while_health_stays_fast() {
    let (_dir, app) = fresh_app_with_limits(limits(1, 1, 1500)).await;
    let id = app.create_experiment(walled()).await;
    let url = app.url(&format!("/v1/experiments/{id}/proposals"));
    let ask = |c: &'static str| {
        let (client, url) = (app.client.clone(), url.clone());
        tokio::spawn(async move {
            let r = client.post(url).json(&blocked_ask(c)).send().await.unwrap();
            (r.status().as_u16(), r.headers().get("retry-after").cloned())
        })
    };
    let running = ask("running");
    // Wait until the first holds the slot, then queue one and overflow with a third.
    tokio::time::sleep(Duration::from_millis(200)).await;
    let waiting = ask("waiting");
    tokio::time::sleep(Duration::from_millis(200)).await;
    let (status, refused) = app.propose(id, &blocked_ask("third")).await;
    assert_eq!((status, code(&refused)), (429, "overloaded"), "{refused}");
    let started = Instant::now();
    for _ in 0..5 {
        assert_eq!(app.get("/healthz").await.0, 200);
        assert_eq!(app.get_at(id, "").await.0, 200);
    }
    assert!(started.elapsed() < Duration::from_millis(500));
    let (s1, r1) = running.await.unwrap();
    let (s2, _) = waiting.await.unwrap();
    assert_eq!((s1, s2), (503, 503));
    assert!(r1.is_some());
}

/// One client flooding one experiment with searches that run to their deadline takes neither
/// every slot nor the whole queue: another experiment's small proposal is answered at once.
#[tokio::test]
async fn a_flood_on_one_experiment_leaves_room_for_the_others() {
    let (_dir, app) = fresh_app_with_limits(Limits {
        max_plans_per_experiment: 1,
        ..limits(2, 4, 3000)
    })
    .await;
    let flooded = app.create_experiment(walled()).await;
    let other = app.create_experiment(json!({})).await;
    let url = app.url(&format!("/v1/experiments/{flooded}/proposals"));
    let flood: Vec<_> = (0..8)
        .map(|k| {
            let (client, url) = (app.client.clone(), url.clone());
            tokio::spawn(async move {
                let r = client
                    .post(url)
                    .json(&blocked_ask(&format!("flood-{k}")))
                    .send()
                    .await
                    .unwrap();
                r.status().as_u16()
            })
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let started = Instant::now();
    app.assert_proposes(
        other,
        &json!({"start": [0, 0], "goal": [2, 0], "client_id": "victim"}),
    )
    .await;
    assert_within(started, Duration::from_millis(2000));
    let mut statuses: Vec<u16> = Vec::new();
    for f in flood {
        statuses.push(f.await.unwrap());
    }
    statuses.sort_unstable();
    // The flooded experiment ran one search at a time, queued half the queue (2), and the
    // other five were refused at once.
    assert_eq!(statuses, vec![429, 429, 429, 429, 429, 503, 503, 503]);
}

/// Rebuilding an older model version (a map or the diagnostics of it) takes a slot of the work
/// gate like a search; the current version and the prior need none.
#[tokio::test]
async fn older_model_versions_are_rebuilt_through_the_work_gate() {
    // One slot, no queue: while a search holds the slot, a rebuild is refused at once.
    let (_dir, app) = fresh_app_with_limits(limits(1, 0, 1500)).await;
    let id = app
        .create_experiment(json!({"mde": {"restarts": 0, "noise": "homoscedastic"},
                                  "learning": {"batch_size": 1000}}))
        .await;
    for y in 0..2 {
        app.store_trajectory(id, &free_row_trajectory(0, y, 4))
            .await;
        app.refit(id).await;
    }
    let walled = app.create_experiment(walled()).await;
    let search = {
        let (client, url) = (
            app.client.clone(),
            app.url(&format!("/v1/experiments/{walled}/proposals")),
        );
        tokio::spawn(async move {
            let r = client.post(url).json(&blocked_ask("s")).send().await;
            r.unwrap().status().as_u16()
        })
    };
    tokio::time::sleep(Duration::from_millis(300)).await;
    let map = |v: &str| format!("/v1/experiments/{id}/precondition/map?x=s.x&y=s.y&nx=5&ny=5{v}");
    let (status, body) = app.get(&map("&version=1")).await;
    assert_eq!((status, code(&body)), (429, "overloaded"), "{body}");
    let (status, body) = app
        .get(&format!("/v1/experiments/{id}/model/diagnostics?version=1"))
        .await;
    assert_eq!((status, code(&body)), (429, "overloaded"), "{body}");
    for current in ["", "&version=2", "&version=0"] {
        let (status, body) = app.get(&map(current)).await;
        assert_eq!(status, 200, "{current}: {body}");
    }
    assert_eq!(search.await.unwrap(), 503);
    let (status, body) = app.get(&map("&version=1")).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["model_version"], 1);
}

#[tokio::test]
async fn a_client_that_goes_away_cancels_its_search() {
    // One slot and a long deadline: only cancellation can free the slot quickly.
    let (_dir, app) = fresh_app_with_limits(limits(1, 4, 60_000)).await;
    let id = app.create_experiment(walled()).await;
    let cancelled_before = cancelled_proposals(&app).await;
    let impatient = reqwest::Client::builder()
        .timeout(Duration::from_millis(300))
        .build()
        .unwrap();
    // Two impatient clients: one searches, the other waits for the slot and goes away first
    // (while the slot is still held), then the searching one goes away.
    let url = app.url(&format!("/v1/experiments/{id}/proposals"));
    let (searching, queued) = tokio::join!(
        impatient
            .post(&url)
            .timeout(Duration::from_millis(700))
            .json(&blocked_ask("impatient"))
            .send(),
        async {
            tokio::time::sleep(Duration::from_millis(50)).await;
            impatient
                .post(&url)
                .json(&blocked_ask("queued"))
                .send()
                .await
        }
    );
    assert!(searching.unwrap_err().is_timeout());
    assert!(queued.unwrap_err().is_timeout());
    // A feasible problem now gets the slot at once.
    app.assert_proposes_within(id, Duration::from_secs(5)).await;
    // The abandoned search counted itself before it gave its slot up (its request was gone),
    // and the abandoned wait for a slot was counted when it left the queue.
    let cancelled = cancelled_proposals(&app).await - cancelled_before;
    assert!(
        cancelled >= 2,
        "precond_proposals_total{{outcome=\"cancelled\"}} grew by {cancelled}, not 2"
    );
}

/// `precond_proposals_total{outcome="cancelled"}` now (0 before the first; the recorder is
/// the process's, shared by the tests running beside this one, so only its growth counts).
async fn cancelled_proposals(app: &TestApp) -> u64 {
    let text = app.metrics().await;
    text.lines()
        .find_map(|l| l.strip_prefix("precond_proposals_total{outcome=\"cancelled\"} "))
        .map_or(0, |v| v.trim().parse().unwrap())
}

#[tokio::test]
async fn the_operator_limits_experiments_and_transitions() {
    let (_dir, app) = fresh_app_with_limits(Limits {
        max_experiments: 2,
        max_transitions: 3,
        ..Limits::default()
    })
    .await;
    let id = app.create_experiment(json!({})).await;
    app.create_experiment(json!({})).await;
    let (status, body) = app.post("/v1/experiments", &json!({})).await;
    assert_eq!((status, code(&body)), (409, "limit_reached"), "{body}");
    app.store_trajectory(id, &free_row_trajectory(0, 0, 3))
        .await;
    let (status, body) = app
        .post_at(id, "trajectories", &free_row_trajectory(0, 0, 4))
        .await;
    assert_eq!(status, 422);
    assert_eq!(body["error"]["details"]["field"], "transitions");
}

#[tokio::test]
async fn metrics_and_request_ids_are_exposed() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    app.post_at(id, "trajectories", &free_row_trajectory(0, 0, 2))
        .await;
    let r = app.client.get(app.url("/metrics")).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    assert!(
        r.headers()["content-type"]
            .to_str()
            .unwrap()
            .starts_with("text/plain")
    );
    let generated = r.headers()["x-request-id"].to_str().unwrap().to_string();
    assert_eq!(generated.len(), 36, "a UUID: {generated}");
    let text = r.text().await.unwrap();
    for needle in [
        "http_requests_total{",
        "route=\"/v1/experiments/{id}/trajectories\"",
        "http_request_duration_seconds_bucket{",
        "precond_store_experiments ",
        "precond_store_transitions ",
        "precond_store_bytes ",
        "precond_planning_queue_depth ",
    ] {
        assert!(text.contains(needle), "{needle} in\n{text}");
    }
    let r = app
        .client
        .get(app.url("/healthz"))
        .header("x-request-id", "robot-7-req-42")
        .send()
        .await
        .unwrap();
    assert_eq!(r.headers()["x-request-id"], "robot-7-req-42");
}

#[tokio::test]
async fn a_refit_past_its_deadline_is_202_with_the_old_version_and_finishes_in_the_background() {
    // 100 ms, the shortest deadline an operator may set, and a batch far larger than the data,
    // so only the forced refit fits.
    let (_dir, app) = fresh_app_with_limits(limits(2, 4, 100)).await;
    let id = app
        .create_experiment(json!({"domain": {"kind": "kinematic"},
                                  "mde": {"restarts": 20},
                                  "learning": {"batch_size": 100}}))
        .await;
    // 400 transitions of the true (kinematic) world.
    let mut rng = 7u64;
    let mut next = || {
        rng = rng
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (rng >> 11) as f64 / (1u64 << 53) as f64
    };
    for _ in 0..4 {
        let transitions: Vec<Value> = (0..100)
            .map(|_| {
                let s = [0.1 + 0.8 * next(), 0.1 + 0.8 * next()];
                let a = [0.2 * next() - 0.1, 0.2 * next() - 0.1];
                json!({"s": s, "a": a, "s_next": [s[0] + a[0], s[1] + a[1]]})
            })
            .collect();
        app.store_trajectory(id, &json!({"transitions": transitions}))
            .await;
    }
    let (status, body) = app.post_at(id, "model/refit", &json!({})).await;
    assert_eq!(status, 202, "{body}");
    assert_eq!(body["version"], 0, "the version still answering: {body}");
    // The fit goes on and is swapped in.
    let started = Instant::now();
    loop {
        let (_, m) = app.get_at(id, "model").await;
        if m["version"] == 1 {
            assert_eq!(m["n_train"], 400, "{m}");
            break;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "no fit: {m}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}
