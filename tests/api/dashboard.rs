//! The dashboard's read endpoints (paged experiments, runs, timeline, precondition map,
//! leave-one-out diagnostics) and its embedded pages.

use crate::helpers::*;
use serde_json::{Value, json};

async fn post_all(app: &TestApp, id: i64, trajectories: &[Value]) -> Vec<Value> {
    let mut out = Vec::new();
    for t in trajectories {
        let body = app.store_trajectory(id, t).await;
        out.push(body);
    }
    out
}

fn ids(page: &Value) -> Vec<i64> {
    ints(&page["items"], "id")
}

#[tokio::test]
async fn experiments_come_in_pages_newest_first_with_their_last_activity() {
    let (_dir, app) = fresh_app().await;
    for name in ["a", "b", "c"] {
        app.create_experiment(json!({"name": name})).await;
    }
    post_all(&app, 1, &[free_row_trajectory(0, 0, 2)]).await;
    let (status, page) = app.get("/v1/experiments?order=newest&limit=2").await;
    assert_eq!(status, 200, "{page}");
    assert_eq!(ids(&page), vec![3, 2]);
    assert_eq!(
        (page["total"].as_i64(), page["next"].as_i64()),
        (Some(3), Some(2))
    );
    let (_, last) = app
        .get("/v1/experiments?order=newest&offset=2&limit=2")
        .await;
    assert_eq!(ids(&last), vec![1]);
    assert!(last["next"].is_null());
    let first = &last["items"][0];
    assert_ne!(first["last_activity"], first["created_at"], "{first}");
    let (_, all) = app.get("/v1/experiments").await;
    assert_eq!(
        ids(&all),
        vec![1, 2, 3],
        "by default every experiment, oldest first"
    );
    assert!(all["next"].is_null());
    let untouched = &all["items"][1];
    assert_eq!(untouched["last_activity"], untouched["created_at"]);
    for (query, field) in [
        ("limit=0", "limit"),
        ("limit=1001", "limit"),
        ("offset=-1", "offset"),
        ("order=sideways", "query"),
    ] {
        let (status, err) = app.get(&format!("/v1/experiments?{query}")).await;
        assert_eq!((status, code(&err)), (422, "validation_failed"), "{query}");
        assert_eq!(err["error"]["details"]["field"], field, "{query}: {err}");
    }
}

#[tokio::test]
async fn runs_list_proposals_and_trajectories_with_their_status() {
    let (_dir, app, id) =
        fresh_experiment(json!({"learning": {"proposal_ttl_seconds": 1, "batch_size": 100}})).await;
    let propose = |client: &str| json!({"start": [0, 0], "goal": [3, 0], "client_id": client});
    let path = format!("/v1/experiments/{id}/proposals");
    let (_, expiring) = app.post(&path, &propose("expiring")).await;
    tokio::time::sleep(std::time::Duration::from_millis(1100)).await;
    let (_, executed) = app.post(&path, &propose("full")).await;
    let mut full = free_row_trajectory(0, 0, 3);
    full["proposal_id"] = executed["id"].clone();
    let (_, partial) = app.post(&path, &propose("stopped")).await;
    let stopped = json!({
        "proposal_id": partial["id"], "partial": true,
        "transitions": [{"s": [3, 2], "a": [1, 0], "s_next": [2, 2]}]
    });
    let posted = post_all(&app, id, &[full, stopped]).await;
    let (_, abandoned) = app.post(&path, &propose("quitter")).await;
    app.post(&format!("{path}/{}/abandon", abandoned["id"]), &json!({}))
        .await;
    let unsolicited = post_all(&app, id, &[free_row_trajectory(5, 1, 4)]).await;
    let (_, open) = app.post(&path, &propose("waiting")).await;
    let (status, page) = app
        .get(&format!("/v1/experiments/{id}/runs?limit=10"))
        .await;
    assert_eq!(status, 200, "{page}");
    assert_eq!(page["total"], 6);
    assert!(page["next"].is_null());
    let items = page["items"].as_array().unwrap();
    let status_of: Vec<&str> = items
        .iter()
        .map(|r| r["status"].as_str().unwrap())
        .collect();
    assert_eq!(
        status_of,
        [
            "open",
            "unsolicited",
            "abandoned",
            "partial",
            "executed",
            "expired"
        ],
        "newest first: {page}"
    );
    assert_eq!(items[0]["proposal_id"], open["id"]);
    assert!(items[0]["trajectory_id"].is_null());
    assert_eq!(
        items[0]["length"].as_u64().unwrap() as usize,
        open["trajectory"]["actions"].as_array().unwrap().len()
    );
    assert_eq!(items[1]["trajectory_id"], unsolicited[0]["id"]);
    assert!(items[1]["proposal_id"].is_null() && items[1]["client_id"].is_null());
    assert_eq!(
        (
            items[1]["length"].as_i64(),
            items[1]["max_deviation"].as_f64()
        ),
        (Some(4), Some(0.0))
    );
    assert_eq!(items[3]["client_id"], "stopped");
    assert_eq!(items[3]["partial"], true);
    // From the ice cell (3, 2) the right move ends at (2, 2): two cells from (4, 2).
    assert_eq!(items[3]["max_deviation"], posted[1]["deviations"][0]);
    assert_eq!(items[3]["max_deviation"], 2.0);
    assert_eq!(items[4]["trajectory_id"], posted[0]["id"]);
    assert_eq!(items[5]["proposal_id"], expiring["id"]);
    let (_, second) = app
        .get(&format!("/v1/experiments/{id}/runs?offset=4&limit=1"))
        .await;
    assert_eq!(second["items"][0]["status"], "executed");
    assert_eq!(second["next"], 5);
    let (status, _) = app.get("/v1/experiments/99/runs").await;
    assert_eq!(status, 404);
}

