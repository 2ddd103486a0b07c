//! What the store keeps of a robot's answers beyond its data: refused proposal requests (runs,
//! timeline, counts), executions that depart from their proposal (`deviating`) and the
//! provenance of posted trajectories (`source`).

use crate::helpers::*;
use serde_json::{Value, json};

/// A kinematic experiment whose wall (x in 0.45–0.55, every y) no search can cross.
fn walled(learning: Value) -> Value {
    json!({
        "domain": {"kind": "kinematic", "obstacles": [{"low": [0.45, -1.0], "high": [0.55, 2.0]}]},
        "learning": learning
    })
}

async fn runs(app: &TestApp, id: i64) -> Vec<Value> {
    let (status, page) = app
        .get(&format!("/v1/experiments/{id}/runs?limit=100"))
        .await;
    assert_eq!(status, 200, "{page}");
    page["items"].as_array().unwrap().clone()
}

#[tokio::test]
async fn a_refused_proposal_is_a_run_counted_in_its_iteration() {
    let (_dir, app, id) =
        fresh_experiment(walled(json!({"max_extensions": 300, "batch_size": 5}))).await;
    let path = format!("/v1/experiments/{id}/proposals");
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["n_refused"], 0);
    let mut refusals = Vec::new();
    for (client, start) in [(json!("arm-1"), [0.1, 0.5]), (Value::Null, [0.2, 0.4])] {
        let mut ask = json!({"start": start, "goal": [0.9, 0.5]});
        if !client.is_null() {
            ask["client_id"] = client.clone();
        }
        let (status, err) = app.post(&path, &ask).await;
        assert_eq!((status, code(&err)), (422, "no_plan"), "{err}");
        refusals.push((client, start, err["error"]["details"]["extensions"].clone()));
    }

    let (_, e) = app.get_at(id, "").await;
    assert_eq!(
        (e["n_refused"].as_i64(), e["n_trajectories"].as_i64()),
        (Some(2), Some(0))
    );
    let items = runs(&app, id).await;
    assert_eq!(items.len(), 2, "{items:?}");
    let (_, page) = app.get(&format!("/v1/experiments/{id}/runs?limit=1")).await;
    assert_eq!(
        (page["total"].as_i64(), page["next"].as_i64()),
        (Some(2), Some(1))
    );
    // Iteration 0's β_j and, relaxed (the default preset), every β down to −k1 = −2.
    let beta_0 = 2.0 * 2.0 / (1.0 + (-0.5 * (0.0 - 10.0f64)).exp()) - 2.0;
    for (run, (client, _, extensions)) in items.iter().zip(refusals.iter().rev()) {
        assert_eq!(run["status"], "refused", "{run}");
        assert!(run["refusal_id"].as_i64().unwrap() >= 1, "{run}");
        assert!(run["proposal_id"].is_null() && run["trajectory_id"].is_null());
        assert_eq!(&run["client_id"], client);
        assert_eq!(
            (run["iteration"].as_i64(), run["length"].as_i64()),
            (Some(0), Some(0))
        );
        assert_eq!(
            &run["extensions"], extensions,
            "the extensions the answer reported"
        );
        assert!(run["extensions"].as_i64().unwrap() >= 300);
        let tried: Vec<f64> = serde_json::from_value(run["betas_tried"].clone()).unwrap();
        assert_eq!(tried.len(), 2, "{run}");
        assert!(
            (tried[0] - beta_0).abs() < 1e-12 && tried[1] == -2.0,
            "{tried:?}"
        );
        assert_eq!(run["beta"].as_f64(), Some(tried[0]));
        assert_eq!(run["model_version"], 0);
        assert!(run["max_deviation"].is_null() && run["source"].is_null());
        assert_eq!(run["deviating"], false);
    }
    assert_ne!(items[0]["refusal_id"], items[1]["refusal_id"]);

    // The timeline counts them in iteration 0, which has no trajectory yet.
    let (_, t) = app.get_at(id, "timeline").await;
    let it = &t["iterations"];
    assert_eq!(it.as_array().unwrap().len(), 1, "{t}");
    assert_eq!(
        (it[0]["iteration"].as_i64(), it[0]["n_refused"].as_i64()),
        (Some(0), Some(2))
    );
    assert_eq!(
        (
            it[0]["n_trajectories"].as_i64(),
            it[0]["n_transitions"].as_i64()
        ),
        (Some(0), Some(0))
    );
    for field in ["mean_deviation", "max_deviation", "share_within_d_max"] {
        assert!(it[0][field].is_null(), "{field}: {t}");
    }

    // Trajectories join the same iteration; five complete it and the next refusal is counted in
    // iteration 1.
    for k in 0..5 {
        let x = 0.1 + 0.01 * k as f64;
        app.store_trajectory(
            id,
            &json!({"transitions": [{"s": [x, 0.2], "a": [0.05, 0.0], "s_next": [x + 0.05, 0.2]}]}),
        )
        .await;
    }
    app.wait_for_model(id, 5).await;
    let (status, err) = app
        .post(
            &path,
            &json!({"start": [0.1, 0.5], "goal": [0.9, 0.5], "client_id": "arm-1"}),
        )
        .await;
    assert_eq!((status, code(&err)), (422, "no_plan"), "{err}");
    let (_, t) = app.get_at(id, "timeline").await;
    let it = t["iterations"].as_array().unwrap();
    assert_eq!(it.len(), 2, "{t}");
    assert_eq!(
        (
            it[0]["n_trajectories"].as_i64(),
            it[0]["n_refused"].as_i64()
        ),
        (Some(5), Some(2))
    );
    assert_eq!(it[0]["mean_deviation"], 0.0);
    assert_eq!(
        (
            it[1]["n_trajectories"].as_i64(),
            it[1]["n_refused"].as_i64()
        ),
        (Some(0), Some(1))
    );
    let items = runs(&app, id).await;
    assert_eq!(items[0]["status"], "refused");
    assert_eq!(
        (
            items[0]["iteration"].as_i64(),
            items[0]["model_version"].as_i64()
        ),
        (Some(1), Some(1))
    );
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["n_refused"], 3);
    assert_eq!(e["last_activity"], items[0]["created_at"]);
}

