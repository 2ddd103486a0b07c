//! Proposals (ask: which trajectory should the robot try next?) and their leases.
//!
//! A proposal plans candidates inside the current precondition with the iteration's `β_j`,
//! lets the strategy choose, and stores the choice leased to the asking client: the same client
//! asking again for the same problem gets the same proposal back until it posts the executed
//! trajectory, abandons it, or the lease expires; asking for another problem meanwhile is a
//! conflict rather than a silent answer to a question it did not ask.
//!
//! A request no trajectory answers (`no_plan`, at every β tried) is recorded as a refusal: the
//! problem, the client, the iteration, every β tried and the extensions spent. Refusals are
//! runs (`refused`) and are counted per iteration in the timeline.

use super::Ingested;
use super::LiveExperiment;
use super::ingest::check_idempotency_key;
use super::learning::{
    check_candidates, check_finite, model_names, needs_candidates, plan_models, plan_models_of,
};
use super::{Error, Result, Service};
use crate::api::{
    CandidateView, ContinueRequest, PlannedTrajectory, ProposalContent, ProposalRequest,
    TrajectoryRequest,
};
use crate::domain::Problem;
use crate::limits::{MAX_CLIENT_ID_LEN, text_problem};
use crate::mde::ServedModel;
use crate::planning::{GivenChoice, Precondition, Proposal, Strategy};
use crate::records::{ProposalStatus, ProposalTerms, RefusalReason};
use crate::seed;
use crate::store::{Inserted, NewProposal, NewRefusal, StoredProposal};
use std::sync::Arc;
use std::time::Instant;

/// At most this many state-actions in flight (executed since the last fit, or planned by
/// open proposals) shape an `active` proposal's choice.
pub const MAX_IN_FLIGHT: usize = 256;

/// Fantasising `k` state-actions with an exact GP of `n` transitions costs about `n² k`
/// multiply-adds (`L⁻¹` times their covariances); `k` is capped so that this stays within
/// this many: all 256 up to n = 3125, 25 at n = 10,000. Measured at n = 3000, d = 6, k = 256
/// and 300 candidate steps (release build, 2 cores): 0.27 s, against 0.05 s for the plain
/// prediction of those steps. The sparse GP's cost, `k m²`, is small at any `k`.
pub const IN_FLIGHT_WORK: usize = 2_500_000_000;

/// How many state-actions in flight a proposal fantasises with `model`: a fantasised row costs
/// about as many multiply-adds as the version keeps floats (`n²` for the exact GP, `Σ n_e²` for
/// local experts, `m² + m d` for the sparse GP).
fn in_flight_limit(model: &ServedModel) -> usize {
    match model.kind() {
        None => 0,
        Some(_) => (IN_FLIGHT_WORK / model.floats().max(1)).min(MAX_IN_FLIGHT),
    }
}

/// A stored proposal with what it chose.
#[derive(Debug, Clone)]
pub struct ProposalRecord {
    /// The stored proposal and its lease.
    pub stored: StoredProposal,
    /// The chosen trajectory and the scored candidates.
    pub content: ProposalContent,
}

impl ProposalRecord {
    fn from_stored(stored: StoredProposal) -> Result<Self> {
        let content = serde_json::from_str(&stored.body).map_err(|e| {
            anyhow::Error::new(e).context(format!("the stored content of proposal {}", stored.id))
        })?;
        Ok(Self { stored, content })
    }
}

/// What a strategy chose, as stored and shown; `schedule_beta` is the iteration's `β_j`.
fn content(p: &Proposal, schedule_beta: f64) -> Result<ProposalContent> {
    check_finite(&p.trajectory)?;
    let scores = p.alpha_step.iter().chain([&p.alpha]);
    if !scores
        .chain(p.candidates.iter().map(|c| &c.alpha))
        .all(|x| x.is_finite())
    {
        return Err(Error::Internal(anyhow::anyhow!(
            "non-finite acquisition value"
        )));
    }
    Ok(ProposalContent {
        trajectory: PlannedTrajectory {
            alpha_step: Some(p.alpha_step.clone()),
            alpha: Some(p.alpha),
            ..PlannedTrajectory::from(&p.trajectory)
        },
        candidates: p
            .candidates
            .iter()
            .map(|c| CandidateView::planned(c.alpha, c.length))
            .collect(),
        chosen_index: p.chosen_index,
        extensions: p.extensions,
        relaxed_from_beta: relaxed_from(p.beta, schedule_beta),
        valued_by: Some(p.valued_by),
        models: None,
        step_models: None,
    })
}

