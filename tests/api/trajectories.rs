use crate::helpers::*;
use precond::http::HttpConfig;
use serde_json::{Value, json};
use std::collections::HashSet;

#[tokio::test]
async fn ingest_labels_transitions_and_survives_a_restart() {
    let (_dir, app, id) = fresh_experiment(json!({"name": "restart"})).await;
    // On ice at (3, 2) the x-move [1, 0] ends at (2, 2): the model said (4, 2), deviation 2.
    let body = json!({"transitions": [
        {"s": [3, 2], "a": [1, 0], "s_next": [2, 2]},
        {"s": [2, 2], "a": [0, 1], "s_next": [2, 3]},
        {"s": [2, 3], "a": [0, 1], "s_next": [2, 4]}
    ]});
    let created = app.store_trajectory(id, &body).await;
    assert_eq!(created["deviations"], json!([2.0, 0.0, 0.0]));
    assert_eq!(created["n_transitions"], 3);
    assert_eq!(created["iteration"], 0);
    let tid = created["id"].as_i64().unwrap();
    for k in 0..5 {
        app.store_trajectory(id, &free_row_trajectory(0, 0, 1 + k))
            .await;
    }
    let before = app.all_transitions(id).await;
    assert_eq!(before.len(), 3 + 1 + 2 + 3 + 4 + 5);
    let (_, experiment) = app.get_at(id, "").await;
    assert_eq!(experiment["n_trajectories"], 6);
    assert_eq!(experiment["iteration"], 1);

    let app = app.restart().await;
    let after = app.all_transitions(id).await;
    assert_eq!(before, after, "every transition and label is still there");
    let (status, t) = app
        .get(&format!("/v1/experiments/{id}/trajectories/{tid}"))
        .await;
    assert_eq!(status, 200);
    let steps = t["transitions"].as_array().unwrap();
    assert_eq!(steps.len(), 3);
    assert_eq!(steps[0]["s_pred"], json!([4.0, 2.0]));
    assert_eq!(steps[0]["deviation"], 2.0);
    let (_, experiment) = app.get_at(id, "").await;
    assert_eq!(experiment["n_transitions"], 18);
    app.stop().await;
}

#[tokio::test]
async fn an_idempotency_key_with_a_tab_is_refused_and_nothing_stored() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    let r = app
        .client
        .post(app.url(&format!("/v1/experiments/{id}/trajectories")))
        .header("Idempotency-Key", "run\t7")
        .json(&free_row_trajectory(0, 0, 3))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 422);
    let body: Value = r.json().await.unwrap();
    assert_eq!(
        body["error"]["details"]["field"], "Idempotency-Key",
        "{body}"
    );
    let (_, list) = app.get_at(id, "transitions").await;
    assert_eq!(list["items"].as_array().unwrap().len(), 0, "{list}");
}

#[tokio::test]
async fn a_retry_with_the_same_idempotency_key_stores_nothing_twice() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    let url = app.url(&format!("/v1/experiments/{id}/trajectories"));
    let body = free_row_trajectory(0, 0, 3);
    let send = |b: Value| {
        app.client
            .post(&url)
            .header("Idempotency-Key", "run-7")
            .json(&b)
            .send()
    };
    let first = send(body.clone()).await.unwrap();
    assert_eq!(first.status().as_u16(), 201);
    let first: Value = first.json().await.unwrap();
    let again = send(body.clone()).await.unwrap();
    assert_eq!(again.status().as_u16(), 201);
    assert_eq!(again.headers()["idempotent-replayed"], "true");
    let again: Value = again.json().await.unwrap();
    assert_eq!(first, again);
    let other = send(free_row_trajectory(0, 1, 3)).await.unwrap();
    assert_eq!(other.status().as_u16(), 409);
    assert_eq!(code(&other.json().await.unwrap()), "conflict");
    assert_eq!(app.all_transitions(id).await.len(), 3);
}

