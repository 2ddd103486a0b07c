//! `/v1/experiments/{id}/proposals` (ask: which trajectory should the robot try next?) and
//! `/plans` (test time: is there a trustworthy plan?).

use super::AppState;
use super::extract::{ApiJson, ApiPath};
use crate::error::Error;
use crate::live::{LiveExperiment, fit_seed};
use crate::planning::{self, PlanningError, Strategy, Trajectory};
use crate::settings::StrategySetting;
use crate::store::{NewProposal, StoredProposal};
use axum::Json;
use axum::extract::State;
use axum::http::StatusCode;
use serde::Deserialize;
use serde_json::{Value, json};
use std::sync::Arc;

/// Longest accepted `client_id`.
pub const MAX_CLIENT_ID_LEN: usize = 200;

/// `POST /v1/experiments/{id}/proposals` body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProposalRequest {
    /// Start state.
    pub start: Vec<f64>,
    /// Goal (the domain's goal vector: a cell, a state, a target volume).
    pub goal: Vec<f64>,
    /// The client the proposal is leased to; asking again while it is open returns it.
    pub client_id: Option<String>,
    /// Overrides the experiment's strategy for this proposal.
    pub strategy: Option<StrategySetting>,
}

/// `POST /v1/experiments/{id}/plans` body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanRequest {
    /// Start state.
    pub start: Vec<f64>,
    /// Goal.
    pub goal: Vec<f64>,
    /// β; default `learning.test_beta`.
    pub beta: Option<f64>,
}

fn check_problem(live: &LiveExperiment, start: &[f64], goal: &[f64]) -> Result<(), Error> {
    live.domain
        .validate_state(start)
        .map_err(|e| Error::validation("start", e.0))?;
    live.domain
        .validate_goal(goal)
        .map_err(|e| Error::validation("goal", e.0))
}

fn planning_error(e: PlanningError) -> Error {
    match e {
        PlanningError::NoPlan { extensions } => Error::NoPlan { extensions },
        PlanningError::InvalidInput { field, reason } => Error::validation(field, reason),
        PlanningError::InvalidSettings { field, reason } => {
            Error::validation(format!("learning.{field}"), reason)
        }
        e @ PlanningError::ModelOutput { .. } => Error::Internal(e.into()),
    }
}

/// A seed for one planning request from the experiment's seed, a salt (how much data or which
/// model version the request sees) and the problem.
fn problem_seed(seed: u64, salt: i64, start: &[f64], goal: &[f64]) -> u64 {
    start
        .iter()
        .chain(goal)
        .fold(fit_seed(seed, salt), |h, x| fit_seed(h ^ x.to_bits(), 1))
}

fn finite_all(values: &[f64]) -> bool {
    values.iter().all(|x| x.is_finite())
}

fn trajectory_body(t: &Trajectory, alpha_step: Option<(&[f64], f64)>) -> Result<Value, Error> {
    if !finite_all(&t.mu) || !finite_all(&t.sigma) {
        return Err(Error::Internal(anyhow::anyhow!(
            "the model answered a non-finite deviation along a trajectory"
        )));
    }
    let mut body = json!({
        "states": t.states,
        "actions": t.actions,
        "mu": t.mu,
        "sigma": t.sigma,
    });
    if let Some((steps, alpha)) = alpha_step {
        if !finite_all(steps) || !alpha.is_finite() {
            return Err(Error::Internal(anyhow::anyhow!(
                "non-finite acquisition value"
            )));
        }
        body["alpha_step"] = json!(steps);
        body["alpha"] = json!(alpha);
    }
    Ok(body)
}

fn proposal_body(p: &StoredProposal) -> Value {
    let mut body = json!({
        "id": p.id,
        "status": p.status,
        "client_id": p.client_id,
        "iteration": p.iteration,
        "beta": p.beta,
        "strategy": p.strategy,
        "model_version": p.model_version,
        "start": p.start,
        "goal": p.goal,
        "created_at": p.created_at,
        "expires_at": p.expires_at,
    });
    if let (Some(out), Some(stored)) = (body.as_object_mut(), p.body.as_object()) {
        for (k, v) in stored {
            out.insert(k.clone(), v.clone());
        }
    }
    body
}