#[tokio::test]
async fn the_timeline_has_each_iteration_with_its_beta_and_each_model_version() {
    let (_dir, app, id) = fresh_experiment(json!({
        "mde": {"restarts": 0},
        "learning": {"batch_size": 2, "iterations": 4, "k1": 2.0, "k2": 0.5}
    }))
    .await;
    let trajectories = gridworld_moves(0..5, 40);
    post_all(&app, id, &trajectories[..5]).await;
    let refit = app.refit(id).await;
    let (status, t) = app.get_at(id, "timeline").await;
    assert_eq!(status, 200, "{t}");
    assert_eq!(
        (t["batch_size"].as_i64(), t["iterations_planned"].as_i64()),
        (Some(2), Some(4))
    );
    let iterations = t["iterations"].as_array().unwrap();
    assert_eq!(ints(&t["iterations"], "n_trajectories"), vec![2, 2, 1]);
    for (j, r) in iterations.iter().enumerate() {
        assert_eq!(r["iteration"], j as i64);
        let beta = 2.0 * 2.0 / (1.0 + (-0.5 * (j as f64 - 2.0)).exp()) - 2.0;
        assert!((r["beta"].as_f64().unwrap() - beta).abs() < 1e-12, "{r}");
        let share = r["share_within_d_max"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&share));
    }
    let total: i64 = ints(&t["iterations"], "n_transitions").iter().sum();
    assert_eq!(total, 5 * 40);
    let models = t["models"].as_array().unwrap();
    let last = models.last().expect("a version");
    assert_eq!(last["version"], refit["version"]);
    assert_eq!(last["n_train"], refit["n_train"]);
    assert_eq!(last["iteration"], 2);
    assert!(
        last["log_marginal_likelihood"]
            .as_f64()
            .unwrap()
            .is_finite()
    );
}

#[tokio::test]
async fn the_precondition_map_evaluates_any_version_on_a_grid() {
    let (_dir, app, id) =
        fresh_experiment(json!({"mde": {"restarts": 0}, "learning": {"batch_size": 1000}})).await;
    let map = |query: &str| format!("/v1/experiments/{id}/precondition/map?{query}");
    let (status, prior) = app.get(&map("x=s.x&y=s.y&nx=12&ny=12&a=1,0")).await;
    assert_eq!(status, 200, "{prior}");
    assert_eq!(
        (prior["model_version"].as_i64(), prior["source"].as_str()),
        (Some(0), Some("prior"))
    );
    assert!(prior["mu"].as_array().unwrap().iter().all(|m| m == 0.0));
    assert!(prior["sigma"].as_array().unwrap().iter().all(|s| s == 1.0));
    post_all(&app, id, &gridworld_moves(0..3, 40)).await;
    let v1 = app.refit(id).await;
    post_all(&app, id, &gridworld_moves(3..6, 40)).await;
    let v2 = app.refit(id).await;
    assert_eq!(
        (v1["version"].as_i64(), v2["version"].as_i64()),
        (Some(1), Some(2))
    );
    let (status, now) = app.get(&map("x=s.x&y=s.y&nx=12&ny=12&a=1,0")).await;
    assert_eq!(status, 200, "{now}");
    assert_eq!(now["model_version"], 2);
    let xs: Vec<f64> = serde_json::from_value(now["x"]["values"].clone()).unwrap();
    assert_eq!(xs, (0..12).map(f64::from).collect::<Vec<_>>());
    assert_eq!(now["mu"].as_array().unwrap().len(), 144);
    // Cell (x=4, y=2) moving right: the grid agrees with a precondition query.
    let (_, judged) = app
        .get(&format!("/v1/experiments/{id}/precondition?s=4,2&a=1,0"))
        .await;
    let k = 2 * 12 + 4;
    for field in ["mu", "sigma"] {
        let grid = now[field][k].as_f64().unwrap();
        let point = judged["results"][0][field].as_f64().unwrap();
        assert!((grid - point).abs() < 1e-9, "{field}: {grid} vs {point}");
    }
    assert_eq!(
        now["training"].as_array().unwrap().len(),
        v2["n_train"].as_u64().unwrap() as usize
    );
    // Version 1, rebuilt from the store: its own training set, other answers.
    let (status, old) = app
        .get(&map("x=s.x&y=s.y&nx=12&ny=12&a=1,0&version=1"))
        .await;
    assert_eq!(status, 200, "{old}");
    assert_eq!(
        (old["model_version"].as_i64(), old["n_train"].as_u64()),
        (Some(1), v1["n_train"].as_u64())
    );
    assert_eq!(
        old["training"].as_array().unwrap().len(),
        v1["n_train"].as_u64().unwrap() as usize
    );
    assert_ne!(old["mu"], now["mu"]);
    let (_, again) = app
        .get(&map("x=s.x&y=s.y&nx=12&ny=12&a=1,0&version=1"))
        .await;
    assert_eq!(again["mu"], old["mu"], "a kept version answers the same");
    let (status, err) = app.get(&map("x=s.x&y=s.y&version=7")).await;
    assert_eq!((status, code(&err)), (404, "not_found"), "{err}");
    for (query, field) in [
        ("x=s.z&y=s.y", "x"),
        ("x=s.x&y=s.x", "y"),
        ("x=s.x&y=a.dx&nx=1", "nx"),
        ("x=s.x&y=s.y&ny=201", "ny"),
        ("x=s.x&y=s.y&s=1", "s"),
        ("x=s.x&y=s.y&a=1,nan", "a"),
        ("x=s.x", "query"),
    ] {
        let (status, err) = app.get(&map(query)).await;
        assert_eq!(
            (status, code(&err)),
            (422, "validation_failed"),
            "{query}: {err}"
        );
        assert_eq!(err["error"]["details"]["field"], field, "{query}: {err}");
    }
}

