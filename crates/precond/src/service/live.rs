//! Live experiments: the in-memory side of stored experiments — the built domain and the MDE
//! version that answers queries — loaded from the store on first use, kept for the process's life.
//!
//! Fits run on threads of their own, never on the async workers, one at a time per experiment
//! (by the store's fit claim across replicas, see [`fitting`](super::fitting)); the new version
//! is stored, then swapped in atomically. Queries keep using the previous version until then,
//! so no request ever waits on a fit.

use super::Error;
use super::further::{Further, fit_further, further_cost, kept_fits};
use super::work::{Slot, WorkGate};
use crate::domain::{Domain, LabelledTransition, NamedModel, Problem, Transition};
use crate::mde::{
    Estimator, EstimatorChoice, EstimatorKind, EstimatorParams, FitRecord, LIKELIHOOD_DROP,
    LocalMargin, RefitPlan, SelectionRecord, ServedModel, Training, capped_labels,
    fit_choosing_label_cap, gp_params, held_out_margins, refit_plan, refit_warm, selection_cost,
    training_data,
};
use crate::planning::{Planner, PlanningSettings, Precondition};
use crate::records::{FitRefusal, StoredTransition};
use crate::remote_model::ModelCalls;
use crate::seed;
use crate::settings::{ExperimentSettings, InvalidSetting};
use crate::store::fits::FitFinish;
use crate::store::{ExclusionSet, FitClaim, Store, StoredModel};
use anyhow::Context;
use nalgebra::DMatrix;
use std::collections::HashMap;
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

/// One experiment's settings, domain and current model.
#[derive(Debug)]
pub struct LiveExperiment {
    /// Identifier.
    pub id: i64,
    /// Resolved settings.
    pub settings: ExperimentSettings,
    /// The domain built from `settings.domain`.
    pub domain: Arc<dyn Domain>,
    /// The further models built from `settings.models`, in their order: each labels every
    /// posted transition.
    pub models: Vec<NamedModel>,
    /// The planner's and acquisition's settings, checked once from `settings.learning`.
    pub planning: PlanningSettings,
    model: RwLock<Arc<ServedModel>>,
    fit_lock: tokio::sync::Mutex<()>,
    /// Older versions rebuilt on request (most recent use last), at most [`KEPT_VERSIONS`]
    /// and [`KEPT_VERSIONS_FLOATS`].
    older: std::sync::Mutex<Vec<Arc<ServedModel>>>,
}

/// Older model versions kept in memory per experiment after a rebuild, at most.
pub const KEPT_VERSIONS: usize = 4;

/// Each kept version holds its `L⁻¹` (`n_train²` floats): beyond this many floats in all
/// (256 MiB) the least recently used are dropped, down to the one just rebuilt.
pub const KEPT_VERSIONS_FLOATS: usize = 1 << 25;

impl LiveExperiment {
    /// A live experiment answering from the prior; an error when its learning settings do
    /// not make valid planning settings (resolved settings always do).
    pub fn new(
        id: i64,
        settings: ExperimentSettings,
        domain: Arc<dyn Domain>,
        models: Vec<NamedModel>,
    ) -> Result<Self, InvalidSetting> {
        let prior = ServedModel::prior(
            domain.feature_dim(),
            settings.mde.prior_mean,
            settings.mde.kernel.candidates()[0],
        );
        Ok(Self {
            id,
            planning: settings.learning.planning()?,
            settings,
            domain,
            models,
            model: RwLock::new(Arc::new(prior)),
            fit_lock: tokio::sync::Mutex::new(()),
            older: std::sync::Mutex::new(Vec::new()),
        })
    }

