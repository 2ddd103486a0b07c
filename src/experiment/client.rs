//! A thin HTTP client for the endpoints the harness drives: experiments, proposals,
//! trajectories, the model, plans and precondition queries. Only the fields the harness reads are
//! decoded; an error status becomes an `anyhow` error carrying the service's error body, except
//! `422 no_plan`, which is an answer ([`Proposed::NoPlan`]).

use anyhow::{Context, bail};
use serde::Deserialize;
use serde::de::DeserializeOwned;
use serde_json::{Value, json};
use std::time::{Duration, Instant};

/// Most points sent in one precondition query (the service's limit).
pub const MAX_POINTS_PER_QUERY: usize = 100_000;

/// A client of one `precond` service.
#[derive(Debug, Clone)]
pub struct ApiClient {
    base: String,
    http: reqwest::Client,
}

/// The fields of a created experiment the harness uses.
#[derive(Debug, Clone, Deserialize)]
pub struct CreatedExperiment {
    /// Identifier.
    pub id: i64,
    /// The resolved tolerance.
    pub d_max: f64,
}

/// A planned trajectory as the service returns it.
#[derive(Debug, Clone, Deserialize)]
pub struct PlannedTrajectory {
    /// Predicted states, one more than `actions`.
    pub states: Vec<Vec<f64>>,
    /// Actions.
    pub actions: Vec<Vec<f64>>,
}

/// The fields of a proposal the harness uses.
#[derive(Debug, Clone, Deserialize)]
pub struct Proposal {
    /// Identifier, to link the executed trajectory.
    pub id: i64,
    /// The trajectory to execute.
    pub trajectory: PlannedTrajectory,
    /// The β it was planned with.
    pub beta: f64,
    /// The service's learning iteration when it was planned.
    pub iteration: i64,
}

/// What a proposal request returned.
#[derive(Debug, Clone)]
pub enum Proposed {
    /// A trajectory to execute.
    Trajectory(Box<Proposal>),
    /// No candidate reached the goal inside the precondition (`422 no_plan`).
    NoPlan,
}

/// A test-time plan.
#[derive(Debug, Clone, Deserialize)]
pub struct Plan {
    /// Whether a plan was found within the extension budget.
    pub found: bool,
    /// Extensions spent.
    pub extensions: u64,
    /// The plan, when found.
    pub trajectory: Option<PlannedTrajectory>,
}

/// The served model's bookkeeping.
#[derive(Debug, Clone, Deserialize)]
pub struct ModelInfo {
    /// Version (0: the prior).
    pub version: i64,
    /// Training transitions of the fit.
    pub n_train: i64,
    /// Trajectories the fit covers.
    pub n_trajectories: i64,
}

/// One answer of a precondition query.
#[derive(Debug, Clone, Copy, Deserialize)]
pub struct Judgement {
    /// Predicted deviation mean.
    pub mu: f64,
    /// Predicted deviation standard deviation (noise included).
    pub sigma: f64,
    /// `μ + βσ`.
    pub upper: f64,
    /// `upper < d_max`.
    pub inside: bool,
}

#[derive(Deserialize)]
struct Judgements {
    results: Vec<Judgement>,
}

/// One executed transition to post.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Executed {
    /// State before.
    pub s: Vec<f64>,
    /// Action executed.
    pub a: Vec<f64>,
    /// True next state.
    pub s_next: Vec<f64>,
}

impl ApiClient {
    /// A client of the service at `base` (e.g. `http://127.0.0.1:8080`).
    pub fn new(base: &str) -> Self {
        Self {
            base: base.trim_end_matches('/').to_string(),
            http: reqwest::Client::new(),
        }
    }

    /// The service's base URL.
    pub fn base(&self) -> &str {
        &self.base
    }

    fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    /// Sends a request and returns the status and the JSON body.
    async fn send(&self, req: reqwest::RequestBuilder, what: &str) -> anyhow::Result<(u16, Value)> {
        let resp = req
            .send()
            .await
            .with_context(|| format!("{what}: request"))?;
        let status = resp.status().as_u16();
        let body: Value = resp
            .json()
            .await
            .with_context(|| format!("{what}: reading the JSON body (status {status})"))?;
        Ok((status, body))
    }

    async fn expect<T: DeserializeOwned>(
        &self,
        req: reqwest::RequestBuilder,
        what: &str,
    ) -> anyhow::Result<T> {
        let (status, body) = self.send(req, what).await?;
        if !(200..300).contains(&status) {
            bail!("{what}: HTTP {status}: {body}");
        }
        serde_json::from_value(body).with_context(|| format!("{what}: unexpected body"))
    }

    /// Checks that the service answers `/healthz`.
    pub async fn health(&self) -> anyhow::Result<()> {
        let _: Value = self
            .expect(self.http.get(self.url("/healthz")), "GET /healthz")
            .await?;
        Ok(())
    }

