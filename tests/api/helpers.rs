//! Test harness: a real server on a real socket over a real SQLite file in a temp dir — or,
//! when `PRECOND_TEST_POSTGRES` names a PostgreSQL server (`scripts/ci-postgres.sh` starts one),
//! over a new PostgreSQL database of that server per test.

use precond::http::{AppState, HttpConfig, serve};
use precond::remote_model::{ModelCallLimits, ModelUrlPolicy};
use precond::service::{Limits, Service};
use precond::store::Store;
use serde_json::{Value, json};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// A running server and a client for it.
pub struct TestApp {
    pub addr: SocketAddr,
    pub client: reqwest::Client,
    pub db_path: PathBuf,
    shutdown: Option<oneshot::Sender<()>>,
    handle: Option<JoinHandle<anyhow::Result<()>>>,
}

/// How long a test waits for a fit before it gives up: far beyond any fit's time on a busy
/// machine, only to end a test that would hang.
pub const FIT_PATIENCE: std::time::Duration = std::time::Duration::from_secs(600);

/// The admin URL of the PostgreSQL server the tests run against instead of SQLite files, if
/// one is set.
pub fn postgres_admin() -> Option<String> {
    std::env::var("PRECOND_TEST_POSTGRES")
        .ok()
        .filter(|url| !url.is_empty())
}

/// Whether a test of SQLite's own file (migrations of old files, backups) should stand aside:
/// the tests run against PostgreSQL. Says so on stderr.
pub fn sqlite_only(test: &str) -> bool {
    let postgres = postgres_admin().is_some();
    if postgres {
        eprintln!("{test}: tests the SQLite file; the SQLite run covers it");
    }
    postgres
}

/// A database for one test and a temp dir that lives as long as the test: a SQLite file in
/// the dir, or (see [`postgres_admin`]) a new PostgreSQL database, whose URL stands in the
/// returned path.
pub fn temp_db() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = match postgres_admin() {
        Some(admin) => PathBuf::from(new_postgres_database(&admin)),
        None => dir.path().join("precond.db"),
    };
    (dir, path)
}

/// Creates a new, empty database on the server of `admin` and returns its URL.
pub fn new_postgres_database(admin: &str) -> String {
    let name = format!("precond_test_{}", uuid::Uuid::new_v4().simple());
    let (server, _) = admin.rsplit_once('/').expect("a postgres:// URL");
    let url = format!("{server}/{name}");
    let admin = admin.to_string();
    // On a thread of its own: the tests' runtimes are single-threaded and cannot block.
    std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async {
            use sqlx::Connection;
            let mut admin = sqlx::PgConnection::connect(&admin)
                .await
                .expect("connecting to the test PostgreSQL server");
            sqlx::query(&format!("CREATE DATABASE {name}"))
                .execute(&mut admin)
                .await
                .expect("creating a test database");
        });
    })
    .join()
    .unwrap();
    url
}

/// A server on a new database in a temp dir; the dir lives as long as the returned guard.
pub async fn fresh_app() -> (tempfile::TempDir, TestApp) {
    let (dir, db) = temp_db();
    (dir, spawn_app(&db).await)
}

/// A server on a new database with one experiment, created from `body`, and its id; the dir
/// lives as long as the returned guard.
pub async fn fresh_experiment(body: Value) -> (tempfile::TempDir, TestApp, i64) {
    let (dir, app) = fresh_app().await;
    let id = app.create_experiment(body).await;
    (dir, app, id)
}

/// A server with HTTP settings on a new database; the dir lives as long as the returned guard.
pub async fn fresh_app_with(config: HttpConfig) -> (tempfile::TempDir, TestApp) {
    let (dir, db) = temp_db();
    (dir, spawn_app_with(&db, config).await)
}

/// A server under the operator's `limits` on a new database; the dir lives as long as the
/// returned guard.
pub async fn fresh_app_with_limits(limits: Limits) -> (tempfile::TempDir, TestApp) {
    let (dir, db) = temp_db();
    (dir, spawn_app_with_limits(&db, limits).await)
}

/// Starts a server on the database file at `db_path` (bind first, then spawn: no sleeps).
pub async fn spawn_app(db_path: &Path) -> TestApp {
    spawn_app_with(db_path, HttpConfig::default()).await
}