    /// The version answering queries now.
    pub fn model(&self) -> Arc<ServedModel> {
        self.model.read().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Model version `version` (`None`: the one answering now). A version older than the
    /// current one is rebuilt from its stored state and training data (no re-optimisation: one
    /// factorisation) and kept among the last [`KEPT_VERSIONS`] used; `NotFound` if it was never
    /// fitted.
    pub async fn model_at(
        &self,
        store: &Store,
        version: Option<i64>,
    ) -> Result<Arc<ServedModel>, Error> {
        let current = self.model();
        let Some(version) = version.filter(|v| *v != current.version) else {
            return Ok(current);
        };
        if version == 0 {
            let prior = ServedModel::prior(
                self.domain.feature_dim(),
                self.settings.mde.prior_mean,
                self.settings.mde.kernel.candidates()[0],
            );
            return Ok(Arc::new(prior));
        }
        {
            let mut kept = self.older_versions();
            if let Some(i) = kept.iter().position(|m| m.version == version) {
                let m = kept.remove(i);
                kept.push(m.clone());
                return Ok(m);
            }
        }
        let stored = store
            .model_version(self.id, version)
            .await?
            .ok_or_else(|| {
                Error::NotFound(format!(
                    "experiment {} has no model version {version}",
                    self.id
                ))
            })?;
        let rebuilt = Arc::new(self.restore(store, stored).await?);
        let mut kept = self.older_versions();
        kept.retain(|m| m.version != version);
        kept.push(rebuilt.clone());
        let floats = |kept: &[Arc<ServedModel>]| -> usize { kept.iter().map(|m| m.floats()).sum() };
        while kept.len() > 1 && (kept.len() > KEPT_VERSIONS || floats(&kept) > KEPT_VERSIONS_FLOATS)
        {
            kept.remove(0);
        }
        Ok(rebuilt)
    }

    fn older_versions(&self) -> std::sync::MutexGuard<'_, Vec<Arc<ServedModel>>> {
        self.older.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn swap_model(&self, model: Arc<ServedModel>) {
        *self.model.write().unwrap_or_else(|p| p.into_inner()) = model;
    }

    /// Swaps `model` in unless the version answering is newer (a replica's watcher and its own
    /// fit may race).
    fn swap_if_newer(&self, model: Arc<ServedModel>) {
        let mut current = self.model.write().unwrap_or_else(|p| p.into_inner());
        if model.version >= current.version {
            *current = model;
        }
    }

    /// The planning problem `start → goal`, checked against the domain; errors name `start`
    /// or `goal` (and the component, where the domain says which).
    pub fn problem(&self, start: Vec<f64>, goal: Vec<f64>) -> Result<Problem, Error> {
        Problem::new(self.domain.as_ref(), start, goal).map_err(|e| Error::invalid_at("", e))
    }

    /// The β test plans and default judgements use with `model`: `learning.test_beta`, or,
    /// with `learning.calibrate_test_beta`, the β `model` certifies ([`BetaChoice`]: at most
    /// `test_beta`; `test_beta` itself until a version certifies one).
    ///
    /// [`BetaChoice`]: crate::mde::BetaChoice
    pub fn test_beta(&self, model: &ServedModel) -> f64 {
        let l = &self.settings.learning;
        if !l.calibrate_test_beta {
            return l.test_beta;
        }
        model
            .fit
            .as_ref()
            .and_then(|f| f.beta_choice)
            .map_or(l.test_beta, |c| c.beta.min(l.test_beta))
    }

    /// The index among the further models of the one called `name` that `model` holds an
    /// estimator of: a 422 naming `field` for a name the experiment has no model of (listing
    /// them), a 409 for a version without that model's estimator yet.
    pub(crate) fn further_with_estimator(
        &self,
        model: &ServedModel,
        field: &str,
        name: &str,
    ) -> Result<usize, Error> {
        let Some(k) = self.models.iter().position(|m| m.name == name) else {
            let mut names = vec![crate::settings::DOMAIN_MODEL.to_string()];
            names.extend(self.models.iter().map(|m| m.name.clone()));
            return Err(Error::validation(
                field,
                format!(
                    "the experiment has no model named {name:?}; it has {}",
                    names.join(", ")
                ),
            ));
        };
        if model.further(name).is_none() {
            return Err(Error::Conflict(format!(
                "model version {} holds no estimator of {name:?}: one is fitted by the first \
                 fit after it labelled a transition",
                model.version
            )));
        }
        Ok(k)
    }

    /// The locally calibrated margin test plans and default judgements use with `model`, with
    /// the test β it never exceeds ([`LiveExperiment::test_beta`]): with
    /// `learning.local_test_margin`, a version that has one, and a positive test β; else
    /// `None` (every state-action judged at the test β).
    pub fn local_margin(&self, model: &ServedModel) -> Option<(Arc<LocalMargin>, f64)> {
        if !self.settings.learning.local_test_margin {
            return None;
        }
        let beta = self.test_beta(model);
        let margin = model.fit.as_ref()?.local_margin.clone()?;
        (beta > 0.0 && margin.dim() == self.domain.feature_dim()).then_some((margin, beta))
    }

    /// The precondition at a request's `beta`, or at `model`'s test β
    /// ([`LiveExperiment::test_beta`]); errors name `beta`.
    pub fn precondition_for(
        &self,
        model: &ServedModel,
        beta: Option<f64>,
    ) -> Result<Precondition, Error> {
        self.precondition(beta.unwrap_or_else(|| self.test_beta(model)))
    }

    /// The precondition at `beta` under the experiment's `d_max`; errors name `beta`.
    pub fn precondition(&self, beta: f64) -> Result<Precondition, Error> {
        Ok(Precondition::new(beta, self.settings.d_max)?)
    }

    /// A planner over this experiment's domain and `model` under its planning settings.
    pub fn planner<'a>(&'a self, model: &'a ServedModel) -> Planner<'a> {
        Planner::new(self.domain.as_ref(), model, &self.planning)
    }

    /// Checks a state-action that sits at `at` in a request (`transitions[3]`, `points[0]`):
    /// the state, the action, and that the action may be taken from the state. Errors name
    /// `<at>.s` or `<at>.a`.
    pub fn check_step(&self, at: &str, s: &[f64], a: &[f64]) -> Result<(), Error> {
        let d = self.domain.as_ref();
        d.validate_state(s)
            .map_err(|e| Error::invalid_at(&format!("{at}.s"), e))?;
        d.validate_action(a)
            .and_then(|()| d.validate_step(s, a))
            .map_err(|e| Error::invalid_at(&format!("{at}.a"), e))
    }

    /// The learning iteration after `n_trajectories` executed trajectories.
    pub fn iteration(&self, n_trajectories: i64) -> i64 {
        self.settings.learning.iteration(n_trajectories)
    }

    /// The exclusions `model` was fitted under (none for the prior).
    pub(super) fn trained_outside(model: &ServedModel) -> ExclusionSet {
        ExclusionSet::new(
            model
                .fit
                .as_ref()
                .map(|f| f.exclusions.clone())
                .unwrap_or_default(),
        )
    }

    /// What the further models' training sets and rebuilds read of this experiment.
    fn further(&self) -> Further<'_> {
        Further {
            id: self.id,
            domain: self.domain.as_ref(),
            models: &self.models,
            d_max: self.settings.d_max,
        }
    }

