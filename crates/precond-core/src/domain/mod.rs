//! Domains: state and action spaces, the given (inaccurate) dynamics model `f̂`, the distance `d`,
//! the MDE feature map `φ`, the planning constraints, the goal test and the samplers.
//!
//! A [`Domain`] is everything the learner and the planner know about a world. The *true* dynamics of
//! the built-in worlds live in `crate::sim` and are never seen by the planner.
//!
//! Every vector is a plain `&[f64]`: states are `s ∈ R^n`, actions `a ∈ R^m`, goals are
//! domain-specific vectors (a cell for the gridworld, a state for the kinematic domain, a target
//! volume for the water plant).

pub mod custom;
pub mod dynamics;
pub mod features;
mod gridworld;
mod kinematic;
pub mod water_plant;

pub use custom::{ClientModel, CustomDomain, CustomParams, LinearModel};
pub use dynamics::{Awaited, DynamicsError, DynamicsModel, LocalModel, NamedModel, Predicted};
pub use features::{FeatureMap, action_length_fraction, predicted_move_fraction};
pub use gridworld::{Cell, DEFAULT_MAP, GridFeatures, IcyGridworld, MOVES};
pub use kinematic::{BoxObstacle, Kinematic, KinematicFeatures, KinematicParams};
pub use water_plant::WaterPlant;

use rand::RngCore;

/// A box-bounded vector space, with its discrete values when it has them.
#[derive(Debug, Clone, PartialEq)]
pub struct Space {
    /// One name per component, e.g. `["x", "y"]`.
    pub names: Vec<String>,
    /// Lower bound of each component.
    pub low: Vec<f64>,
    /// Upper bound of each component.
    pub high: Vec<f64>,
    /// For discrete spaces, the allowed vectors (e.g. the gridworld's four moves); `None` when
    /// continuous.
    pub values: Option<Vec<Vec<f64>>>,
}

impl Space {
    /// Number of components.
    pub fn dim(&self) -> usize {
        self.names.len()
    }

    /// Checks that `v` has one entry per component; the error names the components.
    pub fn check_dim(&self, v: &[f64]) -> Result<(), DomainError> {
        if v.len() != self.dim() {
            return Err(DomainError::new(format!(
                "expected {} components ({}), got {}",
                self.dim(),
                self.names.join(", "),
                v.len()
            )));
        }
        Ok(())
    }

    /// Checks dimension, finiteness, bounds and (for discrete spaces) membership of `v`.
    ///
    /// The error says which component is wrong and why, for the caller to put behind a field name.
    pub fn check(&self, v: &[f64]) -> Result<(), DomainError> {
        self.check_dim(v)?;
        for (i, x) in v.iter().enumerate() {
            if !x.is_finite() {
                return Err(DomainError::new(format!(
                    "component {i} ({}) is not a finite number",
                    self.names[i]
                )));
            }
            if *x < self.low[i] - BOUND_TOLERANCE || *x > self.high[i] + BOUND_TOLERANCE {
                return Err(DomainError::new(format!(
                    "component {i} ({}) = {x} is outside [{}, {}]",
                    self.names[i], self.low[i], self.high[i]
                )));
            }
        }
        if let Some(values) = &self.values
            && !values
                .iter()
                .any(|val| val.iter().zip(v).all(|(p, q)| (p - q).abs() < 1e-9))
        {
            return Err(DomainError::new(format!(
                "{v:?} is not one of the allowed values {values:?}"
            )));
        }
        Ok(())
    }

    /// Scales `v` into the unit box by the bounds (components with zero width map to 0).
    pub fn to_unit<'a>(&'a self, v: &'a [f64]) -> impl Iterator<Item = f64> + 'a {
        v.iter()
            .zip(self.low.iter().zip(&self.high))
            .map(|(x, (lo, hi))| {
                let w = hi - lo;
                if w > 0.0 { (x - lo) / w } else { 0.0 }
            })
    }

    /// Clamps `v` component-wise into the bounds.
    pub fn clamp(&self, v: &mut [f64]) {
        for (x, (lo, hi)) in v.iter_mut().zip(self.low.iter().zip(&self.high)) {
            *x = x.clamp(*lo, *hi);
        }
    }
}

/// Slack allowed on bounds when validating observed values (sensor rounding).
pub const BOUND_TOLERANCE: f64 = 1e-9;