/// Same, with HTTP settings.
pub async fn spawn_app_with(db_path: &Path, config: HttpConfig) -> TestApp {
    let store = open_store(db_path).await;
    spawn_state(db_path, AppState::new(store, config)).await
}

/// Starts a server that allows remote dynamics models under `prefixes`.
pub async fn spawn_app_allowing_models(db_path: &Path, prefixes: &[String]) -> TestApp {
    let store = open_store(db_path).await;
    let service = Service::with_model_urls(store, ModelUrlPolicy::new(prefixes).unwrap());
    spawn_state(
        db_path,
        AppState::with_service(service, HttpConfig::default()),
    )
    .await
}

/// Starts a server that allows remote models under `prefixes`, with the operator's `limits`
/// and limits on model calls.
pub async fn spawn_app_with_models(
    db_path: &Path,
    prefixes: &[String],
    limits: Limits,
    model_limits: ModelCallLimits,
) -> TestApp {
    let store = open_store(db_path).await;
    let service = Service::with_model_urls(store, ModelUrlPolicy::new(prefixes).unwrap())
        .with_limits(limits)
        .with_model_limits(model_limits);
    spawn_state(
        db_path,
        AppState::with_service(service, HttpConfig::default()),
    )
    .await
}

/// Starts a server under the operator's `limits`.
pub async fn spawn_app_with_limits(db_path: &Path, limits: Limits) -> TestApp {
    let store = open_store(db_path).await;
    let service = Service::new(store).with_limits(limits);
    spawn_state(
        db_path,
        AppState::with_service(service, HttpConfig::default()),
    )
    .await
}

/// Opens the store at `db_path` (the server's file, a backup) as the server does.
pub async fn open_store(db_path: &Path) -> Store {
    Store::open(db_path.to_str().unwrap())
        .await
        .expect("open store")
}

async fn spawn_state(db_path: &Path, state: AppState) -> TestApp {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (tx, rx) = oneshot::channel::<()>();
    let handle = tokio::spawn(serve(listener, state, async {
        let _ = rx.await;
    }));
    TestApp {
        addr,
        client: reqwest::Client::new(),
        db_path: db_path.to_path_buf(),
        shutdown: Some(tx),
        handle: Some(handle),
    }
}

