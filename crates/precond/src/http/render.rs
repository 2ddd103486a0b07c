//! From the service's values to the API's response bodies. Rendering never fails and never
//! computes anything the service should have.

use crate::api::{
    CandidateView, Diagnostics, ExclusionPage, ExclusionStatus, ExclusionView, ExperimentResponse,
    LaterRates, MapAxis, MapPoint, ModelCalls, ModelLabelStats, ModelLabels, ModelResponse,
    ModelSource, PlanResponse, PreconditionMap, PreconditionResponse, ProposalResponse,
    RejectionCounts, RunPage, Timeline, TimelineIteration, TimelineModel, TrajectoryCreated,
    TrajectoryHeader, TrajectoryResponse,
};
use crate::mde::ServedModel;
use crate::service::exclusions::{ExclusionRecord, Exclusions};
use crate::service::{
    ExperimentState, Ingested, Judged, LearningTimeline, LooDiagnostics, ModelView, Planned,
    PreconditionGrid, ProposalRecord, Runs,
};
use crate::store::{ExclusionScope, StoredProposal, StoredTrajectory};

/// Whether a version is the prior or a fit.
pub fn source(m: &ServedModel) -> ModelSource {
    if m.fit.is_some() {
        ModelSource::Fit
    } else {
        ModelSource::Prior
    }
}

/// An experiment with its spaces and progress.
pub fn experiment(s: ExperimentState) -> ExperimentResponse {
    let iteration = s.iteration();
    let (e, domain) = (s.experiment, s.domain);
    ExperimentResponse {
        id: e.id,
        iteration,
        settings: e.settings,
        state_space: domain.state_space().into(),
        action_space: domain.action_space().into(),
        feature_names: domain.feature_names(),
        created_at: e.created_at,
        n_trajectories: e.n_trajectories,
        n_transitions: e.n_transitions,
        model_version: e.model_version,
        n_refused: e.n_refused,
        last_activity: e.last_activity,
    }
}

/// A page of runs.
pub fn runs(r: Runs) -> RunPage {
    RunPage {
        items: r.items,
        total: r.total,
        next: r.next,
    }
}

/// Each model's labels, summed up.
pub fn model_labels(
    experiment_id: i64,
    d_max: f64,
    reports: Vec<crate::service::activity::ModelLabelReport>,
) -> ModelLabels {
    ModelLabels {
        experiment_id,
        d_max,
        items: reports
            .into_iter()
            .map(|r| ModelLabelStats {
                model: r.stats.model,
                cost: r.cost,
                kind: r.kind.to_string(),
                n_labelled: r.stats.n_labelled,
                n_missing: r.stats.n_missing,
                mean_deviation: r.stats.mean_deviation,
                max_deviation: r.stats.max_deviation,
                share_within_d_max: r.stats.share_within_d_max,
            })
            .collect(),
    }
}

/// A learning timeline.
pub fn timeline(experiment_id: i64, t: LearningTimeline) -> Timeline {
    Timeline {
        experiment_id,
        batch_size: t.batch_size,
        iterations_planned: t.iterations_planned,
        iterations: t
            .iterations
            .into_iter()
            .map(|(beta, stats)| TimelineIteration { beta, stats })
            .collect(),
        models: t
            .models
            .into_iter()
            .map(|(iteration, model)| TimelineModel { iteration, model })
            .collect(),
        fit_refusals: t.fit_refusals,
    }
}

/// A model version on a grid.
pub fn map(g: PreconditionGrid) -> PreconditionMap {
    PreconditionMap {
        model_version: g.model.version,
        source: source(&g.model),
        n_train: g.model.n_train(),
        d_max: g.d_max,
        test_beta: g.test_beta,
        s: g.s,
        a: g.a,
        x: MapAxis {
            name: g.x.0,
            values: g.x.1,
        },
        y: MapAxis {
            name: g.y.0,
            values: g.y.1,
        },
        mu: g.mu,
        sigma: g.sigma,
        training: g
            .training
            .into_iter()
            .map(|t| MapPoint {
                s: t.s,
                a: t.a,
                deviation: t.deviation,
            })
            .collect(),
        model: g.further,
    }
}

/// Leave-one-out diagnostics.
pub fn diagnostics(experiment_id: i64, d: LooDiagnostics) -> Diagnostics {
    let s = d.summary;
    Diagnostics {
        experiment_id,
        model_version: d.model_version,
        method: "leave_one_out".into(),
        n: s.n,
        rmse: s.rmse,
        mean_log_density: s.mean_log_density,
        coverage: s.coverage,
        precondition: s.precondition,
        later: d.later.map(|l| LaterRates {
            n: l.n,
            coverage: l.coverage,
            rates: l.precondition,
        }),
    }
}

/// A trajectory with its transitions.
pub fn trajectory(t: StoredTrajectory) -> TrajectoryResponse {
    TrajectoryResponse {
        trajectory: TrajectoryHeader {
            id: t.id,
            experiment_id: t.experiment_id,
            proposal_id: t.proposal_id,
            partial: t.partial,
            deviating: t.deviating,
            source: t.source,
        },
        created_at: t.created_at,
        n_transitions: t.transitions.len(),
        transitions: t.transitions,
    }
}