    /// Row-major features and deviations of `transitions`.
    pub(super) fn training_set(&self, transitions: &[StoredTransition]) -> (Vec<f64>, Vec<f64>) {
        let mut features = Vec::with_capacity(transitions.len() * self.domain.feature_dim());
        let mut deviations = Vec::with_capacity(transitions.len());
        for t in transitions {
            features.extend(self.domain.features(&t.s, &t.a, &t.s_pred));
            deviations.push(t.deviation);
        }
        (features, deviations)
    }

    /// Fits version `claim.version` on every stored transition under `claim` (this replica's
    /// right to fit the experiment, which the caller heartbeats meanwhile: see
    /// [`FitQueue::fit`](super::FitQueue::fit); `lease` is its lease), on the fit slot `slot`;
    /// stores it and ends the claim in one transaction, then swaps it in. Without
    /// [`FitClaim::forced`], does nothing (but end the claim) when the latest stored version
    /// already covers the latest complete batch. Returns the version answering afterwards.
    ///
    /// Counted in `precond_fits_total` and `precond_fit_seconds`.
    pub(super) async fn fit_under(
        self: &Arc<Self>,
        store: &Store,
        gate: &WorkGate,
        claim: FitClaim,
        slot: Slot,
        lease: Duration,
    ) -> Result<Arc<ServedModel>, Error> {
        let _one_fit_at_a_time = self.fit_lock.lock().await;
        let fitted = self.fit_claimed(store, gate, &claim, slot).await;
        let (stored, served) = match fitted {
            Ok(Some(fitted)) => fitted,
            Ok(None) => {
                store.finish_fit(&claim, None).await?;
                return Ok(self.model());
            }
            Err(e) => {
                store.finish_fit(&claim, None).await?;
                return Err(e);
            }
        };
        let trigger = if claim.forced { "forced" } else { "batch" };
        match store.finish_fit(&claim, Some(&stored)).await? {
            FitFinish::Done => {}
            FitFinish::Lost => {
                metrics::counter!("precond_fits_total", "trigger" => trigger, "result" => "lost")
                    .increment(1);
                return Err(Error::Conflict(format!(
                    "the fit of experiment {} was taken over by another replica (this one \
                     stalled past its {} s lease); its result was dropped",
                    self.id,
                    lease.as_secs()
                )));
            }
        }
        let served = Arc::new(served);
        self.swap_if_newer(served.clone());
        tracing::info!(
            experiment = self.id,
            version = stored.version,
            estimator = served.kind().map_or("prior", |k| k.as_str()),
            n_train = stored.n_train,
            seconds = stored.fit_seconds,
            label_cap = stored.label_cap,
            "model fitted"
        );
        Ok(served)
    }

