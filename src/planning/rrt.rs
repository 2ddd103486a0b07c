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
//! - `(s, a)` lies in the [`Precondition`] at `φ(s, a)`.
//!
//! It stops when a new node satisfies the goal test or after `max_extensions` extensions, or
//! earlier with [`PlanningError::Stopped`] when the planner's [`Budget`] runs out (checked each round).
//!
//! **Batched rounds.** So that the deviation model sees many points at once, extensions are
//! made in rounds: each round proposes up to `extension_batch` edges (or the dynamics model's
//! round size, 64 for a model behind the network) against the tree as it stood at the start of
//! the round, asks the models about all of them in one call each (the deviation model through
//! [`ModelCache`], which skips what it already knows), then adds the accepted edges in order.
//! A round never proposes more edges than the tree has nodes after a round that grew it, so a
//! young tree still grows one edge at a time; after a round that added nothing the allowance
//! doubles, so a tree that cannot grow does not make one model call per extension. An
//! extension is one examined edge, accepted or not; edges proposed in a round after the one
//! that reached the goal are dropped and not counted. Rounds make the tree grow from a slightly
//! stale tree, so they cost extensions (measured: about twice as many per goal-reaching run at
//! 16 edges per round on the kinematic domain); for in-process models the default is therefore
//! one edge per round, the classic RRT, and `extension_batch` is a knob to turn when the
//! model's batched predictions are much cheaper per point than single ones.
//!
//! **Runs in lockstep.** `grow_together` advances several runs of one problem round by round,
//! one call to each model serving a round of every run. Each run grows exactly the tree it
//! would grow alone, so this changes the number of model calls (and the size of the batches
//! the GP sees), never the outcome.
//!
//! **Prefetching.** In a discrete action space (the gridworld), when the model must be asked
//! about `(s, a)`, it is asked in the same call about the node's other allowed actions too.

use super::cache::ModelCache;
use super::error::PlanningError;
use super::precondition::Precondition;
pub use super::settings::PlannerSettings;
use super::settings::PlanningSettings;
pub use super::trajectory::Trajectory;
use crate::budget::Budget;
use crate::domain::{Domain, DynamicsError, Predicted, Problem};
use rand::{Rng, RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::HashSet;

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
    /// Why the extensions that added no node failed.
    pub rejections: Rejections,
}

/// Why extensions added no node to a tree.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Rejections {
    /// No steered action was allowed by the domain (bounds, collisions, action form, no
    /// progress) and new to the tree: reachability.
    pub constraints: usize,
    /// Some were, but none lay inside the precondition.
    pub precondition: usize,
}

/// The random stream `stream` of `seed`: independent streams for the runs of one proposal.
pub(crate) fn seeded_rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
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

/// An edge proposed in a round: the steered actions the domain allows from its node whose
/// predictions are new to the tree, nearest the target first, with those predictions. The
/// model is asked about each; the first inside the precondition becomes the edge.
struct Proposed {
    parent: usize,
    candidates: Vec<(Vec<f64>, Vec<f64>)>,
}

/// A node and the actions the domain steers with from it towards a target.
struct Steered {
    parent: usize,
    target: Vec<f64>,
    actions: Vec<Vec<f64>>,
}

/// The most edges proposed in one round, whatever the model asks for.
const MAX_ROUND: usize = 4096;

/// What every search of one proposal shares: the domain, the checked problem, the
/// precondition and the checked settings. A [`Planner`](super::Planner) hands it to the
/// searches and the strategies (`Planner::task`); they never see the planner itself.
#[derive(Clone, Copy)]
pub(crate) struct Task<'a> {
    pub domain: &'a dyn Domain,
    pub problem: &'a Problem,
    pub precondition: Precondition,
    pub settings: &'a PlanningSettings,
}

/// One RRT search in progress: its tree, its own random stream, what it has spent, and the
/// scratch of the round it is in. A round has four steps, so that several searches can share
/// each step's call to a model ([`grow_together`]): [`steer`](Self::steer) (the pairs to
/// predict with `f̂`), [`choose`](Self::choose) (the edges and the pairs to prefetch),
/// [`prefetched`](Self::prefetched) (the features to ask the deviation model about) and
/// [`accept`](Self::accept).
struct Search<'a, R> {
    task: Task<'a>,
    rng: R,
    tree: Tree,
    outcome: RrtOutcome,
    /// Whether the search has ended: it reached the goal or spent its extensions.
    done: bool,
    /// Edges the next round may propose at most (before the model's round size): the tree's
    /// size after a round that grew it, doubled after a round that did not. A young tree thus
    /// grows one edge at a time (edges are proposed against the tree as it stood at the start
    /// of the round), while a tree that cannot grow does not make one model call per edge.
    allowance: usize,
    steered: Vec<Steered>,
    round: Vec<Proposed>,
    /// `(node, index into the discrete action values)` to predict after the edges.
    to_prefetch: Vec<(usize, usize)>,
    /// Feature rows of the asked edges, then of the allowed prefetched pairs.
    features: Vec<f64>,
}