/// A domain-level validation failure: which part of the checked value is wrong, and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}{}{reason}", field, if field.is_empty() { "" } else { ": " })]
pub struct DomainError {
    /// The part of the checked value the failure is about, as a path relative to it (a
    /// parameter such as `goal_radius` or `obstacles[2]`), or empty when it is the value as a
    /// whole (a state, an action, a goal).
    pub field: String,
    /// What is wrong, in words.
    pub reason: String,
}

impl DomainError {
    /// A failure of the checked value as a whole.
    pub fn new(reason: impl Into<String>) -> Self {
        Self::at("", reason)
    }

    /// A failure of the part `field` of the checked value.
    pub fn at(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// The full path of the failing field when the checked value sits at `prefix` in a request:
    /// `domain` and `goal_radius` give `domain.goal_radius`; `transitions[0].s` and a failure
    /// of the whole state give `transitions[0].s`.
    pub fn path_under(&self, prefix: &str) -> String {
        match (prefix.is_empty(), self.field.is_empty()) {
            (_, true) => prefix.to_string(),
            (true, false) => self.field.clone(),
            (false, false) if self.field.starts_with('[') => format!("{prefix}{}", self.field),
            (false, false) => format!("{prefix}.{}", self.field),
        }
    }
}

/// An executed transition as the robot observed it: the state, the action taken, and the state
/// that followed — and, when the robot's model lives on the client, what that model predicted.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields)]
pub struct Transition {
    /// State before the action.
    pub s: Vec<f64>,
    /// Action executed.
    pub a: Vec<f64>,
    /// State observed after it.
    pub s_next: Vec<f64>,
    /// The client's own prediction `f̂(s, a)`: required when the experiment's model is the
    /// client's, refused otherwise (a label always comes from one model).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub s_pred: Option<Vec<f64>>,
    /// The predictions of the experiment's further models that are the client's own, by
    /// name: each labels this transition for its model; a model left out leaves its label
    /// missing. Refused for a name that is not such a model.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub predictions: Option<std::collections::BTreeMap<String, Vec<f64>>>,
}

/// An executed transition with the model's prediction and its deviation label
/// `d(f̂(s, a), s_next)`: what the MDE learns from.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelledTransition {
    /// What the robot observed.
    pub observed: Transition,
    /// The model's prediction `f̂(s, a)`.
    pub s_pred: Vec<f64>,
    /// `d(f̂(s, a), s_next)`.
    pub deviation: f64,
}

impl Transition {
    /// A transition without a client-side prediction.
    pub fn new(s: Vec<f64>, a: Vec<f64>, s_next: Vec<f64>) -> Self {
        Self {
            s,
            a,
            s_next,
            s_pred: None,
            predictions: None,
        }
    }
}

/// A planning problem: where to start and what counts as arriving, checked against the domain
/// it belongs to — made only by [`Problem::new`], which checks it, or by a domain's own sampler
/// ([`Problem::sampled`]), so a `Problem` in hand is one the planner can take as it is.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    start: Vec<f64>,
    goal: Vec<f64>,
}

impl Problem {
    /// `start → goal` in `domain`: `start` must be a state of it ([`Domain::validate_state`])
    /// and `goal` one of its goals ([`Domain::validate_goal`]). The error's `field` is the
    /// path of the offending value under `start` or `goal` (`start`, `goal[2]`).
    pub fn new(domain: &dyn Domain, start: Vec<f64>, goal: Vec<f64>) -> Result<Self, DomainError> {
        let under = |prefix: &str, e: DomainError| DomainError::at(e.path_under(prefix), e.reason);
        domain
            .validate_state(&start)
            .map_err(|e| under("start", e))?;
        domain.validate_goal(&goal).map_err(|e| under("goal", e))?;
        Ok(Self { start, goal })
    }

    /// A problem a domain's own sampler drew ([`Domain::sample_problem`]); the sampler vouches
    /// that `start` is a state of its domain and `goal` one of its goals.
    pub fn sampled(start: Vec<f64>, goal: Vec<f64>) -> Self {
        Self { start, goal }
    }

    /// The start state.
    pub fn start(&self) -> &[f64] {
        &self.start
    }

    /// The domain-specific goal vector (see [`Domain::validate_goal`]).
    pub fn goal(&self) -> &[f64] {
        &self.goal
    }
}

