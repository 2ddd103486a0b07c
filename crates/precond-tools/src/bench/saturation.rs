//! `precond bench saturation`: do health checks and cheap reads stay fast while the planner is
//! saturated?
//!
//! Starts the service in this process on a loopback port over a fresh database in a temp
//! directory, with the default limits (one planning slot per core) and a short planning
//! deadline. Creates a kinematic experiment whose goal lies behind a wall (no search can reach
//! it, so every search runs until its deadline), then measures the latency of `GET /healthz`
//! and `GET /v1/experiments/{id}` twice: idle, and while `clients` concurrent clients keep
//! asking for proposals. Prints the percentiles and the proposals' outcomes.

use precond::http::{AppState, HttpConfig, serve};
use precond::service::{Limits, Service};
use precond::store::Store;
use serde_json::json;
use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Options of the benchmark.
#[derive(Debug, Clone)]
pub struct SaturationOptions {
    /// Concurrent clients asking for proposals.
    pub clients: usize,
    /// Seconds of each measurement phase.
    pub seconds: f64,
    /// The planning deadline in milliseconds.
    pub plan_timeout_ms: u64,
}

impl Default for SaturationOptions {
    fn default() -> Self {
        Self {
            clients: 16,
            seconds: 10.0,
            plan_timeout_ms: 2000,
        }
    }
}

/// Latencies of one probe, in milliseconds.
fn summary(mut ms: Vec<f64>) -> String {
    if ms.is_empty() {
        return "no samples".into();
    }
    ms.sort_by(f64::total_cmp);
    let q = |p: f64| ms[((ms.len() - 1) as f64 * p).round() as usize];
    format!(
        "n = {:5}  p50 = {:7.2} ms  p99 = {:7.2} ms  max = {:7.2} ms",
        ms.len(),
        q(0.5),
        q(0.99),
        ms[ms.len() - 1]
    )
}

/// Probes `paths` in turn every 10 ms for `phase`; latencies per path.
async fn probe(
    client: &reqwest::Client,
    base: &str,
    paths: &[String],
    phase: Duration,
) -> anyhow::Result<Vec<Vec<f64>>> {
    let started = Instant::now();
    let mut out = vec![Vec::new(); paths.len()];
    while started.elapsed() < phase {
        for (i, p) in paths.iter().enumerate() {
            let t = Instant::now();
            let r = client.get(format!("{base}{p}")).send().await?;
            anyhow::ensure!(r.status().is_success(), "{p} answered {}", r.status());
            r.bytes().await?;
            out[i].push(t.elapsed().as_secs_f64() * 1e3);
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    Ok(out)
}

/// Runs the benchmark and prints its figures.
pub async fn run(options: &SaturationOptions) -> anyhow::Result<()> {
    let dir = std::env::temp_dir().join(format!("precond-bench-{}", uuid::Uuid::new_v4()));
    std::fs::create_dir_all(&dir)?;
    let db = dir.join("bench.db");
    let store = Store::open(db.to_str().unwrap_or("bench.db")).await?;
    let limits = Limits {
        plan_timeout: Duration::from_millis(options.plan_timeout_ms),
        ..Limits::default()
    };
    limits.check().map_err(anyhow::Error::msg)?;
    println!(
        "saturation: {} planning slots, queue {}, deadline {} ms, {} proposal clients, {} cores",
        limits.max_concurrent_plans,
        limits.max_queued_plans,
        options.plan_timeout_ms,
        options.clients,
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    let state = AppState::with_service(
        Service::new(store).with_limits(limits),
        HttpConfig::default(),
    );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let base = format!("http://{}", listener.local_addr()?);
    let (stop_server, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(serve(listener, state, async {
        let _ = stopped.await;
    }));
    let client = reqwest::Client::new();
    let experiment: serde_json::Value = client
        .post(format!("{base}/v1/experiments"))
        .json(&json!({
            "name": "saturation",
            "domain": {"kind": "kinematic", "state_low": [0, 0], "state_high": [1, 1],
                       "action_low": [-0.05, -0.05], "action_high": [0.05, 0.05],
                       "obstacles": [{"low": [0.45, 0.0], "high": [0.55, 1.0]}]},
            "learning": {"max_extensions": 200000, "n_candidates": 20}
        }))
        .send()
        .await?
        .error_for_status()?
        .json()
        .await?;
    let id = experiment["id"]
        .as_i64()
        .ok_or_else(|| anyhow::anyhow!("no experiment id in {experiment}"))?;
    let paths = vec!["/healthz".to_string(), format!("/v1/experiments/{id}")];
    let phase = Duration::from_secs_f64(options.seconds);

    let idle = probe(&client, &base, &paths, phase).await?;

    let stop = Arc::new(AtomicBool::new(false));
    let mut askers = Vec::new();
    for c in 0..options.clients {
        let (client, base, stop) = (client.clone(), base.clone(), stop.clone());
        askers.push(tokio::spawn(async move {
            let mut outcomes: BTreeMap<String, usize> = BTreeMap::new();
            while !stop.load(Ordering::Relaxed) {
                let r = client
                    .post(format!("{base}/v1/experiments/{id}/proposals"))
                    .json(&json!({"start": [0.1, 0.5], "goal": [0.9, 0.5],
                                  "client_id": format!("bench-{c}")}))
                    .send()
                    .await;
                let key = match r {
                    Ok(r) => {
                        let status = r.status().as_u16();
                        let body: serde_json::Value = r.json().await.unwrap_or_default();
                        let code = body["error"]["code"].as_str().unwrap_or("ok").to_string();
                        if status == 429 {
                            tokio::time::sleep(Duration::from_millis(200)).await;
                        }
                        format!("{status} {code}")
                    }
                    Err(e) => format!("transport error: {e}"),
                };
                *outcomes.entry(key).or_default() += 1;
            }
            outcomes
        }));
    }
    // Let the planner fill up before measuring.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let busy = probe(&client, &base, &paths, phase).await?;
    stop.store(true, Ordering::Relaxed);
    let mut outcomes: BTreeMap<String, usize> = BTreeMap::new();
    for a in askers {
        for (k, n) in a.await? {
            *outcomes.entry(k).or_default() += n;
        }
    }
    let metrics = client
        .get(format!("{base}/metrics"))
        .send()
        .await?
        .text()
        .await?;
    let _ = stop_server.send(());
    server.await??;
    let _ = std::fs::remove_dir_all(&dir);

    for (name, samples) in [("idle", idle), ("planner saturated", busy)] {
        println!("{name}:");
        for (p, ms) in paths.iter().zip(samples) {
            println!("  GET {p:<24} {}", summary(ms));
        }
    }
    println!("proposal answers while saturated: {outcomes:?}");
    let running = metrics
        .lines()
        .find(|l| l.starts_with("precond_planning_running "))
        .unwrap_or("precond_planning_running ?");
    println!("after the run: {running}");
    Ok(())
}