impl<'a, R: RngCore> Search<'a, R> {
    fn new(task: Task<'a>, rng: R) -> Self {
        let tree = Tree::new(task.problem.start());
        let done = task
            .domain
            .is_goal(task.problem.start(), task.problem.goal());
        let outcome = RrtOutcome {
            trajectory: done.then(|| tree.path_to(0)),
            extensions: 0,
            tree_size: 1,
            dynamics_calls: 0,
            rejections: Rejections::default(),
        };
        Self {
            task,
            rng,
            tree,
            outcome,
            done,
            allowance: 1,
            steered: Vec::new(),
            round: Vec::new(),
            to_prefetch: Vec::new(),
            features: Vec::new(),
        }
    }

    /// Samples this round's targets, their nearest nodes and the actions to steer with.
    fn steer(&mut self) {
        let Task {
            domain,
            problem,
            settings,
            ..
        } = self.task;
        let settings = settings.planner();
        let goal = problem.goal();
        let round_size = settings
            .extension_batch
            .max(domain.dynamics().round_size())
            .min(MAX_ROUND);
        let size = round_size
            .min(self.allowance)
            .min(settings.max_extensions - self.outcome.extensions);
        self.steered.clear();
        for _ in 0..size {
            let target = if self.rng.random::<f64>() < settings.goal_bias {
                domain.goal_target(goal, &mut self.rng)
            } else {
                domain.sample_state(&mut self.rng)
            };
            let parent = self.tree.nearest(domain, &target);
            let actions = domain.steer(&self.tree.states[parent], &target, &mut self.rng);
            self.steered.push(Steered {
                parent,
                target,
                actions,
            });
        }
    }

    /// The `(state, action)` pairs this round needs predicted, in order.
    fn pairs(&self) -> impl Iterator<Item = (&[f64], &[f64])> {
        self.steered.iter().flat_map(|e| {
            let s = self.tree.states[e.parent].as_slice();
            e.actions.iter().map(move |a| (s, a.as_slice()))
        })
    }

    fn pair_count(&self) -> usize {
        self.steered.iter().map(|e| e.actions.len()).sum()
    }

    /// Keeps, for each steered edge, the allowed and new prediction nearest its target, and
    /// notes the pairs to prefetch. `predicted` answers [`pairs`](Self::pairs) in order.
    fn choose(&mut self, predicted: Vec<Predicted>, cache: &ModelCache<'_>) {
        let domain = self.task.domain;
        let discrete_actions = domain.action_space().values.as_ref();
        let mut predicted = predicted.into_iter();
        self.round.clear();
        self.to_prefetch.clear();
        self.features.clear();
        for edge in &self.steered {
            let s = &self.tree.states[edge.parent];
            let mut allowed: Vec<(f64, usize, Vec<f64>)> = Vec::new();
            for (j, action) in edge.actions.iter().enumerate() {
                let Some(p) = predicted.next() else { break };
                if !(p.valid
                    && domain.edge_allowed(s, action, &p.next)
                    && !self.tree.contains(&p.next))
                {
                    continue;
                }
                let d = if edge.actions.len() == 1 {
                    0.0
                } else {
                    domain.state_metric(&p.next, &edge.target)
                };
                allowed.push((d, j, p.next));
            }
            // Nearest the target first; the first steered on ties.
            allowed.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            if edge.actions.len() == 1
                && let Some((_, j, next)) = allowed.first()
            {
                let action = &edge.actions[*j];
                let phi = domain.features(s, action, next);
                if let Some(values) = discrete_actions.filter(|_| !cache.contains(&phi)) {
                    // A miss in a discrete action space: ask about the node's other moves in
                    // the same call, since the tree is likely to try them later.
                    self.to_prefetch.extend(
                        values
                            .iter()
                            .enumerate()
                            .filter(|(_, v)| *v != action)
                            .map(|(k, _)| (edge.parent, k)),
                    );
                }
            }
            let candidates: Vec<(Vec<f64>, Vec<f64>)> = allowed
                .into_iter()
                .map(|(_, j, next)| (edge.actions[j].clone(), next))
                .collect();
            for (action, next) in &candidates {
                self.features.extend(domain.features(s, action, next));
            }
            self.round.push(Proposed {
                parent: edge.parent,
                candidates,
            });
        }
    }

