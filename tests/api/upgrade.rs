//! A database written before the stored rows were complete (migrations 0001–0005 only, rows
//! without the settings and records added later) opens, is completed by the later migrations,
//! and serves exactly what it served before: the settings it was used with, its model version,
//! and the first answer to a retried ingest.

use super::helpers::{count_true, spawn_app, temp_db};
use nalgebra::{DMatrix, DVector};
use precond::api::TrajectoryRequest;
use precond::domain::Transition;
use precond::gp::{GpModel, GpParams, NoiseMode};
use precond::settings::ExperimentRequest;
use serde_json::{Value, json};
use sqlx::sqlite::SqliteConnectOptions;
use sqlx::{Connection, SqliteConnection};
use std::borrow::Cow;
use std::path::Path;
use std::str::FromStr;

/// A new database at `db` with the migrations up to `version` only, as an older server left it.
async fn migrated_up_to(db: &Path, version: i64) -> SqliteConnection {
    let mut conn = SqliteConnection::connect_with(
        &SqliteConnectOptions::from_str(db.to_str().unwrap())
            .unwrap()
            .create_if_missing(true),
    )
    .await
    .unwrap();
    let mut old = sqlx::migrate!("../../migrations/sqlite");
    old.migrations = Cow::Owned(
        old.migrations
            .iter()
            .filter(|m| m.version <= version)
            .cloned()
            .collect(),
    );
    old.run(&mut conn).await.unwrap();
    conn
}

/// Removes `path` (`a.b`) from a JSON object.
fn strip(v: &mut Value, path: &str) {
    let (parent, key) = path.rsplit_once('.').unwrap();
    v.pointer_mut(&format!("/{}", parent.replace('.', "/")))
        .and_then(Value::as_object_mut)
        .unwrap()
        .remove(key);
}

