//! A full disk under the real binary: the SQLite file on a small tmpfs filled to the last byte
//! while clients post, then space freed, then a restart. Every `201` must name a trajectory
//! that is stored, with the content posted under its key and an id no other key was given;
//! while the disk is full writes are answered `507` with `Retry-After` (never `201`, never
//! `500`) and `/readyz` says `503`; once space is freed both recover without a restart.
//!
//! Mounting a tmpfs needs root. Without it the test says so and passes, unless
//! `PRECOND_REQUIRE_DISKFULL=1` (set by `.ci/run`, which runs as root) makes that a failure.

mod common;

use common::{Server, experiment, get, http_with_timeout, ingest_only};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// A tmpfs mounted for the test, unmounted when dropped.
struct Tmpfs {
    dir: PathBuf,
}

impl Tmpfs {
    fn mount(dir: &Path, size: &str) -> Option<Self> {
        std::fs::create_dir_all(dir).ok()?;
        let ok = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir)
            .status()
            .is_ok_and(|s| s.success());
        ok.then(|| Self {
            dir: dir.to_path_buf(),
        })
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.dir).status();
    }
}

/// Writes zeros into `path` until the file system refuses (ENOSPC).
fn fill(path: &Path) {
    use std::io::Write;
    let mut f = std::fs::File::create(path).unwrap();
    let block = vec![0u8; 64 * 1024];
    loop {
        match f.write(&block) {
            Ok(0) => break,
            Ok(_) => {}
            Err(_) => break,
        }
    }
    // The last partial block: byte by byte is too slow; 4 KiB pages are what SQLite needs.
    let small = vec![0u8; 512];
    while f.write(&small).is_ok_and(|n| n > 0) {}
    let _ = f.flush();
}

/// One client's trajectory `k`: 20–60 transitions (a few pages of the database each).
fn body(client: usize, k: usize) -> Value {
    let mut rng = ChaCha8Rng::seed_from_u64((client * 100_000 + k) as u64);
    let n = rng.random_range(20..=60);
    let transitions: Vec<Value> = (0..n)
        .map(|_| {
            let s = [rng.random_range(0.2..0.8), rng.random_range(0.2..0.8)];
            let a = [rng.random_range(-0.1..0.1), rng.random_range(-0.1..0.1)];
            json!({"s": s, "a": a, "s_next": [s[0] + a[0], s[1] + 0.5 * a[1]]})
        })
        .collect();
    json!({ "transitions": transitions })
}

/// What a client saw.
#[derive(Default)]
struct Seen {
    /// Key → (id answered, body posted).
    acked: HashMap<String, (i64, Value)>,
    /// Status → count, of the answers that were not `201`.
    refused: HashMap<u16, usize>,
    /// `Retry-After` was present on every 507.
    retry_after_on_507: bool,
}

