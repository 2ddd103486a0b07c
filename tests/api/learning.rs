//! The MDE, precondition queries, proposals with leases, and test-time plans.

use crate::helpers::*;
use precond::domain::{Cell, IcyGridworld, LocalModel};
use precond::sim::Simulated;
use serde_json::{Value, json};

#[tokio::test]
async fn before_any_data_the_prior_answers_and_says_so() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    let (status, model) = app.get_at(id, "model").await;
    assert_eq!(status, 200);
    assert_eq!(
        (model["version"].as_i64(), model["source"].as_str()),
        (Some(0), Some("prior"))
    );
    let (status, p) = app
        .post_at(
            id,
            "precondition",
            &json!({"points": [{"s": [3, 2], "a": [1, 0]}], "beta": 2.0}),
        )
        .await;
    assert_eq!(status, 200, "{p}");
    assert_eq!(p["source"], "prior");
    let r = &p["results"][0];
    assert_eq!(r["mu"], 0.0);
    assert_eq!(r["sigma"], 1.0);
    assert_eq!(r["upper"], 2.0);
    assert_eq!(r["inside"], false);
    let (status, p) = app
        .get(&format!(
            "/v1/experiments/{id}/precondition?s=3,2&a=1,0&beta=-2"
        ))
        .await;
    assert_eq!(status, 200, "{p}");
    assert_eq!(
        p["results"][0]["inside"], true,
        "β = −2 trusts the unexplored prior"
    );
    let (status, _) = app.post_at(id, "model/refit", &json!({})).await;
    assert_eq!(status, 409, "nothing to fit yet");
}

#[tokio::test]
async fn precondition_queries_validate_their_points() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    let path = format!("/v1/experiments/{id}/precondition");
    for (body, field) in [
        (
            json!({"points": [{"s": [3, 2, 1], "a": [1, 0]}]}),
            "points[0].s",
        ),
        (
            json!({"points": [{"s": [3, 2], "a": [1, 0]}, {"s": [3, 2], "a": [2, 0]}]}),
            "points[1].a",
        ),
        (json!({"points": []}), "points"),
        (
            json!({"points": [{"s": [3, 2], "a": [1, 0]}], "beta": "high"}),
            "beta",
        ),
    ] {
        let (status, err) = app.post(&path, &body).await;
        assert_eq!(status, 422, "{body}: {err}");
        assert_eq!(err["error"]["details"]["field"], field);
    }
    let (status, err) = app.get(&format!("{path}?s=3,x&a=1,0")).await;
    assert_eq!(
        (status, err["error"]["details"]["field"].as_str()),
        (422, Some("s"))
    );
    let (status, err) = app.get(&format!("{path}?s=3,2")).await;
    assert_eq!((status, code(&err)), (422, "validation_failed"));
}

#[tokio::test]
async fn the_model_advances_after_each_batch_and_survives_a_restart() {
    let (_dir, app, id) =
        fresh_experiment(json!({"mde": {"noise": "homoscedastic", "restarts": 0}})).await;
    let batches = gridworld_moves(0..12, 48);
    for t in batches.iter().take(5) {
        app.store_trajectory(id, t).await;
    }
    let model = app.wait_for_model(id, 5).await;
    assert_eq!(model["version"], 1);
    assert_eq!(model["source"], "fit");
    assert_eq!(model["n_train"], 5 * 48);
    assert_eq!(
        model["hyperparameters"]["length_scales"]
            .as_array()
            .unwrap()
            .len(),
        4
    );
    assert!(
        model["log_marginal_likelihood"]
            .as_f64()
            .unwrap()
            .is_finite()
    );
    // The default label cap is chosen at the fit among 2, 5 and raw labels; each candidate's
    // held-out judgement covers every training transition.
    let trials = model["label_cap_trials"].as_array().unwrap();
    let caps = floats(&model["label_cap_trials"], "label_cap");
    assert_eq!(caps, vec![2.0, 5.0, 0.0]);
    assert!(caps.contains(&model["label_cap"].as_f64().unwrap()));
    for t in trials {
        let n = t["safe"].as_u64().unwrap() + t["unsafe_transitions"].as_u64().unwrap();
        assert_eq!(n, 5 * 48);
        assert!(t["trusted_safe"].as_u64() <= t["safe"].as_u64());
        // Each distinct state-action is held out with its copies.
        let groups = t["held_out_groups"].as_u64().unwrap();
        assert!((1..=n).contains(&groups), "{t}");
    }
    let points = json!({"points": [{"s": [3, 2], "a": [1, 0]}, {"s": [0, 0], "a": [0, 1]}]});
    let (_, before) = app.post_at(id, "precondition", &points).await;
    assert_eq!(before["model_version"], 1);

    let app = app.restart().await;
    let (_, restored) = app.get_at(id, "model").await;
    assert_eq!(restored["version"], 1);
    assert_eq!(restored["hyperparameters"], model["hyperparameters"]);
    assert_eq!(restored["label_cap"], model["label_cap"]);
    assert_eq!(restored["label_cap_trials"], model["label_cap_trials"]);
    let (lml0, lml1) = (
        model["log_marginal_likelihood"].as_f64().unwrap(),
        restored["log_marginal_likelihood"].as_f64().unwrap(),
    );
    assert!(
        (lml0 - lml1).abs() <= 1e-9 * lml0.abs(),
        "{lml0} then {lml1}"
    );
    let (_, after) = app.post_at(id, "precondition", &points).await;
    for k in 0..2 {
        for f in ["mu", "sigma"] {
            let (b, a) = (
                before["results"][k][f].as_f64().unwrap(),
                after["results"][k][f].as_f64().unwrap(),
            );
            assert!(
                (a - b).abs() <= 1e-9 * b.abs().max(1e-9),
                "{f}[{k}]: {b} then {a}"
            );
        }
    }
    let refit = app.refit(id).await;
    assert_eq!(refit["version"], 2);
    app.stop().await;
}

