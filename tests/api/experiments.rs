use crate::helpers::*;
use serde_json::{Value, json};

#[tokio::test]
async fn health_and_readiness_answer() {
    let (_dir, app) = fresh_app().await;
    assert_eq!(app.get("/healthz").await, (200, json!({"status": "ok"})));
    assert_eq!(app.get("/readyz").await, (200, json!({"status": "ready"})));
}

#[tokio::test]
async fn an_empty_request_resolves_every_default() {
    let (_dir, app) = fresh_app().await;
    let (status, e) = app.post("/v1/experiments", &json!({})).await;
    assert_eq!(status, 201, "{e}");
    assert_eq!(e["domain"]["kind"], "icy_gridworld");
    assert_eq!(e["domain"]["map"].as_array().unwrap().len(), 12);
    assert_eq!(e["d_max"], 0.1);
    assert_eq!(e["mde"]["noise"], "heteroscedastic");
    assert_eq!(e["learning"]["strategy"], "active");
    assert_eq!(e["learning"]["batch_size"], 5);
    assert_eq!(e["learning"]["k2"], 0.5);
    assert_eq!(e["learning"]["preset"], "default");
    assert_eq!(e["mde"]["label_cap"], "auto");
    assert_eq!(e["mde"]["kernel"], "auto");
    assert_eq!(e["mde"]["estimator"], "auto");
    assert_eq!(e["learning"]["relax_beta"], true);
    assert_eq!(e["learning"]["batch_diversity"], false);
    assert_eq!(e["state_space"]["names"], json!(["x", "y"]));
    assert_eq!(e["action_space"]["values"].as_array().unwrap().len(), 4);
    let (status, listed) = app.get("/v1/experiments").await;
    assert_eq!(status, 200);
    assert_eq!(listed["items"][0]["id"], e["id"]);
    let (status, one) = app.get(&format!("/v1/experiments/{}", e["id"])).await;
    assert_eq!(status, 200);
    assert_eq!(one["learning"], e["learning"]);
}

/// Creates an experiment from each request body and asserts that it is created (201) with the
/// setting at `section.field` resolved as paired.
async fn assert_resolves(app: &TestApp, section: &str, field: &str, cases: &[(Value, Value)]) {
    for (body, expected) in cases {
        let (status, e) = app.post("/v1/experiments", body).await;
        assert_eq!(status, 201, "{e}");
        assert_eq!(&e[section][field], expected, "{body}");
    }
}

