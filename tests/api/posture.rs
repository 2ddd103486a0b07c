//! What a web page in the user's browser can make a server do: the token-less loopback default
//! refuses cross-site writes and DNS rebinding; bodies must be declared as JSON everywhere.

use crate::helpers::*;
use precond::http::HttpConfig;
use precond::http::auth::TokenTable;
use serde_json::{Value, json};
use std::sync::Arc;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Sends `request` (a raw HTTP/1.1 request, `Connection: close`) and returns the status and the
/// JSON body.
async fn raw(app: &TestApp, request: String) -> (u16, Value) {
    let mut s = tokio::net::TcpStream::connect(app.addr).await.unwrap();
    s.write_all(request.as_bytes()).await.unwrap();
    let mut answer = Vec::new();
    s.read_to_end(&mut answer).await.unwrap();
    let text = String::from_utf8_lossy(&answer);
    let status = text[9..12].parse().unwrap();
    let body = text.split("\r\n\r\n").nth(1).unwrap_or_default();
    (status, serde_json::from_str(body).unwrap_or(Value::Null))
}

/// A GET with `headers` (`Name: value` lines).
fn get(path: &str, host: &str, headers: &str) -> String {
    format!("GET {path} HTTP/1.1\r\nHost: {host}\r\n{headers}Connection: close\r\n\r\n")
}

/// A POST with `headers` (`Name: value` lines) and `body`.
fn post(path: &str, host: &str, headers: &str, body: &str) -> String {
    format!(
        "POST {path} HTTP/1.1\r\nHost: {host}\r\n{headers}Content-Length: {}\r\n\
         Connection: close\r\n\r\n{body}",
        body.len()
    )
}

/// A raw POST of `body` with `headers` to `/v1/experiments` on `host`: creates an experiment,
/// or is refused.
async fn post_experiment(app: &TestApp, host: &str, headers: &str, body: &str) -> (u16, Value) {
    raw(app, post("/v1/experiments", host, headers, body)).await
}

async fn experiments(app: &TestApp) -> i64 {
    let (_, listed) = app.get("/v1/experiments").await;
    listed["total"].as_i64().unwrap()
}