    /// The pairs to prefetch, in order.
    fn prefetch_pairs(&self) -> impl Iterator<Item = (&[f64], &[f64])> {
        let values = self.task.domain.action_space().values.as_deref();
        self.to_prefetch.iter().filter_map(move |&(i, k)| {
            Some((self.tree.states[i].as_slice(), values?[k].as_slice()))
        })
    }

    /// Adds the feature rows of the prefetched pairs the tree could take; `predicted` answers
    /// [`prefetch_pairs`](Self::prefetch_pairs) in order. Their answers are only cached.
    fn prefetched(&mut self, predicted: Vec<Predicted>) {
        let domain = self.task.domain;
        let Some(values) = domain.action_space().values.as_ref() else {
            return;
        };
        for (&(i, k), n) in self.to_prefetch.iter().zip(predicted) {
            let s = &self.tree.states[i];
            let v = &values[k];
            if n.valid && domain.edge_allowed(s, v, &n.next) && !self.tree.contains(&n.next) {
                self.features.extend(domain.features(s, v, &n.next));
            }
        }
    }

    /// Adds the accepted edges in order; `answers` are the deviation model's `(μ, σ)` for
    /// [`features`](Self::features), row by row.
    fn accept(&mut self, answers: &[(f64, f64)]) {
        let Task {
            domain,
            problem,
            precondition,
            settings,
        } = self.task;
        let max_extensions = settings.planner().max_extensions;
        let goal = problem.goal();
        let before = self.tree.states.len();
        let mut answers = answers.iter();
        for edge in self.round.drain(..) {
            self.outcome.extensions += 1;
            if edge.candidates.is_empty() {
                self.outcome.rejections.constraints += 1;
                continue;
            }
            let judged: Vec<(f64, f64)> = answers
                .by_ref()
                .take(edge.candidates.len())
                .copied()
                .collect();
            let any_inside = judged
                .iter()
                .any(|(mu, sigma)| precondition.inside(*mu, *sigma));
            let chosen =
                edge.candidates
                    .into_iter()
                    .zip(judged)
                    .find(|((_, next), (mu, sigma))| {
                        precondition.inside(*mu, *sigma) && !self.tree.contains(next)
                    });
            let Some(((action, next), (mu, sigma))) = chosen else {
                if any_inside {
                    // Inside, but an earlier edge of this round reached the same state.
                    self.outcome.rejections.constraints += 1;
                } else {
                    self.outcome.rejections.precondition += 1;
                }
                continue;
            };
            let reached = domain.is_goal(&next, goal);
            self.tree.add(edge.parent, action, next, mu, sigma);
            if reached {
                let node = self.tree.states.len() - 1;
                self.outcome.trajectory = Some(self.tree.path_to(node));
                self.done = true;
                break;
            }
        }
        self.allowance = if self.tree.states.len() > before {
            self.tree.states.len()
        } else {
            self.allowance.saturating_mul(2)
        };
        self.outcome.tree_size = self.tree.states.len();
        if self.outcome.extensions >= max_extensions {
            self.done = true;
        }
    }
}

/// One RRT run with a cache that may be shared by the runs of one proposal.
/// Inputs are assumed checked.
pub(crate) fn grow(
    task: Task<'_>,
    cache: &mut ModelCache<'_>,
    rng: &mut dyn RngCore,
    budget: &Budget,
) -> Result<RrtOutcome, PlanningError> {
    let mut outcomes = grow_together(task, cache, vec![rng], budget)?;
    Ok(outcomes.pop().expect("one search, one outcome"))
}