#[tokio::test]
async fn a_test_time_plan_avoids_the_ice_once_the_data_shows_it() {
    let (_dir, app) = fresh_app().await;
    let id = app
        // Heteroscedastic noise (the default) is what made this work with raw labels: a
        // homoscedastic fit of 0-or-2 labels puts σ_noise ≈ 0.08 everywhere, so μ + 2σ > d_max
        // = 0.1 even where the model is exact, and nothing is trusted.
        .create_experiment(json!({
            "mde": {"restarts": 0},
            "learning": {"batch_size": 1000}
        }))
        .await;
    // Before any data the conservative test β trusts nothing.
    let problem = json!({"start": [5, 0], "goal": [5, 5]});
    let (status, plan) = app.post_at(id, "plans", &problem).await;
    assert_eq!(status, 200, "{plan}");
    assert_eq!(plan["found"], false);
    for t in gridworld_moves(0..12, 48) {
        app.store_trajectory(id, &t).await;
    }
    app.refit(id).await;
    let grid = IcyGridworld::default_layout();
    // Problems that must cross or skirt an ice band. (Crossing the wall's two-cell gap is not
    // among them: with these features the fitted x length scale spans most of the grid, so the
    // GP cannot single out the gap's two trusted up-moves in row 5 — see the issue notes.)
    for (start, goal) in [
        ([2, 1], [9, 4]),
        ([4, 4], [7, 0]),
        ([1, 9], [10, 9]),
        ([0, 7], [11, 11]),
    ] {
        let (status, plan) = app
            .post_at(id, "plans", &json!({"start": start, "goal": goal}))
            .await;
        assert_eq!(status, 200, "{plan}");
        assert_eq!(plan["found"], true, "{start:?} → {goal:?}: {plan}");
        let t = &plan["trajectory"];
        let states = t["states"].as_array().unwrap();
        for (k, a) in t["actions"].as_array().unwrap().iter().enumerate() {
            let s: Vec<f64> = serde_json::from_value(states[k].clone()).unwrap();
            let a: Vec<f64> = serde_json::from_value(a.clone()).unwrap();
            let on_ice = grid.cell(s[0] as i64, s[1] as i64) == Some(Cell::Ice);
            assert!(!(on_ice && a[0] != 0.0), "x-move {a:?} from ice cell {s:?}");
            let next = grid.predict(&s, &a);
            assert_ne!(
                grid.cell(next[0] as i64, next[1] as i64),
                Some(Cell::Obstacle)
            );
            let upper = t["mu"][k].as_f64().unwrap() + 2.0 * t["sigma"][k].as_f64().unwrap();
            assert!(upper < 0.1, "edge {k} outside the precondition: {upper}");
        }
        assert_eq!(
            states.last().unwrap(),
            &json!([goal[0] as f64, goal[1] as f64])
        );
    }
}

