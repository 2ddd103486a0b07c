//! The model deviation estimator as a service: the version answering, refits, precondition
//! judgements ("is this state-action trusted?") and test-time plans.

use super::fitting::FitQueue;
use super::live::LiveExperiment;
use super::{Error, Result, Service};
use crate::api::{CandidateTrajectory, Point};
use crate::limits::{MAX_CLIENT_CANDIDATES, MAX_POINTS};
use crate::mde::{Judgement, Margined, ServedModel};
use crate::planning::{self, Path, Precondition, RrtOutcome, Strategy, Trajectory, Verdict};
use crate::records::{FitRefusal, ListOrder};
use crate::seed;
use crate::settings::DOMAIN_MODEL;
use std::sync::Arc;
use std::time::Instant;

/// Judgements of more points than this are computed on the blocking pool.
const INLINE_POINTS: usize = 256;

/// An experiment's model version with what is needed to show it.
#[derive(Debug, Clone)]
pub struct ModelView {
    /// The experiment.
    pub experiment_id: i64,
    /// Names of the feature components.
    pub feature_names: Vec<String>,
    /// The version.
    pub model: Arc<ServedModel>,
    /// The latest fit refused since the version (see [`crate::records::FitRefusal`]).
    pub last_refusal: Option<FitRefusal>,
    /// The β test plans use with this version ([`LiveExperiment::test_beta`]).
    pub test_beta: f64,
}

/// Precondition judgements of a batch of points.
#[derive(Debug, Clone)]
pub struct Judged {
    /// The version that answered.
    pub model: Arc<ServedModel>,
    /// The further model whose precondition was judged (`None`: the domain's own model's).
    pub further: Option<String>,
    /// β used.
    pub beta: f64,
    /// The experiment's tolerance.
    pub d_max: f64,
    /// One judgement per point, in order.
    pub judgements: Vec<Judgement>,
}

/// A test-time plan.
#[derive(Debug, Clone)]
pub struct Planned {
    /// The search's outcome: the plan if found, the extensions spent.
    pub outcome: RrtOutcome,
    /// The client's candidates with their verdicts, when it posted some.
    pub candidates: Option<Vec<Verdict>>,
    /// β used.
    pub beta: f64,
    /// The experiment's tolerance.
    pub d_max: f64,
    /// The model version that answered.
    pub model_version: i64,
    /// The name and cost of each model the plan could step with (the outcome's model indexes
    /// point here), when the experiment has several models.
    pub models: Option<Vec<(String, f64)>>,
}

/// Checks that a planned trajectory carries only finite μ and σ (a model that answered NaN is a
/// bug that must not reach a client).
pub(crate) fn check_finite(t: &Trajectory) -> Result<()> {
    if t.mu.iter().chain(&t.sigma).all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(Error::Internal(anyhow::anyhow!(
            "the model answered a non-finite deviation along a trajectory"
        )))
    }
}

