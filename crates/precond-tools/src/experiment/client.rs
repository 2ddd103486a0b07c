//! A thin HTTP client for the endpoints the harness drives: experiments, proposals,
//! trajectories, the model, plans and precondition queries, speaking the typed bodies of
//! [`precond::api`]. An error status becomes an `anyhow` error carrying the service's error body,
//! except `422 no_plan`, which is an answer ([`Proposed::NoPlan`]).

use anyhow::{Context, bail};
use precond::api::{
    ErrorBody, ExperimentRequest, ExperimentResponse, HealthResponse, Judgement, ModelResponse,
    PlanRequest, PlanResponse, Point, PreconditionRequest, PreconditionResponse, ProposalRequest,
    ProposalResponse, TrajectoryCreated, TrajectoryRequest,
};
use precond_core::domain::Transition;
use precond_core::planning::Strategy;
use serde::de::DeserializeOwned;
use serde_json::Value;
use std::time::{Duration, Instant};

/// Most points sent in one precondition query (the service's limit).
pub const MAX_POINTS_PER_QUERY: usize = precond_core::limits::MAX_POINTS;

/// A client of one `precond` service.
#[derive(Debug, Clone)]
pub struct ApiClient {
    base: String,
    http: reqwest::Client,
}

/// What a proposal request returned.
#[derive(Debug, Clone)]
pub enum Proposed {
    /// A trajectory to execute.
    Trajectory(Box<ProposalResponse>),
    /// No candidate reached the goal inside the precondition (`422 no_plan`).
    NoPlan,
    /// The search ran into the server's planning deadline (`503 deadline_exceeded`).
    TimedOut,
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

    /// A `POST` to experiment `id`'s `tail` (`proposals`, `plans`, `model/refit`, …).
    fn post_to(&self, id: i64, tail: &str) -> reqwest::RequestBuilder {
        self.http
            .post(self.url(&format!("/v1/experiments/{id}/{tail}")))
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
        let _: HealthResponse = self
            .expect(self.http.get(self.url("/healthz")), "GET /healthz")
            .await?;
        Ok(())
    }

    /// `POST /v1/experiments`.
    pub async fn create_experiment(
        &self,
        body: &ExperimentRequest,
    ) -> anyhow::Result<ExperimentResponse> {
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
        strategy: Option<Strategy>,
    ) -> anyhow::Result<Proposed> {
        let body = ProposalRequest {
            start: start.to_vec(),
            goal: goal.to_vec(),
            client_id: client_id.map(str::to_string),
            strategy,
            candidates: None,
            models: None,
        };
        let what = "POST /proposals";
        let (status, body) = self
            .send(self.post_to(id, "proposals").json(&body), what)
            .await?;
        let code = serde_json::from_value::<ErrorBody>(body.clone()).map(|e| e.error.code);
        match (status, code.as_deref()) {
            (422, Ok("no_plan")) => return Ok(Proposed::NoPlan),
            (503, Ok("deadline_exceeded")) => return Ok(Proposed::TimedOut),
            _ => {}
        }
        if !(200..300).contains(&status) {
            bail!("{what}: HTTP {status}: {body}");
        }
        let p: ProposalResponse =
            serde_json::from_value(body).with_context(|| format!("{what}: unexpected body"))?;
        Ok(Proposed::Trajectory(Box::new(p)))
    }

    /// `POST /v1/experiments/{id}/trajectories`.
    pub async fn post_trajectory(
        &self,
        id: i64,
        proposal_id: Option<i64>,
        transitions: Vec<Transition>,
    ) -> anyhow::Result<TrajectoryCreated> {
        let body = TrajectoryRequest {
            proposal_id,
            partial: false,
            source: None,
            transitions,
        };
        self.expect(
            self.post_to(id, "trajectories").json(&body),
            "POST /trajectories",
        )
        .await
    }

    /// `GET /v1/experiments/{id}/model`.
    pub async fn model(&self, id: i64) -> anyhow::Result<ModelResponse> {
        self.expect(
            self.http
                .get(self.url(&format!("/v1/experiments/{id}/model"))),
            "GET /model",
        )
        .await
    }

