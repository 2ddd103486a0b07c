//! Ingest: validate executed transitions against the domain, label each with the experiment's
//! own model (`d(f̂(s, a), s_next)`, one batched model call per trajectory) and with each of its
//! further models ([`label_by_models`]; a model that fails leaves its label missing, never the
//! transition), and store the trajectory in one transaction, idempotently. A batch that
//! completes schedules a refit.
//!
//! A trajectory posted for a proposal is compared with it ([`deviates`]): one that is not the
//! proposal's actions from the proposal's start (or a prefix of them) is stored all the same
//! (the data is real) and flagged `deviating`. A trajectory may carry its provenance (a logged
//! dataset, a simulated environment), stored and shown with it.

use super::live::LiveExperiment;
use super::{Error, Result, Service};
use crate::api::{TrajectoryRequest, TrajectorySource};
use crate::domain::{DynamicsError, DynamicsModel, LabelledTransition, Predicted, Transition};
use crate::limits::{MAX_IDEMPOTENCY_KEY_LEN, MAX_SOURCE_TEXT_LEN, MAX_TRANSITIONS};
use crate::records::{ModelLabel, Provenance, StoredTransition};
use crate::store::{
    IdempotencyKey, IngestOutcome, IngestRecord, ProposalPlan, StoredTrajectory, TrajectoryMeta,
};
use std::sync::Arc;

/// What an ingest answered: what was stored (or, for a retry with the same `Idempotency-Key`
/// and body, what the first request stored), with the learning iteration it reached.
#[derive(Debug, Clone, PartialEq)]
pub struct Ingested {
    /// The experiment.
    pub experiment_id: i64,
    /// The stored trajectory and the state it found.
    pub record: IngestRecord,
    /// The learning iteration after it.
    pub iteration: i64,
    /// Whether this answers a retry: nothing was stored this time.
    pub replayed: bool,
}

/// Relative tolerance under which an executed action, or the executed start, is the proposal's:
/// `|x − p| ≤ 1e-6 · max(1, |p|)` per component. A robot that sends the proposal's numbers back
/// (through `float32` or not) stays well inside it; one that measurably did something else does
/// not. Migration 0009 applies the same rule to trajectories stored before it.
pub const EXECUTION_TOLERANCE: f64 = 1e-6;

fn same(x: &[f64], planned: &[f64]) -> bool {
    x.len() == planned.len()
        && x.iter()
            .zip(planned)
            .all(|(x, p)| (x - p).abs() <= EXECUTION_TOLERANCE * p.abs().max(1.0))
}

/// Whether an execution departs from the proposal it names: it is longer than the proposal,
/// starts elsewhere than the proposal's start, or some action is not the proposal's action at
/// its step (within [`EXECUTION_TOLERANCE`]). A prefix of the proposal — a robot that stopped
/// early — does not deviate.
pub fn deviates<'a>(
    plan: &ProposalPlan,
    executed: impl ExactSizeIterator<Item = (&'a [f64], &'a [f64])>,
) -> bool {
    if executed.len() > plan.actions.len() {
        return true;
    }
    executed
        .enumerate()
        .any(|(step, (s, a))| (step == 0 && !same(s, &plan.start)) || !same(a, &plan.actions[step]))
}

/// A trajectory's provenance as sent, checked; the error names the field.
pub fn check_source(source: TrajectorySource) -> Result<Provenance> {
    let text = |field: &str, value: &str, min: usize| {
        let n = value.chars().count();
        if n < min || n > MAX_SOURCE_TEXT_LEN {
            return Err(Error::validation(
                format!("source.{field}"),
                format!("must be {min} to {MAX_SOURCE_TEXT_LEN} characters, got {n}"),
            ));
        }
        Ok(())
    };
    text("dataset", &source.dataset, 1)?;
    if let Some(label) = &source.label {
        text("label", label, 0)?;
    }
    for (field, value) in [
        ("episode", source.episode),
        ("first_step", source.first_step),
    ] {
        if let Some(v) = value
            && v < 0
        {
            return Err(Error::validation(
                format!("source.{field}"),
                format!("must be at least 0, got {v}"),
            ));
        }
    }
    Ok(source)
}