/// Posts trajectories with unique keys for `duration`, each key retried until `201` or the
/// time is up.
async fn post_for(
    http: reqwest::Client,
    base: String,
    id: i64,
    client: usize,
    first_k: usize,
    duration: Duration,
) -> (Seen, usize) {
    let mut seen = Seen {
        retry_after_on_507: true,
        ..Seen::default()
    };
    let started = Instant::now();
    let mut k = first_k;
    while started.elapsed() < duration {
        let key = format!("c{client}-t{k}");
        let b = body(client, k);
        let r = http
            .post(format!("{base}/v1/experiments/{id}/trajectories"))
            .header("idempotency-key", &key)
            .json(&b)
            .send()
            .await;
        let Ok(r) = r else {
            tokio::time::sleep(Duration::from_millis(20)).await;
            continue;
        };
        let status = r.status().as_u16();
        let has_retry_after = r.headers().contains_key("retry-after");
        let v: Value = r.json().await.unwrap_or(Value::Null);
        if status == 201 {
            seen.acked.insert(key, (v["id"].as_i64().unwrap(), b));
            k += 1;
        } else {
            *seen.refused.entry(status).or_default() += 1;
            if status == 507 && !has_retry_after {
                seen.retry_after_on_507 = false;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }
    (seen, k)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_full_disk_never_acknowledges_what_it_does_not_store() {
    let scratch = tempfile::tempdir().unwrap();
    let mnt = scratch.path().join("mnt");
    let Some(fs) = Tmpfs::mount(&mnt, "16m") else {
        assert!(
            std::env::var("PRECOND_REQUIRE_DISKFULL").as_deref() != Ok("1"),
            "PRECOND_REQUIRE_DISKFULL=1 but a tmpfs could not be mounted (root is needed)"
        );
        eprintln!("skipped: mounting a tmpfs needs root (PRECOND_REQUIRE_DISKFULL=1 to require)");
        return;
    };
    let db = fs.dir.join("full.db");
    let server = Server::start(&db, &[]);
    let http = http_with_timeout(Duration::from_secs(10));
    let id = experiment(&http, &server.base, ingest_only()).await;
    const CLIENTS: usize = 4;

    // Some data first, then no space left at all.
    let mut acked: HashMap<String, (i64, Value)> = HashMap::new();
    let mut next_k = vec![0; CLIENTS];
    let round = |phase: Duration, next_k: Vec<usize>| {
        let tasks: Vec<_> = (0..CLIENTS)
            .map(|c| {
                tokio::spawn(post_for(
                    http.clone(),
                    server.base.clone(),
                    id,
                    c,
                    next_k[c],
                    phase,
                ))
            })
            .collect();
        async move {
            let mut out = Vec::new();
            for t in tasks {
                out.push(t.await.unwrap());
            }
            out
        }
    };
    for (c, (seen, k)) in round(Duration::from_millis(300), next_k.clone())
        .await
        .into_iter()
        .enumerate()
    {
        acked.extend(seen.acked);
        next_k[c] = k;
    }
    assert!(!acked.is_empty(), "writes succeed before the disk fills");
    let filler = fs.dir.join("filler");
    fill(&filler);

    // Full: clients keep posting for a while.
    let mut refused: HashMap<u16, usize> = HashMap::new();
    let mut retry_after = true;
    let mut full_acks = 0;
    for (c, (seen, k)) in round(Duration::from_secs(3), next_k.clone())
        .await
        .into_iter()
        .enumerate()
    {
        full_acks += seen.acked.len();
        acked.extend(seen.acked);
        for (s, n) in seen.refused {
            *refused.entry(s).or_default() += n;
        }
        retry_after &= seen.retry_after_on_507;
        next_k[c] = k;
    }
    assert!(
        refused.get(&507).copied().unwrap_or(0) > 0,
        "a full disk is answered 507: {refused:?} ({full_acks} acknowledged while full)"
    );
    assert_eq!(
        refused.get(&500),
        None,
        "a full disk is not an internal error: {refused:?}"
    );
    assert!(retry_after, "every 507 says when to retry");
    let (status, ready) = get(&http, &format!("{}/readyz", server.base)).await;
    assert_eq!(status, 503, "readiness says the disk is full: {ready}");
    assert!(
        ready["error"]["message"]
            .as_str()
            .is_some_and(|m| m.contains("disk is full")),
        "{ready}"
    );

    // Space freed: writes and readiness come back without a restart.
    std::fs::remove_file(&filler).unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (status, ready) = get(&http, &format!("{}/readyz", server.base)).await;
        if status == 200 {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "readiness came back: {ready}; {:?}",
            Command::new("df")
                .arg(&fs.dir)
                .output()
                .map(|o| String::from_utf8_lossy(&o.stdout).to_string())
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let mut after = 0;
    for (seen, _) in round(Duration::from_millis(800), next_k.clone()).await {
        after += seen.acked.len();
        acked.extend(seen.acked);
    }
    assert!(after > 0, "writes succeed once space is freed");

    // A restart on the same file: every acknowledged trajectory is there, under its own id,
    // with what was posted under its key.
    server.sigterm();
    let mut server = server;
    server.wait_exit(Duration::from_secs(20));
    drop(server);
    let server = Server::start(&db, &[]);
    let mut ids: HashMap<i64, &str> = HashMap::new();
    for (key, (tid, body)) in &acked {
        if let Some(other) = ids.insert(*tid, key) {
            panic!("trajectory id {tid} was answered to {other} and to {key}");
        }
        let (status, t) = get(
            &http,
            &format!("{}/v1/experiments/{id}/trajectories/{tid}", server.base),
        )
        .await;
        assert_eq!(status, 200, "acknowledged {key} as {tid}, lost: {t}");
        let stored = t["transitions"].as_array().unwrap();
        let sent = body["transitions"].as_array().unwrap();
        assert_eq!(stored.len(), sent.len(), "{key} as {tid} is whole");
        for (g, s) in stored.iter().zip(sent) {
            assert_eq!((&g["s"], &g["a"]), (&s["s"], &s["a"]), "{key} as {tid}");
        }
    }
    let (_, e) = get(&http, &format!("{}/v1/experiments/{id}", server.base)).await;
    assert_eq!(
        e["n_trajectories"].as_u64(),
        Some(acked.len() as u64),
        "nothing stored that was not acknowledged"
    );
    drop(server);
    drop(fs);
}
