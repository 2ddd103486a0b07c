//! From a planning problem to a proposal: candidate generation and the three strategies of the
//! paper's comparison.
//!
//! **Candidates.** Up to `n_candidates` RRT runs, run `i` (from 0) seeded with stream `i + 1` of
//! the proposal seed (stream 0 is the strategy's own choices), all sharing one [`ModelCache`] so
//! the deviation model answers each distinct `φ(s, a)` once per proposal. Runs are made one at a
//! time until one reaches the goal; once `max_failed_runs` runs have failed before any
//! succeeded, the proposal gives up with [`PlanningError::NoPlan`]. After the first success the
//! remaining runs grow in lockstep (see [`rrt`](mod@super::rrt)), which gives the same trees with about
//! `n_candidates` times fewer model calls. Each run has its own budget of `max_extensions`.
//! Goal-reaching trajectories are kept, in run order, if their action sequence is new (two runs
//! often find the same path in a discrete domain), so there may be fewer candidates than runs.
//! `extensions` reports the sum over all runs.
//!
//! **Strategies.**
//! - `active`: the candidate with the smallest acquisition value `α` (the first on ties). With
//!   state-actions in flight (executed or chosen since the model was fitted:
//!   [`Planner::with_in_flight`](super::Planner::with_in_flight)), `α` is scored with each
//!   step's σ as if those were labelled already, so the trajectories of one batch spread over
//!   what is uncertain instead of all chasing the same doubt (batch diversity by fantasised
//!   observations: the GP's variance does not depend on the labels).
//!   Under the `bottleneck` acquisition in a finite domain the candidates are joined by a
//!   *probe*, a way to the most promising untrusted step other problems need, which ends there
//!   and not at the goal ([`bottleneck`](super::bottleneck)); the most valuable is executed.
//!   Under `spread` the candidate whose steps would settle the most of the precondition's
//!   boundary over a uniform sample of the space is executed ([`spread`](super::spread)).
//! - `goal_conditioned`: a uniformly random candidate (its `α` is still reported).
//! - `random`: a rollout of `Domain::rollout_length()` steps (for a domain that asks for it,
//!   `Domain::rollout_like_plans`, as many as one RRT run's plan for the problem has) from the
//!   start with actions from
//!   `Domain::sample_action`, ignoring the goal. Each step must satisfy the domain's constraints
//!   and the precondition under `β`: up to `random_action_tries` actions are sampled per step
//!   (each counts as an extension); when none fits the rollout stops there. It fails with
//!   `NoPlan` only when not even the first step is possible.

use super::acquisition::AcquisitionKind;
use super::cache::ModelCache;
use super::error::PlanningError;
use super::model::{DeviationModel, PlanModel};
use super::rrt::{RrtOutcome, Stage, Task, grow, grow_across, predict_pairs, seeded_rng};
use super::spread;
use super::trajectory::Trajectory;
use super::valuation;
use crate::budget::Budget;
use rand::Rng;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;

/// How a proposal chooses the trajectory to execute.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Strategy {
    /// Goal-reaching candidates, argmin of the acquisition function: the method. The default.
    #[default]
    Active,
    /// A uniformly random goal-reaching candidate, no acquisition.
    GoalConditioned,
    /// A random-action rollout from the start, not conditioned on the goal.
    Random,
}

setting_names!(Strategy, "strategy", {
    Active => "active",
    GoalConditioned => "goal_conditioned",
    Random => "random",
});

impl Strategy {
    /// The index of the candidate this strategy executes among candidates with acquisition
    /// values `alphas`, all eligible: `active` the smallest `α` (the first on ties), the others
    /// a uniformly random one (the first draw of stream 0 of `seed`). `None` when there is no
    /// candidate. The one place a strategy chooses, for the planner's candidates and the
    /// client's alike.
    pub fn choose(self, alphas: &[f64], seed: u64) -> Option<usize> {
        if alphas.is_empty() {
            return None;
        }
        Some(match self {
            Self::Active => argmin(alphas.iter().copied()),
            Self::GoalConditioned | Self::Random => {
                seeded_rng(seed, 0).random_range(..alphas.len())
            }
        })
    }
}

/// A scored candidate, as reported with a proposal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CandidateScore {
    /// Its acquisition value `α`.
    pub alpha: f64,
    /// Its number of actions.
    pub length: usize,
}