/// Checks the client's candidate trajectories against the domain and the problem's start:
/// shapes, states, actions and steps, with the field named (`candidates[2].actions[5]`).
pub(crate) fn check_candidates(
    live: &LiveExperiment,
    start: &[f64],
    candidates: Vec<CandidateTrajectory>,
) -> Result<Vec<Path>> {
    if candidates.is_empty() || candidates.len() > MAX_CLIENT_CANDIDATES {
        return Err(Error::validation(
            "candidates",
            format!("must hold 1 to {MAX_CLIENT_CANDIDATES} trajectories"),
        ));
    }
    let steps: usize = candidates.iter().map(|c| c.actions.len()).sum();
    if steps > MAX_POINTS {
        return Err(Error::validation(
            "candidates",
            format!("at most {MAX_POINTS} steps in all, got {steps}"),
        ));
    }
    let d = live.domain.as_ref();
    candidates
        .into_iter()
        .enumerate()
        .map(|(i, c)| {
            let at = format!("candidates[{i}]");
            if c.actions.is_empty() || c.states.len() != c.actions.len() + 1 {
                return Err(Error::validation(
                    format!("{at}.states"),
                    format!(
                        "a candidate needs at least one action and one more state than actions \
                         ({} states, {} actions)",
                        c.states.len(),
                        c.actions.len()
                    ),
                ));
            }
            for (t, s) in c.states.iter().enumerate() {
                d.validate_state(s)
                    .map_err(|e| Error::invalid_at(&format!("{at}.states[{t}]"), e))?;
            }
            let s0 = &c.states[0];
            if s0.len() != start.len()
                || s0
                    .iter()
                    .zip(start)
                    .any(|(a, b)| (a - b).abs() > 1e-9 * (1.0 + b.abs()))
            {
                return Err(Error::validation(
                    format!("{at}.states[0]"),
                    format!("must be the start state {start:?}"),
                ));
            }
            for (t, a) in c.actions.iter().enumerate() {
                d.validate_action(a)
                    .and_then(|()| d.validate_step(&c.states[t], a))
                    .map_err(|e| Error::invalid_at(&format!("{at}.actions[{t}]"), e))?;
            }
            Ok((c.states, c.actions))
        })
        .collect()
}

/// Judges the client's (checked) candidates with `model` inside `precondition`, off the async
/// workers.
pub(crate) async fn judge_given(
    live: &Arc<LiveExperiment>,
    model: Arc<ServedModel>,
    goal: Vec<f64>,
    candidates: Vec<Path>,
    precondition: Precondition,
) -> Result<Vec<Verdict>> {
    let live = live.clone();
    let verdicts =
        Service::blocking(move || live.planner(&model).judge(&goal, candidates, precondition))
            .await??;
    for v in &verdicts {
        check_finite(&v.trajectory)?;
    }
    Ok(verdicts)
}

/// The answer to a client whose model lives on its side and who asked the service to plan.
pub(crate) fn needs_candidates(live: &LiveExperiment) -> Result<()> {
    if live.domain.dynamics().client_side() {
        return Err(Error::validation(
            "candidates",
            "the experiment's model is the client's, so the service cannot plan with it: post \
             candidate trajectories (`candidates`) for it to score",
        ));
    }
    Ok(())
}

/// What a forced refit answers.
#[derive(Debug, Clone)]
pub struct Refit {
    /// The new version, or (unfinished) the one still answering.
    pub view: ModelView,
    /// Whether the new version is done; if not it goes on in the background.
    pub finished: bool,
}

impl Service {
    /// The version answering queries now.
    pub async fn model(&self, id: i64) -> Result<ModelView> {
        let live = self.live(id).await?;
        let model = live.model();
        Ok(ModelView {
            experiment_id: id,
            feature_names: live.domain.feature_names(),
            last_refusal: self.last_refusal(id, &model).await?,
            test_beta: live.test_beta(&model),
            model,
        })
    }

    /// The latest refused fit of experiment `id` made after `model`'s fit, if any.
    async fn last_refusal(&self, id: i64, model: &ServedModel) -> Result<Option<FitRefusal>> {
        let covered = model.fit.as_ref().map_or(0, |f| f.n_trajectories);
        Ok(self
            .store
            .latest_fit_refusal(id)
            .await?
            .filter(|r| r.n_trajectories > covered))
    }