/// [`content`] of a proposal across the models named `names` (in the order the planner was
/// given them): which models it stepped with, cheapest first, and which each step relied on.
fn content_across(
    p: &Proposal,
    schedule_beta: f64,
    names: &[(String, f64)],
) -> Result<ProposalContent> {
    let mut by_cost: Vec<&(String, f64)> = names.iter().collect();
    by_cost.sort_by(|a, b| a.1.total_cmp(&b.1));
    Ok(ProposalContent {
        models: Some(by_cost.into_iter().map(|(n, _)| n.clone()).collect()),
        step_models: Some(p.step_models.iter().map(|&m| names[m].0.clone()).collect()),
        ..content(p, schedule_beta)?
    })
}

/// The models a proposal's own candidates step with: the domain's alone unless the request
/// names others (see [`plan_models`]) — proposals across every model taught the preconditions
/// no more than the domain model's own on the worlds measured, and cost the dearer models'
/// calls on every proposal (docs/research/several-models.md, "Step 3"). A `random` rollout
/// steps with the domain's model alone (an error naming `models` when the request named
/// others).
fn proposal_models(
    live: &LiveExperiment,
    model: &ServedModel,
    strategy: Strategy,
    request: &ProposalRequest,
) -> Result<Vec<Option<usize>>> {
    let Some(named) = request.models.as_deref() else {
        return Ok(vec![None]);
    };
    let steppers = plan_models(live, model, Some(named))?;
    if strategy != Strategy::Random {
        return Ok(steppers);
    }
    if steppers != [None] {
        return Err(Error::validation(
            "models",
            "a random rollout steps with the domain's model alone",
        ));
    }
    Ok(vec![None])
}

/// `Some(β_j)` when the proposal was made at a β other than the schedule's.
fn relaxed_from(beta: f64, schedule_beta: f64) -> Option<f64> {
    (beta != schedule_beta).then_some(schedule_beta)
}

/// What a strategy chose among the client's judged candidates (judged at `beta`; the iteration's
/// is `schedule_beta`), as stored and shown; `no_plan` with every verdict when there is nothing
/// to choose.
fn given_content(given: &GivenChoice, beta: f64, schedule_beta: f64) -> Result<ProposalContent> {
    let candidates: Vec<CandidateView> = given.verdicts.iter().map(CandidateView::judged).collect();
    let Some(chosen) = given.chosen else {
        return Err(Error::NoPlan {
            extensions: 0,
            candidates,
        });
    };
    let v = &given.verdicts[chosen];
    Ok(ProposalContent {
        trajectory: PlannedTrajectory {
            alpha_step: Some(v.alpha_step.clone()),
            alpha: Some(v.alpha),
            ..PlannedTrajectory::from(&v.trajectory)
        },
        candidates,
        chosen_index: chosen,
        extensions: 0,
        relaxed_from_beta: relaxed_from(beta, schedule_beta),
        valued_by: Some(given.valued_by),
        models: None,
        step_models: None,
    })
}

/// What a proposal is planned under: the learning iteration, its β ladder (the schedule's `β_j`
/// first, then the relaxed ones), the strategy answering, the model version and the seed.
struct Schedule {
    iteration: i64,
    schedule_beta: f64,
    ladder: Vec<Precondition>,
    strategy: Strategy,
    model: Arc<ServedModel>,
    seed: u64,
}

