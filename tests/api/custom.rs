//! Custom domains: any robot's spaces, distance and goal, with its own model served over HTTP,
//! given as a linear map, or kept on the client (candidates and client predictions).

use crate::helpers::*;
use crate::model_server::{self, ModelServer};
use serde_json::{Value, json};
use std::sync::atomic::Ordering;

/// A robot in the unit square moving by at most 0.1 per axis; distance weights `[1, 4]`.
fn plane(model: Value) -> Value {
    json!({
        "kind": "custom",
        "state": {"names": ["x", "y"], "low": [0, 0], "high": [1, 1]},
        "action": {"names": ["dx", "dy"], "low": [-0.1, -0.1], "high": [0.1, 0.1]},
        "distance": {"weights": [1, 4]},
        "goal": {"radius": 0.05},
        "steer_samples": 8,
        "model": model,
    })
}

fn remote(server: &ModelServer, endpoint: &str) -> Value {
    json!({"kind": "remote", "url": server.url(endpoint), "timeout_ms": 500})
}

async fn app_with_models(server: &ModelServer) -> (tempfile::TempDir, TestApp) {
    let (dir, db) = temp_db();
    let app = spawn_app_allowing_models(&db, &[server.prefix()]).await;
    (dir, app)
}

/// Creates an experiment on `domain` with `change`'s parts put in place of its own, asserts
/// the `422` names `field`, and returns the answer.
async fn refused(app: &TestApp, domain: &Value, change: &Value, field: &str) -> Value {
    let mut domain = domain.clone();
    for (k, v) in change.as_object().unwrap() {
        domain[k] = v.clone();
    }
    let (status, body) = app
        .post("/v1/experiments", &json!({"domain": domain}))
        .await;
    assert_eq!(
        (status, code(&body)),
        (422, "validation_failed"),
        "{field}: {body}"
    );
    assert_eq!(body["error"]["details"]["field"], field, "{body}");
    body
}

fn weighted(p: &[f64], o: &[f64]) -> f64 {
    ((p[0] - o[0]).powi(2) + 4.0 * (p[1] - o[1]).powi(2)).sqrt()
}

#[tokio::test]
async fn a_remote_model_labels_every_transition_in_one_call_with_the_declared_distance() {
    let server = model_server::start().await;
    let (_dir, app) = app_with_models(&server).await;
    let (status, exp) = app
        .post(
            "/v1/experiments",
            &json!({"domain": plane(remote(&server, "predict")), "d_max": 0.02}),
        )
        .await;
    assert_eq!(status, 201, "{exp}");
    // The resolved settings say what is used.
    assert_eq!(
        exp["domain"]["features"],
        json!({"state": [0, 1], "action": [0, 1], "action_length": true,
               "prediction": [0, 1], "move_length": true})
    );
    assert_eq!(exp["domain"]["goal"]["components"], json!([0, 1]));
    assert_eq!(
        exp["feature_names"],
        json!([
            "x",
            "y",
            "dx",
            "dy",
            "action_length",
            "predicted x",
            "predicted y",
            "move_length"
        ])
    );
    let id = exp["id"].as_i64().unwrap();
    let transitions = [
        ([0.2, 0.3], [0.05, 0.0], [0.26, 0.31]),
        ([0.26, 0.31], [0.0, -0.1], [0.26, 0.21]),
        ([0.9, 0.9], [0.1, 0.1], [0.95, 0.97]),
    ];
    let body = json!({"transitions": transitions
        .iter()
        .map(|(s, a, n)| json!({"s": s, "a": a, "s_next": n}))
        .collect::<Vec<_>>()});
    let created = app.store_trajectory(id, &body).await;
    assert_eq!(server.counts.calls.load(Ordering::Relaxed), 1);
    assert_eq!(server.counts.points.load(Ordering::Relaxed), 3);
    let stored = app.all_transitions(id).await;
    for (k, (s, a, n)) in transitions.iter().enumerate() {
        let pred = [s[0] + a[0], s[1] + a[1]];
        let d = created["deviations"][k].as_f64().unwrap();
        assert!(
            (d - weighted(&pred, n)).abs() < 1e-12,
            "transition {k}: {d}"
        );
        let s_pred: Vec<f64> = serde_json::from_value(stored[k]["s_pred"].clone()).unwrap();
        assert!((s_pred[0] - pred[0]).abs() < 1e-12 && (s_pred[1] - pred[1]).abs() < 1e-12);
    }
}