    /// Fits a new version on every stored transition now (off the async workers) and answers
    /// with it. The fit is requested in the store and claimed by this replica in a task of its
    /// own; when another fit of the experiment runs (here or on another replica), the answer
    /// is the version that fit stores. If no version covering what is stored now answers within
    /// the planning deadline, the answer is the version answering now, marked unfinished, and
    /// the fit goes on, is stored and swapped in when done (a client that goes away does not
    /// lose it either).
    pub async fn refit(&self, id: i64) -> Result<Refit> {
        let live = self.live(id).await?;
        let stored_now = self
            .store
            .experiment(id)
            .await?
            .map_or(0, |e| e.n_trajectories);
        if stored_now == 0 {
            return Err(Error::Conflict(
                "nothing to fit: the experiment has no transitions yet".into(),
            ));
        }
        let refused_before = self.store.fit_refusal_count(id).await?;
        self.store.request_fit(id, true).await?;
        // One forced fit per experiment waits for a fit slot at a time: a request while one
        // waits or runs is answered by what that one (or the worker after it) stores. Without
        // it, a client asking for refits in a loop queued a task per request, each holding a
        // place in the fit line ahead of every other experiment's background fit.
        // The slot it gets goes to the fit that would finish first (see `Store::claim_fit`),
        // this experiment's or another's: a client forcing refits in a loop does not jump the
        // line of every other experiment's background fit, and its own fit, if another went
        // first, is claimed by the next slot (the answer is then `202`, the fit goes on).
        let fit = FitQueue::start_forcing(&self.fits, id).map(|forcing| {
            let service = self.clone();
            tokio::spawn(async move {
                let _forcing = forcing;
                let slot = service.work.fit_slot().await?;
                let Some(claim) = service.fits.claim_next(&service.store).await? else {
                    return Ok(None);
                };
                let other = claim.experiment_id;
                if other == id {
                    return service.fits.fit_claim(&service, claim, slot).await.map(Some);
                }
                if let Err(e) = service.fits.fit_claim(&service, claim, slot).await {
                    tracing::warn!(experiment = other, error = %e, "fit (in a refit's slot) not made");
                }
                Ok(None)
            })
        });
        let covering = async {
            let fitted = match fit {
                Some(task) => task
                    .await
                    .map_err(|e| Error::Internal(anyhow::Error::new(e).context("refit task")))??,
                None => None,
            };
            if let Some(model) = fitted {
                return Ok::<_, Error>(model);
            }
            // Another fit holds the claim: wait for the version it stores to answer here,
            // or for the refusal of a fit of this data (the fit in flight was refused and the
            // worker refused the forced one after it).
            loop {
                let model = live.model();
                if model
                    .fit
                    .as_ref()
                    .is_some_and(|f| f.n_trajectories >= stored_now)
                {
                    return Ok(model);
                }
                if self.store.fit_refusal_count(id).await? > refused_before
                    && let Some(refusal) = self
                        .store
                        .latest_fit_refusal(id)
                        .await?
                        .filter(|r| r.n_trajectories >= stored_now)
                {
                    return Err(Error::LimitReached(refusal.reason));
                }
                tokio::time::sleep(std::time::Duration::from_millis(20)).await;
            }
        };
        let (model, finished) =
            match tokio::time::timeout(self.work.limits().plan_timeout, covering).await {
                Ok(model) => (model?, true),
                Err(_elapsed) => (live.model(), false),
            };
        Ok(Refit {
            view: ModelView {
                experiment_id: id,
                feature_names: live.domain.feature_names(),
                last_refusal: self.last_refusal(id, &model).await?,
                test_beta: live.test_beta(&model),
                model,
            },
            finished,
        })
    }

    /// Loads every experiment whose latest complete batch has no fitted model (the server
    /// stopped before or during its fit), which requests that fit. Returns how many were
    /// requested.
    pub async fn resume_refits(&self) -> Result<usize> {
        let mut scheduled = 0;
        for e in self.store.experiments(ListOrder::Oldest, 0, None).await? {
            let covered = self
                .store
                .latest_model(e.id)
                .await?
                .map_or(0, |m| m.n_trajectories);
            let l = &e.settings.learning;
            if l.iteration(e.n_trajectories) > l.iteration(covered)
                && self.live.cached(e.id).is_none()
            {
                self.live(e.id).await?;
                scheduled += 1;
            }
        }
        Ok(scheduled)
    }