/// `POST /v1/experiments/{id}/proposals`: plan candidates inside the current precondition with
/// the iteration's `β_j` and hand out the one the strategy picks, leased to the client.
pub async fn create_proposal(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiJson(request): ApiJson<ProposalRequest>,
) -> Result<(StatusCode, Json<Value>), Error> {
    let live = state.experiments.get(&state.store, id).await?;
    check_problem(&live, &request.start, &request.goal)?;
    if let Some(client) = &request.client_id {
        if client.is_empty() || client.chars().count() > MAX_CLIENT_ID_LEN {
            return Err(Error::validation(
                "client_id",
                format!("must be 1 to {MAX_CLIENT_ID_LEN} characters"),
            ));
        }
        if let Some(open) = state.store.open_proposal(id, client).await? {
            return lease_answer(open, &request);
        }
    }
    let n_trajectories = state
        .store
        .experiment(id)
        .await?
        .map_or(0, |e| e.n_trajectories);
    let iteration = live.iteration(n_trajectories);
    let beta = live.training_beta(iteration);
    let strategy: Strategy = request
        .strategy
        .unwrap_or(live.settings.learning.strategy)
        .into();
    let model = live.model();
    let seed = problem_seed(
        live.settings.seed,
        n_trajectories,
        &request.start,
        &request.goal,
    );
    let proposal = {
        let live = Arc::clone(&live);
        let model = model.clone();
        let (start, goal) = (request.start.clone(), request.goal.clone());
        tokio::task::spawn_blocking(move || {
            let l = &live.settings.learning;
            planning::propose(
                strategy,
                live.domain.as_ref(),
                model.as_ref(),
                &start,
                &goal,
                beta,
                live.settings.d_max,
                &l.planner(),
                &l.acquisition(),
                seed,
            )
        })
        .await
        .map_err(|e| Error::Internal(e.into()))?
        .map_err(planning_error)?
    };
    let candidates: Vec<Value> = proposal
        .candidates
        .iter()
        .map(|c| json!({"alpha": c.alpha, "length": c.length}))
        .collect();
    if !proposal.candidates.iter().all(|c| c.alpha.is_finite()) {
        return Err(Error::Internal(anyhow::anyhow!(
            "non-finite candidate score"
        )));
    }
    let body = json!({
        "trajectory": trajectory_body(
            &proposal.trajectory,
            Some((&proposal.alpha_step, proposal.alpha)),
        )?,
        "candidates": candidates,
        "chosen_index": proposal.chosen_index,
        "extensions": proposal.extensions,
    });
    let (stored, created) = state
        .store
        .insert_proposal(
            id,
            &NewProposal {
                client_id: request.client_id.clone(),
                iteration,
                beta,
                strategy: strategy.as_str().to_string(),
                model_version: model.version,
                start: request.start.clone(),
                goal: request.goal.clone(),
                body,
                ttl_seconds: live.settings.learning.proposal_ttl_seconds,
            },
        )
        .await?;
    if created {
        Ok((StatusCode::CREATED, Json(proposal_body(&stored))))
    } else {
        lease_answer(stored, &request)
    }
}

/// A client that holds an open lease gets it back when it asks for the same problem; asking for
/// another problem is a conflict rather than a silent answer to a question it did not ask.
fn lease_answer(
    open: StoredProposal,
    request: &ProposalRequest,
) -> Result<(StatusCode, Json<Value>), Error> {
    if open.start != request.start || open.goal != request.goal {
        return Err(Error::Conflict(format!(
            "client {:?} holds open proposal {} for start {:?} and goal {:?}; execute or abandon \
             it before asking for another problem",
            open.client_id.as_deref().unwrap_or_default(),
            open.id,
            open.start,
            open.goal
        )));
    }
    Ok((StatusCode::OK, Json(proposal_body(&open))))
}

fn no_proposal(id: i64, pid: i64) -> Error {
    Error::NotFound(format!("no proposal {pid} in experiment {id}"))
}

/// `GET /v1/experiments/{id}/proposals/{pid}`.
pub async fn get_proposal(
    State(state): State<AppState>,
    ApiPath((id, pid)): ApiPath<(i64, i64)>,
) -> Result<Json<Value>, Error> {
    state.experiments.get(&state.store, id).await?;
    let p = state
        .store
        .proposal(id, pid)
        .await?
        .ok_or_else(|| no_proposal(id, pid))?;
    Ok(Json(proposal_body(&p)))
}

/// `POST /v1/experiments/{id}/proposals/{pid}/abandon`: the client will not execute it.
pub async fn abandon_proposal(
    State(state): State<AppState>,
    ApiPath((id, pid)): ApiPath<(i64, i64)>,
) -> Result<Json<Value>, Error> {
    state.experiments.get(&state.store, id).await?;
    let p = state
        .store
        .abandon_proposal(id, pid)
        .await?
        .ok_or_else(|| no_proposal(id, pid))?;
    if p.status == "executed" {
        return Err(Error::Conflict(format!(
            "proposal {pid} was already executed"
        )));
    }
    Ok(Json(proposal_body(&p)))
}

/// `POST /v1/experiments/{id}/plans`: a test-time plan with the conservative β. Nothing is
/// stored.
pub async fn create_plan(
    State(state): State<AppState>,
    ApiPath(id): ApiPath<i64>,
    ApiJson(request): ApiJson<PlanRequest>,
) -> Result<Json<Value>, Error> {
    let live = state.experiments.get(&state.store, id).await?;
    check_problem(&live, &request.start, &request.goal)?;
    let beta = request.beta.unwrap_or(live.settings.learning.test_beta);
    if !beta.is_finite() {
        return Err(Error::validation("beta", "must be a finite number"));
    }
    let model = live.model();
    let seed = problem_seed(
        live.settings.seed,
        model.version,
        &request.start,
        &request.goal,
    );
    let outcome = {
        let live = Arc::clone(&live);
        let model = model.clone();
        tokio::task::spawn_blocking(move || {
            planning::plan(
                live.domain.as_ref(),
                model.as_ref(),
                &request.start,
                &request.goal,
                beta,
                live.settings.d_max,
                &live.settings.learning.planner(),
                seed,
            )
        })
        .await
        .map_err(|e| Error::Internal(e.into()))?
        .map_err(planning_error)?
    };
    let trajectory = match &outcome.trajectory {
        Some(t) => trajectory_body(t, None)?,
        None => Value::Null,
    };
    Ok(Json(json!({
        "found": outcome.trajectory.is_some(),
        "extensions": outcome.extensions,
        "beta": beta,
        "d_max": live.settings.d_max,
        "model_version": model.version,
        "trajectory": trajectory,
    })))
}