    /// `POST /v1/experiments`.
    pub async fn create_experiment(&self, body: &Value) -> anyhow::Result<CreatedExperiment> {
        self.expect(
            self.http.post(self.url("/v1/experiments")).json(body),
            "POST /v1/experiments",
        )
        .await
    }

    /// `POST /v1/experiments/{id}/proposals`, optionally leased to `client_id` and overriding
    /// the strategy. (The service answers a client's open proposal again until it is executed,
    /// whatever the problem: leave `client_id` out for proposals that are not executed.)
    pub async fn propose(
        &self,
        id: i64,
        start: &[f64],
        goal: &[f64],
        client_id: Option<&str>,
        strategy: Option<&str>,
    ) -> anyhow::Result<Proposed> {
        let mut body = json!({"start": start, "goal": goal});
        if let Some(c) = client_id {
            body["client_id"] = json!(c);
        }
        if let Some(s) = strategy {
            body["strategy"] = json!(s);
        }
        let what = "POST /proposals";
        let (status, body) = self
            .send(
                self.http
                    .post(self.url(&format!("/v1/experiments/{id}/proposals")))
                    .json(&body),
                what,
            )
            .await?;
        if status == 422 && body["error"]["code"] == "no_plan" {
            return Ok(Proposed::NoPlan);
        }
        if !(200..300).contains(&status) {
            bail!("{what}: HTTP {status}: {body}");
        }
        let p: Proposal =
            serde_json::from_value(body).with_context(|| format!("{what}: unexpected body"))?;
        Ok(Proposed::Trajectory(Box::new(p)))
    }

    /// `POST /v1/experiments/{id}/trajectories`.
    pub async fn post_trajectory(
        &self,
        id: i64,
        proposal_id: Option<i64>,
        transitions: &[Executed],
    ) -> anyhow::Result<()> {
        let body =
            json!({"proposal_id": proposal_id, "partial": false, "transitions": transitions});
        let _: Value = self
            .expect(
                self.http
                    .post(self.url(&format!("/v1/experiments/{id}/trajectories")))
                    .json(&body),
                "POST /trajectories",
            )
            .await?;
        Ok(())
    }

    /// `GET /v1/experiments/{id}/model`.
    pub async fn model(&self, id: i64) -> anyhow::Result<ModelInfo> {
        self.expect(
            self.http
                .get(self.url(&format!("/v1/experiments/{id}/model"))),
            "GET /model",
        )
        .await
    }

    /// `POST /v1/experiments/{id}/model/refit`: fit now on everything stored.
    pub async fn refit(&self, id: i64) -> anyhow::Result<ModelInfo> {
        self.expect(
            self.http
                .post(self.url(&format!("/v1/experiments/{id}/model/refit"))),
            "POST /model/refit",
        )
        .await
    }

    /// Waits until the served model covers `n_trajectories` trajectories (the background refit
    /// after a completed batch), polling with short sleeps; after `timeout` forces a refit.
    pub async fn wait_for_fit(
        &self,
        id: i64,
        n_trajectories: i64,
        timeout: Duration,
    ) -> anyhow::Result<ModelInfo> {
        let started = Instant::now();
        let mut sleep = Duration::from_millis(5);
        loop {
            let m = self.model(id).await?;
            if m.n_trajectories >= n_trajectories {
                return Ok(m);
            }
            if started.elapsed() > timeout {
                tracing::warn!(
                    experiment = id,
                    "no background fit after {timeout:?}; forcing a refit"
                );
                return self.refit(id).await;
            }
            tokio::time::sleep(sleep).await;
            sleep = (sleep * 2).min(Duration::from_millis(100));
        }
    }

    /// `POST /v1/experiments/{id}/plans` with the experiment's test β.
    pub async fn plan(&self, id: i64, start: &[f64], goal: &[f64]) -> anyhow::Result<Plan> {
        self.expect(
            self.http
                .post(self.url(&format!("/v1/experiments/{id}/plans")))
                .json(&json!({"start": start, "goal": goal})),
            "POST /plans",
        )
        .await
    }

    /// `POST /v1/experiments/{id}/precondition` for any number of `(s, a)` points (split into
    /// queries of at most [`MAX_POINTS_PER_QUERY`]), with the experiment's test β.
    pub async fn precondition(
        &self,
        id: i64,
        points: &[(&[f64], &[f64])],
    ) -> anyhow::Result<Vec<Judgement>> {
        let mut out = Vec::with_capacity(points.len());
        for chunk in points.chunks(MAX_POINTS_PER_QUERY) {
            let body = json!({
                "points": chunk.iter().map(|(s, a)| json!({"s": s, "a": a})).collect::<Vec<_>>(),
            });
            let j: Judgements = self
                .expect(
                    self.http
                        .post(self.url(&format!("/v1/experiments/{id}/precondition")))
                        .json(&body),
                    "POST /precondition",
                )
                .await?;
            if j.results.len() != chunk.len() {
                bail!(
                    "POST /precondition: {} answers for {} points",
                    j.results.len(),
                    chunk.len()
                );
            }
            out.extend(j.results);
        }
        Ok(out)
    }
}
