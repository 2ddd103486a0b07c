//! The `bottleneck` acquisition's cross-problem value: which untrusted steps would, trusted,
//! open the most problems of the domain's distribution — not only the asked one.
//!
//! In a domain with finitely many state-actions ([`Domain::finite_state_actions`]) the learned
//! precondition at the test β is a graph. For `K` problems drawn from the domain's distribution
//! (a seeded stream of the proposal) that it does not solve, a step `e = (u, a)` is a
//! *bottleneck* of the problem when it is not trusted, `u` is reached from the start over
//! trusted steps and the model's `f̂(u, a)` reaches the goal over trusted steps: trusting `e`
//! alone would open the problem. Its value `v(e)` counts those problems. A candidate's value is
//! `Σ_t r_t v(e_t)` over its steps, where `r_t = Π_{k<t} p_k` is the probability that the robot
//! reaches step `t` where it was planned (`p_k = Φ((d_max − μ_k)/σ_k)`): executing the step
//! teaches whether it may be trusted, and a step after a likely failure is executed from
//! elsewhere. The candidate with the largest value is executed; when no candidate crosses a
//! bottleneck (every value 0) the choice is the paper's `lcb`.
//!
//! Exact on graphs; a continuous domain has no such graph and falls back to `lcb` throughout, as
//! does a graph larger than [`MAX_STATE_ACTIONS`].

use super::PlanningError;
use super::acquisition::within_probability;
use super::cache::ModelCache;
use super::precondition::Precondition;
use super::rrt::seeded_rng;
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

