//! What the tests that run the real binary share: a `precond serve` subprocess, HTTP helpers
//! and seeded trajectories whose labels are known.
#![allow(dead_code)]

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

/// A `precond serve` subprocess on a loopback port, its log collected.
pub struct Server {
    child: Child,
    /// `http://127.0.0.1:PORT`.
    pub base: String,
    /// Every line it logged so far.
    pub log: Arc<Mutex<Vec<String>>>,
}

impl Server {
    /// Starts the binary on `db` and returns once it listens (it logs its address once bound).
    pub fn start(db: impl AsRef<std::ffi::OsStr>, extra: &[&str]) -> Server {
        let mut child = Command::new(env!("CARGO_BIN_EXE_precond"))
            .args(["serve", "--addr", "127.0.0.1:0", "--log-format", "json"])
            .arg("--database-url")
            .arg(db.as_ref())
            .args(extra)
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("the precond binary starts");
        let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let mut log = Vec::new();
        let addr = loop {
            let line = lines
                .next()
                .expect("the server logs its address before exiting")
                .unwrap();
            log.push(line.clone());
            let v: Value = serde_json::from_str(&line).unwrap_or_default();
            if v["fields"]["message"] == "serving" {
                break v["fields"]["addr"].as_str().unwrap().to_string();
            }
        };
        let log = Arc::new(Mutex::new(log));
        let sink = log.clone();
        // Keep draining stdout so the server never blocks on a full pipe.
        std::thread::spawn(move || {
            for line in lines.map_while(Result::ok) {
                sink.lock().unwrap().push(line);
            }
        });
        Server {
            child,
            base: format!("http://{addr}"),
            log,
        }
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn kill9(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }

    pub fn sigterm(&self) {
        let status = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .unwrap();
        assert!(status.success());
    }

    /// Waits for the process to exit, at most `limit`; its exit status and the time it took.
    pub fn wait_exit(&mut self, limit: Duration) -> (std::process::ExitStatus, Duration) {
        let started = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return (status, started.elapsed());
            }
            assert!(
                started.elapsed() < limit,
                "the server did not exit within {limit:?}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    pub fn logged(&self, needle: &str) -> bool {
        self.log.lock().unwrap().iter().any(|l| l.contains(needle))
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub async fn post(client: &reqwest::Client, url: &str, body: &Value) -> (u16, Value) {
    let r = client.post(url).json(body).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

pub async fn get(client: &reqwest::Client, url: &str) -> (u16, Value) {
    let r = client.get(url).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// A client whose requests give up after `timeout`.
pub fn http_with_timeout(timeout: Duration) -> reqwest::Client {
    reqwest::Client::builder().timeout(timeout).build().unwrap()
}

/// Creates an experiment on the server at `base` and returns its id.
pub async fn experiment(http: &reqwest::Client, base: &str, body: Value) -> i64 {
    let (status, e) = post(http, &format!("{base}/v1/experiments"), &body).await;
    assert_eq!(status, 201, "{e}");
    e["id"].as_i64().unwrap()
}

/// A kinematic experiment that refits after every `batch_size` trajectories with `restarts`
/// optimiser restarts (more restarts: a longer fit, to be caught running).
pub fn refits_every(batch_size: usize, restarts: usize) -> Value {
    json!({"domain": {"kind": "kinematic"}, "learning": {"batch_size": batch_size},
           "mde": {"restarts": restarts}})
}

/// The server's `/metrics` text.
pub async fn metrics(http: &reqwest::Client, base: &str) -> String {
    http.get(format!("{base}/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap()
}

/// A kinematic experiment whose batch is never full while the tests ingest: no refit.
pub fn ingest_only() -> Value {
    json!({"domain": {"kind": "kinematic"}, "learning": {"batch_size": 10000}})
}

/// Every transition of experiment `id`, following the cursor.
pub async fn all_transitions(client: &reqwest::Client, base: &str, id: i64) -> Vec<Value> {
    transitions_in_pages(client, base, id, 1000).await
}

/// Every transition of experiment `id`, following the cursor through pages of `limit`.
pub async fn transitions_in_pages(
    client: &reqwest::Client,
    base: &str,
    id: i64,
    limit: usize,
) -> Vec<Value> {
    let mut out = Vec::new();
    let mut after = 0;
    loop {
        let (status, page) = get(
            client,
            &format!("{base}/v1/experiments/{id}/transitions?after={after}&limit={limit}"),
        )
        .await;
        assert_eq!(status, 200, "{page}");
        out.extend(page["items"].as_array().unwrap().iter().cloned());
        match page["next"].as_i64() {
            Some(next) => after = next,
            None => return out,
        }
    }
}

/// One client's trajectory `k`: seeded, in the kinematic unit square, with the deviations the
/// service must compute (`s_next = s + f·a`, so the label is `(1 − f)|a|`).
pub fn trajectory(client: usize, k: usize) -> (Value, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64((client * 1000 + k) as u64);
    let n = rng.random_range(1..=6);
    let mut transitions = Vec::new();
    let mut labels = Vec::new();
    for _ in 0..n {
        let s = [rng.random_range(0.2..0.8), rng.random_range(0.2..0.8)];
        let a: [f64; 2] = [rng.random_range(-0.1..0.1), rng.random_range(-0.1..0.1)];
        let f = [1.0, 0.5, 0.0][rng.random_range(0..3)];
        let s_next = [s[0] + f * a[0], s[1] + f * a[1]];
        labels.push((1.0 - f) * (a[0] * a[0] + a[1] * a[1]).sqrt());
        transitions.push(json!({"s": s, "a": a, "s_next": s_next}));
    }
    (json!({ "transitions": transitions }), labels)
}

/// A trajectory the server acknowledged: its id, the body posted and the labels it must carry.
pub type Acked = (i64, Value, Vec<f64>);

/// Robot `c`'s and robot `c + 1`'s trajectory `k` as the transitions of one body (to make
/// batches of about 7 transitions a trajectory).
pub fn two_robots_trajectory(c: usize, k: usize) -> Value {
    let mut body = json!({"transitions": []});
    for j in 0..2 {
        let (t, _) = trajectory(c + j, k);
        body["transitions"]
            .as_array_mut()
            .unwrap()
            .extend(t["transitions"].as_array().unwrap().iter().cloned());
    }
    body
}

/// Robots `0..robots`, each posting `per_robot` trajectories with
/// [`post_until_acknowledged`], started at once.
pub fn spawn_robots(
    http: &reqwest::Client,
    servers: &Arc<RwLock<Vec<String>>>,
    id: i64,
    robots: usize,
    per_robot: usize,
) -> Vec<tokio::task::JoinHandle<(Vec<Acked>, usize)>> {
    (0..robots)
        .map(|c| {
            tokio::spawn(post_until_acknowledged(
                http.clone(),
                servers.clone(),
                id,
                c,
                per_robot,
            ))
        })
        .collect()
}

/// Waits for every robot of [`spawn_robots`]: all they had acknowledged and the retries it took.
pub async fn join_robots(
    robots: Vec<tokio::task::JoinHandle<(Vec<Acked>, usize)>>,
) -> (Vec<Acked>, usize) {
    let mut acked = Vec::new();
    let mut retries = 0;
    for robot in robots {
        let (a, r) = robot.await.unwrap();
        acked.extend(a);
        retries += r;
    }
    (acked, retries)
}

/// Robot `c` posts its `n` seeded trajectories to experiment `id`, paced 10–60 ms apart (a robot
/// takes a while to execute one), each under its own `Idempotency-Key` until acknowledged with
/// `201` — any other answer but a 5xx fails the test. It starts on server `c mod servers`
/// and, after a failure, retries on the next one (`servers` may change meanwhile: restarts).
/// Returns what was acknowledged and how many retries it took.
pub async fn post_until_acknowledged(
    http: reqwest::Client,
    servers: Arc<RwLock<Vec<String>>>,
    id: i64,
    c: usize,
    n: usize,
) -> (Vec<Acked>, usize) {
    let mut acked = Vec::new();
    let mut retries = 0;
    let mut pace = ChaCha8Rng::seed_from_u64(c as u64);
    let mut server = c;
    for k in 0..n {
        let (body, labels) = trajectory(c, k);
        tokio::time::sleep(Duration::from_millis(pace.random_range(10..60))).await;
        loop {
            let url = {
                let servers = servers.read().unwrap();
                format!(
                    "{}/v1/experiments/{id}/trajectories",
                    servers[server % servers.len()]
                )
            };
            let sent = http
                .post(&url)
                .header("idempotency-key", format!("client-{c}-trajectory-{k}"))
                .json(&body)
                .send()
                .await;
            if let Ok(r) = sent {
                let status = r.status().as_u16();
                if let Ok(v) = r.json::<Value>().await {
                    assert!(
                        status == 201 || status >= 500,
                        "client {c} trajectory {k}: {status} {v}"
                    );
                    if status == 201 {
                        acked.push((v["id"].as_i64().unwrap(), body.clone(), labels));
                        break;
                    }
                }
            }
            retries += 1;
            server += 1;
            tokio::time::sleep(Duration::from_millis(15)).await;
        }
    }
    (acked, retries)
}

/// Every acknowledged trajectory is stored at `base` exactly once, whole, with its labels, and
/// nothing else is.
pub async fn assert_stored_exactly_once(
    http: &reqwest::Client,
    base: &str,
    id: i64,
    acked: &[Acked],
) {
    let stored = all_transitions(http, base, id).await;
    let mut by_trajectory: HashMap<i64, Vec<&Value>> = HashMap::new();
    for t in &stored {
        by_trajectory
            .entry(t["trajectory_id"].as_i64().unwrap())
            .or_default()
            .push(t);
    }
    assert_eq!(
        by_trajectory.len(),
        acked.len(),
        "one stored trajectory per acknowledged one, no more"
    );
    for (tid, body, labels) in acked {
        let got = &by_trajectory[tid];
        let sent = body["transitions"].as_array().unwrap();
        assert_eq!(got.len(), sent.len(), "trajectory {tid} is whole");
        for ((g, s), label) in got.iter().zip(sent).zip(labels) {
            assert_eq!(g["s"], s["s"]);
            assert_eq!(g["a"], s["a"]);
            let d = g["deviation"].as_f64().unwrap();
            assert!((d - label).abs() < 1e-9, "trajectory {tid}: {d} vs {label}");
        }
    }
    let (_, e) = get(http, &format!("{base}/v1/experiments/{id}")).await;
    assert_eq!(e["n_trajectories"], acked.len() as i64);
}

/// The problem [`assert_lease_answered`] asks again, for client `arm-1`.
pub fn leased_problem() -> Value {
    json!({"start": [0.1, 0.1], "goal": [0.6, 0.6], "client_id": "arm-1"})
}

/// Proposes [`leased_problem`] on `base` (a kinematic experiment `id`): `201`, the proposal leased
/// to `arm-1`.
pub async fn lease(http: &reqwest::Client, base: &str, id: i64) -> Value {
    let url = format!("{base}/v1/experiments/{id}/proposals");
    let (status, first) = post(http, &url, &leased_problem()).await;
    assert_eq!(status, 201, "{first}");
    first
}

/// Asking `base` again for [`leased_problem`], whose proposal `first` is leased to `arm-1`,
/// answers that open lease (`200`, the same proposal); asking for another problem while it is
/// open is `409`.
pub async fn assert_lease_answered(http: &reqwest::Client, base: &str, id: i64, first: &Value) {
    let url = format!("{base}/v1/experiments/{id}/proposals");
    let (status, again) = post(http, &url, &leased_problem()).await;
    assert_eq!(status, 200, "the open lease is answered: {again}");
    assert_eq!(again["id"], first["id"]);
    assert_eq!(again["trajectory"], first["trajectory"]);
    let other = json!({"start": [0.1, 0.1], "goal": [0.9, 0.2], "client_id": "arm-1"});
    let (status, refused) = post(http, &url, &other).await;
    assert_eq!(status, 409, "{refused}");
}
