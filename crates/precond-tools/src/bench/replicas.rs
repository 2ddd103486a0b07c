//! `precond bench replicas`: proposals per second and their latency with 1, 2, 4 … replicas of
//! this binary over one PostgreSQL database, in the same run.
//!
//! For each replica count: a new database on the given server, that many `precond serve`
//! processes over it (loopback ports), `experiments` kinematic experiments, and `clients`
//! concurrent robots that each ask for a proposal (the service plans `n_candidates` RRT searches
//! around a wall with a GP fitted on 300 transitions, and scores them), execute it as planned and post the trajectory, then ask again — spread
//! over the replicas in turn, as a round-robin load balancer would. Batches are large, so no
//! fit runs: the figure is planning and ingest. Prints proposals per second, latency
//! percentiles, failures, the replicas' CPU time and the whole machine's busy share (what
//! limits the throughput), and the ratios to one replica.

use anyhow::Context;
use serde_json::{Value, json};
use sqlx::Connection;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Options of the benchmark.
#[derive(Debug, Clone)]
pub struct ReplicasOptions {
    /// A PostgreSQL URL whose user may create databases (one per replica count).
    pub database_url: String,
    /// Replica counts to measure, in order.
    pub replicas: Vec<usize>,
    /// Concurrent clients.
    pub clients: usize,
    /// Seconds of measurement per replica count.
    pub seconds: f64,
    /// Experiments the clients share (client `c` works on experiment `c mod experiments`).
    pub experiments: usize,
    /// Each replica's `--max-concurrent-plans` (`None`: its default, one per core), to see
    /// replicas add cores when each is held to fewer than the machine has.
    pub plans_per_replica: Option<usize>,
}

/// One `precond serve` process.
struct Replica {
    child: Child,
    base: String,
}

impl Replica {
    fn start(database_url: &str, plans: Option<usize>) -> anyhow::Result<Self> {
        let exe = std::env::current_exe().context("this binary's path")?;
        let mut command = Command::new(exe);
        command
            .args(["serve", "--addr", "127.0.0.1:0", "--log-format", "json"])
            .args(["--database-url", database_url]);
        if let Some(plans) = plans {
            command.args(["--max-concurrent-plans", &plans.to_string()]);
        }
        let mut child = command
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .context("starting a replica")?;
        let mut lines = BufReader::new(child.stdout.take().context("its log")?).lines();
        let addr = loop {
            let line = lines
                .next()
                .context("the replica exited before serving")??;
            let v: Value = serde_json::from_str(&line).unwrap_or_default();
            if v["fields"]["message"] == "serving" {
                break v["fields"]["addr"]
                    .as_str()
                    .context("its address")?
                    .to_string();
            }
        };
        std::thread::spawn(move || for _ in lines.map_while(Result::ok) {});
        Ok(Self {
            child,
            base: format!("http://{addr}"),
        })
    }

    /// CPU seconds (user + system) the process has used.
    fn cpu_seconds(&self) -> f64 {
        cpu_seconds(self.child.id())
    }
}

impl Drop for Replica {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// CPU seconds of process `pid` (Linux `/proc`; 0 elsewhere).
fn cpu_seconds(pid: u32) -> f64 {
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
        return 0.0;
    };
    // Fields after the parenthesised name: state is field 3; utime and stime are 14 and 15.
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else {
        return 0.0;
    };
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}

/// The machine's busy and total jiffies (Linux `/proc/stat`).
fn machine_jiffies() -> (f64, f64) {
    let Ok(stat) = std::fs::read_to_string("/proc/stat") else {
        return (0.0, 0.0);
    };
    let Some(cpu) = stat.lines().next() else {
        return (0.0, 0.0);
    };
    let v: Vec<f64> = cpu
        .split_whitespace()
        .skip(1)
        .filter_map(|x| x.parse().ok())
        .collect();
    let total: f64 = v.iter().sum();
    let idle = v.get(3).copied().unwrap_or(0.0) + v.get(4).copied().unwrap_or(0.0);
    (total - idle, total)
}