    /// Judges state-actions against the current model: `upper = μ + βσ`, `inside = upper <
    /// d_max`, with β the request's or the experiment's test β. Errors name the point
    /// (`points[i].s`). More than a few hundred points are evaluated off the async workers, in
    /// an evaluation slot of the work gate
    /// ([`WorkGate::evaluation_slot`](super::WorkGate::evaluation_slot)).
    ///
    /// With `further`, the precondition of that one of the experiment's further models (its
    /// estimator in the current version, at β the request's or `learning.test_beta`); `domain`
    /// names the domain's own model.
    pub async fn judge(
        &self,
        id: i64,
        points: &[Point],
        beta: Option<f64>,
        further: Option<&str>,
    ) -> Result<Judged> {
        let arrived = Instant::now();
        let live = self.live(id).await?;
        if points.is_empty() {
            return Err(Error::validation("points", "must hold at least one point"));
        }
        if points.len() > MAX_POINTS {
            return Err(Error::validation(
                "points",
                format!("at most {MAX_POINTS} points"),
            ));
        }
        if let Some(name) = further.filter(|n| *n != DOMAIN_MODEL) {
            return self.judge_further(&live, name, points, beta, arrived).await;
        }
        let model = live.model();
        let precondition = live.precondition_for(&model, beta)?;
        let domain = live.domain.as_ref();
        let dim = domain.feature_dim();
        let client_side = domain.dynamics().client_side();
        let reads_prediction = domain.features_use_prediction();
        for (i, p) in points.iter().enumerate() {
            live.check_step(&format!("points[{i}]"), &p.s, &p.a)?;
            match (&p.s_pred, client_side && reads_prediction) {
                (Some(s_pred), true) => domain
                    .validate_observed_state(s_pred)
                    .map_err(|e| Error::invalid_at(&format!("points[{i}].s_pred"), e))?,
                (None, true) => {
                    return Err(Error::validation(
                        format!("points[{i}].s_pred"),
                        "the experiment's features read the model's prediction and its model \
                         is the client's: send it with every point",
                    ));
                }
                (Some(_), false) => {
                    return Err(Error::validation(
                        format!("points[{i}].s_pred"),
                        "only a client-side model whose features read the prediction takes \
                         one: the service predicts with any other model itself",
                    ));
                }
                (None, false) => {}
            }
        }
        // The prediction the features read: the client's, or the model's, asked in one call.
        let predicted: Vec<Vec<f64>> = if !reads_prediction {
            vec![Vec::new(); points.len()]
        } else if client_side {
            points
                .iter()
                .map(|p| p.s_pred.clone().unwrap_or_default())
                .collect()
        } else {
            let pairs: Vec<(&[f64], &[f64])> = points
                .iter()
                .map(|p| (p.s.as_slice(), p.a.as_slice()))
                .collect();
            super::ingest::predict_pairs(&live, &pairs).await?
        };
        let mut features = Vec::with_capacity(points.len() * dim);
        for (p, next) in points.iter().zip(&predicted) {
            features.extend(domain.features(&p.s, &p.a, next));
        }
        // Without a β of the request's own, each point at its local margin where the
        // experiment calibrates one.
        let margin = beta.is_none().then(|| live.local_margin(&model)).flatten();
        let evaluate = {
            let model = model.clone();
            move || {
                let betas = margin.map(|(m, prior)| m.betas(&features, prior));
                (model.answer(&features, dim), betas)
            }
        };
        let (answers, betas) = self
            .evaluate_points(points.len(), arrived, evaluate)
            .await?;
        Ok(Judged {
            model,
            further: None,
            beta: precondition.beta(),
            d_max: precondition.d_max(),
            judgements: judgements_of(&answers, precondition, betas.as_deref())?,
        })
    }

