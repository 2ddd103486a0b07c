//! One RRT run inside the model precondition, and the test-time plan built on it.
//!
//! The tree grows from the start. An *extension* samples a target (the domain's goal target with
//! probability `goal_bias`, else a uniform state), finds the nearest node by the domain's state
//! metric, steers an action towards the target, predicts `ŝ' = f̂(s, a)` with the domain's model
//! and keeps the edge only if
//! - the domain's constraints hold (`Domain::edge_allowed`: bounds, collisions, action form,
//!   progress),
//! - `ŝ'` is not already a node (exact equality; it matters for discrete domains, where the
//!   tree would otherwise fill with copies of the same cells), and
//! - `(s, a)` lies in the precondition: `μ + β σ < d_max` at `φ(s, a)`.
//!
//! It stops when a new node satisfies the goal test or after `max_extensions` extensions, or
//! earlier with [`PlanningError::Stopped`] when its [`Budget`] runs out (checked each round).
//!
//! **Batched rounds.** So that the deviation model sees many points at once, extensions are
//! made in rounds: each round proposes up to `extension_batch` edges against the tree as it
//! stood at the start of the round (never more edges than the tree has nodes, so a young tree
//! still grows one edge at a time), asks the model about all of them in one call (through [`ModelCache`],
//! which skips what it already knows), then adds the accepted edges in order. An extension is
//! one examined edge, accepted or not; edges proposed in a round after the one that reached the
//! goal are dropped and not counted. Rounds make the tree grow from a slightly stale tree, so
//! they cost extensions (measured: about twice as many per goal-reaching run at 16 edges per
//! round on the kinematic domain); the default is therefore one edge per round, the classic
//! RRT, and `extension_batch` is a knob to turn when the model's batched predictions are much
//! cheaper per point than single ones.
//!
//! **Prefetching.** In a discrete action space (the gridworld), when the model must be asked
//! about `(s, a)`, it is asked in the same call about the node's other allowed actions too.

use super::budget::Budget;
use super::cache::ModelCache;
use super::{DeviationModel, PlanningError};
use crate::domain::{Domain, DynamicsError, Predicted};
use crate::limits::{MAX_CANDIDATES, MAX_EXTENSIONS};
use rand::{Rng, RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::HashSet;

/// The planner's parameters (experiment settings).
#[derive(Debug, Clone, PartialEq)]
pub struct PlannerSettings {
    /// Budget of one RRT run, in extensions (attempted edges). Default 5000 (paper);
    /// 1 ..= [`MAX_EXTENSIONS`].
    pub max_extensions: usize,
    /// Number of seeded RRT runs per proposal, hence the largest number of candidates.
    /// Default 20; 1 ..= [`MAX_CANDIDATES`].
    pub n_candidates: usize,
    /// Probability that an extension grows towards the goal rather than a uniform state.
    /// Default 0.2 (a common choice: enough pull to reach the goal quickly in open space,
    /// enough spread to get around regions outside the precondition); in `[0, 1]`.
    pub goal_bias: f64,
    /// Largest number of edges proposed per round and sent to the deviation model together
    /// (see the module docs). Default 1, the classic one-edge-at-a-time RRT; 1 ..= 4096.
    pub extension_batch: usize,
    /// Candidate generation gives up (no plan) after this many runs have failed before any run
    /// reached the goal. Default 1: a run that spends its whole budget without reaching the
    /// goal is strong evidence that the goal is not reachable inside the precondition, and the
    /// answer "no plan within `max_extensions`" then costs one run, not `n_candidates`. Runs
    /// that fail after a success only contribute no candidate. 1 ..= `n_candidates`.
    pub max_failed_runs: usize,
    /// `random` strategy: actions sampled per step before the rollout stops early because none
    /// satisfies the constraints and the precondition. Default 20; 1 ..= 10 000.
    pub random_action_tries: usize,
}

impl Default for PlannerSettings {
    fn default() -> Self {
        Self {
            max_extensions: 5000,
            n_candidates: 20,
            goal_bias: 0.2,
            extension_batch: 1,
            max_failed_runs: 1,
            random_action_tries: 20,
        }
    }
}

impl PlannerSettings {
    /// Checks the ranges; the error names the field.
    pub fn check(&self) -> Result<(), PlanningError> {
        let in_range = |field, v: usize, lo: usize, hi: usize| {
            if v < lo || v > hi {
                Err(PlanningError::settings(
                    field,
                    format!("must lie in {lo} ..= {hi}, got {v}"),
                ))
            } else {
                Ok(())
            }
        };
        in_range(
            "max_extensions",
            self.max_extensions,
            1,
            MAX_EXTENSIONS as usize,
        )?;
        in_range(
            "n_candidates",
            self.n_candidates,
            1,
            MAX_CANDIDATES as usize,
        )?;
        in_range("extension_batch", self.extension_batch, 1, 4096)?;
        in_range(
            "max_failed_runs",
            self.max_failed_runs,
            1,
            self.n_candidates.max(1),
        )?;
        in_range("random_action_tries", self.random_action_tries, 1, 10_000)?;
        if !(0.0..=1.0).contains(&self.goal_bias) {
            return Err(PlanningError::settings(
                "goal_bias",
                format!("must lie in [0, 1], got {}", self.goal_bias),
            ));
        }
        Ok(())
    }
}

/// A planned trajectory: predicted states and the actions between them, with the deviation
/// model's answer at each step.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// Predicted states `s_0 = start, s_{t+1} = f̂(s_t, a_t)`; one more than `actions`.
    pub states: Vec<Vec<f64>>,
    /// Actions `a_t`.
    pub actions: Vec<Vec<f64>>,
    /// `μ(φ(s_t, a_t))`, per action.
    pub mu: Vec<f64>,
    /// `σ(φ(s_t, a_t))` (noise included), per action.
    pub sigma: Vec<f64>,
}