/// A new database on the server of `admin`; its URL.
async fn new_database(admin: &str) -> anyhow::Result<String> {
    let name = format!("precond_bench_{}", uuid::Uuid::new_v4().simple());
    let mut conn = sqlx::PgConnection::connect(admin)
        .await
        .with_context(|| format!("connecting to {}", precond::store::redact(admin)))?;
    sqlx::query(&format!("CREATE DATABASE {name}"))
        .execute(&mut conn)
        .await
        .context("creating the benchmark's database")?;
    let (server, _) = admin
        .rsplit_once('/')
        .context("a postgres:// URL with a database")?;
    Ok(format!("{server}/{name}"))
}

async fn drop_database(admin: &str, url: &str) {
    let Some((_, name)) = url.rsplit_once('/') else {
        return;
    };
    if let Ok(mut conn) = sqlx::PgConnection::connect(admin).await {
        let _ = sqlx::query(&format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)"))
            .execute(&mut conn)
            .await;
    }
}

/// What one replica count measured.
struct Row {
    replicas: usize,
    proposals: usize,
    failures: BTreeMap<String, usize>,
    seconds: f64,
    latencies_ms: Vec<f64>,
    replica_cpu: f64,
    machine_busy: f64,
}

impl Row {
    fn rate(&self) -> f64 {
        self.proposals as f64 / self.seconds
    }

    fn quantile(&self, q: f64) -> f64 {
        if self.latencies_ms.is_empty() {
            return f64::NAN;
        }
        self.latencies_ms[((self.latencies_ms.len() - 1) as f64 * q).round() as usize]
    }
}

fn count(failures: &mut BTreeMap<String, usize>, why: String) {
    *failures.entry(why).or_insert(0) += 1;
}

/// One robot: ask, execute as planned (the kinematic model is exact here), post; again.
async fn robot(
    http: reqwest::Client,
    bases: Arc<Vec<String>>,
    id: i64,
    client: usize,
    until: Instant,
) -> (Vec<f64>, BTreeMap<String, usize>) {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(client as u64);
    let (mut latencies, mut failures) = (Vec::new(), BTreeMap::new());
    let mut turn = client;
    while Instant::now() < until {
        let base = &bases[turn % bases.len()];
        turn += 1;
        // Start and goal apart (a start within the goal's radius is refused).
        let (start, goal) = loop {
            let s: [f64; 2] = [rng.random_range(0.05..0.95), rng.random_range(0.05..0.95)];
            let g = [rng.random_range(0.05..0.95), rng.random_range(0.05..0.95)];
            if (s[0] - g[0]).hypot(s[1] - g[1]) > 0.3 {
                break (s, g);
            }
        };
        let asked = Instant::now();
        let answer = http
            .post(format!("{base}/v1/experiments/{id}/proposals"))
            .json(&json!({"start": start, "goal": goal}))
            .send()
            .await;
        let proposal: Value = match answer {
            Ok(r) if r.status().as_u16() == 201 => r.json().await.unwrap_or_default(),
            Ok(r) => {
                let status = r.status().as_u16();
                let body: Value = r.json().await.unwrap_or_default();
                let code = body["error"]["code"].as_str().unwrap_or("-").to_string();
                count(&mut failures, format!("proposal {status} {code}"));
                continue;
            }
            Err(_) => {
                count(&mut failures, "proposal: no answer".into());
                continue;
            }
        };
        latencies.push(asked.elapsed().as_secs_f64() * 1e3);
        let (states, actions) = (
            &proposal["trajectory"]["states"],
            &proposal["trajectory"]["actions"],
        );
        let Some(actions) = actions.as_array() else {
            continue;
        };
        let transitions: Vec<Value> = actions
            .iter()
            .enumerate()
            .map(|(k, a)| json!({"s": states[k], "a": a, "s_next": states[k + 1]}))
            .collect();
        let posted = http
            .post(format!("{base}/v1/experiments/{id}/trajectories"))
            .json(&json!({"proposal_id": proposal["id"], "transitions": transitions}))
            .send()
            .await;
        match posted {
            Ok(r) if r.status().as_u16() == 201 => {}
            Ok(r) => count(&mut failures, format!("trajectory {}", r.status().as_u16())),
            Err(_) => count(&mut failures, "trajectory: no answer".into()),
        }
    }
    (latencies, failures)
}