#[tokio::test]
async fn invalid_trajectories_are_refused_whole_with_the_field_named() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    let path = format!("/v1/experiments/{id}/trajectories");
    let good = json!({"s": [0, 0], "a": [1, 0], "s_next": [1, 0]});
    let cases = [
        (
            json!({"transitions": [good, {"s": [1, 0, 0], "a": [1, 0], "s_next": [2, 0]}]}),
            "transitions[1].s",
        ),
        (
            json!({"transitions": [{"s": [0, 0], "a": [1, 1], "s_next": [1, 0]}]}),
            "transitions[0].a",
        ),
        (
            json!({"transitions": [{"s": [0, 0], "a": [1, 0], "s_next": [1]}]}),
            "transitions[0].s_next",
        ),
        (
            json!({"transitions": [{"s": [0.5, 0], "a": [1, 0], "s_next": [1, 0]}]}),
            "transitions[0].s",
        ),
        (
            json!({"transitions": [{"s": [0, 0], "a": [1, 0], "s_next": [1, 0], "t": 3}]}),
            "transitions[0].t",
        ),
        (
            json!({"transitions": [{"s": [0, 0], "a": [1, 0], "s_next": [1, null]}]}),
            "transitions[0].s_next[1]",
        ),
        (json!({"transitions": []}), "transitions"),
        (json!({"trajectory": []}), "trajectory"),
        (
            json!({"transitions": [good], "proposal_id": 99}),
            "proposal_id",
        ),
    ];
    for (body, field) in cases {
        let (status, err) = app.post(&path, &body).await;
        assert_eq!(status, 422, "{body} -> {err}");
        assert_eq!(code(&err), "validation_failed");
        assert_eq!(err["error"]["details"]["field"], field, "{body}");
        assert!(!reason(&err).is_empty());
    }
    // Numbers JSON cannot hold as a finite f64 are refused too.
    let (status, err) = app
        .post_raw(
            &path,
            r#"{"transitions": [{"s": [0, 0], "a": [1, 0], "s_next": [1e999, 0]}]}"#,
        )
        .await;
    assert!(status == 400 || status == 422, "{status} {err}");
    let (status, err) = app.post_raw(&path, r#"{"transitions": [{"s": [0, 0"#).await;
    assert_eq!(status, 400, "{err}");
    assert_eq!(code(&err), "bad_request");
    let (status, err) = app.post_raw(&path, "not json").await;
    assert_eq!((status, code(&err)), (400, "bad_request"));
    let (status, err) = app
        .post(
            "/v1/experiments/999/trajectories",
            &json!({"transitions": [good]}),
        )
        .await;
    assert_eq!((status, code(&err)), (404, "not_found"));
    assert!(
        app.all_transitions(id).await.is_empty(),
        "nothing was stored"
    );
}

#[tokio::test]
async fn an_oversized_body_is_413() {
    let (_dir, app) = fresh_app_with(HttpConfig {
        max_body_bytes: 2048,
        ..HttpConfig::default()
    })
    .await;
    let id = app.create_experiment(json!({})).await;
    let (status, err) = app
        .post_at(id, "trajectories", &free_row_trajectory(0, 0, 100))
        .await;
    assert_eq!(status, 413, "{err}");
    assert_eq!(code(&err), "payload_too_large");
    assert!(app.all_transitions(id).await.is_empty());
}

#[tokio::test]
async fn transitions_come_as_csv_when_asked() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    app.post_at(id, "trajectories", &free_row_trajectory(0, 0, 2))
        .await;
    let r = app
        .client
        .get(app.url(&format!("/v1/experiments/{id}/transitions")))
        .header("accept", "text/csv")
        .send()
        .await
        .unwrap();
    assert!(
        r.headers()["content-type"]
            .to_str()
            .unwrap()
            .starts_with("text/csv")
    );
    let text = r.text().await.unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(
        lines[0],
        "id,trajectory_id,step,s.x,s.y,a.dx,a.dy,s_next.x,s_next.y,s_pred.x,s_pred.y,deviation"
    );
    assert_eq!(lines.len(), 3);
    assert_eq!(lines[2], "2,1,1,1,0,1,0,2,0,2,0,0");
}