impl TestApp {
    /// Waits until experiment `id`'s answering model covers `n_trajectories` trajectories, and
    /// returns it. A fit takes as long as the machine needs: the wait is bounded only to
    /// end a test that would otherwise hang (10 minutes).
    pub async fn wait_for_model(&self, id: i64, n_trajectories: i64) -> Value {
        let deadline = std::time::Instant::now() + FIT_PATIENCE;
        loop {
            let (_, model) = self.get(&format!("/v1/experiments/{id}/model")).await;
            if model["n_trajectories"].as_i64() >= Some(n_trajectories) {
                return model;
            }
            assert!(
                std::time::Instant::now() < deadline,
                "no model covering {n_trajectories} trajectories within {FIT_PATIENCE:?}"
            );
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    }

    /// A forced refit of experiment `id`, and the model it made: answered at once (`200`) or,
    /// when the fit outlasts the planning deadline on a busy machine (`202`, as documented),
    /// once the background fit has swapped its version in.
    pub async fn refit(&self, id: i64) -> Value {
        let (status, answered) = self.post_at(id, "model/refit", &json!({})).await;
        match status {
            200 => answered,
            202 => {
                let before = answered["version"].as_i64().unwrap();
                let deadline = std::time::Instant::now() + FIT_PATIENCE;
                loop {
                    let (_, model) = self.get(&format!("/v1/experiments/{id}/model")).await;
                    if model["version"].as_i64() > Some(before) {
                        return model;
                    }
                    assert!(std::time::Instant::now() < deadline, "the refit finished");
                    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                }
            }
            _ => panic!("refit answered {status}: {answered}"),
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://{}{}", self.addr, path)
    }

    /// Graceful shutdown; waits until the server has stopped and closed the store.
    pub async fn stop(mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(h) = self.handle.take() {
            h.await.unwrap().unwrap();
        }
    }

    /// Stops this server and starts a new one on the same file.
    pub async fn restart(self) -> TestApp {
        let path = self.db_path.clone();
        self.stop().await;
        spawn_app(&path).await
    }

    pub async fn get(&self, path: &str) -> (u16, Value) {
        answer(self.client.get(self.url(path))).await
    }

    pub async fn post(&self, path: &str, body: &Value) -> (u16, Value) {
        answer(self.client.post(self.url(path)).json(body)).await
    }

    /// `GET /v1/experiments/{id}/{tail}` (`tail` e.g. `model`, `timeline`; `""`: the experiment
    /// itself).
    pub async fn get_at(&self, id: i64, tail: &str) -> (u16, Value) {
        match tail {
            "" => self.get(&format!("/v1/experiments/{id}")).await,
            _ => self.get(&format!("/v1/experiments/{id}/{tail}")).await,
        }
    }

    /// Posts `body` to `/v1/experiments/{id}/{tail}` (`tail` e.g. `trajectories`, `proposals`,
    /// `plans`, `precondition`, `model/refit`).
    pub async fn post_at(&self, id: i64, tail: &str, body: &Value) -> (u16, Value) {
        self.post(&format!("/v1/experiments/{id}/{tail}"), body)
            .await
    }

    /// Asks experiment `id` for a proposal: posts `ask` to `/v1/experiments/{id}/proposals`.
    pub async fn propose(&self, id: i64, ask: &Value) -> (u16, Value) {
        self.post_at(id, "proposals", ask).await
    }

    /// Asks experiment `id` for a proposal, asserting that it is made (201), and returns it.
    pub async fn assert_proposes(&self, id: i64, ask: &Value) -> Value {
        let (status, body) = self.propose(id, ask).await;
        assert_eq!(status, 201, "{body}");
        body
    }

    /// Asks kinematic experiment `id` for a short proposal in free space and asserts that it is
    /// made (201) within `limit`: a planner slot was free.
    pub async fn assert_proposes_within(&self, id: i64, limit: std::time::Duration) {
        let started = std::time::Instant::now();
        self.assert_proposes(id, &json!({"start": [0.1, 0.2], "goal": [0.3, 0.2]}))
            .await;
        assert_within(started, limit);
    }

    /// Posts a trajectory to experiment `id`, asserting that it is stored (201), and returns
    /// the answer.
    pub async fn store_trajectory(&self, id: i64, trajectory: &Value) -> Value {
        let (status, body) = self.post_at(id, "trajectories", trajectory).await;
        assert_eq!(status, 201, "{body}");
        body
    }

    /// Sends a bodiless `method` request to `path` and returns the whole response (for the
    /// headers and statuses that [`TestApp::get`] does not show).
    pub async fn request(&self, method: reqwest::Method, path: &str) -> reqwest::Response {
        self.client
            .request(method, self.url(path))
            .send()
            .await
            .unwrap()
    }

    pub async fn post_raw(&self, path: &str, body: impl Into<reqwest::Body>) -> (u16, Value) {
        let request = self
            .client
            .post(self.url(path))
            .header("content-type", "application/json")
            .body(body);
        answer(request).await
    }

    /// Posts `body` to `path` from a client that gives up 300 ms in, as a robot that went
    /// away: the answer is its timeout error unless the server was quicker.
    pub async fn post_and_go_away(
        &self,
        path: &str,
        body: &Value,
    ) -> reqwest::Result<reqwest::Response> {
        let impatient = reqwest::Client::builder()
            .timeout(std::time::Duration::from_millis(300))
            .build()
            .unwrap();
        impatient.post(self.url(path)).json(body).send().await
    }

    /// The Prometheus text of `GET /metrics`.
    pub async fn metrics(&self) -> String {
        let r = self.client.get(self.url("/metrics")).send().await.unwrap();
        r.text().await.unwrap()
    }

    /// Creates an experiment and returns its id.
    pub async fn create_experiment(&self, body: Value) -> i64 {
        let (status, body) = self.post("/v1/experiments", &body).await;
        assert_eq!(status, 201, "{body}");
        body["id"].as_i64().unwrap()
    }

    /// All transitions of an experiment, following the cursor through pages of 7.
    pub async fn all_transitions(&self, id: i64) -> Vec<Value> {
        crate::common::transitions_in_pages(&self.client, &self.url(""), id, 7).await
    }
}

/// Sends `request`: its status and its JSON body (`null` when it has none).
async fn answer(request: reqwest::RequestBuilder) -> (u16, Value) {
    let r = request.send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

impl Drop for TestApp {
    fn drop(&mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
    }
}

/// A gridworld trajectory as the true world would produce it on the default map: from (x0, y)
/// moving right `n` times on a row without ice or obstacles.
pub fn free_row_trajectory(x0: i64, y: i64, n: i64) -> Value {
    let transitions: Vec<Value> = (0..n)
        .map(|k| json!({"s": [x0 + k, y], "a": [1, 0], "s_next": [x0 + k + 1, y]}))
        .collect();
    json!({ "transitions": transitions })
}

/// The error code of an error body.
pub fn code(body: &Value) -> &str {
    body["error"]["code"].as_str().unwrap_or("<none>")
}

/// The message of an error body (panics without one).
pub fn message(body: &Value) -> &str {
    body["error"]["message"]
        .as_str()
        .unwrap_or_else(|| panic!("no error message in {body}"))
}

/// The `details.reason` of an error body (panics without one).
pub fn reason(body: &Value) -> &str {
    body["error"]["details"]["reason"]
        .as_str()
        .unwrap_or_else(|| panic!("no details.reason in {body}"))
}

/// The integer `key` of every item of the array `list` (panics on anything else).
pub fn ints(list: &Value, key: &str) -> Vec<i64> {
    items(list)
        .map(|item| item[key].as_i64().unwrap())
        .collect()
}

/// The number `key` of every item of the array `list` (panics on anything else).
pub fn floats(list: &Value, key: &str) -> Vec<f64> {
    items(list)
        .map(|item| item[key].as_f64().unwrap())
        .collect()
}

/// How many items of the array `list` have `key` true.
pub fn count_true(list: &Value, key: &str) -> usize {
    items(list).filter(|item| item[key] == true).count()
}

fn items(list: &Value) -> std::slice::Iter<'_, Value> {
    list.as_array()
        .unwrap_or_else(|| panic!("not an array: {list}"))
        .iter()
}

/// Every move from every open cell of the default gridworld's rows `rows` (all of them:
/// `0..12`), executed in the true world, as trajectories of at most `per_trajectory`
/// transitions.
pub fn gridworld_moves(rows: std::ops::Range<i64>, per_trajectory: usize) -> Vec<Value> {
    use precond::domain::{Cell, IcyGridworld, MOVES};
    use precond::sim::Simulated;
    let grid = IcyGridworld::default_layout();
    let mut world = grid.world();
    let mut transitions = Vec::new();
    for y in rows {
        for x in 0..grid.width() as i64 {
            if grid.cell(x, y) == Some(Cell::Obstacle) {
                continue;
            }
            for m in MOVES {
                let s = [x as f64, y as f64];
                let next = world.step(&s, &m);
                transitions.push(json!({"s": s, "a": m, "s_next": next}));
            }
        }
    }
    transitions
        .chunks(per_trajectory)
        .map(|c| json!({"transitions": c}))
        .collect()
}

/// Asserts that less than `limit` has passed since `started` (saying how much did).
pub fn assert_within(started: std::time::Instant, limit: std::time::Duration) {
    let elapsed = started.elapsed();
    assert!(elapsed < limit, "{elapsed:?}");
}

/// `n` kinematic transitions on a lattice of the unit square, moving by `(0.05, 0)`; the world
/// pushes the robot up by 0.1 where `x > 0.5` (the model is wrong there).
pub fn pushed_lattice(n: usize, offset: usize) -> Value {
    let transitions: Vec<Value> = (0..n)
        .map(|k| {
            let i = k + offset;
            let (x, y) = ((i % 37) as f64 / 40.0, ((i / 37) % 37) as f64 / 40.0);
            let push = if x > 0.5 { 0.1 } else { 0.0 };
            json!({"s": [x, y], "a": [0.05, 0.0], "s_next": [x + 0.05, (y + push).min(1.0)]})
        })
        .collect();
    json!({ "transitions": transitions })
}