/// Everything the learner and the planner know about a world.
///
/// Implementations must be cheap to call: the planner calls `features`, `edge_allowed` and
/// `steer` thousands of times per proposal. The model `f̂` is reached through
/// [`Domain::dynamics`], in batches.
pub trait Domain: Send + Sync + std::fmt::Debug {
    /// The `kind` tag of this domain (`"icy_gridworld"`, `"kinematic"`, `"water_plant"`).
    fn kind(&self) -> &'static str;

    /// The state space.
    fn state_space(&self) -> &Space;

    /// The action space.
    fn action_space(&self) -> &Space;

    /// The given, inaccurate dynamics model `ŝ' = f̂(s, a)` (see [`dynamics`]).
    fn dynamics(&self) -> &dyn DynamicsModel;

    /// The distance `d(ŝ', s') ≥ 0` between a predicted and an observed state.
    fn distance(&self, predicted: &[f64], observed: &[f64]) -> f64;

    /// The default tolerance `d_max`.
    fn default_d_max(&self) -> f64;

    /// Dimension of the MDE feature vector `φ(s, a)`.
    fn feature_dim(&self) -> usize;

    /// The MDE feature vector `φ(s, a)`, every component in `[0, 1]` (for states and
    /// predictions within the bounds). `s_pred` is the model's prediction `f̂(s, a)`: read only
    /// by a domain whose features [use it](Self::features_use_prediction) (a custom domain's
    /// `features.prediction`), which cannot compute it itself (its model may live behind the
    /// network); others ignore it, and callers may pass `&[]` to them.
    fn features(&self, s: &[f64], a: &[f64], s_pred: &[f64]) -> Vec<f64>;

    /// Whether [`features`](Self::features) reads the model's prediction: callers without
    /// one at hand must then ask the model ([`DynamicsModel::predict_batch`]).
    fn features_use_prediction(&self) -> bool {
        false
    }

    /// Names of the feature components (for reports and plots).
    fn feature_names(&self) -> Vec<String>;

    /// The feature map as data, for programs that compute `φ(s, a)` themselves (the exported
    /// model): its [`FeatureMap::features`] must equal [`features`](Self::features).
    fn feature_map(&self) -> FeatureMap;

    /// Checks that `s` is a state of this domain.
    fn validate_state(&self, s: &[f64]) -> Result<(), DomainError> {
        self.state_space().check(s)
    }

    /// Checks that an observed next state is acceptable (dimension and finiteness; robots may be
    /// pushed slightly outside the nominal bounds, so bounds are not enforced by default).
    fn validate_observed_state(&self, s: &[f64]) -> Result<(), DomainError> {
        let space = self.state_space();
        space.check_dim(s)?;
        match s.iter().position(|x| !x.is_finite()) {
            Some(i) => Err(DomainError::new(format!(
                "component {i} ({}) is not a finite number",
                space.names[i]
            ))),
            None => Ok(()),
        }
    }

    /// Checks that `a` is an action of this domain.
    fn validate_action(&self, a: &[f64]) -> Result<(), DomainError> {
        self.action_space().check(a)
    }

    /// Checks that `a` may be executed from `s`, beyond each being valid on its own (e.g. the
    /// water plant's "translate or rotate, not both"). Called after [`Domain::validate_state`]
    /// and [`Domain::validate_action`] have passed. Default: no further condition.
    fn validate_step(&self, _s: &[f64], _a: &[f64]) -> Result<(), DomainError> {
        Ok(())
    }

    /// Checks that `goal` is a goal of this domain.
    fn validate_goal(&self, goal: &[f64]) -> Result<(), DomainError>;

    /// The goal test `g(s)`.
    fn is_goal(&self, s: &[f64], goal: &[f64]) -> bool;

    /// The planning constraints on an edge `s --a--> ŝ'` other than the precondition: bounds,
    /// the approximate collision check, the form of the action. An edge that makes no progress
    /// (`ŝ' = s`) is not allowed.
    fn edge_allowed(&self, s: &[f64], a: &[f64], s_pred: &[f64]) -> bool;

    /// A state to grow the tree towards, drawn uniformly over the state space.
    fn sample_state(&self, rng: &mut dyn RngCore) -> Vec<f64>;

    /// A state to grow the tree towards when the planner takes its goal bias.
    fn goal_target(&self, goal: &[f64], rng: &mut dyn RngCore) -> Vec<f64>;