impl Trajectory {
    /// Number of actions.
    pub fn len(&self) -> usize {
        self.actions.len()
    }

    /// Whether it has no action (the start already satisfies the goal).
    pub fn is_empty(&self) -> bool {
        self.actions.is_empty()
    }
}

/// What one RRT run produced.
#[derive(Debug, Clone, PartialEq)]
pub struct RrtOutcome {
    /// The path from the start to the first node that satisfied the goal test, if any.
    pub trajectory: Option<Trajectory>,
    /// Extensions (examined edges) spent.
    pub extensions: usize,
    /// Number of nodes in the tree at the end, the start included.
    pub tree_size: usize,
    /// Calls made to the dynamics model (each with a batch of points).
    pub dynamics_calls: usize,
}

/// One RRT run from `start` towards `goal`, keeping only edges with `μ + β σ < d_max`
/// (see the module docs). `rng` drives every random choice.
#[allow(clippy::too_many_arguments)]
pub fn rrt(
    domain: &dyn Domain,
    mde: &dyn DeviationModel,
    start: &[f64],
    goal: &[f64],
    beta: f64,
    d_max: f64,
    settings: &PlannerSettings,
    rng: &mut dyn RngCore,
) -> Result<RrtOutcome, PlanningError> {
    rrt_within(
        domain,
        mde,
        start,
        goal,
        beta,
        d_max,
        settings,
        rng,
        &Budget::unlimited(),
    )
}

/// [`rrt`] that stops with [`PlanningError::Stopped`] once `budget` says so.
#[allow(clippy::too_many_arguments)]
pub fn rrt_within(
    domain: &dyn Domain,
    mde: &dyn DeviationModel,
    start: &[f64],
    goal: &[f64],
    beta: f64,
    d_max: f64,
    settings: &PlannerSettings,
    rng: &mut dyn RngCore,
    budget: &Budget,
) -> Result<RrtOutcome, PlanningError> {
    settings.check()?;
    check_problem(domain, start, Some(goal), beta, d_max)?;
    let mut cache = ModelCache::new(mde, domain.feature_dim());
    grow(
        domain, &mut cache, start, goal, beta, d_max, settings, rng, budget,
    )
}

