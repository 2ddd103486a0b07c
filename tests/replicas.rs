//! Several replicas of the real binary over one PostgreSQL database: what one replica is told,
//! the other knows; a lease taken on one holds on the other; kill -9 of either replica loses
//! and duplicates nothing; a fit claimed by a killed replica is finished by another.
//!
//! They need a PostgreSQL server: `PRECOND_TEST_POSTGRES` (an admin URL; each test creates a
//! database of its own), which `scripts/ci-postgres.sh` starts and sets. Without it each test
//! says so and passes (the SQLite run cannot have replicas).

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
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

/// A new database on the test server, or `None` (said on stderr) without one.
async fn database(test: &str) -> Option<String> {
    let Some(admin) = std::env::var("PRECOND_TEST_POSTGRES")
        .ok()
        .filter(|u| !u.is_empty())
    else {
        eprintln!("{test}: no PRECOND_TEST_POSTGRES; run scripts/ci-postgres.sh");
        return None;
    };
    let name = format!("precond_replicas_{}", uuid::Uuid::new_v4().simple());
    let mut conn = sqlx::PgConnection::connect(&admin).await.unwrap();
    sqlx::query(&format!("CREATE DATABASE {name}"))
        .execute(&mut conn)
        .await
        .unwrap();
    let (server, _) = admin.rsplit_once('/').unwrap();
    Some(format!("{server}/{name}"))
}

/// Replica options for tests: short leases and polls, so a takeover fits in a test.
const FAST: &[&str] = &["--fit-lease-secs", "2", "--replica-poll-ms", "100"];

