//! The estimator seam as a client sees it: a fit that would not fit the memory budget is
//! refused and recorded while the previous version keeps answering (also across a restart);
//! `auto` hands such a fit to the sparse GP; the sparse GP takes each posted trajectory in at
//! once and again after a restart.

use super::helpers::{fresh_app_with_limits, pushed_lattice, spawn_app_with_limits};
use precond::service::Limits;
use serde_json::{Value, json};

fn small_budget() -> Limits {
    Limits {
        max_fit_memory: 64 << 20,
        ..Limits::default()
    }
}

/// Polls `GET …/model` until `done` holds (fits run at a lower priority and take what a busy
/// machine gives them: the wait ends only a test that would hang, see `FIT_PATIENCE`).
async fn model_until(
    app: &super::helpers::TestApp,
    id: i64,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = std::time::Instant::now() + super::helpers::FIT_PATIENCE;
    loop {
        let (_, model) = app.get_at(id, "model").await;
        if done(&model) {
            return model;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the model did not get there: {model}"
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
}

#[tokio::test]
async fn a_fit_beyond_the_memory_budget_is_refused_and_the_server_keeps_serving() {
    let (_dir, app) = fresh_app_with_limits(small_budget()).await;
    // The exact GP on 1600 transitions needs about 100 MB at its peak: beyond 64 MiB.
    let exact = app
        .create_experiment(json!({
            "domain": {"kind": "kinematic"},
            "mde": {"estimator": "exact", "restarts": 0},
            "learning": {"batch_size": 2}
        }))
        .await;
    for k in 0..2 {
        app.store_trajectory(exact, &pushed_lattice(800, 800 * k))
            .await;
    }
    let model = model_until(&app, exact, |m| !m["last_fit_refusal"].is_null()).await;
    assert_eq!(model["version"], 0, "the prior keeps answering: {model}");
    let refusal = &model["last_fit_refusal"];
    assert_eq!(refusal["n_train"], 1600);
    assert_eq!(refusal["estimator"], "exact");
    assert!(refusal["needed_bytes"].as_f64().unwrap() > refusal["budget_bytes"].as_f64().unwrap());
    assert!(
        refusal["reason"]
            .as_str()
            .unwrap()
            .contains("--max-fit-memory-mib")
    );
    let (status, forced) = app.post_at(exact, "model/refit", &json!({})).await;
    assert_eq!(status, 409, "{forced}");
    assert_eq!(forced["error"]["code"], "limit_reached");
    let (_, timeline) = app.get_at(exact, "timeline").await;
    assert!(
        timeline["fit_refusals"].as_array().unwrap().len() >= 2,
        "{timeline}"
    );
    let metrics = app.metrics().await;
    assert!(
        metrics
            .lines()
            .any(|l| l.starts_with("precond_fits_total") && l.contains("result=\"refused\"")),
        "{metrics}"
    );
    // The same data with `auto`: the sparse GP takes the fit over. One kernel and one label
    // cap, so the fit is the sparse GP's alone (choosing them would add five exact fits on the
    // same 1600 points, a minute on a loaded debug build).
    let auto = app
        .create_experiment(json!({
            "domain": {"kind": "kinematic"},
            "mde": {"restarts": 0, "kernel": "matern52", "label_cap": 0},
            "learning": {"batch_size": 2}
        }))
        .await;
    for k in 0..2 {
        app.store_trajectory(auto, &pushed_lattice(800, 800 * k))
            .await;
    }
    let model = model_until(&app, auto, |m| m["version"] == 1).await;
    assert_eq!(model["estimator"], "sparse", "{model}");
    assert!(model["last_fit_refusal"].is_null());
    // A restart resumes the refused fit, refuses it again, and serves on.
    let path = app.db_path.clone();
    app.stop().await;
    let app = spawn_app_with_limits(&path, small_budget()).await;
    let (status, model) = app.get_at(exact, "model").await;
    assert_eq!(status, 200, "{model}");
    assert_eq!(model["version"], 0);
    let (status, judged) = app
        .post_at(
            exact,
            "precondition",
            &json!({"points": [{"s": [0.2, 0.2], "a": [0.05, 0.0]}]}),
        )
        .await;
    assert_eq!(status, 200, "{judged}");
    let (_, model) = app.get_at(auto, "model").await;
    assert_eq!(
        (model["version"].clone(), model["estimator"].clone()),
        (json!(1), json!("sparse"))
    );
    app.stop().await;
}

#[tokio::test]
async fn the_sparse_gp_takes_each_trajectory_in_at_once_and_again_after_a_restart() {
    let (_dir, app) = fresh_app_with_limits(Limits::default()).await;
    let id = app
        .create_experiment(json!({
            "domain": {"kind": "kinematic"},
            "mde": {"estimator": "sparse", "restarts": 0, "inducing_points": 32,
                    "noise": "homoscedastic"},
            "learning": {"batch_size": 3}
        }))
        .await;
    for k in 0..3 {
        app.post_at(id, "trajectories", &pushed_lattice(40, 40 * k))
            .await;
    }
    let fitted = model_until(&app, id, |m| m["version"] == 1).await;
    assert_eq!(fitted["estimator"], "sparse");
    assert_eq!(fitted["online_trajectories"], 0);
    let probe = json!({"points": [{"s": [0.7, 0.9], "a": [0.05, 0.0]}], "beta": 0});
    let (_, before) = app.post_at(id, "precondition", &probe).await;
    // One more trajectory, where the model is wrong, right at the probe: taken in at once.
    let at_probe = json!({"transitions": [
        {"s": [0.7, 0.9], "a": [0.05, 0.0], "s_next": [0.75, 1.0]},
        {"s": [0.7, 0.9], "a": [0.05, 0.0], "s_next": [0.75, 1.0]},
    ]});
    app.store_trajectory(id, &at_probe).await;
    let (_, updated) = app.get_at(id, "model").await;
    assert_eq!(updated["version"], 1, "no refit: {updated}");
    assert_eq!(updated["online_trajectories"], 1);
    assert_eq!(updated["n_train"], fitted["n_train"].as_i64().unwrap() + 2);
    let (_, after) = app.post_at(id, "precondition", &probe).await;
    let mu = |j: &Value| j["results"][0]["mu"].as_f64().unwrap();
    let sigma = |j: &Value| j["results"][0]["sigma"].as_f64().unwrap();
    // The label there is 0.1: μ moves towards it and σ shrinks.
    assert!(
        (mu(&after) - 0.1).abs() < (mu(&before) - 0.1).abs(),
        "{before} → {after}"
    );
    assert!(sigma(&after) < sigma(&before), "{before} → {after}");
    // After a restart the same version takes the same trajectory in again.
    let path = app.db_path.clone();
    app.stop().await;
    let app = spawn_app_with_limits(&path, Limits::default()).await;
    let (_, restored) = app.get_at(id, "model").await;
    assert_eq!(
        (
            restored["version"].clone(),
            restored["online_trajectories"].clone()
        ),
        (json!(1), json!(1))
    );
    let (_, again) = app.post_at(id, "precondition", &probe).await;
    assert!((mu(&again) - mu(&after)).abs() < 1e-9, "{after} vs {again}");
    assert!((sigma(&again) - sigma(&after)).abs() < 1e-9);
    app.stop().await;
}

/// Posts batches of `pushed_lattice` (80 transitions, then 10 a batch: the data never double
/// between fits) and returns each fitted version's `selection`.
async fn selections(body: Value, versions: usize) -> Vec<Value> {
    let (_dir, app) = fresh_app_with_limits(Limits::default()).await;
    let id = app.create_experiment(body).await;
    let mut out = Vec::new();
    for v in 1..=versions {
        let (n, offset) = if v == 1 { (80, 0) } else { (10, 80 + 10 * v) };
        app.store_trajectory(id, &pushed_lattice(n, offset)).await;
        let model = model_until(&app, id, |m| m["version"].as_i64() >= Some(v as i64)).await;
        assert_eq!(model["version"], v as i64, "one version per batch");
        out.push(model["selection"].clone());
    }
    out
}

#[tokio::test]
async fn refits_keep_the_last_choice_warm_and_choose_anew_every_nth_fit() {
    let s = selections(
        json!({"domain": {"kind": "kinematic"}, "learning": {"batch_size": 1},
               "mde": {"reselect_every": 3, "noise": "homoscedastic"}}),
        4,
    )
    .await;
    // Version 1 chooses (the first fit), 2 and 3 keep its choice warm, 4 chooses anew.
    let chosen_at: Vec<i64> = s
        .iter()
        .map(|r| r["selected_at_version"].as_i64().unwrap())
        .collect();
    assert_eq!(chosen_at, [1, 1, 1, 4], "{s:?}");
    assert!(
        s[0]["reason"].as_str().unwrap().contains("first fit"),
        "{}",
        s[0]
    );
    assert!(
        s[1]["reason"].as_str().unwrap().contains("keeps version 1"),
        "{}",
        s[1]
    );
    assert!(
        s[3]["reason"].as_str().unwrap().contains("every 3"),
        "{}",
        s[3]
    );
    let phases = |r: &Value| -> Vec<String> {
        r["phases"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["phase"].as_str().unwrap().to_string())
            .collect()
    };
    assert_eq!(
        phases(&s[1]),
        ["warm fit", "held-out judgements, certified β"]
    );
    assert!(
        phases(&s[0])
            .iter()
            .any(|p| p.starts_with("kernels: 3 fits")),
        "{}",
        s[0]
    );
    assert!(
        phases(&s[3])
            .iter()
            .any(|p| p.starts_with("kernels: 3 fits")),
        "{}",
        s[3]
    );

    // The paper preset fits from scratch every time.
    let paper = selections(
        json!({"domain": {"kind": "kinematic"}, "learning": {"batch_size": 1, "preset": "paper"},
               "mde": {"noise": "homoscedastic"}}),
        2,
    )
    .await;
    let chosen_at: Vec<i64> = paper
        .iter()
        .map(|r| r["selected_at_version"].as_i64().unwrap())
        .collect();
    assert_eq!(chosen_at, [1, 2], "{paper:?}");
}

#[tokio::test]
async fn a_fit_estimated_beyond_the_time_budget_is_refused_and_recorded() {
    let (_dir, app) = fresh_app_with_limits(Limits {
        max_fit_seconds: 10,
        ..Limits::default()
    })
    .await;
    // The exact GP's model selection on 1600 transitions (three kernels, then two more label
    // caps, each from three starts) is estimated at well over 10 s by the cost model.
    let exact = app
        .create_experiment(json!({
            "domain": {"kind": "kinematic"},
            "mde": {"estimator": "exact"},
            "learning": {"batch_size": 2}
        }))
        .await;
    for k in 0..2 {
        app.store_trajectory(exact, &pushed_lattice(800, 800 * k))
            .await;
    }
    let model = model_until(&app, exact, |m| !m["last_fit_refusal"].is_null()).await;
    assert_eq!(model["version"], 0, "the prior keeps answering: {model}");
    let refusal = &model["last_fit_refusal"];
    assert_eq!(refusal["budget_seconds"], 10.0, "{refusal}");
    assert!(
        refusal["needed_seconds"].as_f64().unwrap() > 10.0,
        "{refusal}"
    );
    assert!(
        refusal["reason"]
            .as_str()
            .unwrap()
            .contains("--max-fit-seconds"),
        "{refusal}"
    );
}
