//! `GET …/model/export`: the exported document, evaluated by the Rust library
//! (`precond::mde::ExportedModel`), answers what `POST …/precondition` answers — `μ` and `σ` to
//! 1e-9 on random state-actions — for the exact GP (kernel `auto`, heteroscedastic and
//! homoscedastic noise, both gridworld feature maps, the kinematic domain) and the sparse GP
//! (after online updates too); the prior is refused with `409`, a bad `version` with `422`, a
//! missing one with `404`.

use super::helpers::{TestApp, code, fresh_app, fresh_experiment, message};
use precond::gp::GpPredictor;
use precond::mde::ExportedModel;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};

/// Parity tolerance: `|got − want| ≤ TOL · (1 + |want|)`.
const TOL: f64 = 1e-9;

/// Kinematic transitions on a lattice of the unit square moving by `(0.05, 0.02)`; the world
/// pushes the robot up by 0.08 where `x > 0.5`, with a little seeded jitter.
fn kinematic_trajectory(n: usize, offset: usize, seed: u64) -> Value {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let transitions: Vec<Value> = (0..n)
        .map(|k| {
            let i = k + offset;
            let (x, y) = ((i % 19) as f64 / 20.0, ((i / 19) % 19) as f64 / 20.0);
            let push = if x > 0.5 { 0.08 } else { 0.0 } + 0.01 * rng.random::<f64>();
            json!({"s": [x, y], "a": [0.05, 0.02],
                   "s_next": [(x + 0.05).min(1.0), (y + 0.02 + push).min(1.0)]})
        })
        .collect();
    json!({ "transitions": transitions })
}

/// Gridworld transitions: right along the free row 0, and right along the ice of row 2, where
/// the world sends the robot left instead.
fn gridworld_trajectories() -> Vec<Value> {
    let free: Vec<Value> = (0..10)
        .map(|x| json!({"s": [x, 0], "a": [1, 0], "s_next": [x + 1, 0]}))
        .collect();
    let ice: Vec<Value> = (3..9)
        .map(|x| json!({"s": [x, 2], "a": [1, 0], "s_next": [x - 1, 2]}))
        .collect();
    let up: Vec<Value> = (0..8)
        .map(|y| json!({"s": [11, y], "a": [0, 1], "s_next": [11, y + 1]}))
        .collect();
    vec![
        json!({ "transitions": free }),
        json!({ "transitions": ice }),
        json!({ "transitions": up }),
    ]
}

/// 200 seeded random state-actions valid for the experiment: uniform in the boxes (integer
/// cells for the gridworld), actions from the allowed values where there are some.
fn random_points(experiment: &Value, grid: bool, seed: u64) -> Vec<(Vec<f64>, Vec<f64>)> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let bounds = |space: &Value| -> Vec<(f64, f64)> {
        let low = space["low"].as_array().unwrap();
        let high = space["high"].as_array().unwrap();
        low.iter()
            .zip(high)
            .map(|(l, h)| (l.as_f64().unwrap(), h.as_f64().unwrap()))
            .collect()
    };
    let (state, action) = (
        bounds(&experiment["state_space"]),
        bounds(&experiment["action_space"]),
    );
    let values: Option<Vec<Vec<f64>>> = experiment["action_space"]["values"].as_array().map(|vs| {
        vs.iter()
            .map(|v| serde_json::from_value(v.clone()).unwrap())
            .collect()
    });
    (0..200)
        .map(|_| {
            let s: Vec<f64> = state
                .iter()
                .map(|(l, h)| {
                    let v = rng.random_range(*l..=*h);
                    if grid { v.round() } else { v }
                })
                .collect();
            let a = match &values {
                Some(vs) => vs[rng.random_range(0..vs.len())].clone(),
                None => action
                    .iter()
                    .map(|(l, h)| rng.random_range(*l..=*h))
                    .collect(),
            };
            (s, a)
        })
        .collect()
}

/// Exports the current model, checks the document, and compares its evaluations with the
/// server's at 200 random points. Returns the export and the largest relative differences of
/// `μ` and `σ`.
async fn parity(app: &TestApp, id: i64, grid: bool, seed: u64) -> (ExportedModel, f64, f64) {
    parity_predicted(app, id, grid, seed, |_, _| Vec::new()).await
}

