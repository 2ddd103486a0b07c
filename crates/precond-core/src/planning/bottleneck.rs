//! The `bottleneck` acquisition's cross-problem value: which untrusted steps would, trusted,
//! open the most problems of the domain's distribution — not only the asked one.
//!
//! In a domain with finitely many state-actions ([`Domain::finite_state_actions`]) the learned
//! precondition at the test β is a graph. For `K` problems drawn from the domain's distribution
//! (a seeded stream of the proposal) that it does not solve, a step `e = (u, a)` is a
//! *bottleneck* of the problem when it is not trusted, `u` is reached from the start over
//! trusted steps and the model's `f̂(u, a)` reaches the goal over trusted steps: trusting `e`
//! alone would open the problem. Its value `v(e)` counts those problems. A trajectory's value
//! is the number of problems its execution is expected to open, `Σ_t r_{t+1} v(e_t)` over its
//! steps, where `r_{t+1} = Π_{k≤t} p_k` is the probability that every step up to and including
//! `t` stays within `d_max` (`p_k = Φ((d_max − μ_k)/σ_k)`): a step within is learned as such,
//! and a step after a likely failure is executed from elsewhere.
//!
//! The candidates of a training proposal are planned inside the training precondition; once its
//! β nears the test β, the bottlenecks lie outside it and no candidate crosses them. So beside
//! the candidates the acquisition builds a *probe*: the shortest way inside the training
//! precondition from the start to the most promising bottleneck, ending with that step (outside the
//! training precondition once its β nears the test β; [`assess`]). The most valuable of the candidates and the probe is executed;
//! when nothing crosses a bottleneck (every value 0) the choice is the paper's `lcb`.
//!
//! Exact on graphs; a continuous domain has no such graph and falls back to `lcb` throughout, as
//! does a graph larger than [`MAX_STATE_ACTIONS`].

use super::acquisition::within_probability;
use super::cache::ModelCache;
use super::error::PlanningError;
use super::precondition::Precondition;
use super::rrt::{Task, predictions_for_features, seeded_rng};
use super::trajectory::Trajectory;
use crate::budget::Budget;
use crate::domain::{Domain, Problem};
use std::collections::{HashMap, HashSet, VecDeque};

/// Problems drawn to value the bottlenecks.
pub const PROBLEMS: usize = 32;

/// Most state-actions a domain may have for the graph to be judged at every proposal (a 64 × 64
/// grid's); a larger one is valued like a continuous domain (`lcb`), so that a proposal's cost
/// stays that of its candidates.
pub const MAX_STATE_ACTIONS: usize = 16_384;

/// State-actions judged per call to the deviation model, between checks of the budget.
const JUDGED_PER_CALL: usize = 1024;

/// The stream of the proposal seed the problems are drawn from (far from the candidates' runs,
/// streams `1 ..= n_candidates + 1`).
const PROBLEM_STREAM: u64 = 1 << 40;

type Key = Vec<u64>;

fn key(s: &[f64]) -> Key {
    s.iter().map(|x| (x + 0.0).to_bits()).collect()
}

/// A finite domain's learned precondition as a graph: its state-actions, the model's next state
/// of each and whether each is trusted. One definition of "one untrusted move short", for the
/// acquisition and the harness's attribution alike.
pub struct TrustedGraph<'a> {
    domain: &'a dyn Domain,
    moves: &'a [(Vec<f64>, Vec<f64>)],
    next: &'a [Vec<f64>],
    trusted: &'a [bool],
    /// Trusted moves by the state they leave.
    from: HashMap<Key, Vec<usize>>,
    /// Trusted moves by the state they enter.
    into: HashMap<Key, Vec<usize>>,
}

impl<'a> TrustedGraph<'a> {
    /// The graph of `moves` (`(s, a)`), `next[i] = f̂(moves[i])`, `trusted[i]` whether move
    /// `i` is inside the precondition (all three equally long).
    pub fn new(
        domain: &'a dyn Domain,
        moves: &'a [(Vec<f64>, Vec<f64>)],
        next: &'a [Vec<f64>],
        trusted: &'a [bool],
    ) -> Self {
        let mut from: HashMap<Key, Vec<usize>> = HashMap::new();
        let mut into: HashMap<Key, Vec<usize>> = HashMap::new();
        for (i, (s, _)) in moves.iter().enumerate().filter(|(i, _)| trusted[*i]) {
            from.entry(key(s)).or_default().push(i);
            into.entry(key(&next[i])).or_default().push(i);
        }
        Self {
            domain,
            moves,
            next,
            trusted,
            from,
            into,
        }
    }