#[tokio::test]
async fn the_papers_preset_tries_one_beta_and_a_clients_candidates_are_refused_too() {
    let (_dir, app, id) =
        fresh_experiment(walled(json!({"max_extensions": 200, "preset": "paper"}))).await;
    let path = format!("/v1/experiments/{id}/proposals");
    let (status, err) = app
        .post(&path, &json!({"start": [0.1, 0.5], "goal": [0.9, 0.5]}))
        .await;
    assert_eq!((status, code(&err)), (422, "no_plan"), "{err}");
    // A candidate that does not reach the goal.
    let (status, err) = app
        .post(
            &path,
            &json!({"start": [0.1, 0.5], "goal": [0.9, 0.5], "client_id": "own-planner",
                    "candidates": [{"states": [[0.1, 0.5], [0.2, 0.5]], "actions": [[0.1, 0.0]]}]}),
        )
        .await;
    assert_eq!((status, code(&err)), (422, "no_plan"), "{err}");
    let items = runs(&app, id).await;
    assert_eq!(items.len(), 2);
    for run in &items {
        assert_eq!(run["status"], "refused");
        assert_eq!(run["betas_tried"].as_array().unwrap().len(), 1, "{run}");
    }
    assert_eq!(
        (
            items[0]["client_id"].as_str(),
            items[0]["extensions"].as_i64()
        ),
        (Some("own-planner"), Some(0))
    );
    assert!(items[1]["extensions"].as_i64().unwrap() >= 200);
}

/// The states a gridworld robot passes through executing `actions` from `start` if every move
/// succeeded (what the transitions below claim happened; their labels do not matter here).
fn walk(start: [f64; 2], actions: &[[f64; 2]]) -> Vec<Value> {
    let mut s = start;
    actions
        .iter()
        .map(|a| {
            let next = [
                (s[0] + a[0]).clamp(0.0, 11.0),
                (s[1] + a[1]).clamp(0.0, 11.0),
            ];
            let t = json!({"s": s, "a": a, "s_next": next});
            s = next;
            t
        })
        .collect()
}