/// The test-time plan: one RRT run with the (conservative) test `β`, seeded by `seed`.
/// `trajectory` is `None` when no plan was found within `max_extensions`; an `Err` means the
/// inputs or settings were invalid.
#[allow(clippy::too_many_arguments)]
pub fn plan(
    domain: &dyn Domain,
    mde: &dyn DeviationModel,
    start: &[f64],
    goal: &[f64],
    beta: f64,
    d_max: f64,
    settings: &PlannerSettings,
    seed: u64,
) -> Result<RrtOutcome, PlanningError> {
    plan_within(
        domain,
        mde,
        start,
        goal,
        beta,
        d_max,
        settings,
        seed,
        &Budget::unlimited(),
    )
}

/// [`plan`] that stops with [`PlanningError::Stopped`] once `budget` says so.
#[allow(clippy::too_many_arguments)]
pub fn plan_within(
    domain: &dyn Domain,
    mde: &dyn DeviationModel,
    start: &[f64],
    goal: &[f64],
    beta: f64,
    d_max: f64,
    settings: &PlannerSettings,
    seed: u64,
    budget: &Budget,
) -> Result<RrtOutcome, PlanningError> {
    let mut rng = seeded_rng(seed, 0);
    rrt_within(
        domain, mde, start, goal, beta, d_max, settings, &mut rng, budget,
    )
}

/// The random stream `stream` of `seed`: independent streams for the runs of one proposal.
pub(crate) fn seeded_rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// Checks start, goal (when the strategy uses one), β and d_max; errors name the input.
pub(crate) fn check_problem(
    domain: &dyn Domain,
    start: &[f64],
    goal: Option<&[f64]>,
    beta: f64,
    d_max: f64,
) -> Result<(), PlanningError> {
    domain
        .validate_state(start)
        .map_err(|e| PlanningError::input("start", e.to_string()))?;
    if let Some(goal) = goal {
        domain
            .validate_goal(goal)
            .map_err(|e| PlanningError::input("goal", e.to_string()))?;
    }
    if !beta.is_finite() {
        return Err(PlanningError::input("beta", "must be a finite number"));
    }
    if !(d_max.is_finite() && d_max > 0.0) {
        return Err(PlanningError::input("d_max", "must be a positive number"));
    }
    Ok(())
}

/// The tree: node `i` was reached from `parent[i]` by `action[i]` (node 0 is the start).
struct Tree {
    states: Vec<Vec<f64>>,
    parent: Vec<usize>,
    action: Vec<Vec<f64>>,
    mu: Vec<f64>,
    sigma: Vec<f64>,
    known: HashSet<Vec<u64>>,
}

impl Tree {
    fn new(start: &[f64]) -> Self {
        let mut known = HashSet::new();
        known.insert(state_key(start));
        Self {
            states: vec![start.to_vec()],
            parent: vec![0],
            action: vec![Vec::new()],
            mu: vec![0.0],
            sigma: vec![0.0],
            known,
        }
    }

    fn nearest(&self, domain: &dyn Domain, target: &[f64]) -> usize {
        let mut best = (0, f64::INFINITY);
        for (i, s) in self.states.iter().enumerate() {
            let d = domain.state_metric(s, target);
            if d < best.1 {
                best = (i, d);
            }
        }
        best.0
    }

    fn contains(&self, s: &[f64]) -> bool {
        self.known.contains(&state_key(s))
    }

    fn add(&mut self, parent: usize, action: Vec<f64>, state: Vec<f64>, mu: f64, sigma: f64) {
        self.known.insert(state_key(&state));
        self.states.push(state);
        self.parent.push(parent);
        self.action.push(action);
        self.mu.push(mu);
        self.sigma.push(sigma);
    }