#[tokio::test]
async fn strategies_produce_what_they_promise() {
    // The paper's acquisition: `active` executes a goal-reaching candidate (the default,
    // `bottleneck`, may execute a probe instead; see below).
    let (_dir, app, id) = fresh_experiment(
        json!({"seed": 3, "learning": {"acquisition": "lcb", "warmup_iterations": 0}}),
    )
    .await;
    let path = format!("/v1/experiments/{id}/proposals");
    let goal = json!([9, 10]);
    for strategy in ["active", "goal_conditioned"] {
        let (status, p) = app
            .post(
                &path,
                &json!({"start": [1, 1], "goal": goal, "strategy": strategy}),
            )
            .await;
        assert_eq!(status, 201, "{p}");
        assert_eq!(p["strategy"], strategy);
        assert_eq!(p["status"], "open");
        let t = &p["trajectory"];
        assert_eq!(
            t["states"].as_array().unwrap().last().unwrap(),
            &json!([9.0, 10.0])
        );
        let n = t["actions"].as_array().unwrap().len();
        assert_eq!(t["mu"].as_array().unwrap().len(), n);
        assert_eq!(t["alpha_step"].as_array().unwrap().len(), n);
        let alphas = floats(&p["candidates"], "alpha");
        assert!(!alphas.is_empty());
        let chosen = p["chosen_index"].as_u64().unwrap() as usize;
        assert_eq!(alphas[chosen], t["alpha"].as_f64().unwrap());
        if strategy == "active" {
            let min = alphas.iter().cloned().fold(f64::INFINITY, f64::min);
            assert_eq!(t["alpha"].as_f64().unwrap(), min, "active picks the argmin");
        }
        // β of iteration 0 of the schedule: 2·2/(1+e^{0.5·10}) − 2.
        let beta0 = 4.0 / (1.0 + (5.0f64).exp()) - 2.0;
        assert!((p["beta"].as_f64().unwrap() - beta0).abs() < 1e-12);
    }
    let (status, p) = app
        .post(
            &path,
            &json!({"start": [1, 1], "goal": goal, "strategy": "random"}),
        )
        .await;
    assert_eq!(status, 201, "{p}");
    let n = p["trajectory"]["actions"].as_array().unwrap().len();
    assert_eq!(
        n, 8,
        "a random rollout has the domain's length (mean problem length)"
    );
    let last = p["trajectory"]["states"]
        .as_array()
        .unwrap()
        .last()
        .unwrap()
        .clone();
    assert_ne!(
        last,
        json!([9.0, 10.0]),
        "17 moves away: 8 random moves cannot arrive"
    );

    // The default acquisition, `bottleneck`: the argmin of the reported `α` (minus each
    // trajectory's value), either a goal-reaching candidate or the probe, listed last, whose
    // value is positive.
    let (_dir, app, id) = fresh_experiment(json!({"seed": 3})).await;
    let (status, p) = app
        .post(
            &format!("/v1/experiments/{id}/proposals"),
            &json!({"start": [1, 1], "goal": goal, "strategy": "active"}),
        )
        .await;
    assert_eq!(status, 201, "{p}");
    let alphas = floats(&p["candidates"], "alpha");
    let chosen = p["chosen_index"].as_u64().unwrap() as usize;
    let alpha = p["trajectory"]["alpha"].as_f64().unwrap();
    assert_eq!(alphas[chosen], alpha);
    assert_eq!(alpha, alphas.iter().cloned().fold(f64::INFINITY, f64::min));
    let last = p["trajectory"]["states"]
        .as_array()
        .unwrap()
        .last()
        .unwrap();
    if last != &json!([9.0, 10.0]) {
        assert_eq!(chosen, alphas.len() - 1, "a probe is listed last: {p}");
        assert!(alpha < 0.0, "a probe is chosen for its value: {p}");
    }
}

