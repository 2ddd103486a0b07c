//! Large answers under the real binary: the CSV of every transition and the model export are
//! written a chunk at a time, in a few export slots. Clients that stop reading hold no more
//! than a few chunks each (the server's memory does not grow with the answer's size), one
//! beyond the slots is answered `429` with `Retry-After` instead of queueing without bound, a
//! client that leaves frees its slot, and an answer read to the end is whole.

mod common;

use common::{Server, experiment, get, post};
use serde_json::{Value, json};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

/// The server's resident memory, in bytes (Linux).
fn rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find(|l| l.starts_with("VmRSS:"))
        .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
        .map_or(0, |kib| kib * 1024)
}

/// Sends a GET and reads only the status line and headers, never the body: a reader that
/// stalls (the server's writes stop once the kernel's socket buffers are full).
fn stalled_get(base: &str, path: &str, accept: &str) -> (TcpStream, String) {
    let addr = base.trim_start_matches("http://");
    let mut stream = TcpStream::connect(addr).unwrap();
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nAccept: {accept}\r\n\r\n"
    )
    .unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        if stream.read(&mut byte).unwrap() == 0 {
            break;
        }
        head.push(byte[0]);
    }
    (stream, String::from_utf8_lossy(&head).to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn large_answers_are_streamed_in_bounded_slots() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path().join("exports.db"),
        &["--max-concurrent-exports", "2"],
    );
    let http = reqwest::Client::new();
    let id = experiment(
        &http,
        &server.base,
        json!({"domain": {"kind": "kinematic"}, "learning": {"batch_size": 10000}}),
    )
    .await;
    // 120,000 transitions: a CSV of about 14 MB.
    const TRAJECTORIES: usize = 12;
    const STEPS: usize = 10_000;
    for k in 0..TRAJECTORIES {
        let transitions: Vec<Value> = (0..STEPS)
            .map(|i| {
                let x = 0.1 + 0.8 * ((i * 7 + k) % 1000) as f64 / 1000.0;
                json!({"s": [x, 0.5], "a": [0.01, -0.02], "s_next": [x + 0.009, 0.49]})
            })
            .collect();
        let (status, body) = post(
            &http,
            &format!("{}/v1/experiments/{id}/trajectories", server.base),
            &json!({ "transitions": transitions }),
        )
        .await;
        assert_eq!(status, 201, "{body}");
    }
    let n = TRAJECTORIES * STEPS;
    let csv_path = format!("/v1/experiments/{id}/transitions");

    // Read whole, the CSV has every transition and its header.
    let whole = http
        .get(format!("{}{csv_path}", server.base))
        .header("accept", "text/csv")
        .send()
        .await
        .unwrap();
    assert_eq!(whole.status(), 200);
    let text = whole.text().await.unwrap();
    assert_eq!(
        text.lines().count(),
        n + 1,
        "the header and every transition"
    );
    assert!(
        text.starts_with("id,trajectory_id,step,"),
        "{}",
        &text[..80]
    );
    let size = text.len() as u64;
    drop(text);

    // Two readers that stall hold the two slots and little memory.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let before = rss(server.pid());
    let (a, head_a) = stalled_get(&server.base, &csv_path, "text/csv");
    let (b, head_b) = stalled_get(&server.base, &csv_path, "text/csv");
    assert!(
        head_a.starts_with("HTTP/1.1 200") && head_b.starts_with("HTTP/1.1 200"),
        "{head_a}"
    );
    tokio::time::sleep(Duration::from_secs(1)).await;
    // Each holds a page of transitions, a few chunks and its read connection's page cache
    // (SQLite's default, 2 MiB); built whole, each would hold the CSV and more.
    let held = rss(server.pid()).saturating_sub(before);
    assert!(
        held < 16 << 20 && held < size,
        "two stalled readers of a {size}-byte CSV made the server hold {held} more bytes"
    );

    // A third is refused, saying when to retry, within a few seconds.
    let asked = Instant::now();
    let third = http
        .get(format!("{}{csv_path}", server.base))
        .header("accept", "text/csv")
        .send()
        .await
        .unwrap();
    assert_eq!(third.status(), 429);
    assert!(third.headers().contains_key("retry-after"));
    assert!(asked.elapsed() < Duration::from_secs(5));
    let err: Value = third.json().await.unwrap();
    assert_eq!(err["error"]["code"], "overloaded", "{err}");

    // Clients that leave free their slots: the next export is whole again.
    drop(a);
    drop(b);
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let r = http
            .get(format!("{}{csv_path}?limit=1000", server.base))
            .header("accept", "text/csv")
            .send()
            .await
            .unwrap();
        if r.status() == 200 {
            assert_eq!(r.headers()["x-next-cursor"], "1000");
            assert_eq!(r.text().await.unwrap().lines().count(), 1001);
            break;
        }
        assert!(Instant::now() < deadline, "the slots were freed");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let (status, _) = get(&http, &format!("{}/healthz", server.base)).await;
    assert_eq!(status, 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_model_export_is_whole_and_gated_like_the_csv() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path().join("model.db"),
        &["--max-concurrent-exports", "1"],
    );
    let http = reqwest::Client::new();
    let id = experiment(
        &http,
        &server.base,
        json!({"domain": {"kind": "kinematic"}, "learning": {"batch_size": 1},
               "mde": {"kernel": "matern52", "label_cap": 0, "restarts": 0,
                       "noise": "homoscedastic", "estimator": "exact"}}),
    )
    .await;
    let transitions: Vec<Value> = (0..1500)
        .map(|i| {
            let x = 0.1 + 0.8 * (i as f64 / 1500.0);
            let y = 0.1 + 0.8 * ((i * 37 % 1500) as f64 / 1500.0);
            json!({"s": [x, y], "a": [0.05, 0.0], "s_next": [x + 0.05 * (1.0 - y), y]})
        })
        .collect();
    let (status, body) = post(
        &http,
        &format!("{}/v1/experiments/{id}/trajectories", server.base),
        &json!({ "transitions": transitions }),
    )
    .await;
    assert_eq!(status, 201, "{body}");
    // Wait for the fit (as long as it takes: the test does not depend on the machine's speed).
    loop {
        let (_, m) = get(&http, &format!("{}/v1/experiments/{id}/model", server.base)).await;
        if m["version"].as_i64() >= Some(1) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let path = format!("/v1/experiments/{id}/model/export");
    let r = http
        .get(format!("{}{path}", server.base))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "application/json");
    let doc: Value = r.json().await.unwrap();
    assert_eq!(doc["format"], "precond-model");
    assert_eq!(doc["n_train"], 1500);
    let factor = doc["predictor"]["main"]["factor"].as_array().unwrap();
    assert_eq!(factor.len(), 1500 * 1501 / 2, "the whole packed L⁻¹");

    // One slot: a stalled reader holds it, the next is refused, and leaving frees it.
    let (stalled, head) = stalled_get(&server.base, &path, "application/json");
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    let refused = http
        .get(format!("{}{path}", server.base))
        .send()
        .await
        .unwrap();
    assert_eq!(refused.status(), 429);
    drop(stalled);
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let r = http
            .get(format!("{}{path}", server.base))
            .send()
            .await
            .unwrap();
        if r.status() == 200 {
            let again: Value = r.json().await.unwrap();
            assert_eq!(again, doc, "the same document again");
            break;
        }
        assert!(Instant::now() < deadline, "the slot was freed");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}