    /// `POST /v1/experiments/{id}/model/refit`: fit now on everything stored. A fit that
    /// outlasts the service's deadline is answered `202` with the old version and goes on in
    /// the background; this waits for it.
    pub async fn refit(&self, id: i64) -> anyhow::Result<ModelResponse> {
        let before = self.model(id).await?.version;
        let mut m: ModelResponse = self
            .expect(self.post_to(id, "model/refit"), "POST /model/refit")
            .await?;
        while m.version <= before {
            tokio::time::sleep(Duration::from_millis(100)).await;
            m = self.model(id).await?;
        }
        Ok(m)
    }

    /// Waits until the served model covers `n_trajectories` trajectories (the background refit
    /// after a completed batch), polling with short sleeps; after `timeout` forces a refit.
    pub async fn wait_for_fit(
        &self,
        id: i64,
        n_trajectories: i64,
        timeout: Duration,
    ) -> anyhow::Result<ModelResponse> {
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

    /// `POST /v1/experiments/{id}/plans` with the experiment's test β. A search that runs into
    /// the server's planning deadline (`503 deadline_exceeded`) is answered as no plan found,
    /// with the extensions it spent.
    pub async fn plan(&self, id: i64, start: &[f64], goal: &[f64]) -> anyhow::Result<PlanResponse> {
        self.plan_within(id, start, goal, None).await
    }

    /// [`plan`](Self::plan) with a search budget of `max_extensions` (`None`: the
    /// experiment's `learning.max_extensions`).
    pub async fn plan_within(
        &self,
        id: i64,
        start: &[f64],
        goal: &[f64],
        max_extensions: Option<u32>,
    ) -> anyhow::Result<PlanResponse> {
        let body = PlanRequest {
            start: start.to_vec(),
            goal: goal.to_vec(),
            beta: None,
            candidates: None,
            max_extensions,
            models: None,
        };
        let what = "POST /plans";
        let (status, body) = self
            .send(self.post_to(id, "plans").json(&body), what)
            .await?;
        if status == 503
            && let Ok(e) = serde_json::from_value::<ErrorBody>(body.clone())
            && e.error.code == "deadline_exceeded"
        {
            return Ok(PlanResponse {
                found: false,
                extensions: e.error.details["extensions"].as_u64().unwrap_or(0) as usize,
                rejections: precond::api::RejectionCounts {
                    constraints: 0,
                    precondition: 0,
                },
                beta: f64::NAN,
                d_max: f64::NAN,
                model_version: -1,
                trajectory: None,
                candidates: None,
                step_models: None,
                model_calls: None,
            });
        }
        if !(200..300).contains(&status) {
            bail!("{what}: HTTP {status}: {body}");
        }
        serde_json::from_value(body).with_context(|| format!("{what}: unexpected body"))
    }

    /// `POST /v1/experiments/{id}/precondition` for any number of `(s, a)` points (split into
    /// queries of at most [`MAX_POINTS_PER_QUERY`]), with the experiment's test β.
    pub async fn precondition(
        &self,
        id: i64,
        points: &[(&[f64], &[f64])],
    ) -> anyhow::Result<Vec<Judgement>> {
        Ok(self.precondition_at(id, points).await?.0)
    }

    /// [`ApiClient::precondition`] and the β the service judged at (the experiment's test β,
    /// or the β its current version certifies).
    pub async fn precondition_at(
        &self,
        id: i64,
        points: &[(&[f64], &[f64])],
    ) -> anyhow::Result<(Vec<Judgement>, f64)> {
        let mut out = Vec::with_capacity(points.len());
        let mut beta = f64::NAN;
        for chunk in points.chunks(MAX_POINTS_PER_QUERY) {
            let body = PreconditionRequest {
                points: chunk
                    .iter()
                    .map(|(s, a)| Point {
                        s: s.to_vec(),
                        a: a.to_vec(),
                        s_pred: None,
                    })
                    .collect(),
                beta: None,
                model: None,
            };
            let j: PreconditionResponse = self
                .expect(
                    self.post_to(id, "precondition").json(&body),
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
            beta = j.beta;
            out.extend(j.results);
        }
        Ok((out, beta))
    }
}