/// An `Idempotency-Key` as sent (the header's bytes), checked: 1 to
/// [`MAX_IDEMPOTENCY_KEY_LEN`] visible ASCII characters (space to `~`). The one rule for keys.
pub fn check_idempotency_key(key: &[u8]) -> Result<&str> {
    let visible = |b: &u8| (b' '..=b'~').contains(b);
    match std::str::from_utf8(key) {
        Ok(k) if !k.is_empty() && k.len() <= MAX_IDEMPOTENCY_KEY_LEN && key.iter().all(visible) => {
            Ok(k)
        }
        _ => Err(Error::validation(
            "Idempotency-Key",
            format!("must be 1 to {MAX_IDEMPOTENCY_KEY_LEN} visible ASCII characters"),
        )),
    }
}

/// Validates every transition against the domain (the field named by its index) and labels it
/// with the model's prediction. The model is called once for the whole trajectory, off the
/// async workers (an in-process model on the blocking pool, a remote one on its own call
/// thread under [`ModelCalls`](crate::remote_model::ModelCalls)' limits); if it fails, nothing
/// is labelled.
pub async fn label(
    live: &Arc<LiveExperiment>,
    transitions: Vec<Transition>,
    max_transitions: usize,
) -> Result<Vec<LabelledTransition>> {
    if transitions.is_empty() {
        return Err(Error::validation(
            "transitions",
            "must hold at least one transition",
        ));
    }
    if transitions.len() > max_transitions.min(MAX_TRANSITIONS) {
        return Err(Error::validation(
            "transitions",
            format!(
                "at most {} transitions per trajectory",
                max_transitions.min(MAX_TRANSITIONS)
            ),
        ));
    }
    let client_side = live.domain.dynamics().client_side();
    for (i, t) in transitions.iter().enumerate() {
        let at = |name: &str| format!("transitions[{i}].{name}");
        live.check_step(&format!("transitions[{i}]"), &t.s, &t.a)?;
        live.domain
            .validate_observed_state(&t.s_next)
            .map_err(|e| Error::invalid_at(&at("s_next"), e))?;
        match (&t.s_pred, client_side) {
            (Some(s_pred), true) => live
                .domain
                .validate_observed_state(s_pred)
                .map_err(|e| Error::invalid_at(&at("s_pred"), e))?,
            (None, true) => {
                return Err(Error::validation(
                    at("s_pred"),
                    "the experiment's model is the client's: post its prediction with every \
                     transition",
                ));
            }
            (Some(_), false) => {
                return Err(Error::validation(
                    at("s_pred"),
                    "the experiment's model is not the client's: the service predicts with it, \
                     so that every label comes from one model",
                ));
            }
            (None, false) => {}
        }
        for (name, s_pred) in t.predictions.iter().flatten() {
            check_client_prediction(live, i, name, s_pred)?;
        }
    }
    let predicted: Vec<Vec<f64>> = if client_side {
        transitions
            .iter()
            .map(|t| t.s_pred.clone().unwrap_or_default())
            .collect()
    } else {
        let pairs: Vec<(&[f64], &[f64])> = transitions
            .iter()
            .map(|t| (t.s.as_slice(), t.a.as_slice()))
            .collect();
        predict_pairs(live, &pairs).await?
    };
    transitions
        .into_iter()
        .zip(predicted)
        .enumerate()
        .map(|(i, (observed, s_pred))| {
            let deviation = live.domain.distance(&s_pred, &observed.s_next);
            if !deviation.is_finite() {
                return Err(Error::validation(
                    format!("transitions[{i}].s_next"),
                    "the deviation from the prediction is not a finite number",
                ));
            }
            Ok(LabelledTransition {
                observed,
                s_pred,
                deviation,
            })
        })
        .collect()
}