    /// The fit itself (see [`LiveExperiment::fit_under`]): `None` when nothing needs fitting.
    async fn fit_claimed(
        self: &Arc<Self>,
        store: &Store,
        gate: &WorkGate,
        claim: &FitClaim,
        slot: Slot,
    ) -> Result<Option<(StoredModel, ServedModel)>, Error> {
        let trigger = if claim.forced { "forced" } else { "batch" };
        let n_trajectories = store
            .experiment(self.id)
            .await?
            .map(|e| e.n_trajectories)
            .unwrap_or(0);
        if !claim.forced
            && self.iteration(n_trajectories) <= self.iteration(claim.covered_trajectories)
        {
            return Ok(None);
        }
        let exclusions = store.active_exclusions(self.id).await?;
        let transitions = store
            .transitions_outside(self.id, &exclusions, 0, None)
            .await?;
        if transitions.is_empty() {
            return Err(Error::Conflict(if exclusions.is_empty() {
                "nothing to fit: the experiment has no transitions yet".into()
            } else {
                "nothing to fit: every stored transition is excluded".into()
            }));
        }
        let version = claim.version;
        let (features, deviations) = self.training_set(&transitions);
        let further_sets = self.further().training(store, &transitions).await?;
        let trajectories: Vec<i64> = transitions.iter().map(|t| t.trajectory_id).collect();
        let dim = self.domain.feature_dim();
        let mde = &self.settings.mde;
        let params = EstimatorParams::new(
            gp_params(
                mde.noise,
                mde.kernel.candidates()[0],
                mde.prior_mean,
                mde.restarts,
                seed::mix(self.settings.seed, version),
            ),
            mde.inducing_points,
        )
        .map_err(|e| Error::Internal(anyhow::anyhow!("estimator parameters: {e}")))?
        .with_expert_size(mde.expert_size)
        .with_selection_subset(mde.selection_subset);
        let n = deviations.len();
        let budget = gate.limits().max_fit_memory;
        let seconds_budget = gate.limits().max_fit_seconds as f64;
        let caps = self.settings.label_caps();
        let kernels = mde.kernel.candidates();
        let cost = |kind| selection_cost(kind, n, dim, kernels.len(), caps.len(), &params);
        let mut kind = mde.estimator.kind_for(n, dim, &params, budget);
        if mde.estimator == EstimatorChoice::Auto
            && kind == EstimatorKind::Exact
            && cost(kind).seconds > seconds_budget
            && cost(EstimatorKind::Sparse).seconds < cost(kind).seconds
        {
            kind = EstimatorKind::Sparse;
        }
        let previous = self.model();
        let plan = refit_plan(
            previous.as_previous(),
            version,
            n,
            kind,
            &kernels,
            &caps,
            mde.reselect_every,
        );
        // A warm refit is one fit; a selection one per candidate (its full cost, the
        // candidates fitted at once held in memory together).
        let (needed, seconds) = match &plan {
            RefitPlan::Warm { .. } => {
                let one = selection_cost(kind, n, dim, 1, 1, &params);
                (one.peak_bytes, one.seconds)
            }
            RefitPlan::Select { .. } => (cost(kind).peak_bytes, cost(kind).seconds),
        };
        let (further_kinds, (needed, seconds)) = further_cost(
            &further_sets,
            mde.estimator,
            dim,
            &params,
            budget,
            (needed, seconds),
        );
        let refusal = if needed > budget as f64 {
            Some(FitRefusal::now(
                n as i64,
                n_trajectories,
                kind,
                needed,
                budget as f64,
            ))
        } else if seconds > seconds_budget {
            Some(FitRefusal::over_time(
                n as i64,
                n_trajectories,
                kind,
                (needed, budget as f64),
                (seconds, seconds_budget),
            ))
        } else {
            None
        };
        if let Some(refusal) = refusal {
            store.insert_fit_refusal(self.id, &refusal).await?;
            metrics::counter!("precond_fits_total", "trigger" => trigger, "result" => "refused")
                .increment(1);
            tracing::warn!(experiment = self.id, n_train = n, reason = %refusal.reason, "fit refused");
            return Err(Error::LimitReached(refusal.reason));
        }
        tracing::info!(
            experiment = self.id,
            n_train = n,
            estimator = kind.as_str(),
            estimated_seconds = seconds,
            warm = matches!(plan, RefitPlan::Warm { .. }),
            "fitting"
        );
        // A warm refit keeps the selection's trials (what the kept choice rests on).
        let kept_trials = previous
            .fit
            .as_ref()
            .map(|f| (f.label_cap_trials.clone(), f.kernel_trials.clone()));
        let precondition = self.precondition(self.settings.learning.test_beta)?;
        let started = Instant::now();
        let gp = super::work::run_niced(move || {
            let _slot = slot;
            let x = DMatrix::from_row_slice(deviations.len(), dim, &features);
            let training = || Training {
                x: &x,
                deviations: &deviations,
                trajectories: &trajectories,
            };
            let select = |reason: String| {
                fit_choosing_label_cap(training(), precondition, &kernels, &caps, kind, &params)
                    .map(|c| {
                        let record = SelectionRecord {
                            selected_at_version: version,
                            selected_n_train: n,
                            reason,
                            phases: Vec::new(),
                        };
                        (c, record)
                    })
            };
            let (mut choice, mut record) = match plan {
                RefitPlan::Select { reason } => select(reason)?,
                RefitPlan::Warm {
                    carry,
                    selected_at_version,
                    selected_n_train,
                    previous_lml_per_transition,
                    reason,
                } => {
                    let warm = refit_warm(training(), precondition, &carry, kind, &params)?;
                    let per = warm.gp.log_marginal_likelihood() / n.max(1) as f64;
                    if per < previous_lml_per_transition - LIKELIHOOD_DROP {
                        let (mut chosen, record) = select(format!(
                            "the warm refit's log likelihood per transition fell from \
                             {previous_lml_per_transition:.3} to {per:.3}: chosen anew"
                        ))?;
                        let mut phases = warm.phases;
                        phases.append(&mut chosen.phases);
                        chosen.phases = phases;
                        (chosen, record)
                    } else {
                        let mut warm = warm;
                        if let Some((trials, kernel_trials)) = kept_trials {
                            warm.trials = trials;
                            warm.kernel_trials = kernel_trials;
                        }
                        let record = SelectionRecord {
                            selected_at_version,
                            selected_n_train,
                            reason,
                            phases: Vec::new(),
                        };
                        (warm, record)
                    }
                }
            };
            record.phases = std::mem::take(&mut choice.phases);
            // Here, not in the first query: a small query is answered on an async worker.
            choice.gp.prepare();
            let kernel = choice.gp.hyperparameters().map_or(kernels[0], |h| h.kernel);
            let further = fit_further(
                further_sets,
                &further_kinds,
                (kernel, choice.label_cap),
                precondition,
                dim,
                &params,
            );
            Ok::<_, crate::gp::GpError>((choice, record, further))
        })
        .await?;
        let result = if gp.is_ok() { "ok" } else { "failed" };
        metrics::counter!("precond_fits_total", "trigger" => trigger, "result" => result)
            .increment(1);
        metrics::histogram!("precond_fit_seconds").record(started.elapsed().as_secs_f64());
        let (choice, selection, further) =
            gp.map_err(|e| Error::Internal(anyhow::anyhow!("fitting the MDE: {e}")))?;
        let (stored_further, further) = kept_fits(self.id, further, choice.label_cap);
        let gp = choice.gp;
        let fit = FitRecord {
            fit_seconds: started.elapsed().as_secs_f64(),
            fitted_at: crate::store::now(),
            n_trajectories,
            label_cap: choice.label_cap,
            label_cap_trials: choice.trials,
            online_trajectories: 0,
            kernel_trials: choice.kernel_trials,
            beta_choice: choice.beta_choice,
            selection: Some(selection),
            local_margin: choice.local_margin.map(Arc::new),
            exclusions: exclusions.ids().to_vec(),
        };
        let stored = StoredModel {
            version,
            n_train: gp.n_train() as i64,
            exclusions,
            n_trajectories,
            state: gp.state(),
            log_marginal_likelihood: gp.log_marginal_likelihood(),
            fit_seconds: fit.fit_seconds,
            fitted_at: fit.fitted_at.clone(),
            label_cap: fit.label_cap,
            label_cap_trials: fit.label_cap_trials.clone(),
            kernel_trials: fit.kernel_trials.clone(),
            beta_choice: fit.beta_choice,
            selection: fit.selection.clone(),
            further: stored_further,
        };
        Ok(Some((
            stored,
            ServedModel {
                version,
                estimator: Estimator::Fitted(gp),
                fit: Some(fit),
                further: Arc::new(further),
            },
        )))
    }