/// A model version.
pub fn model(v: ModelView) -> ModelResponse {
    let m = v.model.as_ref();
    ModelResponse {
        experiment_id: v.experiment_id,
        version: m.version,
        source: source(m),
        n_train: m.n_train(),
        noise: m.noise_mode(),
        feature_names: v.feature_names,
        hyperparameters: m.hyperparameters().cloned(),
        noise_model: m.noise_summary(),
        log_marginal_likelihood: m.log_marginal_likelihood(),
        fit_seconds: m.fit.as_ref().map(|f| f.fit_seconds),
        fitted_at: m.fit.as_ref().map(|f| f.fitted_at.clone()),
        n_trajectories: m.fit.as_ref().map_or(0, |f| f.n_trajectories),
        label_cap: m.fit.as_ref().map(|f| f.label_cap),
        label_cap_trials: m
            .fit
            .as_ref()
            .map(|f| f.label_cap_trials.clone())
            .unwrap_or_default(),
        estimator: m.kind(),
        online_trajectories: m.fit.as_ref().map_or(0, |f| f.online_trajectories),
        last_fit_refusal: v.last_refusal,
        kernel_trials: m
            .fit
            .as_ref()
            .map(|f| f.kernel_trials.clone())
            .unwrap_or_default(),
        beta_choice: m.fit.as_ref().and_then(|f| f.beta_choice),
        test_beta: v.test_beta,
        selection: m.fit.as_ref().and_then(|f| f.selection.clone()),
        exclusions: m
            .fit
            .as_ref()
            .map(|f| f.exclusions.clone())
            .unwrap_or_default(),
    }
}

/// Precondition judgements.
pub fn judged(j: Judged) -> PreconditionResponse {
    PreconditionResponse {
        model_version: j.model.version,
        source: source(&j.model),
        beta: j.beta,
        d_max: j.d_max,
        results: j.judgements,
        model: j.further,
        s: None,
        a: None,
    }
}

/// A proposal.
pub fn proposal(p: ProposalRecord) -> ProposalResponse {
    let StoredProposal {
        id,
        status,
        terms,
        created_at,
        expires_at,
        deviating,
        ..
    } = p.stored;
    ProposalResponse {
        id,
        status,
        deviating,
        terms,
        created_at,
        expires_at,
        content: p.content,
    }
}

/// A test-time plan.
pub fn plan(p: Planned) -> PlanResponse {
    PlanResponse {
        found: p.outcome.trajectory.is_some(),
        extensions: p.outcome.extensions,
        rejections: RejectionCounts {
            constraints: p.outcome.rejections.constraints,
            precondition: p.outcome.rejections.precondition,
        },
        beta: p.beta,
        d_max: p.d_max,
        model_version: p.model_version,
        trajectory: p.outcome.trajectory.as_ref().map(Into::into),
        candidates: p
            .candidates
            .map(|verdicts| verdicts.iter().map(CandidateView::judged).collect()),
        step_models: p.models.as_ref().map(|models| {
            p.outcome
                .step_models
                .iter()
                .map(|&m| models[m].0.clone())
                .collect()
        }),
        model_calls: p.models.as_ref().map(|models| {
            models
                .iter()
                .zip(&p.outcome.model_calls)
                .map(|((model, cost), &calls)| ModelCalls {
                    model: model.clone(),
                    calls,
                    cost: *cost,
                })
                .collect()
        }),
    }
}

/// The `201` answer to a posted trajectory (the same for a retry with the same
/// `Idempotency-Key`: the first ingest's record).
pub fn trajectory_created(i: &Ingested) -> TrajectoryCreated {
    let r = &i.record;
    TrajectoryCreated {
        trajectory: TrajectoryHeader {
            id: r.trajectory_id,
            experiment_id: i.experiment_id,
            proposal_id: r.proposal_id,
            partial: r.partial,
            deviating: r.deviating,
            source: r.source.clone(),
        },
        n_transitions: r.deviations.len(),
        deviations: r.deviations.clone(),
        iteration: i.iteration,
        model_version: r.model_version,
        n_trajectories: r.n_trajectories,
        created_at: r.created_at.clone(),
    }
}

/// `201 Created` with `body`, and the header `idempotent-replayed: true` when the answer replays
/// an earlier request's under the same `Idempotency-Key` (nothing new was stored).
pub fn created<T: serde::Serialize>(body: T, replayed: bool) -> axum::response::Response {
    use axum::response::IntoResponse;
    let mut answer = (axum::http::StatusCode::CREATED, axum::Json(body)).into_response();
    if replayed {
        answer.headers_mut().insert(
            "idempotent-replayed",
            axum::http::HeaderValue::from_static("true"),
        );
    }
    answer
}

/// An exclusion and whether the model answering agrees with it.
pub fn exclusion(experiment_id: i64, r: ExclusionRecord) -> ExclusionView {
    let e = r.exclusion;
    let (trajectory_id, since, until) = match e.scope {
        ExclusionScope::Trajectory(t) => (Some(t), None, None),
        ExclusionScope::TimeRange { from, to } => (None, Some(from), Some(to)),
    };
    ExclusionView {
        id: e.id,
        experiment_id,
        status: if e.restored_at.is_some() {
            ExclusionStatus::Restored
        } else {
            ExclusionStatus::InEffect
        },
        trajectory_id,
        since,
        until,
        reason: e.reason,
        trajectory_ids: e.trajectory_ids,
        n_transitions: e.n_transitions,
        created_at: e.created_at,
        created_by: e.created_by,
        restored_at: e.restored_at,
        restored_by: e.restored_by,
        applied: r.applied,
    }
}

/// A page of exclusions.
pub fn exclusions(experiment_id: i64, page: Exclusions) -> ExclusionPage {
    ExclusionPage {
        items: page
            .items
            .into_iter()
            .map(|r| exclusion(experiment_id, r))
            .collect(),
        total: page.total,
        next: page.next,
    }
}
