//! Planner-level tests: invariants of every planned edge, the icy gridworld, the strategies.

use super::synthetic::{ConstantModel, IceModel, WallGapsModel};
use super::*;
use crate::domain::{BoxObstacle, Domain, IcyGridworld, Kinematic, KinematicParams, Problem};
use proptest::prelude::{Just, ProptestConfig, any, prop_assert, prop_oneof, proptest};
use std::sync::atomic::{AtomicUsize, Ordering};

/// A bump of deviation around a point of the state features; `σ` constant.
struct BumpModel {
    centre: [f64; 2],
    height: f64,
    sigma: f64,
}

impl DeviationModel for BumpModel {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        features
            .chunks(dim)
            .map(|f| {
                let r2 = (f[0] - self.centre[0]).powi(2) + (f[1] - self.centre[1]).powi(2);
                (self.height * (-r2 / 0.02).exp(), self.sigma)
            })
            .collect()
    }
}

/// μ grows with the x feature, σ shrinks with it: candidates get different α.
struct SlopeModel;

impl DeviationModel for SlopeModel {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        features
            .chunks(dim)
            .map(|f| (0.05 * f[0] + 0.01 * f[1], 0.02 + 0.03 * (1.0 - f[0])))
            .collect()
    }
}

/// Counts calls and points, answering like the wrapped model.
struct Counting<'a> {
    inner: &'a dyn DeviationModel,
    calls: AtomicUsize,
    points: AtomicUsize,
}

impl DeviationModel for Counting<'_> {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        self.calls.fetch_add(1, Ordering::Relaxed);
        self.points
            .fetch_add(features.len() / dim, Ordering::Relaxed);
        self.inner.predict(features, dim)
    }
}

fn walled_kinematic() -> Kinematic {
    // A wall at x ∈ [0.45, 0.5] with a gap at y ∈ [0.4, 0.6].
    Kinematic::new(KinematicParams {
        obstacles: vec![
            BoxObstacle {
                low: vec![0.45, 0.0],
                high: vec![0.5, 0.4],
            },
            BoxObstacle {
                low: vec![0.45, 0.6],
                high: vec![0.5, 1.0],
            },
        ],
        ..Default::default()
    })
    .unwrap()
}

/// One planning question of a test, spelled by name: a domain and a deviation model, the
/// problem, the precondition (β 2, d_max 0.1 unless [`at`](Self::at) says otherwise), the
/// settings (defaults unless given) and the budget (unlimited unless given). Its answers go
/// through the public [`Planner`]; a problem the domain refuses is the planner's
/// `InvalidInput` naming `start` or `goal`, as a client would see it.
struct Ask<'a> {
    domain: &'a dyn Domain,
    mde: &'a dyn DeviationModel,
    start: Vec<f64>,
    goal: Vec<f64>,
    beta: f64,
    d_max: f64,
    planner: PlannerSettings,
    acquisition: AcquisitionSettings,
    budget: Budget,
}

impl<'a> Ask<'a> {
    fn new(
        domain: &'a dyn Domain,
        mde: &'a dyn DeviationModel,
        start: &[f64],
        goal: &[f64],
    ) -> Self {
        Self {
            domain,
            mde,
            start: start.to_vec(),
            goal: goal.to_vec(),
            beta: 2.0,
            d_max: 0.1,
            planner: PlannerSettings::default(),
            acquisition: AcquisitionSettings::default(),
            budget: Budget::unlimited(),
        }
    }

    fn at(self, beta: f64, d_max: f64) -> Self {
        Self {
            beta,
            d_max,
            ..self
        }
    }

    fn planner(self, planner: &PlannerSettings) -> Self {
        Self {
            planner: planner.clone(),
            ..self
        }
    }

    fn acquisition(self, acquisition: &AcquisitionSettings) -> Self {
        Self {
            acquisition: *acquisition,
            ..self
        }
    }

    fn within(self, budget: &Budget) -> Self {
        Self {
            budget: budget.clone(),
            ..self
        }
    }

    /// The checked values, or the first check that fails.
    fn checked(&self) -> Result<(PlanningSettings, Problem, Precondition), PlanningError> {
        let settings = PlanningSettings::new(self.planner.clone(), self.acquisition)?;
        let problem =
            Problem::new(self.domain, self.start.clone(), self.goal.clone()).map_err(|e| {
                let field = if e.field.starts_with("start") {
                    "start"
                } else {
                    "goal"
                };
                PlanningError::input(field, e.reason)
            })?;
        Ok((settings, problem, Precondition::new(self.beta, self.d_max)?))
    }