#[tokio::test]
async fn an_execution_that_departs_from_its_proposal_is_flagged_and_a_prefix_is_not() {
    let (_dir, app, id) = fresh_experiment(json!({"learning": {"batch_size": 100}})).await;
    let path = format!("/v1/experiments/{id}");
    let start = [0.0, 0.0];
    let mut cases = Vec::new();
    for client in ["exact", "prefix", "other", "longer", "elsewhere"] {
        let (status, p) = app
            .post(
                &format!("{path}/proposals"),
                &json!({"start": start, "goal": [3, 0], "client_id": client}),
            )
            .await;
        assert_eq!(status, 201, "{p}");
        let actions: Vec<[f64; 2]> =
            serde_json::from_value(p["trajectory"]["actions"].clone()).unwrap();
        assert!(actions.len() >= 2, "{p}");
        let (transitions, partial) = match client {
            "exact" => (walk(start, &actions), false),
            "prefix" => (walk(start, &actions[..1]), true),
            "other" => {
                let mut a = actions.clone();
                a[1] = if a[1] == [0.0, 1.0] {
                    [1.0, 0.0]
                } else {
                    [0.0, 1.0]
                };
                (walk(start, &a), false)
            }
            "longer" => {
                let mut a = actions.clone();
                a.push([0.0, 1.0]);
                (walk(start, &a), false)
            }
            _ => (walk([0.0, 1.0], &actions), false),
        };
        let (status, created) = app
            .post(
                &format!("{path}/trajectories"),
                &json!({"proposal_id": p["id"], "partial": partial, "transitions": transitions}),
            )
            .await;
        assert_eq!(status, 201, "{created}");
        cases.push((client, p["id"].clone(), created));
    }
    let items = runs(&app, id).await;
    for (client, pid, created) in &cases {
        let deviating = !matches!(*client, "exact" | "prefix");
        assert_eq!(created["deviating"], deviating, "{client}: {created}");
        let (_, t) = app
            .get(&format!("{path}/trajectories/{}", created["id"]))
            .await;
        assert_eq!(t["deviating"], deviating, "{client}: {t}");
        let (_, p) = app.get(&format!("{path}/proposals/{pid}")).await;
        assert_eq!(
            (p["deviating"].as_bool(), p["status"].as_str()),
            (Some(deviating), Some("executed")),
            "{client}"
        );
        let run = items.iter().find(|r| r["proposal_id"] == *pid).unwrap();
        assert_eq!(run["deviating"], deviating, "{client}: {run}");
        let status = if *client == "prefix" {
            "partial"
        } else {
            "executed"
        };
        assert_eq!(
            run["status"], status,
            "{client}: the status stays the lease's"
        );
    }
    // A proposal not executed yet does not deviate; an unsolicited trajectory never does.
    let (_, open) = app
        .post(
            &format!("{path}/proposals"),
            &json!({"start": [5, 5], "goal": [5, 8], "client_id": "later"}),
        )
        .await;
    assert_eq!(open["deviating"], false);
    let (_, unsolicited) = app
        .post(
            &format!("{path}/trajectories"),
            &free_row_trajectory(0, 0, 2),
        )
        .await;
    assert_eq!(unsolicited["deviating"], false);
}

#[tokio::test]
async fn continuous_actions_equal_within_the_tolerance_do_not_deviate() {
    let (_dir, app, id) =
        fresh_experiment(json!({"domain": {"kind": "kinematic"}, "learning": {"batch_size": 100}}))
            .await;
    let path = format!("/v1/experiments/{id}");
    for (client, scale, deviating) in [
        ("float32", 1.0 - 1e-8, false),
        ("drifted", 1.0 - 1e-3, true),
    ] {
        let (status, p) = app
            .post(
                &format!("{path}/proposals"),
                &json!({"start": [0.1, 0.1], "goal": [0.5, 0.5], "client_id": client}),
            )
            .await;
        assert_eq!(status, 201, "{p}");
        let states: Vec<Vec<f64>> =
            serde_json::from_value(p["trajectory"]["states"].clone()).unwrap();
        let actions: Vec<Vec<f64>> =
            serde_json::from_value(p["trajectory"]["actions"].clone()).unwrap();
        let transitions: Vec<Value> = actions
            .iter()
            .enumerate()
            .map(|(k, a)| {
                let a: Vec<f64> = a.iter().map(|x| x * scale).collect();
                json!({"s": states[k], "a": a, "s_next": states[k + 1]})
            })
            .collect();
        let (status, created) = app
            .post(
                &format!("{path}/trajectories"),
                &json!({"proposal_id": p["id"], "transitions": transitions}),
            )
            .await;
        assert_eq!(status, 201, "{created}");
        assert_eq!(created["deviating"], deviating, "{client}");
    }
}

