//! A domain declared by the client: any robot's state and action spaces, the components fed to
//! the MDE, a weighted Euclidean distance, a goal test on chosen state components, box
//! obstacles, and the robot's own model `f̂` behind the [`DynamicsModel`] seam (served by the
//! robot over the network, a linear map, or kept on the client).
//!
//! The planner cannot see inside the model, so it steers by sampling: from a node it tries
//! [`CustomParams::steer_samples`] actions (all values of a discrete action space), predicts them
//! in one batch and keeps the allowed one whose prediction is nearest the target (distances in
//! the unit box of the state bounds, so that components in different units compare).
//!
//! State components declared periodic (a heading, a continuous joint) are angles of period
//! `high − low`: the service wraps its model's predictions into the bounds, and distances, the
//! goal test, steering and obstacle checks take the shorter way round; each feeds the MDE as a
//! point on the circle (see [`FeatureMap::UnitBox`]'s `periodic`).

use super::features::periodic_difference;
use super::{
    Awaited, FeatureMap, Space, check_goal_radius, check_magnitudes, euclidean, segment_clear,
    uniform_between,
};
use super::{BoxObstacle, Domain, DomainError, DynamicsError, DynamicsModel, Predicted, Problem};
use rand::RngCore;
use rand::seq::IndexedRandom;
use std::sync::Arc;

/// Largest accepted state or action dimension.
pub const MAX_DIM: usize = 64;
/// Most values of a discrete action space.
pub const MAX_ACTION_VALUES: usize = 256;
/// Most box obstacles.
pub const MAX_OBSTACLES: usize = 1000;
/// Most actions sampled per steering step.
pub const MAX_STEER_SAMPLES: usize = 256;
/// Longest `random`-strategy rollout.
pub const MAX_ROLLOUT_LENGTH: usize = 10_000;

/// Steps of a `random`-strategy rollout when none is declared and no plan was found to measure.
pub const FALLBACK_ROLLOUT_LENGTH: usize = 20;

/// A client-declared domain's parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct CustomParams {
    /// The state space (continuous).
    pub state: Space,
    /// State components that are angles, their period `high − low` (see the module docs).
    pub periodic: Vec<usize>,
    /// The action space: continuous bounds, or discrete `values` (bounds spanning them).
    pub action: Space,
    /// State components fed to the MDE, in order.
    pub feature_state: Vec<usize>,
    /// Action components fed to the MDE, in order.
    pub feature_action: Vec<usize>,
    /// Whether the length of those action components ([`action_length_fraction`]) follows.
    pub action_length: bool,
    /// Components of the model's prediction `ŝ'` fed to the MDE after them, in order.
    pub feature_prediction: Vec<usize>,
    /// Whether the length of the predicted move in the domain's distance, over the state box's
    /// diagonal ([`weighted_move_fraction`](super::features::weighted_move_fraction)), follows
    /// as the last feature.
    pub move_length: bool,
    /// Weights `w_i ≥ 0` (not all 0) of `d = sqrt(Σ w_i (ŝ_i − s_i)²)`, one per state component.
    pub weights: Vec<f64>,
    /// State components the goal test compares.
    pub goal_components: Vec<usize>,
    /// A state is a goal when those components lie within this Euclidean distance of the goal
    /// (one radius), or within `Σ ((s_i − g_i) / r_i)² ≤ 1` (one radius per goal component).
    pub goal_radius: Vec<f64>,
    /// Boxes in the state space that planned edges may not pass through.
    pub obstacles: Vec<BoxObstacle>,
    /// Actions sampled per steering step (continuous action spaces).
    pub steer_samples: usize,
    /// Steps of a `random`-strategy rollout; `None`: as long as a goal-reaching plan for the
    /// same problem (see [`Domain::rollout_like_plans`]), or [`FALLBACK_ROLLOUT_LENGTH`].
    pub rollout_length: Option<usize>,
}