#[tokio::test]
async fn proposals_are_leases() {
    let (_dir, app, id) = fresh_experiment(json!({"learning": {"proposal_ttl_seconds": 1}})).await;
    let path = format!("/v1/experiments/{id}/proposals");
    let ask = json!({"start": [0, 0], "goal": [0, 4], "client_id": "robot-a"});
    let (status, first) = app.post(&path, &ask).await;
    assert_eq!(status, 201, "{first}");
    let (status, again) = app.post(&path, &ask).await;
    assert_eq!(status, 200, "asking again returns the open lease");
    assert_eq!(again["id"], first["id"]);
    let (_, other) = app
        .post(
            &path,
            &json!({"start": [0, 0], "goal": [0, 4], "client_id": "robot-b"}),
        )
        .await;
    assert_ne!(other["id"], first["id"], "another client gets its own");
    let (status, err) = app
        .post(
            &path,
            &json!({"start": [1, 0], "goal": [0, 4], "client_id": "robot-a"}),
        )
        .await;
    assert_eq!(
        (status, code(&err)),
        (409, "conflict"),
        "a lease is for one problem"
    );
    assert_eq!(err["error"]["details"]["proposal_id"], first["id"], "{err}");
    assert_eq!(err["error"]["details"]["client_id"], "robot-a");

    // Executing it closes the lease.
    let pid = first["id"].as_i64().unwrap();
    let states = first["trajectory"]["states"].as_array().unwrap();
    let transitions: Vec<Value> = first["trajectory"]["actions"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
        .map(|(k, a)| json!({"s": states[k], "a": a, "s_next": states[k + 1]}))
        .collect();
    let body = json!({"proposal_id": pid, "transitions": transitions});
    let t = app.store_trajectory(id, &body).await;
    assert_eq!(t["proposal_id"], pid);
    let (_, p) = app.get(&format!("{path}/{pid}")).await;
    assert_eq!(p["status"], "executed");
    let (status, err) = app.post_at(id, "trajectories", &body).await;
    assert_eq!(
        (status, code(&err)),
        (409, "conflict"),
        "executed once only"
    );
    let (status, _) = app.post(&format!("{path}/{pid}/abandon"), &json!({})).await;
    assert_eq!(status, 409);
    let (status, fresh) = app.post(&path, &ask).await;
    assert_eq!(status, 201);
    assert_ne!(fresh["id"], first["id"]);

    // Abandoning, and expiry.
    let oid = other["id"].as_i64().unwrap();
    let (status, abandoned) = app.post(&format!("{path}/{oid}/abandon"), &json!({})).await;
    assert_eq!(
        (status, abandoned["status"].as_str()),
        (200, Some("abandoned"))
    );
    tokio::time::sleep(std::time::Duration::from_millis(1100)).await;
    let fid = fresh["id"].as_i64().unwrap();
    let (_, expired) = app.get(&format!("{path}/{fid}")).await;
    assert_eq!(expired["status"], "expired");
    let (status, renewed) = app.post(&path, &ask).await;
    assert_eq!(status, 201, "an expired lease is not handed out again");
    assert_ne!(renewed["id"], fresh["id"]);
    let (status, _) = app.get(&format!("{path}/9999")).await;
    assert_eq!(status, 404);
}

#[tokio::test]
async fn continuing_a_proposal_stores_the_prefix_and_replans_from_where_the_robot_is() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    let path = format!("/v1/experiments/{id}/proposals");
    let (status, first) = app
        .post(
            &path,
            &json!({"start": [0, 0], "goal": [0, 4], "client_id": "robot-a"}),
        )
        .await;
    assert_eq!(status, 201, "{first}");
    let pid = first["id"].as_i64().unwrap();
    let states = first["trajectory"]["states"].as_array().unwrap().clone();
    let actions = first["trajectory"]["actions"].as_array().unwrap().clone();
    assert!(actions.len() >= 2, "{first}");
    // The robot executes the first step only, in the true world, and asks to go on from there.
    let mut world = IcyGridworld::default_layout().world();
    let s0: Vec<f64> = serde_json::from_value(states[0].clone()).unwrap();
    let a0: Vec<f64> = serde_json::from_value(actions[0].clone()).unwrap();
    let s1 = world.step(&s0, &a0);
    let prefix = json!({"transitions": [{"s": s0, "a": a0, "s_next": s1}]});
    let url = app.url(&format!("{path}/{pid}/continue"));
    let send = |key: &'static str, body: Value| {
        app.client
            .post(&url)
            .header("Idempotency-Key", key)
            .json(&body)
            .send()
    };
    let response = send("step-1", prefix.clone()).await.unwrap();
    assert_eq!(response.status().as_u16(), 201);
    let next: Value = response.json().await.unwrap();
    assert_eq!(next["trajectory"]["proposal_id"], pid, "{next}");
    assert_eq!(next["trajectory"]["n_transitions"], 1, "{next}");
    assert_eq!(next["trajectory"]["partial"], true, "{next}");
    let new_id = next["proposal"]["id"].as_i64().unwrap();
    assert_ne!(new_id, pid);
    assert_eq!(next["proposal"]["client_id"], "robot-a");
    assert_eq!(next["proposal"]["start"], json!(s1));
    assert_eq!(next["proposal"]["goal"], json!([0.0, 4.0]));
    assert_eq!(next["proposal"]["status"], "open");
    let (_, old) = app.get(&format!("{path}/{pid}")).await;
    assert_eq!(old["status"], "executed", "the prefix closes the old lease");
    let stored = app.all_transitions(id).await;
    assert_eq!(stored.len(), 1, "the prefix is stored once");

    // A retry after a lost answer stores nothing twice and hands back the same lease.
    let again = send("step-1", prefix.clone()).await.unwrap();
    assert_eq!(again.headers()["idempotent-replayed"], "true");
    let again: Value = again.json().await.unwrap();
    assert_eq!(again["trajectory"], next["trajectory"]);
    assert_eq!(again["proposal"]["id"], new_id);
    assert_eq!(app.all_transitions(id).await.len(), 1);

    // A prefix that does not start where the proposal did is refused, and nothing is stored.
    let (status, err) = app
        .post(
            &format!("{path}/{new_id}/continue"),
            &json!({"transitions": [{"s": [3, 3], "a": [1, 0], "s_next": [4, 3]}]}),
        )
        .await;
    assert_eq!((status, code(&err)), (422, "validation_failed"), "{err}");
    assert_eq!(
        err["error"]["details"]["field"], "transitions[0].s",
        "{err}"
    );
    assert_eq!(app.all_transitions(id).await.len(), 1);
    let (status, _) = app.post(&format!("{path}/9999/continue"), &prefix).await;
    assert_eq!(status, 404);
}

