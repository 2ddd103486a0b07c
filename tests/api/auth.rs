//! Access tokens gate every route but the health checks.

use crate::helpers::*;
use precond::http::HttpConfig;
use precond::http::auth::TokenTable;
use serde_json::{Value, json};
use sha2::{Digest, Sha256};
use std::sync::Arc;

const ADMIN: &str = "admin-token-0123456789";
const WRITER: &str = "writer-token-0123456789";
const READER: &str = "reader-token-0123456789";
const SCOPED: &str = "scoped-token-0123456789";

async fn app_with_tokens(db: &std::path::Path, scoped_to: i64) -> TestApp {
    let file =
        format!("{ADMIN} admin *\n{WRITER} write\n{READER} read *\n{SCOPED} write {scoped_to}\n");
    let config = HttpConfig {
        tokens: Some(Arc::new(TokenTable::parse(&file).unwrap())),
        ..HttpConfig::default()
    };
    spawn_app_with(db, config).await
}

async fn call(
    app: &TestApp,
    method: &str,
    path: &str,
    token: Option<&str>,
    body: Option<Value>,
) -> (u16, Value) {
    let mut r = app.client.request(method.parse().unwrap(), app.url(path));
    if let Some(t) = token {
        r = r.bearer_auth(t);
    }
    if let Some(b) = body {
        r = r.json(&b);
    }
    let r = r.send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

#[tokio::test]
async fn health_routes_stay_open_and_everything_else_needs_a_known_token() {
    let (_dir, db) = temp_db();
    let app = app_with_tokens(&db, 1).await;
    assert_eq!(call(&app, "GET", "/healthz", None, None).await.0, 200);
    assert_eq!(call(&app, "GET", "/readyz", None, None).await.0, 200);
    for token in [None, Some("not-a-token-0123456789"), Some("")] {
        let (status, body) = call(&app, "GET", "/v1/experiments", token, None).await;
        assert_eq!(status, 401, "{token:?}: {body}");
        assert_eq!(code(&body), "unauthorized");
    }
    let r = app.request(reqwest::Method::GET, "/v1/experiments").await;
    assert_eq!(r.headers()["www-authenticate"], "Bearer");
    // Basic credentials are not a bearer token.
    let r = app
        .client
        .get(app.url("/v1/experiments"))
        .basic_auth(READER, None::<&str>)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 401);
}

#[tokio::test]
async fn the_dashboard_pages_are_open_and_its_api_calls_need_a_token() {
    let (_dir, db) = temp_db();
    let app = app_with_tokens(&db, 1).await;
    for path in ["/", "/ui/experiments"] {
        let r = app.client.get(app.url(path)).send().await.unwrap();
        assert_eq!(r.status().as_u16(), 200, "{path}");
        assert!(r.text().await.unwrap().contains("<html"), "{path}");
    }
    assert_eq!(
        call(&app, "GET", "/v1/experiments", None, None).await.0,
        401
    );
    assert_eq!(
        call(&app, "GET", "/v1/experiments", Some(READER), None)
            .await
            .0,
        200
    );
}