impl CustomParams {
    /// A point in a plane moved by planar actions: both components of the state and of the
    /// action fed to the MDE, the distance unweighted, a goal within 0.05 of both state
    /// components, no obstacles, 8 steering samples.
    pub fn plane(state: Space, action: Space, rollout_length: Option<usize>) -> CustomParams {
        CustomParams {
            state,
            periodic: vec![],
            action,
            feature_state: vec![0, 1],
            feature_action: vec![0, 1],
            action_length: false,
            feature_prediction: vec![],
            move_length: false,
            weights: vec![1.0, 1.0],
            goal_components: vec![0, 1],
            goal_radius: vec![0.05],
            obstacles: vec![],
            steer_samples: 8,
            rollout_length,
        }
    }
}

/// The default tolerance `d_max` of a custom domain, in the units of its distance (clients
/// usually set their own).
pub const DEFAULT_D_MAX: f64 = 0.1;

/// The client-declared domain (see the module docs).
#[derive(Debug, Clone)]
pub struct CustomDomain {
    params: CustomParams,
    model: Arc<dyn DynamicsModel>,
    /// The features as data, built once: [`Domain::features`] evaluates it, the export carries
    /// it (one definition of `φ`).
    features: FeatureMap,
}

fn check_space(space: &Space, what: &str) -> Result<(), DomainError> {
    let n = space.dim();
    if n == 0 || n > MAX_DIM {
        return Err(DomainError::at(
            format!("{what}.names"),
            format!("the dimension must be between 1 and {MAX_DIM}, got {n}"),
        ));
    }
    for (field, v) in [("low", &space.low), ("high", &space.high)] {
        if v.len() != n {
            return Err(DomainError::at(
                format!("{what}.{field}"),
                format!("expected {n} components like names, got {}", v.len()),
            ));
        }
        check_magnitudes(&format!("{what}.{field}"), v)?;
    }
    if let Some(i) = (0..n).find(|&i| space.low[i] > space.high[i]) {
        return Err(DomainError::at(
            format!("{what}.high[{i}]"),
            "must not be below low",
        ));
    }
    if space.values.is_none()
        && let Some(i) = (0..n).find(|&i| space.low[i] == space.high[i])
    {
        return Err(DomainError::at(
            format!("{what}.high[{i}]"),
            "must exceed low (a continuous component needs room)",
        ));
    }
    Ok(())
}

fn check_indices(indices: &[usize], n: usize, field: &str) -> Result<(), DomainError> {
    if let Some((k, i)) = indices.iter().enumerate().find(|(_, i)| **i >= n) {
        return Err(DomainError::at(
            format!("{field}[{k}]"),
            format!("index {i} is out of range (there are {n} components)"),
        ));
    }
    let mut seen = vec![false; n];
    for (k, i) in indices.iter().enumerate() {
        if std::mem::replace(&mut seen[*i], true) {
            return Err(DomainError::at(
                format!("{field}[{k}]"),
                format!("index {i} is listed twice"),
            ));
        }
    }
    Ok(())
}