/// The experiment's model's predictions `f̂(s, a)` of `pairs`, in order: a remote model waited
/// for as a task (the call on a thread of its own, bounded by the operator's limits; no
/// blocking-pool thread is held), an in-process one on the blocking pool. Not for a client-side
/// model, which the service never calls.
pub async fn predict_pairs(
    live: &Arc<LiveExperiment>,
    pairs: &[(&[f64], &[f64])],
) -> Result<Vec<Vec<f64>>> {
    let domain = live.domain.clone();
    predict_through(
        live.domain.dynamics(),
        &format!("of the {} domain", live.domain.kind()),
        pairs,
        move |states, actions| domain.dynamics().predict_batch(states, actions),
    )
    .await
}

/// The further model `named`'s predictions of `pairs`, in order (see [`predict_pairs`]).
pub async fn predict_named(
    named: &crate::domain::NamedModel,
    pairs: &[(&[f64], &[f64])],
) -> Result<Vec<Vec<f64>>> {
    let model = named.model.clone();
    predict_through(
        named.model.as_ref(),
        &named.name,
        pairs,
        move |states, actions| model.predict_batch(states, actions),
    )
    .await
}

/// `model`'s predictions of `pairs` (see [`predict_pairs`]); `blocking` is the same model's
/// batch call, run on the blocking pool when the model has no awaitable answer. `name` names
/// the model in an error.
async fn predict_through(
    model: &dyn DynamicsModel,
    name: &str,
    pairs: &[(&[f64], &[f64])],
    blocking: impl FnOnce(&[&[f64]], &[&[f64]]) -> std::result::Result<Vec<Predicted>, DynamicsError>
    + Send
    + 'static,
) -> Result<Vec<Vec<f64>>> {
    let states: Vec<&[f64]> = pairs.iter().map(|(s, _)| *s).collect();
    let actions: Vec<&[f64]> = pairs.iter().map(|(_, a)| *a).collect();
    let awaited = match model.predict_awaitable(&states, &actions) {
        Some(answer) => Some(answer.await),
        None => None,
    };
    let predicted = match awaited {
        Some(predicted) => predicted,
        None => {
            let owned: Vec<(Vec<f64>, Vec<f64>)> = pairs
                .iter()
                .map(|(s, a)| (s.to_vec(), a.to_vec()))
                .collect();
            Service::blocking(move || {
                let states: Vec<&[f64]> = owned.iter().map(|(s, _)| s.as_slice()).collect();
                let actions: Vec<&[f64]> = owned.iter().map(|(_, a)| a.as_slice()).collect();
                blocking(&states, &actions)
            })
            .await?
        }
    }?;
    if predicted.len() != pairs.len() {
        return Err(Error::Dynamics(DynamicsError::Unavailable {
            model: name.to_string(),
            reason: format!(
                "answered {} predictions for {} points",
                predicted.len(),
                pairs.len()
            ),
        }));
    }
    Ok(predicted.into_iter().map(|p| p.next).collect())
}

/// Checks transition `i`'s prediction by the further model `name`: it must be one of the
/// client's own and the prediction a state of the domain.
fn check_client_prediction(
    live: &LiveExperiment,
    i: usize,
    name: &str,
    s_pred: &[f64],
) -> Result<()> {
    let field = format!("transitions[{i}].predictions");
    match live.models.iter().find(|m| m.name == name) {
        Some(m) if m.model.client_side() => live
            .domain
            .validate_observed_state(s_pred)
            .map_err(|e| Error::invalid_at(&format!("{field}.{name}"), e)),
        Some(_) => Err(Error::validation(
            format!("{field}.{name}"),
            format!(
                "the service predicts with {name:?} itself, so that every label of it comes from the model"
            ),
        )),
        None => {
            let shown: String = name
                .chars()
                .take(crate::settings::models::MAX_MODEL_NAME_LEN)
                .collect();
            let own: Vec<&str> = live
                .models
                .iter()
                .filter(|m| m.model.client_side())
                .map(|m| m.name.as_str())
                .collect();
            Err(Error::validation(
                field,
                format!(
                    "{shown:?} is not a further model of the experiment's that is the client's own (those are: {})",
                    if own.is_empty() {
                        "none".to_string()
                    } else {
                        own.join(", ")
                    }
                ),
            ))
        }
    }
}