#[tokio::test]
async fn a_trajectorys_source_is_stored_shown_and_checked() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    let path = format!("/v1/experiments/{id}/trajectories");
    let source =
        json!({"dataset": "logs/grid.csv", "episode": 3, "first_step": 0, "label": "teleop"});
    let mut body = free_row_trajectory(0, 0, 3);
    body["source"] = source.clone();
    let send = |key: &'static str, body: Value| {
        let app = &app;
        let path = path.clone();
        async move {
            let r = app
                .client
                .post(app.url(&path))
                .header("idempotency-key", key)
                .json(&body)
                .send()
                .await
                .unwrap();
            let replayed = r.headers().contains_key("idempotent-replayed");
            (
                r.status().as_u16(),
                replayed,
                r.json::<Value>().await.unwrap(),
            )
        }
    };
    let (status, replayed, created) = send("import-ep-3", body.clone()).await;
    assert_eq!((status, replayed), (201, false), "{created}");
    assert_eq!(created["source"], source);
    let (_, t) = app.get(&format!("{path}/{}", created["id"])).await;
    assert_eq!(t["source"], source);
    let items = runs(&app, id).await;
    assert_eq!(
        (items[0]["status"].as_str(), &items[0]["source"]),
        (Some("unsolicited"), &source)
    );
    // A re-run posts nothing new; another source under the same key is another request.
    let (status, replayed, again) = send("import-ep-3", body.clone()).await;
    assert_eq!((status, replayed), (201, true));
    assert_eq!(
        (again["id"].clone(), again["source"].clone()),
        (created["id"].clone(), source.clone())
    );
    let mut relabelled = body.clone();
    relabelled["source"]["label"] = json!("other");
    let (status, _, err) = send("import-ep-3", relabelled).await;
    assert_eq!((status, code(&err)), (409, "conflict"), "{err}");
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["n_trajectories"], 1);
    // Only the dataset is required; without a source the answer says null.
    let mut bare = free_row_trajectory(0, 1, 1);
    bare["source"] = json!({"dataset": "gymnasium:GridWorld-v0"});
    let (status, created) = app.post(&path, &bare).await;
    assert_eq!(
        (status, created["source"].clone()),
        (201, json!({"dataset": "gymnasium:GridWorld-v0"}))
    );
    let (_, plain) = app.post(&path, &free_row_trajectory(0, 2, 1)).await;
    assert!(plain["source"].is_null(), "{plain}");

    for (bad, field) in [
        (json!({"dataset": ""}), "source.dataset"),
        (json!({"dataset": "x".repeat(1001)}), "source.dataset"),
        (json!({"dataset": "d", "episode": -1}), "source.episode"),
        (
            json!({"dataset": "d", "first_step": -2}),
            "source.first_step",
        ),
        (
            json!({"dataset": "d", "label": "l".repeat(1001)}),
            "source.label",
        ),
    ] {
        let mut body = free_row_trajectory(0, 3, 1);
        body["source"] = bad.clone();
        let (status, err) = app.post(&path, &body).await;
        assert_eq!(
            (status, code(&err)),
            (422, "validation_failed"),
            "{bad}: {err}"
        );
        assert_eq!(err["error"]["details"]["field"], field, "{err}");
    }
    let mut unknown = free_row_trajectory(0, 3, 1);
    unknown["source"] = json!({"dataset": "d", "episodes": 2});
    let (status, err) = app.post(&path, &unknown).await;
    assert_eq!((status, code(&err)), (422, "validation_failed"), "{err}");
    assert!(message(&err).contains("episodes"), "{err}");
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(
        e["n_trajectories"], 3,
        "nothing stored for the refused bodies"
    );
}