    /// `evaluate`, the answers about `points` state-actions: inline on the async worker for at
    /// most [`INLINE_POINTS`], else on the blocking pool in an evaluation slot of the work gate.
    async fn evaluate_points<T: Send + 'static>(
        &self,
        points: usize,
        arrived: Instant,
        evaluate: impl FnOnce() -> T + Send + 'static,
    ) -> Result<T> {
        if points <= INLINE_POINTS {
            return Ok(evaluate());
        }
        let slot = self.work.evaluation_slot(arrived).await?;
        Self::blocking(move || {
            let _slot = slot;
            evaluate()
        })
        .await
    }

    /// [`Service::judge`] for the further model `name`: its prediction read by the features
    /// (the service asks the model, in one call), its estimator in the current version.
    async fn judge_further(
        &self,
        live: &Arc<LiveExperiment>,
        name: &str,
        points: &[Point],
        beta: Option<f64>,
        arrived: Instant,
    ) -> Result<Judged> {
        let model = live.model();
        let named = &live.models[live.further_with_estimator(&model, "model", name)?];
        let precondition = live.precondition(beta.unwrap_or(live.settings.learning.test_beta))?;
        let domain = live.domain.as_ref();
        let dim = domain.feature_dim();
        // The client's own model: where the features read its prediction, the client sends it.
        let posted = named.model.client_side() && domain.features_use_prediction();
        for (i, p) in points.iter().enumerate() {
            live.check_step(&format!("points[{i}]"), &p.s, &p.a)?;
            let field = format!("points[{i}].s_pred");
            match (&p.s_pred, posted) {
                (Some(s_pred), true) => domain
                    .validate_observed_state(s_pred)
                    .map_err(|e| Error::invalid_at(&field, e))?,
                (None, true) => {
                    return Err(Error::validation(
                        field,
                        format!(
                            "the experiment's features read the model's prediction and {name:?} is the client's: send its prediction with every point"
                        ),
                    ));
                }
                (Some(_), false) => {
                    return Err(Error::validation(
                        field,
                        if named.model.client_side() {
                            "the experiment's features do not read the model's prediction"
                                .to_string()
                        } else {
                            format!("the service predicts with {name:?} itself")
                        },
                    ));
                }
                (None, false) => {}
            }
        }
        let predicted: Vec<Vec<f64>> = if posted {
            points
                .iter()
                .map(|p| p.s_pred.clone().unwrap_or_default())
                .collect()
        } else if domain.features_use_prediction() {
            let pairs: Vec<(&[f64], &[f64])> = points
                .iter()
                .map(|p| (p.s.as_slice(), p.a.as_slice()))
                .collect();
            super::ingest::predict_named(named, &pairs).await?
        } else {
            vec![Vec::new(); points.len()]
        };
        let mut features = Vec::with_capacity(points.len() * dim);
        for (p, next) in points.iter().zip(&predicted) {
            features.extend(domain.features(&p.s, &p.a, next));
        }
        let evaluate = {
            let (model, name) = (model.clone(), name.to_string());
            move || {
                model
                    .further(&name)
                    .map(|f| f.estimator.answer(&features, dim))
                    .unwrap_or_default()
            }
        };
        let answers = self
            .evaluate_points(points.len(), arrived, evaluate)
            .await?;
        Ok(Judged {
            model,
            further: Some(name.to_string()),
            beta: precondition.beta(),
            d_max: precondition.d_max(),
            judgements: judgements_of(&answers, precondition, None)?,
        })
    }

    /// A test-time plan from `start` to `goal` inside the precondition at β (default: the test
    /// β): planned by the service — stepping with every model the request allows (default
    /// all with an estimator), each step the cheapest whose precondition trusts it — or the
    /// best of the client's `candidates` (the eligible one with the smallest `α`). Nothing is
    /// stored.
    pub async fn plan(&self, id: i64, request: crate::api::PlanRequest) -> Result<Planned> {
        let crate::api::PlanRequest {
            start,
            goal,
            beta,
            candidates,
            max_extensions,
            models,
        } = request;
        let arrived = std::time::Instant::now();
        if let Some(n) = max_extensions {
            if !(1..=crate::limits::MAX_EXTENSIONS).contains(&n) {
                return Err(Error::validation(
                    "max_extensions",
                    format!("must lie in 1 to {}", crate::limits::MAX_EXTENSIONS),
                ));
            }
            if candidates.is_some() {
                return Err(Error::validation(
                    "max_extensions",
                    "applies to the service's search, not to the client's candidates",
                ));
            }
        }
        if models.is_some() && candidates.is_some() {
            return Err(Error::validation(
                "models",
                "applies to the service's search, not to the client's candidates",
            ));
        }
        let live = self.live(id).await?;
        let problem = live.problem(start, goal)?;
        let model = live.model();
        let steppers = plan_models(&live, &model, models.as_deref())?;
        let precondition = live.precondition_for(&model, beta)?;
        let own_beta = beta.is_some();
        let (beta, d_max) = (precondition.beta(), precondition.d_max());
        let model_version = model.version;
        let several = (!live.models.is_empty()).then(|| model_names(&live, &steppers));
        if let Some(candidates) = candidates {
            let checked = check_candidates(&live, problem.start(), candidates)?;
            let verdicts =
                judge_given(&live, model, problem.goal().to_vec(), checked, precondition).await?;
            let chosen = planning::choose(Strategy::Active, &verdicts, 0);
            let trajectory = chosen.map(|i| verdicts[i].trajectory.clone());
            return Ok(Planned {
                outcome: RrtOutcome {
                    // Every step of a client's candidate is judged by the domain's model.
                    step_models: vec![0; trajectory.as_ref().map_or(0, |t| t.len())],
                    trajectory,
                    extensions: 0,
                    tree_size: 0,
                    dynamics_calls: 0,
                    rejections: Default::default(),
                    model_calls: vec![0],
                },
                candidates: Some(verdicts),
                beta,
                d_max,
                model_version,
                models: several.map(|_| vec![(DOMAIN_MODEL.to_string(), 1.0)]),
            });
        }
        needs_candidates(&live)?;
        // Without a β of the request's own, each step judged at its local margin where the
        // experiment calibrates one ([`Margined`]).
        let margin = (!own_beta).then(|| live.local_margin(&model)).flatten();
        let margined = margin.is_some();
        let seed = seed::mix_values(
            live.settings.seed,
            model.version,
            problem.start().iter().chain(problem.goal()).copied(),
        );
        let searched = (live.clone(), model.clone(), steppers.clone());
        let mut outcome = self
            .search(id, arrived, super::SearchKind::Plan, move |budget| {
                let (live, model, steppers) = searched;
                // The experiment's planner settings, unless this plan asked for its own budget.
                let asked = max_extensions.map(|n| live.planning.with_max_extensions(n as usize));
                let settings = asked.as_ref().unwrap_or(&live.planning);
                let judged = margin
                    .as_ref()
                    .and_then(|(m, prior)| Margined::new(model.as_ref(), m, *prior));
                let deviation: &dyn planning::DeviationModel = match &judged {
                    Some(margined) => margined,
                    None => model.as_ref(),
                };
                let domain = live.domain.as_ref();
                let planner =
                    planning::Planner::new(domain, deviation, settings).within(budget.clone());
                if steppers == [None] {
                    return planner.plan(&problem, precondition, seed);
                }
                let stepping = plan_models_of(&live, &model, &steppers, deviation);
                planner.plan_across(&problem, precondition, &stepping, seed)
            })
            .await?;
        if margined {
            report_own_answers(&live, &model, &steppers, &mut outcome);
        }
        if let Some(t) = &outcome.trajectory {
            check_finite(t)?;
        }
        Ok(Planned {
            outcome,
            candidates: None,
            beta,
            d_max,
            model_version,
            models: several,
        })
    }
}