#[tokio::test]
async fn a_replayed_continue_answers_its_first_proposal_and_never_leases_another() {
    let (_dir, app, id) = fresh_experiment(json!({})).await;
    let path = format!("/v1/experiments/{id}/proposals");
    let mut world = IcyGridworld::default_layout().world();
    // The first step of `proposal`, executed in the true world, as a continue body.
    let mut first_step = |proposal: &Value| {
        let s0: Vec<f64> =
            serde_json::from_value(proposal["trajectory"]["states"][0].clone()).unwrap();
        let a0: Vec<f64> =
            serde_json::from_value(proposal["trajectory"]["actions"][0].clone()).unwrap();
        let s1 = world.step(&s0, &a0);
        json!({"transitions": [{"s": s0, "a": a0, "s_next": s1}]})
    };
    let continue_with = |pid: i64, key: &'static str, body: Value| {
        app.client
            .post(app.url(&format!("{path}/{pid}/continue")))
            .header("Idempotency-Key", key)
            .json(&body)
            .send()
    };
    // A late replay: the continuation was executed meanwhile.
    let (_, first) = app
        .post(
            &path,
            &json!({"start": [0, 0], "goal": [0, 4], "client_id": "arm-6"}),
        )
        .await;
    let prefix = first_step(&first);
    let r = continue_with(first["id"].as_i64().unwrap(), "late", prefix.clone())
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let made: Value = r.json().await.unwrap();
    let made_id = made["proposal"]["id"].as_i64().unwrap();
    let executed = first_step(&made["proposal"]);
    let (status, posted) = app
        .post(
            &format!("/v1/experiments/{id}/trajectories"),
            &json!({"proposal_id": made_id, "transitions": executed["transitions"]}),
        )
        .await;
    assert_eq!(status, 201, "{posted}");
    let r = continue_with(first["id"].as_i64().unwrap(), "late", prefix)
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    assert_eq!(r.headers()["idempotent-replayed"], "true");
    let again: Value = r.json().await.unwrap();
    assert_eq!(again["proposal"]["id"], made_id, "{again}");
    assert_eq!(again["proposal"]["status"], "executed", "{again}");
    let (status, lease) = app
        .post(
            &path,
            &json!({"start": [1, 1], "goal": [1, 5], "client_id": "arm-6"}),
        )
        .await;
    assert_eq!(status, 201, "no lease left open by the replay: {lease}");
    assert_eq!(lease["id"], made_id + 1, "the replay made no proposal");
    app.post(&format!("{path}/{}/abandon", lease["id"]), &json!({}))
        .await;

    // Without a client: three calls under one key, one proposal.
    let (_, anonymous) = app
        .post(&path, &json!({"start": [2, 0], "goal": [2, 4]}))
        .await;
    let prefix = first_step(&anonymous);
    let mut ids = Vec::new();
    for _ in 0..3 {
        let r = continue_with(anonymous["id"].as_i64().unwrap(), "anon", prefix.clone())
            .await
            .unwrap();
        assert_eq!(r.status(), 201);
        let v: Value = r.json().await.unwrap();
        ids.push(v["proposal"]["id"].as_i64().unwrap());
    }
    assert!(ids.iter().all(|i| *i == ids[0]), "{ids:?}");

    // The client holds another lease: the prefix is stored, and the 409 says so in a field.
    let (_, held) = app
        .post(
            &path,
            &json!({"start": [3, 0], "goal": [3, 4], "client_id": "arm-7"}),
        )
        .await;
    app.post(&format!("{path}/{}/abandon", held["id"]), &json!({}))
        .await;
    let (_, other) = app
        .post(
            &path,
            &json!({"start": [5, 0], "goal": [5, 4], "client_id": "arm-7"}),
        )
        .await;
    assert_ne!(other["id"], held["id"]);
    let r = continue_with(held["id"].as_i64().unwrap(), "held", first_step(&held))
        .await
        .unwrap();
    assert_eq!(r.status(), 409);
    let err: Value = r.json().await.unwrap();
    let stored = err["error"]["details"]["stored_trajectory_id"].as_i64();
    assert!(stored.is_some(), "{err}");
    assert_eq!(err["error"]["details"]["proposal_id"], other["id"], "{err}");
    let (status, t) = app
        .get(&format!(
            "/v1/experiments/{id}/trajectories/{}",
            stored.unwrap()
        ))
        .await;
    assert_eq!(
        (status, t["proposal_id"].clone()),
        (200, held["id"].clone())
    );
}