/// The labels of `transitions` by each of the experiment's further models, one list per
/// transition in the models' order (empty lists when there are none). The models are asked
/// at once, each with one batched call; a model that fails, or whose prediction is not a
/// state of the domain or gives no finite deviation, leaves its label of that transition
/// missing with the reason — the transitions are stored all the same.
pub async fn label_by_models(
    live: &Arc<LiveExperiment>,
    transitions: &[LabelledTransition],
) -> Vec<Vec<ModelLabel>> {
    let pairs: Vec<(&[f64], &[f64])> = transitions
        .iter()
        .map(|t| (t.observed.s.as_slice(), t.observed.a.as_slice()))
        .collect();
    let answers = futures_util::future::join_all(live.models.iter().map(|named| {
        let model = named.model.clone();
        let pairs = &pairs;
        async move {
            if model.client_side() {
                // The client's own model: its predictions came with the transitions.
                return Ok::<_, Error>(
                    transitions
                        .iter()
                        .map(|t| {
                            t.observed
                                .predictions
                                .as_ref()
                                .and_then(|p| p.get(&named.name).cloned())
                        })
                        .collect::<Vec<_>>(),
                );
            }
            let predicted = predict_through(
                named.model.as_ref(),
                &named.name,
                pairs,
                move |states, actions| model.predict_batch(states, actions),
            )
            .await?;
            Ok(predicted.into_iter().map(Some).collect())
        }
    }))
    .await;
    let mut labels: Vec<Vec<ModelLabel>> = transitions
        .iter()
        .map(|_| Vec::with_capacity(live.models.len()))
        .collect();
    for (named, answer) in live.models.iter().zip(answers) {
        let name = named.name.as_str();
        match answer {
            Ok(predicted) => {
                for ((of, t), s_pred) in labels.iter_mut().zip(transitions).zip(predicted) {
                    of.push(match s_pred {
                        Some(s_pred) => model_label(live, name, t, s_pred),
                        None => ModelLabel::missing(
                            name,
                            "the client posted no prediction of it with the transition",
                        ),
                    });
                }
            }
            Err(e) => {
                tracing::warn!(experiment = live.id, model = name, error = %e, "a further model left its labels missing");
                let why = e.to_string();
                for of in &mut labels {
                    of.push(ModelLabel::missing(name, why.clone()));
                }
            }
        }
    }
    labels
}

/// `model`'s label of `t` from its prediction `s_pred`, or why there is none.
fn model_label(
    live: &LiveExperiment,
    model: &str,
    t: &LabelledTransition,
    s_pred: Vec<f64>,
) -> ModelLabel {
    if let Err(e) = live.domain.validate_observed_state(&s_pred) {
        return ModelLabel::missing(model, format!("its prediction is not a state: {e}"));
    }
    let deviation = live.domain.distance(&s_pred, &t.observed.s_next);
    if deviation.is_finite() {
        ModelLabel::labelled(model, s_pred, deviation)
    } else {
        ModelLabel::missing(
            model,
            "the deviation from its prediction is not a finite number",
        )
    }
}