/// The value of each of `trajectories` (see the module docs), or `None` when the domain has no
/// finite set of state-actions (or more than [`MAX_STATE_ACTIONS`]), or when `budget` has
/// already run out (the choice is then `lcb`'s, which costs nothing more). `trusted` is the precondition at the test β; every state-action
/// of the domain is judged once through `cache`.
pub fn candidate_values(
    domain: &dyn Domain,
    cache: &mut ModelCache<'_>,
    trusted: &Precondition,
    trajectories: &[Trajectory],
    seed: u64,
    budget: &Budget,
) -> Result<Option<Vec<f64>>, PlanningError> {
    let Some(moves) = domain
        .finite_state_actions()
        .filter(|m| m.len() <= MAX_STATE_ACTIONS && budget.stop().is_none())
    else {
        return Ok(None);
    };
    let features: Vec<f64> = moves
        .iter()
        .flat_map(|(s, a)| domain.features(s, a))
        .collect();
    let judged = cache.predict(&features)?;
    let (s_refs, a_refs): (Vec<&[f64]>, Vec<&[f64]>) = moves
        .iter()
        .map(|(s, a)| (s.as_slice(), a.as_slice()))
        .unzip();
    let predicted = domain.dynamics().predict_batch(&s_refs, &a_refs)?;
    let ok: Vec<bool> = judged
        .iter()
        .zip(&predicted)
        .map(|((mu, sigma), p)| p.valid && trusted.inside(*mu, *sigma))
        .collect();
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
    let index: HashMap<(Key, Key), usize> = moves
        .iter()
        .enumerate()
        .map(|(i, (s, a))| ((key(s), key(a)), i))
        .collect();
    let d_max = trusted.d_max();
    Ok(Some(
        trajectories
            .iter()
            .map(|t| {
                let mut reach = 1.0;
                let mut total = 0.0;
                for (k, (s, a)) in t.states.iter().zip(&t.actions).enumerate() {
                    if let Some(v) = index.get(&(key(s), key(a))).and_then(|i| value.get(i)) {
                        total += reach * v;
                    }
                    reach *= within_probability(t.mu[k], t.sigma[k], d_max);
                }
                total
            })
            .collect(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::IcyGridworld;
    use crate::planning::DeviationModel;

    /// A 5 × 5 map whose wall (column 2) has two gaps, rows 1 and 3.
    fn two_gaps() -> IcyGridworld {
        IcyGridworld::new(&["..#..", ".....", "..#..", ".....", "..#.."]).expect("a valid map")
    }

    /// What a learner might know of it: every move trusted but those touching the wall's
    /// column, which bump; the way into the upper gap is doubtful (one untrusted move), the
    /// lower gap's two moves are doubtful (two untrusted moves).
    #[derive(Debug)]
    struct Learned;
    impl DeviationModel for Learned {
        fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
            features
                .chunks(dim)
                .map(|f| {
                    let (x, y) = ((f[0] * 4.0).round(), (f[1] * 4.0).round());
                    let dx = 2.0 * f[2] - 1.0;
                    let to = x + dx;
                    let doubtful = [(1.0, 1.0), (1.0, 3.0), (2.0, 3.0)];
                    if dx == 1.0 && doubtful.contains(&(x, y)) {
                        (0.05, 0.05)
                    } else if dx == 1.0 && (x, y) == (2.0, 1.0) {
                        (0.0, 0.001)
                    } else if x == 2.0 || to == 2.0 {
                        (1.0, 0.001)
                    } else {
                        (0.0, 0.001)
                    }
                })
                .collect()
        }
    }

    fn path(start: [f64; 2], moves: &[[f64; 2]], model: &Learned) -> Trajectory {
        let g = two_gaps();
        let mut states = vec![start.to_vec()];
        for m in moves {
            let s = states.last().unwrap();
            states.push(vec![s[0] + m[0], s[1] + m[1]]);
        }
        let features: Vec<f64> = states
            .iter()
            .zip(moves)
            .flat_map(|(s, m)| g.features(s, m))
            .collect();
        let (mu, sigma) = model.predict(&features, 4).into_iter().unzip();
        Trajectory {
            states,
            actions: moves.iter().map(|m| m.to_vec()).collect(),
            mu,
            sigma,
        }
    }

    #[test]
    fn the_way_one_untrusted_move_from_open_is_worth_more_than_the_way_two_moves_short() {
        let g = two_gaps();
        let (r, u, d) = ([1.0, 0.0], [0.0, -1.0], [0.0, 1.0]);
        let upper = path([0.0, 2.0], &[u, r, r, r, r, d], &Learned);
        let lower = path([0.0, 2.0], &[d, r, r, r, r, u], &Learned);
        let at_test = Precondition::new(2.0, 0.1).unwrap();
        let mut cache = ModelCache::new(&Learned, 4);
        let values = candidate_values(
            &g,
            &mut cache,
            &at_test,
            &[upper.clone(), lower.clone()],
            7,
            &Budget::unlimited(),
        )
        .unwrap()
        .expect("a grid is finite");
        // Trusting the way into the upper gap opens every crossing problem; either of the lower
        // gap's two moves opens only problems that start or end in that gap.
        assert!(
            values[0] > values[1],
            "the upper gap's way opens more sampled problems: {values:?}"
        );
        let direct = path([0.0, 0.0], &[d, r], &Learned);
        let none =
            candidate_values(&g, &mut cache, &at_test, &[direct], 7, &Budget::unlimited()).unwrap();
        assert_eq!(none, Some(vec![0.0]), "a trusted way opens nothing");
        // Seeded: the same problems, the same values.
        let again = candidate_values(
            &g,
            &mut cache,
            &at_test,
            &[upper, lower],
            7,
            &Budget::unlimited(),
        )
        .unwrap();
        assert_eq!(again, Some(values));
        // A continuous domain has no graph: the acquisition is `lcb` there.
        let plane = crate::domain::Kinematic::new(crate::domain::KinematicParams::default())
            .expect("the default kinematic domain");
        let model = crate::planning::synthetic::ConstantModel {
            mu: 0.0,
            sigma: 0.01,
        };
        let mut cache = ModelCache::new(&model, plane.feature_dim());
        assert_eq!(
            candidate_values(&plane, &mut cache, &at_test, &[], 7, &Budget::unlimited()).unwrap(),
            None
        );
    }
}