    /// Loads the newest stored version (fitted by another replica) and swaps it in unless a
    /// newer one answers already; returns the version answering afterwards.
    pub async fn load_latest(&self, store: &Store) -> Result<i64, Error> {
        let Some(stored) = store.latest_model(self.id).await? else {
            return Ok(self.model().version);
        };
        if stored.version <= self.model().version {
            return Ok(self.model().version);
        }
        let served = self.restore(store, stored).await?;
        self.swap_if_newer(Arc::new(served));
        Ok(self.model().version)
    }

    /// Takes a posted trajectory into the answering version at its hyperparameters, when that
    /// version is a regressor that updates online (the sparse GP): queries reflect the new data
    /// at once, between refits. `transitions` are the trajectory's, stored after the version's
    /// training data. Does nothing for the prior and the exact GP (they wait for the batch's
    /// refit); a failed update leaves the version as it was (logged).
    pub fn absorb(&self, transitions: &[LabelledTransition], trajectories: usize) {
        let current = self.model();
        let (Estimator::Fitted(gp), Some(fit)) = (&current.estimator, &current.fit) else {
            return;
        };
        if !gp.kind().updates_online() || transitions.is_empty() {
            return;
        }
        let dim = self.domain.feature_dim();
        let mut features = Vec::with_capacity(transitions.len() * dim);
        let mut deviations = Vec::with_capacity(transitions.len());
        for t in transitions {
            features.extend(
                self.domain
                    .features(&t.observed.s, &t.observed.a, &t.s_pred),
            );
            deviations.push(t.deviation);
        }
        let labels = capped_labels(&deviations, fit.label_cap, self.settings.d_max);
        let (x, y) = training_data(features, labels, dim);
        match gp.update(&x, &y) {
            Ok(updated) => {
                // Absorbing runs on a blocking thread; the queries after it need not form this.
                updated.prepare();
                let mut fit = fit.clone();
                fit.online_trajectories += trajectories;
                self.swap_model(Arc::new(ServedModel {
                    version: current.version,
                    estimator: Estimator::Fitted(updated),
                    fit: Some(fit),
                    further: current.further.clone(),
                }));
            }
            Err(e) => tracing::warn!(experiment = self.id, error = %e, "online update failed"),
        }
    }