/// The open lease answered again for the same problem, or a conflict for another one.
fn lease_answer(open: StoredProposal, request: &ProposalRequest) -> Result<ProposalRecord> {
    let terms = &open.terms;
    if terms.start != request.start || terms.goal != request.goal {
        return Err(Error::LeaseHeld {
            proposal_id: open.id,
            client_id: terms.client_id.clone().unwrap_or_default(),
            start: terms.start.clone(),
            goal: terms.goal.clone(),
        });
    }
    ProposalRecord::from_stored(open)
}

impl Service {
    /// Proposes the trajectory to execute next for `request`'s problem (see the module docs).
    /// Returns the proposal and whether it is new (`false`: the client's open lease).
    ///
    /// Counts each answer in `precond_proposals_total` by outcome; a search whose client went
    /// away is counted as `cancelled` by the search itself (in `Service::search`), since
    /// this future is dropped with the request.
    pub async fn propose(
        &self,
        id: i64,
        request: ProposalRequest,
    ) -> Result<(ProposalRecord, bool)> {
        self.propose_metered(id, request, None).await
    }

    /// [`Service::propose`], recording the proposal with the key of the `continue` that asks
    /// (`continues`), and counting its outcome.
    async fn propose_metered(
        &self,
        id: i64,
        request: ProposalRequest,
        continues: Option<&str>,
    ) -> Result<(ProposalRecord, bool)> {
        let answer = self.propose_unmetered(id, request, continues).await;
        let outcome = match &answer {
            // Counted where the search stopped.
            Err(Error::Cancelled) => return answer,
            Ok((_, true)) => "created",
            Ok((_, false)) => "lease_returned",
            Err(Error::NoPlan { .. }) => "no_plan",
            Err(Error::LeaseHeld { .. }) => "lease_held",
            Err(Error::DeadlineExceeded { .. }) => "deadline_exceeded",
            Err(Error::Overloaded { .. }) => "overloaded",
            Err(Error::Validation { .. } | Error::NotFound(_)) => "invalid",
            Err(_) => "failed",
        };
        metrics::counter!("precond_proposals_total", "outcome" => outcome).increment(1);
        answer
    }

    /// A proposal in three steps: what it is planned under ([`schedule`](Self::schedule)), the
    /// planner's candidates or the client's judged and valued inside it
    /// ([`plan_or_judge`](Self::plan_or_judge)), and what is stored — the proposal, or the
    /// refusal of one ([`record_refusal`](Self::record_refusal)).
    async fn propose_unmetered(
        &self,
        id: i64,
        request: ProposalRequest,
        continues: Option<&str>,
    ) -> Result<(ProposalRecord, bool)> {
        let arrived = Instant::now();
        let live = self.live(id).await?;
        let problem = live.problem(request.start.clone(), request.goal.clone())?;
        if let Some(open) = self.open_lease(id, request.client_id.as_deref()).await? {
            return Ok((lease_answer(open, &request)?, false));
        }
        let schedule = self.schedule(id, &live, &request).await?;
        let answer = self
            .plan_or_judge(id, arrived, &live, &schedule, problem, &request)
            .await;
        self.record_refusal(id, &schedule, &request, &answer).await;
        let (content, beta) = answer?;
        let body = serde_json::to_string(&content).map_err(anyhow::Error::from)?;
        let (n_actions, extensions) = (
            content.trajectory.actions.len() as i64,
            content.extensions as i64,
        );
        let (stored, inserted) = self
            .store
            .insert_proposal(
                id,
                &NewProposal {
                    terms: ProposalTerms {
                        client_id: request.client_id.clone(),
                        iteration: schedule.iteration,
                        beta,
                        strategy: schedule.strategy,
                        model_version: schedule.model.version,
                        start: request.start.clone(),
                        goal: request.goal.clone(),
                    },
                    body,
                    n_actions,
                    extensions,
                    ttl_seconds: live.settings.learning.proposal_ttl_seconds,
                    continues: continues.map(str::to_string),
                },
            )
            .await?;
        match inserted {
            Inserted::Created => Ok((ProposalRecord::from_stored(stored)?, true)),
            Inserted::Continued => Ok((ProposalRecord::from_stored(stored)?, false)),
            Inserted::OpenLease => Ok((lease_answer(stored, &request)?, false)),
        }
    }