/// [`parity`] for features that read the model's prediction, `predict(s, a)` being the
/// experiment's model (which the exported document's reader supplies).
async fn parity_predicted(
    app: &TestApp,
    id: i64,
    grid: bool,
    seed: u64,
    predict: impl Fn(&[f64], &[f64]) -> Vec<f64>,
) -> (ExportedModel, f64, f64) {
    let (status, doc) = app.get_at(id, "model/export").await;
    assert_eq!(status, 200, "{doc}");
    assert_eq!(doc["format"], "precond-model");
    let version = if doc["estimator"] == "local_experts" {
        2
    } else {
        1
    };
    assert_eq!(doc["format_version"], version);
    let model: ExportedModel = serde_json::from_value(doc.clone()).expect("the document reads");
    model.check().expect("the document checks");
    let (_, experiment) = app.get_at(id, "").await;
    assert_eq!(doc["model_version"], experiment["model_version"]);
    assert_eq!(doc["feature_names"], experiment["feature_names"]);
    let points = random_points(&experiment, grid, seed);
    let body: Vec<Value> = points
        .iter()
        .map(|(s, a)| json!({"s": s, "a": a}))
        .collect();
    let (status, answer) = app
        .post_at(id, "precondition", &json!({"points": body}))
        .await;
    assert_eq!(status, 200, "{answer}");
    assert_eq!(answer["model_version"], doc["model_version"]);
    let results = answer["results"].as_array().unwrap();
    let (mut worst_mu, mut worst_sigma, mut worst_resolution) = (0.0f64, 0.0f64, 0.0f64);
    let beta = answer["beta"].as_f64().unwrap();
    for ((s, a), want) in points.iter().zip(results) {
        let s_pred = predict(s, a);
        let (mu, sigma) = model.evaluate_predicted(s, a, &s_pred);
        let (want_mu, want_sigma) = (
            want["mu"].as_f64().unwrap(),
            want["sigma"].as_f64().unwrap(),
        );
        let rel = |got: f64, want: f64| (got - want).abs() / (1.0 + want.abs());
        worst_mu = worst_mu.max(rel(mu, want_mu));
        worst_sigma = worst_sigma.max(rel(sigma, want_sigma));
        // Where σ² = s² − ‖F k‖² + … cancels many digits, σ is only defined to the rounding of
        // that sum, whatever the order it is summed in (the server's own σ of a point differs by
        // as much between a query of one point and a batch): allow that, and 1e-9 beyond it.
        let x = model.feature_map.features(s, a, &s_pred);
        let resolution = variance_rounding(&model.predictor.answering(&x).main, &x)
            / want_sigma.max(f64::MIN_POSITIVE);
        worst_resolution = worst_resolution.max(resolution);
        assert!(
            rel(mu, want_mu) <= TOL
                && (sigma - want_sigma).abs() <= TOL * (1.0 + want_sigma) + resolution,
            "at s = {s:?}, a = {a:?}: exported ({mu}, {sigma}), server ({want_mu}, {want_sigma}), \
             σ resolution {resolution:e}"
        );
        let upper = want["upper"].as_f64().unwrap();
        // The verdict agrees wherever rounding cannot decide it.
        if (upper - model.d_max).abs() > 1e-9 {
            assert_eq!(
                model.inside(s, a, &s_pred, beta),
                want["inside"].as_bool().unwrap()
            );
        }
    }
    // Time per point (reported, not asserted: the machine is shared).
    let mut scratch = precond::mde::export::Scratch::default();
    let started = std::time::Instant::now();
    let mut sink = 0.0;
    for _ in 0..25 {
        for (s, a) in &points {
            sink += model.evaluate_with(s, a, &predict(s, a), &mut scratch).1;
        }
    }
    let per_point = started.elapsed().as_secs_f64() / (25 * points.len()) as f64;
    eprintln!(
        "{} {} (n = {} points): {:.2} µs per evaluation ({sink:.1})",
        doc["estimator"],
        doc["predictor"]["noise"]["kind"],
        model.predictor.points(),
        per_point * 1e6
    );
    if worst_resolution > TOL {
        eprintln!("σ resolved only to {worst_resolution:e} at some point (cancellation)");
    }
    (model, worst_mu, worst_sigma)
}

/// A first-order bound on the rounding error of the latent variance `s² − ‖F k‖² + ‖C k‖²` at
/// features `x`, summed in any order: for each row `t_i = Σ_j F_ij k_j` is off by at most
/// `(i + 1) ε Σ_j |F_ij k_j|`, so `t_i²` by twice that times `|t_i|`, and the sum of squares by
/// `n ε Σ t_i²` more. Two evaluations (the server's, the export's) may differ by twice it.
fn variance_rounding(p: &GpPredictor, x: &[f64]) -> f64 {
    let eps = f64::EPSILON;
    let k: Vec<f64> = p
        .points
        .iter()
        .map(|q| {
            let r2: f64 = q
                .iter()
                .zip(x)
                .zip(&p.length_scales)
                .map(|((a, b), l)| ((a - b) / l).powi(2))
                .sum();
            p.kernel.value(r2, p.signal_variance)
        })
        .collect();
    let n = k.len();
    let mut bound = eps * p.signal_variance;
    for f in [&p.factor, &p.correction].into_iter().flatten() {
        let (mut start, mut squares) = (0, 0.0);
        for i in 0..n {
            let row = &f[start..start + i + 1];
            let t: f64 = row.iter().zip(&k).map(|(a, b)| a * b).sum();
            let spread: f64 = row.iter().zip(&k).map(|(a, b)| (a * b).abs()).sum();
            bound += 2.0 * t.abs() * (i + 1) as f64 * eps * spread;
            squares += t * t;
            start += i + 1;
        }
        bound += n as f64 * eps * squares;
    }
    2.0 * bound
}