#[tokio::test]
async fn the_paper_preset_fits_raw_labels_with_the_smooth_kernel_and_never_relaxes_unless_told_otherwise()
 {
    let (_dir, app) = fresh_app().await;
    let cases = [
        (json!({"learning": {"preset": "paper"}}), json!(0.0)),
        (
            json!({"learning": {"preset": "paper"}, "mde": {"label_cap": 3}}),
            json!(3.0),
        ),
        (json!({"mde": {"label_cap": 0}}), json!(0.0)),
        (
            json!({"learning": {"preset": "paper"}, "mde": {"label_cap": "auto"}}),
            json!("auto"),
        ),
    ];
    assert_resolves(&app, "mde", "label_cap", &cases).await;
    let cases = [
        (json!({"learning": {"preset": "paper"}}), json!("matern52")),
        (
            json!({"learning": {"preset": "paper"}, "mde": {"kernel": "matern12"}}),
            json!("matern12"),
        ),
        (json!({"mde": {"kernel": "matern32"}}), json!("matern32")),
        (json!({"mde": {"kernel": null}}), json!("auto")),
        (json!({"mde": {"kernel": "auto"}}), json!("auto")),
    ];
    assert_resolves(&app, "mde", "kernel", &cases).await;
    let cases = [
        (json!({"learning": {"preset": "paper"}}), json!(false)),
        (
            json!({"learning": {"preset": "paper", "relax_beta": true}}),
            json!(true),
        ),
        (json!({"learning": {"relax_beta": false}}), json!(false)),
    ];
    assert_resolves(&app, "learning", "relax_beta", &cases).await;
    let cases = [
        (json!({"learning": {"preset": "paper"}}), json!(false)),
        (
            json!({"learning": {"preset": "paper", "batch_diversity": true}}),
            json!(true),
        ),
        (json!({"learning": {"batch_diversity": true}}), json!(true)),
        (json!({"learning": {}}), json!(false)),
    ];
    assert_resolves(&app, "learning", "batch_diversity", &cases).await;
    let cases = [
        (json!({"learning": {"preset": "paper"}}), json!(0)),
        (json!({"learning": {}}), json!(0)),
        (
            json!({"learning": {"preset": "paper", "warmup_iterations": 2}}),
            json!(2),
        ),
        (json!({"learning": {"warmup_iterations": 1}}), json!(1)),
        (json!({"learning": {"warmup_iterations": null}}), json!(0)),
    ];
    assert_resolves(&app, "learning", "warmup_iterations", &cases).await;
    // The acquisition: `bottleneck` on a graph, `spread` in a continuous domain, the paper's
    // `lcb` under its preset or when asked.
    let kinematic = json!({"kind": "kinematic"});
    let cases = [
        (json!({}), json!("bottleneck")),
        (json!({"domain": kinematic}), json!("spread")),
        (
            json!({"domain": kinematic, "learning": {"preset": "paper"}}),
            json!("lcb"),
        ),
        (
            json!({"domain": kinematic, "learning": {"acquisition": "lcb"}}),
            json!("lcb"),
        ),
        (
            json!({"learning": {"acquisition": "spread"}}),
            json!("spread"),
        ),
    ];
    assert_resolves(&app, "learning", "acquisition", &cases).await;
    // More random iterations than the schedule plans is refused by name.
    let (status, e) = app
        .post(
            "/v1/experiments",
            &json!({"learning": {"iterations": 3, "warmup_iterations": 4}}),
        )
        .await;
    assert_eq!(status, 422, "{e}");
    assert!(e.to_string().contains("learning.warmup_iterations"), "{e}");
}

#[tokio::test]
async fn a_kinematic_experiment_shows_its_spaces() {
    let (_dir, app) = fresh_app().await;
    let (status, e) = app
        .post(
            "/v1/experiments",
            &json!({"domain": {"kind": "kinematic", "state_low": [0, 0, 0], "state_high": [1, 2, 3],
                    "action_low": [-0.1, -0.1, -0.1], "action_high": [0.1, 0.1, 0.1]}}),
        )
        .await;
    assert_eq!(status, 201, "{e}");
    assert_eq!(e["state_space"]["high"], json!([1.0, 2.0, 3.0]));
    assert!(e["action_space"].get("values").is_none());
    // The state, the action, the model's prediction and the length of its move, unless told
    // otherwise.
    assert_eq!(e["domain"]["features"], "state_action_prediction_length");
    assert_eq!(e["feature_names"].as_array().unwrap().len(), 10);
    assert_eq!(e["feature_names"][6], "predicted_x0");
    assert_eq!(e["feature_names"][9], "predicted_move_length");
    // The other maps, on the default 2-D square.
    for (features, dim) in [("state_action_prediction", 6), ("state_action", 4)] {
        let (status, e) = app
            .post(
                "/v1/experiments",
                &json!({"domain": {"kind": "kinematic", "features": features}}),
            )
            .await;
        assert_eq!(status, 201, "{e}");
        assert_eq!(
            e["feature_names"].as_array().unwrap().len(),
            dim,
            "{features}"
        );
    }
}

