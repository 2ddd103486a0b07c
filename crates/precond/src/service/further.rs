//! An experiment's further models of its robot, as its versions hold them: each model's
//! training set among a version's training transitions (its own labels, features of its own
//! prediction), the fit of its estimator beside the domain model's — its kind, its cost added
//! to the fit's budget, a failure that leaves only that model without one — and the rebuild of
//! a stored version's.

use super::Error;
use crate::domain::{Domain, NamedModel};
use crate::mde::{
    Estimator, EstimatorChoice, EstimatorKind, EstimatorParams, FurtherEstimator, Training,
    capped_labels, fit_choosing_label_cap, selection_cost, training_data,
};
use crate::planning::Precondition;
use crate::records::StoredTransition;
use crate::store::{Store, StoredFurther, StoredModel};
use anyhow::Context;
use nalgebra::DMatrix;
use std::collections::HashMap;

/// What the further models' training sets and rebuilds read of a live experiment.
pub(super) struct Further<'a> {
    /// The experiment.
    pub id: i64,
    /// Its domain (features, distances).
    pub domain: &'a dyn Domain,
    /// Its further models, in their order.
    pub models: &'a [NamedModel],
    /// Its tolerance.
    pub d_max: f64,
}

impl Further<'_> {
    /// Each further model's training set among `transitions` (a version's, in id order): the
    /// ones it labelled, with features of its own prediction; models without a label are left
    /// out.
    pub(super) async fn training(
        &self,
        store: &Store,
        transitions: &[StoredTransition],
    ) -> Result<Vec<FurtherSet>, Error> {
        let (Some(first), Some(last)) = (transitions.first(), transitions.last()) else {
            return Ok(Vec::new());
        };
        if self.models.is_empty() {
            return Ok(Vec::new());
        }
        // model → transition → (prediction, deviation)
        let mut labels: HashMap<String, HashMap<i64, (Vec<f64>, f64)>> = HashMap::new();
        for (id, label) in store.model_labels(self.id, first.id, last.id).await? {
            if let (Some(s_pred), Some(deviation)) = (label.s_pred, label.deviation) {
                labels
                    .entry(label.model)
                    .or_default()
                    .insert(id, (s_pred, deviation));
            }
        }
        let dim = self.domain.feature_dim();
        let mut sets = Vec::new();
        for m in self.models {
            let Some(labelled) = labels.get(&m.name) else {
                continue;
            };
            let mut set = FurtherSet {
                model: m.name.clone(),
                features: Vec::new(),
                deviations: Vec::new(),
                trajectories: Vec::new(),
            };
            for t in transitions {
                if let Some((s_pred, deviation)) = labelled.get(&t.id) {
                    set.features.reserve(dim);
                    set.features
                        .extend(self.domain.features(&t.s, &t.a, s_pred));
                    set.deviations.push(*deviation);
                    set.trajectories.push(t.trajectory_id);
                }
            }
            if !set.deviations.is_empty() {
                sets.push(set);
            }
        }
        Ok(sets)
    }

    /// Rebuilds the further models' estimators of a stored version, each from its own
    /// labelled training transitions where its state needs them.
    pub(super) async fn restore(
        &self,
        store: &Store,
        stored: &StoredModel,
    ) -> Result<Vec<FurtherEstimator>, Error> {
        if stored.further.is_empty() {
            return Ok(Vec::new());
        }
        let mut sets = if stored.further.iter().any(|f| f.state.needs_training_data()) {
            let transitions = store
                .transitions_outside(self.id, &stored.exclusions, 0, Some(stored.n_train))
                .await?;
            self.training(store, &transitions).await?
        } else {
            Vec::new()
        };
        let dim = self.domain.feature_dim();
        let d_max = self.d_max;
        let mut rebuilt = Vec::with_capacity(stored.further.len());
        for f in &stored.further {
            let (features, deviations) = if f.state.needs_training_data() {
                let set = sets
                    .iter_mut()
                    .find(|s| s.model == f.model)
                    .filter(|s| s.deviations.len() as i64 == f.n_train)
                    .ok_or_else(|| {
                        Error::Internal(anyhow::anyhow!(
                            "model {} of experiment {}: the estimator of {} was fitted on {} \
                             labelled transitions, which are no longer stored as they were",
                            stored.version,
                            self.id,
                            f.model,
                            f.n_train
                        ))
                    })?;
                (
                    std::mem::take(&mut set.features),
                    std::mem::take(&mut set.deviations),
                )
            } else {
                (Vec::new(), Vec::new())
            };
            let labels = capped_labels(&deviations, f.label_cap, d_max);
            let state = f.state.clone();
            let gp = tokio::task::spawn_blocking(move || {
                let (x, y) = training_data(features, labels, dim);
                let gp = state.restore(&x, &y)?;
                gp.prepare();
                Ok::<_, crate::gp::GpError>(gp)
            })
            .await
            .context("restore task")?
            .map_err(|e| Error::Internal(anyhow::anyhow!("rebuilding a stored MDE: {e}")))?;
            rebuilt.push(FurtherEstimator {
                model: f.model.clone(),
                estimator: Estimator::Fitted(gp),
                label_cap: f.label_cap,
            });
        }
        Ok(rebuilt)
    }
}