    fn path_to(&self, mut node: usize) -> Trajectory {
        let mut nodes = vec![node];
        while node != 0 {
            node = self.parent[node];
            nodes.push(node);
        }
        nodes.reverse();
        let steps = &nodes[1..];
        Trajectory {
            states: nodes.iter().map(|&i| self.states[i].clone()).collect(),
            actions: steps.iter().map(|&i| self.action[i].clone()).collect(),
            mu: steps.iter().map(|&i| self.mu[i]).collect(),
            sigma: steps.iter().map(|&i| self.sigma[i]).collect(),
        }
    }
}

fn state_key(s: &[f64]) -> Vec<u64> {
    s.iter().map(|x| (x + 0.0).to_bits()).collect()
}

/// A dynamics model must answer one prediction per point, each a state.
pub(crate) fn check_predictions(
    domain: &dyn Domain,
    got: usize,
    expected: usize,
) -> Result<(), PlanningError> {
    if got != expected {
        return Err(PlanningError::Dynamics(DynamicsError::Unavailable {
            model: format!("of the {} domain", domain.kind()),
            reason: format!("answered {got} predictions for {expected} points"),
        }));
    }
    Ok(())
}

/// An edge proposed in a round.
struct Proposed {
    parent: usize,
    action: Vec<f64>,
    next: Vec<f64>,
    /// Whether it passed the domain's constraints and was new, so the model was asked.
    asked: bool,
}

/// A node and the actions the domain steers with from it towards a target.
struct Steered {
    parent: usize,
    target: Vec<f64>,
    actions: Vec<Vec<f64>>,
}

/// The most edges proposed in one round, whatever the model asks for.
const MAX_ROUND: usize = 4096;