    /// The untrusted moves (indices) that would each, trusted alone, make `problem` solvable: a
    /// move from a state the start reaches over trusted moves into a state from which the goal
    /// is reached over trusted moves. `None` when the problem is solvable already; empty when
    /// no single move would do.
    pub fn opening_moves(&self, problem: &Problem) -> Option<Vec<usize>> {
        let (start, goal) = (problem.start(), problem.goal());
        let is_goal = |s: &[f64]| self.domain.is_goal(s, goal);
        let mut ahead = HashSet::from([key(start)]);
        let mut queue = VecDeque::from([start]);
        let mut solved = is_goal(start);
        while let Some(s) = queue.pop_front() {
            for &i in self.from.get(&key(s)).into_iter().flatten() {
                if ahead.insert(key(&self.next[i])) {
                    solved |= is_goal(&self.next[i]);
                    queue.push_back(&self.next[i]);
                }
            }
        }
        if solved {
            return None;
        }
        let mut behind: HashSet<Key> = self
            .moves
            .iter()
            .map(|(s, _)| s)
            .chain(self.next)
            .filter(|s| is_goal(s))
            .map(|s| key(s))
            .collect();
        let mut queue: VecDeque<Key> = behind.iter().cloned().collect();
        while let Some(k) = queue.pop_front() {
            for &i in self.into.get(&k).into_iter().flatten() {
                let before = key(&self.moves[i].0);
                if behind.insert(before.clone()) {
                    queue.push_back(before);
                }
            }
        }
        Some(
            (0..self.moves.len())
                .filter(|&i| {
                    !self.trusted[i]
                        && ahead.contains(&key(&self.moves[i].0))
                        && behind.contains(&key(&self.next[i]))
                })
                .collect(),
        )
    }
}

/// What the `bottleneck` acquisition knows of one proposal: the value of each candidate and,
/// where one can be reached, a probe of the most promising bottleneck.
#[derive(Debug, Clone, PartialEq)]
pub struct Assessment {
    /// The value of each candidate, in order (see the module docs).
    pub values: Vec<f64>,
    /// A trajectory from the start to the most promising bottleneck, ending with it, and its
    /// value; `None` when no bottleneck is reached (see [`assess`]).
    pub probe: Option<(Trajectory, f64)>,
}

/// The value of each of `trajectories` (see the module docs) for the `task` whose candidates
/// they are, and a probe: the shortest way from the start over steps inside the task's
/// precondition (the one the candidates were planned in) to the bottleneck `e` with the largest
/// `v(e) p_e` (`p_e` the probability that `e` is within `d_max`: a step almost surely out of
/// bounds teaches little), ending with `e`. Once the training β nears the test β a bottleneck
/// — untrusted at the test β — lies outside the task's precondition too, so no candidate
/// crosses it and only a probe executes it. Bottlenecks whose features are `in_flight`
/// (executed or chosen since the fit) are worth nothing until the next fit, so the
/// trajectories of one batch probe different ones.
///
/// `None` when the domain has no finite set of state-actions (or more than
/// [`MAX_STATE_ACTIONS`]), or when `budget` runs out before every state-action of the domain
/// is judged (once, through `cache`, in chunks of 1024; the choice is then `lcb`'s, which costs
/// nothing more).
pub(crate) fn assess(
    task: Task<'_>,
    cache: &mut ModelCache<'_>,
    trajectories: &[Trajectory],
    in_flight: &[f64],
    seed: u64,
    budget: &Budget,
) -> Result<Option<Assessment>, PlanningError> {
    let domain = task.domain;
    let Some(moves) = domain
        .finite_state_actions()
        .filter(|m| m.len() <= MAX_STATE_ACTIONS && budget.stop().is_none())
    else {
        return Ok(None);
    };
    let trusted = task
        .precondition
        .at_beta(task.settings.acquisition().test_beta)?;
    let dim = domain.feature_dim();
    let predicted = predictions_for_features(domain, &moves, budget)?;
    let features: Vec<f64> = moves
        .iter()
        .zip(&predicted)
        .flat_map(|((s, a), next)| domain.features(s, a, next))
        .collect();
    // Judged in chunks, so that a large graph on a large model stops within a chunk of the
    // budget's end (the choice is then `lcb`'s) instead of overrunning it.
    let mut judged = Vec::with_capacity(moves.len());
    for chunk in features.chunks(JUDGED_PER_CALL * dim) {
        if budget.stop().is_some() {
            return Ok(None);
        }
        judged.extend(cache.predict(chunk)?);
    }
    let (s_refs, a_refs): (Vec<&[f64]>, Vec<&[f64]>) = moves
        .iter()
        .map(|(s, a)| (s.as_slice(), a.as_slice()))
        .unzip();
    let predicted = domain.dynamics().predict_batch(&s_refs, &a_refs)?;
    // Which moves are valid and inside a precondition.
    let inside_of = |pre: Precondition| -> Vec<bool> {
        judged
            .iter()
            .zip(&predicted)
            .map(|((mu, sigma), p)| p.valid && pre.inside(*mu, *sigma))
            .collect()
    };
    let ok = inside_of(trusted);
    let inside = inside_of(task.precondition);
    let next: Vec<Vec<f64>> = predicted.into_iter().map(|p| p.next).collect();
    let graph = TrustedGraph::new(domain, &moves, &next, &ok);
    let mut value: HashMap<usize, f64> = HashMap::new();
    let mut rng = seeded_rng(seed, PROBLEM_STREAM);
    for _ in 0..PROBLEMS {
        let problem = domain.sample_problem(&mut rng);
        for i in graph.opening_moves(&problem).into_iter().flatten() {
            *value.entry(i).or_default() += 1.0;
        }
    }
    if !in_flight.is_empty() {
        let flying: HashSet<Key> = in_flight.chunks(dim).map(key).collect();
        value.retain(|&i, _| !flying.contains(&key(&features[i * dim..(i + 1) * dim])));
    }
    let index: HashMap<(Key, Key), usize> = moves
        .iter()
        .enumerate()
        .map(|(i, (s, a))| ((key(s), key(a)), i))
        .collect();
    let d_max = trusted.d_max();
    let worth = |t: &Trajectory| {
        let mut reach = 1.0;
        let mut total = 0.0;
        for (k, (s, a)) in t.states.iter().zip(&t.actions).enumerate() {
            reach *= within_probability(t.mu[k], t.sigma[k], d_max);
            if let Some(v) = index.get(&(key(s), key(a))).and_then(|i| value.get(i)) {
                total += reach * v;
            }
        }
        total
    };
    let values = trajectories.iter().map(worth).collect();
    let promise: HashMap<usize, f64> = value
        .iter()
        .map(|(&i, v)| (i, v * within_probability(judged[i].0, judged[i].1, d_max)))
        .collect();
    let probe = probe(task.problem.start(), &moves, &next, &inside, &promise).map(|way| {
        let mut states = vec![task.problem.start().to_vec()];
        states.extend(way.iter().map(|&i| next[i].clone()));
        let (mu, sigma) = way.iter().map(|&i| judged[i]).unzip();
        let t = Trajectory {
            states,
            actions: way.iter().map(|&i| moves[i].1.clone()).collect(),
            mu,
            sigma,
        };
        let v = worth(&t);
        (t, v)
    });
    Ok(Some(Assessment { values, probe }))
}

