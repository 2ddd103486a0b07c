//! Candidates given by the client: a lab that plans with its own planner (or whose model lives
//! on its side) posts candidate trajectories, and the service scores each step with the MDE,
//! keeps the candidates that stay inside the precondition and reach the goal, and lets the
//! strategy choose among them — the same choice its own RRT candidates would get.
//!
//! Every step of every candidate goes to the deviation model in one batch.

use super::acquisition::AcquisitionSettings;
use super::cache::ModelCache;
use super::error::PlanningError;
use super::model::DeviationModel;
use super::precondition::Precondition;
use super::strategy::Strategy;
use super::trajectory::Trajectory;
use crate::domain::Domain;

/// A candidate as posted: its states (starting with the start state) and the actions between
/// them.
pub type Path = (Vec<Vec<f64>>, Vec<Vec<f64>>);

/// A candidate's verdict.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    /// The candidate with `μ` and `σ` at each step.
    pub trajectory: Trajectory,
    /// `α_step` of each step.
    pub alpha_step: Vec<f64>,
    /// Its acquisition value `α`.
    pub alpha: f64,
    /// Whether every step lies in the precondition (`μ + βσ < d_max`).
    pub inside: bool,
    /// The first step outside the precondition, if any.
    pub first_outside: Option<usize>,
    /// Whether its last state satisfies the goal test.
    pub reaches_goal: bool,
}

impl Verdict {
    /// Inside the precondition and reaching the goal: a candidate the strategies may choose.
    pub fn eligible(&self) -> bool {
        self.inside && self.reaches_goal
    }
}

/// Scores every step of every candidate `(states, actions)` (states start with the start
/// state; one more state than actions) with `model` and `acquisition` inside `precondition`,
/// and judges each against it and the goal. Inputs are assumed validated against the domain.
pub(crate) fn judge(
    domain: &dyn Domain,
    model: &dyn DeviationModel,
    acquisition: &AcquisitionSettings,
    goal: &[f64],
    candidates: Vec<Path>,
    precondition: Precondition,
) -> Result<Vec<Verdict>, PlanningError> {
    let mut cache = ModelCache::new(model, domain.feature_dim());
    let features: Vec<f64> = candidates
        .iter()
        .flat_map(|(states, actions)| {
            actions
                .iter()
                .enumerate()
                .flat_map(|(t, a)| domain.features(&states[t], a, &states[t + 1]))
        })
        .collect();
    let mut answers = cache.predict(&features)?.into_iter();
    Ok(candidates
        .into_iter()
        .map(|(states, actions)| {
            let (mu, sigma): (Vec<f64>, Vec<f64>) = answers.by_ref().take(actions.len()).unzip();
            let first_outside = mu
                .iter()
                .zip(&sigma)
                .position(|(m, s)| !precondition.inside(*m, *s));
            let reaches_goal = states.last().is_some_and(|s| domain.is_goal(s, goal));
            let trajectory = Trajectory {
                states,
                actions,
                mu,
                sigma,
            };
            let (alpha_step, alpha) = acquisition.score(&trajectory, precondition.d_max());
            Verdict {
                trajectory,
                alpha_step,
                alpha,
                inside: first_outside.is_none(),
                first_outside,
                reaches_goal,
            }
        })
        .collect())
}