#[tokio::test]
async fn bad_settings_name_the_field() {
    let (_dir, app) = fresh_app().await;
    let cases = [
        (json!({"learning": {"gamma": 2.0}}), "learning.gamma"),
        (
            json!({"learning": {"batch_size": 0}}),
            "learning.batch_size",
        ),
        (json!({"d_max": -1}), "d_max"),
        (json!({"mde": {"noise": "loud"}}), "mde.noise"),
        (json!({"mde": {"label_cap": 0.5}}), "mde.label_cap"),
        (json!({"mde": {"label_cap": -1}}), "mde.label_cap"),
        (json!({"mde": {"label_cap": "max"}}), "mde.label_cap"),
        (json!({"mde": {"kernel": "rbf"}}), "mde.kernel"),
        (
            json!({"mde": {"selection_subset": 100}}),
            "mde.selection_subset",
        ),
        (json!({"learning": {"preset": "cmax"}}), "learning.preset"),
        (json!({"learning": {"bogus": 1}}), "learning.bogus"),
        (
            json!({"domain": {"kind": "icy_gridworld", "map": ["..", "."]}}),
            "domain.map",
        ),
        (
            json!({"domain": {"kind": "kinematic", "goal_radius": 0}}),
            "domain.goal_radius",
        ),
        (
            json!({"domain": {"kind": "kinematic", "features": "next"}}),
            "domain",
        ),
        (json!({"domain": {"kind": "moon"}}), "domain"),
    ];
    for (body, field) in cases {
        let (status, err) = app.post("/v1/experiments", &body).await;
        assert_eq!(status, 422, "{body} -> {err}");
        assert_eq!(code(&err), "validation_failed");
        let got = err["error"]["details"]["field"].as_str().unwrap();
        assert!(
            got.starts_with(field),
            "{body}: field {got}, expected {field}"
        );
    }
    // A kinematic domain's fields reach serde's error only as `domain`: the reason names it.
    let (_, err) = app
        .post(
            "/v1/experiments",
            &json!({"domain": {"kind": "kinematic", "features": "next"}}),
        )
        .await;
    let reason = err["error"]["details"]["reason"].as_str().unwrap();
    assert!(reason.starts_with("features: \"next\""), "{reason}");
    let (_, listed) = app.get("/v1/experiments").await;
    assert!(
        listed["items"].as_array().unwrap().is_empty(),
        "nothing stored"
    );
}