impl Service {
    /// Validates, labels and stores one executed trajectory atomically (see the module docs).
    /// With `idempotency_key`, a retry of the same request answers the first response and
    /// stores nothing; the same key with another request is a conflict.
    pub async fn ingest(
        &self,
        id: i64,
        request: TrajectoryRequest,
        idempotency_key: Option<&[u8]>,
    ) -> Result<Ingested> {
        let live = self.live(id).await?;
        let idempotency_key = idempotency_key.map(check_idempotency_key).transpose()?;
        let canonical = serde_json::to_string(&request).map_err(anyhow::Error::from)?;
        let TrajectoryRequest {
            proposal_id,
            partial,
            source,
            transitions,
        } = request;
        let source = source.map(check_source).transpose()?;
        let labelled = label(&live, transitions, self.work.limits().max_transitions).await?;
        let labels = label_by_models(&live, &labelled).await;
        // A proposal's content never changes once made: compared outside the ingest
        // transaction, which checks again that the proposal exists.
        let deviating = match proposal_id {
            Some(pid) => self
                .store
                .proposal_plan(id, pid)
                .await?
                .is_some_and(|plan| {
                    let executed = labelled
                        .iter()
                        .map(|t| (t.observed.s.as_slice(), t.observed.a.as_slice()));
                    deviates(&plan, executed)
                }),
            None => false,
        };
        let outcome = self
            .store
            .ingest_trajectory(
                id,
                TrajectoryMeta {
                    proposal_id,
                    partial,
                    deviating,
                    source: source.as_ref(),
                },
                &labelled,
                &labels,
                idempotency_key.map(|key| IdempotencyKey {
                    key,
                    request: &canonical,
                }),
                live.model().version,
            )
            .await?;
        let proposal = || proposal_id.unwrap_or_default();
        let answer = |record: IngestRecord, replayed| Ingested {
            experiment_id: id,
            iteration: live.iteration(record.n_trajectories),
            record,
            replayed,
        };
        match outcome {
            IngestOutcome::Created(record) => {
                tracing::info!(
                    experiment = id,
                    n = labelled.len(),
                    deviating,
                    "trajectory stored"
                );
                if live
                    .model()
                    .kind()
                    .is_some_and(crate::mde::EstimatorKind::updates_online)
                {
                    let absorbing = live.clone();
                    if let Err(e) = Service::blocking(move || absorbing.absorb(&labelled, 1)).await
                    {
                        tracing::error!(experiment = id, error = %e, "online update failed; the trajectory is stored");
                    }
                }
                // A batch just completed: the iteration moved on.
                // The trajectory is committed: what follows must not turn its `201` into an
                // error (a retry without a key would store it twice). A fit request that fails
                // is made again by the next batch, or at the next start (batches left unfitted).
                if live.iteration(record.n_trajectories) > live.iteration(record.n_trajectories - 1)
                {
                    match self.store.request_fit(id, false).await {
                        Ok(()) => self.fits.wake(),
                        Err(e) => tracing::error!(
                            experiment = id,
                            error = %e,
                            "could not request the batch's fit; the trajectory is stored"
                        ),
                    }
                }
                Ok(answer(record, false))
            }
            IngestOutcome::Replayed(record) => Ok(answer(record, true)),
            IngestOutcome::KeyReused { stored_request } => {
                let (field, difference) = describe_difference(&stored_request, &canonical);
                Err(Error::KeyReused { field, difference })
            }
            IngestOutcome::ProposalNotFound => Err(Error::validation(
                "proposal_id",
                format!("no proposal {} in experiment {id}", proposal()),
            )),
            IngestOutcome::ProposalAlreadyExecuted => Err(Error::Conflict(format!(
                "proposal {} was already executed: its trajectory is stored",
                proposal()
            ))),
        }
    }

    /// The experiment's transitions with an id greater than `after`, in id order: at most
    /// `limit` (all when `None`), with the cursor of the next page when there is one.
    pub async fn transitions(
        &self,
        id: i64,
        after: i64,
        limit: Option<i64>,
    ) -> Result<(Vec<StoredTransition>, Option<i64>)> {
        let experiment = self.experiment(id).await?.experiment;
        let mut items = self
            .store
            .transitions(id, after, limit.map(|l| l + 1))
            .await?;
        let next = match limit {
            Some(l) if items.len() as i64 > l => {
                items.truncate(l as usize);
                items.last().map(|t| t.id)
            }
            _ => None,
        };
        let models = experiment.settings.further_model_names();
        attach_labels(&self.store, id, &models, &mut items).await?;
        Ok((items, next))
    }