#[tokio::test]
async fn bodies_not_declared_as_json_are_415_in_the_error_shape() {
    let (_dir, app) = fresh_app().await;
    let host = app.addr.to_string();
    for content_type in [
        Some("text/plain"),
        Some("application/x-www-form-urlencoded"),
        Some("multipart/form-data; boundary=x"),
        Some("application/jsonx"),
        None,
    ] {
        let header = content_type.map_or(String::new(), |ct| format!("Content-Type: {ct}\r\n"));
        let (status, err) = post_experiment(&app, &host, &header, r#"{"name":"csrf"}"#).await;
        assert_eq!(
            (status, code(&err)),
            (415, "unsupported_media_type"),
            "{content_type:?}: {err}"
        );
        assert!(message(&err).contains("application/json"), "{err}");
    }
    assert_eq!(experiments(&app).await, 0, "nothing was created");
    // Declared as JSON (any case, with parameters) it is accepted.
    for ct in ["application/json", "Application/JSON; charset=utf-8"] {
        let (status, body) =
            post_experiment(&app, &host, &format!("Content-Type: {ct}\r\n"), "{}").await;
        assert_eq!(status, 201, "{ct}: {body}");
    }
    // An ingest posted as a form is refused too; a bodiless POST (refit, abandon) needs none.
    let (status, err) = raw(
        &app,
        post(
            "/v1/experiments/1/trajectories",
            &host,
            "Content-Type: application/x-www-form-urlencoded\r\n",
            r#"{"transitions": [{"s": [3, 2], "a": [1, 0], "s_next": [3, 2]}]}"#,
        ),
    )
    .await;
    assert_eq!((status, code(&err)), (415, "unsupported_media_type"));
    let (status, err) = raw(&app, post("/v1/experiments/1/model/refit", &host, "", "")).await;
    assert_eq!(
        (status, code(&err)),
        (409, "conflict"),
        "nothing to fit yet"
    );
}

#[tokio::test]
async fn a_tokenless_loopback_server_answers_only_its_own_names_and_pages() {
    let (_dir, app) = fresh_app().await;
    let port = app.addr.port();
    let json_ct = "Content-Type: application/json\r\n";
    // DNS rebinding: a name that is not this machine's gets nothing, not even a read.
    for host in [
        format!("attacker.example:{port}"),
        "localhost.attacker.example".into(),
    ] {
        let (status, err) = raw(&app, get("/v1/experiments", &host, "")).await;
        assert_eq!((status, code(&err)), (403, "forbidden"), "{host}: {err}");
        assert!(message(&err).contains(&host));
    }
    // Health probes stay open.
    let (status, _) = raw(&app, get("/healthz", "probe.example", "")).await;
    assert_eq!(status, 200);
    // This machine's names all pass.
    for host in [
        format!("127.0.0.1:{port}"),
        format!("localhost:{port}"),
        "[::1]".into(),
    ] {
        let (status, body) = raw(&app, get("/v1/experiments", &host, "")).await;
        assert_eq!(status, 200, "{host}: {body}");
    }
    // A write from another site's page is refused, even declared as JSON; one from the
    // server's own pages (the dashboard) and one without Origin (curl, robots) pass.
    let own = format!("127.0.0.1:{port}");
    for origin in [
        "http://evil.example".to_string(),
        "null".into(),
        format!("http://127.0.0.1:{}", port.wrapping_add(1)),
    ] {
        let (status, err) =
            post_experiment(&app, &own, &format!("{json_ct}Origin: {origin}\r\n"), "{}").await;
        assert_eq!((status, code(&err)), (403, "forbidden"), "{origin}: {err}");
    }
    assert_eq!(experiments(&app).await, 0);
    let same_site = format!("{json_ct}Origin: http://{own}\r\n");
    let (status, body) = post_experiment(&app, &own, &same_site, "{}").await;
    assert_eq!(status, 201, "{body}");
    let (status, body) = post_experiment(&app, &own, json_ct, "{}").await;
    assert_eq!(status, 201, "{body}");
}

#[tokio::test]
async fn with_tokens_the_host_is_not_checked_but_bodies_must_be_json() {
    let (_dir, db) = temp_db();
    let token = "admin-token-0123456789";
    let app = spawn_app_with(
        &db,
        HttpConfig {
            tokens: Some(Arc::new(
                TokenTable::parse(&format!("{token} admin *")).unwrap(),
            )),
            ..HttpConfig::default()
        },
    )
    .await;
    let auth = format!("Authorization: Bearer {token}\r\n");
    let (status, body) = raw(
        &app,
        get("/v1/experiments", "lab-server.example:8080", &auth),
    )
    .await;
    assert_eq!(status, 200, "a lab server behind any name: {body}");
    let (status, err) = post_experiment(
        &app,
        "lab-server.example",
        &format!("{auth}Content-Type: text/plain\r\n"),
        "{}",
    )
    .await;
    assert_eq!((status, code(&err)), (415, "unsupported_media_type"));
    let (status, body) = post_experiment(
        &app,
        "lab-server.example",
        &format!("{auth}Content-Type: application/json\r\n"),
        &json!({}).to_string(),
    )
    .await;
    assert_eq!(status, 201, "{body}");
}

/// Slowloris: a connection that sends its headers a byte at a time, says nothing, or trickles
/// its body is closed (or answered `408`) once its time is up.
#[tokio::test]
async fn slow_headers_idle_connections_and_slow_bodies_are_timed_out() {
    use std::time::{Duration, Instant};
    let (_dir, app) = fresh_app_with(HttpConfig {
        header_read_timeout: Duration::from_millis(600),
        body_read_timeout: Duration::from_millis(600),
        ..HttpConfig::default()
    })
    .await;
    // Reads until the server closes (or 5 s pass): what it answered, and when it closed.
    async fn until_closed(s: &mut tokio::net::TcpStream, started: Instant) -> (String, Duration) {
        let mut got = Vec::new();
        let mut buf = [0u8; 4096];
        loop {
            match tokio::time::timeout(Duration::from_secs(5), s.read(&mut buf)).await {
                Ok(Ok(0)) | Ok(Err(_)) => break,
                Ok(Ok(n)) => got.extend_from_slice(&buf[..n]),
                Err(_) => panic!("the server kept the connection open for 5 s"),
            }
        }
        (
            String::from_utf8_lossy(&got).into_owned(),
            started.elapsed(),
        )
    }
    // Headers never finished: closed without an answer.
    let started = Instant::now();
    let mut s = tokio::net::TcpStream::connect(app.addr).await.unwrap();
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        .await
        .unwrap();
    for _ in 0..3 {
        tokio::time::sleep(Duration::from_millis(150)).await;
        let _ = s.write_all(b"a").await;
    }
    let (_, took) = until_closed(&mut s, started).await;
    assert!(took < Duration::from_secs(3), "{took:?}");
    // Connected and silent: closed too.
    let started = Instant::now();
    let mut s = tokio::net::TcpStream::connect(app.addr).await.unwrap();
    let (answer, took) = until_closed(&mut s, started).await;
    assert!(
        answer.is_empty() && took < Duration::from_secs(3),
        "{took:?}"
    );
    // A kept-alive connection is served, then closed once idle.
    let started = Instant::now();
    let mut s = tokio::net::TcpStream::connect(app.addr).await.unwrap();
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        .await
        .unwrap();
    let (answer, took) = until_closed(&mut s, started).await;
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    assert!(took < Duration::from_secs(3), "{took:?}");
    // A body that trickles: 408 in the error shape, then closed.
    let started = Instant::now();
    let mut s = tokio::net::TcpStream::connect(app.addr).await.unwrap();
    s.write_all(
        b"POST /v1/experiments HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n\
          Content-Length: 100\r\n\r\n{\"na",
    )
    .await
    .unwrap();
    let (answer, took) = until_closed(&mut s, started).await;
    assert!(answer.starts_with("HTTP/1.1 408"), "{answer}");
    assert!(answer.contains("\"request_timeout\""), "{answer}");
    assert!(took < Duration::from_secs(3), "{took:?}");
    // Prompt clients are unaffected.
    assert_eq!(app.get("/healthz").await.0, 200);
    assert_eq!(experiments(&app).await, 0);
}