    /// The open proposal leased to `client` (checked: 1 to [`MAX_CLIENT_ID_LEN`] printable
    /// characters), if any: a client asks again and gets its lease back.
    async fn open_lease(&self, id: i64, client: Option<&str>) -> Result<Option<StoredProposal>> {
        let Some(client) = client else {
            return Ok(None);
        };
        if client.is_empty() || client.chars().count() > MAX_CLIENT_ID_LEN {
            return Err(Error::validation(
                "client_id",
                format!("must be 1 to {MAX_CLIENT_ID_LEN} characters"),
            ));
        }
        if let Some(why) = text_problem(client) {
            return Err(Error::validation("client_id", why));
        }
        Ok(self.store.open_proposal(id, client).await?)
    }

    /// What a proposal for `request` is planned under now.
    async fn schedule(
        &self,
        id: i64,
        live: &LiveExperiment,
        request: &ProposalRequest,
    ) -> Result<Schedule> {
        let n_trajectories = self
            .store
            .experiment(id)
            .await?
            .map_or(0, |e| e.n_trajectories);
        let learning = &live.settings.learning;
        let iteration = live.iteration(n_trajectories);
        let schedule_beta = learning.training_beta(iteration);
        let ladder = learning
            .training_betas(schedule_beta)
            .into_iter()
            .map(|beta| live.precondition(beta))
            .collect::<Result<Vec<_>>>()?;
        Ok(Schedule {
            iteration,
            schedule_beta,
            ladder,
            strategy: learning.answering_strategy(request.strategy, iteration),
            model: live.model(),
            seed: seed::mix_values(
                live.settings.seed,
                n_trajectories,
                request.start.iter().chain(&request.goal).copied(),
            ),
        })
    }

    /// The proposal's content and the β it was made at: the planner's RRT candidates, or the
    /// client's posted ones judged and valued — either way compared by the experiment's
    /// acquisition, with the state-actions in flight, down the β ladder within one planning
    /// deadline.
    async fn plan_or_judge(
        &self,
        id: i64,
        arrived: Instant,
        live: &Arc<LiveExperiment>,
        schedule: &Schedule,
        problem: Problem,
        request: &ProposalRequest,
    ) -> Result<(ProposalContent, f64)> {
        if request.models.is_some() && request.candidates.is_some() {
            return Err(Error::validation(
                "models",
                "applies to the service's search, not to the client's candidates",
            ));
        }
        let checked = match request.candidates.clone() {
            Some(candidates) => Some(check_candidates(live, problem.start(), candidates)?),
            None => {
                needs_candidates(live)?;
                None
            }
        };
        let Schedule {
            strategy,
            seed,
            schedule_beta,
            ..
        } = *schedule;
        let in_flight = if strategy == Strategy::Active && live.settings.learning.batch_diversity {
            self.in_flight(live, &schedule.model, request.client_id.as_deref())
                .await?
        } else {
            Vec::new()
        };
        let (live, model, ladder) = (
            live.clone(),
            schedule.model.clone(),
            schedule.ladder.clone(),
        );
        let kind = super::SearchKind::Proposal;
        match checked {
            Some(candidates) => {
                let given = self
                    .search(id, arrived, kind, move |budget| {
                        live.planner(&model)
                            .with_in_flight(&in_flight)
                            .within(budget.clone())
                            .judge_relaxing(&problem, candidates, &ladder, strategy, seed)
                    })
                    .await?;
                for v in &given.verdicts {
                    check_finite(&v.trajectory)?;
                }
                let beta = given.precondition.beta();
                Ok((given_content(&given, beta, schedule_beta)?, beta))
            }
            None => {
                let steppers = proposal_models(&live, &model, strategy, request)?;
                if steppers == [None] {
                    let proposal = self
                        .search(id, arrived, kind, move |budget| {
                            live.planner(&model)
                                .with_in_flight(&in_flight)
                                .within(budget.clone())
                                .propose_relaxing(strategy, &problem, &ladder, seed)
                        })
                        .await?;
                    return Ok((content(&proposal, schedule_beta)?, proposal.beta));
                }
                let names = model_names(&live, &steppers);
                let proposal = self
                    .search(id, arrived, kind, move |budget| {
                        let stepping = plan_models_of(&live, &model, &steppers, &*model);
                        // A further model's features read its own prediction where the
                        // domain's read one: the batch's are the domain's, so it has none.
                        let shared = !live.domain.features_use_prediction();
                        let flights: Vec<&[f64]> = steppers
                            .iter()
                            .map(|s| match s {
                                Some(_) if !shared => &[][..],
                                _ => in_flight.as_slice(),
                            })
                            .collect();
                        live.planner(&model)
                            .within(budget.clone())
                            .propose_across(strategy, &problem, &ladder, &stepping, &flights, seed)
                    })
                    .await?;
                Ok((
                    content_across(&proposal, schedule_beta, &names)?,
                    proposal.beta,
                ))
            }
        }
    }