    fn with_planner<T>(
        &self,
        f: impl FnOnce(&Planner<'_>, &Problem, Precondition) -> Result<T, PlanningError>,
    ) -> Result<T, PlanningError> {
        let (settings, problem, precondition) = self.checked()?;
        let planner = Planner::new(self.domain, self.mde, &settings).within(self.budget.clone());
        f(&planner, &problem, precondition)
    }

    fn propose(&self, strategy: Strategy, seed: u64) -> Result<Proposal, PlanningError> {
        self.with_planner(|planner, problem, pre| planner.propose(strategy, problem, pre, seed))
    }

    fn plan(&self, seed: u64) -> Result<RrtOutcome, PlanningError> {
        self.with_planner(|planner, problem, pre| planner.plan(problem, pre, seed))
    }

    fn rrt(&self, rng: &mut dyn rand::RngCore) -> Result<RrtOutcome, PlanningError> {
        self.with_planner(|planner, problem, pre| planner.rrt(problem, pre, rng))
    }

    /// Proposes inside the precondition at each of `betas` in turn (this ask's `d_max`).
    fn propose_relaxing(
        &self,
        strategy: Strategy,
        betas: &[f64],
        seed: u64,
    ) -> Result<Proposal, PlanningError> {
        self.with_planner(|planner, problem, pre| {
            let ladder = betas
                .iter()
                .map(|&b| pre.at_beta(b))
                .collect::<Result<Vec<_>, _>>()?;
            planner.propose_relaxing(strategy, problem, &ladder, seed)
        })
    }
}

fn small_settings() -> PlannerSettings {
    PlannerSettings {
        max_extensions: 2000,
        n_candidates: 5,
        ..Default::default()
    }
}

/// Every step satisfies the constraints and the precondition under `beta`, with the μ, σ the
/// model gives, and the states chain through the model from the start.
fn assert_valid(
    domain: &dyn Domain,
    mde: &dyn DeviationModel,
    t: &Trajectory,
    start: &[f64],
    beta: f64,
    d_max: f64,
) {
    assert_eq!(t.states.len(), t.actions.len() + 1);
    assert_eq!(t.mu.len(), t.actions.len());
    assert_eq!(t.sigma.len(), t.actions.len());
    assert_eq!(t.states[0], start);
    for (i, a) in t.actions.iter().enumerate() {
        let (s, next) = (&t.states[i], &t.states[i + 1]);
        assert!(domain.validate_action(a).is_ok(), "step {i}: action {a:?}");
        let predicted = domain.dynamics().predict_one(s, a).unwrap();
        assert_eq!(&predicted.next, next, "step {i} does not chain");
        assert!(
            domain.edge_allowed(s, a, next),
            "step {i} breaks a constraint"
        );
        let (mu, sigma) = mde.predict(&domain.features(s, a, next), domain.feature_dim())[0];
        assert_eq!((mu, sigma), (t.mu[i], t.sigma[i]), "step {i}: stored μ, σ");
        assert!(
            mu + beta * sigma < d_max,
            "step {i} is outside the precondition"
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    #[test]
    fn every_gridworld_edge_is_allowed_and_inside(
        seed in any::<u64>(),
        beta in -2.0f64..3.0,
        problem_seed in any::<u64>(),
        batch in 1usize..20,
        strategy in prop_oneof![
            Just(Strategy::Active), Just(Strategy::GoalConditioned), Just(Strategy::Random)
        ],
    ) {
        let grid = IcyGridworld::default_layout();
        let mde = IceModel::new(&grid, 0.02);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(problem_seed);
        let p = grid.sample_problem(&mut rng);
        let settings = PlannerSettings { extension_batch: batch, ..small_settings() };
        let result = Ask::new(&grid, &mde, p.start(), p.goal()).at(beta, 0.1).planner(&settings).acquisition(&AcquisitionSettings::default()).propose(strategy, seed);
        match result {
            Ok(prop) => {
                assert_valid(&grid, &mde, &prop.trajectory, p.start(), beta, 0.1);
                if strategy != Strategy::Random {
                    prop_assert!(grid.is_goal(prop.trajectory.states.last().unwrap(), p.goal()));
                }
            }
            Err(PlanningError::NoPlan { .. }) => {}
            Err(e) => panic!("unexpected error {e}"),
        }
        let out = Ask::new(&grid, &mde, p.start(), p.goal()).at(beta, 0.1).planner(&settings).plan(seed).unwrap();
        if let Some(t) = out.trajectory {
            assert_valid(&grid, &mde, &t, p.start(), beta, 0.1);
        }
    }

    #[test]
    fn every_kinematic_edge_is_allowed_and_inside(
        seed in any::<u64>(),
        beta in -1.0f64..3.0,
        problem_seed in any::<u64>(),
        batch in 1usize..40,
    ) {
        let domain = walled_kinematic();
        let mde = BumpModel { centre: [0.25, 0.5], height: 0.5, sigma: 0.02 };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(problem_seed);
        let p = domain.sample_problem(&mut rng);
        let settings = PlannerSettings { extension_batch: batch, ..small_settings() };
        let mut run_rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let out = Ask::new(&domain, &mde, p.start(), p.goal()).at(beta, 0.1).planner(&settings).rrt(&mut run_rng).unwrap();
        prop_assert!(out.extensions <= settings.max_extensions);
        if let Some(t) = out.trajectory {
            assert_valid(&domain, &mde, &t, p.start(), beta, 0.1);
            prop_assert!(domain.is_goal(t.states.last().unwrap(), p.goal()));
        }
    }
}

use rand::SeedableRng;

#[test]
fn a_test_beta_plan_never_takes_an_x_move_from_ice() {
    let grid = IcyGridworld::default_layout();
    let mde = IceModel::new(&grid, 0.01);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut found = 0;
    for seed in 0..40 {
        let p = grid.sample_problem(&mut rng);
        let out = Ask::new(&grid, &mde, p.start(), p.goal())
            .plan(seed)
            .unwrap();
        let Some(t) = out.trajectory else { continue };
        found += 1;
        for (s, a) in t.states.iter().zip(&t.actions) {
            let on_ice = mde.is_ice(s[0] as usize, s[1] as usize);
            assert!(!(on_ice && a[0] != 0.0), "x-move {a:?} from ice cell {s:?}");
        }
    }
    assert_eq!(found, 40, "every cell is reachable without x-moves on ice");
}

#[test]
fn without_the_ice_knowledge_the_plan_crosses_the_ice() {
    // The control for the test above: along an ice row the direct path is all x-moves on ice.
    let grid = IcyGridworld::default_layout();
    let (start, goal) = ([2.0, 2.0], [9.0, 2.0]);
    let trusting = ConstantModel {
        mu: 0.0,
        sigma: 0.01,
    };
    let t = Ask::new(&grid, &trusting, &start, &goal)
        .plan(3)
        .unwrap()
        .trajectory
        .unwrap();
    assert!(t.actions.iter().any(|a| a[0] != 0.0));
    let knowing = IceModel::new(&grid, 0.01);
    let t = Ask::new(&grid, &knowing, &start, &goal)
        .plan(3)
        .unwrap()
        .trajectory
        .unwrap();
    assert!(t.len() > 7, "the plan must leave the ice row to move in x");
}

#[test]
fn active_picks_the_argmin_of_the_candidates() {
    let grid = IcyGridworld::default_layout();
    let acq = AcquisitionSettings::default();
    for seed in 0..5 {
        let p = Ask::new(&grid, &SlopeModel, &[0.0, 0.0], &[11.0, 11.0])
            .at(0.0, 0.1)
            .acquisition(&acq)
            .propose(Strategy::Active, seed)
            .unwrap();
        assert!(p.candidates.len() > 1);
        let min = p
            .candidates
            .iter()
            .map(|c| c.alpha)
            .fold(f64::INFINITY, f64::min);
        assert_eq!(p.alpha, min);
        assert_eq!(p.candidates[p.chosen_index].alpha, p.alpha);
        assert_eq!(p.candidates[p.chosen_index].length, p.trajectory.len());
        let (steps, alpha) = acq.score(&p.trajectory, 0.1);
        assert_eq!((steps, alpha), (p.alpha_step.clone(), p.alpha));
        assert!(grid.is_goal(p.trajectory.states.last().unwrap(), &[11.0, 11.0]));
    }
}

#[test]
fn goal_conditioned_picks_some_goal_reaching_candidate() {
    let grid = IcyGridworld::default_layout();
    let acq = AcquisitionSettings::default();
    let mut not_argmin = 0;
    for seed in 0..10 {
        let p = Ask::new(&grid, &SlopeModel, &[0.0, 0.0], &[11.0, 11.0])
            .at(0.0, 0.1)
            .acquisition(&acq)
            .propose(Strategy::GoalConditioned, seed)
            .unwrap();
        assert!(grid.is_goal(p.trajectory.states.last().unwrap(), &[11.0, 11.0]));
        assert_eq!(p.candidates[p.chosen_index].alpha, p.alpha);
        assert_eq!(acq.score(&p.trajectory, 0.1).1, p.alpha);
        let min = p
            .candidates
            .iter()
            .map(|c| c.alpha)
            .fold(f64::INFINITY, f64::min);
        if p.alpha > min {
            not_argmin += 1;
        }
    }
    assert!(not_argmin > 0, "a random choice is not always the argmin");
}

#[test]
fn random_ignores_the_goal() {
    let grid = IcyGridworld::default_layout();
    let mde = ConstantModel {
        mu: 0.0,
        sigma: 0.01,
    };
    let start = [5.0, 5.0];
    let a = Ask::new(&grid, &mde, &start, &[5.0, 4.0])
        .propose(Strategy::Random, 11)
        .unwrap();
    let b = Ask::new(&grid, &mde, &start, &[0.0, 11.0])
        .propose(Strategy::Random, 11)
        .unwrap();
    assert_eq!(
        a.trajectory, b.trajectory,
        "the goal does not change the rollout"
    );
    assert_eq!(
        a.trajectory.len(),
        grid.rollout_length(),
        "no early stop when every move is fine"
    );
    assert_eq!((a.candidates.len(), a.chosen_index, a.runs), (1, 0, 1));
    assert_valid(&grid, &mde, &a.trajectory, &start, 2.0, 0.1);
}

#[test]
fn random_stops_early_where_no_move_is_trusted() {
    // From [2, 2] (ice), only the y-moves are inside; with a tiny try budget the rollout may stop,
    // but it never takes an x-move on ice and fails only if the first step is impossible.
    let grid = IcyGridworld::default_layout();
    let mde = IceModel::new(&grid, 0.01);
    for seed in 0..20 {
        let settings = PlannerSettings {
            random_action_tries: 2,
            ..Default::default()
        };
        match Ask::new(&grid, &mde, &[2.0, 2.0], &[0.0, 0.0])
            .planner(&settings)
            .propose(Strategy::Random, seed)
        {
            Ok(p) => {
                assert!(p.trajectory.len() <= grid.rollout_length());
                assert_valid(&grid, &mde, &p.trajectory, &[2.0, 2.0], 2.0, 0.1);
            }
            Err(PlanningError::NoPlan { extensions }) => assert_eq!(extensions, 2),
            Err(e) => panic!("unexpected error {e}"),
        }
    }
}

#[test]
fn no_plan_when_nothing_is_trusted() {
    let grid = IcyGridworld::default_layout();
    let distrust = ConstantModel {
        mu: 1.0,
        sigma: 0.1,
    };
    let settings = PlannerSettings {
        max_extensions: 300,
        ..Default::default()
    };
    for strategy in [Strategy::Active, Strategy::GoalConditioned] {
        let err = Ask::new(&grid, &distrust, &[0.0, 0.0], &[3.0, 0.0])
            .at(0.0, 0.1)
            .planner(&settings)
            .propose(strategy, 1)
            .unwrap_err();
        assert_eq!(
            err,
            PlanningError::NoPlan { extensions: 300 },
            "one failed run is final"
        );
    }
    let err = Ask::new(&grid, &distrust, &[0.0, 0.0], &[3.0, 0.0])
        .at(0.0, 0.1)
        .planner(&settings)
        .propose(Strategy::Random, 1)
        .unwrap_err();
    assert_eq!(
        err,
        PlanningError::NoPlan {
            extensions: settings.random_action_tries
        }
    );
    let patient = PlannerSettings {
        max_failed_runs: 3,
        ..settings
    };
    let err = Ask::new(&grid, &distrust, &[0.0, 0.0], &[3.0, 0.0])
        .at(0.0, 0.1)
        .planner(&patient)
        .propose(Strategy::Active, 1)
        .unwrap_err();
    assert_eq!(err, PlanningError::NoPlan { extensions: 900 });
    let out = Ask::new(&grid, &distrust, &[0.0, 0.0], &[3.0, 0.0])
        .at(0.0, 0.1)
        .planner(&settings)
        .plan(1)
        .unwrap();
    assert_eq!(
        (out.trajectory, out.extensions, out.tree_size),
        (None, 300, 1)
    );
}

#[test]
fn kinematic_edges_never_cross_the_wall() {
    let domain = walled_kinematic();
    let mde = ConstantModel {
        mu: 0.0,
        sigma: 0.01,
    };
    let (start, goal) = ([0.1, 0.1], [0.9, 0.9]);
    for seed in 0..4 {
        let p = Ask::new(&domain, &mde, &start, &goal)
            .propose(Strategy::Active, seed)
            .unwrap();
        let t = &p.trajectory;
        assert_valid(&domain, &mde, t, &start, 2.0, 0.1);
        assert!(domain.is_goal(t.states.last().unwrap(), &goal));
        for w in t.states.windows(2) {
            for k in 0..=100 {
                let u = k as f64 / 100.0;
                let q = [
                    w[0][0] + u * (w[1][0] - w[0][0]),
                    w[0][1] + u * (w[1][1] - w[0][1]),
                ];
                assert!(
                    !domain.in_collision(&q),
                    "edge {:?} → {:?} hits the wall",
                    w[0],
                    w[1]
                );
            }
        }
        // It has to go through the gap: some edge passes x ∈ [0.45, 0.5] (the wall's span)
        // with y in the gap.
        let through_gap = t.states.windows(2).any(|w| {
            (0..=100).any(|k| {
                let u = k as f64 / 100.0;
                let x = w[0][0] + u * (w[1][0] - w[0][0]);
                let y = w[0][1] + u * (w[1][1] - w[0][1]);
                (0.45..=0.5).contains(&x) && (0.4..=0.6).contains(&y)
            })
        });
        assert!(through_gap, "{:?}", t.states);
    }
}

#[test]
fn same_seed_same_proposal() {
    let grid = IcyGridworld::default_layout();
    let mde = IceModel::new(&grid, 0.05);
    for strategy in [
        Strategy::Active,
        Strategy::GoalConditioned,
        Strategy::Random,
    ] {
        let run = |seed| {
            Ask::new(&grid, &mde, &[0.0, 0.0], &[11.0, 11.0])
                .at(0.5, 0.2)
                .propose(strategy, seed)
                .unwrap()
        };
        assert_eq!(run(42), run(42));
        assert_ne!(run(42).trajectory, run(43).trajectory);
    }
    let domain = walled_kinematic();
    let mde = BumpModel {
        centre: [0.3, 0.5],
        height: 0.5,
        sigma: 0.02,
    };
    let run = |seed| {
        Ask::new(&domain, &mde, &[0.1, 0.5], &[0.9, 0.5])
            .at(1.0, 0.1)
            .plan(seed)
            .unwrap()
    };
    assert_eq!(run(5), run(5));
}

#[test]
fn the_model_sees_each_gridworld_pair_once_per_proposal_in_batches() {
    let grid = IcyGridworld::default_layout();
    let inner = IceModel::new(&grid, 0.02);
    let mde = Counting {
        inner: &inner,
        calls: AtomicUsize::new(0),
        points: AtomicUsize::new(0),
    };
    let p = Ask::new(&grid, &mde, &[0.0, 0.0], &[11.0, 11.0])
        .acquisition(&AcquisitionSettings::default())
        .propose(Strategy::Active, 9)
        .unwrap();
    let (calls, points) = (mde.calls.into_inner(), mde.points.into_inner());
    assert_eq!(points, p.model_points);
    assert!(
        points <= 12 * 12 * 4,
        "{points} points for 576 distinct pairs"
    );
    assert!(
        calls * 4 < p.extensions,
        "{calls} calls for {} extensions",
        p.extensions
    );
}

#[test]
fn inputs_and_settings_are_checked_by_name() {
    let grid = IcyGridworld::default_layout();
    let mde = ConstantModel {
        mu: 0.0,
        sigma: 0.01,
    };
    let s = PlannerSettings::default();
    let field = |r: Result<Proposal, PlanningError>| match r {
        Err(
            PlanningError::InvalidInput { field, .. }
            | PlanningError::InvalidSettings { field, .. },
        ) => field,
        other => panic!("expected a field error, got {other:?}"),
    };
    let go = |start: &[f64], goal: &[f64], beta, d_max, s: &PlannerSettings| {
        Ask::new(&grid, &mde, start, goal)
            .at(beta, d_max)
            .planner(s)
            .propose(Strategy::Active, 0)
    };
    assert_eq!(field(go(&[0.5, 0.0], &[3.0, 3.0], 0.0, 0.1, &s)), "start");
    assert_eq!(field(go(&[0.0, 0.0], &[3.0], 0.0, 0.1, &s)), "goal");
    assert_eq!(field(go(&[0.0, 0.0], &[0.0, 0.0], 0.0, 0.1, &s)), "goal");
    assert_eq!(
        field(go(&[0.0, 0.0], &[3.0, 3.0], f64::NAN, 0.1, &s)),
        "beta"
    );
    assert_eq!(field(go(&[0.0, 0.0], &[3.0, 3.0], 0.0, 0.0, &s)), "d_max");
    let bad = PlannerSettings {
        goal_bias: 1.5,
        ..s.clone()
    };
    assert_eq!(
        field(go(&[0.0, 0.0], &[3.0, 3.0], 0.0, 0.1, &bad)),
        "goal_bias"
    );
    let bad = PlannerSettings {
        max_extensions: 0,
        ..s.clone()
    };
    assert_eq!(
        field(go(&[0.0, 0.0], &[3.0, 3.0], 0.0, 0.1, &bad)),
        "max_extensions"
    );
    // A test-time plan from the goal itself is found, and empty.
    let out = Ask::new(&grid, &mde, &[3.0, 3.0], &[3.0, 3.0])
        .planner(&s)
        .plan(0)
        .unwrap();
    assert_eq!(out.trajectory.map(|t| t.len()), Some(0));
}

/// A kinematic world cut in two by a wall: the goal side cannot be reached.
fn walled_off() -> Kinematic {
    Kinematic::new(KinematicParams {
        obstacles: vec![BoxObstacle {
            low: vec![0.45, 0.0],
            high: vec![0.55, 1.0],
        }],
        ..KinematicParams::default()
    })
    .unwrap()
}

#[test]
fn a_search_stops_at_its_deadline_with_the_extensions_spent() {
    let domain = walled_off();
    let mde = ConstantModel {
        mu: 0.0,
        sigma: 0.0,
    };
    let settings = PlannerSettings {
        max_extensions: 200_000,
        ..PlannerSettings::default()
    };
    let started = std::time::Instant::now();
    let budget = Budget::until(started + std::time::Duration::from_millis(100));
    let err = Ask::new(&domain, &mde, &[0.1, 0.5], &[0.9, 0.5])
        .at(0.0, 0.1)
        .planner(&settings)
        .acquisition(&AcquisitionSettings::default())
        .within(&budget)
        .propose(Strategy::Active, 3)
        .unwrap_err();
    let PlanningError::Stopped { reason, extensions } = err else {
        panic!("expected Stopped, got {err:?}");
    };
    assert_eq!(reason, Stop::Deadline);
    assert!(extensions > 0 && extensions < 200_000, "{extensions}");
    assert!(started.elapsed() < std::time::Duration::from_secs(2));
    // The same search without a budget spends all of it and finds no plan.
    let small = PlannerSettings {
        max_extensions: 300,
        ..settings
    };
    let out = Ask::new(&domain, &mde, &[0.1, 0.5], &[0.9, 0.5])
        .at(0.0, 0.1)
        .planner(&small)
        .within(&Budget::unlimited())
        .plan(3)
        .unwrap();
    assert!(out.trajectory.is_none());
    assert_eq!(out.extensions, 300);
}

#[test]
fn a_cancelled_search_stops_before_its_next_round() {
    let domain = walled_off();
    let mde = ConstantModel {
        mu: 0.0,
        sigma: 0.0,
    };
    let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let budget = Budget::unlimited().cancelled_by(flag);
    for strategy in [Strategy::Active, Strategy::Random] {
        let err = Ask::new(&domain, &mde, &[0.1, 0.5], &[0.9, 0.5])
            .at(0.0, 0.1)
            .acquisition(&AcquisitionSettings::default())
            .within(&budget)
            .propose(strategy, 3)
            .unwrap_err();
        assert_eq!(
            err,
            PlanningError::Stopped {
                reason: Stop::Cancelled,
                extensions: 0
            },
            "{strategy}"
        );
    }
}

/// Runs grown together give exactly the outcomes they give one at a time (each depends only on
/// its own random stream and the models' answers), with fewer calls to the deviation model.
#[test]
fn runs_grown_together_grow_the_trees_they_grow_alone() {
    use super::rrt::{grow, grow_together, seeded_rng};
    let grid = IcyGridworld::default_layout();
    let kin = walled_kinematic();
    let ice = IceModel::new(&grid, 0.02);
    let bump = BumpModel {
        centre: [0.3, 0.5],
        height: 0.4,
        sigma: 0.02,
    };
    type Case<'a> = (&'a dyn Domain, &'a dyn DeviationModel, [f64; 2], [f64; 2]);
    let cases: [Case<'_>; 2] = [
        (&grid, &ice, [0.0, 0.0], [11.0, 11.0]),
        (&kin, &bump, [0.1, 0.1], [0.9, 0.9]),
    ];
    for (domain, model, start, goal) in cases {
        let settings =
            PlanningSettings::new(small_settings(), AcquisitionSettings::default()).unwrap();
        let checked = Problem::new(domain, start.to_vec(), goal.to_vec()).unwrap();
        let planner = Planner::new(domain, model, &settings);
        let problem = planner.task(&checked, Precondition::new(1.0, 0.1).unwrap());
        let alone_model = Counting {
            inner: model,
            calls: AtomicUsize::new(0),
            points: AtomicUsize::new(0),
        };
        let mut cache = ModelCache::new(&alone_model, domain.feature_dim());
        let alone: Vec<RrtOutcome> = (1..=6)
            .map(|run| {
                let mut rng = seeded_rng(7, run);
                grow(problem, &mut cache, &mut rng, &Budget::unlimited()).unwrap()
            })
            .collect();
        let together_model = Counting {
            inner: model,
            calls: AtomicUsize::new(0),
            points: AtomicUsize::new(0),
        };
        let mut cache = ModelCache::new(&together_model, domain.feature_dim());
        let rngs = (1..=6).map(|run| seeded_rng(7, run)).collect();
        let together = grow_together(problem, &mut cache, rngs, &Budget::unlimited()).unwrap();
        assert_eq!(together.len(), alone.len());
        assert!(alone.iter().any(|o| o.trajectory.is_some()));
        for (a, t) in alone.iter().zip(&together) {
            assert_eq!(a.trajectory, t.trajectory, "{}", domain.kind());
            assert_eq!(a.extensions, t.extensions);
            assert_eq!(a.tree_size, t.tree_size);
        }
        let (alone_calls, together_calls) = (
            alone_model.calls.into_inner(),
            together_model.calls.into_inner(),
        );
        assert!(
            together_calls < alone_calls,
            "{}: {together_calls} calls together, {alone_calls} alone",
            domain.kind()
        );
    }
}

/// A custom domain that declares no rollout length rolls out as many random steps as a plan
/// for the same problem has; one that declares it rolls out that many.
#[test]
fn random_rollouts_without_a_declared_length_are_as_long_as_a_plan() {
    use crate::domain::{CustomDomain, CustomParams, LinearModel, Space};
    use std::sync::Arc;
    let space = |lo: f64, hi: f64| Space {
        names: vec!["a".into(), "b".into()],
        low: vec![lo; 2],
        high: vec![hi; 2],
        values: None,
    };
    let (st, ac) = (space(0.0, 1.0), space(-0.1, 0.1));
    let eye = vec![vec![1.0, 0.0], vec![0.0, 1.0]];
    let domain = |rollout_length: Option<usize>| {
        let model = LinearModel::new(eye.clone(), eye.clone(), vec![0.0; 2], &st, &ac).unwrap();
        CustomDomain::new(
            CustomParams::plane(st.clone(), ac.clone(), rollout_length),
            Arc::new(model),
        )
        .unwrap()
    };
    let trusted = ConstantModel {
        mu: 0.0,
        sigma: 0.01,
    };
    let proposal = |strategy, d: &CustomDomain, seed| {
        Ask::new(d, &trusted, &[0.1, 0.1], &[0.35, 0.1])
            .at(0.0, 0.1)
            .planner(&small_settings())
            .acquisition(&AcquisitionSettings::default())
            .propose(strategy, seed)
            .unwrap()
    };
    let measured = domain(None);
    for seed in 0..5 {
        let p = proposal(Strategy::Random, &measured, seed);
        let plan = proposal(Strategy::GoalConditioned, &measured, seed);
        // The goal is 0.25 away, at most 0.14 a step: plans take a few steps, never 20.
        assert!(
            (2..=10).contains(&p.trajectory.len()),
            "seed {seed}: {} random steps",
            p.trajectory.len()
        );
        let longest = plan.candidates.iter().map(|c| c.length).max().unwrap();
        assert!(p.trajectory.len() <= longest.max(2) * 2, "seed {seed}");
        assert_eq!(p.runs, 2);
    }
    let declared = proposal(Strategy::Random, &domain(Some(20)), 0);
    assert_eq!((declared.trajectory.len(), declared.runs), (20, 1));
}

#[test]
fn a_relaxed_proposal_is_planned_at_the_first_beta_of_the_ladder_with_a_plan() {
    let grid = IcyGridworld::default_layout();
    // μ + βσ < d_max = 0.1 holds for β < −1: the ladder from 1.5 to −2 (1.5, 0.625, −0.25,
    // −1.125, −2) first finds a plan at −1.125.
    let doubtful = ConstantModel {
        mu: 0.15,
        sigma: 0.05,
    };
    let settings = PlannerSettings {
        max_extensions: 300,
        ..Default::default()
    };
    let betas = relaxation_ladder(1.5, -2.0);
    let relaxed = |mde: &dyn DeviationModel, betas: &[f64]| {
        Ask::new(&grid, mde, &[0.0, 0.0], &[3.0, 0.0])
            .at(0.0, 0.1)
            .planner(&settings)
            .within(&Budget::unlimited())
            .propose_relaxing(Strategy::Active, betas, 1)
    };
    let p = relaxed(&doubtful, &betas).unwrap();
    assert_eq!(p.beta, betas[3]);
    assert!(
        p.trajectory
            .mu
            .iter()
            .zip(&p.trajectory.sigma)
            .all(|(m, s)| m + p.beta * s < 0.1)
    );
    let direct = Ask::new(&grid, &doubtful, &[0.0, 0.0], &[3.0, 0.0])
        .at(betas[3], 0.1)
        .planner(&settings)
        .propose(Strategy::Active, 1)
        .unwrap();
    assert_eq!(p.trajectory, direct.trajectory, "the same search at that β");
    assert_eq!(
        p.extensions,
        3 * 300 + direct.extensions,
        "the three failed attempts count"
    );
    // Only the schedule's β: no plan, as without relaxation.
    assert_eq!(
        relaxed(&doubtful, &betas[..1]).unwrap_err(),
        PlanningError::NoPlan { extensions: 300 }
    );
    // Nothing trusted at any β: no plan, every attempt counted.
    let distrust = ConstantModel {
        mu: 1.0,
        sigma: 0.1,
    };
    assert_eq!(
        relaxed(&distrust, &betas).unwrap_err(),
        PlanningError::NoPlan {
            extensions: 5 * 300
        }
    );
}

/// A 5 × 5 map's learner (see [`WallGapsModel`]) whose wall has one gap, in row 2, the way into
/// it doubtful.
fn one_gap() -> WallGapsModel {
    WallGapsModel {
        doubtful: vec![(1.0, 2.0)],
        through: vec![(2.0, 2.0)],
    }
}

#[test]
fn a_bottleneck_probe_executes_the_gap_that_the_asked_problem_does_not_need() {
    let grid = IcyGridworld::new(&["..#..", "..#..", ".....", "..#..", "..#.."]).unwrap();
    let model = one_gap();
    // The asked problem stays on the left of the wall; the training β is the test β (late in
    // learning), so no candidate may cross the doubtful move.
    let ask = |kind| {
        Ask::new(&grid, &model, &[0.0, 0.0], &[0.0, 4.0])
            .planner(&small_settings())
            .acquisition(&AcquisitionSettings {
                kind,
                ..Default::default()
            })
            .propose(Strategy::Active, 3)
            .unwrap()
    };
    let into_gap = |t: &Trajectory| {
        t.states
            .iter()
            .zip(&t.actions)
            .any(|(s, a)| s == &[1.0, 2.0] && a == &[1.0, 0.0])
    };
    let paper = ask(AcquisitionKind::Lcb);
    assert!(!into_gap(&paper.trajectory), "{:?}", paper.trajectory);
    assert!(grid.is_goal(paper.trajectory.states.last().unwrap(), &[0.0, 4.0]));
    let probing = ask(AcquisitionKind::Bottleneck);
    assert!(into_gap(&probing.trajectory), "{:?}", probing.trajectory);
    // It is a probe: the way there inside the precondition, the gap's move last, reported as
    // the last of the candidates and chosen for its value (negated as `α`).
    let t = &probing.trajectory;
    assert_eq!(t.actions.last(), Some(&vec![1.0, 0.0]));
    assert_eq!(t.states[t.len() - 1], vec![1.0, 2.0]);
    assert!((0..t.len() - 1).all(|k| t.mu[k] + 2.0 * t.sigma[k] < 0.1));
    assert_eq!(probing.chosen_index, probing.candidates.len() - 1);
    assert!(probing.alpha < 0.0, "{}", probing.alpha);
    // The same seed, the same probe.
    assert_eq!(ask(AcquisitionKind::Bottleneck), probing);
}

/// Trusted (μ 0) where the state's x feature lies on its side of the middle, else μ 1.
struct HalfModel {
    left: bool,
}

impl DeviationModel for HalfModel {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        features
            .chunks(dim)
            .map(|f| {
                let trusted = (f[0] < 0.5) == self.left;
                (if trusted { 0.0 } else { 1.0 }, 0.001)
            })
            .collect()
    }
}

/// Plans from the left of the open kinematic domain to its right at β 2, d_max 0.1, stepping
/// with `models` (each with the domain's own dynamics and the given deviation model and cost).
fn plan_left_to_right(models: &[(&dyn DeviationModel, f64)], seed: u64) -> RrtOutcome {
    let domain = Kinematic::new(KinematicParams::default()).unwrap();
    let problem = Problem::new(&domain, vec![0.1, 0.5], vec![0.9, 0.5]).unwrap();
    let settings = PlanningSettings::new(small_settings(), AcquisitionSettings::default()).unwrap();
    let models: Vec<PlanModel<'_>> = models
        .iter()
        .map(|&(deviation, cost)| PlanModel {
            dynamics: domain.dynamics(),
            deviation,
            cost,
        })
        .collect();
    let precondition = Precondition::new(2.0, 0.1).unwrap();
    Planner::new(&domain, models[0].deviation, &settings)
        .plan_across(&problem, precondition, &models, seed)
        .unwrap()
}

/// Neither half's model trusts a way across; together they do, each step relying on the
/// model whose half it starts in.
#[test]
fn a_plan_across_models_crosses_where_neither_model_alone_does() {
    let (left, right) = (HalfModel { left: true }, HalfModel { left: false });
    for seed in 0..5 {
        assert!(
            plan_left_to_right(&[(&left, 1.0)], seed)
                .trajectory
                .is_none()
        );
        assert!(
            plan_left_to_right(&[(&right, 1.0)], seed)
                .trajectory
                .is_none()
        );
        let both = plan_left_to_right(&[(&left, 1.0), (&right, 3.0)], seed);
        let t = both.trajectory.as_ref().expect("a plan across both models");
        assert_eq!(both.step_models.len(), t.len());
        for ((s, _, _), &m) in t.steps().zip(&both.step_models) {
            assert_eq!(m, if s[0] < 0.5 { 0 } else { 1 }, "step from {s:?}");
        }
        assert!(both.model_calls.iter().all(|&c| c > 0));
        assert_eq!(both.model_calls.iter().sum::<usize>(), both.dynamics_calls);
    }
}

/// Where a cheap model and a dear one both trust a step, the step relies on the cheap one,
/// whatever order the models are given in; the dear one is asked only about the rest.
#[test]
fn each_step_relies_on_the_cheapest_model_that_trusts_it() {
    let (left, everywhere) = (
        HalfModel { left: true },
        ConstantModel {
            mu: 0.0,
            sigma: 0.001,
        },
    );
    for seed in 0..5 {
        let out = plan_left_to_right(&[(&everywhere, 10.0), (&left, 1.0)], seed);
        let t = out.trajectory.as_ref().expect("a plan");
        for ((s, _, _), &m) in t.steps().zip(&out.step_models) {
            assert_eq!(m, if s[0] < 0.5 { 1 } else { 0 }, "step from {s:?}");
        }
        // Alone, the dear model is asked about every action; after the cheap one, only
        // about those on the right.
        let alone = plan_left_to_right(&[(&everywhere, 10.0)], seed);
        assert!(alone.trajectory.is_some());
        assert!(
            out.model_calls[0] < out.model_calls[1],
            "{:?}",
            out.model_calls
        );
    }
}

/// With the domain's model and the planner's deviation model alone, a plan across models is
/// the plan, to the last extension and model call — on a continuous domain and on the
/// gridworld, whose first model also prefetches.
#[test]
fn a_plan_across_one_model_is_the_plan() {
    let walled = walled_kinematic();
    let bump = BumpModel {
        centre: [0.3, 0.5],
        height: 1.0,
        sigma: 0.01,
    };
    let grid = IcyGridworld::default_layout();
    let ice = IceModel::new(&grid, 0.02);
    /// A domain, its deviation model, a start and a goal.
    type Case<'a> = (&'a dyn Domain, &'a dyn DeviationModel, [[f64; 2]; 2]);
    let cases: [Case<'_>; 2] = [
        (&walled, &bump, [[0.1, 0.2], [0.9, 0.8]]),
        (&grid, &ice, [[0.0, 0.0], [6.0, 4.0]]),
    ];
    for (domain, mde, [start, goal]) in cases {
        let settings =
            PlanningSettings::new(small_settings(), AcquisitionSettings::default()).unwrap();
        let problem = Problem::new(domain, start.to_vec(), goal.to_vec()).unwrap();
        let precondition = Precondition::new(2.0, 0.1).unwrap();
        let planner = Planner::new(domain, mde, &settings);
        let one = [PlanModel {
            dynamics: domain.dynamics(),
            deviation: mde,
            cost: 1.0,
        }];
        for seed in 0..5 {
            let plan = planner.plan(&problem, precondition, seed).unwrap();
            let across = planner
                .plan_across(&problem, precondition, &one, seed)
                .unwrap();
            assert_eq!(across, plan);
            if let Some(t) = &plan.trajectory {
                assert_eq!(plan.step_models, vec![0; t.len()]);
            }
        }
    }
}

/// A model without a positive cost, or no model at all, is the caller's mistake.
#[test]
fn a_plan_across_models_needs_models_with_costs() {
    let domain = Kinematic::new(KinematicParams::default()).unwrap();
    let problem = Problem::new(&domain, vec![0.1, 0.5], vec![0.9, 0.5]).unwrap();
    let settings = PlanningSettings::default();
    let model = ConstantModel {
        mu: 0.0,
        sigma: 0.01,
    };
    let planner = Planner::new(&domain, &model, &settings);
    let pre = Precondition::new(2.0, 0.1).unwrap();
    let err = planner.plan_across(&problem, pre, &[], 0).unwrap_err();
    assert!(err.to_string().contains("models"), "{err}");
    let free = PlanModel {
        dynamics: domain.dynamics(),
        deviation: &model,
        cost: 0.0,
    };
    let err = planner.plan_across(&problem, pre, &[free], 0).unwrap_err();
    assert!(err.to_string().contains("cost"), "{err}");
}

/// μ rises across the first state feature and reaches `d_max` = 0.1 at 0.5; σ is 0.05, or
/// 0.005 within 0.1 (in the state features) of a pending state-action: a model `spread` can
/// fantasise with.
struct Doubtful;

impl DeviationModel for Doubtful {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        self.predict_fantasised(features, &[], dim)
    }

    fn predict_fantasised(&self, features: &[f64], pending: &[f64], dim: usize) -> Vec<(f64, f64)> {
        features
            .chunks(dim)
            .map(|x| {
                let near = pending
                    .chunks(dim)
                    .any(|p| (p[0] - x[0]).hypot(p[1] - x[1]) < 0.1);
                (0.2 * x[0], if near { 0.005 } else { 0.05 })
            })
            .collect()
    }
}

/// With the domain's model alone, a proposal across models is the proposal — the same
/// candidates, values (by `spread`, which this model can fantasise with), choice and calls —
/// its steps all relying on that model.
#[test]
fn a_proposal_across_one_model_is_the_proposal() {
    let domain = Kinematic::new(KinematicParams::default()).unwrap();
    // Trusted left of x = 0.375 at β 0.5.
    let problem = Problem::new(&domain, vec![0.1, 0.1], vec![0.3, 0.9]).unwrap();
    let spread = AcquisitionSettings {
        kind: AcquisitionKind::Spread,
        ..AcquisitionSettings::default()
    };
    let settings = PlanningSettings::new(small_settings(), spread).unwrap();
    let planner = Planner::new(&domain, &Doubtful, &settings);
    let ladder = [Precondition::new(0.5, 0.1).unwrap()];
    let one = [PlanModel {
        dynamics: domain.dynamics(),
        deviation: &Doubtful,
        cost: 1.0,
    }];
    for seed in 0..5 {
        let single = planner
            .propose_relaxing(Strategy::Active, &problem, &ladder, seed)
            .unwrap();
        assert_eq!(single.valued_by, AcquisitionKind::Spread);
        let mut across = planner
            .propose_across(Strategy::Active, &problem, &ladder, &one, &[&[]], seed)
            .unwrap();
        assert_eq!(across.step_models, vec![0; across.trajectory.len()]);
        across.step_models.clear();
        assert_eq!(across, single);
    }
}

/// Neither half's model trusts a way across; a proposal across both does cross, each step
/// relying on the model whose half it starts in; a random rollout is the domain model's alone.
#[test]
fn a_proposal_across_models_crosses_where_neither_model_alone_does() {
    let domain = Kinematic::new(KinematicParams::default()).unwrap();
    let problem = Problem::new(&domain, vec![0.1, 0.5], vec![0.9, 0.5]).unwrap();
    let settings = PlanningSettings::new(small_settings(), AcquisitionSettings::default()).unwrap();
    let (left, right) = (HalfModel { left: true }, HalfModel { left: false });
    let ladder = [Precondition::new(2.0, 0.1).unwrap()];
    let planner = Planner::new(&domain, &left, &settings);
    let models = [
        PlanModel {
            dynamics: domain.dynamics(),
            deviation: &right,
            cost: 3.0,
        },
        PlanModel {
            dynamics: domain.dynamics(),
            deviation: &left,
            cost: 1.0,
        },
    ];
    for seed in 0..5 {
        assert!(matches!(
            planner.propose_relaxing(Strategy::Active, &problem, &ladder, seed),
            Err(PlanningError::NoPlan { .. })
        ));
        for strategy in [Strategy::Active, Strategy::GoalConditioned] {
            let p = planner
                .propose_across(strategy, &problem, &ladder, &models, &[&[], &[]], seed)
                .unwrap();
            let end = p.trajectory.states.last().unwrap();
            assert!(domain.is_goal(end, problem.goal()), "{end:?}");
            assert_eq!(p.step_models.len(), p.trajectory.len());
            for ((s, _, _), &m) in p.trajectory.steps().zip(&p.step_models) {
                assert_eq!(m, if s[0] < 0.5 { 1 } else { 0 }, "step from {s:?}");
            }
        }
    }
    let err = planner
        .propose_across(Strategy::Random, &problem, &ladder, &models, &[&[], &[]], 0)
        .unwrap_err();
    assert!(err.to_string().contains("strategy"), "{err}");
    let err = planner
        .propose_across(Strategy::Active, &problem, &ladder, &models, &[&[]], 0)
        .unwrap_err();
    assert!(err.to_string().contains("in_flight"), "{err}");
}