    /// Distance used to find the nearest tree node to a target.
    fn state_metric(&self, a: &[f64], b: &[f64]) -> f64;

    /// Actions from `s` towards `target` (the RRT's steering function): the planner predicts
    /// them all (in one batch with the rest of its round) and keeps the one whose allowed
    /// prediction is nearest `target` by [`Domain::state_metric`]. Worlds that steer
    /// analytically return one action; a domain that cannot see inside its model returns
    /// several samples.
    fn steer(&self, s: &[f64], target: &[f64], rng: &mut dyn RngCore) -> Vec<Vec<f64>>;

    /// A random action from `s`, from the same sampler the planner uses (the `random` strategy).
    fn sample_action(&self, s: &[f64], rng: &mut dyn RngCore) -> Vec<f64>;

    /// Number of steps of a `random`-strategy rollout.
    fn rollout_length(&self) -> usize;

    /// Whether a `random` rollout should instead be as long as a goal-reaching plan for the
    /// same problem: for domains that cannot tell how far one step goes (a model behind the
    /// network), so that `random` executes about as much as the goal-conditioned strategies.
    /// [`rollout_length`](Self::rollout_length) is then the length when no plan is found.
    fn rollout_like_plans(&self) -> bool {
        false
    }

    /// A random planning problem from the domain's distribution of problems.
    fn sample_problem(&self, rng: &mut dyn RngCore) -> Problem;

    /// Every state-action the planner may consider, where there are finitely many (a grid's
    /// cells × its moves, each step the domain allows): what a search over the whole learned
    /// precondition needs. `None` (the default) for a continuous domain.
    fn finite_state_actions(&self) -> Option<Vec<(Vec<f64>, Vec<f64>)>> {
        None
    }
}

/// The model's predictions `f̂(s, a)` of `pairs` when `domain`'s features read them
/// ([`Domain::features_use_prediction`]), else empty vectors (what [`Domain::features`] takes
/// then): for state-actions nobody has predicted yet (a grid, a sample). Blocking: a model
/// behind the network is called here, in batches of at most 4096 points.
pub fn predictions_for_features(
    domain: &dyn Domain,
    pairs: &[(Vec<f64>, Vec<f64>)],
) -> Result<Vec<Vec<f64>>, DynamicsError> {
    predictions_of(domain, domain.dynamics(), pairs)
}

/// [`predictions_for_features`] by `dynamics`, one of the robot's models (the domain's own or
/// a further one): what [`Domain::features`] reads of that model's prediction.
pub fn predictions_of(
    domain: &dyn Domain,
    dynamics: &dyn DynamicsModel,
    pairs: &[(Vec<f64>, Vec<f64>)],
) -> Result<Vec<Vec<f64>>, DynamicsError> {
    if !domain.features_use_prediction() {
        return Ok(vec![Vec::new(); pairs.len()]);
    }
    let mut out = Vec::with_capacity(pairs.len());
    for chunk in pairs.chunks(4096) {
        let states: Vec<&[f64]> = chunk.iter().map(|(s, _)| s.as_slice()).collect();
        let actions: Vec<&[f64]> = chunk.iter().map(|(_, a)| a.as_slice()).collect();
        let predicted = dynamics.predict_batch(&states, &actions)?;
        if predicted.len() != chunk.len() {
            return Err(DynamicsError::Unavailable {
                model: format!("of the {} domain", domain.kind()),
                reason: format!(
                    "answered {} predictions for {} points",
                    predicted.len(),
                    chunk.len()
                ),
            });
        }
        out.extend(predicted.into_iter().map(|p| p.next));
    }
    Ok(out)
}

/// A uniform draw from `[low, high]` that cannot panic: `rand`'s own draw when the width is
/// finite (the common case, so seeded streams stay as they were), else an overflow-free
/// interpolation between the bounds (a width beyond `f64::MAX` would make `rand` panic). Bounds
/// are checked where a domain is built ([`check_magnitudes`]); this keeps a sampler total even
/// for bounds that somehow escaped the check.
pub(crate) fn uniform_between(rng: &mut dyn RngCore, low: f64, high: f64) -> f64 {
    use rand::Rng;
    if low.is_finite() && high.is_finite() && low <= high && (high - low).is_finite() {
        return rng.random_range(low..=high);
    }
    if !(low.is_finite() && high.is_finite() && low <= high) {
        return if low.is_finite() { low } else { 0.0 };
    }
    let u: f64 = rng.random();
    (low * (1.0 - u) + high * u).clamp(low, high)
}

