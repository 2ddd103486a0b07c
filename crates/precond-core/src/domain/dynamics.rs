//! The dynamics-model seam: the given model `ŝ' = f̂(s, a)` as the planner and the labeller
//! reach it — batched and fallible, so that a model served by a robot's own process (over the
//! network) plugs in beside the built-in worlds' analytical ones without touching the planner.
//!
//! - [`DynamicsModel`] is what every caller uses: one call predicts many `(s, a)` pairs and may
//!   fail with a [`DynamicsError`] that names the model.
//! - [`LocalModel`] is how the built-in worlds provide theirs: an in-process, cheap, infallible
//!   `predict` per point; every [`LocalModel`] is a [`DynamicsModel`].
//!
//! The pattern is the deviation model's (`planning::DeviationModel` with its cache): callers ask
//! for many points at once, the model decides how to answer them.

use super::Domain;
use std::fmt;
use std::future::Future;
use std::pin::Pin;

/// What [`DynamicsModel::predict_awaitable`] answers: the predictions, once awaited.
pub type Awaited<'a> =
    Pin<Box<dyn Future<Output = Result<Vec<Predicted>, DynamicsError>> + Send + 'a>>;

/// One prediction of the dynamics model.
#[derive(Debug, Clone, PartialEq)]
pub struct Predicted {
    /// The predicted next state `ŝ' = f̂(s, a)`.
    pub next: Vec<f64>,
    /// The model's own verdict on the step (a robot's collision or joint-limit check); `true`
    /// when the model has none. An invalid step is never planned.
    pub valid: bool,
}

impl Predicted {
    /// A valid prediction.
    pub fn valid(next: Vec<f64>) -> Self {
        Self { next, valid: true }
    }
}

/// Why the dynamics model could not answer. Each variant names the model (e.g. its URL).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DynamicsError {
    /// The model did not answer in time.
    #[error("the dynamics model {model} did not answer within {timeout_ms} ms")]
    Timeout {
        /// Which model (e.g. its URL).
        model: String,
        /// The time limit.
        timeout_ms: u64,
    },
    /// The model could not be reached, failed, or answered something unusable.
    #[error("the dynamics model {model} is unavailable: {reason}")]
    Unavailable {
        /// Which model (e.g. its URL).
        model: String,
        /// What went wrong.
        reason: String,
    },
    /// No call could start with a tenth of its time left: the operator's limit of concurrent
    /// calls to this model (or to all models) is reached. Nothing was sent.
    #[error("the dynamics model {model} is busy: {reason}")]
    Busy {
        /// Which model (e.g. its URL).
        model: String,
        /// Which limit, in words.
        reason: String,
    },
    /// The server no longer allows calling this model (its URL is not under a prefix the
    /// operator allows now, e.g. after `--allow-model-url` changed). Nothing was sent.
    #[error("the dynamics model {model} may not be called on this server: {reason}")]
    NotAllowed {
        /// Which model (its URL as stored).
        model: String,
        /// Why not.
        reason: String,
    },
    /// The model lives on the client, which posts its own predictions and plans itself; the
    /// service has nothing to call.
    #[error("the dynamics model is the client's own: the client posts its predictions")]
    ClientSide,
}

/// The given, inaccurate dynamics model `ŝ' = f̂(s, a)`, batched and fallible.
pub trait DynamicsModel: Send + Sync + fmt::Debug {
    /// Predicts the next state of every pair `(states[i], actions[i])`, in order: exactly one
    /// [`Predicted`] per pair, each with the state's dimension, or an error for the whole batch.
    ///
    /// `states` and `actions` are equally long; callers have validated every vector against the
    /// domain's spaces.
    fn predict_batch(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
    ) -> Result<Vec<Predicted>, DynamicsError>;

    /// [`DynamicsModel::predict_batch`] during a search with `budget`: a model whose calls take
    /// time (one behind the network) ends each call by the budget's deadline and stops waiting
    /// for it once the budget says stop; in-process models answer at once and ignore it.
    fn predict_batch_within(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
        budget: &crate::budget::Budget,
    ) -> Result<Vec<Predicted>, DynamicsError> {
        let _ = budget;
        self.predict_batch(states, actions)
    }

    /// [`DynamicsModel::predict_batch`] as a future, for callers that can wait for the model
    /// without holding a thread (an ingest): a model behind the network answers one (the
    /// remote model waits for its permits and its answer as a task); in-process models answer
    /// `None`, and the caller runs `predict_batch` on a blocking thread.
    fn predict_awaitable<'a>(
        &'a self,
        states: &'a [&'a [f64]],
        actions: &'a [&'a [f64]],
    ) -> Option<Awaited<'a>> {
        let _ = (states, actions);
        None
    }

    /// Whether the model lives on the client, which posts its own predictions (`s_pred`) and
    /// plans itself: the service never calls it.
    fn client_side(&self) -> bool {
        false
    }

    /// How many RRT edges the planner should propose per round, each round's predictions
    /// going to the model in one call. In-process models answer one point as cheaply as many
    /// (1, the classic RRT); a model behind the network answers a large batch at nearly the cost
    /// of one call.
    fn round_size(&self) -> usize {
        1
    }

    /// Predicts one pair (a batch of one).
    fn predict_one(&self, s: &[f64], a: &[f64]) -> Result<Predicted, DynamicsError> {
        self.predict_batch(&[s], &[a])?
            .pop()
            .ok_or_else(|| DynamicsError::Unavailable {
                model: format!("{self:?}"),
                reason: "answered no prediction for one point".into(),
            })
    }
}

/// One of an experiment's further models of its robot (beside the domain's own): its name,
/// what one call costs in calls of the domain's model, and the model.
#[derive(Debug, Clone)]
pub struct NamedModel {
    /// The model's name, unique in its experiment.
    pub name: String,
    /// Cost of one call, in calls of the domain's own model.
    pub cost: f64,
    /// The model.
    pub model: std::sync::Arc<dyn DynamicsModel>,
}

/// A domain whose model runs in-process, cheaply and without failing: the built-in worlds.
///
/// Implementing it makes the domain a [`DynamicsModel`] (one point at a time); its
/// [`Domain::dynamics`] is then simply `self`.
pub trait LocalModel: Domain {
    /// `ŝ' = f̂(s, a)`.
    fn predict(&self, s: &[f64], a: &[f64]) -> Vec<f64>;

    /// The deviation label `d(f̂(s, a), s')` of an executed transition.
    fn deviation(&self, s: &[f64], a: &[f64], s_next: &[f64]) -> f64 {
        self.distance(&self.predict(s, a), s_next)
    }
}

impl<T: LocalModel> DynamicsModel for T {
    fn predict_batch(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
    ) -> Result<Vec<Predicted>, DynamicsError> {
        Ok(predict_each(states, actions, |s, a| self.predict(s, a)))
    }
}

/// A batch predicted one pair at a time by an in-process model that cannot fail and has no
/// constraint check of its own (every prediction valid).
pub fn predict_each(
    states: &[&[f64]],
    actions: &[&[f64]],
    predict: impl Fn(&[f64], &[f64]) -> Vec<f64>,
) -> Vec<Predicted> {
    states
        .iter()
        .zip(actions)
        .map(|(s, a)| Predicted::valid(predict(s, a)))
        .collect()
}