#[tokio::test]
async fn sixteen_concurrent_clients_lose_and_duplicate_nothing() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    let url = app.url(&format!("/v1/experiments/{id}/trajectories"));
    let mut tasks = Vec::new();
    for client in 0..16i64 {
        let url = url.clone();
        let http = reqwest::Client::new();
        tasks.push(tokio::spawn(async move {
            let mut ids = Vec::new();
            for k in 0..5i64 {
                // Row y = client % 12 has neither ice nor obstacles at y ∈ {0, 1, 4, 5, 7, 8, 10, 11}.
                let y = [0, 1, 4, 5, 7, 8, 10, 11][(client % 8) as usize];
                let body = free_row_trajectory(k, y, 1 + (client + k) % 4);
                let key = format!("client-{client}-traj-{k}");
                // Every request is sent twice, as a client that lost the first response would.
                let mut seen = None;
                for _ in 0..2 {
                    let r = http
                        .post(&url)
                        .header("Idempotency-Key", &key)
                        .json(&body)
                        .send()
                        .await
                        .unwrap();
                    assert_eq!(r.status().as_u16(), 201);
                    let v: Value = r.json().await.unwrap();
                    if let Some(prev) = &seen {
                        assert_eq!(prev, &v);
                    }
                    seen = Some(v);
                }
                let v = seen.unwrap();
                ids.push((
                    v["id"].as_i64().unwrap(),
                    v["n_transitions"].as_i64().unwrap(),
                ));
            }
            ids
        }));
    }
    let mut trajectory_ids = HashSet::new();
    let mut expected_transitions = 0;
    for t in tasks {
        for (tid, n) in t.await.unwrap() {
            assert!(
                trajectory_ids.insert(tid),
                "trajectory {tid} handed out twice"
            );
            expected_transitions += n;
        }
    }
    assert_eq!(trajectory_ids.len(), 80);
    let all = app.all_transitions(id).await;
    assert_eq!(all.len() as i64, expected_transitions);
    let unique: HashSet<i64> = all.iter().map(|t| t["id"].as_i64().unwrap()).collect();
    assert_eq!(unique.len(), all.len());
    let (_, experiment) = app.get_at(id, "").await;
    assert_eq!(experiment["n_trajectories"], 80);
    assert_eq!(experiment["iteration"], 16);
}

/// A server on a new database with one experiment that holds `rows` trajectories of 4
/// transitions (rows `0..rows` of the gridworld); the dir lives as long as it is kept.
async fn app_with_rows(rows: i64) -> (tempfile::TempDir, std::path::PathBuf, TestApp, i64) {
    let (dir, db) = temp_db();
    let app = spawn_app(&db).await;
    let id = app.create_experiment(json!({})).await;
    for y in 0..rows {
        app.store_trajectory(id, &free_row_trajectory(0, y, 4))
            .await;
    }
    (dir, db, app, id)
}

#[tokio::test]
async fn an_online_backup_is_a_consistent_copy() {
    if super::helpers::sqlite_only("an_online_backup_is_a_consistent_copy") {
        return;
    }
    let (dir, db, app, id) = app_with_rows(3).await;
    // While the server is serving.
    let live = open_store(&db).await;
    let copy = dir.path().join("backup.db");
    live.backup_to(copy.to_str().unwrap()).await.unwrap();
    live.close().await;
    let (status, _) = app
        .post_at(id, "trajectories", &free_row_trajectory(0, 3, 4))
        .await;
    assert_eq!(status, 201, "the server keeps writing");
    let backup = open_store(&copy).await;
    let size = backup.size().await.unwrap();
    assert_eq!(
        (size.experiments, size.trajectories, size.transitions),
        (1, 3, 12)
    );
}