#[tokio::test]
async fn a_database_from_before_the_records_were_complete_serves_what_it_served() {
    if super::helpers::sqlite_only(
        "a_database_from_before_the_records_were_complete_serves_what_it_served",
    ) {
        return;
    }
    let (_dir, db) = temp_db();
    let mut conn = migrated_up_to(&db, 5).await;

    // An experiment of that time: no kernel, no label cap, no relax_beta, acquisition,
    // batch_diversity, warmup_iterations or local_test_margin in its settings.
    let (settings, _) = ExperimentRequest::default()
        .resolve(&Default::default())
        .unwrap();
    let mut stored = serde_json::to_value(&settings).unwrap();
    for path in [
        "mde.kernel",
        "mde.label_cap",
        "learning.relax_beta",
        "learning.acquisition",
        "learning.batch_diversity",
        "learning.warmup_iterations",
        "learning.local_test_margin",
    ] {
        strip(&mut stored, path);
    }
    // A kinematic experiment of that time: its domain without `features`.
    let (kinematic, _) = serde_json::from_value::<ExperimentRequest>(json!({
        "domain": {"kind": "kinematic"}
    }))
    .unwrap()
    .resolve(&Default::default())
    .unwrap();
    let mut kinematic = serde_json::to_value(&kinematic).unwrap();
    strip(&mut kinematic, "domain.features");
    // A custom one: its features without `action_length`.
    let (custom, _) = serde_json::from_value::<ExperimentRequest>(json!({
        "domain": {"kind": "custom",
                   "state": {"low": [0, 0], "high": [1, 1]},
                   "action": {"low": [-0.1, -0.1], "high": [0.1, 0.1]},
                   "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]}}
    }))
    .unwrap()
    .resolve(&Default::default())
    .unwrap();
    let mut custom = serde_json::to_value(&custom).unwrap();
    assert_eq!(custom["domain"]["features"]["action_length"], true);
    strip(&mut custom, "domain.features.action_length");
    let created = "2026-01-01T00:00:00Z";
    for (id, settings) in [(1, &stored), (2, &kinematic), (3, &custom)] {
        sqlx::query(
            "INSERT INTO experiments (id, name, settings, created_at) VALUES (?, '', ?, ?)",
        )
        .bind(id)
        .bind(settings.to_string())
        .bind(created)
        .execute(&mut conn)
        .await
        .unwrap();
    }
    // One trajectory of two gridworld moves, the second one off ice and bumped (deviation 1).
    let transitions = [
        ([0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.0], 0.0),
        ([1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0], 1.0),
    ];
    sqlx::query(
        "INSERT INTO trajectories (id, experiment_id, proposal_id, partial, n_transitions, created_at)
         VALUES (1, 1, NULL, 0, 2, ?)",
    )
    .bind(created)
    .execute(&mut conn)
    .await
    .unwrap();
    for (step, (s, a, s_next, s_pred, deviation)) in transitions.iter().enumerate() {
        sqlx::query(
            "INSERT INTO transitions
               (experiment_id, trajectory_id, step, s, a, s_next, s_pred, deviation)
             VALUES (1, 1, ?, ?, ?, ?, ?, ?)",
        )
        .bind(step as i64)
        .bind(json!(s).to_string())
        .bind(json!(a).to_string())
        .bind(json!(s_next).to_string())
        .bind(json!(s_pred).to_string())
        .bind(deviation)
        .execute(&mut conn)
        .await
        .unwrap();
    }
    // Its model version 1, fitted on the raw labels with the smooth kernel, recorded without a
    // kernel, a cap or trials.
    let features = [[0.0, 0.0, 1.0, 0.5], [1.0 / 11.0, 0.0, 0.5, 1.0]];
    let x = DMatrix::from_fn(2, 4, |i, j| features[i][j]);
    let y = DVector::from_vec(vec![0.0, 1.0]);
    let params = GpParams {
        noise: NoiseMode::Homoscedastic,
        restarts: 0,
        ..GpParams::default()
    }
    .check()
    .unwrap();
    let gp = GpModel::fit(&x, &y, &params).unwrap();
    let mut state = serde_json::to_value(gp.state()).unwrap();
    strip(&mut state, "hyperparameters.kernel");
    let mut hyper = serde_json::to_value(gp.hyperparameters()).unwrap();
    hyper.as_object_mut().unwrap().remove("kernel");
    sqlx::query(
        "INSERT INTO models (experiment_id, version, n_train, n_trajectories, noise, state,
                             hyperparameters, log_marginal_likelihood, fit_seconds, fitted_at)
         VALUES (1, 1, 2, 1, 'homoscedastic', ?, ?, ?, 0.01, ?)",
    )
    .bind(state.to_string())
    .bind(hyper.to_string())
    .bind(gp.log_marginal_likelihood())
    .bind(created)
    .execute(&mut conn)
    .await
    .unwrap();
    // The idempotency record of that ingest, as an HTTP answer with its status.
    let request = TrajectoryRequest {
        proposal_id: None,
        partial: false,
        source: None,
        transitions: transitions
            .iter()
            .map(|(s, a, s_next, _, _)| Transition::new(s.to_vec(), a.to_vec(), s_next.to_vec()))
            .collect(),
    };
    let first_answer = json!({
        "id": 1, "experiment_id": 1, "proposal_id": null, "partial": false,
        "n_transitions": 2, "deviations": [0.0, 1.0], "iteration": 0, "model_version": 0,
        "n_trajectories": 1, "created_at": created
    });
    sqlx::query(
        "INSERT INTO idempotency_keys (experiment_id, key, request, status, response, created_at)
         VALUES (1, 'first-try', ?, 201, ?, ?)",
    )
    .bind(serde_json::to_string(&request).unwrap())
    .bind(first_answer.to_string())
    .bind(created)
    .execute(&mut conn)
    .await
    .unwrap();
    conn.close().await.unwrap();

    let app = spawn_app(&db).await;
    let (status, experiment) = app.get("/v1/experiments/1").await;
    assert_eq!(status, 200, "{experiment}");
    assert_eq!(experiment["mde"]["kernel"], "matern52");
    assert_eq!(experiment["mde"]["label_cap"], 0.0);
    assert_eq!(experiment["learning"]["relax_beta"], false);
    assert_eq!(experiment["learning"]["acquisition"], "lcb");
    assert_eq!(experiment["learning"]["batch_diversity"], false);
    // Every `active` trajectory was the acquisition's.
    assert_eq!(experiment["learning"]["warmup_iterations"], 0);
    // Every state-action was judged at the test β.
    assert_eq!(experiment["learning"]["local_test_margin"], false);
    assert_eq!(experiment["model_version"], 1);
    // The kinematic one keeps the features its models were fitted on.
    let (status, old) = app.get("/v1/experiments/2").await;
    assert_eq!(status, 200, "{old}");
    assert_eq!(old["domain"]["features"], "state_action");
    let (status, old) = app.get("/v1/experiments/3").await;
    assert_eq!(status, 200, "{old}");
    assert_eq!(old["domain"]["features"]["action_length"], false);
    assert_eq!(old["domain"]["features"]["action"], json!([0, 1]));

    let (status, model) = app.get("/v1/experiments/1/model").await;
    assert_eq!(status, 200, "{model}");
    assert_eq!(model["version"], 1);
    assert_eq!(model["label_cap"], 0.0);
    assert_eq!(model["hyperparameters"]["kernel"], "matern52");
    assert_eq!(model["label_cap_trials"], json!([]));
    // The rebuilt version predicts as the fitted one did.
    let (status, judged) = app
        .post(
            "/v1/experiments/1/precondition",
            &json!({"points": [{"s": [1, 0], "a": [0, 1]}], "beta": 0}),
        )
        .await;
    assert_eq!(status, 200, "{judged}");
    let expected = gp.predict(&DMatrix::from_row_slice(1, 4, &features[1]));
    let mu = judged["results"][0]["mu"].as_f64().unwrap();
    assert!(
        (mu - expected.mean[0]).abs() < 1e-9,
        "{mu} vs {}",
        expected.mean[0]
    );

    // A retry under the old key answers the first answer, and stores nothing.
    let replay = app
        .client
        .post(format!("http://{}/v1/experiments/1/trajectories", app.addr))
        .header("idempotency-key", "first-try")
        .json(&request)
        .send()
        .await
        .unwrap();
    assert_eq!(replay.status(), 201);
    assert_eq!(replay.headers()["idempotent-replayed"], "true");
    let body: Value = replay.json().await.unwrap();
    // The first answer, with what answers say since migration 0009: an unsolicited
    // trajectory never deviates, and this one said nothing of its source.
    let mut expected = first_answer.clone();
    expected["deviating"] = json!(false);
    expected["source"] = Value::Null;
    assert_eq!(body, expected);
    let (_, experiment) = app.get("/v1/experiments/1").await;
    assert_eq!(experiment["n_trajectories"], 1);
    app.stop().await;
}