#[tokio::test]
async fn a_failing_remote_model_is_a_clear_error_naming_it_and_nothing_is_stored() {
    let server = model_server::start().await;
    let (_dir, app) = app_with_models(&server).await;
    for (endpoint, status, code_wanted) in [
        ("slow", 504, "model_timeout"),
        ("error", 502, "model_unavailable"),
        ("short", 502, "model_unavailable"),
        ("nan", 502, "model_unavailable"),
    ] {
        let id = app
            .create_experiment(json!({"domain": plane(remote(&server, endpoint))}))
            .await;
        let (got, body) = app
            .post_at(
                id,
                "trajectories",
                &json!({"transitions": [{"s": [0.2, 0.2], "a": [0.1, 0], "s_next": [0.3, 0.2]}]}),
            )
            .await;
        assert_eq!(
            (got, code(&body)),
            (status, code_wanted),
            "{endpoint}: {body}"
        );
        assert_eq!(body["error"]["details"]["model"], server.url(endpoint));
        let (got, body) = app
            .propose(
                id,
                &json!({"start": [0.1, 0.1], "goal": [0.5, 0.5], "client_id": "robot"}),
            )
            .await;
        assert_eq!(
            (got, code(&body)),
            (status, code_wanted),
            "{endpoint}: {body}"
        );
        let (_, exp) = app.get_at(id, "").await;
        assert_eq!(
            (
                exp["n_trajectories"].as_i64(),
                exp["n_transitions"].as_i64()
            ),
            (Some(0), Some(0)),
            "{endpoint}"
        );
        let (got, _) = app.get(&format!("/v1/experiments/{id}/proposals/1")).await;
        assert_eq!(got, 404, "{endpoint}: no proposal may be stored");
    }
}

#[tokio::test]
async fn model_urls_are_allowed_only_under_the_operators_prefixes() {
    let server = model_server::start().await;
    let (_dir, app) = app_with_models(&server).await;
    let elsewhere = json!({"kind": "remote", "url": "http://10.0.0.9:9000/predict"});
    let (status, body) = app
        .post("/v1/experiments", &json!({"domain": plane(elsewhere)}))
        .await;
    assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
    assert_eq!(body["error"]["details"]["field"], "domain.model.url");

    let (_dir2, db2) = temp_db();
    let closed = spawn_app(&db2).await;
    let (status, body) = closed
        .post(
            "/v1/experiments",
            &json!({"domain": plane(remote(&server, "predict"))}),
        )
        .await;
    assert_eq!(status, 422, "{body}");
    assert_eq!(body["error"]["details"]["field"], "domain.model.url");
    assert!(reason(&body).contains("--allow-model-url"), "{body}");
}