/// A kinematic experiment with the `mde` settings and batches of 2, fed two trajectories of
/// `steps` steps: its id and the model fitted on them.
async fn fitted_kinematic(app: &TestApp, mde: Value, steps: usize) -> (i64, Value) {
    let id = app
        .create_experiment(json!({
            "domain": {"kind": "kinematic"},
            "mde": mde,
            "learning": {"batch_size": 2}
        }))
        .await;
    for k in 0..2 {
        app.store_trajectory(id, &kinematic_trajectory(steps, steps * k, k as u64))
            .await;
    }
    (id, app.wait_for_model(id, 2).await)
}

#[tokio::test]
async fn an_exported_exact_gp_answers_as_the_server() {
    let (_dir, app) = fresh_app().await;
    // The default settings: kernel `auto`, heteroscedastic noise, the exact GP.
    let (kinematic, fitted) = fitted_kinematic(&app, json!({"restarts": 0}), 60).await;
    assert_eq!(fitted["estimator"], "exact", "{fitted}");
    assert_eq!(fitted["noise"], "heteroscedastic", "{fitted}");
    assert!(
        !fitted["kernel_trials"].as_array().unwrap().is_empty(),
        "kernel auto: {fitted}"
    );
    let (model, mu, sigma) = parity(&app, kinematic, false, 1).await;
    assert_eq!(model.n_train, 120);
    eprintln!("kinematic, exact, heteroscedastic: worst relative |Δμ| {mu:e}, |Δσ| {sigma:e}");

    for (features, noise) in [("scaled", "homoscedastic"), ("per_move", "heteroscedastic")] {
        let grid = app
            .create_experiment(json!({
                "domain": {"kind": "icy_gridworld", "features": features},
                "mde": {"restarts": 0, "noise": noise},
                "learning": {"batch_size": 3}
            }))
            .await;
        for t in gridworld_trajectories() {
            app.store_trajectory(grid, &t).await;
        }
        app.wait_for_model(grid, 3).await;
        let (_, mu, sigma) = parity(&app, grid, true, 2).await;
        eprintln!("gridworld {features}, exact, {noise}: worst |Δμ| {mu:e}, |Δσ| {sigma:e}");
    }
}