/// Trajectories stored before migration 0009 are checked once against their proposals by the
/// rule ingest applies since: other actions, a longer execution or another start deviate; a
/// prefix and a trajectory without a proposal do not.
#[tokio::test]
async fn migration_0009_flags_the_stored_executions_that_departed_from_their_proposals() {
    if super::helpers::sqlite_only(
        "migration_0009_flags_the_stored_executions_that_departed_from_their_proposals",
    ) {
        return;
    }
    let (_dir, db) = temp_db();
    let mut conn = migrated_up_to(&db, 7).await;
    let (settings, _) = ExperimentRequest::default()
        .resolve(&std::sync::Arc::new(
            precond::remote_model::ModelCalls::default(),
        ))
        .unwrap();
    let created = "2026-01-01T00:00:00Z";
    sqlx::query("INSERT INTO experiments (id, name, settings, created_at) VALUES (1, '', ?, ?)")
        .bind(serde_json::to_string(&settings).unwrap())
        .bind(created)
        .execute(&mut conn)
        .await
        .unwrap();
    let planned = [[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]];
    let body = json!({
        "trajectory": {"states": [[0, 0], [1, 0], [2, 0], [3, 0]], "actions": planned,
                       "mu": [0, 0, 0], "sigma": [1, 1, 1], "alpha_step": [-1, -1, -1],
                       "alpha": -1.0},
        "candidates": [{"alpha": -1.0, "length": 3}], "chosen_index": 0, "extensions": 12
    });
    // (start, actions) executed for proposals 1–4, then one trajectory without a proposal.
    let executions: [([f64; 2], Vec<[f64; 2]>, bool); 5] = [
        ([0.0, 0.0], planned[..2].to_vec(), false),
        ([0.0, 0.0], vec![[1.0, 0.0], [0.0, 1.0]], true),
        ([0.0, 1.0], planned.to_vec(), true),
        ([0.0, 0.0], [&planned[..], &[[0.0, 1.0]]].concat(), true),
        ([0.0, 0.0], vec![[0.0, 1.0]], false),
    ];
    for (k, (start, actions, _)) in executions.iter().enumerate() {
        let id = k as i64 + 1;
        let proposal = (k < 4).then_some(id);
        if proposal.is_some() {
            sqlx::query(
                "INSERT INTO proposals (id, experiment_id, client_id, status, iteration, beta,
                                        strategy, model_version, start, goal, body, created_at,
                                        expires_at, expires_unix)
                 VALUES (?, 1, NULL, 'executed', 0, -1.97, 'active', 0, '[0.0,0.0]', '[3.0,0.0]',
                         ?, ?, ?, 0)",
            )
            .bind(id)
            .bind(body.to_string())
            .bind(created)
            .bind(created)
            .execute(&mut conn)
            .await
            .unwrap();
        }
        sqlx::query(
            "INSERT INTO trajectories (id, experiment_id, proposal_id, partial, n_transitions,
                                       created_at)
             VALUES (?, 1, ?, 0, ?, ?)",
        )
        .bind(id)
        .bind(proposal)
        .bind(actions.len() as i64)
        .bind(created)
        .execute(&mut conn)
        .await
        .unwrap();
        let mut s = *start;
        for (step, a) in actions.iter().enumerate() {
            let next = [s[0] + a[0], s[1] + a[1]];
            sqlx::query(
                "INSERT INTO transitions
                   (experiment_id, trajectory_id, step, s, a, s_next, s_pred, deviation)
                 VALUES (1, ?, ?, ?, ?, ?, ?, 0.0)",
            )
            .bind(id)
            .bind(step as i64)
            .bind(json!(s).to_string())
            .bind(json!(a).to_string())
            .bind(json!(next).to_string())
            .bind(json!(next).to_string())
            .execute(&mut conn)
            .await
            .unwrap();
            s = next;
        }
    }
    conn.close().await.unwrap();

    let app = spawn_app(&db).await;
    for (k, (_, _, deviating)) in executions.iter().enumerate() {
        let id = k + 1;
        let (status, t) = app
            .get(&format!("/v1/experiments/1/trajectories/{id}"))
            .await;
        assert_eq!(status, 200, "{t}");
        assert_eq!(t["deviating"], *deviating, "trajectory {id}");
        assert!(t["source"].is_null());
        if k < 4 {
            let (_, p) = app.get(&format!("/v1/experiments/1/proposals/{id}")).await;
            assert_eq!(p["deviating"], *deviating, "proposal {id}: {p}");
        }
    }
    let (_, page) = app.get("/v1/experiments/1/runs").await;
    let flagged = count_true(&page["items"], "deviating");
    assert_eq!(flagged, 3, "{page}");
    app.stop().await;
}