#[tokio::test]
async fn each_role_reaches_its_routes_and_no_further() {
    let (_dir, db) = temp_db();
    let app = app_with_tokens(&db, 1).await;
    let create = Some(json!({}));
    for t in [READER, WRITER] {
        let (status, body) = call(&app, "POST", "/v1/experiments", Some(t), create.clone()).await;
        assert_eq!(status, 403, "{body}");
        assert_eq!(code(&body), "forbidden");
    }
    let (status, e) = call(&app, "POST", "/v1/experiments", Some(ADMIN), create).await;
    assert_eq!(status, 201, "{e}");
    let id = e["id"].as_i64().unwrap();
    let traj = free_row_trajectory(0, 0, 2);
    let point = json!({"points": [{"s": [0, 0], "a": [1, 0]}]});
    let plan = json!({"start": [0, 0], "goal": [1, 0]});
    // Reads, precondition queries and plans: read.
    for (method, path, body) in [
        ("GET", format!("/v1/experiments/{id}"), None),
        ("GET", format!("/v1/experiments/{id}/model"), None),
        (
            "POST",
            format!("/v1/experiments/{id}/precondition"),
            Some(point),
        ),
        ("POST", format!("/v1/experiments/{id}/plans"), Some(plan)),
    ] {
        let (status, body) = call(&app, method, &path, Some(READER), body).await;
        assert!(
            status != 401 && status != 403,
            "{method} {path}: {status} {body}"
        );
    }
    // Posting a trajectory: write.
    let path = format!("/v1/experiments/{id}/trajectories");
    let (status, _) = call(&app, "POST", &path, Some(READER), Some(traj.clone())).await;
    assert_eq!(status, 403);
    let (status, body) = call(&app, "POST", &path, Some(WRITER), Some(traj)).await;
    assert_eq!(status, 201, "{body}");
    // Refits: admin.
    let path = format!("/v1/experiments/{id}/model/refit");
    assert_eq!(call(&app, "POST", &path, Some(WRITER), None).await.0, 403);
    let (status, body) = call(&app, "POST", &path, Some(ADMIN), None).await;
    assert_eq!(status, 200, "{body}");
    // Exclusions: admin, recorded with the caller's token fingerprint (a second trajectory:
    // excluding the only one would leave nothing to fit).
    let more = free_row_trajectory(0, 1, 2);
    let path = format!("/v1/experiments/{id}/trajectories");
    let (status, body) = call(&app, "POST", &path, Some(WRITER), Some(more)).await;
    assert_eq!(status, 201, "{body}");
    let path = format!("/v1/experiments/{id}/exclusions");
    let exclude = json!({"trajectory_id": 1, "reason": "a bad run"});
    let (status, _) = call(&app, "POST", &path, Some(WRITER), Some(exclude.clone())).await;
    assert_eq!(status, 403);
    let (status, body) = call(&app, "POST", &path, Some(ADMIN), Some(exclude)).await;
    assert_eq!(status, 201, "{body}");
    let fingerprint: String = Sha256::digest(ADMIN.as_bytes())[..6]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    assert_eq!(body["created_by"], json!(fingerprint));
    let (status, _) = call(&app, "GET", &path, Some(READER), None).await;
    assert_eq!(status, 200);
    let restore = format!("{path}/1/restore");
    assert_eq!(
        call(&app, "POST", &restore, Some(WRITER), None).await.0,
        403
    );
    let (status, body) = call(&app, "POST", &restore, Some(ADMIN), None).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["restored_by"], json!(fingerprint));
}

#[tokio::test]
async fn a_scoped_token_reaches_only_its_experiments() {
    let (_dir, db) = temp_db();
    let app = app_with_tokens(&db, 2).await;
    for _ in 0..3 {
        let (status, _) = call(
            &app,
            "POST",
            "/v1/experiments",
            Some(ADMIN),
            Some(json!({})),
        )
        .await;
        assert_eq!(status, 201);
    }
    let (status, list) = call(&app, "GET", "/v1/experiments", Some(SCOPED), None).await;
    assert_eq!(status, 200);
    assert_eq!(ints(&list["items"], "id"), vec![2]);
    // Its pages count only what it reaches.
    assert_eq!(list["total"], 1, "{list}");
    let (_, page) = call(
        &app,
        "GET",
        "/v1/experiments?offset=1&limit=1",
        Some(SCOPED),
        None,
    )
    .await;
    assert_eq!(page["items"].as_array().unwrap().len(), 0, "{page}");
    let (_, all) = call(&app, "GET", "/v1/experiments", Some(READER), None).await;
    assert_eq!(all["items"].as_array().unwrap().len(), 3);
    assert_eq!(all["total"], 3);
    let traj = free_row_trajectory(0, 0, 1);
    let (status, body) = call(
        &app,
        "POST",
        "/v1/experiments/2/trajectories",
        Some(SCOPED),
        Some(traj.clone()),
    )
    .await;
    assert_eq!(status, 201, "{body}");
    for path in [
        "/v1/experiments/1/trajectories",
        "/v1/experiments/3/trajectories",
    ] {
        let (status, body) = call(&app, "POST", path, Some(SCOPED), Some(traj.clone())).await;
        assert_eq!(status, 403, "{path}: {body}");
    }
    let (status, _) = call(&app, "GET", "/v1/experiments/3", Some(SCOPED), None).await;
    assert_eq!(status, 403);
    // The metrics hold every experiment's totals: a scoped token does not read them.
    let (status, body) = call(&app, "GET", "/metrics", Some(SCOPED), None).await;
    assert_eq!((status, code(&body)), (403, "forbidden"), "{body}");
    let r = app
        .client
        .get(app.url("/metrics"))
        .bearer_auth(READER)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
}