/// `precond backup`: the counts it reports are the copy's; the copy takes its name only once
/// complete; a missing source is an error, never created; nothing is left behind on failure.
#[tokio::test]
async fn a_backup_reports_its_own_counts_and_leaves_nothing_half_written() {
    if super::helpers::sqlite_only(
        "a_backup_reports_its_own_counts_and_leaves_nothing_half_written",
    ) {
        return;
    }
    let (dir, db, app, _) = app_with_rows(2).await;
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let copy = out.join("copy.db");
    let size = precond::store::backup(db.to_str().unwrap(), &copy)
        .await
        .unwrap();
    assert_eq!(
        (size.experiments, size.trajectories, size.transitions),
        (1, 2, 8)
    );
    assert_eq!(size.bytes as u64, std::fs::metadata(&copy).unwrap().len());
    let opened = open_store(&copy).await;
    let inside = opened.size().await.unwrap();
    assert_eq!(
        (inside.experiments, inside.trajectories, inside.transitions),
        (size.experiments, size.trajectories, size.transitions)
    );
    opened.close().await;
    let listing = |d: &std::path::Path| -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| !n.ends_with("-wal") && !n.ends_with("-shm"))
            .collect();
        names.sort();
        names
    };
    assert_eq!(listing(&out), vec!["copy.db"], "no temporary file is left");

    // A second backup to the same name is refused and leaves the first alone.
    let e = precond::store::backup(db.to_str().unwrap(), &copy)
        .await
        .unwrap_err();
    assert!(e.to_string().contains("exists"), "{e}");
    // A mistyped source is an error and is not created.
    let typo = dir.path().join("typo.db");
    let e = precond::store::backup(typo.to_str().unwrap(), &out.join("x.db"))
        .await
        .unwrap_err();
    assert!(e.to_string().contains("does not exist"), "{e}");
    assert!(!typo.exists(), "the backup created its source");
    // A source that is not a database fails, and leaves no file under the final name nor a
    // temporary one.
    let junk = dir.path().join("junk.db");
    std::fs::write(&junk, b"not a database at all, just some bytes").unwrap();
    assert!(
        precond::store::backup(junk.to_str().unwrap(), &out.join("y.db"))
            .await
            .is_err()
    );
    assert_eq!(listing(&out), vec!["copy.db"]);
    // A killed backup's hidden temporary (its process gone) is removed by the next backup to
    // the same name; one of a backup that still runs (here: this test's parent) is left alone.
    let gone = std::process::Command::new("true").spawn().unwrap();
    let dead = gone.id();
    let mut gone = gone;
    gone.wait().unwrap();
    let running = std::os::unix::process::parent_id();
    for pid in [dead, running] {
        std::fs::write(out.join(format!(".z.db.backup-{pid}.tmp")), b"half").unwrap();
    }
    std::fs::write(out.join(format!(".z.db.backup-{dead}.tmp-journal")), b"j").unwrap();
    precond::store::backup(db.to_str().unwrap(), &out.join("z.db"))
        .await
        .unwrap();
    assert_eq!(
        listing(&out),
        vec![
            format!(".z.db.backup-{running}.tmp"),
            "copy.db".to_string(),
            "z.db".to_string()
        ]
    );
    app.stop().await;
}

#[tokio::test]
async fn a_long_trajectory_is_stored_whole_in_its_order() {
    let (_dir, app) = fresh_app().await;
    let id = app
        .create_experiment(json!({"domain": {"kind": "kinematic"}}))
        .await;
    // 700 steps (several INSERT statements' worth), each moving 80 % of a distinct action.
    let transitions: Vec<Value> = (0..700)
        .map(|k| {
            let x = 0.1 + 0.001 * k as f64;
            json!({"s": [x, 0.5], "a": [0.001, 0.0], "s_next": [x + 0.0008, 0.5]})
        })
        .collect();
    let (status, created) = app
        .post(
            &format!("/v1/experiments/{id}/trajectories"),
            &json!({ "transitions": transitions }),
        )
        .await;
    assert_eq!(status, 201, "{created}");
    let stored = app.all_transitions(id).await;
    assert_eq!(stored.len(), 700);
    let mut last_id = 0;
    for (k, (t, sent)) in stored.iter().zip(&transitions).enumerate() {
        assert_eq!(t["step"], k as i64, "ids follow the steps");
        assert_eq!(t["s"], sent["s"]);
        assert!(t["id"].as_i64().unwrap() > last_id);
        last_id = t["id"].as_i64().unwrap();
    }
    app.stop().await;
}