/// Several RRT runs of the same problem in lockstep, run `i` drawing from `rngs[i]`: each
/// round, one call to `f̂` predicts the pairs of every run still searching, and one call to the
/// deviation model (through `cache`) answers all their edges. Each run grows exactly the tree
/// it would grow alone (its choices depend only on its own stream and on the models' answers),
/// so running them together changes the number of model calls, not the outcomes. Every
/// outcome's `dynamics_calls` is the number of calls shared by the group.
///
/// On [`PlanningError::Stopped`], `extensions` is the sum over the runs until then.
pub(crate) fn grow_together<R: RngCore>(
    task: Task<'_>,
    cache: &mut ModelCache<'_>,
    rngs: Vec<R>,
    budget: &Budget,
) -> Result<Vec<RrtOutcome>, PlanningError> {
    let domain = task.domain;
    let mut searches: Vec<Search<'_, R>> =
        rngs.into_iter().map(|rng| Search::new(task, rng)).collect();
    let mut calls = 0;
    loop {
        let spent: usize = searches.iter().map(|s| s.outcome.extensions).sum();
        let mut active: Vec<&mut Search<'_, R>> = searches.iter_mut().filter(|s| !s.done).collect();
        if active.is_empty() {
            break;
        }
        if let Some(reason) = budget.stop() {
            return Err(PlanningError::Stopped {
                reason,
                extensions: searches.iter().map(|s| s.outcome.extensions).sum(),
            });
        }
        for s in active.iter_mut() {
            s.steer();
        }
        let (states, actions): (Vec<&[f64]>, Vec<&[f64]>) =
            active.iter().flat_map(|s| s.pairs()).unzip();
        let predicted = predict_pairs(domain, &states, &actions, &mut calls, budget, spent)?;
        let counts: Vec<usize> = active.iter().map(|s| s.pair_count()).collect();
        for (s, p) in active.iter_mut().zip(split_by(predicted, &counts)) {
            s.choose(p, cache);
        }
        let (states, actions): (Vec<&[f64]>, Vec<&[f64]>) =
            active.iter().flat_map(|s| s.prefetch_pairs()).unzip();
        let prefetched = predict_pairs(domain, &states, &actions, &mut calls, budget, spent)?;
        let counts: Vec<usize> = active.iter().map(|s| s.to_prefetch.len()).collect();
        for (s, p) in active.iter_mut().zip(split_by(prefetched, &counts)) {
            s.prefetched(p);
        }
        // The answers to the prefetched rows come after those of the edges; they are cached.
        let features: Vec<f64> = active
            .iter()
            .flat_map(|s| s.features.iter().copied())
            .collect();
        let answers = cache.predict(&features)?;
        let dim = domain.feature_dim().max(1);
        let mut from = 0;
        for s in active.iter_mut() {
            let rows = s.features.len() / dim;
            s.accept(&answers[from..from + rows]);
            from += rows;
        }
    }
    Ok(searches
        .into_iter()
        .map(|s| RrtOutcome {
            dynamics_calls: calls,
            ..s.outcome
        })
        .collect())
}

/// Splits `items` into consecutive parts of `counts[i]` items.
fn split_by<T>(items: Vec<T>, counts: &[usize]) -> Vec<Vec<T>> {
    let mut items = items.into_iter();
    counts
        .iter()
        .map(|&n| items.by_ref().take(n).collect())
        .collect()
}

/// Predicts `f̂(states[i], actions[i])` in one call within the search's `budget`, counting it
/// and checking that the model answered one prediction per pair. A call that failed because
/// the budget ran out (a remote model's call ends by the search's deadline and is abandoned
/// when the search is cancelled) stops the search like a round would, after `spent`
/// extensions.
pub(crate) fn predict_pairs(
    domain: &dyn Domain,
    states: &[&[f64]],
    actions: &[&[f64]],
    calls: &mut usize,
    budget: &Budget,
    spent: usize,
) -> Result<Vec<Predicted>, PlanningError> {
    if states.is_empty() {
        return Ok(Vec::new());
    }
    *calls += 1;
    let predicted = domain
        .dynamics()
        .predict_batch_within(states, actions, budget)
        .map_err(|e| match budget.stop() {
            Some(reason) => PlanningError::Stopped {
                reason,
                extensions: spent,
            },
            None => e.into(),
        })?;
    check_predictions(domain, predicted.len(), states.len())?;
    Ok(predicted)
}

/// The model's predictions of `pairs` when the domain's features read them
/// ([`Domain::features_use_prediction`]), else none (empty vectors): what a caller passes to
/// [`Domain::features`] for state-actions it has no prediction of yet (a sample, a grid).
pub(crate) fn predictions_for_features(
    domain: &dyn Domain,
    pairs: &[(Vec<f64>, Vec<f64>)],
    budget: &Budget,
) -> Result<Vec<Vec<f64>>, PlanningError> {
    if !domain.features_use_prediction() {
        return Ok(vec![Vec::new(); pairs.len()]);
    }
    let states: Vec<&[f64]> = pairs.iter().map(|(s, _)| s.as_slice()).collect();
    let actions: Vec<&[f64]> = pairs.iter().map(|(_, a)| a.as_slice()).collect();
    let mut calls = 0;
    Ok(
        predict_pairs(domain, &states, &actions, &mut calls, budget, 0)?
            .into_iter()
            .map(|p| p.next)
            .collect(),
    )
}