    /// One stored trajectory with its transitions.
    pub async fn trajectory(&self, id: i64, trajectory_id: i64) -> Result<StoredTrajectory> {
        let experiment = self.experiment(id).await?.experiment;
        let mut trajectory = self
            .store
            .trajectory(id, trajectory_id)
            .await?
            .ok_or_else(|| {
                Error::NotFound(format!("no trajectory {trajectory_id} in experiment {id}"))
            })?;
        let models = experiment.settings.further_model_names();
        attach_labels(&self.store, id, &models, &mut trajectory.transitions).await?;
        Ok(trajectory)
    }
}

/// Fills in the labels of `items` (in id order) by the experiment's further models `models`,
/// each transition's in that order; nothing to do when there are none.
pub(crate) async fn attach_labels(
    store: &crate::store::Store,
    id: i64,
    models: &[String],
    items: &mut [StoredTransition],
) -> Result<()> {
    let (Some(first), Some(last)) = (items.first(), items.last()) else {
        return Ok(());
    };
    if models.is_empty() {
        return Ok(());
    }
    let mut by_transition: std::collections::HashMap<i64, Vec<ModelLabel>> =
        std::collections::HashMap::new();
    for (transition, label) in store.model_labels(id, first.id, last.id).await? {
        by_transition.entry(transition).or_default().push(label);
    }
    let order = |label: &ModelLabel| models.iter().position(|m| *m == label.model);
    for t in items.iter_mut() {
        let mut labels = by_transition.remove(&t.id).unwrap_or_default();
        labels.sort_by_key(order);
        t.labels = Some(labels);
    }
    Ok(())
}

/// Where a request differs from the one stored under its idempotency key: the first field
/// (a path such as `transitions[3].a[1]` or `source.dataset`) whose value differs, and a
/// sentence with both values (shortened).
pub fn describe_difference(stored: &str, sent: &str) -> (String, String) {
    let parse = |t: &str| serde_json::from_str::<serde_json::Value>(t).ok();
    let (Some(stored), Some(sent)) = (parse(stored), parse(sent)) else {
        return (String::new(), "the bodies differ".into());
    };
    match first_difference(&stored, &sent, String::new()) {
        None => (String::new(), "the bodies differ".into()),
        Some((path, a, b)) => {
            let show = |v: &serde_json::Value| {
                let t = v.to_string();
                if t.len() <= 80 {
                    t
                } else {
                    format!("{}…", &t[..t.floor_char_boundary(77)])
                }
            };
            let shown = if path.is_empty() {
                "the body"
            } else {
                path.as_str()
            };
            let sentence = format!("{shown} was {} and is now {}", show(&a), show(&b));
            (path, sentence)
        }
    }
}

/// The first path at which `a` and `b` differ, with the values there.
fn first_difference(
    a: &serde_json::Value,
    b: &serde_json::Value,
    path: String,
) -> Option<(String, serde_json::Value, serde_json::Value)> {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            keys.into_iter().find_map(|k| {
                let at = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                match (x.get(k), y.get(k)) {
                    (Some(u), Some(v)) => first_difference(u, v, at),
                    (u, v) => Some((
                        at,
                        u.cloned().unwrap_or(Value::Null),
                        v.cloned().unwrap_or(Value::Null),
                    )),
                }
            })
        }
        (Value::Array(x), Value::Array(y)) => {
            let common = x
                .iter()
                .zip(y)
                .enumerate()
                .find_map(|(i, (u, v))| first_difference(u, v, format!("{path}[{i}]")));
            common.or_else(|| {
                (x.len() != y.len()).then(|| {
                    (
                        format!("{path} (length)"),
                        Value::from(x.len()),
                        Value::from(y.len()),
                    )
                })
            })
        }
        (u, v) if u == v => None,
        (u, v) => Some((path, u.clone(), v.clone())),
    }
}