impl CustomDomain {
    /// Checks the parameters and builds the domain around `model`. Errors name the parameter
    /// (`state.low`, `features.action[1]`, `goal.radius`, `obstacles[2]`, …).
    pub fn new(params: CustomParams, model: Arc<dyn DynamicsModel>) -> Result<Self, DomainError> {
        check_space(&params.state, "state")?;
        check_space(&params.action, "action")?;
        let (n, m) = (params.state.dim(), params.action.dim());
        if params.state.values.is_some() {
            return Err(DomainError::at(
                "state.values",
                "the state space is continuous",
            ));
        }
        if let Some(values) = &params.action.values {
            if values.is_empty() || values.len() > MAX_ACTION_VALUES {
                return Err(DomainError::at(
                    "action.values",
                    format!("must hold 1 to {MAX_ACTION_VALUES} actions"),
                ));
            }
            for (k, v) in values.iter().enumerate() {
                params
                    .action
                    .check(v)
                    .map_err(|e| DomainError::at(format!("action.values[{k}]"), e.reason))?;
            }
        }
        check_indices(&params.periodic, n, "state.periodic")?;
        check_indices(&params.feature_state, n, "features.state")?;
        check_indices(&params.feature_action, m, "features.action")?;
        check_indices(&params.feature_prediction, n, "features.prediction")?;
        if params.feature_state.len()
            + params.feature_action.len()
            + params.feature_prediction.len()
            == 0
            && !params.move_length
        {
            return Err(DomainError::at(
                "features",
                "at least one state, action or prediction component must feed the MDE",
            ));
        }
        // Prediction features with a client-side model are allowed: the client then posts
        // `s_pred` with its queries too (checked there).
        if params.action_length && params.feature_action.is_empty() {
            return Err(DomainError::at(
                "features.action_length",
                "the action's length needs at least one component in features.action",
            ));
        }
        if params.weights.len() != n {
            return Err(DomainError::at(
                "distance.weights",
                format!("expected {n} weights, one per state component"),
            ));
        }
        if let Some(i) = params
            .weights
            .iter()
            .position(|w| !(w.is_finite() && *w >= 0.0))
        {
            return Err(DomainError::at(
                format!("distance.weights[{i}]"),
                "must be a finite number ≥ 0",
            ));
        }
        check_magnitudes("distance.weights", &params.weights)?;
        if params.weights.iter().all(|w| *w == 0.0) {
            return Err(DomainError::at(
                "distance.weights",
                "at least one weight must be positive",
            ));
        }
        if params.goal_components.is_empty() {
            return Err(DomainError::at(
                "goal.components",
                "name at least one state component",
            ));
        }
        check_indices(&params.goal_components, n, "goal.components")?;
        match params.goal_radius.as_slice() {
            [r] => check_goal_radius("goal.radius", *r)?,
            radii if radii.len() == params.goal_components.len() => {
                for (k, r) in radii.iter().enumerate() {
                    check_goal_radius(&format!("goal.radius[{k}]"), *r)?;
                }
            }
            radii => {
                return Err(DomainError::at(
                    "goal.radius",
                    format!(
                        "give one radius, or one per goal component ({}), not {}",
                        params.goal_components.len(),
                        radii.len()
                    ),
                ));
            }
        }
        if params.obstacles.len() > MAX_OBSTACLES {
            return Err(DomainError::at(
                "obstacles",
                format!("at most {MAX_OBSTACLES} obstacles"),
            ));
        }
        for (k, o) in params.obstacles.iter().enumerate() {
            o.check(k, n)?;
        }
        if !(1..=MAX_STEER_SAMPLES).contains(&params.steer_samples) {
            return Err(DomainError::at(
                "steer_samples",
                format!("must be between 1 and {MAX_STEER_SAMPLES}"),
            ));
        }
        if params
            .rollout_length
            .is_some_and(|n| !(1..=MAX_ROLLOUT_LENGTH).contains(&n))
        {
            return Err(DomainError::at(
                "rollout_length",
                format!("must be between 1 and {MAX_ROLLOUT_LENGTH}"),
            ));
        }
        let features = FeatureMap::UnitBox {
            state_low: params.state.low.clone(),
            state_high: params.state.high.clone(),
            action_low: params.action.low.clone(),
            action_high: params.action.high.clone(),
            state_components: params.feature_state.clone(),
            action_components: params.feature_action.clone(),
            action_length: params.action_length,
            prediction_components: params.feature_prediction.clone(),
            weights: if params.move_length {
                params.weights.clone()
            } else {
                Vec::new()
            },
            move_length: params.move_length,
            periodic: params.periodic.clone(),
        };
        let model = wrapping_angles(model, &params.state, &params.periodic);
        Ok(Self {
            params,
            model,
            features,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &CustomParams {
        &self.params
    }

    fn in_collision(&self, p: &[f64]) -> bool {
        let st = &self.params.state;
        self.params.obstacles.iter().any(|o| {
            p.iter()
                .enumerate()
                .zip(o.low.iter().zip(&o.high))
                .all(|((i, x), (lo, hi))| {
                    let x = if self.params.periodic.contains(&i) {
                        wrap(*x, st.low[i], st.high[i])
                    } else {
                        *x
                    };
                    x >= *lo && x <= *hi
                })
        })
    }

    /// `x − y` in component `i`, the shorter way round for a periodic one.
    fn difference(&self, i: usize, x: f64, y: f64) -> f64 {
        if self.params.periodic.contains(&i) {
            let st = &self.params.state;
            periodic_difference(x, y, st.high[i] - st.low[i])
        } else {
            x - y
        }
    }

    /// How far `s` is from `goal` in goal radii: at most 1 inside the goal.
    fn goal_distance(&self, s: &[f64], goal: &[f64]) -> f64 {
        let radii = &self.params.goal_radius;
        self.params
            .goal_components
            .iter()
            .zip(goal)
            .enumerate()
            .map(|(k, (&i, g))| {
                let r = radii.get(k).or(radii.first()).copied().unwrap_or(1.0);
                (self.difference(i, s[i], *g) / r).powi(2)
            })
            .sum::<f64>()
            .sqrt()
    }
}

impl Domain for CustomDomain {
    fn kind(&self) -> &'static str {
        "custom"
    }

    fn state_space(&self) -> &Space {
        &self.params.state
    }

    fn action_space(&self) -> &Space {
        &self.params.action
    }

    fn dynamics(&self) -> &dyn DynamicsModel {
        self.model.as_ref()
    }

    /// `sqrt(Σ w_i (ŝ_i − s_i)²)`, a periodic component's difference the shorter way round.
    fn distance(&self, predicted: &[f64], observed: &[f64]) -> f64 {
        self.params
            .weights
            .iter()
            .zip(predicted.iter().zip(observed))
            .enumerate()
            .map(|(i, (w, (p, o)))| w * self.difference(i, *p, *o).powi(2))
            .sum::<f64>()
            .sqrt()
    }

    fn default_d_max(&self) -> f64 {
        DEFAULT_D_MAX
    }

    fn feature_dim(&self) -> usize {
        self.features.dim()
    }

    fn features(&self, s: &[f64], a: &[f64], s_pred: &[f64]) -> Vec<f64> {
        self.features.features(s, a, s_pred)
    }

    fn features_use_prediction(&self) -> bool {
        self.features.uses_prediction()
    }

    fn feature_map(&self) -> FeatureMap {
        self.features.clone()
    }

    fn feature_names(&self) -> Vec<String> {
        let p = &self.params;
        // An angle feeds two features, its cosine and sine.
        let state_names = |prefix: &str, i: usize| -> Vec<String> {
            let name = &p.state.names[i];
            if p.periodic.contains(&i) {
                vec![format!("{prefix}cos {name}"), format!("{prefix}sin {name}")]
            } else {
                vec![format!("{prefix}{name}")]
            }
        };
        p.feature_state
            .iter()
            .flat_map(|&i| state_names("", i))
            .chain(p.feature_action.iter().map(|&i| p.action.names[i].clone()))
            .chain(p.action_length.then(|| "action_length".to_string()))
            .chain(
                p.feature_prediction
                    .iter()
                    .flat_map(|&i| state_names("predicted ", i)),
            )
            .chain(p.move_length.then(|| "move_length".to_string()))
            .collect()
    }

    fn validate_goal(&self, goal: &[f64]) -> Result<(), DomainError> {
        let comps = &self.params.goal_components;
        if goal.len() != comps.len() {
            return Err(DomainError::new(format!(
                "expected {} components (the goal's state components {comps:?}), got {}",
                comps.len(),
                goal.len()
            )));
        }
        for (g, &i) in goal.iter().zip(comps) {
            let s = &self.params.state;
            if !g.is_finite() {
                return Err(DomainError::new(format!(
                    "component {i} ({}) is not a finite number",
                    s.names[i]
                )));
            }
            if *g < s.low[i] || *g > s.high[i] {
                return Err(DomainError::new(format!(
                    "component {i} ({}) = {g} is outside [{}, {}]",
                    s.names[i], s.low[i], s.high[i]
                )));
            }
        }
        Ok(())
    }

    fn is_goal(&self, s: &[f64], goal: &[f64]) -> bool {
        self.goal_distance(s, goal) <= 1.0
    }

    /// The prediction stays within the state bounds, moves, and its segment from `s` misses
    /// every obstacle.
    fn edge_allowed(&self, s: &[f64], _a: &[f64], s_pred: &[f64]) -> bool {
        let st = &self.params.state;
        if s_pred.len() != s.len() || st.check(s_pred).is_err() {
            return false;
        }
        if euclidean(s, s_pred) < 1e-12 {
            return false;
        }
        if self.params.obstacles.is_empty() {
            return true;
        }
        // The segment the shorter way round an angle (the collision test wraps its points).
        let end: Vec<f64> = (0..s.len())
            .map(|i| s[i] + self.difference(i, s_pred[i], s[i]))
            .collect();
        segment_clear(s, &end, |p| self.in_collision(p))
    }

    fn sample_state(&self, rng: &mut dyn RngCore) -> Vec<f64> {
        let st = &self.params.state;
        (0..st.dim())
            .map(|i| uniform_between(rng, st.low[i], st.high[i]))
            .collect()
    }

    /// A uniform state with the goal's components set to the goal.
    fn goal_target(&self, goal: &[f64], rng: &mut dyn RngCore) -> Vec<f64> {
        let mut s = self.sample_state(rng);
        for (&i, g) in self.params.goal_components.iter().zip(goal) {
            s[i] = *g;
        }
        s
    }

    /// Euclidean distance in the unit box of the state bounds (an angle the shorter way round).
    fn state_metric(&self, a: &[f64], b: &[f64]) -> f64 {
        let st = &self.params.state;
        st.to_unit(a)
            .zip(st.to_unit(b))
            .enumerate()
            .map(|(i, (p, q))| {
                let d = if self.params.periodic.contains(&i) {
                    periodic_difference(p, q, 1.0)
                } else {
                    p - q
                };
                d * d
            })
            .sum::<f64>()
            .sqrt()
    }

    /// Every value of a discrete action space, else `steer_samples` uniform actions.
    fn steer(&self, s: &[f64], _target: &[f64], rng: &mut dyn RngCore) -> Vec<Vec<f64>> {
        match &self.params.action.values {
            Some(values) => values.clone(),
            None => (0..self.params.steer_samples)
                .map(|_| self.sample_action(s, rng))
                .collect(),
        }
    }

    fn sample_action(&self, _s: &[f64], rng: &mut dyn RngCore) -> Vec<f64> {
        let act = &self.params.action;
        match &act.values {
            Some(values) => values.choose(rng).cloned().unwrap_or_default(),
            None => (0..act.dim())
                .map(|i| uniform_between(rng, act.low[i], act.high[i]))
                .collect(),
        }
    }

    fn rollout_length(&self) -> usize {
        self.params
            .rollout_length
            .unwrap_or(FALLBACK_ROLLOUT_LENGTH)
    }

    fn rollout_like_plans(&self) -> bool {
        self.params.rollout_length.is_none()
    }

    /// A uniform start outside the obstacles and a goal (on the goal components) at least twice
    /// the goal radius away from it.
    fn sample_problem(&self, rng: &mut dyn RngCore) -> Problem {
        let free = |rng: &mut dyn RngCore| {
            let mut s = self.sample_state(rng);
            for _ in 0..1000 {
                if !self.in_collision(&s) {
                    break;
                }
                s = self.sample_state(rng);
            }
            s
        };
        let start = free(rng);
        let mut goal_state = free(rng);
        let goal_of =
            |s: &[f64]| -> Vec<f64> { self.params.goal_components.iter().map(|&i| s[i]).collect() };
        for _ in 0..1000 {
            if self.goal_distance(&start, &goal_of(&goal_state)) > 2.0 {
                break;
            }
            goal_state = free(rng);
        }
        Problem::sampled(start, goal_of(&goal_state))
    }
}

/// `x` wrapped into `[low, high)` (period `high − low`); `x` itself when that is not positive.
pub fn wrap(x: f64, low: f64, high: f64) -> f64 {
    let period = high - low;
    if period > 0.0 && x.is_finite() {
        let w = low + (x - low).rem_euclid(period);
        // Rounding can land on `high` itself; `low` is the same angle.
        if w >= high { low } else { w }
    } else {
        x
    }
}

/// `model` with its predictions of the `periodic` components of `state` wrapped into their
/// bounds (a robot's model may answer a heading of 3.2 rad where the state says `[−π, π]`);
/// `model` itself when there are none, or when it is the client's. The caller has checked
/// `periodic` against `state`.
pub fn wrapping_angles(
    model: Arc<dyn DynamicsModel>,
    state: &Space,
    periodic: &[usize],
) -> Arc<dyn DynamicsModel> {
    if periodic.is_empty() || model.client_side() {
        model
    } else {
        Arc::new(Wrapping {
            inner: model,
            angles: periodic
                .iter()
                .map(|&i| (i, state.low[i], state.high[i]))
                .collect(),
        })
    }
}

/// A model whose predictions of the periodic components are wrapped into their bounds.
#[derive(Debug)]
struct Wrapping {
    inner: Arc<dyn DynamicsModel>,
    /// `(component, low, high)` of every angle.
    angles: Vec<(usize, f64, f64)>,
}

impl Wrapping {
    fn wrap_all(&self, mut out: Vec<Predicted>) -> Vec<Predicted> {
        for p in &mut out {
            for &(i, lo, hi) in &self.angles {
                if let Some(x) = p.next.get_mut(i) {
                    *x = wrap(*x, lo, hi);
                }
            }
        }
        out
    }
}

impl DynamicsModel for Wrapping {
    fn predict_batch(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
    ) -> Result<Vec<Predicted>, DynamicsError> {
        self.inner
            .predict_batch(states, actions)
            .map(|p| self.wrap_all(p))
    }

    fn predict_batch_within(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
        budget: &crate::budget::Budget,
    ) -> Result<Vec<Predicted>, DynamicsError> {
        self.inner
            .predict_batch_within(states, actions, budget)
            .map(|p| self.wrap_all(p))
    }

    fn predict_awaitable<'a>(
        &'a self,
        states: &'a [&'a [f64]],
        actions: &'a [&'a [f64]],
    ) -> Option<Awaited<'a>> {
        let inner = self.inner.predict_awaitable(states, actions)?;
        Some(Box::pin(
            async move { inner.await.map(|p| self.wrap_all(p)) },
        ))
    }

    fn client_side(&self) -> bool {
        self.inner.client_side()
    }

    fn round_size(&self) -> usize {
        self.inner.round_size()
    }
}