/// The moves of the shortest way from `start` over the moves marked `inside` to the move with
/// the largest `promise`, ending with it; the first found on ties (breadth-first, in move
/// order). `None` when no promising move leaves a state the start reaches.
fn probe(
    start: &[f64],
    moves: &[(Vec<f64>, Vec<f64>)],
    next: &[Vec<f64>],
    inside: &[bool],
    promise: &HashMap<usize, f64>,
) -> Option<Vec<usize>> {
    let mut leaving: HashMap<Key, Vec<usize>> = HashMap::new();
    for (i, (s, _)) in moves.iter().enumerate() {
        leaving.entry(key(s)).or_default().push(i);
    }
    // Breadth-first over inside moves, keeping the move each state was first entered by.
    let mut entered: HashMap<Key, Option<usize>> = HashMap::from([(key(start), None)]);
    let mut queue = VecDeque::from([start]);
    let mut best: Option<(f64, usize)> = None;
    while let Some(s) = queue.pop_front() {
        for &i in leaving.get(&key(s)).into_iter().flatten() {
            if let Some(&p) = promise.get(&i)
                && p > 0.0
                && best.is_none_or(|(b, _)| p > b)
            {
                best = Some((p, i));
            }
            if inside[i] && !entered.contains_key(&key(&next[i])) {
                entered.insert(key(&next[i]), Some(i));
                queue.push_back(&next[i]);
            }
        }
    }
    let (_, target) = best?;
    let mut way = vec![target];
    let mut at = key(&moves[target].0);
    while let Some(Some(i)) = entered.get(&at) {
        way.push(*i);
        at = key(&moves[*i].0);
    }
    way.reverse();
    Some(way)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::IcyGridworld;
    use crate::planning::DeviationModel;
    use crate::planning::synthetic::WallGapsModel;

    /// A 5 × 5 map whose wall (column 2) has two gaps, rows 1 and 3.
    fn two_gaps() -> IcyGridworld {
        IcyGridworld::new(&["..#..", ".....", "..#..", ".....", "..#.."]).expect("a valid map")
    }

    /// What a learner might know of it: the way into the upper gap is doubtful (one untrusted
    /// move), the lower gap's two moves are doubtful (two untrusted moves).
    fn learned() -> WallGapsModel {
        WallGapsModel {
            doubtful: vec![(1.0, 1.0), (1.0, 3.0), (2.0, 3.0)],
            through: vec![(2.0, 1.0)],
        }
    }

    fn path(start: [f64; 2], moves: &[[f64; 2]], model: &WallGapsModel) -> Trajectory {
        let g = two_gaps();
        let mut states = vec![start.to_vec()];
        for m in moves {
            let s = states.last().unwrap();
            states.push(vec![s[0] + m[0], s[1] + m[1]]);
        }
        let features: Vec<f64> = states
            .iter()
            .zip(moves)
            .flat_map(|(s, m)| g.features(s, m, &[]))
            .collect();
        let (mu, sigma) = model.predict(&features, 4).into_iter().unzip();
        Trajectory {
            states,
            actions: moves.iter().map(|m| m.to_vec()).collect(),
            mu,
            sigma,
        }
    }

    /// The task of planning from `start` to `goal` on `g` inside the precondition at β 2.
    fn ask<'a>(
        g: &'a IcyGridworld,
        problem: &'a Problem,
        settings: &'a crate::planning::PlanningSettings,
    ) -> Task<'a> {
        Task {
            domain: g,
            problem,
            precondition: Precondition::new(2.0, 0.1).unwrap(),
            settings,
        }
    }

    #[test]
    fn the_way_one_untrusted_move_from_open_is_worth_more_than_the_way_two_moves_short() {
        let g = two_gaps();
        let model = learned();
        let (r, u, d) = ([1.0, 0.0], [0.0, -1.0], [0.0, 1.0]);
        let upper = path([0.0, 2.0], &[u, r, r, r, r, d], &model);
        let lower = path([0.0, 2.0], &[d, r, r, r, r, u], &model);
        let settings = crate::planning::PlanningSettings::default();
        let problem = Problem::new(&g, vec![0.0, 2.0], vec![4.0, 2.0]).unwrap();
        let task = ask(&g, &problem, &settings);
        let mut cache = ModelCache::new(&model, 4);
        let assess_all = |cache: &mut ModelCache<'_>, ts: &[Trajectory], in_flight: &[f64]| {
            assess(task, cache, ts, in_flight, 7, &Budget::unlimited())
                .unwrap()
                .expect("a grid is finite")
        };
        let both = assess_all(&mut cache, &[upper.clone(), lower.clone()], &[]);
        // Trusting the way into the upper gap opens every crossing problem; either of the lower
        // gap's two moves opens only problems that start or end in that gap.
        assert!(
            both.values[0] > both.values[1],
            "the upper gap's way opens more sampled problems: {:?}",
            both.values
        );
        let direct = path([0.0, 0.0], &[d, r], &model);
        assert_eq!(
            assess_all(&mut cache, &[direct], &[]).values,
            vec![0.0],
            "a trusted way opens nothing"
        );
        // Seeded: the same problems, the same values.
        let again = assess_all(&mut cache, &[upper.clone(), lower], &[]);
        assert_eq!(again, both);
        // The probe goes from the start to the upper gap's doubtful move and ends with it.
        let (probe, value) = both.probe.expect("a bottleneck is reached from the start");
        assert_eq!(probe.states.first(), Some(&vec![0.0, 2.0]));
        assert_eq!(probe.actions.last(), Some(&r.to_vec()));
        assert_eq!(probe.states[probe.len() - 1], vec![1.0, 1.0]);
        assert!(value > 0.0);
        // With that move in flight it is worth nothing until the next fit: the probe turns to
        // another bottleneck, if the sampled problems need one.
        let in_flight = g.features(&[1.0, 1.0], &r, &[]);
        let spread = assess_all(&mut cache, &[upper], &in_flight);
        assert_eq!(spread.values, vec![0.0], "{:?}", spread.values);
        assert!(
            spread
                .probe
                .as_ref()
                .is_none_or(|(t, _)| t.states[t.len() - 1] != vec![1.0, 1.0]),
            "{:?}",
            spread.probe
        );
        // A continuous domain has no graph: the acquisition is `lcb` there.
        let plane = crate::domain::Kinematic::new(crate::domain::KinematicParams::default())
            .expect("the default kinematic domain");
        let model = crate::planning::synthetic::ConstantModel {
            mu: 0.0,
            sigma: 0.01,
        };
        let problem = Problem::new(&plane, vec![0.1, 0.1], vec![0.9, 0.9]).unwrap();
        let task = Task {
            domain: &plane,
            problem: &problem,
            precondition: Precondition::new(2.0, 0.1).unwrap(),
            settings: &settings,
        };
        let mut cache = ModelCache::new(&model, plane.feature_dim());
        assert_eq!(
            assess(task, &mut cache, &[], &[], 7, &Budget::unlimited()).unwrap(),
            None
        );
    }
}