#[tokio::test]
async fn no_plan_is_422_with_the_extensions_used() {
    let (_dir, app, id) = fresh_experiment(json!({
        "domain": {"kind": "kinematic", "obstacles": [{"low": [0.45, -1.0], "high": [0.55, 2.0]}]},
        "learning": {"max_extensions": 300}
    }))
    .await;
    let (status, err) = app
        .propose(id, &json!({"start": [0.1, 0.5], "goal": [0.9, 0.5]}))
        .await;
    assert_eq!(status, 422, "{err}");
    assert_eq!(code(&err), "no_plan");
    assert!(err["error"]["details"]["extensions"].as_u64().unwrap() >= 300);
    let (status, err) = app
        .propose(id, &json!({"start": [0.1, 0.5, 0.0], "goal": [0.9, 0.5]}))
        .await;
    assert_eq!(
        (status, err["error"]["details"]["field"].as_str()),
        (422, Some("start"))
    );
}

/// After β turned positive, a training problem whose every route leaves what is trusted is
/// planned at a lower β (the default preset) rather than answered `no_plan` (the paper's).
#[tokio::test]
async fn a_training_problem_beyond_the_precondition_is_relaxed_by_default_and_not_by_the_paper() {
    let (_dir, app) = fresh_app().await;
    let map = ["..#...", "......", "......", "......", "......", "......"];
    // One iteration of one trajectory with a steep schedule: from the second trajectory on,
    // β_j ≈ k1 = 2.
    let learning = json!({"iterations": 1, "batch_size": 1, "k2": 10.0, "max_extensions": 2000});
    let mut ids = Vec::new();
    for preset in ["default", "paper"] {
        let mut l = learning.clone();
        l["preset"] = json!(preset);
        let id = app
            .create_experiment(json!({
                "domain": {"kind": "icy_gridworld", "map": map},
                "learning": l
            }))
            .await;
        // A safe move and a bump into the obstacle, far from the problem below.
        app.store_trajectory(
            id,
            &json!({"transitions": [
                {"s": [0, 0], "a": [1, 0], "s_next": [1, 0]},
                {"s": [1, 0], "a": [1, 0], "s_next": [1, 0]}
            ]}),
        )
        .await;
        app.wait_for_model(id, 1).await;
        ids.push(id);
    }
    let problem = json!({"start": [5, 1], "goal": [5, 5]});
    let candidate = json!({
        "states": [[5, 1], [5, 2], [5, 3], [5, 4], [5, 5]],
        "actions": [[0, 1], [0, 1], [0, 1], [0, 1]]
    });
    let mut given = problem.clone();
    given["candidates"] = json!([candidate]);

    let path = format!("/v1/experiments/{}/proposals", ids[0]);
    for ask in [&problem, &given] {
        let (status, p) = app.post(&path, ask).await;
        assert_eq!(status, 201, "{p}");
        let schedule = p["relaxed_from_beta"].as_f64().expect("relaxed");
        let beta = p["beta"].as_f64().unwrap();
        assert!(schedule > 1.9, "β_j {schedule}");
        assert!(beta < schedule, "planned at {beta}, below β_j {schedule}");
        let t = &p["trajectory"];
        let (mu, sigma) = (t["mu"].as_array().unwrap(), t["sigma"].as_array().unwrap());
        assert!(
            mu.iter()
                .zip(sigma)
                .any(|(m, s)| { m.as_f64().unwrap() + schedule * s.as_f64().unwrap() >= 0.1 }),
            "some step lies outside the precondition at β_j"
        );
        assert!(
            mu.iter()
                .zip(sigma)
                .all(|(m, s)| m.as_f64().unwrap() + beta * s.as_f64().unwrap() < 0.1),
            "every step inside it at the β used"
        );
        let last = t["states"].as_array().unwrap().last().unwrap().clone();
        assert_eq!(last, json!([5.0, 5.0]));
    }

    let path = format!("/v1/experiments/{}/proposals", ids[1]);
    for ask in [&problem, &given] {
        let (status, err) = app.post(&path, ask).await;
        assert_eq!((status, code(&err)), (422, "no_plan"), "{err}");
    }
    for (id, relaxes) in ids.iter().zip([true, false]) {
        let (_, e) = app.get_at(*id, "").await;
        assert_eq!(e["learning"]["relax_beta"], relaxes, "{e}");
    }
}