/// Waits (at most `limit`) until `base` answers experiment `id` with a model of `version` or
/// later, and returns it.
async fn model_at_least(
    http: &reqwest::Client,
    base: &str,
    id: i64,
    version: i64,
    limit: Duration,
) -> Value {
    let started = Instant::now();
    loop {
        let (status, model) = get(http, &format!("{base}/v1/experiments/{id}/model")).await;
        assert_eq!(status, 200, "{model}");
        if model["version"].as_i64() >= Some(version) {
            return model;
        }
        assert!(
            started.elapsed() < limit,
            "{base} answers version {} after {limit:?}, not {version}",
            model["version"]
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_trajectory_posted_to_one_replica_is_labelled_once_and_seen_by_the_other() {
    let Some(db) = database("labelled_once").await else {
        return;
    };
    let (a, b) = (Server::start(&db, FAST), Server::start(&db, FAST));
    let http = reqwest::Client::new();
    let id = experiment(&http, &a.base, refits_every(2, 1)).await;
    let (body, labels) = trajectory(1, 1);
    let send = |base: &str| {
        http.post(format!("{base}/v1/experiments/{id}/trajectories"))
            .header("idempotency-key", "robot-1-run-1")
            .json(&body)
            .send()
    };
    let first = send(&a.base).await.unwrap();
    assert_eq!(first.status(), 201);
    let first: Value = first.json().await.unwrap();
    // The robot did not hear the answer and retries on the other replica: the same answer,
    // nothing stored twice.
    let retry = send(&b.base).await.unwrap();
    assert_eq!(retry.status(), 201);
    assert_eq!(retry.headers()["idempotent-replayed"], "true");
    let retry: Value = retry.json().await.unwrap();
    assert_eq!(retry["id"], first["id"]);
    let seen = all_transitions(&http, &b.base, id).await;
    assert_eq!(seen.len(), labels.len(), "stored once: {seen:?}");
    for (t, label) in seen.iter().zip(&labels) {
        assert!((t["deviation"].as_f64().unwrap() - label).abs() < 1e-9);
    }
    // The batch completes on B; whichever replica fits, both answer the new version.
    let (status, _) = post(
        &http,
        &format!("{}/v1/experiments/{id}/trajectories", b.base),
        &trajectory(1, 2).0,
    )
    .await;
    assert_eq!(status, 201);
    let on_a = model_at_least(&http, &a.base, id, 1, Duration::from_secs(600)).await;
    let on_b = model_at_least(&http, &b.base, id, 1, Duration::from_secs(600)).await;
    assert_eq!(on_a["version"], 1);
    assert_eq!(on_a["n_trajectories"], 2);
    assert_eq!(on_a["hyperparameters"], on_b["hyperparameters"]);
    // One fit for one batch: no second version appears.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let (_, e) = get(&http, &format!("{}/v1/experiments/{id}", a.base)).await;
    assert_eq!(e["model_version"], 1, "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_proposal_leased_on_one_replica_is_the_same_on_the_other() {
    let Some(db) = database("lease").await else {
        return;
    };
    let (a, b) = (Server::start(&db, FAST), Server::start(&db, FAST));
    let http = reqwest::Client::new();
    let id = experiment(&http, &a.base, json!({"domain": {"kind": "kinematic"}})).await;
    let first = lease(&http, &a.base, id).await;
    assert_lease_answered(&http, &b.base, id, &first).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn kill_9_of_either_replica_loses_and_duplicates_nothing() {
    const CLIENTS: usize = 16;
    const PER_CLIENT: usize = 15;
    const KILLS: usize = 4;
    let Some(db) = database("kill_9").await else {
        return;
    };
    let mut replicas = vec![Server::start(&db, FAST), Server::start(&db, FAST)];
    let http = http_with_timeout(Duration::from_secs(5));
    let id = experiment(&http, &replicas[0].base, ingest_only()).await;
    let bases = Arc::new(RwLock::new(vec![
        replicas[0].base.clone(),
        replicas[1].base.clone(),
    ]));
    let started = Instant::now();

    // Clients: half start on each replica; after a failure they retry with the same key on the
    // other one, as a load balancer would send them.
    let clients = spawn_robots(&http, &bases, id, CLIENTS, PER_CLIENT);

    // The killer: kill -9 one replica or the other at seeded moments, and restart it.
    let mut rng = ChaCha8Rng::seed_from_u64(27);
    for kill in 0..KILLS {
        tokio::time::sleep(Duration::from_millis(rng.random_range(60..250))).await;
        assert!(
            clients.iter().any(|c| !c.is_finished()),
            "kill {kill} comes while clients are ingesting"
        );
        // The victim dies; until it is back, clients that send to it find it gone and retry
        // on the other replica.
        let victim = rng.random_range(0..2);
        let dead = replicas.remove(victim);
        dead.kill9();
        let restarted = Server::start(&db, FAST);
        bases.write().unwrap()[victim] = restarted.base.clone();
        replicas.insert(victim, restarted);
    }
    let (acked, retries) = join_robots(clients).await;
    assert!(started.elapsed() < Duration::from_secs(60));
    assert!(retries > 0, "the kills interrupted ingest");
    assert_eq!(acked.len(), CLIENTS * PER_CLIENT);

    // Every acknowledged trajectory stored exactly once, whole, with its labels — as either
    // replica sees it.
    for replica in &replicas {
        assert_stored_exactly_once(&http, &replica.base, id, &acked).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_fit_claimed_by_a_killed_replica_is_finished_by_the_other() {
    let Some(db) = database("takeover").await else {
        return;
    };
    let mut replicas = vec![Server::start(&db, FAST), Server::start(&db, FAST)];
    let http = reqwest::Client::new();
    // One batch of 60 trajectories (about 420 transitions) fitted with several restarts:
    // seconds in a test build, long enough to be caught running.
    let id = experiment(&http, &replicas[0].base, refits_every(60, 4)).await;
    for k in 0..60 {
        let body = two_robots_trajectory(300, k);
        let (status, v) = post(
            &http,
            &format!("{}/v1/experiments/{id}/trajectories", replicas[k % 2].base),
            &body,
        )
        .await;
        assert_eq!(status, 201, "{v}");
    }
    // Which replica claimed the fit? Its name carries its process id.
    let mut conn = sqlx::PgConnection::connect(&db).await.unwrap();
    let started = Instant::now();
    let holder = loop {
        let claimed: Option<Option<String>> =
            sqlx::query_scalar("SELECT claimed_by FROM fit_jobs WHERE experiment_id = $1")
                .bind(id)
                .fetch_optional(&mut conn)
                .await
                .unwrap();
        if let Some(Some(name)) = claimed {
            break name;
        }
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "no replica claimed the fit"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let victim = replicas
        .iter()
        .position(|r| holder.contains(&format!("-{}-", r.pid())))
        .expect("the claim names one of the replicas");
    // Each replica's metrics say who fits: the holder "here", the other "elsewhere".
    let fitting = |base: String, state: &'static str| {
        let http = http.clone();
        async move {
            metrics(&http, &base)
                .await
                .lines()
                .find_map(|l| {
                    l.strip_prefix(&format!("precond_fit_requests{{state=\"{state}\"}} "))
                        .map(|v| v.trim().parse::<f64>().unwrap())
                })
                .unwrap_or_default()
        }
    };
    assert_eq!(
        fitting(replicas[victim].base.clone(), "fitting_here").await,
        1.0
    );
    assert_eq!(
        fitting(replicas[1 - victim].base.clone(), "fitting_elsewhere").await,
        1.0
    );
    let survivor = replicas.remove(1 - victim);
    replicas.remove(0).kill9();
    // Nothing was stored by the dead replica; the survivor takes the fit over after the
    // lease and stores version 1.
    let model = model_at_least(&http, &survivor.base, id, 1, Duration::from_secs(600)).await;
    assert_eq!(model["version"], 1);
    assert_eq!(model["n_trajectories"], 60);
    let left: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM fit_jobs")
        .fetch_one(&mut conn)
        .await
        .unwrap();
    assert_eq!(left, 0, "the request is done");
    assert!(survivor.logged("model fitted"));
}