/// The candidate the strategy executes ([`Strategy::choose`]) among those it may take:
/// `active` and `goal_conditioned` the [eligible](Verdict::eligible) ones, `random` those
/// inside the precondition whether or not they reach the goal. `None` when there is none to
/// choose.
pub fn choose(strategy: Strategy, verdicts: &[Verdict], seed: u64) -> Option<usize> {
    let pool: Vec<usize> = (0..verdicts.len())
        .filter(|&i| match strategy {
            Strategy::Random => verdicts[i].inside,
            _ => verdicts[i].eligible(),
        })
        .collect();
    let alphas: Vec<f64> = pool.iter().map(|&i| verdicts[i].alpha).collect();
    strategy.choose(&alphas, seed).map(|k| pool[k])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::IcyGridworld;
    use crate::planning::{
        AcquisitionKind, Aggregation, Planner, PlannerSettings, PlanningSettings,
    };

    /// The verdicts of `candidates` for the goal `goal` on the default map under [`Wall`], at
    /// β = 2 and d_max = 0.1.
    fn judge_candidates(
        goal: &[f64],
        candidates: Vec<Path>,
        acquisition: &AcquisitionSettings,
    ) -> Vec<Verdict> {
        let grid = IcyGridworld::default_layout();
        let settings = PlanningSettings::new(PlannerSettings::default(), *acquisition).unwrap();
        Planner::new(&grid, &Wall, &settings)
            .judge(goal, candidates, Precondition::new(2.0, 0.1).unwrap())
            .unwrap()
    }

    /// A passage whose one move, right from (4, 1), lies on the level set (μ = d_max = 0.1, σ =
    /// 0.05: nobody knows which side); every other move is surely safe (μ = 0, σ = 0.001).
    struct Gap;
    impl DeviationModel for Gap {
        fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
            features
                .chunks(dim)
                .map(|r| {
                    let at = (r[0] * 11.0).round() == 4.0 && (r[1] * 11.0).round() == 1.0;
                    let right = r[2] == 1.0 && r[3] == 0.5;
                    if at && right {
                        (0.1, 0.05)
                    } else {
                        (0.0, 0.001)
                    }
                })
                .collect()
        }
    }

    #[test]
    fn the_level_set_acquisition_executes_the_doubtful_passage_and_the_paper_s_does_not() {
        // Two ways from (3, 1) to (6, 1): straight through the doubtful move, or around it.
        let candidates = || {
            vec![
                walk(
                    [3.0, 1.0],
                    &[[0.0, 1.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, -1.0]],
                ),
                walk([3.0, 1.0], &[[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]]),
            ]
        };
        let judge = |kind| {
            let acq = AcquisitionSettings {
                kind,
                ..AcquisitionSettings::default()
            };
            let grid = IcyGridworld::default_layout();
            let settings = PlanningSettings::new(PlannerSettings::default(), acq).unwrap();
            // The optimistic β of early training, at which the doubtful move may be planned.
            Planner::new(&grid, &Gap, &settings)
                .judge(
                    &[6.0, 1.0],
                    candidates(),
                    Precondition::new(-2.0, 0.1).unwrap(),
                )
                .unwrap()
        };
        let lcb = judge(AcquisitionKind::Lcb);
        assert!(lcb.iter().all(Verdict::eligible));
        // The paper's lower confidence bound prefers the way it is surest of: around.
        assert_eq!(choose(Strategy::Active, &lcb, 0), Some(0));
        // The level set's: the move whose side of d_max is in doubt.
        let level_set = judge(AcquisitionKind::LevelSet);
        assert_eq!(choose(Strategy::Active, &level_set, 0), Some(1));
        // Its α: the doubtful step (t = 1, p = 1/2, reached surely) weighs γ = 0.9.
        assert!(
            (level_set[1].alpha + 0.9).abs() < 1e-6,
            "{}",
            level_set[1].alpha
        );
    }

    /// μ = 0.3 on x-moves from x ≥ 5 (in grid units), else 0; σ = 0.01.
    struct Wall;
    impl DeviationModel for Wall {
        fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
            features
                .chunks(dim)
                .map(|r| {
                    let x_move = r[2] != 0.5;
                    (
                        if r[0] >= 5.0 / 11.0 && x_move {
                            0.3
                        } else {
                            0.0
                        },
                        0.01,
                    )
                })
                .collect()
        }
    }

    fn walk(start: [f64; 2], moves: &[[f64; 2]]) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
        let mut states = vec![start.to_vec()];
        for m in moves {
            let s = states.last().unwrap();
            states.push(vec![s[0] + m[0], s[1] + m[1]]);
        }
        (states, moves.iter().map(|m| m.to_vec()).collect())
    }

    #[test]
    fn candidates_are_judged_step_by_step_and_the_strategies_choose_among_the_eligible() {
        let acq = AcquisitionSettings {
            kind: AcquisitionKind::Lcb,
            c: 1.0,
            gamma: 0.9,
            aggregation: Aggregation::Max,
            test_beta: 2.0,
        };
        let candidates = vec![
            // Through x ≥ 5 with x-moves: outside from step 1.
            walk([4.0, 0.0], &[[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),
            // Up first, then the x-moves from x = 4 and 5: the second x-move is outside.
            walk([4.0, 0.0], &[[0.0, 1.0], [1.0, 0.0], [1.0, 0.0]]),
            // Stays at x ≤ 4: inside, but does not reach [6, 1].
            walk([4.0, 0.0], &[[0.0, 1.0], [-1.0, 0.0]]),
        ];
        let v = judge_candidates(&[6.0, 1.0], candidates, &acq);
        assert_eq!(v[0].first_outside, Some(1));
        assert_eq!(v[1].first_outside, Some(2));
        assert!(v[2].inside && !v[2].reaches_goal);
        assert!(v[0].reaches_goal && v[1].reaches_goal);
        for x in &v {
            let (steps, alpha) = acq.score(&x.trajectory, 0.1);
            assert_eq!((steps, alpha), (x.alpha_step.clone(), x.alpha));
        }
        assert_eq!(choose(Strategy::Active, &v, 1), None);
        assert_eq!(choose(Strategy::GoalConditioned, &v, 1), None);
        assert_eq!(choose(Strategy::Random, &v, 1), Some(2));

        // Two eligible candidates to [3, 1]: `active` takes the smaller α.
        let candidates = vec![
            walk(
                [4.0, 0.0],
                &[[-1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [1.0, 0.0]],
            ),
            walk([4.0, 0.0], &[[0.0, 1.0], [-1.0, 0.0]]),
            walk([4.0, 0.0], &[[1.0, 0.0], [1.0, 0.0]]),
        ];
        let v = judge_candidates(&[3.0, 1.0], candidates, &acq);
        assert!(v[0].eligible() && v[1].eligible() && !v[2].eligible());
        let best = if v[0].alpha <= v[1].alpha { 0 } else { 1 };
        assert_ne!(v[0].alpha, v[1].alpha);
        assert_eq!(choose(Strategy::Active, &v, 1), Some(best));
        for seed in 0..20 {
            let pick = choose(Strategy::GoalConditioned, &v, seed).unwrap();
            assert!(pick < 2, "goal_conditioned picked an ineligible candidate");
        }
    }
}