#[tokio::test]
async fn a_bad_custom_domain_is_refused_with_the_field_named() {
    let (_dir, app) = fresh_app().await;
    let linear = json!({"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]});
    let cases: Vec<(Value, &str)> = vec![
        (
            json!({"state": {"low": [0, 0], "high": [1]}}),
            "domain.state.high",
        ),
        (
            json!({"state": {"low": [0, 1], "high": [1, 1]}}),
            "domain.state.high[1]",
        ),
        (
            json!({"distance": {"weights": [0, 0]}}),
            "domain.distance.weights",
        ),
        (
            json!({"distance": {"weights": [1, -1]}}),
            "domain.distance.weights[1]",
        ),
        (
            json!({"goal": {"components": [2], "radius": 0.1}}),
            "domain.goal.components[0]",
        ),
        (
            json!({"features": {"state": [], "action": [5]}}),
            "domain.features.action[0]",
        ),
        (
            json!({"features": {"state": [0], "action": [], "action_length": true}}),
            "domain.features.action_length",
        ),
        (
            json!({"model": {"kind": "linear", "A": [[1, 0]], "B": [[1, 0], [0, 1]]}}),
            "domain.model.A",
        ),
        (
            json!({"obstacles": [{"low": [0], "high": [1]}]}),
            "domain.obstacles[0]",
        ),
    ];
    for (change, field) in cases {
        refused(&app, &plane(linear.clone()), &change, field).await;
    }
    // Errors of type and shape inside the tagged `domain` name their field too (serde buffers
    // a tagged enum, losing the path; the service reads the part again to find it).
    for (change, field, said) in [
        (
            json!({"goal": {"radius": "x"}}),
            "domain.goal.radius",
            "must be a number, or an array",
        ),
        (
            json!({"goal": {"radus": 1}}),
            "domain.goal.radus",
            "unknown field `radus`",
        ),
        (
            json!({"obstacles": [{"low": [0, 0], "high": [1, "a"]}]}),
            "domain.obstacles[0].high[1]",
            "expected f64",
        ),
        (
            json!({"model": {"kind": "remote"}}),
            "domain.model",
            "`url`",
        ),
    ] {
        let body = refused(&app, &plane(linear.clone()), &change, field).await;
        assert!(reason(&body).contains(said), "{body}");
    }
    let (_, list) = app.get("/v1/experiments").await;
    assert_eq!(list["items"].as_array().unwrap().len(), 0);
}

#[tokio::test]
async fn a_linear_model_with_identities_labels_like_the_kinematic_shorthand() {
    let (_dir, app, linear) = fresh_experiment(json!({"domain": plane(json!({
            "kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]}))}))
    .await;
    let kinematic = app
        .create_experiment(json!({"domain": {"kind": "kinematic"}}))
        .await;
    let body = json!({"transitions": [
        {"s": [0.95, 0.5], "a": [0.1, -0.05], "s_next": [1.0, 0.4]},
        {"s": [1.0, 0.4], "a": [-0.1, 0.0], "s_next": [0.85, 0.4]}]});
    let (_, a) = app.post_at(linear, "trajectories", &body).await;
    let (_, b) = app.post_at(kinematic, "trajectories", &body).await;
    let (a, b) = (&a["deviations"], &b["deviations"]);
    // Both clip the prediction to the bounds; the custom distance weighs y by 4.
    assert_eq!(a[1], b[1]);
    let expected = weighted(&[1.0, 0.45], &[1.0, 0.4]);
    assert!((a[0].as_f64().unwrap() - expected).abs() < 1e-12, "{a}");
}

#[tokio::test]
async fn plans_respect_the_robots_own_validity_check() {
    let server = model_server::start().await;
    let (_dir, app) = app_with_models(&server).await;
    let id = app
        .create_experiment(json!({
            "domain": plane(remote(&server, "valid")),
            "learning": {"n_candidates": 4, "max_extensions": 3000}}))
        .await;
    let p = app
        .assert_proposes(id, &json!({"start": [0.2, 0.5], "goal": [0.8, 0.5]}))
        .await;
    let states = p["trajectory"]["states"].as_array().unwrap();
    assert!(states.len() > 2);
    for s in &states[1..] {
        let x = s[0].as_f64().unwrap();
        assert!(
            !(0.48..=0.52).contains(&x),
            "a state the model called invalid: {s}"
        );
    }
    // Rounds of edges go to the model together: far fewer calls than extensions.
    let calls = server.counts.calls.load(Ordering::Relaxed);
    assert!(
        calls > 0 && calls < p["extensions"].as_u64().unwrap() as usize,
        "{calls} calls"
    );
}

#[tokio::test]
async fn a_client_model_posts_its_predictions_and_its_candidates() {
    let (_dir, app, id) = fresh_experiment(json!({
            "domain": plane(json!({"kind": "client"})),
            "d_max": 0.05,
            "learning": {"c": 1.5, "gamma": 0.8}}))
    .await;
    let path = format!("/v1/experiments/{id}/trajectories");
    let (status, body) = app
        .post(
            &path,
            &json!({"transitions": [{"s": [0.2, 0.2], "a": [0.1, 0], "s_next": [0.3, 0.2]}]}),
        )
        .await;
    assert_eq!(status, 422, "{body}");
    assert_eq!(body["error"]["details"]["field"], "transitions[0].s_pred");
    let (status, body) = app
        .post(
            &path,
            &json!({"transitions": [
                {"s": [0.2, 0.2], "a": [0.1, 0], "s_next": [0.3, 0.2], "s_pred": [0.31, 0.22]}]}),
        )
        .await;
    assert_eq!(status, 201, "{body}");
    let expected = weighted(&[0.31, 0.22], &[0.3, 0.2]);
    assert!((body["deviations"][0].as_f64().unwrap() - expected).abs() < 1e-12);

    // The service cannot plan with the client's model.
    let problem = json!({"start": [0.1, 0.1], "goal": [0.3, 0.1]});
    for route in ["proposals", "plans"] {
        let (status, body) = app
            .post(&format!("/v1/experiments/{id}/{route}"), &problem)
            .await;
        assert_eq!(status, 422, "{body}");
        assert_eq!(body["error"]["details"]["field"], "candidates");
    }

    // Candidates: the service scores every step and chooses the eligible one with least α.
    let straight = json!({"states": [[0.1, 0.1], [0.2, 0.1], [0.3, 0.1]],
                          "actions": [[0.1, 0], [0.1, 0]]});
    let detour = json!({"states": [[0.1, 0.1], [0.1, 0.2], [0.2, 0.2], [0.3, 0.15], [0.3, 0.1]],
                        "actions": [[0, 0.1], [0.1, 0], [0.1, -0.05], [0, -0.05]]});
    let short = json!({"states": [[0.1, 0.1], [0.15, 0.1]], "actions": [[0.05, 0]]});
    let request = json!({"start": [0.1, 0.1], "goal": [0.3, 0.1], "client_id": "arm",
                         "candidates": [straight, detour, short]});
    let p = app.assert_proposes(id, &request).await;
    let candidates = p["candidates"].as_array().unwrap();
    assert_eq!(candidates.len(), 3);
    let (c, gamma, beta, d_max) = (1.5, 0.8, p["beta"].as_f64().unwrap(), 0.05);
    let mut eligible = Vec::new();
    for (k, cand) in candidates.iter().enumerate() {
        let mu: Vec<f64> = serde_json::from_value(cand["mu"].clone()).unwrap();
        let sigma: Vec<f64> = serde_json::from_value(cand["sigma"].clone()).unwrap();
        // α = h_max of γ^t (μ_t − c σ_t), recomputed from what was returned.
        let alpha = mu
            .iter()
            .zip(&sigma)
            .enumerate()
            .map(|(t, (m, s))| gamma_pow(gamma, t) * (m - c * s))
            .fold(f64::NEG_INFINITY, f64::max);
        assert!(
            (alpha - cand["alpha"].as_f64().unwrap()).abs() < 1e-9,
            "{cand}"
        );
        let inside = mu.iter().zip(&sigma).all(|(m, s)| m + beta * s < d_max);
        assert_eq!(cand["inside"], inside, "{cand}");
        if inside && cand["reaches_goal"] == true {
            eligible.push((k, alpha));
        }
    }
    assert_eq!(candidates[2]["reaches_goal"], false);
    let best = eligible
        .iter()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("an eligible candidate")
        .0;
    assert_eq!(p["chosen_index"].as_u64(), Some(best as u64));
    assert_eq!(
        p["trajectory"]["states"],
        request["candidates"][best]["states"]
    );

    // A bad candidate is refused with its field named.
    let bad = json!({"start": [0.1, 0.1], "goal": [0.3, 0.1],
                     "candidates": [{"states": [[0.2, 0.1], [0.3, 0.1]], "actions": [[0.1, 0]]}]});
    let (status, body) = app.post_at(id, "plans", &bad).await;
    assert_eq!(status, 422, "{body}");
    assert_eq!(body["error"]["details"]["field"], "candidates[0].states[0]");
}

fn gamma_pow(gamma: f64, t: usize) -> f64 {
    gamma.powi(t as i32)
}

/// The true world of the learning test: `s' = s + a`, except on a sticky patch
/// (`x ∈ [0.35, 0.65]`, `y < 0.6`) where the robot only makes a fifth of the commanded move.
fn true_step(s: &[f64], a: &[f64]) -> Vec<f64> {
    let sticky = (0.35..=0.65).contains(&s[0]) && s[1] < 0.6;
    let k = if sticky { 0.2 } else { 1.0 };
    s.iter()
        .zip(a)
        .map(|(x, d)| (x + k * d).clamp(0.0, 1.0))
        .collect()
}

fn execute(states: &Value, actions: &Value) -> (Vec<Value>, Vec<f64>) {
    let mut s: Vec<f64> = serde_json::from_value(states[0].clone()).unwrap();
    let mut out = Vec::new();
    for a in actions.as_array().unwrap() {
        let a: Vec<f64> = serde_json::from_value(a.clone()).unwrap();
        let next = true_step(&s, &a);
        out.push(json!({"s": s, "a": a, "s_next": next}));
        s = next;
    }
    (out, s)
}

/// What the test plans of one seeded learning run did in the true world.
#[derive(Debug, Default)]
struct TestPlans {
    found: usize,
    reached_goal: usize,
    steps: usize,
    steps_beyond_d_max: usize,
}

/// Learns with 40 proposals across the square (8 batches of 5), then plans across the sticky
/// patch's rows and executes the plans in the true world.
async fn learn_then_plan(
    app: &TestApp,
    server: &model_server::ModelServer,
    seed: u64,
) -> TestPlans {
    let id = app
        .create_experiment(json!({
            "domain": plane(remote(server, "predict")),
            "d_max": 0.05,
            "seed": seed,
            "mde": {"noise": "homoscedastic", "restarts": 0},
            "learning": {"batch_size": 5, "iterations": 8, "n_candidates": 5,
                         "max_extensions": 1500}}))
        .await;
    // Problems across the square, some of whose straight lines cross the sticky patch.
    let problems: Vec<([f64; 2], [f64; 2])> = (0..40)
        .map(|k| {
            let y0 = 0.1 + 0.8 * ((k * 7) % 10) as f64 / 10.0;
            let y1 = 0.1 + 0.8 * ((k * 3) % 10) as f64 / 10.0;
            if k % 2 == 0 {
                ([0.1, y0], [0.9, y1])
            } else {
                ([0.9, y0], [0.1, y1])
            }
        })
        .collect();
    let mut executed = 0;
    for (start, goal) in &problems {
        let (status, p) = app
            .propose(
                id,
                &json!({"start": start, "goal": goal, "client_id": "robot"}),
            )
            .await;
        if status == 422 && code(&p) == "no_plan" {
            continue;
        }
        assert_eq!(status, 201, "{p}");
        let (transitions, _) = execute(&p["trajectory"]["states"], &p["trajectory"]["actions"]);
        app.store_trajectory(
            id,
            &json!({"proposal_id": p["id"], "transitions": transitions}),
        )
        .await;
        // The paper's loop: the next proposal waits for the fit on the finished batch, so the
        // run does not depend on how fast the background fit is.
        executed += 1;
        if executed % 5 == 0 {
            app.wait_for_model(id, executed).await;
        }
    }
    app.refit(id).await;
    // Test time: across the patch's rows, executed in the true world.
    let mut out = TestPlans::default();
    for y in [0.15, 0.3, 0.45] {
        let (status, plan) = app
            .post_at(id, "plans", &json!({"start": [0.1, y], "goal": [0.9, y]}))
            .await;
        assert_eq!(status, 200, "{plan}");
        if plan["found"] != true {
            continue;
        }
        out.found += 1;
        let t = &plan["trajectory"];
        let (executed, end) = execute(&t["states"], &t["actions"]);
        for step in &executed {
            let s: Vec<f64> = serde_json::from_value(step["s"].clone()).unwrap();
            let next: Vec<f64> = serde_json::from_value(step["s_next"].clone()).unwrap();
            let a: Vec<f64> = serde_json::from_value(step["a"].clone()).unwrap();
            let pred = [s[0] + a[0], s[1] + a[1]];
            out.steps += 1;
            out.steps_beyond_d_max += usize::from(weighted(&pred, &next) >= 0.05);
        }
        out.reached_goal +=
            usize::from(((end[0] - 0.9).powi(2) + (end[1] - y).powi(2)).sqrt() <= 0.05);
    }
    out
}

#[tokio::test]
async fn learning_with_a_remote_model_ends_with_plans_that_avoid_where_it_is_wrong() {
    // Four seeds, not one: with this small budget some seeds still trust a corner of the patch
    // (measured at seeds 1–8: the strict "no planned step beyond 0.02" held in 3–4 of 8 with
    // label caps 2, raw and auto alike). A planner that ignores the patch puts about a third
    // of its steps across these rows inside it.
    let server = model_server::start().await;
    let (_dir, app) = app_with_models(&server).await;
    let mut runs = Vec::new();
    for seed in 0..4 {
        runs.push(learn_then_plan(&app, &server, seed).await);
    }
    let sum = |f: fn(&TestPlans) -> usize| runs.iter().map(f).sum::<usize>();
    let (found, reached, steps, beyond) = (
        sum(|r| r.found),
        sum(|r| r.reached_goal),
        sum(|r| r.steps),
        sum(|r| r.steps_beyond_d_max),
    );
    assert!(
        runs.iter().filter(|r| r.found > 0).count() >= 3,
        "test plans found in fewer than 3 of 4 seeds: {runs:?}"
    );
    assert!(
        beyond * 10 <= steps,
        "more than a tenth of the planned steps leave d_max: {runs:?}"
    );
    assert!(
        reached * 4 >= found * 3,
        "fewer than three quarters of the found plans reach their goal: {runs:?}"
    );
}

/// A heading `θ ∈ [−π, π]` declared periodic, moved by a linear model (`θ' = θ + ω`).
fn heading(model: Value) -> Value {
    let pi = std::f64::consts::PI;
    json!({
        "kind": "custom",
        "state": {"names": ["x", "theta"], "low": [0, -pi], "high": [1, pi], "periodic": [1]},
        "action": {"names": ["v", "omega"], "low": [-0.1, -0.3], "high": [0.1, 0.3]},
        "goal": {"components": [1], "radius": 0.05},
        "model": model,
    })
}

#[tokio::test]
async fn a_periodic_heading_is_judged_and_planned_the_short_way_round() {
    let identity = json!({"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]});
    let (_dir, app, id) = fresh_experiment(json!({"domain": heading(identity)})).await;
    let (_, exp) = app.get_at(id, "").await;
    assert_eq!(exp["domain"]["state"]["periodic"], json!([1]), "{exp}");
    // Features: x, cos θ, sin θ, v, ω, the action's length, the prediction (x̂, cos θ̂, sin θ̂)
    // and the predicted move's length.
    let (_, model) = app.get_at(id, "model").await;
    let names: Vec<&str> = model["feature_names"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        [
            "x",
            "cos theta",
            "sin theta",
            "v",
            "omega",
            "action_length",
            "predicted x",
            "predicted cos theta",
            "predicted sin theta",
            "move_length"
        ],
        "{model}"
    );
    // Turning left past π: the model says 3.3, wrapped to −2.983; the robot is at −2.98.
    let (status, body) = app
        .post_at(
            id,
            "trajectories",
            &json!({"transitions": [{"s": [0.5, 3.0], "a": [0.0, 0.3], "s_next": [0.5, -2.98]}]}),
        )
        .await;
    assert_eq!(status, 201, "{body}");
    let d = body["deviations"][0].as_f64().unwrap();
    let expected = (3.3 - 2.0 * std::f64::consts::PI) - (-2.98);
    assert!(
        (d - expected.abs()).abs() < 1e-9,
        "deviation {d}, expected {expected}"
    );
    // A plan from θ = 3.0 to θ = −3.0 turns through π (0.28 rad), not back round (6 rad,
    // at least 21 steps of 0.3).
    let (status, plan) = app
        .post_at(
            id,
            "plans",
            &json!({"start": [0.5, 3.0], "goal": [-3.0], "beta": -1000.0}),
        )
        .await;
    assert_eq!(status, 200, "{plan}");
    assert_eq!(plan["found"], true, "{plan}");
    let states = plan["trajectory"]["states"].as_array().unwrap();
    assert!(states.len() <= 6, "{} states: {plan}", states.len());
    for s in states {
        let theta = s[1].as_f64().unwrap();
        assert!(theta.abs() <= std::f64::consts::PI, "{s}");
    }
    let last = states.last().unwrap()[1].as_f64().unwrap();
    assert!((last + 3.0).abs() <= 0.05, "ends at θ = {last}");
}

#[tokio::test]
async fn periodic_components_and_goal_radii_are_checked_by_field() {
    let (_dir, app) = fresh_app().await;
    let identity = json!({"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]});
    for (change, field) in [
        (
            json!({"action": {"low": [-1, -1], "high": [1, 1], "periodic": [0]}}),
            "domain.action.periodic",
        ),
        (
            json!({"state": {"low": [0, 0], "high": [1, 1], "periodic": [1, 1]}}),
            "domain.state.periodic[1]",
        ),
        (
            json!({"state": {"low": [0, 0], "high": [1, 1], "periodic": [2]}}),
            "domain.state.periodic[0]",
        ),
        (
            json!({"state": {"low": [0, 0], "high": [1, 1], "periodic": vec![0; 100_000]}}),
            "domain.state.periodic",
        ),
        (
            json!({"goal": {"components": [1], "radius": [0.1, 0.2]}}),
            "domain.goal.radius",
        ),
        (
            json!({"goal": {"components": [0, 1], "radius": [0.1, 0]}}),
            "domain.goal.radius[1]",
        ),
    ] {
        refused(&app, &heading(identity.clone()), &change, field).await;
    }
}

#[tokio::test]
async fn a_goal_can_have_a_radius_per_component() {
    let identity = json!({"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]});
    let mut domain = heading(identity);
    // Metres and radians: within 5 cm in x and 0.3 rad in heading.
    domain["goal"] = json!({"components": [0, 1], "radius": [0.05, 0.3]});
    let (_dir, app, id) = fresh_experiment(json!({"domain": domain})).await;
    let (_, exp) = app.get_at(id, "").await;
    assert_eq!(exp["domain"]["goal"]["radius"], json!([0.05, 0.3]), "{exp}");
    let (status, plan) = app
        .post_at(
            id,
            "plans",
            &json!({"start": [0.2, 3.0], "goal": [0.4, -3.0], "beta": -1000.0}),
        )
        .await;
    assert_eq!(status, 200, "{plan}");
    assert_eq!(plan["found"], true, "{plan}");
    let last = plan["trajectory"]["states"]
        .as_array()
        .unwrap()
        .last()
        .unwrap()
        .clone();
    let (x, theta) = (last[0].as_f64().unwrap(), last[1].as_f64().unwrap());
    let dtheta = (theta + 3.0 + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
        - std::f64::consts::PI;
    let inside = ((x - 0.4) / 0.05).powi(2) + (dtheta / 0.3).powi(2);
    assert!(
        inside <= 1.0 + 1e-9,
        "ends at {last}: {inside} radii from the goal"
    );
}