/// The trajectory a strategy chose for the robot to execute, with the evidence.
#[derive(Debug, Clone, PartialEq)]
pub struct Proposal {
    /// The strategy that chose it.
    pub strategy: Strategy,
    /// The β of the precondition it was planned inside.
    pub beta: f64,
    /// The chosen trajectory (predicted states, actions, per-step μ and σ).
    pub trajectory: Trajectory,
    /// `α_step` of each of its actions.
    pub alpha_step: Vec<f64>,
    /// Its acquisition value `α`.
    pub alpha: f64,
    /// All candidates in the order they were found (for `random`, the rollout alone; a
    /// `bottleneck` probe last).
    pub candidates: Vec<CandidateScore>,
    /// Index of the chosen trajectory in `candidates`.
    pub chosen_index: usize,
    /// The rule whose `α` the candidates were compared by
    /// ([`Valuation::valued_by`](super::valuation::Valuation::valued_by)).
    pub valued_by: AcquisitionKind,
    /// Extensions spent, over all runs (for `random`, actions tried).
    pub extensions: usize,
    /// RRT runs made (for `random`, 1).
    pub runs: usize,
    /// Distinct points sent to the deviation model.
    pub model_points: usize,
    /// Calls made to the deviation model (each with a batch of points).
    pub model_calls: usize,
    /// Calls made to the dynamics model `f̂` (each with a batch of points); across several
    /// models, to all of them.
    pub dynamics_calls: usize,
    /// Which model each step of the trajectory relied on, an index into the models of
    /// [`Planner::propose_across`](super::Planner::propose_across); empty for a proposal
    /// with the domain's model alone.
    pub step_models: Vec<usize>,
}

/// The proposal of `strategy` for the task's problem inside its precondition, asking `model`
/// within `budget` (see the module docs). `in_flight`: features of state-actions executed or
/// chosen since the model was fitted, which `active` scores as if labelled (see
/// [`fantasised_scores`]). The same inputs and `seed` give the same proposal.
pub(crate) fn propose(
    task: Task<'_>,
    model: &dyn DeviationModel,
    budget: &Budget,
    strategy: Strategy,
    seed: u64,
    in_flight: &[f64],
) -> Result<Proposal, PlanningError> {
    let Task {
        domain,
        problem,
        precondition,
        settings,
    } = task;
    let acquisition = settings.acquisition();
    let mut cache = ModelCache::new(model, domain.feature_dim());
    if strategy == Strategy::Random {
        let mut own_rng = seeded_rng(seed, 0);
        let mut dynamics_calls = 0;
        let (length, measured) = rollout_length(task, &mut cache, seed, budget)?;
        let (trajectory, extensions) = rollout(
            task,
            &mut cache,
            length,
            &mut own_rng,
            &mut dynamics_calls,
            budget,
        )?;
        let (runs, extensions, dynamics_calls) = match measured {
            Some(m) => (
                2,
                extensions + m.extensions,
                dynamics_calls + m.dynamics_calls,
            ),
            None => (1, extensions, dynamics_calls),
        };
        let (alpha_step, alpha) = acquisition.score(&trajectory, precondition.d_max());
        return Ok(Proposal {
            strategy,
            beta: precondition.beta(),
            candidates: vec![CandidateScore {
                alpha,
                length: trajectory.len(),
            }],
            trajectory,
            alpha_step,
            alpha,
            chosen_index: 0,
            valued_by: match acquisition.kind {
                AcquisitionKind::Bottleneck | AcquisitionKind::Spread => AcquisitionKind::Lcb,
                kind => kind,
            },
            extensions,
            runs,
            model_points: cache.points(),
            model_calls: cache.calls(),
            dynamics_calls,
            step_models: Vec::new(),
        });
    }
    if domain.is_goal(problem.start(), problem.goal()) {
        return Err(PlanningError::input(
            "goal",
            "the start already satisfies the goal: there is nothing to plan",
        ));
    }
    let mut found = {
        let mut stages = [Stage {
            dynamics: domain.dynamics(),
            cache: &mut cache,
        }];
        candidates(task, &mut stages, seed, budget)?
    };
    let valuation = valuation::value_candidates(
        valuation::Context {
            task,
            model,
            in_flight,
            seed,
            budget,
        },
        &mut cache,
        &mut found.trajectories,
        strategy == Strategy::Active,
        valuation::Probe::Allowed,
    )?;
    let calls = (cache.points(), cache.calls());
    Ok(found.choose(strategy, precondition.beta(), valuation, seed, calls, false))
}