/// The models a search steps with: `steppers` (see [`plan_models`]) with their dynamics, their
/// deviation models — `deviation` the domain's, each further model's estimator in `model` —
/// and their costs.
pub(super) fn plan_models_of<'a>(
    live: &'a LiveExperiment,
    model: &'a ServedModel,
    steppers: &[Option<usize>],
    deviation: &'a dyn planning::DeviationModel,
) -> Vec<planning::PlanModel<'a>> {
    steppers
        .iter()
        .map(|&i| match i {
            None => planning::PlanModel {
                dynamics: live.domain.dynamics(),
                deviation,
                cost: 1.0,
            },
            Some(k) => {
                let named = &live.models[k];
                let further = model
                    .further(&named.name)
                    .expect("plan_models chose models with an estimator");
                planning::PlanModel {
                    dynamics: named.model.as_ref(),
                    deviation: &further.estimator,
                    cost: named.cost,
                }
            }
        })
        .collect()
}

/// The name and cost of each model of `steppers` (see [`plan_models`]).
pub(super) fn model_names(live: &LiveExperiment, steppers: &[Option<usize>]) -> Vec<(String, f64)> {
    steppers
        .iter()
        .map(|&i| match i {
            None => (DOMAIN_MODEL.to_string(), 1.0),
            Some(k) => (live.models[k].name.clone(), live.models[k].cost),
        })
        .collect()
}