/// A further model's training set among a version's training transitions (see
/// [`Further::training`]).
pub(super) struct FurtherSet {
    model: String,
    features: Vec<f64>,
    deviations: Vec<f64>,
    trajectories: Vec<i64>,
}

/// A further model's fitted estimator and its training-set size.
type FurtherFit = (usize, Box<dyn crate::mde::Regressor>);

/// Fits each further model's estimator on its set, of the kind given for it, with the domain
/// model's `(kernel, label cap)`: per model, the training-set size and the prepared estimator,
/// or why it could not be fitted. Runs on the fit's thread.
pub(super) fn fit_further(
    sets: Vec<FurtherSet>,
    kinds: &[EstimatorKind],
    (kernel, label_cap): (crate::gp::Kernel, f64),
    precondition: Precondition,
    dim: usize,
    params: &EstimatorParams,
) -> Vec<(String, Result<FurtherFit, crate::gp::GpError>)> {
    sets.into_iter()
        .zip(kinds)
        .map(|(set, &kind)| {
            let n = set.deviations.len();
            let x = DMatrix::from_row_slice(n, dim, &set.features);
            let training = Training {
                x: &x,
                deviations: &set.deviations,
                trajectories: &set.trajectories,
            };
            let fitted = fit_choosing_label_cap(
                training,
                precondition,
                &[kernel],
                &[label_cap],
                kind,
                params,
            )
            .map(|c| {
                c.gp.prepare();
                (n, c.gp)
            });
            (set.model, fitted)
        })
        .collect()
}

/// The kind of each further model's estimator (by its own training-set size, as the domain
/// model's is chosen) and the fit's cost with theirs: they are fitted after the domain
/// model's, one at a time, so their peaks add to none and their seconds to all.
pub(super) fn further_cost(
    sets: &[FurtherSet],
    choice: EstimatorChoice,
    dim: usize,
    params: &EstimatorParams,
    budget: u64,
    (bytes, seconds): (f64, f64),
) -> (Vec<EstimatorKind>, (f64, f64)) {
    let kinds: Vec<EstimatorKind> = sets
        .iter()
        .map(|f| choice.kind_for(f.deviations.len(), dim, params, budget))
        .collect();
    let cost = sets
        .iter()
        .zip(&kinds)
        .fold((bytes, seconds), |(bytes, secs), (f, &k)| {
            let c = selection_cost(k, f.deviations.len(), dim, 1, 1, params);
            (bytes.max(c.peak_bytes), secs + c.seconds)
        });
    (kinds, cost)
}

/// What a version keeps of its further fits: what it stores and what it serves, each fitted
/// at `label_cap`; a fit that failed is logged and left out.
pub(super) fn kept_fits(
    experiment: i64,
    fits: Vec<(String, Result<FurtherFit, crate::gp::GpError>)>,
    label_cap: f64,
) -> (Vec<StoredFurther>, Vec<FurtherEstimator>) {
    let mut stored = Vec::new();
    let mut served = Vec::new();
    for (model, fitted) in fits {
        match fitted {
            Ok((n, gp)) => {
                stored.push(StoredFurther {
                    model: model.clone(),
                    n_train: n as i64,
                    label_cap,
                    log_marginal_likelihood: gp.log_marginal_likelihood(),
                    state: gp.state(),
                });
                served.push(FurtherEstimator {
                    model,
                    estimator: Estimator::Fitted(gp),
                    label_cap,
                });
            }
            Err(e) => tracing::warn!(
                experiment,
                model = %model,
                error = %e,
                "a further model's estimator could not be fitted; the version has none for it"
            ),
        }
    }
    (stored, served)
}