/// `ŝ' = clip(A s + B a + c)` to the state bounds.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearModel {
    a: Vec<Vec<f64>>,
    b: Vec<Vec<f64>>,
    c: Vec<f64>,
    state: Space,
    /// Components left unclipped (angles, which the domain wraps instead).
    periodic: Vec<usize>,
}

impl LinearModel {
    /// Checks the shapes (`A`: n×n, `B`: n×m, `c`: n) and finiteness against the spaces.
    /// Errors name `A`, `B` or `c` (relative to the model).
    pub fn new(
        a: Vec<Vec<f64>>,
        b: Vec<Vec<f64>>,
        c: Vec<f64>,
        state: &Space,
        action: &Space,
    ) -> Result<Self, DomainError> {
        let (n, m) = (state.dim(), action.dim());
        for (name, mat, cols) in [("A", &a, n), ("B", &b, m)] {
            if mat.len() != n {
                return Err(DomainError::at(
                    name,
                    format!(
                        "expected {n} rows (one per state component), got {}",
                        mat.len()
                    ),
                ));
            }
            for (r, row) in mat.iter().enumerate() {
                if row.len() != cols {
                    return Err(DomainError::at(
                        format!("{name}[{r}]"),
                        format!("expected {cols} columns, got {}", row.len()),
                    ));
                }
                check_magnitudes(&format!("{name}[{r}]"), row)?;
            }
        }
        if c.len() != n {
            return Err(DomainError::at(
                "c",
                format!("expected {n} components, got {}", c.len()),
            ));
        }
        check_magnitudes("c", &c)?;
        Ok(Self {
            a,
            b,
            c,
            state: state.clone(),
            periodic: Vec::new(),
        })
    }