/// Checks that every number of `values` is finite and at most
/// [`MAX_MAGNITUDE`](crate::limits::MAX_MAGNITUDE) in magnitude; the error names
/// `field[i]`.
pub fn check_magnitudes(field: &str, values: &[f64]) -> Result<(), DomainError> {
    use crate::limits::MAX_MAGNITUDE;
    match values
        .iter()
        .position(|x| !(x.is_finite() && x.abs() <= MAX_MAGNITUDE))
    {
        None => Ok(()),
        Some(i) if !values[i].is_finite() => Err(DomainError::at(
            format!("{field}[{i}]"),
            "must be a finite number",
        )),
        Some(i) => Err(DomainError::at(
            format!("{field}[{i}]"),
            format!(
                "must be at most {MAX_MAGNITUDE:e} in magnitude (got {:e}): beyond that the \
                 widths and distances the planner computes overflow",
                values[i]
            ),
        )),
    }
}

/// Checks a goal radius: a positive number at most
/// [`MAX_MAGNITUDE`](crate::limits::MAX_MAGNITUDE); the error names `field`.
pub(crate) fn check_goal_radius(field: &str, radius: f64) -> Result<(), DomainError> {
    use crate::limits::MAX_MAGNITUDE;
    if !(radius.is_finite() && radius > 0.0) {
        return Err(DomainError::at(field, "must be a positive number"));
    }
    if radius > MAX_MAGNITUDE {
        return Err(DomainError::at(
            field,
            format!("must be at most {MAX_MAGNITUDE:e}"),
        ));
    }
    Ok(())
}

/// Euclidean distance between two equally long vectors.
pub fn euclidean(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| (p - q) * (p - q))
        .sum::<f64>()
        .sqrt()
}

/// Points checked along each edge by the approximate collision check.
const COLLISION_SAMPLES: usize = 8;

/// Whether the segment from `s` to `s_next` stays clear of what `in_collision` reports, checked
/// at [`COLLISION_SAMPLES`] evenly spaced points after `s`, `s_next` included (an approximate
/// check, for the domains with box obstacles).
pub(crate) fn segment_clear(
    s: &[f64],
    s_next: &[f64],
    in_collision: impl Fn(&[f64]) -> bool,
) -> bool {
    let mut p = vec![0.0; s.len()];
    (1..=COLLISION_SAMPLES).all(|k| {
        let t = k as f64 / COLLISION_SAMPLES as f64;
        for (i, pi) in p.iter_mut().enumerate() {
            *pi = s[i] + t * (s_next[i] - s[i]);
        }
        !in_collision(&p)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn uniform_draws_never_panic_and_stay_in_their_bounds() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for (low, high) in [
            (0.0, 1.0),
            (-1e308, 1e308),
            (-f64::MAX, f64::MAX),
            (2.0, 2.0),
        ] {
            for _ in 0..100 {
                let x = uniform_between(&mut rng, low, high);
                assert!(
                    x.is_finite() && (low..=high).contains(&x),
                    "{low} {high}: {x}"
                );
            }
        }
        // Bounds no domain accepts still give a finite number rather than a panic.
        for (low, high) in [(2.0, 1.0), (f64::NAN, 1.0), (0.0, f64::INFINITY)] {
            assert!(uniform_between(&mut rng, low, high).is_finite());
        }
        // A finite width draws as `rand` does, so seeded streams are unchanged.
        let mut a = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let mut b = a.clone();
        use rand::Rng;
        assert_eq!(
            uniform_between(&mut a, -3.0, 5.0),
            b.random_range(-3.0..=5.0)
        );
    }

    #[test]
    fn magnitudes_are_bounded_and_named() {
        assert!(check_magnitudes("low", &[0.0, -1e12, 1e12]).is_ok());
        let e = check_magnitudes("low", &[0.0, 1e13]).unwrap_err();
        assert_eq!(e.field, "low[1]");
        assert!(e.reason.contains("1e12"), "{e}");
        let e = check_magnitudes("low", &[f64::NAN]).unwrap_err();
        assert_eq!(
            (e.field.as_str(), e.reason.as_str()),
            ("low[0]", "must be a finite number")
        );
    }
}