/// A plan searched at the local margin reports `model`'s own μ and σ, not the search's scaled
/// σ, of the steps that relied on the domain's model (the others were never scaled).
fn report_own_answers(
    live: &LiveExperiment,
    model: &ServedModel,
    steppers: &[Option<usize>],
    outcome: &mut RrtOutcome,
) {
    let Some(t) = &mut outcome.trajectory else {
        return;
    };
    let dim = live.domain.feature_dim();
    let domain_steps: Vec<usize> = (0..t.len())
        .filter(|&k| steppers[outcome.step_models[k]].is_none())
        .collect();
    let mut features = Vec::with_capacity(domain_steps.len() * dim);
    for &k in &domain_steps {
        let a = &t.actions[k];
        features.extend(live.domain.features(&t.states[k], a, &t.states[k + 1]));
    }
    let answers = model.answer(&features, dim);
    for (&k, a) in domain_steps.iter().zip(answers) {
        t.mu[k] = a.mu;
        t.sigma[k] = a.sigma;
    }
}

/// The models a test-time plan steps with, as indexes into the experiment's further models
/// (`None` the domain's own), in the order asked: those `asked` by name, or by default the
/// domain's and every further model with an estimator in `model`. An unknown or repeated
/// name is a 422 naming `models`; a further model without an estimator in this version a 409.
pub(super) fn plan_models(
    live: &LiveExperiment,
    model: &ServedModel,
    asked: Option<&[String]>,
) -> Result<Vec<Option<usize>>> {
    let Some(asked) = asked else {
        let mut all = vec![None];
        all.extend(
            live.models
                .iter()
                .enumerate()
                .filter(|(_, m)| !m.model.client_side() && model.further(&m.name).is_some())
                .map(|(k, _)| Some(k)),
        );
        return Ok(all);
    };
    if asked.is_empty() {
        return Err(Error::validation(
            "models",
            "names no model: leave it out to plan with every model",
        ));
    }
    let mut chosen = Vec::with_capacity(asked.len());
    for (i, name) in asked.iter().enumerate() {
        let field = format!("models[{i}]");
        if asked[..i].contains(name) {
            return Err(Error::validation(field, format!("{name:?} is named twice")));
        }
        if name == DOMAIN_MODEL {
            chosen.push(None);
            continue;
        }
        if live
            .models
            .iter()
            .any(|m| &m.name == name && m.model.client_side())
        {
            return Err(Error::validation(
                field,
                format!("{name:?} is the client's own model: the service cannot step with it"),
            ));
        }
        chosen.push(Some(live.further_with_estimator(model, &field, name)?));
    }
    Ok(chosen)
}

/// The judgement of each answer under `precondition` — at its own β where `betas` gives one —
/// or an internal error for a non-finite answer.
fn judgements_of(
    answers: &[crate::mde::Answer],
    precondition: Precondition,
    betas: Option<&[f64]>,
) -> Result<Vec<Judgement>> {
    answers
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let at = match betas {
                Some(b) => precondition.at_beta(b[i])?,
                None => precondition,
            };
            Judgement::of(a, at).ok_or_else(|| {
                Error::Internal(anyhow::anyhow!(
                    "the model answered a non-finite deviation (μ = {}, σ = {})",
                    a.mu,
                    a.sigma
                ))
            })
        })
        .collect()
}