    /// Records a proposal answered `no_plan` or past its deadline as a refused run (the
    /// dashboard counts them). The answer is the refusal either way: a store that cannot
    /// record it is logged, not turned into another answer.
    async fn record_refusal<T>(
        &self,
        id: i64,
        schedule: &Schedule,
        request: &ProposalRequest,
        answer: &Result<T>,
    ) {
        let (reason, extensions) = match answer {
            Err(Error::NoPlan { extensions, .. }) => (RefusalReason::NoPlan, *extensions),
            Err(Error::DeadlineExceeded { extensions, .. }) => {
                (RefusalReason::DeadlineExceeded, *extensions)
            }
            _ => return,
        };
        let refusal = NewRefusal {
            client_id: request.client_id.clone(),
            iteration: schedule.iteration,
            strategy: schedule.strategy,
            model_version: schedule.model.version,
            start: request.start.clone(),
            goal: request.goal.clone(),
            betas: schedule.ladder.iter().map(|p| p.beta()).collect(),
            extensions: extensions as i64,
            candidates: request.candidates.as_ref().map(|c| c.len() as i64),
            reason,
        };
        match self.store.insert_refusal(id, &refusal).await {
            Ok(refusal_id) => tracing::info!(
                experiment = id,
                refusal = refusal_id,
                extensions,
                reason = reason.as_str(),
                "proposal refused"
            ),
            Err(e) => tracing::error!(
                experiment = id,
                error = %e,
                "could not record a refused proposal"
            ),
        }
    }

    /// Features (row-major) of the state-actions the current batch has in flight beyond what
    /// `model` was fitted on: the transitions stored after its training data (executed, not
    /// yet fitted; none for a sparse GP that took them in online) and the planned steps of
    /// other clients' open proposals, at most [`MAX_IN_FLIGHT`] (executed ones first) and
    /// fewer for a large exact GP ([`IN_FLIGHT_WORK`]). Empty for the prior, which does not
    /// fantasise.
    async fn in_flight(
        &self,
        live: &LiveExperiment,
        model: &ServedModel,
        client_id: Option<&str>,
    ) -> Result<Vec<f64>> {
        let limit = in_flight_limit(model);
        if limit == 0 {
            return Ok(Vec::new());
        }
        let executed = self
            .store
            .transitions_after_first(
                live.id,
                &LiveExperiment::trained_outside(model),
                model.n_train() as i64,
                limit as i64,
            )
            .await?;
        let (mut features, _) = live.training_set(&executed);
        let room = limit - executed.len().min(limit);
        if room > 0 {
            let plans = self
                .store
                .open_plans(live.id, client_id, room as i64)
                .await?;
            let steps = plans
                .iter()
                .flat_map(|p| p.states.iter().zip(&p.actions).zip(p.states.iter().skip(1)))
                .filter(|((s, a), _)| {
                    live.domain.validate_state(s).is_ok() && live.domain.validate_action(a).is_ok()
                })
                .take(room);
            for ((s, a), next) in steps {
                features.extend(live.domain.features(s, a, next));
            }
        }
        Ok(features)
    }