async fn measure(o: &ReplicasOptions, n: usize) -> anyhow::Result<Row> {
    let db = new_database(&o.database_url).await?;
    let replicas = (0..n)
        .map(|_| Replica::start(&db, o.plans_per_replica))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let bases: Arc<Vec<String>> = Arc::new(replicas.iter().map(|r| r.base.clone()).collect());
    let http = reqwest::Client::builder()
        .timeout(Duration::from_secs(60))
        .build()?;
    let mut ids = Vec::new();
    for e in 0..o.experiments {
        let r = http
            .post(format!("{}/v1/experiments", bases[0]))
            .json(
                &json!({"name": format!("bench-{e}"), "domain": {"kind": "kinematic"},
                          "seed": e, "learning": {"batch_size": 10000}}),
            )
            .send()
            .await?;
        anyhow::ensure!(
            r.status().as_u16() == 201,
            "creating an experiment: {}",
            r.status()
        );
        ids.push(r.json::<Value>().await?["id"].as_i64().context("its id")?);
    }
    let cpu_before: f64 = replicas.iter().map(Replica::cpu_seconds).sum();
    let machine_before = machine_jiffies();
    let started = Instant::now();
    let until = started + Duration::from_secs_f64(o.seconds);
    let robots: Vec<_> = (0..o.clients)
        .map(|c| {
            tokio::spawn(robot(
                http.clone(),
                bases.clone(),
                ids[c % ids.len()],
                c,
                until,
            ))
        })
        .collect();
    let (mut latencies, mut failures) = (Vec::new(), BTreeMap::new());
    for r in robots {
        let (l, f) = r.await?;
        latencies.extend(l);
        for (why, n) in f {
            *failures.entry(why).or_insert(0) += n;
        }
    }
    let seconds = started.elapsed().as_secs_f64();
    let machine_after = machine_jiffies();
    let cpu_after: f64 = replicas.iter().map(Replica::cpu_seconds).sum();
    drop(replicas);
    drop_database(&o.database_url, &db).await;
    latencies.sort_by(f64::total_cmp);
    let busy = (machine_after.0 - machine_before.0) / (machine_after.1 - machine_before.1).max(1.0);
    Ok(Row {
        replicas: n,
        proposals: latencies.len(),
        failures,
        seconds,
        latencies_ms: latencies,
        replica_cpu: cpu_after - cpu_before,
        machine_busy: busy,
    })
}

/// Runs the benchmark and prints its table.
pub async fn run(o: &ReplicasOptions) -> anyhow::Result<()> {
    anyhow::ensure!(
        precond::store::Backend::of_url(&o.database_url) == precond::store::Backend::Postgres,
        "--database-url must name a PostgreSQL server (postgres://…)"
    );
    anyhow::ensure!(
        !o.replicas.is_empty() && o.replicas.iter().all(|&n| (1..=16).contains(&n)),
        "--replicas: counts from 1 to 16"
    );
    anyhow::ensure!(
        o.clients >= 1 && o.experiments >= 1,
        "--clients and --experiments ≥ 1"
    );
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!(
        "precond bench replicas: {} clients over {} experiments, {:.0} s each, {cores} cores, \
         planning slots per replica: {}, PostgreSQL at {}",
        o.clients,
        o.experiments,
        o.seconds,
        o.plans_per_replica
            .map_or_else(|| format!("{cores} (default)"), |p| p.to_string()),
        precond::store::redact(&o.database_url)
    );
    println!(
        "{:>8} {:>11} {:>9} {:>9} {:>9} {:>8} {:>12} {:>12}",
        "replicas",
        "proposals/s",
        "p50 ms",
        "p99 ms",
        "failures",
        "ratio",
        "replica CPU",
        "machine busy"
    );
    let mut rows: Vec<Row> = Vec::new();
    for &n in &o.replicas {
        let row = measure(o, n).await?;
        let ratio = rows.first().map_or(1.0, |first| row.rate() / first.rate());
        println!(
            "{:>8} {:>11.1} {:>9.1} {:>9.1} {:>9} {:>8.2} {:>10.1} s {:>11.0} %",
            row.replicas,
            row.rate(),
            row.quantile(0.5),
            row.quantile(0.99),
            row.failures.values().sum::<usize>(),
            ratio,
            row.replica_cpu,
            row.machine_busy * 100.0
        );
        rows.push(row);
    }
    for row in &rows {
        if !row.failures.is_empty() {
            println!(
                "failures with {} replicas: {:?}",
                row.replicas, row.failures
            );
        }
    }
    Ok(())
}