    /// The same model leaving the `periodic` state components unclipped: they are angles,
    /// which the domain wraps instead.
    pub fn with_periodic(mut self, periodic: &[usize]) -> Self {
        self.periodic = periodic.to_vec();
        self
    }

    /// `clip(A s + B a + c)` (a periodic component unclipped).
    pub fn predict(&self, s: &[f64], a: &[f64]) -> Vec<f64> {
        let dot = |row: &[f64], v: &[f64]| row.iter().zip(v).map(|(p, q)| p * q).sum::<f64>();
        let mut next: Vec<f64> = (0..self.c.len())
            .map(|i| dot(&self.a[i], s) + dot(&self.b[i], a) + self.c[i])
            .collect();
        let raw = next.clone();
        self.state.clamp(&mut next);
        for &i in &self.periodic {
            if let (Some(x), Some(r)) = (next.get_mut(i), raw.get(i)) {
                *x = *r;
            }
        }
        next
    }
}

impl DynamicsModel for LinearModel {
    fn predict_batch(
        &self,
        states: &[&[f64]],
        actions: &[&[f64]],
    ) -> Result<Vec<Predicted>, DynamicsError> {
        Ok(super::dynamics::predict_each(states, actions, |s, a| {
            self.predict(s, a)
        }))
    }
}