    /// Continues open proposal `proposal_id` from where the robot is (closed loop): stores the
    /// executed prefix `transitions` as a partial trajectory of it (idempotently with
    /// `idempotency_key`, as any posted trajectory), then proposes again from the prefix's last
    /// observed state to the same goal, for the same client (the lease carries over) and with
    /// the same strategy. The prefix must start at the proposal's start. When no trajectory
    /// reaches the goal from there the answer is `no_plan`; the prefix stays stored.
    pub async fn continue_proposal(
        &self,
        id: i64,
        proposal_id: i64,
        request: ContinueRequest,
        idempotency_key: Option<&[u8]>,
    ) -> Result<(Ingested, ProposalRecord)> {
        let ContinueRequest {
            transitions,
            candidates,
        } = request;
        let stored = self.store.proposal(id, proposal_id).await?;
        let stored = stored.ok_or_else(|| no_proposal(id, proposal_id))?;
        let terms = stored.terms.clone();
        let Some(first) = transitions.first() else {
            return Err(Error::validation(
                "transitions",
                "must hold the executed prefix: at least one transition",
            ));
        };
        let close = first.s.len() == terms.start.len()
            && first
                .s
                .iter()
                .zip(&terms.start)
                .all(|(a, b)| (a - b).abs() <= 1e-9 * (1.0 + b.abs()));
        if !close {
            return Err(Error::validation(
                "transitions[0].s",
                format!("must be the proposal's start {:?}", terms.start),
            ));
        }
        let here = transitions
            .last()
            .map(|t| t.s_next.clone())
            .unwrap_or_default();
        let key = idempotency_key.map(check_idempotency_key).transpose()?;
        let ingested = self
            .ingest(
                id,
                TrajectoryRequest {
                    proposal_id: Some(proposal_id),
                    partial: true,
                    transitions,
                    source: None,
                },
                key.map(str::as_bytes),
            )
            .await?;
        let stored_as = ingested.record.trajectory_id;
        // A replay answers the proposal the first call made, whatever happened to it since.
        if let Some(key) = key
            && let Some(made) = self.store.continuation(id, key).await?
            && let Some(made) = self.store.proposal(id, made).await?
        {
            return Ok((ingested, ProposalRecord::from_stored(made)?));
        }
        let (next, _) = self
            .propose_metered(
                id,
                ProposalRequest {
                    start: here,
                    goal: terms.goal,
                    client_id: terms.client_id,
                    strategy: Some(terms.strategy),
                    candidates,
                    models: ProposalRecord::from_stored(stored)?.content.models,
                },
                key,
            )
            .await
            .map_err(|e| {
                let e = match e {
                    Error::Validation { field, reason } if field.starts_with("start") => {
                        Error::validation(
                            format!("transitions[-1].s_next{}", &field["start".len()..]),
                            reason,
                        )
                    }
                    e => e,
                };
                Error::PrefixStored {
                    trajectory_id: stored_as,
                    error: Box::new(e),
                }
            })?;
        Ok((ingested, next))
    }

    /// One proposal, its lease brought up to date.
    pub async fn proposal(&self, id: i64, proposal_id: i64) -> Result<ProposalRecord> {
        self.experiment(id).await?;
        let stored = self.store.proposal(id, proposal_id).await?;
        ProposalRecord::from_stored(stored.ok_or_else(|| no_proposal(id, proposal_id))?)
    }

    /// Gives up an open proposal: the client will not execute it. An executed one is a
    /// conflict; an expired or abandoned one is answered as it is.
    pub async fn abandon(&self, id: i64, proposal_id: i64) -> Result<ProposalRecord> {
        self.experiment(id).await?;
        let stored = self.store.abandon_proposal(id, proposal_id).await?;
        let stored = stored.ok_or_else(|| no_proposal(id, proposal_id))?;
        if stored.status == ProposalStatus::Executed {
            return Err(Error::Conflict(format!(
                "proposal {proposal_id} was already executed"
            )));
        }
        ProposalRecord::from_stored(stored)
    }
}

fn no_proposal(id: i64, proposal_id: i64) -> Error {
    Error::NotFound(format!("no proposal {proposal_id} in experiment {id}"))
}
