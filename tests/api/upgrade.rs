//! A database written before the stored rows were complete (migrations 0001–0005 only, rows
//! without the settings and records added later) opens, is completed by the later migrations,
//! and serves exactly what it served before: the settings it was used with, its model version,
//! and the first answer to a retried ingest.

use super::helpers::{spawn_app, temp_db};
use nalgebra::{DMatrix, DVector};
use precond::api::TrajectoryRequest;
use precond::domain::Transition;
use precond::gp::{GpModel, GpParams, NoiseMode};
use precond::settings::ExperimentRequest;
use serde_json::{Value, json};
use sqlx::sqlite::SqliteConnectOptions;
use sqlx::{Connection, SqliteConnection};
use std::borrow::Cow;
use std::str::FromStr;

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
    let (_dir, db) = temp_db();
    let mut conn = SqliteConnection::connect_with(
        &SqliteConnectOptions::from_str(db.to_str().unwrap())
            .unwrap()
            .create_if_missing(true),
    )
    .await
    .unwrap();
    let mut old = sqlx::migrate!("./migrations");
    old.migrations = Cow::Owned(
        old.migrations
            .iter()
            .filter(|m| m.version <= 5)
            .cloned()
            .collect(),
    );
    old.run(&mut conn).await.unwrap();

    // An experiment of that time: no kernel, no label cap, no relax_beta in its settings.
    let (settings, _) = ExperimentRequest::default()
        .resolve(&Default::default())
        .unwrap();
    let mut stored = serde_json::to_value(&settings).unwrap();
    for path in ["mde.kernel", "mde.label_cap", "learning.relax_beta"] {
        strip(&mut stored, path);
    }
    let created = "2026-01-01T00:00:00Z";
    sqlx::query("INSERT INTO experiments (id, name, settings, created_at) VALUES (1, '', ?, ?)")
        .bind(stored.to_string())
        .bind(created)
        .execute(&mut conn)
        .await
        .unwrap();
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
    assert_eq!(experiment["model_version"], 1);

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
    assert_eq!(body, first_answer);
    let (_, experiment) = app.get("/v1/experiments/1").await;
    assert_eq!(experiment["n_trajectories"], 1);
    app.stop().await;
}