#[tokio::test]
async fn diagnostics_check_a_fit_by_leave_one_out() {
    let (_dir, app, id) =
        fresh_experiment(json!({"mde": {"restarts": 0}, "learning": {"batch_size": 1000}})).await;
    let path = format!("/v1/experiments/{id}/model/diagnostics");
    let (status, err) = app.get(&path).await;
    assert_eq!(
        (status, code(&err)),
        (409, "conflict"),
        "the prior has no labels: {err}"
    );
    post_all(&app, id, &gridworld_moves(0..4, 40)).await;
    let model = app.refit(id).await;
    let (status, d) = app.get(&format!("{path}?beta=2")).await;
    assert_eq!(status, 200, "{d}");
    assert_eq!(d["method"], "leave_one_out");
    assert_eq!(d["n"], model["n_train"]);
    let coverage = d["coverage"].as_array().unwrap();
    assert_eq!(coverage.len(), 6);
    let observed = floats(&d["coverage"], "observed");
    assert!(observed.windows(2).all(|w| w[0] <= w[1]), "{observed:?}");
    assert!(observed.iter().all(|o| (0.0..=1.0).contains(o)));
    assert!((coverage[1]["nominal"].as_f64().unwrap() - 0.6827).abs() < 1e-4);
    let p = &d["precondition"];
    assert_eq!(p["beta"], 2.0);
    let n = d["n"].as_u64().unwrap();
    assert_eq!(
        p["positives"].as_u64().unwrap() + p["negatives"].as_u64().unwrap(),
        n
    );
    // Rows 0..4 hold ice (rows 2 and 3): both kinds of label are there.
    assert!(p["negatives"].as_u64().unwrap() > 0 && p["positives"].as_u64().unwrap() > 0);
    for rate in ["tpr", "tnr"] {
        assert!((0.0..=1.0).contains(&p[rate].as_f64().unwrap()), "{p}");
    }
    assert!(d["later"].is_null(), "the fit saw every transition: {d}");
    // Transitions posted after the fit are judged by it as they are: never seen, not refitted.
    post_all(&app, id, &gridworld_moves(4..6, 40)).await;
    let (_, d) = app.get(&format!("{path}?beta=2")).await;
    let later = &d["later"];
    assert_eq!(later["n"], 2 * 12 * 4, "{d}");
    assert_eq!(
        later["positives"].as_u64().unwrap() + later["negatives"].as_u64().unwrap(),
        2 * 12 * 4
    );
    // The same judgements through the precondition query (the model was not refitted).
    let n_train = model["n_train"].as_u64().unwrap() as usize;
    let unseen: Vec<Value> = app.all_transitions(id).await.split_off(n_train);
    let points: Vec<Value> = unseen
        .iter()
        .map(|t| json!({"s": t["s"], "a": t["a"]}))
        .collect();
    let (_, judged) = app
        .post_at(id, "precondition", &json!({"points": points, "beta": 2.0}))
        .await;
    let (mut tp, mut tn) = (0, 0);
    for (t, j) in unseen.iter().zip(judged["results"].as_array().unwrap()) {
        let positive = t["deviation"].as_f64().unwrap() < 0.1;
        let inside = j["inside"].as_bool().unwrap();
        tp += u64::from(positive && inside);
        tn += u64::from(!positive && !inside);
    }
    assert_eq!(
        (
            later["true_positives"].as_u64(),
            later["true_negatives"].as_u64()
        ),
        (Some(tp), Some(tn))
    );
    assert_eq!(
        d["n"], model["n_train"],
        "leave-one-out still checks the training set"
    );
    let (status, err) = app.get(&format!("{path}?beta=x")).await;
    assert_eq!((status, code(&err)), (422, "validation_failed"), "{err}");
    let (status, _) = app.get(&format!("{path}?version=5")).await;
    assert_eq!(status, 404);
}