    /// Rebuilds a stored version without re-optimising: the exact GP from its hyperparameters
    /// and training data, the sparse GP from its stored factors.
    async fn restore(&self, store: &Store, stored: StoredModel) -> Result<ServedModel, Error> {
        let further = self.further().restore(store, &stored).await?;
        let dim = self.domain.feature_dim();
        let (features, labels, deviations, trajectories) = if stored.state.needs_training_data() {
            let transitions = store
                .transitions_outside(self.id, &stored.exclusions, 0, Some(stored.n_train))
                .await?;
            if transitions.len() as i64 != stored.n_train {
                return Err(Error::Internal(anyhow::anyhow!(
                    "model {} of experiment {} was fitted on {} transitions but {} are stored",
                    stored.version,
                    self.id,
                    stored.n_train,
                    transitions.len()
                )));
            }
            let (features, deviations) = self.training_set(&transitions);
            let labels = capped_labels(&deviations, stored.label_cap, self.settings.d_max);
            let trajectories = transitions.iter().map(|t| t.trajectory_id).collect();
            (features, labels, deviations, trajectories)
        } else {
            (Vec::new(), Vec::new(), Vec::new(), Vec::new())
        };
        let state = stored.state.clone();
        // The local margin is not stored: rebuilt from the same held-out judgements the fit
        // made, where test plans use it.
        let margin_up_to = self
            .settings
            .learning
            .local_test_margin
            .then_some(self.settings.learning.test_beta);
        let d_max = self.settings.d_max;
        let (gp, local_margin) = tokio::task::spawn_blocking(move || {
            let (x, y) = training_data(features, labels.clone(), dim);
            let gp = state.restore(&x, &y)?;
            gp.prepare();
            let margin = margin_up_to
                .filter(|_| !deviations.is_empty())
                .and_then(|max_beta| {
                    let training = Training {
                        x: &x,
                        deviations: &deviations,
                        trajectories: &trajectories,
                    };
                    held_out_margins(gp.as_ref(), training, &labels, d_max, max_beta).1
                });
            Ok::<_, crate::gp::GpError>((gp, margin))
        })
        .await
        .context("restore task")?
        .map_err(|e| Error::Internal(anyhow::anyhow!("rebuilding the stored MDE: {e}")))?;
        Ok(ServedModel {
            version: stored.version,
            estimator: Estimator::Fitted(gp),
            fit: Some(FitRecord {
                fit_seconds: stored.fit_seconds,
                fitted_at: stored.fitted_at,
                n_trajectories: stored.n_trajectories,
                label_cap: stored.label_cap,
                label_cap_trials: stored.label_cap_trials,
                online_trajectories: 0,
                kernel_trials: stored.kernel_trials,
                beta_choice: stored.beta_choice,
                selection: stored.selection,
                local_margin: local_margin.map(Arc::new),
                exclusions: stored.exclusions.ids().to_vec(),
            }),
            further: Arc::new(further),
        })
    }
}