#[tokio::test]
async fn an_export_whose_features_read_the_prediction_answers_as_the_server_given_it() {
    let (_dir, app) = fresh_app().await;
    // A custom domain whose model is "the state moves by the action": its default features
    // read the prediction (where the move ends) and the predicted move's length.
    let id = app
        .create_experiment(json!({
            "domain": {"kind": "custom",
                       "state": {"low": [0, 0], "high": [1, 1]},
                       "action": {"low": [-0.1, -0.1], "high": [0.1, 0.1]},
                       "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]}},
            "mde": {"restarts": 0},
            "learning": {"batch_size": 2}
        }))
        .await;
    let (_, e) = app.get_at(id, "").await;
    assert_eq!(e["domain"]["features"]["prediction"], json!([0, 1]), "{e}");
    assert_eq!(e["domain"]["features"]["move_length"], true);
    for k in 0..2 {
        app.store_trajectory(id, &kinematic_trajectory(60, 60 * k, k as u64))
            .await;
    }
    app.wait_for_model(id, 2).await;
    let clip = |s: &[f64], a: &[f64]| -> Vec<f64> {
        s.iter()
            .zip(a)
            .map(|(x, d)| (x + d).clamp(0.0, 1.0))
            .collect()
    };
    let (model, mu, sigma) = parity_predicted(&app, id, false, 5, clip).await;
    assert!(model.uses_prediction());
    assert_eq!(model.predictor.dim(), 2 + 2 + 1 + 2 + 1);
    // Without the prediction the document answers nothing rather than something wrong.
    assert!(model.evaluate(&[0.5, 0.5], &[0.05, 0.0]).0.is_nan());
    eprintln!("custom, prediction features: worst |Δμ| {mu:e}, |Δσ| {sigma:e}");
}

#[tokio::test]
async fn an_exported_sparse_gp_answers_as_the_server_also_after_online_updates() {
    let (_dir, app) = fresh_app().await;
    for noise in ["homoscedastic", "heteroscedastic"] {
        let mde = json!({"estimator": "sparse", "restarts": 0, "inducing_points": 32,
                         "noise": noise});
        let (id, fitted) = fitted_kinematic(&app, mde, 150).await;
        assert_eq!(fitted["estimator"], "sparse", "{fitted}");
        let (model, mu, sigma) = parity(&app, id, false, 3).await;
        // 300 transitions are within the full-rank size: every distinct input is an inducing
        // point, whatever `inducing_points` says (the low-rank export is a unit test's).
        let points = model.predictor.points();
        assert!((33..=300).contains(&points), "{points} inducing points");
        eprintln!("kinematic, sparse, {noise}: worst |Δμ| {mu:e}, |Δσ| {sigma:e}");
        // One more trajectory is taken in online (no refit): the export follows it.
        app.store_trajectory(id, &kinematic_trajectory(80, 300, 7))
            .await;
        let (_, updated) = app.get_at(id, "model").await;
        assert_eq!(updated["online_trajectories"], 1, "{updated}");
        let (model, mu, sigma) = parity(&app, id, false, 4).await;
        assert_eq!(model.n_train, 380);
        eprintln!("kinematic, sparse, {noise}, updated: worst |Δμ| {mu:e}, |Δσ| {sigma:e}");
    }
}

#[tokio::test]
async fn exported_local_experts_answer_as_the_server_also_after_a_restart() {
    let (_dir, app) = fresh_app().await;
    let mde = json!({"estimator": "local_experts", "expert_size": 60, "restarts": 0});
    let (id, fitted) = fitted_kinematic(&app, mde, 120).await;
    assert_eq!(fitted["estimator"], "local_experts", "{fitted}");
    // Each expert has its own hyperparameters, so the model has none of its own; model
    // selection ran on the experts' own held-out judgements (a label cap per candidate).
    assert!(fitted["hyperparameters"].is_null(), "{fitted}");
    assert!(
        !fitted["label_cap_trials"].as_array().unwrap().is_empty(),
        "{fitted}"
    );
    let (model, mu, sigma) = parity(&app, id, false, 5).await;
    assert_eq!(model.format_version, 2);
    let precond::mde::EstimatorPredictor::Experts(experts) = &model.predictor else {
        panic!("not experts: {:?}", model.estimator);
    };
    // 240 transitions at about 60 each.
    assert!(
        (2..=4).contains(&experts.experts.len()),
        "{}",
        experts.experts.len()
    );
    eprintln!("kinematic, local experts: worst |Δμ| {mu:e}, |Δσ| {sigma:e}");
    // Restored from the store (each expert refactorised on its own rows): the same answers.
    let app = app.restart().await;
    let (_, again) = app.get_at(id, "model").await;
    assert_eq!(again["version"], fitted["version"], "{again}");
    let (restored, ..) = parity(&app, id, false, 5).await;
    assert_eq!(restored.predictor, model.predictor);
}

#[tokio::test]
async fn the_prior_a_bad_version_and_a_missing_one_are_refused() {
    let (_dir, app, id) = fresh_experiment(json!({
        "domain": {"kind": "kinematic"},
        "mde": {"restarts": 0},
        "learning": {"batch_size": 1}
    }))
    .await;
    let export = |q: &str| format!("/v1/experiments/{id}/model/export{q}");
    let (status, body) = app.get(&export("")).await;
    assert_eq!((status, code(&body)), (409, "conflict"), "{body}");
    assert!(message(&body).contains("is the prior"), "{body}");
    let (status, body) = app.get(&export("?version=0")).await;
    assert_eq!((status, code(&body)), (409, "conflict"), "{body}");
    let (status, body) = app.get(&export("?version=-1")).await;
    assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
    assert_eq!(body["error"]["details"]["field"], "version", "{body}");
    let (status, body) = app.get(&export("?version=one")).await;
    assert_eq!((status, code(&body)), (422, "validation_failed"), "{body}");
    assert!(message(&body).contains("version"), "{body}");
    let (status, body) = app.get(&export("?versio=1")).await;
    assert_eq!(status, 422, "an unknown parameter: {body}");
    app.store_trajectory(id, &kinematic_trajectory(20, 0, 0))
        .await;
    app.wait_for_model(id, 1).await;
    let (status, body) = app.get(&export("?version=1")).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["model_version"], 1);
    let (status, body) = app.get(&export("?version=9")).await;
    assert_eq!((status, code(&body)), (404, "not_found"), "{body}");
    let (status, body) = app.get("/v1/experiments/999/model/export").await;
    assert_eq!((status, code(&body)), (404, "not_found"), "{body}");
}