/// The proposal of `strategy` (`active` or `goal_conditioned`) for the task's problem when an
/// execution labels every model of `models` (given cheapest first; each step of a candidate
/// relies on the cheapest model whose precondition trusts it, as in
/// [`Planner::plan_across`](super::Planner::plan_across)). Under `active` with the `spread`
/// acquisition a candidate is valued by the boundary uncertainty its execution would remove
/// summed over every model's precondition ([`spread::values_across`]), each model's with
/// the features of its own state-actions in flight (`in_flight[m]`); every other acquisition
/// compares the candidates' scores, each step's μ and σ the model's it relied on (no
/// fantasised σ: `bottleneck` and `lcb` alike score by `lcb`). `step_models` of the answer
/// index into `models`.
pub(crate) fn propose_across(
    task: Task<'_>,
    models: &[PlanModel<'_>],
    in_flight: &[&[f64]],
    budget: &Budget,
    strategy: Strategy,
    seed: u64,
) -> Result<Proposal, PlanningError> {
    let (domain, problem, precondition) = (task.domain, task.problem, task.precondition);
    if strategy == Strategy::Random {
        return Err(PlanningError::settings(
            "strategy",
            "a random rollout steps with the domain's model alone",
        ));
    }
    if in_flight.len() != models.len() {
        return Err(PlanningError::input(
            "in_flight",
            format!("{} sets for {} models", in_flight.len(), models.len()),
        ));
    }
    if domain.is_goal(problem.start(), problem.goal()) {
        return Err(PlanningError::input(
            "goal",
            "the start already satisfies the goal: there is nothing to plan",
        ));
    }
    let dim = domain.feature_dim();
    let mut caches: Vec<ModelCache<'_>> = models
        .iter()
        .map(|m| ModelCache::new(m.deviation, dim))
        .collect();
    let found = {
        let mut stages: Vec<Stage<'_, '_>> = models
            .iter()
            .zip(caches.iter_mut())
            .map(|(m, cache)| Stage {
                dynamics: m.dynamics,
                cache,
            })
            .collect();
        candidates(task, &mut stages, seed, budget)?
    };
    let acquisition = task.settings.acquisition();
    let scored: Vec<(Vec<f64>, f64)> = found
        .trajectories
        .iter()
        .map(|t| acquisition.score(t, precondition.d_max()))
        .collect();
    let values = if strategy == Strategy::Active && acquisition.kind == AcquisitionKind::Spread {
        let spread_models: Vec<spread::SpreadModel<'_>> = models
            .iter()
            .zip(in_flight)
            .map(|(m, in_flight)| spread::SpreadModel {
                dynamics: m.dynamics,
                deviation: m.deviation,
                in_flight,
            })
            .collect();
        spread::values_across(
            task,
            &spread_models,
            &found.trajectories,
            &found.step_models,
            seed,
            budget,
        )?
    } else {
        None
    };
    let kind = match acquisition.kind {
        AcquisitionKind::Bottleneck => AcquisitionKind::Lcb,
        kind => kind,
    };
    let valuation = valuation::compare(kind, scored, values);
    let calls = (
        caches.iter().map(ModelCache::points).sum(),
        caches.iter().map(ModelCache::calls).sum(),
    );
    Ok(found.choose(strategy, precondition.beta(), valuation, seed, calls, true))
}

/// Index of the smallest value, the first on ties (`total_cmp` order). 0 when empty.
fn argmin(values: impl Iterator<Item = f64>) -> usize {
    let mut best: Option<(usize, f64)> = None;
    for (i, v) in values.enumerate() {
        if best.is_none_or(|(_, b)| v.total_cmp(&b).is_lt()) {
            best = Some((i, v));
        }
    }
    best.map_or(0, |(i, _)| i)
}

/// The distinct goal-reaching trajectories of one proposal's runs.
struct Candidates {
    trajectories: Vec<Trajectory>,
    /// The stage each step of each trajectory relied on.
    step_models: Vec<Vec<usize>>,
    extensions: usize,
    runs: usize,
    dynamics_calls: usize,
}

impl Candidates {
    /// The proposal `strategy` makes of these candidates valued `valuation` (planned at
    /// `beta`): the one it chooses — `candidates` answers NoPlan rather than an empty set, so
    /// there is one — with its `α` as it was compared (for `bottleneck` and `spread`, the
    /// value negated). `calls`: distinct points and calls the deviation models answered;
    /// `across`: whether the steps' models are reported (a proposal across models).
    fn choose(
        self,
        strategy: Strategy,
        beta: f64,
        valuation: valuation::Valuation,
        seed: u64,
        (model_points, model_calls): (usize, usize),
        across: bool,
    ) -> Proposal {
        let valuation::Valuation {
            scored,
            alphas,
            valued_by,
        } = valuation;
        let chosen_index = strategy.choose(&alphas, seed).unwrap_or(0);
        let candidates = self
            .trajectories
            .iter()
            .zip(&alphas)
            .map(|(t, alpha)| CandidateScore {
                alpha: *alpha,
                length: t.len(),
            })
            .collect();
        let (alpha_step, alpha) = (scored[chosen_index].0.clone(), alphas[chosen_index]);
        let (mut trajectories, mut step_models) = (self.trajectories, self.step_models);
        Proposal {
            strategy,
            beta,
            trajectory: trajectories.swap_remove(chosen_index),
            alpha_step,
            alpha,
            candidates,
            chosen_index,
            valued_by,
            extensions: self.extensions,
            runs: self.runs,
            model_points,
            model_calls,
            dynamics_calls: self.dynamics_calls,
            step_models: if across {
                step_models.swap_remove(chosen_index)
            } else {
                Vec::new()
            },
        }
    }
}

/// The candidates of one proposal (see the module docs), stepping with `stages` (the domain's
/// model alone, or several models cheapest first).
fn candidates(
    task: Task<'_>,
    stages: &mut [Stage<'_, '_>],
    seed: u64,
    budget: &Budget,
) -> Result<Candidates, PlanningError> {
    let planner = task.settings.planner();
    let mut found = Candidates {
        trajectories: Vec::new(),
        step_models: Vec::new(),
        extensions: 0,
        runs: 0,
        dynamics_calls: 0,
    };
    let stopped = |spent: usize| {
        move |e| match e {
            PlanningError::Stopped { reason, extensions } => PlanningError::Stopped {
                reason,
                extensions: spent + extensions,
            },
            e => e,
        }
    };
    // Runs one at a time until one reaches the goal (or enough fail to give up) ...
    let mut outcomes: Vec<RrtOutcome> = Vec::new();
    let mut failed = 0;
    while outcomes.len() < planner.n_candidates {
        let rng = seeded_rng(seed, outcomes.len() as u64 + 1);
        let outcome = grow_across(task, stages, vec![rng], budget)
            .map_err(stopped(found.extensions))?
            .pop()
            .expect("one search, one outcome");
        found.extensions += outcome.extensions;
        found.dynamics_calls += outcome.dynamics_calls;
        let reached = outcome.trajectory.is_some();
        outcomes.push(outcome);
        if reached {
            break;
        }
        failed += 1;
        if failed >= planner.max_failed_runs {
            break;
        }
    }
    // ... then the others together, one model call serving a round of each.
    if outcomes.last().is_some_and(|o| o.trajectory.is_some()) {
        let rngs = (outcomes.len()..planner.n_candidates)
            .map(|run| seeded_rng(seed, run as u64 + 1))
            .collect::<Vec<_>>();
        if !rngs.is_empty() {
            let rest =
                grow_across(task, stages, rngs, budget).map_err(stopped(found.extensions))?;
            found.dynamics_calls += rest.first().map_or(0, |o| o.dynamics_calls);
            found.extensions += rest.iter().map(|o| o.extensions).sum::<usize>();
            outcomes.extend(rest);
        }
    }
    found.runs = outcomes.len();
    let mut seen: HashSet<Vec<u64>> = HashSet::new();
    for o in outcomes {
        let Some(t) = o.trajectory else { continue };
        let key = t.actions.iter().flatten().map(|x| (x + 0.0).to_bits());
        if seen.insert(key.collect()) {
            found.trajectories.push(t);
            found.step_models.push(o.step_models);
        }
    }
    if found.trajectories.is_empty() {
        return Err(PlanningError::NoPlan {
            extensions: found.extensions,
        });
    }
    Ok(found)
}

/// Steps of a `random` rollout: the domain's, or for a domain that asks for it
/// ([`Domain::rollout_like_plans`]) the length of one RRT run's plan for this problem
/// (stream `n_candidates + 1` of the seed), returned with that run.
fn rollout_length(
    task: Task<'_>,
    cache: &mut ModelCache<'_>,
    seed: u64,
    budget: &Budget,
) -> Result<(usize, Option<RrtOutcome>), PlanningError> {
    let domain = task.domain;
    if !domain.rollout_like_plans() {
        return Ok((domain.rollout_length(), None));
    }
    let mut rng = seeded_rng(seed, task.settings.planner().n_candidates as u64 + 1);
    let run = grow(task, cache, &mut rng, budget)?;
    let length = run
        .trajectory
        .as_ref()
        .map_or(domain.rollout_length(), |t| t.len().max(1));
    Ok((length, Some(run)))
}

fn rollout(
    task: Task<'_>,
    cache: &mut ModelCache<'_>,
    length: usize,
    rng: &mut dyn rand::RngCore,
    dynamics_calls: &mut usize,
    budget: &Budget,
) -> Result<(Trajectory, usize), PlanningError> {
    let domain = task.domain;
    let planner = task.settings.planner();
    let mut t = Trajectory {
        states: vec![task.problem.start().to_vec()],
        actions: Vec::new(),
        mu: Vec::new(),
        sigma: Vec::new(),
    };
    let mut extensions = 0;
    for _ in 0..length {
        if let Some(reason) = budget.stop() {
            return Err(PlanningError::Stopped { reason, extensions });
        }
        let s = t
            .states
            .last()
            .expect("a trajectory has a first state")
            .clone();
        // Every try of a step is predicted in one call; the first allowed one inside the
        // precondition is taken.
        let tries: Vec<Vec<f64>> = (0..planner.random_action_tries)
            .map(|_| domain.sample_action(&s, rng))
            .collect();
        let states = vec![s.as_slice(); tries.len()];
        let actions: Vec<&[f64]> = tries.iter().map(Vec::as_slice).collect();
        let predicted = predict_pairs(
            domain,
            &states,
            &actions,
            dynamics_calls,
            budget,
            extensions,
        )?;
        let allowed: Vec<(usize, Vec<f64>, Vec<f64>)> = tries
            .into_iter()
            .zip(predicted)
            .enumerate()
            .filter(|(_, (a, p))| p.valid && domain.edge_allowed(&s, a, &p.next))
            .map(|(k, (a, p))| (k, a, p.next))
            .collect();
        let features: Vec<f64> = allowed
            .iter()
            .flat_map(|(_, a, next)| domain.features(&s, a, next))
            .collect();
        let answers = cache.predict(&features)?;
        let chosen = allowed
            .into_iter()
            .zip(answers)
            .find(|(_, (mu, sigma))| task.precondition.inside(*mu, *sigma));
        let Some(((k, a, next), (mu, sigma))) = chosen else {
            extensions += planner.random_action_tries;
            break;
        };
        // Actions tried until this one.
        extensions += k + 1;
        t.states.push(next);
        t.actions.push(a);
        t.mu.push(mu);
        t.sigma.push(sigma);
    }
    if t.is_empty() {
        return Err(PlanningError::NoPlan { extensions });
    }
    Ok((t, extensions))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn argmin_takes_the_first_smallest() {
        assert_eq!(argmin([0.3, -0.1, 0.2, -0.1].into_iter()), 1);
        assert_eq!(argmin([5.0].into_iter()), 0);
        assert_eq!(argmin([2.0, 1.0, 0.5].into_iter()), 2);
    }

    #[test]
    fn strategy_names_round_trip() {
        for s in [
            Strategy::Active,
            Strategy::GoalConditioned,
            Strategy::Random,
        ] {
            assert_eq!(s.as_str().parse::<Strategy>(), Ok(s));
        }
        assert!(matches!(
            "greedy".parse::<Strategy>(),
            Err(PlanningError::InvalidSettings {
                field: "strategy",
                ..
            })
        ));
    }
}