#[tokio::test]
async fn the_dashboard_is_served_from_the_binary() {
    let (_dir, app) = fresh_app().await;
    for path in ["/", "/ui", "/ui/experiments/3", "/ui/experiments/3/map"] {
        let r = app.client.get(app.url(path)).send().await.unwrap();
        assert_eq!(r.status(), 200, "{path}");
        assert!(
            r.headers()["content-type"]
                .to_str()
                .unwrap()
                .starts_with("text/html")
        );
        assert!(r.headers().contains_key("content-security-policy"));
        let body = r.text().await.unwrap();
        assert!(body.contains(r#"src="/ui/assets/app.js""#), "{path}");
    }
    // The stylesheet, the entry module and every module reachable by its imports (`from './x.js'`):
    // a new module missing from the embedded assets fails here.
    let mut queue = vec!["style.css".to_string(), "app.js".to_string()];
    let mut served = std::collections::BTreeSet::new();
    while let Some(asset) = queue.pop() {
        if !served.insert(asset.clone()) {
            continue;
        }
        let r = app
            .client
            .get(app.url(&format!("/ui/assets/{asset}")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "{asset}");
        let kind = if asset.ends_with(".css") {
            "text/css"
        } else {
            "text/javascript"
        };
        assert!(
            r.headers()["content-type"]
                .to_str()
                .unwrap()
                .starts_with(kind),
            "{asset}"
        );
        let body = r.text().await.unwrap();
        for import in body.split("from './").skip(1) {
            queue.push(import.split('\'').next().unwrap().to_string());
        }
    }
    for module in [
        "app.js",
        "api.js",
        "dom.js",
        "format.js",
        "pages.js",
        "charts.js",
    ] {
        assert!(served.contains(module), "{module} in {served:?}");
    }
    let (status, err) = app.get("/ui/assets/missing.js").await;
    assert_eq!((status, code(&err)), (404, "not_found"));
}

#[tokio::test]
async fn only_configured_origins_may_read_the_api_from_a_browser() {
    let (_dir, app) = fresh_app_with(precond::http::HttpConfig {
        cors_allow_origins: vec!["http://lab-pc:8080".into()],
        ..Default::default()
    })
    .await;
    for (origin, allowed) in [("http://lab-pc:8080", true), ("http://evil.example", false)] {
        let r = app
            .client
            .get(app.url("/v1/experiments"))
            .header("origin", origin)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        let allow = r.headers().get("access-control-allow-origin");
        assert_eq!(
            allow.map(|v| v.to_str().unwrap()),
            allowed.then_some(origin),
            "{origin}"
        );
    }
    let (status, _) = app.get("/v1/experiments").await;
    assert_eq!(status, 200, "same-origin requests need no CORS");
    // The dashboard pointed at this server with `?api=` sends its token: the preflight from the
    // allowed origin lets `Authorization` through; a foreign origin's gets no grant.
    for (origin, allowed) in [("http://lab-pc:8080", true), ("http://evil.example", false)] {
        let r = app
            .client
            .request(reqwest::Method::OPTIONS, app.url("/v1/experiments"))
            .header("origin", origin)
            .header("access-control-request-method", "POST")
            .header(
                "access-control-request-headers",
                "authorization,content-type",
            )
            .send()
            .await
            .unwrap();
        let header = |name: &str| {
            r.headers()
                .get(name)
                .map(|v| v.to_str().unwrap().to_ascii_lowercase())
        };
        if allowed {
            let headers = header("access-control-allow-headers").unwrap_or_default();
            assert!(
                headers.contains("authorization") && headers.contains("content-type"),
                "{headers}"
            );
            assert_eq!(
                header("access-control-allow-origin").as_deref(),
                Some(origin)
            );
        } else {
            assert_eq!(header("access-control-allow-origin"), None, "{origin}");
        }
    }
}