/// Settings whose arithmetic overflows made an experiment panic (±1e308 bounds: a width of
/// 2e308 to sample in; a prior mean of 1e308: an infinite target scale) or unusable (`k1`
/// 1e308: every β infinite); they are refused at creation, naming the field and the bound.
#[tokio::test]
async fn settings_whose_arithmetic_overflows_are_refused_with_the_bound() {
    let (_dir, app) = fresh_app().await;
    let huge = [-1e308, -1e308];
    let plane = |extra: serde_json::Value| {
        let mut d = json!({"kind": "custom", "state": {"low": [0, 0], "high": [1, 1]},
            "action": {"low": [-0.1, -0.1], "high": [0.1, 0.1]},
            "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]}});
        for (k, v) in extra.as_object().unwrap() {
            d[k] = v.clone();
        }
        json!({ "domain": d })
    };
    let cases = [
        (
            json!({"domain": {"kind": "kinematic", "state_low": huge, "state_high": [1e308, 1e308],
                              "action_low": huge, "action_high": [1e308, 1e308]}}),
            "domain.state_low[0]",
        ),
        (
            json!({"domain": {"kind": "kinematic", "action_high": [1e13, 0.1]}}),
            "domain.action_high[0]",
        ),
        (
            json!({"domain": {"kind": "kinematic", "goal_radius": 1e300}}),
            "domain.goal_radius",
        ),
        (
            json!({"domain": {"kind": "kinematic",
                              "obstacles": [{"low": [0.1, 0.1], "high": [0.2, 1e300]}]}}),
            "domain.obstacles[0].high[1]",
        ),
        (json!({"mde": {"prior_mean": 1e308}}), "mde.prior_mean"),
        (json!({"mde": {"prior_mean": -1e308}}), "mde.prior_mean"),
        (json!({"learning": {"k1": 1e308}}), "learning.k1"),
        (json!({"learning": {"k2": 1e308}}), "learning.k2"),
        (json!({"learning": {"c": 1e308}}), "learning.c"),
        (
            json!({"learning": {"test_beta": -1e308}}),
            "learning.test_beta",
        ),
        (
            plane(json!({"state": {"low": [-1e308, 0], "high": [1e308, 1]}})),
            "domain.state.low[0]",
        ),
        (
            plane(json!({"distance": {"weights": [1e300, 1]}})),
            "domain.distance.weights[0]",
        ),
        (
            plane(
                json!({"model": {"kind": "linear", "A": [[1e300, 0], [0, 1]],
                                   "B": [[1, 0], [0, 1]]}}),
            ),
            "domain.model.A[0][0]",
        ),
    ];
    for (body, field) in cases {
        let (status, err) = app.post("/v1/experiments", &body).await;
        assert_eq!(
            (status, code(&err)),
            (422, "validation_failed"),
            "{body} -> {err}"
        );
        assert_eq!(err["error"]["details"]["field"], field, "{body}: {err}");
        let reason = reason(&err);
        assert!(
            reason.contains("at most 1e") || reason.contains("finite"),
            "{body}: the reason says the bound: {reason}"
        );
    }
    // At the bounds, everything works: creation, an ingest, a refit and a proposal.
    let id = app
        .create_experiment(json!({
            "domain": {"kind": "kinematic", "state_low": [-1e12, -1e12], "state_high": [1e12, 1e12],
                       "action_low": [-1e12, -1e12], "action_high": [1e12, 1e12]},
            "mde": {"prior_mean": 1e12, "noise": "homoscedastic", "restarts": 1},
            "learning": {"k1": 1e6, "batch_size": 100}}))
        .await;
    app.store_trajectory(
        id,
        &json!({"transitions": [{"s": [0, 0], "a": [1e11, 0], "s_next": [1e11, 5e10]},
                                    {"s": [1e11, 5e10], "a": [-1e11, 1e11], "s_next": [0, 1e11]}]}),
    )
    .await;
    let (status, body) = app.post_at(id, "model/refit", &json!({})).await;
    assert!(status == 200 || status == 202, "{status} {body}");
    let (status, body) = app
        .propose(id, &json!({"start": [0, 0], "goal": [9e11, 9e11]}))
        .await;
    assert!(
        status == 201 || (status == 422 && code(&body) == "no_plan"),
        "{status} {body}"
    );
}

/// Names and client ids end up in terminals, logs and CSV exports: control characters and
/// bidirectional overrides in them are refused, the field named.
#[tokio::test]
async fn control_characters_in_names_and_client_ids_are_refused() {
    let (_dir, app) = fresh_app().await;
    for name in ["a\u{0}b", "\u{1b}[2J", "evil\u{202e}txt.exe", "two\nlines"] {
        let (status, err) = app.post("/v1/experiments", &json!({ "name": name })).await;
        assert_eq!((status, code(&err)), (422, "validation_failed"), "{err}");
        assert_eq!(err["error"]["details"]["field"], "name");
    }
    let custom = json!({"domain": {"kind": "custom",
        "state": {"names": ["x", "y\u{1b}"], "low": [0, 0], "high": [1, 1]},
        "action": {"low": [-0.1, -0.1], "high": [0.1, 0.1]},
        "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]}}});
    let (status, err) = app.post("/v1/experiments", &custom).await;
    assert_eq!(status, 422, "{err}");
    assert_eq!(err["error"]["details"]["field"], "domain.state.names[1]");
    let (_, listed) = app.get("/v1/experiments").await;
    assert_eq!(listed["total"], 0, "nothing stored: {listed}");

    let id = app
        .create_experiment(json!({"name": "Bench 2 — arm ü"}))
        .await;
    let (status, err) = app
        .propose(
            id,
            &json!({"start": [0, 0], "goal": [2, 0], "client_id": "\u{0}\n\r\u{1b}"}),
        )
        .await;
    assert_eq!((status, code(&err)), (422, "validation_failed"), "{err}");
    assert_eq!(err["error"]["details"]["field"], "client_id");
    app.assert_proposes(
        id,
        &json!({"start": [0, 0], "goal": [2, 0], "client_id": "robot-ü 1"}),
    )
    .await;
}

#[tokio::test]
async fn unknown_things_are_404_in_the_error_shape() {
    let (_dir, app) = fresh_app().await;
    for path in [
        "/v1/experiments/42",
        "/v1/experiments/abc",
        "/nope",
        "/v1/experiments/42/transitions",
    ] {
        let (status, err) = app.get(path).await;
        assert_eq!(status, 404, "{path}");
        assert_eq!(code(&err), "not_found", "{path}");
        assert!(err["error"]["message"].is_string());
    }
    let r = app
        .request(reqwest::Method::DELETE, "/v1/experiments")
        .await;
    assert_eq!(r.status().as_u16(), 405);
    let body: serde_json::Value = r.json().await.unwrap();
    assert_eq!(code(&body), "method_not_allowed");
}
