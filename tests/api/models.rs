//! Several models of one robot in one experiment (`models`): every posted transition is
//! labelled by each, a model that fails leaves only its own label missing, the labels are
//! shown with the transitions (JSON and CSV) and survive a restart; an experiment with no
//! further models is stored and answered as before they existed.

use crate::helpers::*;
use crate::model_server;
use serde_json::{Value, json};

/// A point in the unit square moved by its action; the domain's own model is `s + a`.
fn plane(models: Value) -> Value {
    json!({"d_max": 0.05, "learning": {"batch_size": 1000},
           "domain": {"kind": "custom",
                      "state": {"low": [0, 0], "high": [1, 1]},
                      "action": {"low": [-0.1, -0.1], "high": [0.1, 0.1]},
                      "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]}},
           "models": models})
}

/// A model that ignores the action: `ŝ' = s`.
fn still() -> Value {
    json!({"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[0, 0], [0, 0]]})
}

/// Two transitions; the robot moves as `s + a` on the first, slides by 0.03 more on the second.
fn two_steps() -> Value {
    json!({"transitions": [
        {"s": [0.2, 0.2], "a": [0.1, 0], "s_next": [0.3, 0.2]},
        {"s": [0.3, 0.2], "a": [0.1, 0], "s_next": [0.43, 0.2]}]})
}

/// Every transition of experiment `id` as CSV.
async fn transitions_csv(app: &TestApp, id: i64) -> String {
    app.client
        .get(app.url(&format!("/v1/experiments/{id}/transitions")))
        .header("accept", "text/csv")
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap()
}

fn close(a: &Value, b: f64) -> bool {
    a.as_f64().is_some_and(|a| (a - b).abs() < 1e-9)
}

#[tokio::test]
async fn every_posted_transition_is_labelled_by_every_further_model() {
    let server = model_server::start().await;
    let (_dir, db) = temp_db();
    let app = spawn_app_allowing_models(&db, &[server.prefix()]).await;
    let id = app
        .create_experiment(plane(json!([
            {"name": "still", "cost": 0.1, "model": still()},
            {"name": "sim", "cost": 20,
             "model": {"kind": "remote", "url": server.url("predict")}}])))
        .await;
    let (_, experiment) = app.get(&format!("/v1/experiments/{id}")).await;
    let models = &experiment["models"];
    assert_eq!(models[0]["name"], "still", "{experiment}");
    assert_eq!(models[1]["cost"], 20.0, "{experiment}");
    assert_eq!(
        models[1]["model"]["timeout_ms"], 2000,
        "defaults filled in: {experiment}"
    );

    let (status, body) = app.post_at(id, "trajectories", &two_steps()).await;
    assert_eq!(status, 201, "{body}");
    let items = app.all_transitions(id).await;
    assert_eq!(items.len(), 2);
    // The domain's model and the remote `s + a` agree; `still` misses the whole move.
    for (t, moved) in items.iter().zip([0.0, 0.03]) {
        assert!(close(&t["deviation"], moved), "{t}");
        let labels = t["labels"].as_array().expect("labels");
        let names: Vec<&str> = labels
            .iter()
            .map(|l| l["model"].as_str().unwrap())
            .collect();
        assert_eq!(names, ["still", "sim"], "in the settings' order: {t}");
        assert!(close(&labels[0]["deviation"], 0.1 + moved), "{t}");
        assert_eq!(labels[0]["s_pred"], t["s"], "{t}");
        assert!(close(&labels[1]["deviation"], moved), "{t}");
        assert!(labels.iter().all(|l| l["missing"].is_null()), "{t}");
    }
    let trajectory_id = body["id"].as_i64().unwrap();
    let (_, trajectory) = app
        .get(&format!(
            "/v1/experiments/{id}/trajectories/{trajectory_id}"
        ))
        .await;
    assert_eq!(trajectory["transitions"][1]["labels"], items[1]["labels"]);

    let text = transitions_csv(&app, id).await;
    let lines: Vec<&str> = text.lines().collect();
    assert!(
        lines[0].ends_with(",deviation,deviation.still,deviation.sim"),
        "{}",
        lines[0]
    );
    let last: Vec<f64> = lines[2]
        .rsplit(',')
        .take(3)
        .map(|x| x.parse().unwrap())
        .collect();
    assert!(
        (last[0] - 0.03).abs() < 1e-9 && (last[1] - 0.13).abs() < 1e-9,
        "{}",
        lines[2]
    );
}

#[tokio::test]
async fn a_further_model_that_fails_leaves_its_label_missing_never_the_transition() {
    let server = model_server::start().await;
    let (_dir, db) = temp_db();
    let app = spawn_app_allowing_models(&db, &[server.prefix()]).await;
    let id = app
        .create_experiment(plane(json!([
            {"name": "broken", "model": {"kind": "remote", "url": server.url("error")}},
            {"name": "nan", "model": {"kind": "remote", "url": server.url("nan")}},
            {"name": "still", "model": still()}])))
        .await;
    let (status, body) = app.post_at(id, "trajectories", &two_steps()).await;
    assert_eq!(status, 201, "{body}");
    let items = app.all_transitions(id).await;
    assert_eq!(items.len(), 2, "both transitions stored");
    for t in &items {
        let labels = t["labels"].as_array().unwrap();
        assert_eq!(labels.len(), 3, "{t}");
        for missing in &labels[..2] {
            assert!(
                missing["deviation"].is_null() && missing["s_pred"].is_null(),
                "{t}"
            );
            assert!(!missing["missing"].as_str().unwrap().is_empty(), "{t}");
        }
        assert!(labels[2]["deviation"].as_f64().is_some(), "{t}");
    }
    let broken = items[0]["labels"][0]["missing"].as_str().unwrap();
    assert!(broken.contains("unavailable"), "{broken}");
    let text = transitions_csv(&app, id).await;
    let row: Vec<&str> = text.lines().nth(1).unwrap().rsplit(',').take(3).collect();
    assert_eq!(
        row[1..],
        ["", ""],
        "missing labels are empty cells: {row:?}"
    );
    assert!(
        (row[0].parse::<f64>().unwrap() - 0.1).abs() < 1e-9,
        "{row:?}"
    );
}

#[tokio::test]
async fn further_models_are_checked_field_by_field() {
    let (_dir, app) = fresh_app().await;
    let too_many: Vec<Value> = (0..5)
        .map(|i| json!({"name": format!("m{i}"), "model": still()}))
        .collect();
    for (models, field, why) in [
        (
            json!([{"name": "", "model": still()}]),
            "models[0].name",
            "1 to 32",
        ),
        (
            json!([{"name": "a b", "model": still()}]),
            "models[0].name",
            "letters",
        ),
        (
            json!([{"name": "domain", "model": still()}]),
            "models[0].name",
            "domain's own",
        ),
        (
            json!([{"name": "x", "model": still()}, {"name": "x", "model": still()}]),
            "models[1].name",
            "earlier model",
        ),
        (
            json!([{"name": "x", "cost": 0, "model": still()}]),
            "models[0].cost",
            "positive",
        ),
        (
            json!([{"name": "x", "cost": 1e7, "model": still()}]),
            "models[0].cost",
            "at most",
        ),
        (
            json!([{"name": "x", "model": {"kind": "oracle"}}]),
            "models[0].model",
            "unknown variant `oracle`",
        ),
        (
            json!([{"name": "x", "model": {"kind": "linear", "A": [[1, 0]], "B": [[1, 0], [0, 1]]}}]),
            "models[0].model.A",
            "",
        ),
        (
            json!([{"name": "x", "model": {"kind": "remote", "url": "http://nowhere.example/p"}}]),
            "models[0].model.url",
            "",
        ),
        (Value::Array(too_many), "models", "at most 4"),
    ] {
        let (status, body) = app.post("/v1/experiments", &plane(models.clone())).await;
        assert_eq!(status, 422, "{models}: {body}");
        let details = &body["error"]["details"];
        assert!(
            details["field"].as_str().unwrap().starts_with(field),
            "{models}: {body}"
        );
        assert!(
            details["reason"].as_str().unwrap().contains(why),
            "{models}: {body}"
        );
    }
    let (_, list) = app.get("/v1/experiments").await;
    assert_eq!(list["total"], 0, "nothing stored: {list}");
}

#[tokio::test]
async fn a_single_model_experiment_is_stored_and_answered_as_before() {
    let (_dir, db) = temp_db();
    let app = spawn_app(&db).await;
    let mut body = plane(json!([]));
    body.as_object_mut().unwrap().remove("models");
    let id = app.create_experiment(body).await;
    let (status, answer) = app.post_at(id, "trajectories", &two_steps()).await;
    assert_eq!(status, 201, "{answer}");
    let (_, experiment) = app.get(&format!("/v1/experiments/{id}")).await;
    assert_eq!(
        experiment["d_max"], 0.05,
        "the settings at the top: {experiment}"
    );
    assert!(experiment.get("models").is_none(), "{experiment}");
    for t in app.all_transitions(id).await {
        assert!(t.get("labels").is_none(), "{t}");
    }
    app.stop().await;
    if sqlite_only("a_single_model_experiment_is_stored_and_answered_as_before") {
        return;
    }
    let pool = sqlx::SqlitePool::connect(&format!("sqlite:{}", db.display()))
        .await
        .unwrap();
    let settings: String = sqlx::query_scalar("SELECT settings FROM experiments WHERE id = ?")
        .bind(id)
        .fetch_one(&pool)
        .await
        .unwrap();
    assert!(!settings.contains("\"models\""), "{settings}");
    let labels: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM model_labels")
        .fetch_one(&pool)
        .await
        .unwrap();
    assert_eq!(labels, 0);
}

#[tokio::test]
async fn labels_survive_a_restart_and_the_models_label_again_after_it() {
    let (_dir, app) = fresh_app().await;
    let id = app
        .create_experiment(plane(json!([{"name": "still", "model": still()}])))
        .await;
    app.post_at(id, "trajectories", &two_steps()).await;
    let before = app.all_transitions(id).await;
    let app = app.restart().await;
    assert_eq!(app.all_transitions(id).await, before);
    let (status, body) = app.post_at(id, "trajectories", &two_steps()).await;
    assert_eq!(status, 201, "{body}");
    let after = app.all_transitions(id).await;
    assert_eq!(after.len(), 4);
    assert_eq!(
        after[3]["labels"], before[1]["labels"],
        "the rebuilt model labels alike"
    );
}

/// A retried post (same `Idempotency-Key` and body) stores nothing: no second set of labels.
#[tokio::test]
async fn a_replayed_post_stores_no_second_set_of_labels() {
    let (_dir, app) = fresh_app().await;
    let id = app
        .create_experiment(plane(json!([{"name": "still", "model": still()}])))
        .await;
    for expected in [201, 201] {
        let r = app
            .client
            .post(app.url(&format!("/v1/experiments/{id}/trajectories")))
            .header("idempotency-key", "one")
            .json(&two_steps())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), expected);
    }
    let items = app.all_transitions(id).await;
    assert_eq!(items.len(), 2);
    assert!(
        items
            .iter()
            .all(|t| t["labels"].as_array().unwrap().len() == 1)
    );
}

/// `GET …/labels` sums up each model's labels: how often each was right where the robot went,
/// from the same executions; a model that could not answer counts its missing labels.
#[tokio::test]
async fn the_labels_summary_says_how_often_each_model_was_right() {
    let server = model_server::start().await;
    let (_dir, db) = temp_db();
    let app = spawn_app_allowing_models(&db, &[server.prefix()]).await;
    let id = app
        .create_experiment(plane(json!([
            {"name": "still", "cost": 0.1, "model": still()},
            {"name": "broken", "model": {"kind": "remote", "url": server.url("error")}}])))
        .await;
    let (status, empty) = app.get_at(id, "labels").await;
    assert_eq!(status, 200, "{empty}");
    assert_eq!(empty["items"][0]["n_labelled"], 0, "{empty}");
    assert!(empty["items"][1]["share_within_d_max"].is_null(), "{empty}");

    app.post_at(id, "trajectories", &two_steps()).await;
    let (_, summary) = app.get_at(id, "labels").await;
    let items = summary["items"].as_array().unwrap();
    let names: Vec<&str> = items.iter().map(|m| m["model"].as_str().unwrap()).collect();
    assert_eq!(names, ["domain", "still", "broken"], "{summary}");
    let domain = &items[0];
    assert_eq!(
        (&domain["kind"], &domain["cost"], &domain["n_labelled"]),
        (&json!("linear"), &json!(1.0), &json!(2)),
        "{summary}"
    );
    // The domain's model: 0 and 0.03 (d_max 0.05): right on both; `still`: 0.1 and 0.13.
    assert_eq!(domain["share_within_d_max"], 1.0, "{summary}");
    assert!(close(&domain["max_deviation"], 0.03), "{summary}");
    let still = &items[1];
    assert_eq!(still["share_within_d_max"], 0.0, "{summary}");
    assert!(close(&still["mean_deviation"], 0.115), "{summary}");
    assert_eq!(still["cost"], 0.1, "{summary}");
    let broken = &items[2];
    assert_eq!(
        (&broken["n_labelled"], &broken["n_missing"]),
        (&json!(0), &json!(2))
    );
    assert!(broken["mean_deviation"].is_null(), "{summary}");

    let (status, _) = app.get("/v1/experiments/999/labels").await;
    assert_eq!(status, 404);
}

/// The robot moves as its action says left of `x = 0.5` and not at all right of it: the
/// domain's model (`s + a`) is right on the left, `still` on the right.
fn half_and_half(seed: u64) -> Vec<Value> {
    let mut trajectories = Vec::new();
    let mut x = seed as f64 * 0.013;
    for k in 0..8 {
        let mut transitions = Vec::new();
        for j in 0..8 {
            x = (x + 0.137 + 0.01 * j as f64).fract();
            let s = [0.1 + 0.8 * x, 0.1 + 0.1 * k as f64];
            let a = [if j % 2 == 0 { 0.1 } else { -0.1 }, 0.0];
            let s_next = if s[0] < 0.5 { [s[0] + a[0], s[1]] } else { s };
            transitions.push(json!({"s": s, "a": a, "s_next": s_next}));
        }
        trajectories.push(json!({ "transitions": transitions }));
    }
    trajectories
}

async fn judged(app: &TestApp, id: i64, model: &str) -> Value {
    let points = json!([{"s": [0.2, 0.5], "a": [0.1, 0]}, {"s": [0.8, 0.5], "a": [0.1, 0]}]);
    let (status, body) = app
        .post_at(
            id,
            "precondition",
            &json!({"points": points, "beta": 0, "model": model}),
        )
        .await;
    assert_eq!(status, 200, "{body}");
    body
}

fn inside(body: &Value) -> Vec<bool> {
    body["results"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["inside"].as_bool().unwrap())
        .collect()
}

/// Each further model's precondition is learnt from its own labels in the same fit, queried by
/// name, and rebuilt after a restart with the same answers.
#[tokio::test]
async fn each_models_precondition_is_learnt_from_its_own_labels() {
    let (_dir, app) = fresh_app().await;
    let id = app
        .create_experiment(plane(json!([{"name": "still", "model": still()}])))
        .await;
    let (status, body) = app
        .post_at(
            id,
            "precondition",
            &json!({"points": [{"s": [0.2, 0.5], "a": [0.1, 0]}], "model": "still"}),
        )
        .await;
    assert_eq!(
        (status, code(&body)),
        (409, "conflict"),
        "before a fit: {body}"
    );
    for t in half_and_half(1) {
        app.store_trajectory(id, &t).await;
    }
    let model = app.refit(id).await;
    assert!(model["version"].as_i64() >= Some(1), "{model}");

    let domain = judged(&app, id, "domain").await;
    assert!(domain.get("model").is_none(), "the domain's own: {domain}");
    assert_eq!(inside(&domain), [true, false], "{domain}");
    let still = judged(&app, id, "still").await;
    assert_eq!(still["model"], "still", "{still}");
    assert_eq!(inside(&still), [false, true], "{still}");
    let (_, unnamed) = app
        .post_at(
            id,
            "precondition",
            &json!({"points": [{"s": [0.2, 0.5], "a": [0.1, 0]}], "beta": 0}),
        )
        .await;
    assert_eq!(
        unnamed["results"][0], domain["results"][0],
        "domain is the default"
    );
    let (_, one) = app
        .get_at(id, "precondition?s=0.8,0.5&a=0.1,0&beta=0&model=still")
        .await;
    assert_eq!(one["results"][0], still["results"][1], "{one}");

    let (status, body) = app
        .post_at(
            id,
            "precondition",
            &json!({"points": [{"s": [0.2, 0.5], "a": [0.1, 0]}], "model": "sim"}),
        )
        .await;
    assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
    assert_eq!(body["error"]["details"]["field"], "model", "{body}");
    assert!(reason(&body).contains("domain, still"), "{body}");

    // The export of `still`'s estimator evaluates to what the server judged, given what
    // `still` predicts (`s`: it ignores the action).
    let (status, doc) = app.get_at(id, "model/export?model=still").await;
    assert_eq!(status, 200, "{doc}");
    assert_eq!(doc["model"], "still", "{doc}");
    let exported: precond::mde::ExportedModel = serde_json::from_value(doc.clone()).unwrap();
    exported.check().unwrap();
    for (k, s) in [[0.2, 0.5], [0.8, 0.5]].iter().enumerate() {
        let (mu, _) = exported.evaluate_predicted(s, &[0.1, 0.0], s);
        let served = still["results"][k]["mu"].as_f64().unwrap();
        assert!(
            (mu - served).abs() < 1e-9 * served.abs().max(1.0),
            "{mu} against {served}"
        );
    }
    let (_, own) = app.get_at(id, "model/export").await;
    assert!(
        own.get("model").is_none(),
        "the domain model's export names none"
    );
    let (status, body) = app.get_at(id, "model/export?model=sim").await;
    assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");

    let app = app.restart().await;
    let rebuilt = judged(&app, id, "still").await;
    assert_eq!(
        rebuilt["results"], still["results"],
        "rebuilt as it was fitted"
    );
    assert_eq!(
        judged(&app, id, "domain").await["results"],
        domain["results"]
    );
}

/// A further model without a single label has no estimator: asking for its precondition is a
/// conflict, and the fit of the domain's model is not held up by it.
#[tokio::test]
async fn a_model_without_labels_has_no_precondition_yet() {
    let server = model_server::start().await;
    let (_dir, db) = temp_db();
    let app = spawn_app_allowing_models(&db, &[server.prefix()]).await;
    let id = app
        .create_experiment(plane(json!([
            {"name": "broken", "model": {"kind": "remote", "url": server.url("error")}}])))
        .await;
    for t in half_and_half(2).into_iter().take(3) {
        app.store_trajectory(id, &t).await;
    }
    let model = app.refit(id).await;
    assert!(model["version"].as_i64() >= Some(1), "{model}");
    let (status, body) = app
        .post_at(
            id,
            "precondition",
            &json!({"points": [{"s": [0.2, 0.5], "a": [0.1, 0]}], "model": "broken"}),
        )
        .await;
    assert_eq!((status, code(&body)), (409, "conflict"), "{body}");
    assert!(message(&body).contains("no estimator"), "{body}");
}

/// A point in the unit square moved by one of four moves of 0.1; the domain's model (`s + a`)
/// is right left of `x = 0.5`, and `slow` (`s + a / 2`) right of it, where the robot wades
/// through sand. Tolerance 0.02: each model is 0.05 off on the other half.
fn sand(models: Value) -> Value {
    json!({"d_max": 0.02, "learning": {"batch_size": 1000},
           "domain": {"kind": "custom",
                      "state": {"low": [0, 0], "high": [1, 1]},
                      "action": {"values": [[0.1, 0], [-0.1, 0], [0, 0.1], [0, -0.1]]},
                      "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]}},
           "models": models})
}

fn slow() -> Value {
    json!({"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[0.5, 0], [0, 0.5]]})
}

/// Every move from a grid of states over the square, as the sand world answers it.
fn through_sand() -> Vec<Value> {
    let moves = [[0.1, 0.0], [-0.1, 0.0], [0.0, 0.1], [0.0, -0.1]];
    (0..9)
        .map(|i| {
            let x = 0.1 + 0.1 * i as f64;
            let transitions: Vec<Value> = (0..9)
                .flat_map(|j| {
                    let s = [x, 0.1 + 0.1 * j as f64];
                    moves.iter().map(move |a| {
                        let k = if s[0] < 0.5 { 1.0 } else { 0.5 };
                        let s_next = [s[0] + k * a[0], s[1] + k * a[1]];
                        json!({"s": s, "a": a, "s_next": s_next})
                    })
                })
                .collect();
            json!({ "transitions": transitions })
        })
        .collect()
}

/// A fresh server with the sand experiment (`domain` and `slow`) fitted on every move over the
/// square.
async fn learnt_sand() -> (tempfile::TempDir, TestApp, i64) {
    let (dir, app) = fresh_app().await;
    let id = app
        .create_experiment(sand(json!([{"name": "slow", "cost": 4, "model": slow()}])))
        .await;
    for t in through_sand() {
        app.store_trajectory(id, &t).await;
    }
    app.refit(id).await;
    (dir, app, id)
}

async fn plan(app: &TestApp, id: i64, models: Option<&[&str]>) -> (u16, Value) {
    let mut body = json!({"start": [0.2, 0.5], "goal": [0.8, 0.5], "beta": 0});
    if let Some(models) = models {
        body["models"] = json!(models);
    }
    app.post_at(id, "plans", &body).await
}

/// A plan steps with whichever model is trusted where it is: across the sand neither model
/// alone finds one, together they do, each step relying on the cheapest model trusted there;
/// the plan names each step's model and the calls the search made to each.
#[tokio::test]
async fn a_plan_steps_with_the_cheapest_trusted_model_and_says_which() {
    let (_dir, app, id) = learnt_sand().await;

    for alone in ["domain", "slow"] {
        let (status, body) = plan(&app, id, Some(&[alone])).await;
        assert_eq!(status, 200, "{body}");
        assert_eq!(body["found"], false, "{alone} alone: {body}");
        let calls = body["model_calls"].as_array().unwrap();
        assert_eq!(calls.len(), 1, "{body}");
        assert_eq!(calls[0]["model"], alone, "{body}");
    }
    let (status, body) = plan(&app, id, None).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["found"], true, "{body}");
    let states = body["trajectory"]["states"].as_array().unwrap();
    let steps: Vec<&str> = body["step_models"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m.as_str().unwrap())
        .collect();
    assert_eq!(steps.len() + 1, states.len(), "{body}");
    for (s, m) in states.iter().zip(&steps) {
        let x = s[0].as_f64().unwrap();
        assert_eq!(*m, if x < 0.5 { "domain" } else { "slow" }, "{body}");
    }
    let calls = &body["model_calls"];
    assert_eq!(calls[0]["model"], "domain", "{body}");
    assert_eq!(calls[1]["model"], "slow", "{body}");
    assert_eq!(calls[1]["cost"], 4.0, "{body}");
    assert!(calls[1]["calls"].as_u64() > Some(0), "{body}");
    // In the given order, dear first: the same plan, the models still tried cheapest first.
    let (_, reordered) = plan(&app, id, Some(&["slow", "domain"])).await;
    assert_eq!(reordered["trajectory"], body["trajectory"], "{reordered}");
    assert_eq!(reordered["step_models"], body["step_models"], "{reordered}");

    // What the request may name.
    for (models, field) in [
        (json!(["sim"]), "models[0]"),
        (json!(["domain", "domain"]), "models[1]"),
        (json!([]), "models"),
    ] {
        let (status, body) = app
            .post_at(
                id,
                "plans",
                &json!({"start": [0.2, 0.5], "goal": [0.8, 0.5], "models": models}),
            )
            .await;
        assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
        assert_eq!(body["error"]["details"]["field"], field, "{body}");
    }
    let candidate = json!({"states": [[0.2, 0.5], [0.3, 0.5]], "actions": [[0.1, 0]]});
    let (status, body) = app
        .post_at(
            id,
            "plans",
            &json!({"start": [0.2, 0.5], "goal": [0.3, 0.5],
                    "candidates": [candidate], "models": ["domain"]}),
        )
        .await;
    assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
    assert_eq!(body["error"]["details"]["field"], "models", "{body}");
}

/// A single-model experiment's plan answers as before several models existed: no
/// `step_models`, no `model_calls`; naming `domain` is the same plan.
#[tokio::test]
async fn a_single_model_experiments_plan_is_unchanged() {
    let (_dir, app) = fresh_app().await;
    let id = app.create_experiment(sand(Value::Null)).await;
    for t in through_sand() {
        app.store_trajectory(id, &t).await;
    }
    app.refit(id).await;
    let body = json!({"start": [0.1, 0.5], "goal": [0.4, 0.5]});
    let (status, plain) = app.post_at(id, "plans", &body).await;
    assert_eq!(status, 200, "{plain}");
    assert_eq!(plain["found"], true, "{plain}");
    assert!(plain.get("step_models").is_none(), "{plain}");
    assert!(plain.get("model_calls").is_none(), "{plain}");
    let mut named = body.clone();
    named["models"] = json!(["domain"]);
    let (_, again) = app.post_at(id, "plans", &named).await;
    assert_eq!(again, plain);
}

/// Each model's precondition has its own map: the domain's trusts the left of the sand, `slow`
/// the right; `slow`'s training points carry its own labels.
#[tokio::test]
async fn each_model_has_its_own_precondition_map() {
    let (_dir, app, id) = learnt_sand().await;
    let query = "precondition/map?x=s.s0&y=s.s1&a=0.1,0&nx=11&ny=3";
    let trusted_left = |map: &Value| -> (Vec<bool>, f64) {
        let (mu, sigma) = (
            map["mu"].as_array().unwrap(),
            map["sigma"].as_array().unwrap(),
        );
        let beta = map["test_beta"].as_f64().unwrap();
        // The middle row, from x = 0 to 1 in steps of 0.1.
        let inside: Vec<bool> = (11..22)
            .map(|k| mu[k].as_f64().unwrap() + beta * sigma[k].as_f64().unwrap() < 0.02)
            .collect();
        let worst = map["training"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["deviation"].as_f64().unwrap())
            .fold(0.0, f64::max);
        (inside, worst)
    };
    let (status, domain) = app.get_at(id, query).await;
    assert_eq!(status, 200, "{domain}");
    assert!(domain.get("model").is_none(), "{domain}");
    let (status, slow_map) = app.get_at(id, &format!("{query}&model=slow")).await;
    assert_eq!(status, 200, "{slow_map}");
    assert_eq!(slow_map["model"], "slow", "{slow_map}");
    let (d_inside, d_worst) = trusted_left(&domain);
    let (s_inside, s_worst) = trusted_left(&slow_map);
    // Away from the border (x = 0.1…0.3 and 0.7…0.9).
    for k in [1, 2, 3] {
        assert!(
            d_inside[k] && !s_inside[k],
            "x = 0.{k}: {d_inside:?} {s_inside:?}"
        );
    }
    for k in [7, 8, 9] {
        assert!(
            !d_inside[k] && s_inside[k],
            "x = 0.{k}: {d_inside:?} {s_inside:?}"
        );
    }
    // Both models miss by 0.05 on their wrong half: each map's points carry its own labels.
    assert!((d_worst - 0.05).abs() < 1e-9 && (s_worst - 0.05).abs() < 1e-9);
    assert_eq!(
        slow_map["training"].as_array().unwrap().len(),
        domain["training"].as_array().unwrap().len()
    );
    let (status, body) = app.get_at(id, &format!("{query}&model=sim")).await;
    assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
    assert_eq!(body["error"]["details"]["field"], "model", "{body}");
}

/// A proposal that names several models steps, like a plan, with whichever is trusted where
/// it is — the one trajectory that crosses the sand takes both — says which model each step
/// relied on, and a continuation of it steps with the same models. Without `models` a
/// proposal steps with the domain's model alone, as in a single-model experiment.
#[tokio::test]
async fn a_proposal_that_names_its_models_steps_with_each_and_says_which() {
    let (_dir, app, id) = learnt_sand().await;
    let problem = json!({"start": [0.2, 0.5], "goal": [0.8, 0.5], "client_id": "arm",
                         "models": ["slow", "domain"]});
    let (status, body) = app.post_at(id, "proposals", &problem).await;
    assert_eq!(status, 201, "{body}");
    assert_eq!(body["models"], json!(["domain", "slow"]), "{body}");
    let states = body["trajectory"]["states"].as_array().unwrap();
    let steps = body["step_models"].as_array().unwrap();
    assert_eq!(steps.len() + 1, states.len(), "{body}");
    assert!(steps.contains(&json!("domain")), "{body}");
    assert!(steps.contains(&json!("slow")), "{body}");
    for (s, m) in states.iter().zip(steps) {
        let x = s[0].as_f64().unwrap();
        // Each model is trusted on its side of the sand, away from the border.
        if (x - 0.5).abs() > 0.15 {
            assert_eq!(*m, if x < 0.5 { "domain" } else { "slow" }, "{body}");
        }
    }
    // The robot takes the first move and re-plans from where it is: the same models.
    let pid = body["id"].as_i64().unwrap();
    let first = json!({"transitions": [{"s": [0.2, 0.5], "a": body["trajectory"]["actions"][0],
        "s_next": states[1]}]});
    let (status, next) = app
        .post_at(id, &format!("proposals/{pid}/continue"), &first)
        .await;
    assert_eq!(status, 201, "{next}");
    assert_eq!(next["proposal"]["models"], body["models"], "{next}");
    assert!(next["proposal"]["step_models"].is_array(), "{next}");

    // Unnamed, or the domain's model alone: answered as a single-model proposal is.
    for (client, models) in [("base", None), ("cart", Some(json!(["domain"])))] {
        let mut body = json!({"start": [0.1, 0.2], "goal": [0.4, 0.2], "client_id": client});
        if let Some(models) = models {
            body["models"] = models;
        }
        let (status, answer) = app.post_at(id, "proposals", &body).await;
        assert_eq!(status, 201, "{answer}");
        assert!(answer.get("models").is_none(), "{answer}");
        assert!(answer.get("step_models").is_none(), "{answer}");
    }

    // What a proposal may not name.
    let candidate = json!({"states": [[0.1, 0.3], [0.2, 0.3]], "actions": [[0.1, 0]]});
    for (body, field) in [
        (
            json!({"start": [0.1, 0.3], "goal": [0.2, 0.3], "models": ["sim"]}),
            "models[0]",
        ),
        (
            json!({"start": [0.1, 0.3], "goal": [0.2, 0.3], "models": ["slow"],
                   "strategy": "random"}),
            "models",
        ),
        (
            json!({"start": [0.1, 0.3], "goal": [0.2, 0.3], "models": ["slow"],
                   "candidates": [candidate]}),
            "models",
        ),
    ] {
        let (status, answer) = app.post_at(id, "proposals", &body).await;
        assert_eq!(
            (status, code(&answer)),
            (422, "validation_failed"),
            "{answer}"
        );
        assert_eq!(answer["error"]["details"]["field"], field, "{answer}");
    }
}

/// A further model that is the client's own labels each transition from the prediction the
/// client posts with it (`predictions.<name>`; one left out leaves that label missing), has a
/// precondition of its own, and is never stepped with: the service cannot call it.
#[tokio::test]
async fn a_client_model_labels_from_the_predictions_posted_with_each_transition() {
    let (_dir, app) = fresh_app().await;
    let id = app
        .create_experiment(sand(json!([
            {"name": "mine", "cost": 2, "model": {"kind": "client"}},
            {"name": "slow", "cost": 4, "model": slow()}])))
        .await;
    let (_, e) = app.get(&format!("/v1/experiments/{id}")).await;
    assert_eq!(e["models"][0]["model"], json!({"kind": "client"}), "{e}");
    // The client's model is `slow`'s (s + a/2), sent with every transition but the first
    // trajectory's (9 × 4 = 36 transitions).
    let mut omitted = 0;
    for (k, mut t) in through_sand().into_iter().enumerate() {
        for tr in t["transitions"].as_array_mut().unwrap() {
            if k == 0 {
                omitted += 1;
                continue;
            }
            let (s, a) = (&tr["s"], &tr["a"]);
            let pred: Vec<f64> = (0..2)
                .map(|i| s[i].as_f64().unwrap() + 0.5 * a[i].as_f64().unwrap())
                .collect();
            tr["predictions"] = json!({ "mine": pred });
        }
        app.store_trajectory(id, &t).await;
    }
    let (_, summary) = app.get_at(id, "labels").await;
    let mine = &summary["items"][1];
    assert_eq!(mine["model"], "mine", "{summary}");
    assert_eq!(mine["kind"], "client", "{summary}");
    assert_eq!(mine["n_missing"], omitted, "{summary}");
    assert_eq!(mine["n_labelled"], 9 * 36 - omitted, "{summary}");
    // Its labels are `slow`'s where it has them: 0.05 at worst, off the sand.
    assert!(close(&mine["max_deviation"], 0.05), "{summary}");
    assert_eq!(mine["max_deviation"], summary["items"][2]["max_deviation"]);

    app.refit(id).await;
    // Right on the sand, as `slow` is; the features read its prediction, which the client
    // sends.
    let points = json!([{"s": [0.2, 0.5], "a": [0.1, 0], "s_pred": [0.25, 0.5]},
                        {"s": [0.8, 0.5], "a": [0.1, 0], "s_pred": [0.85, 0.5]}]);
    let (status, mine) = app
        .post_at(
            id,
            "precondition",
            &json!({"points": points, "beta": 0, "model": "mine"}),
        )
        .await;
    assert_eq!(status, 200, "{mine}");
    assert_eq!(inside(&mine), [false, true]);
    assert_eq!(inside(&judged(&app, id, "slow").await), [false, true]);
    let (status, body) = app
        .get_at(
            id,
            "precondition/map?x=s.s0&y=s.s1&a=0.1,0&nx=3&ny=3&model=mine",
        )
        .await;
    assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
    assert_eq!(body["error"]["details"]["field"], "model", "{body}");
    // Never stepped with: not among a plan's models, and not to be named.
    let (status, plan) = app
        .post_at(
            id,
            "plans",
            &json!({"start": [0.2, 0.5], "goal": [0.8, 0.5], "beta": 0}),
        )
        .await;
    assert_eq!(status, 200, "{plan}");
    let stepped: Vec<&str> = plan["model_calls"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["model"].as_str().unwrap())
        .collect();
    assert_eq!(stepped, ["domain", "slow"], "{plan}");
    for path in ["plans", "proposals"] {
        let (status, body) = app
            .post_at(
                id,
                path,
                &json!({"start": [0.2, 0.5], "goal": [0.8, 0.5], "models": ["mine"]}),
            )
            .await;
        assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
        assert_eq!(body["error"]["details"]["field"], "models[0]", "{body}");
    }

    // What a posted prediction may not be: of a model the service calls, of no model, not a
    // state. Nothing is stored.
    let (_, before) = app.get(&format!("/v1/experiments/{id}")).await;
    let step = |predictions: Value| {
        json!({"transitions": [{"s": [0.2, 0.5], "a": [0.1, 0], "s_next": [0.3, 0.5],
                                "predictions": predictions}]})
    };
    for (predictions, field) in [
        (
            json!({"slow": [0.25, 0.5]}),
            "transitions[0].predictions.slow",
        ),
        (json!({"sim": [0.25, 0.5]}), "transitions[0].predictions"),
        (json!({"mine": [0.25]}), "transitions[0].predictions.mine"),
        (
            json!({"mine": [0.25, 0.5, 0.1]}),
            "transitions[0].predictions.mine",
        ),
    ] {
        let (status, body) = app.post_at(id, "trajectories", &step(predictions)).await;
        assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
        assert_eq!(body["error"]["details"]["field"], field, "{body}");
    }
    let (_, after) = app.get(&format!("/v1/experiments/{id}")).await;
    assert_eq!(after["n_transitions"], before["n_transitions"]);
}