/// Every experiment this process has touched.
#[derive(Debug, Default)]
pub struct Registry {
    experiments: RwLock<HashMap<i64, Arc<LiveExperiment>>>,
    loading: tokio::sync::Mutex<()>,
}

impl Registry {
    /// The live experiment `id` if this process has loaded it.
    pub fn cached(&self, id: i64) -> Option<Arc<LiveExperiment>> {
        self.experiments
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .get(&id)
            .cloned()
    }

    /// Adds a just-created experiment.
    pub fn insert(&self, live: LiveExperiment) -> Arc<LiveExperiment> {
        let live = Arc::new(live);
        self.experiments
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .insert(live.id, live.clone());
        live
    }

    /// The live experiment `id`, loading it (and its latest model) from the store if needed;
    /// 404 if it does not exist. A batch that completed but was never fitted (the server stopped
    /// first) is requested a fit, and `fit_requested` called (to wake a fit worker).
    pub async fn get(
        &self,
        store: &Store,
        fit_requested: impl FnOnce(),
        model_calls: &Arc<ModelCalls>,
        id: i64,
    ) -> Result<Arc<LiveExperiment>, Error> {
        if let Some(live) = self.cached(id) {
            return Ok(live);
        }
        let _one_load_at_a_time = self.loading.lock().await;
        if let Some(live) = self.cached(id) {
            return Ok(live);
        }
        let stored = store
            .experiment(id)
            .await?
            .ok_or_else(|| Error::no_experiment(id))?;
        let domain = build_stored_domain(id, &stored.settings, model_calls)?;
        let models = stored
            .settings
            .build_models(&*domain, model_calls)
            .map_err(|e| {
                Error::Internal(anyhow::anyhow!(
                    "the further models of stored experiment {id} no longer build: {e}"
                ))
            })?;
        let live = LiveExperiment::new(id, stored.settings, domain, models).map_err(|e| {
            Error::Internal(anyhow::anyhow!(
                "stored experiment {id} no longer has valid settings: {e}"
            ))
        })?;
        let mut covered = 0;
        let mut online_from = None;
        if let Some(model) = store.latest_model(id).await? {
            covered = model.n_trajectories;
            let (n_train, exclusions) = (model.n_train, model.exclusions.clone());
            let served = live.restore(store, model).await?;
            if served.kind().is_some_and(EstimatorKind::updates_online)
                && stored.n_trajectories > covered
            {
                online_from = Some((n_train, exclusions));
            }
            live.swap_model(Arc::new(served));
        }
        let live = self.insert(live);
        if let Some((n_train, exclusions)) = online_from {
            // What was taken in online before the restart is taken in again.
            let later: Vec<LabelledTransition> = store
                .transitions_after_first(id, &exclusions, n_train, i64::MAX)
                .await?
                .into_iter()
                .map(|t| LabelledTransition {
                    observed: Transition::new(t.s, t.a, t.s_next),
                    s_pred: t.s_pred,
                    deviation: t.deviation,
                })
                .collect();
            let trajectories = (stored.n_trajectories - covered) as usize;
            let absorbing = live.clone();
            tokio::task::spawn_blocking(move || absorbing.absorb(&later, trajectories))
                .await
                .context("online update task")?;
        }
        if live.iteration(stored.n_trajectories) > live.iteration(covered) {
            store.request_fit(id, false).await?;
            fit_requested();
        }
        Ok(live)
    }
}

/// Builds the domain of stored experiment `id` (a remote model called under `model_calls`,
/// whose policy refuses every call to a URL the operator no longer allows); a failure is a bug
/// (or a stored row edited by hand): it was validated when the experiment was created.
pub fn build_stored_domain(
    id: i64,
    settings: &ExperimentSettings,
    model_calls: &Arc<ModelCalls>,
) -> Result<Arc<dyn Domain>, Error> {
    settings.domain.build(model_calls).map_err(|e| {
        Error::Internal(anyhow::anyhow!(
            "stored experiment {id} no longer builds: {e}"
        ))
    })
}