/// The model of an experiment whose client predicts for itself: the client posts `s_pred`
/// with every transition and plans on its side; the service never calls it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ClientModel;

impl DynamicsModel for ClientModel {
    fn predict_batch(&self, _: &[&[f64]], _: &[&[f64]]) -> Result<Vec<Predicted>, DynamicsError> {
        Err(DynamicsError::ClientSide)
    }

    fn client_side(&self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn space(names: &[&str], low: &[f64], high: &[f64]) -> Space {
        Space {
            names: names.iter().map(|s| s.to_string()).collect(),
            low: low.to_vec(),
            high: high.to_vec(),
            values: None,
        }
    }

    fn params() -> CustomParams {
        CustomParams {
            state: space(&["x", "y", "v"], &[0.0, 0.0, -1.0], &[2.0, 1.0, 1.0]),
            periodic: vec![],
            action: space(&["ax", "ay"], &[-0.1, -0.1], &[0.1, 0.1]),
            feature_state: vec![0, 1],
            feature_action: vec![1],
            action_length: false,
            feature_prediction: vec![],
            move_length: false,
            weights: vec![1.0, 4.0, 0.0],
            goal_components: vec![0, 1],
            goal_radius: vec![0.05],
            obstacles: vec![],
            steer_samples: 8,
            rollout_length: Some(20),
        }
    }

    fn linear(p: &CustomParams) -> LinearModel {
        let eye = |n: usize, m: usize| -> Vec<Vec<f64>> {
            (0..n)
                .map(|i| (0..m).map(|j| f64::from(u8::from(i == j))).collect())
                .collect()
        };
        LinearModel::new(eye(3, 3), eye(3, 2), vec![0.0; 3], &p.state, &p.action).unwrap()
    }

    fn domain() -> CustomDomain {
        let p = params();
        let model = Arc::new(linear(&p));
        CustomDomain::new(p, model).unwrap()
    }

    #[test]
    fn distance_is_weighted_and_features_pick_the_declared_components() {
        let d = domain();
        assert!(
            (d.distance(&[0.0, 0.0, 0.0], &[0.3, 0.1, 5.0]) - (0.09f64 + 0.04).sqrt()).abs()
                < 1e-12
        );
        assert_eq!(
            d.features(&[1.0, 0.5, 0.0], &[0.0, 0.1], &[]),
            vec![0.5, 0.5, 1.0]
        );
        assert_eq!(d.feature_names(), vec!["x", "y", "ay"]);
        let with_length = CustomDomain::new(
            CustomParams {
                feature_action: vec![0, 1],
                action_length: true,
                ..params()
            },
            Arc::new(linear(&params())),
        )
        .unwrap();
        let phi = with_length.features(&[1.0, 0.5, 0.0], &[0.1, -0.05], &[]);
        assert_eq!(phi.len(), with_length.feature_dim());
        assert!((phi[4] - (0.5f64 * (1.0 + 0.25)).sqrt()).abs() < 1e-12);
        assert_eq!(with_length.feature_names()[4], "action_length");
        let refused = CustomDomain::new(
            CustomParams {
                feature_action: vec![],
                action_length: true,
                ..params()
            },
            Arc::new(linear(&params())),
        )
        .unwrap_err();
        assert_eq!(
            refused.path_under("domain"),
            "domain.features.action_length"
        );
        assert!(d.is_goal(&[1.0, 0.5, 0.9], &[1.03, 0.5]));
        assert!(!d.is_goal(&[1.0, 0.5, 0.9], &[1.06, 0.5]));
    }

    #[test]
    fn linear_model_clips_to_the_state_bounds() {
        let p = params();
        let m = linear(&p);
        assert_eq!(
            m.predict(&[1.95, 0.5, 0.0], &[0.1, -0.05]),
            vec![2.0, 0.45, 0.0]
        );
    }

    #[test]
    fn errors_name_the_parameter() {
        let model: Arc<dyn DynamicsModel> = Arc::new(ClientModel);
        type Change = Box<dyn Fn(&mut CustomParams)>;
        let cases: Vec<(Change, &str)> = vec![
            (Box::new(|p| p.state.low[1] = f64::NAN), "state.low[1]"),
            (Box::new(|p| p.state.high[0] = 0.0), "state.high[0]"),
            (
                Box::new(|p| p.action.high.pop().map(|_| ()).unwrap_or(())),
                "action.high",
            ),
            (
                Box::new(|p| p.feature_action = vec![2]),
                "features.action[0]",
            ),
            (
                Box::new(|p| p.feature_state = vec![0, 0]),
                "features.state[1]",
            ),
            (Box::new(|p| p.weights = vec![0.0; 3]), "distance.weights"),
            (Box::new(|p| p.weights[2] = -1.0), "distance.weights[2]"),
            (
                Box::new(|p| p.goal_components = vec![3]),
                "goal.components[0]",
            ),
            (Box::new(|p| p.goal_radius = vec![0.0]), "goal.radius"),
            (
                Box::new(|p| p.goal_radius = vec![0.1, -1.0]),
                "goal.radius[1]",
            ),
            (
                Box::new(|p| p.goal_radius = vec![0.1, 0.1, 0.1]),
                "goal.radius",
            ),
            (
                Box::new(|p| {
                    p.obstacles = vec![BoxObstacle {
                        low: vec![0.0],
                        high: vec![1.0],
                    }]
                }),
                "obstacles[0]",
            ),
        ];
        for (change, field) in cases {
            let mut p = params();
            change(&mut p);
            let e = CustomDomain::new(p, model.clone()).unwrap_err();
            assert_eq!(e.field, field, "{e}");
        }
        let p = params();
        let e = LinearModel::new(
            vec![vec![1.0; 3]; 3],
            vec![vec![1.0; 3]; 3],
            vec![0.0; 3],
            &p.state,
            &p.action,
        )
        .unwrap_err();
        assert_eq!(e.field, "B[0]");
    }

    #[test]
    fn steering_samples_actions_and_problems_keep_their_goal_apart() {
        let d = domain();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let actions = d.steer(&[1.0, 0.5, 0.0], &[0.0, 0.0, 0.0], &mut rng);
        assert_eq!(actions.len(), 8);
        assert!(actions.iter().all(|a| d.validate_action(a).is_ok()));
        for _ in 0..50 {
            let p = d.sample_problem(&mut rng);
            assert!(d.validate_goal(p.goal()).is_ok());
            assert!(!d.is_goal(p.start(), p.goal()));
        }
    }

    #[test]
    fn angles_wrap_into_their_bounds_and_differ_the_short_way() {
        use std::f64::consts::PI;
        assert!((wrap(3.3, -PI, PI) - (3.3 - 2.0 * PI)).abs() < 1e-12);
        assert_eq!(wrap(PI, -PI, PI), -PI);
        assert_eq!(wrap(-PI, -PI, PI), -PI);
        assert!((wrap(-7.0, -PI, PI) - (-7.0 + 2.0 * PI)).abs() < 1e-12);
        assert_eq!(wrap(0.5, 0.0, 0.0), 0.5);
        let d = periodic_difference(3.1, -3.1, 2.0 * PI);
        assert!((d - (6.2 - 2.0 * PI)).abs() < 1e-12, "{d}");
        // A domain with the third component periodic: distance and metric the short way.
        let mut p = params();
        p.periodic = vec![2];
        p.weights = vec![1.0, 4.0, 1.0];
        let dom = CustomDomain::new(p, Arc::new(ClientModel)).unwrap();
        assert!((dom.distance(&[0.0, 0.0, 0.95], &[0.0, 0.0, -0.95]) - 0.1).abs() < 1e-12);
        assert!((dom.state_metric(&[0.0, 0.0, 0.95], &[0.0, 0.0, -0.95]) - 0.05).abs() < 1e-12);
    }

    #[test]
    fn the_client_model_refuses_to_predict() {
        assert_eq!(
            ClientModel.predict_batch(&[&[0.0]], &[&[0.0]]),
            Err(DynamicsError::ClientSide)
        );
        assert!(ClientModel.client_side());
    }
}