/// The RRT proper, with a cache that may be shared by the runs of one proposal.
/// Inputs are assumed checked.
#[allow(clippy::too_many_arguments)]
pub(crate) fn grow(
    domain: &dyn Domain,
    cache: &mut ModelCache<'_>,
    start: &[f64],
    goal: &[f64],
    beta: f64,
    d_max: f64,
    settings: &PlannerSettings,
    rng: &mut dyn RngCore,
    budget: &Budget,
) -> Result<RrtOutcome, PlanningError> {
    let mut tree = Tree::new(start);
    let mut outcome = RrtOutcome {
        trajectory: None,
        extensions: 0,
        tree_size: 1,
        dynamics_calls: 0,
    };
    if domain.is_goal(start, goal) {
        outcome.trajectory = Some(tree.path_to(0));
        return Ok(outcome);
    }
    let dynamics = domain.dynamics();
    let round_size = settings
        .extension_batch
        .max(dynamics.round_size())
        .min(MAX_ROUND);
    let mut round: Vec<Proposed> = Vec::with_capacity(round_size);
    let mut features: Vec<f64> = Vec::new();
    let mut prefetch: Vec<f64> = Vec::new();
    let discrete_actions = domain.action_space().values.as_ref();
    while outcome.extensions < settings.max_extensions {
        if let Some(reason) = budget.stop() {
            return Err(PlanningError::Stopped {
                reason,
                extensions: outcome.extensions,
            });
        }
        let size = round_size
            .min(tree.states.len())
            .min(settings.max_extensions - outcome.extensions);
        round.clear();
        features.clear();
        prefetch.clear();
        let mut steered: Vec<Steered> = Vec::with_capacity(size);
        for _ in 0..size {
            let target = if rng.random::<f64>() < settings.goal_bias {
                domain.goal_target(goal, rng)
            } else {
                domain.sample_state(rng)
            };
            let parent = tree.nearest(domain, &target);
            let actions = domain.steer(&tree.states[parent], &target, rng);
            steered.push(Steered {
                parent,
                target,
                actions,
            });
        }
        // One call predicts every action of every edge of the round.
        let pairs: Vec<(usize, &[f64])> = steered
            .iter()
            .flat_map(|e| e.actions.iter().map(|a| (e.parent, a.as_slice())))
            .collect();
        let mut predicted =
            predict(domain, &tree, &pairs, &mut outcome.dynamics_calls)?.into_iter();
        let mut to_prefetch: Vec<(usize, &[f64])> = Vec::new();
        for edge in &steered {
            let s = &tree.states[edge.parent];
            // The allowed, new prediction nearest the target.
            let mut best: Option<(f64, usize, Vec<f64>)> = None;
            for (j, action) in edge.actions.iter().enumerate() {
                let Some(p) = predicted.next() else { break };
                if !(p.valid && domain.edge_allowed(s, action, &p.next) && !tree.contains(&p.next))
                {
                    continue;
                }
                let d = if edge.actions.len() == 1 {
                    0.0
                } else {
                    domain.state_metric(&p.next, &edge.target)
                };
                if best.as_ref().is_none_or(|(b, _, _)| d < *b) {
                    best = Some((d, j, p.next));
                }
            }
            let Some((_, j, next)) = best else {
                round.push(Proposed {
                    parent: edge.parent,
                    action: Vec::new(),
                    next: Vec::new(),
                    asked: false,
                });
                continue;
            };
            let action = &edge.actions[j];
            let phi = domain.features(s, action);
            if edge.actions.len() == 1
                && let Some(values) = discrete_actions.filter(|_| !cache.contains(&phi))
            {
                // A miss in a discrete action space: ask about the node's other moves in the
                // same call, since the tree is likely to try them later.
                to_prefetch.extend(
                    values
                        .iter()
                        .filter(|v| *v != action)
                        .map(|v| (edge.parent, v.as_slice())),
                );
            }
            features.extend(phi);
            round.push(Proposed {
                parent: edge.parent,
                action: action.clone(),
                next,
                asked: true,
            });
        }
        if !to_prefetch.is_empty() {
            let next = predict(domain, &tree, &to_prefetch, &mut outcome.dynamics_calls)?;
            for ((i, v), n) in to_prefetch.iter().zip(next) {
                let s = &tree.states[*i];
                if n.valid && domain.edge_allowed(s, v, &n.next) && !tree.contains(&n.next) {
                    prefetch.extend(domain.features(s, v));
                }
            }
        }
        // The answers to the prefetched rows come after those of the edges; they are cached.
        features.append(&mut prefetch);
        let answers = cache.predict(&features)?;
        let mut answers = answers.into_iter();
        for edge in round.drain(..) {
            outcome.extensions += 1;
            if !edge.asked {
                continue;
            }
            let Some((mu, sigma)) = answers.next() else {
                break;
            };
            // Written so that a NaN from the model keeps the edge out.
            let inside = mu + beta * sigma < d_max;
            if !inside || tree.contains(&edge.next) {
                continue;
            }
            let reached = domain.is_goal(&edge.next, goal);
            tree.add(edge.parent, edge.action, edge.next, mu, sigma);
            if reached {
                let node = tree.states.len() - 1;
                outcome.trajectory = Some(tree.path_to(node));
                outcome.tree_size = tree.states.len();
                return Ok(outcome);
            }
        }
    }
    outcome.tree_size = tree.states.len();
    Ok(outcome)
}

/// Predicts `f̂(node, action)` for every pair in one call to the domain's dynamics model,
/// counting the call.
fn predict(
    domain: &dyn Domain,
    tree: &Tree,
    pairs: &[(usize, &[f64])],
    calls: &mut usize,
) -> Result<Vec<Predicted>, PlanningError> {
    let states: Vec<&[f64]> = pairs
        .iter()
        .map(|(i, _)| tree.states[*i].as_slice())
        .collect();
    let actions: Vec<&[f64]> = pairs.iter().map(|(_, a)| *a).collect();
    predict_pairs(domain, &states, &actions, calls)
}

/// Predicts `f̂(states[i], actions[i])` in one call, counting it and checking that the model
/// answered one prediction per pair.
pub(crate) fn predict_pairs(
    domain: &dyn Domain,
    states: &[&[f64]],
    actions: &[&[f64]],
    calls: &mut usize,
) -> Result<Vec<Predicted>, PlanningError> {
    if states.is_empty() {
        return Ok(Vec::new());
    }
    *calls += 1;
    let predicted = domain.dynamics().predict_batch(states, actions)?;
    check_predictions(domain, predicted.len(), states.len())?;
    Ok(predicted)
}
