//! Crash and shutdown tests against the real binary: `kill -9` at random (seeded) moments while
//! clients ingest with `Idempotency-Key` and retry across restarts; SIGTERM during ingest and
//! during a refit; an open proposal across a crash. Each test is bounded in time.

mod common;

use common::{
    Server, all_transitions, assert_lease_answered, assert_stored_exactly_once, experiment, get,
    http_with_timeout, ingest_only, join_robots, lease, metrics, post, refits_every, spawn_robots,
    trajectory, two_robots_trajectory,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use sqlx::Connection;
use std::path::Path;
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

async fn integrity_check(db: &Path) {
    let mut conn = sqlx::SqliteConnection::connect(&format!("sqlite://{}", db.display()))
        .await
        .unwrap();
    let (ok,): (String,) = sqlx::query_as("PRAGMA integrity_check")
        .fetch_one(&mut conn)
        .await
        .unwrap();
    assert_eq!(ok, "ok");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn kill_9_during_concurrent_ingest_loses_no_acknowledged_trajectory() {
    const CLIENTS: usize = 16;
    const PER_CLIENT: usize = 20;
    const KILLS: usize = 6;
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("crash.db");
    let server = Server::start(&db, &[]);
    let http = http_with_timeout(Duration::from_secs(5));
    let id = experiment(&http, &server.base, ingest_only()).await;
    let base = Arc::new(RwLock::new(vec![server.base.clone()]));
    let started = Instant::now();

    // Clients: post each trajectory with its key until acknowledged, whatever happens.
    let clients = spawn_robots(&http, &base, id, CLIENTS, PER_CLIENT);

    // The killer: kill -9 at seeded random moments, restart on the same file.
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let mut server = server;
    for kill in 0..KILLS {
        tokio::time::sleep(Duration::from_millis(rng.random_range(40..200))).await;
        assert!(
            clients.iter().any(|c| !c.is_finished()),
            "kill {kill} comes while clients are ingesting"
        );
        server.kill9();
        server = Server::start(&db, &[]);
        base.write().unwrap()[0] = server.base.clone();
    }
    let (acked, retries) = join_robots(clients).await;
    assert!(started.elapsed() < Duration::from_secs(40));
    assert!(
        retries >= KILLS,
        "the kills interrupted ingest ({retries} retries)"
    );
    assert_eq!(acked.len(), CLIENTS * PER_CLIENT);

    // Every acknowledged trajectory stored exactly once, whole, with its labels.
    assert_stored_exactly_once(&http, &server.base, id, &acked).await;
    server.kill9();
    integrity_check(&db).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn an_open_proposal_survives_a_crash_and_is_returned_to_its_client() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("proposal.db");
    let server = Server::start(&db, &[]);
    let http = reqwest::Client::new();
    let id = experiment(
        &http,
        &server.base,
        json!({"domain": {"kind": "kinematic"}}),
    )
    .await;
    let first = lease(&http, &server.base, id).await;
    server.kill9();
    let server = Server::start(&db, &[]);
    assert_lease_answered(&http, &server.base, id, &first).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn sigterm_during_ingest_finishes_or_fails_cleanly_and_exits_in_time() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("term.db");
    let mut server = Server::start(&db, &["--shutdown-grace-secs", "3"]);
    let http = http_with_timeout(Duration::from_secs(10));
    let id = experiment(&http, &server.base, ingest_only()).await;
    let url = format!("{}/v1/experiments/{id}/trajectories", server.base);
    let mut clients = Vec::new();
    for c in 0..8 {
        let (http, url) = (http.clone(), url.clone());
        clients.push(tokio::spawn(async move {
            let mut acked = Vec::new();
            for k in 0..1000 {
                let (body, _) = trajectory(100 + c, k);
                match http.post(&url).json(&body).send().await {
                    Ok(r) => {
                        let status = r.status().as_u16();
                        let v: Value = r.json().await.unwrap_or(Value::Null);
                        assert_eq!(status, 201, "an in-flight request finishes: {v}");
                        acked.push(v["id"].as_i64().unwrap());
                    }
                    // Refused or closed once the server stops accepting: a clean failure.
                    Err(e) => {
                        assert!(e.is_connect() || e.is_request(), "{e}");
                        break;
                    }
                }
            }
            acked
        }));
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    server.sigterm();
    let (status, took) = server.wait_exit(Duration::from_secs(3 + 5));
    assert!(status.success(), "{status}");
    assert!(took < Duration::from_secs(3 + 2), "{took:?}");
    let mut acked = Vec::new();
    for c in clients {
        acked.extend(c.await.unwrap());
    }
    assert!(!acked.is_empty());
    assert!(server.logged("shutdown requested"));
    let server = Server::start(&db, &[]);
    let stored = all_transitions(&http, &server.base, id).await;
    let tids: std::collections::HashSet<i64> = stored
        .iter()
        .map(|t| t["trajectory_id"].as_i64().unwrap())
        .collect();
    for tid in &acked {
        assert!(
            tids.contains(tid),
            "acknowledged trajectory {tid} is stored"
        );
    }
    server.kill9();
    integrity_check(&db).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn sigterm_during_a_refit_exits_in_time_and_the_next_start_refits() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("refit.db");
    let mut server = Server::start(&db, &["--shutdown-grace-secs", "1"]);
    let http = reqwest::Client::new();
    // One batch of 40 trajectories (about 280 transitions): a heteroscedastic fit with a few
    // restarts takes seconds in a debug build, long enough to be caught running.
    let id = experiment(&http, &server.base, refits_every(40, 3)).await;
    let url = format!("{}/v1/experiments/{id}/trajectories", server.base);
    for k in 0..40 {
        let body = two_robots_trajectory(200, k);
        let (status, v) = post(&http, &url, &body).await;
        assert_eq!(status, 201, "{v}");
    }
    // The batch is complete: a background fit starts. Wait until it runs, then stop.
    let started = Instant::now();
    loop {
        if metrics(&http, &server.base)
            .await
            .contains("precond_planning_running 1")
        {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "no fit started"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    server.sigterm();
    let (status, took) = server.wait_exit(Duration::from_secs(10));
    assert!(status.success(), "{status}");
    assert!(took < Duration::from_secs(1 + 3), "{took:?}");
    // The next start fits the batch the stopped one did not store.
    let server = Server::start(&db, &[]);
    let started = Instant::now();
    loop {
        let (_, model) = get(&http, &format!("{}/v1/experiments/{id}/model", server.base)).await;
        if model["version"].as_i64().unwrap_or(0) >= 1 {
            assert_eq!(model["n_train"].as_i64().unwrap(), {
                let e = get(&http, &format!("{}/v1/experiments/{id}", server.base))
                    .await
                    .1;
                e["n_transitions"].as_i64().unwrap()
            });
            eprintln!("refitted after the restart in {:?}", started.elapsed());
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(40),
            "the batch was not refitted after the restart: {:?}",
            server.log.lock().unwrap()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    server.kill9();
    integrity_check(&db).await;
}