/// The state-actions of a proposal's planned trajectory.
fn planned_steps(p: &Value) -> Vec<(Value, Value)> {
    let t = &p["trajectory"];
    let states = t["states"].as_array().unwrap();
    t["actions"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
        .map(|(k, a)| (states[k].clone(), a.clone()))
        .collect()
}

#[tokio::test]
async fn active_answers_its_warm_up_iterations_with_random_rollouts() {
    // Batches of 2 and one warm-up iteration: the first two `active` proposals are random
    // rollouts and say so; from the second iteration on the acquisition chooses.
    let (_dir, app, id) = fresh_experiment(json!({
        "seed": 3,
        "learning": {"batch_size": 2, "warmup_iterations": 1}
    }))
    .await;
    let path = format!("/v1/experiments/{id}/proposals");
    let ask = json!({"start": [1, 1], "goal": [9, 10], "strategy": "active"});
    for _ in 0..2 {
        let (status, p) = app.post(&path, &ask).await;
        assert_eq!(status, 201, "{p}");
        assert_eq!(p["strategy"], "random", "{p}");
        assert_eq!(p["iteration"], 0, "{p}");
        assert_eq!(p["candidates"].as_array().unwrap().len(), 1, "{p}");
        let t = &p["trajectory"];
        let executed = json!({
            "proposal_id": p["id"],
            "transitions": t["actions"].as_array().unwrap().iter().enumerate().map(|(i, a)| json!({
                "s": t["states"][i], "a": a, "s_next": t["states"][i + 1]
            })).collect::<Vec<_>>()
        });
        app.store_trajectory(id, &executed).await;
    }
    let (status, p) = app.post(&path, &ask).await;
    assert_eq!(status, 201, "{p}");
    assert_eq!(p["iteration"], 1, "{p}");
    assert_eq!(p["strategy"], "active", "{p}");
    assert!(p["candidates"].as_array().unwrap().len() > 1, "{p}");
    // `goal_conditioned` is never replaced.
    let (_dir, app, id) = fresh_experiment(json!({"learning": {"warmup_iterations": 1}})).await;
    let ask = json!({"start": [1, 1], "goal": [9, 10], "strategy": "goal_conditioned"});
    let p = app.assert_proposes(id, &ask).await;
    assert_eq!(p["strategy"], "goal_conditioned");
}

#[tokio::test]
async fn spread_executes_the_candidate_that_settles_the_most_of_the_boundary() {
    // The right half of the square pushes every move 0.1 along x (the deviation is d_max),
    // the left half moves as the model says: the boundary of the precondition runs through
    // the right half.
    let (_dir, app, id) = fresh_experiment(json!({
        "domain": {"kind": "kinematic"},
        "seed": 2,
        "mde": {"restarts": 0},
        "learning": {"acquisition": "spread", "batch_size": 1000}
    }))
    .await;
    for row in 0..4 {
        let y = 0.2 + 0.2 * f64::from(row);
        let transitions: Vec<Value> = (0..9)
            .map(|k| {
                let x = 0.05 + 0.1 * f64::from(k);
                let push = if x > 0.5 { 0.1 } else { 0.0 };
                json!({"s": [x, y], "a": [0.1, 0.0], "s_next": [(x + 0.1 + push).min(1.0), y]})
            })
            .collect();
        app.store_trajectory(id, &json!({"transitions": transitions}))
            .await;
    }
    app.refit(id).await;
    let ask = json!({"start": [0.1, 0.1], "goal": [0.9, 0.9], "strategy": "active"});
    let p = app.assert_proposes(id, &ask).await;
    let alphas = floats(&p["candidates"], "alpha");
    assert!(alphas.len() > 1, "a choice to make: {p}");
    // Each candidate's α is minus the boundary σ its execution would remove, and the chosen
    // one removes the most.
    assert!(alphas.iter().all(|a| *a <= 0.0), "{alphas:?}");
    let chosen = p["chosen_index"].as_u64().unwrap() as usize;
    let best = alphas.iter().cloned().fold(f64::INFINITY, f64::min);
    assert_eq!(alphas[chosen], best);
    assert!(best < 0.0, "some candidate settles something: {alphas:?}");
    assert!(
        alphas.iter().any(|a| *a > best * 0.99),
        "candidates differ in what they settle: {alphas:?}"
    );
    assert_eq!(p["valued_by"], "spread", "{p}");

    // The same trajectory posted as a client's candidate is valued the same way, not by `lcb`:
    // the same α, by the same rule.
    let pid = p["id"].as_i64().unwrap();
    let (status, _) = app
        .post(
            &format!("/v1/experiments/{id}/proposals/{pid}/abandon"),
            &json!({}),
        )
        .await;
    assert_eq!(status, 200);
    let own = json!({"states": p["trajectory"]["states"], "actions": p["trajectory"]["actions"]});
    let ask = json!({"start": [0.1, 0.1], "goal": [0.9, 0.9], "strategy": "active",
                     "candidates": [own]});
    let given = app.assert_proposes(id, &ask).await;
    assert_eq!(given["valued_by"], "spread", "{given}");
    let alpha = given["candidates"][0]["alpha"].as_f64().unwrap();
    assert!(
        (alpha - alphas[chosen]).abs() <= 1e-12,
        "posted {alpha}, planned {}",
        alphas[chosen]
    );
}

#[tokio::test]
async fn a_batch_does_not_chase_one_uncertainty_twice() {
    for diversity in [true, false] {
        let (b_steps, c_steps) = two_robots_in_one_batch(diversity).await;
        let shared = c_steps.iter().filter(|s| b_steps.contains(s)).count();
        if diversity {
            // While robot B's trajectory is in flight, robot C is sent elsewhere: the steps B
            // will teach no longer count as uncertain.
            assert!(
                shared < c_steps.len() / 2,
                "C repeats {shared} of its {} steps from B's trajectory",
                c_steps.len()
            );
        } else {
            // Without batch diversity both get the same trajectory.
            assert_eq!(c_steps, b_steps);
        }
    }
}

/// A gridworld experiment with a fitted model (`learning.batch_diversity` as given) where
/// robot A asks for a problem and abandons it, then robots B and C ask for the same one in the
/// same batch: checks that B gets A's trajectory (nothing was in flight for either, and the seed
/// is the same), and returns B's and C's planned state-actions.
async fn two_robots_in_one_batch(diversity: bool) -> (Vec<(Value, Value)>, Vec<(Value, Value)>) {
    let (_dir, app, id) = fresh_experiment(json!({
        "seed": 5,
        "mde": {"restarts": 0},
        "learning": {"batch_size": 1000, "batch_diversity": diversity}
    }))
    .await;
    for t in gridworld_moves(0..3, 48) {
        app.store_trajectory(id, &t).await;
    }
    app.refit(id).await;
    let path = format!("/v1/experiments/{id}/proposals");
    let ask = |client: &str| json!({"start": [1, 2], "goal": [9, 10], "client_id": client});
    let (status, a) = app.post(&path, &ask("robot-a")).await;
    assert_eq!(status, 201, "{a}");
    assert!(
        a["candidates"].as_array().unwrap().len() > 1,
        "a choice to make: {a}"
    );
    let (status, _) = app
        .post(&format!("{path}/{}/abandon", a["id"]), &json!({}))
        .await;
    assert_eq!(status, 200);
    let (status, b) = app.post(&path, &ask("robot-b")).await;
    assert_eq!(status, 201, "{b}");
    assert_eq!(planned_steps(&b), planned_steps(&a));
    let (status, c) = app.post(&path, &ask("robot-c")).await;
    assert_eq!(status, 201, "{c}");
    (planned_steps(&b), planned_steps(&c))
}

/// A test-time plan may search longer or shorter than the experiment's budget; the budget is
/// checked at the door, and does not apply to the client's own candidates.
#[tokio::test]
async fn a_plan_searches_within_the_budget_it_asks_for() {
    let (_dir, app, id) = fresh_experiment(json!({"learning": {"max_extensions": 20}})).await;
    // Before any data nothing is trusted, so a search spends its whole budget.
    let ask = |extra: Value| {
        let mut body = json!({"start": [5, 0], "goal": [5, 5]});
        body.as_object_mut()
            .unwrap()
            .extend(extra.as_object().unwrap().clone());
        body
    };
    for (extra, spent) in [
        (json!({}), 20),
        (json!({"max_extensions": 50}), 50),
        (json!({"max_extensions": 1}), 1),
        (json!({"max_extensions": null}), 20),
    ] {
        let (status, plan) = app.post_at(id, "plans", &ask(extra.clone())).await;
        assert_eq!(status, 200, "{extra}: {plan}");
        assert_eq!(plan["found"], false, "{extra}");
        assert_eq!(plan["extensions"], spent, "{extra}: {plan}");
    }
    for (extra, why) in [
        (json!({"max_extensions": 0}), "must lie in 1 to 200000"),
        (
            json!({"max_extensions": 200_001}),
            "must lie in 1 to 200000",
        ),
        (
            json!({"max_extensions": 10,
                   "candidates": [{"states": [[5, 0], [5, 1]], "actions": [[0, 1]]}]}),
            "applies to the service's search, not to the client's candidates",
        ),
    ] {
        let (status, err) = app.post_at(id, "plans", &ask(extra.clone())).await;
        assert_eq!(status, 422, "{extra}: {err}");
        assert_eq!(err["error"]["details"]["field"], "max_extensions", "{err}");
        assert_eq!(reason(&err), why);
    }
    app.stop().await;
}
