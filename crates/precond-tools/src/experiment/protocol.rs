//! The paper's protocol for one domain: held-out pools, then per strategy × seed the learning
//! iterations (train a batch, wait for the refit, evaluate), all through [`ApiClient`].
//!
//! **Seeds.** Every random choice of the harness comes from a ChaCha8 stream named by
//! `(seed, purpose, i, j)` ([`stream`]). Training and test problems and the simulator's
//! episodes depend on the seed, the iteration and the slot, never on the strategy, so every
//! strategy sees the same problems at a given seed and iteration (common random numbers). The
//! service seeds its own choices from the experiment's seed and the data it has seen.
//!
//! **Held-out transitions.** Before the runs, for every seed `k` a *pool* of transitions is
//! executed in the simulator: half of the trajectories are planned for random problems by the
//! service's prior model (a fresh experiment, which trusts every state-action early on, so the
//! planner goes wherever `f̂` says the goal is: good and bad pours, ice and walls alike) and half
//! are random-action rollouts from the same samplers, all with episodes (leaves) drawn from the
//! pool's own streams. The run of seed `k` is evaluated on the pools of every *other* seed, so
//! no evaluated transition comes from the same episodes or problems as its training data.
//!
//! **Training slots.** A slot samples a problem and asks for a proposal. A `no_plan` answer is
//! recorded and the slot tries a fresh problem, up to `problem_tries` times; only then is it
//! skipped. Retrying keeps every batch at `batch_size` trajectories, which keeps the service's
//! iteration counter (and so its β schedule and its background refits) in step with the
//! harness. Should a slot be skipped anyway, the harness forces a refit at the end of the
//! iteration (and the service's batches then no longer align with the harness's iterations);
//! when a later post completes one of the service's batches mid-iteration, the harness waits
//! for its background fit before the next proposal, so a seed's run repeats exactly.

use super::client::{ApiClient, Proposed};
use super::layouts::Layout;
use super::reference::{self, ClosedLoop, References};
use super::{Config, DomainKind};
use indicatif::ProgressBar;
use precond::api::{ExperimentRequest, PlannedTrajectory};
use precond::settings::{DomainSpec, LearningRequest, MdeRequest};
use precond_core::domain::water_plant::{Motion, Pose, SRC_VOLUME, TGT_VOLUME};
use precond_core::domain::{
    DEFAULT_MAP, Domain, GridFeatures, IcyGridworld, Kinematic, LocalModel, MOVES, Problem,
    Transition, WaterPlant,
};
use precond_core::planning::bottleneck::TrustedGraph;
use precond_core::planning::{Agreement, Strategy, Trajectory};
use precond_core::sim::{ContinuousWorld, Simulated, World};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use std::sync::Arc;
use std::time::Instant;

/// See [`Bench::long_search_factor`].
pub const LONG_SEARCH_FACTOR: u32 = 10;

/// The client-side view of a built-in world: its domain (the model, goal test and samplers)
/// and its simulator, like a robot's own code would hold them.
#[derive(Debug, Clone)]
pub enum Bench {
    /// The icy gridworld on its default map.
    Grid(IcyGridworld),
    /// The water plant in its default scene.
    Plant(WaterPlant),
    /// A continuous world ([`ContinuousWorld`]) and its robot's kinematic model.
    Continuous {
        /// The world.
        world: ContinuousWorld,
        /// The robot's model of it.
        domain: Kinematic,
    },
}

impl Bench {
    /// The world of `kind`: the gridworld on `layout` (default: the documented map), the
    /// water plant in its default scene.
    pub fn new(
        kind: DomainKind,
        layout: Option<&Layout>,
        features: GridFeatures,
    ) -> anyhow::Result<Self> {
        Ok(match kind {
            DomainKind::IcyGridworld => Self::Grid(
                match layout {
                    Some(l) => IcyGridworld::new(&l.map)
                        .map_err(|e| anyhow::anyhow!("layout {}: {e}", l.name))?,
                    None => IcyGridworld::default_layout(),
                }
                .with_features(features),
            ),
            DomainKind::WaterPlant => Self::Plant(WaterPlant::default()),
            DomainKind::Arm | DomainKind::Base | DomainKind::Pusher => {
                let world = match kind {
                    DomainKind::Arm => ContinuousWorld::arm(),
                    DomainKind::Base => ContinuousWorld::base(),
                    _ => ContinuousWorld::pusher(),
                };
                Self::Continuous {
                    domain: world.domain(),
                    world,
                }
            }
        })
    }

    /// A problem of the world's distribution (for a continuous world: one whose start and goal
    /// are states the robot can be in).
    pub fn sample_problem(&self, rng: &mut dyn rand::RngCore) -> Problem {
        match self {
            Self::Continuous { world, domain } => world.sample_problem(domain, rng),
            _ => self.domain().sample_problem(rng),
        }
    }

    /// The oracle's and the baseline's answers to `problem` (see [`reference`]); `None` for
    /// the water plant, whose episodes vary and whose true precondition is not known.
    pub async fn references(
        &self,
        problem: &Problem,
        d_max: f64,
        max_extensions: u32,
        seed: u64,
    ) -> anyhow::Result<Option<References>> {
        Ok(match self {
            Self::Plant(_) => None,
            Self::Grid(g) => {
                let solvable = self.oracle(problem, d_max) == Some(true);
                let mut world = g.world();
                Some(References {
                    oracle_solvable: solvable,
                    // A gridworld plan of exact steps arrives whether executed open or closed
                    // loop.
                    oracle_open_loop: solvable,
                    oracle_closed_loop: solvable,
                    baseline: reference::baseline(
                        world.as_mut(),
                        g,
                        problem,
                        d_max,
                        max_extensions,
                        seed,
                    ),
                })
            }
            Self::Continuous { world, domain } => {
                let (world, domain, problem) = (world.clone(), domain.clone(), problem.clone());
                Some(
                    tokio::task::spawn_blocking(move || {
                        reference::continuous(&world, &domain, &problem, max_extensions, seed)
                    })
                    .await?,
                )
            }
        })
    }

    /// Whether `problem` can be solved inside the *true* precondition (every step's true
    /// deviation below `d_max`): a breadth-first search over the gridworld's true dynamics.
    /// `None` for the water plant, whose episodes vary and whose action space is continuous.
    pub fn oracle(&self, problem: &Problem, d_max: f64) -> Option<bool> {
        let Self::Grid(g) = self else {
            return None;
        };
        let mut world = g.world();
        Some(grid_search(g, problem, |s, m| {
            let next = world.step(s, m);
            (g.deviation(s, m, &next) < d_max).then_some(next)
        }))
    }

    /// Whether `problem` can be solved inside a *learned* precondition: a breadth-first search
    /// over the gridworld's model `f̂`, taking only the moves that `trusted` answers true for
    /// (the service's judgement at test β). The planner plans over exactly these edges, so a
    /// problem solvable here but not planned is the planner's loss, and one the oracle solves
    /// but this does not is the learner's. `None` outside the gridworld.
    pub fn learned_solvable(
        &self,
        problem: &Problem,
        trusted: impl Fn(&[f64], &[f64]) -> bool,
    ) -> Option<bool> {
        let Self::Grid(g) = self else {
            return None;
        };
        Some(grid_search(g, problem, |s, m| {
            trusted(s, m).then(|| g.predict(s, m))
        }))
    }

    /// For a problem the learned precondition does not solve (gridworld), the truly safe moves
    /// it does not trust that would each, trusted alone, make the problem solvable: a move from
    /// a cell the start reaches inside the learned precondition into (by the model) a cell from
    /// which the goal is reached inside it ([`TrustedGraph::opening_moves`], filtered by the
    /// true world). Empty when no single move would do (the problem is further from solvable,
    /// or solvable already); `None` outside the gridworld. What the learner missed is then
    /// attributed: a blocking move that was executed and labelled safe yet is not trusted is
    /// the estimator's loss; one never executed is the choice of executions'.
    pub fn blocking_moves(
        &self,
        problem: &Problem,
        d_max: f64,
        trusted: impl Fn(&[f64], &[f64]) -> bool,
    ) -> Option<Vec<[i64; 4]>> {
        let Self::Grid(g) = self else {
            return None;
        };
        let moves = self.all_state_actions();
        let next: Vec<Vec<f64>> = moves.iter().map(|(s, m)| g.predict(s, m)).collect();
        let ok: Vec<bool> = moves.iter().map(|(s, m)| trusted(s, m)).collect();
        let graph = TrustedGraph::new(g, &moves, &next, &ok);
        let mut world = g.world();
        Some(
            graph
                .opening_moves(problem)
                .unwrap_or_default()
                .into_iter()
                .map(|i| &moves[i])
                .filter(|(s, m)| g.deviation(s, m, &world.step(s, m)) < d_max)
                .map(|(s, m)| move_key(s, m))
                .collect(),
        )
    }

    /// Every state-action of the gridworld the planner may consider (each cell × each move the
    /// model allows; obstacles included, since the model does not know them), for judging a
    /// learned precondition in full. Empty elsewhere.
    pub fn all_state_actions(&self) -> Vec<(Vec<f64>, Vec<f64>)> {
        match self {
            Self::Grid(g) => g.finite_state_actions().unwrap_or_default(),
            _ => Vec::new(),
        }
    }

    /// The domain, with its model run in-process.
    pub fn domain(&self) -> &dyn LocalModel {
        match self {
            Self::Grid(g) => g,
            Self::Plant(p) => p,
            Self::Continuous { domain, .. } => domain,
        }
    }

    /// A fresh simulator.
    pub fn world(&self) -> Box<dyn World> {
        match self {
            Self::Grid(g) => g.world(),
            Self::Plant(p) => p.world(),
            Self::Continuous { world, .. } => world.world(),
        }
    }

    /// How many times the experiment's extension budget a continuous world's *learned*
    /// solvability is searched with, given the run's `factor` (`--long-search`): a test
    /// problem the planner did not solve at the default budget is searched again this much
    /// longer, and counts as solvable inside the learned precondition if that search finds a
    /// plan (the gridworld's is exhaustive instead; the water plant's is not measured). `None`
    /// where it does not apply or `factor` is 0.
    pub fn long_search_factor(&self, factor: u32) -> Option<u32> {
        (matches!(self, Self::Continuous { .. }) && factor > 0).then_some(factor)
    }

    /// Whether plans are executed closed loop too (not the water plant, whose plans are a pour
    /// or two).
    pub fn closed_loop(&self) -> bool {
        !matches!(self, Self::Plant(_))
    }

    /// The action to execute from `actual` for the planned action `a` planned from `planned`:
    /// the water plant keeps a planned action a translation or a rotation after a deviation;
    /// gridworld moves are executed as they are.
    pub fn reanchor(&self, planned: &[f64], a: &[f64], actual: &[f64]) -> Vec<f64> {
        match self {
            Self::Grid(_) | Self::Continuous { .. } => a.to_vec(),
            Self::Plant(p) => p.reanchor(planned, a, actual),
        }
    }
}

/// One executed transition with its true deviation label.
#[derive(Debug, Clone, PartialEq)]
pub struct Labelled {
    /// The transition.
    pub t: Transition,
    /// `d(f̂(s, a), s')`.
    pub deviation: f64,
}

/// A trajectory executed open loop in the simulator.
#[derive(Debug, Clone)]
pub struct Execution {
    /// Its transitions with their labels.
    pub steps: Vec<Labelled>,
    /// The state it ended in.
    pub final_state: Vec<f64>,
}

/// Executes `plan` open loop from its first state in `world` (already reset).
pub fn execute(bench: &Bench, world: &mut dyn World, plan: &PlannedTrajectory) -> Execution {
    let domain = bench.domain();
    let mut s = plan.states[0].clone();
    let mut steps = Vec::with_capacity(plan.actions.len());
    for (k, a) in plan.actions.iter().enumerate() {
        let a = bench.reanchor(&plan.states[k], a, &s);
        let s_next = world.step(&s, &a);
        let deviation = domain.deviation(&s, &a, &s_next);
        steps.push(Labelled {
            t: Transition::new(s.clone(), a, s_next.clone()),
            deviation,
        });
        s = s_next;
    }
    Execution {
        steps,
        final_state: s,
    }
}

/// Kinds of water-plant training trajectories (the paper's Fig. 3), by their first pour.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PourType {
    /// Not a water-plant trajectory, or no pour in it.
    NoPour,
    /// The lip was not above a leaf and at least 98 % of the pour entered the target.
    BelowSuccess,
    /// The lip was not above a leaf and more than 2 % of the pour was spilled.
    BelowSpill,
    /// The lip was above a leaf and at least 98 % entered the target.
    AboveSuccess,
    /// The lip was above a leaf and more than 2 % was spilled.
    AboveSpill,
}

impl PourType {
    /// All kinds, in CSV column order.
    pub const ALL: [PourType; 5] = [
        Self::NoPour,
        Self::BelowSuccess,
        Self::BelowSpill,
        Self::AboveSuccess,
        Self::AboveSpill,
    ];

    /// The snake-case name.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::NoPour => "no_pour",
            Self::BelowSuccess => "below_success",
            Self::BelowSpill => "below_spill",
            Self::AboveSuccess => "above_success",
            Self::AboveSpill => "above_spill",
        }
    }
}

/// Classifies an executed trajectory by its first pour: whether a (nominal) leaf lies below the
/// lip, and whether the pour spilled more than 2 %.
pub fn classify(bench: &Bench, exec: &Execution) -> PourType {
    let Bench::Plant(plant) = bench else {
        return PourType::NoPour;
    };
    let Some(step) = exec
        .steps
        .iter()
        .find(|l| l.t.s_next[SRC_VOLUME] < l.t.s[SRC_VOLUME] - 1e-9)
    else {
        return PourType::NoPour;
    };
    let scene = plant.scene();
    let lip = scene.lip(Pose::from_slice(&step.t.s_next));
    let above = scene.leaves.iter().any(|leaf| {
        leaf.segments().any(|seg| {
            let (lo, hi) = (seg.a.x.min(seg.b.x), seg.a.x.max(seg.b.x));
            if lip.x < lo || lip.x > hi || hi == lo {
                return false;
            }
            let y = seg.a.y + (seg.b.y - seg.a.y) * (lip.x - seg.a.x) / (seg.b.x - seg.a.x);
            y < lip.y
        })
    });
    let poured = step.t.s[SRC_VOLUME] - step.t.s_next[SRC_VOLUME];
    let gained = step.t.s_next[TGT_VOLUME] - step.t.s[TGT_VOLUME];
    let success = gained >= 0.98 * poured - 1e-12;
    match (above, success) {
        (false, true) => PourType::BelowSuccess,
        (false, false) => PourType::BelowSpill,
        (true, true) => PourType::AboveSuccess,
        (true, false) => PourType::AboveSpill,
    }
}

/// Purposes of the random streams (see [`stream`]).
mod purpose {
    pub const POOL_PROBLEM: u64 = 1;
    pub const POOL_EPISODE: u64 = 2;
    pub const TRAIN_PROBLEM: u64 = 3;
    pub const TRAIN_EPISODE: u64 = 4;
    pub const TEST_PROBLEM: u64 = 5;
    pub const TEST_EPISODE: u64 = 6;
}

/// The random stream of `(seed, purpose, i, j)`.
pub fn stream(seed: u64, purpose: u64, i: u64, j: u64) -> ChaCha8Rng {
    use precond_core::seed::splitmix64 as mix;
    let key = mix(mix(mix(mix(seed) ^ purpose) ^ i) ^ j);
    ChaCha8Rng::seed_from_u64(key)
}

/// The request that creates the experiment of one run.
fn experiment_body(
    cfg: &Config,
    bench: &Bench,
    name: String,
    strategy: Strategy,
    seed: u64,
) -> ExperimentRequest {
    let mut d_max = None;
    let domain = match cfg.domain {
        DomainKind::IcyGridworld => match &cfg.layout {
            Some(l) => DomainSpec::IcyGridworld {
                map: l.map.clone(),
                features: cfg.grid_features,
            },
            None => DomainSpec::IcyGridworld {
                map: DEFAULT_MAP.iter().map(|r| r.to_string()).collect(),
                features: cfg.grid_features,
            },
        },
        DomainKind::WaterPlant => DomainSpec::WaterPlant {},
        DomainKind::Arm | DomainKind::Base | DomainKind::Pusher => {
            let Bench::Continuous { world, .. } = bench else {
                unreachable!("a continuous kind builds a continuous bench")
            };
            d_max = Some(world.d_max());
            let p = world.params();
            DomainSpec::Kinematic {
                state_low: p.state_low,
                state_high: p.state_high,
                action_low: p.action_low,
                action_high: p.action_high,
                obstacles: Vec::new(),
                goal_radius: p.goal_radius,
                features: cfg.kinematic_features,
            }
        }
    };
    let learning = LearningRequest::default();
    ExperimentRequest {
        name,
        domain,
        d_max,
        seed,
        models: None,
        mde: MdeRequest {
            noise: cfg.noise.unwrap_or(MdeRequest::default().noise),
            label_cap: cfg.label_cap,
            kernel: cfg.kernel,
            estimator: cfg.estimator.unwrap_or_default(),
            ..MdeRequest::default()
        },
        learning: LearningRequest {
            preset: cfg.preset,
            strategy,
            batch_size: cfg.batch_size as u32,
            iterations: cfg.schedule_iterations.unwrap_or(cfg.iterations as u32),
            n_candidates: cfg.n_candidates,
            max_extensions: cfg.max_extensions,
            relax_beta: cfg.relax_beta,
            c: cfg.c.unwrap_or(learning.c),
            aggregation: cfg.aggregation.unwrap_or(learning.aggregation),
            acquisition: cfg.acquisition,
            batch_diversity: cfg.batch_diversity,
            test_beta: cfg.test_beta.unwrap_or(learning.test_beta),
            calibrate_test_beta: cfg.calibrate_test_beta,
            local_test_margin: cfg.local_test_margin,
            k1: cfg.k1.unwrap_or(learning.k1),
            k2: cfg.k2.unwrap_or(learning.k2),
            warmup_iterations: cfg.warmup_iterations,
            ..learning
        },
    }
}

/// Builds the held-out pool of seed `seed` (see the module docs).
pub async fn build_pool(
    client: &ApiClient,
    bench: &Bench,
    cfg: &Config,
    seed: u64,
) -> anyhow::Result<Vec<Labelled>> {
    let exp = client
        .create_experiment(&experiment_body(
            cfg,
            bench,
            format!("held-out pool, seed {seed}"),
            Strategy::GoalConditioned,
            seed,
        ))
        .await?;
    let mut world = bench.world();
    let mut out = Vec::new();
    for i in 0..cfg.pool_trajectories as u64 {
        let problem = bench.sample_problem(&mut stream(seed, purpose::POOL_PROBLEM, i, 0));
        let strategy = if i % 2 == 0 {
            None
        } else {
            Some(Strategy::Random)
        };
        let Proposed::Trajectory(p) = client
            .propose(exp.id, problem.start(), problem.goal(), None, strategy)
            .await?
        else {
            continue;
        };
        world.reset(&mut stream(seed, purpose::POOL_EPISODE, i, 0));
        let exec = execute(bench, world.as_mut(), &p.content.trajectory);
        out.extend(exec.steps);
    }
    Ok(out)
}

/// Measurements of one iteration of one run.
#[derive(Debug, Clone, Serialize)]
pub struct IterationRecord {
    /// Strategy.
    pub strategy: Strategy,
    /// Seed.
    pub seed: u64,
    /// Iteration (0-based; evaluated after its batch).
    pub iteration: usize,
    /// β of the iteration's proposals (`None` if no proposal was made).
    pub beta_train: Option<f64>,
    /// Training trajectories executed and posted.
    pub train_trajectories: usize,
    /// `no_plan` answers to training proposals.
    pub train_no_plan: usize,
    /// Slots skipped after `problem_tries` `no_plan` answers.
    pub train_skipped: usize,
    /// Proposals made at a β below `beta_train` because none reached the goal at it
    /// (`learning.relax_beta`).
    pub train_relaxed: usize,
    /// Mean number of transitions of the posted trajectories.
    pub mean_traj_length: Option<f64>,
    /// Posted trajectories that ended in a goal state.
    pub train_goal_reached: usize,
    /// Posted transitions with a true deviation of at least `d_max`.
    pub train_high_deviation: usize,
    /// Training transitions of the model evaluated.
    pub n_train: i64,
    /// Version of the model evaluated.
    pub model_version: i64,
    /// Trajectories the evaluated model covers.
    pub model_trajectories: i64,
    /// Test problems.
    pub test_problems: usize,
    /// Test problems with a plan found within the budget at test β.
    pub plans_found: usize,
    /// Test problems whose plan, executed, reached the goal.
    pub successes: usize,
    /// Test problems solvable inside the true precondition (gridworld; 0 where unknown).
    pub oracle_solvable: usize,
    /// `oracle_solvable / test_problems`, where the oracle is known.
    pub oracle_rate: Option<f64>,
    /// Test problems solvable inside the *learned* precondition at test β (gridworld: an
    /// exhaustive search over the model's moves the service trusts; continuous worlds: found
    /// by the planner or by a search [`Bench::long_search_factor`] times longer; 0 for the
    /// water plant).
    pub learned_solvable: usize,
    /// `learned_solvable / test_problems`, where it is known.
    pub learned_rate: Option<f64>,
    /// Test problems the oracle solves and the learned precondition does not, one truly safe
    /// untrusted move short of solvable ([`Bench::blocking_moves`]; gridworld).
    pub one_move_short: usize,
    /// Of those, problems where some such move was executed in training (labelled safe, yet
    /// not trusted: the estimator's loss rather than the choice of executions').
    pub one_move_short_executed: usize,
    /// `plans_found / test_problems`.
    pub plan_found_rate: f64,
    /// Steps of the test plans found.
    pub planned_steps: usize,
    /// Of those, steps whose *true* deviation from the plan's own state is at least `d_max`:
    /// the moves the learned precondition trusted wrongly and the planner used. Held-out TNR
    /// judges uniform state-actions; this judges the ones a planner picks, where a search over
    /// many candidates finds a model's false trust.
    pub unsafe_planned_steps: usize,
    /// `unsafe_planned_steps / planned_steps` (`None` without a plan).
    pub unsafe_step_rate: Option<f64>,
    /// `successes / test_problems`.
    pub success_rate: f64,
    /// Test problems reached executing the learned plan closed loop (re-planning at test β
    /// from where the robot is whenever it strays more than `d_max` from the plan).
    pub closed_loop_successes: usize,
    /// `closed_loop_successes / test_problems` (`None` for the water plant).
    pub closed_loop_rate: Option<f64>,
    /// Plans asked for after the first, over the closed-loop executions.
    pub replans: usize,
    /// Test problems whose oracle plan reached the goal executed open loop.
    pub oracle_open_successes: usize,
    /// Test problems the oracle reached executing closed loop.
    pub oracle_closed_successes: usize,
    /// Test problems the model's own plan (no precondition) reached, executed open loop.
    pub baseline_successes: usize,
    /// `baseline_successes / test_problems`, where known.
    pub baseline_rate: Option<f64>,
    /// Median σ of the model at the held-out state-actions.
    pub held_out_median_sigma: Option<f64>,
    /// The β the held-out transitions were judged at: `learning.test_beta`, or the certified
    /// one with `learning.calibrate_test_beta`.
    pub test_beta: Option<f64>,
    /// Held-out transitions judged.
    pub held_out: usize,
    /// Held-out transitions with a true deviation below `d_max`.
    pub held_out_low: usize,
    /// Held-out transitions with a true deviation of at least `d_max`.
    pub held_out_high: usize,
    /// Truly-low transitions judged inside.
    pub true_positives: usize,
    /// Truly-high transitions judged outside.
    pub true_negatives: usize,
    /// `true_positives / held_out_low`.
    pub tpr: Option<f64>,
    /// `true_negatives / held_out_high`.
    pub tnr: Option<f64>,
    /// Training trajectories per [`PourType`], in [`PourType::ALL`] order.
    pub pour_types: [usize; 5],
    /// Wall-clock seconds of the iteration (training and evaluation).
    pub seconds: f64,
}

/// One training slot.
#[derive(Debug, Clone, Serialize)]
pub struct TrainingRecord {
    /// Strategy.
    pub strategy: Strategy,
    /// Seed.
    pub seed: u64,
    /// Iteration.
    pub iteration: usize,
    /// Slot in the batch.
    pub slot: usize,
    /// `no_plan` answers before a proposal (or before giving up).
    pub no_plan: usize,
    /// The β the executed proposal was planned at.
    pub beta: Option<f64>,
    /// Whether that β is below the iteration's (`learning.relax_beta`).
    pub relaxed: bool,
    /// Whether a trajectory was executed and posted.
    pub executed: bool,
    /// Transitions.
    pub length: usize,
    /// Whether it ended in a goal state.
    pub goal_reached: bool,
    /// Largest true deviation along it.
    pub max_deviation: f64,
    /// Its kind (water plant).
    pub pour_type: PourType,
}

/// One test problem.
#[derive(Debug, Clone, Serialize)]
pub struct TestRecord {
    /// Strategy.
    pub strategy: Strategy,
    /// Seed.
    pub seed: u64,
    /// Iteration.
    pub iteration: usize,
    /// Index of the problem.
    pub problem: usize,
    /// Its start state.
    pub start: Vec<f64>,
    /// Its goal.
    pub goal: Vec<f64>,
    /// A plan was found at test β.
    pub found: bool,
    /// Extensions the planner spent.
    pub extensions: u64,
    /// Actions in the plan (0 if none).
    pub plan_length: usize,
    /// The executed plan reached the goal.
    pub success: bool,
    /// The problem is solvable inside the true precondition (`None` where that is unknown).
    pub oracle: Option<bool>,
    /// The problem is solvable inside the learned precondition at test β (`None` where that
    /// is not searched: the water plant; see [`IterationRecord::learned_solvable`]).
    pub learned: Option<bool>,
    /// For a problem the oracle solves and the learned precondition does not (gridworld): how
    /// many truly safe untrusted moves would each alone make it solvable, and how many of them
    /// were executed in training ([`Bench::blocking_moves`]).
    pub blocking: Option<(usize, usize)>,
    /// Steps of the plan whose true deviation from the plan's own state is at least `d_max`.
    pub unsafe_steps: usize,
    /// The learned plan executed closed loop reached the goal (`None`: not measured).
    pub closed_loop_success: Option<bool>,
    /// Plans asked for after the first in the closed-loop execution.
    pub replans: usize,
    /// The oracle's plan reached the goal open loop (`None` where the oracle is unknown).
    pub oracle_open_loop: Option<bool>,
    /// The oracle reached the goal closed loop.
    pub oracle_closed_loop: Option<bool>,
    /// The model's own plan, with no precondition, reached the goal open loop.
    pub baseline: Option<bool>,
}

/// Which slice of the water plant's action space a precondition map shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MapKind {
    /// Upright translations to `(x, y)`.
    Translation,
    /// Tilts to [`Config::map_tilt_degrees`] at `(x, y)`.
    Rotation,
}

/// `μ + βσ` (test β) over a grid of the action plane, with the training actions of that kind.
#[derive(Debug, Clone, Serialize)]
pub struct PreconditionMap {
    /// Iteration after whose batch it was taken.
    pub iteration: usize,
    /// Translation or rotation actions.
    pub kind: MapKind,
    /// Grid columns (source centre `x`, m).
    pub xs: Vec<f64>,
    /// Grid rows (source centre `y`, m).
    pub ys: Vec<f64>,
    /// `upper[r][c]` at `(xs[c], ys[r])`.
    pub upper: Vec<Vec<f64>>,
    /// Training actions of this kind so far: `(x, y, true deviation)`.
    pub points: Vec<(f64, f64, f64)>,
}

/// Everything one run measured.
#[derive(Debug, Clone, Default)]
pub struct RunResult {
    /// One record per iteration.
    pub iterations: Vec<IterationRecord>,
    /// One record per training slot.
    pub training: Vec<TrainingRecord>,
    /// One record per test problem.
    pub tests: Vec<TestRecord>,
    /// Precondition maps (water plant, the designated run only).
    pub maps: Vec<PreconditionMap>,
}

/// What one run needs besides the client.
#[derive(Debug, Clone)]
pub struct RunSpec {
    /// Strategy.
    pub strategy: Strategy,
    /// Seed.
    pub seed: u64,
    /// Held-out transitions (other seeds' pools).
    pub held_out: Arc<Vec<Labelled>>,
    /// Whether to take precondition maps.
    pub maps: bool,
    /// The oracle's and the baseline's answers per `(seed, iteration, problem)`, shared by the
    /// runs of one seed.
    pub references: Arc<tokio::sync::Mutex<ReferenceCache>>,
}

/// The oracle's and the baseline's answers to test problem `k` of iteration `j`, computed once
/// per seed and shared by the strategies' runs (they see the same problems).
async fn references(
    spec: &RunSpec,
    bench: &Bench,
    cfg: &Config,
    d_max: f64,
    problem: &Problem,
    j: u64,
    k: usize,
) -> anyhow::Result<Option<References>> {
    let key = (spec.seed, j, k);
    if let Some(r) = spec.references.lock().await.get(&key) {
        return Ok(*r);
    }
    let seed = precond_core::seed::mix(spec.seed, (j * 1_000_003 + k as u64) as i64);
    let r = bench
        .references(problem, d_max, cfg.max_extensions, seed)
        .await?;
    spec.references.lock().await.insert(key, r);
    Ok(r)
}

/// Reference answers by `(seed, iteration, problem)`.
pub type ReferenceCache = std::collections::HashMap<(u64, u64, usize), Option<References>>;

/// The planner's view of a planned trajectory as the API shows it.
fn trajectory(p: &PlannedTrajectory) -> Trajectory {
    Trajectory {
        states: p.states.clone(),
        actions: p.actions.clone(),
        mu: p.mu.clone(),
        sigma: p.sigma.clone(),
    }
}

/// Runs the protocol for one strategy and seed (see the module docs).
pub async fn run_one(
    client: &ApiClient,
    bench: &Bench,
    cfg: &Config,
    spec: &RunSpec,
    progress: &ProgressBar,
) -> anyhow::Result<RunResult> {
    let name = format!(
        "experiment {}, {}, seed {}",
        cfg.domain.as_str(),
        spec.strategy.as_str(),
        spec.seed
    );
    let exp = client
        .create_experiment(&experiment_body(cfg, bench, name, spec.strategy, spec.seed))
        .await?;
    let mut run = Run {
        client,
        bench,
        cfg,
        spec,
        id: exp.id,
        d_max: exp.settings.d_max,
        world: bench.world(),
        result: RunResult::default(),
        posted: 0,
        executed: Vec::new(),
    };
    for j in 0..cfg.iterations {
        let started = Instant::now();
        let mut rec = IterationRecord::new(spec, cfg, j);
        run.train_batch(&mut rec).await?;
        run.refit(&mut rec).await?;
        run.evaluate(&mut rec).await?;
        run.judge_held_out(&mut rec).await?;
        run.take_maps(j).await?;
        rec.seconds = started.elapsed().as_secs_f64();
        report(progress, &rec);
        run.result.iterations.push(rec);
    }
    Ok(run.result)
}

/// The state of one run between its steps.
struct Run<'a> {
    client: &'a ApiClient,
    bench: &'a Bench,
    cfg: &'a Config,
    spec: &'a RunSpec,
    /// The run's experiment.
    id: i64,
    d_max: f64,
    world: Box<dyn World>,
    result: RunResult,
    /// Trajectories posted so far.
    posted: i64,
    /// Every executed transition with its true deviation (for the precondition maps).
    executed: Vec<Labelled>,
}

impl Run<'_> {
    /// Training: one batch of `batch_size` slots.
    async fn train_batch(&mut self, rec: &mut IterationRecord) -> anyhow::Result<()> {
        let mut total_length = 0;
        for slot in 0..self.cfg.batch_size {
            let train = self.train_slot(rec, slot).await?;
            rec.train_no_plan += train.no_plan;
            rec.train_relaxed += usize::from(train.relaxed);
            if train.executed {
                rec.train_trajectories += 1;
                total_length += train.length;
                rec.train_goal_reached += usize::from(train.goal_reached);
                let k = PourType::ALL
                    .iter()
                    .position(|p| *p == train.pour_type)
                    .unwrap_or(0);
                rec.pour_types[k] += 1;
            } else {
                rec.train_skipped += 1;
            }
            self.result.training.push(train);
        }
        if rec.train_trajectories > 0 {
            rec.mean_traj_length = Some(total_length as f64 / rec.train_trajectories as f64);
        }
        Ok(())
    }

    /// One slot: fresh problems until a proposal comes back (or `problem_tries` run out), then
    /// execute it in the simulator and post it.
    async fn train_slot(
        &mut self,
        rec: &mut IterationRecord,
        slot: usize,
    ) -> anyhow::Result<TrainingRecord> {
        let (seed, j) = (self.spec.seed, rec.iteration);
        let domain = self.bench.domain();
        let mut train = TrainingRecord {
            strategy: self.spec.strategy,
            seed,
            iteration: j,
            slot,
            no_plan: 0,
            beta: None,
            relaxed: false,
            executed: false,
            length: 0,
            goal_reached: false,
            max_deviation: 0.0,
            pour_type: PourType::NoPour,
        };
        let tries = self.cfg.problem_tries.max(1);
        for t in 0..tries {
            let key = (slot * tries + t) as u64;
            let problem =
                self.bench
                    .sample_problem(&mut stream(seed, purpose::TRAIN_PROBLEM, j as u64, key));
            let proposed = self
                .client
                .propose(
                    self.id,
                    problem.start(),
                    problem.goal(),
                    Some("precond-experiment"),
                    None,
                )
                .await?;
            let p = match proposed {
                // Past the server's planning deadline: no plan within it.
                Proposed::NoPlan | Proposed::TimedOut => {
                    train.no_plan += 1;
                    continue;
                }
                Proposed::Trajectory(p) => p,
            };
            // (Within rounding: serde_json's default float parser may be off by an ulp.)
            anyhow::ensure!(
                p.content
                    .trajectory
                    .states
                    .first()
                    .is_some_and(|s0| close(s0, problem.start())),
                "proposal {} does not start at the problem's start {:?}",
                p.id,
                problem.start()
            );
            self.world
                .reset(&mut stream(seed, purpose::TRAIN_EPISODE, j as u64, key));
            let exec = execute(self.bench, self.world.as_mut(), &p.content.trajectory);
            let transitions: Vec<Transition> = exec.steps.iter().map(|l| l.t.clone()).collect();
            self.client
                .post_trajectory(self.id, Some(p.id), transitions)
                .await?;
            self.posted += 1;
            // A batch the service completes mid-iteration (after a skipped slot) is refitted
            // in the background; wait for that fit, so the next proposal is answered by the
            // same version in every run of this seed, not by whichever the race left.
            let batch = self.cfg.batch_size as i64;
            if self.posted % batch == 0 && slot + 1 < self.cfg.batch_size {
                self.client
                    .wait_for_fit(self.id, self.posted, self.cfg.fit_timeout)
                    .await?;
            }
            rec.beta_train = Some(p.content.relaxed_from_beta.unwrap_or(p.terms.beta));
            train.beta = Some(p.terms.beta);
            train.relaxed = p.content.relaxed_from_beta.is_some();
            train.executed = true;
            train.length = exec.steps.len();
            train.goal_reached = domain.is_goal(&exec.final_state, problem.goal());
            train.max_deviation = exec.steps.iter().map(|l| l.deviation).fold(0.0, f64::max);
            train.pour_type = classify(self.bench, &exec);
            rec.train_high_deviation += exec
                .steps
                .iter()
                .filter(|l| l.deviation >= self.d_max)
                .count();
            self.executed.extend(exec.steps);
            break;
        }
        Ok(train)
    }

    /// The refit: the service fits in the background after every complete batch; a batch cut
    /// short by skipped slots is fitted on demand.
    async fn refit(&mut self, rec: &mut IterationRecord) -> anyhow::Result<()> {
        let batch = self.cfg.batch_size as i64;
        let model = if self.posted == 0 {
            self.client.model(self.id).await?
        } else if self.posted % batch == 0 {
            self.client
                .wait_for_fit(self.id, self.posted, self.cfg.fit_timeout)
                .await?
        } else {
            self.client.refit(self.id).await?
        };
        rec.n_train = model.n_train as i64;
        rec.model_version = model.version;
        rec.model_trajectories = model.n_trajectories;
        Ok(())
    }

    /// Evaluation: the same fresh problems for every strategy at this seed and iteration, each
    /// planned at test β and, if a plan is found, executed open loop (the paper's protocol) and
    /// closed loop; beside them the oracle's and the baseline's answers to the same problems.
    async fn evaluate(&mut self, rec: &mut IterationRecord) -> anyhow::Result<()> {
        let (seed, j) = (self.spec.seed, rec.iteration as u64);
        let domain = self.bench.domain();
        let mut known_oracle = false;
        let mut known_learned = false;
        let mut known_baseline = false;
        let trusted = Self::trusted_moves(self.client, self.bench, self.id).await?;
        let trusted = |s: &[f64], a: &[f64]| trusted.contains(&move_key(s, a));
        let executed: std::collections::HashSet<[i64; 4]> = match self.bench {
            Bench::Grid(_) => self
                .executed
                .iter()
                .map(|l| move_key(&l.t.s, &l.t.a))
                .collect(),
            _ => Default::default(),
        };
        for k in 0..self.cfg.test_problems {
            let problem =
                self.bench
                    .sample_problem(&mut stream(seed, purpose::TEST_PROBLEM, j, k as u64));
            let plan = self
                .client
                .plan(self.id, problem.start(), problem.goal())
                .await?;
            let references =
                references(self.spec, self.bench, self.cfg, self.d_max, &problem, j, k).await?;
            let mut test = TestRecord {
                strategy: self.spec.strategy,
                seed,
                iteration: rec.iteration,
                problem: k,
                start: problem.start().to_vec(),
                goal: problem.goal().to_vec(),
                found: false,
                extensions: plan.extensions as u64,
                plan_length: 0,
                success: false,
                oracle: references.map(|r| r.oracle_solvable),
                learned: self.bench.learned_solvable(&problem, trusted),
                blocking: None,
                unsafe_steps: 0,
                closed_loop_success: self.bench.closed_loop().then_some(false),
                replans: 0,
                oracle_open_loop: references.map(|r| r.oracle_open_loop),
                oracle_closed_loop: references.map(|r| r.oracle_closed_loop),
                baseline: references.map(|r| r.baseline),
            };
            if test.oracle == Some(true) && test.learned == Some(false) {
                test.blocking = self
                    .bench
                    .blocking_moves(&problem, self.d_max, trusted)
                    .map(|moves| {
                        let executed = moves.iter().filter(|m| executed.contains(*m)).count();
                        (moves.len(), executed)
                    });
            }
            if let Some(factor) = self.bench.long_search_factor(self.cfg.long_search) {
                test.learned = Some(
                    plan.found || {
                        let budget = self
                            .cfg
                            .max_extensions
                            .saturating_mul(factor)
                            .min(precond_core::limits::MAX_EXTENSIONS);
                        self.client
                            .plan_within(self.id, problem.start(), problem.goal(), Some(budget))
                            .await?
                            .found
                    },
                );
            }
            if let (true, Some(traj)) = (plan.found, plan.trajectory.as_ref()) {
                test.found = true;
                test.plan_length = traj.actions.len();
                self.world
                    .reset(&mut stream(seed, purpose::TEST_EPISODE, j, k as u64));
                test.unsafe_steps = traj
                    .states
                    .iter()
                    .zip(&traj.actions)
                    .filter(|(s, a)| {
                        let next = self.world.step(s, a);
                        domain.deviation(s, a, &next) >= self.d_max
                    })
                    .count();
                self.world
                    .reset(&mut stream(seed, purpose::TEST_EPISODE, j, k as u64));
                let exec = execute(self.bench, self.world.as_mut(), traj);
                test.success = domain.is_goal(&exec.final_state, problem.goal());
                if self.bench.closed_loop() {
                    self.world
                        .reset(&mut stream(seed, purpose::TEST_EPISODE, j, k as u64));
                    let mut closed = ClosedLoop::new(&problem, trajectory(traj), self.d_max);
                    while let Some(s) = closed.advance(self.world.as_mut(), domain, &problem) {
                        let again = self.client.plan(self.id, &s, problem.goal()).await?;
                        closed.replanned(again.trajectory.as_ref().map(trajectory));
                    }
                    test.closed_loop_success = Some(closed.executed().success);
                    test.replans = closed.executed().replans;
                }
            }
            rec.plans_found += usize::from(test.found);
            rec.planned_steps += test.plan_length;
            rec.unsafe_planned_steps += test.unsafe_steps;
            rec.successes += usize::from(test.success);
            rec.closed_loop_successes += usize::from(test.closed_loop_success == Some(true));
            rec.replans += test.replans;
            rec.oracle_solvable += usize::from(test.oracle == Some(true));
            rec.learned_solvable += usize::from(test.learned == Some(true));
            if let Some((short, executed)) = test.blocking {
                rec.one_move_short += usize::from(short > 0);
                rec.one_move_short_executed += usize::from(executed > 0);
            }
            known_learned |= test.learned.is_some();
            rec.oracle_open_successes += usize::from(test.oracle_open_loop == Some(true));
            rec.oracle_closed_successes += usize::from(test.oracle_closed_loop == Some(true));
            rec.baseline_successes += usize::from(test.baseline == Some(true));
            known_oracle |= test.oracle.is_some();
            known_baseline |= test.baseline.is_some();
            self.result.tests.push(test);
        }
        let n = self.cfg.test_problems;
        if n > 0 {
            let rate = |k: usize| k as f64 / n as f64;
            rec.plan_found_rate = rate(rec.plans_found);
            rec.unsafe_step_rate = (rec.planned_steps > 0)
                .then(|| rec.unsafe_planned_steps as f64 / rec.planned_steps as f64);
            rec.success_rate = rate(rec.successes);
            rec.closed_loop_rate = self
                .bench
                .closed_loop()
                .then(|| rate(rec.closed_loop_successes));
            rec.oracle_rate = known_oracle.then(|| rate(rec.oracle_solvable));
            rec.learned_rate = known_learned.then(|| rate(rec.learned_solvable));
            rec.baseline_rate = known_baseline.then(|| rate(rec.baseline_successes));
        }
        Ok(())
    }

    /// The state-actions of the gridworld the service trusts at test β (see
    /// [`Bench::all_state_actions`]); empty elsewhere.
    async fn trusted_moves(
        client: &ApiClient,
        bench: &Bench,
        id: i64,
    ) -> anyhow::Result<std::collections::HashSet<[i64; 4]>> {
        let all = bench.all_state_actions();
        if all.is_empty() {
            return Ok(Default::default());
        }
        let points: Vec<(&[f64], &[f64])> = all
            .iter()
            .map(|(s, a)| (s.as_slice(), a.as_slice()))
            .collect();
        let judged = client.precondition(id, &points).await?;
        Ok(all
            .iter()
            .zip(&judged)
            .filter(|(_, j)| j.inside)
            .map(|((s, a), _)| move_key(s, a))
            .collect())
    }

    /// TPR and TNR of the precondition on the held-out transitions.
    async fn judge_held_out(&mut self, rec: &mut IterationRecord) -> anyhow::Result<()> {
        let held = &self.spec.held_out;
        if held.is_empty() {
            return Ok(());
        }
        let points: Vec<(&[f64], &[f64])> = held
            .iter()
            .map(|l| (l.t.s.as_slice(), l.t.a.as_slice()))
            .collect();
        let (judged, beta) = self.client.precondition_at(self.id, &points).await?;
        rec.test_beta = Some(beta);
        let mut sigmas: Vec<f64> = judged.iter().map(|j| j.sigma).collect();
        sigmas.sort_by(f64::total_cmp);
        rec.held_out_median_sigma = sigmas.get(sigmas.len() / 2).copied();
        let mut agreement = Agreement::default();
        for (l, j) in held.iter().zip(&judged) {
            agreement.count(l.deviation, self.d_max, j.inside);
        }
        rec.held_out_low += agreement.positives;
        rec.held_out_high += agreement.negatives;
        rec.true_positives += agreement.true_positives;
        rec.true_negatives += agreement.true_negatives;
        rec.tpr = ratio(rec.true_positives, rec.held_out_low);
        rec.tnr = ratio(rec.true_negatives, rec.held_out_high);
        Ok(())
    }

    /// The precondition maps of the designated run (water plant) at the chosen iterations.
    async fn take_maps(&mut self, j: usize) -> anyhow::Result<()> {
        let Bench::Plant(plant) = self.bench else {
            return Ok(());
        };
        if !self.spec.maps || !self.cfg.map_iterations.contains(&j) {
            return Ok(());
        }
        for kind in [MapKind::Translation, MapKind::Rotation] {
            let map = precondition_map(
                self.client,
                self.id,
                plant,
                self.cfg,
                j,
                kind,
                &self.executed,
            )
            .await?;
            self.result.maps.push(map);
        }
        Ok(())
    }
}

impl IterationRecord {
    /// An empty record of iteration `j`.
    fn new(spec: &RunSpec, cfg: &Config, j: usize) -> Self {
        Self {
            strategy: spec.strategy,
            seed: spec.seed,
            iteration: j,
            beta_train: None,
            train_trajectories: 0,
            train_no_plan: 0,
            train_skipped: 0,
            train_relaxed: 0,
            mean_traj_length: None,
            train_goal_reached: 0,
            train_high_deviation: 0,
            n_train: 0,
            model_version: 0,
            model_trajectories: 0,
            test_problems: cfg.test_problems,
            plans_found: 0,
            successes: 0,
            oracle_solvable: 0,
            oracle_rate: None,
            learned_solvable: 0,
            learned_rate: None,
            one_move_short: 0,
            one_move_short_executed: 0,
            planned_steps: 0,
            unsafe_planned_steps: 0,
            unsafe_step_rate: None,
            plan_found_rate: 0.0,
            success_rate: 0.0,
            closed_loop_successes: 0,
            closed_loop_rate: None,
            replans: 0,
            oracle_open_successes: 0,
            oracle_closed_successes: 0,
            baseline_successes: 0,
            baseline_rate: None,
            held_out_median_sigma: None,
            test_beta: None,
            held_out: spec.held_out.len(),
            held_out_low: 0,
            held_out_high: 0,
            true_positives: 0,
            true_negatives: 0,
            tpr: None,
            tnr: None,
            pour_types: [0; 5],
            seconds: 0.0,
        }
    }
}

/// Breadth-first search from `problem`'s start over the moves the model allows (a move off
/// the grid predicts no progress), `step` answering where a move leads or `None` where it may
/// not be taken: whether a goal state is reached.
fn grid_search(
    g: &IcyGridworld,
    problem: &Problem,
    mut step: impl FnMut(&[f64], &[f64]) -> Option<Vec<f64>>,
) -> bool {
    let key = |s: &[f64]| (s[0] as i64, s[1] as i64);
    let mut seen = std::collections::HashSet::from([key(problem.start())]);
    let mut queue = std::collections::VecDeque::from([problem.start().to_vec()]);
    while let Some(s) = queue.pop_front() {
        if g.is_goal(&s, problem.goal()) {
            return true;
        }
        for m in MOVES {
            if !g.edge_allowed(&s, &m, &g.predict(&s, &m)) {
                continue;
            }
            if let Some(next) = step(&s, &m).filter(|next| seen.insert(key(next))) {
                queue.push_back(next);
            }
        }
    }
    false
}

/// A gridworld state-action as integers (cells and unit moves are whole numbers).
fn move_key(s: &[f64], a: &[f64]) -> [i64; 4] {
    [s[0] as i64, s[1] as i64, a[0] as i64, a[1] as i64]
}

/// Whether two states agree within rounding.
fn close(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(x, y)| (x - y).abs() <= 1e-9 * (1.0 + y.abs()))
}

/// One line of progress per iteration: on the bar, or on stderr when the bar is hidden.
fn report(progress: &ProgressBar, rec: &IterationRecord) {
    progress.inc(1);
    let line = format!(
        "{} seed {} iteration {}: plan found {:.2}, success {:.2}, closed loop {}, oracle {}, \
         baseline {}, TPR {}, TNR {}, σ {}, β {}, n_train {}, no_plan {}, {:.1} s",
        rec.strategy.as_str(),
        rec.seed,
        rec.iteration,
        rec.plan_found_rate,
        rec.success_rate,
        fmt_opt(rec.closed_loop_rate),
        fmt_opt(rec.oracle_rate),
        fmt_opt(rec.baseline_rate),
        fmt_opt(rec.tpr),
        fmt_opt(rec.tnr),
        fmt_opt(rec.held_out_median_sigma),
        fmt_opt(rec.test_beta),
        rec.n_train,
        rec.train_no_plan,
        rec.seconds
    );
    if progress.is_hidden() {
        eprintln!("{line}");
    } else {
        progress.set_message(line);
    }
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map_or_else(|| "-".into(), |v| format!("{v:.2}"))
}

fn ratio(k: usize, n: usize) -> Option<f64> {
    (n > 0).then(|| k as f64 / n as f64)
}

/// Queries the precondition map of one kind (see [`PreconditionMap`]).
async fn precondition_map(
    client: &ApiClient,
    id: i64,
    plant: &WaterPlant,
    cfg: &Config,
    iteration: usize,
    kind: MapKind,
    executed: &[Labelled],
) -> anyhow::Result<PreconditionMap> {
    let sc = plant.scene();
    let (nx, ny) = cfg.map_resolution;
    let lin = |lo: f64, hi: f64, n: usize| -> Vec<f64> {
        (0..n)
            .map(|i| lo + (hi - lo) * i as f64 / (n.max(2) - 1) as f64)
            .collect()
    };
    let xs = lin(sc.source_low[0], sc.source_high[0], nx);
    let ys = lin(sc.source_low[1], sc.source_high[1], ny);
    let tilt = cfg.map_tilt_degrees.to_radians();
    let mut states = Vec::with_capacity(nx * ny);
    let mut actions = Vec::with_capacity(nx * ny);
    for &y in &ys {
        for &x in &xs {
            match kind {
                MapKind::Rotation => {
                    states.push(plant.start_state(x, y));
                    actions.push(vec![x, y, tilt]);
                }
                MapKind::Translation => {
                    // The features are the action and the motion flag: any start that makes
                    // this a translation gives the same answer.
                    let from = if x - 0.05 >= sc.source_low[0] {
                        x - 0.05
                    } else {
                        x + 0.05
                    };
                    states.push(plant.start_state(from, y));
                    actions.push(vec![x, y, 0.0]);
                }
            }
        }
    }
    let points: Vec<(&[f64], &[f64])> = states
        .iter()
        .zip(&actions)
        .map(|(s, a)| (s.as_slice(), a.as_slice()))
        .collect();
    let judged = client.precondition(id, &points).await?;
    let upper = judged
        .chunks(nx)
        .map(|r| r.iter().map(|j| j.upper).collect())
        .collect();
    let wanted = match kind {
        MapKind::Translation => Motion::Translate,
        MapKind::Rotation => Motion::Rotate,
    };
    let points = executed
        .iter()
        .filter(|l| plant.motion(&l.t.s, &l.t.a) == wanted)
        .map(|l| (l.t.a[0], l.t.a[1], l.deviation))
        .collect();
    Ok(PreconditionMap {
        iteration,
        kind,
        xs,
        ys,
        upper,
        points,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 5 × 3 map whose wall has a single gap at (2, 1).
    fn gap_bench() -> (Bench, IcyGridworld) {
        let g = IcyGridworld::new(&["..#..", ".....", "..#.."]).expect("a valid map");
        (Bench::Grid(g.clone()), g)
    }

    #[test]
    fn the_learned_search_goes_exactly_where_trust_allows() {
        let (bench, g) = gap_bench();
        let problem = Problem::new(&g, vec![0.0, 0.0], vec![4.0, 0.0]).expect("a problem");
        assert_eq!(bench.learned_solvable(&problem, |_, _| true), Some(true));
        assert_eq!(bench.learned_solvable(&problem, |_, _| false), Some(false));
        // Every move trusted but those into or out of the wall's column except through the
        // gap: still solvable; distrust the gap's moves and it is not.
        let not_wall = |s: &[f64], a: &[f64]| {
            let to = [s[0] + a[0], s[1] + a[1]];
            s[0] != 2.0 && to[0] != 2.0 || s[1] == 1.0 && to[1] == 1.0
        };
        assert_eq!(bench.learned_solvable(&problem, not_wall), Some(true));
        let no_gap = |s: &[f64], a: &[f64]| not_wall(s, a) && !(s[0] == 1.0 && s[1] == 1.0);
        assert_eq!(bench.learned_solvable(&problem, no_gap), Some(false));
    }

    #[test]
    fn the_one_untrusted_safe_move_between_two_trusted_regions_is_the_blocking_one() {
        let (bench, g) = gap_bench();
        let problem = Problem::new(&g, vec![0.0, 0.0], vec![4.0, 0.0]).expect("a problem");
        let not_wall = |s: &[f64], a: &[f64]| {
            let to = [s[0] + a[0], s[1] + a[1]];
            s[0] != 2.0 && to[0] != 2.0 || s[1] == 1.0 && to[1] == 1.0
        };
        let gap_closed = |s: &[f64], a: &[f64]| not_wall(s, a) && !(s == [1.0, 1.0] && a[0] == 1.0);
        assert_eq!(
            bench.blocking_moves(&problem, 0.1, gap_closed),
            Some(vec![[1, 1, 1, 0]]),
            "into the gap: safe, untrusted, and the only way across"
        );
        // Two moves short (the way out of the gap closed too): no single move would do.
        let two_closed =
            |s: &[f64], a: &[f64]| gap_closed(s, a) && !(s == [2.0, 1.0] && a[0] == 1.0);
        assert_eq!(
            bench.blocking_moves(&problem, 0.1, two_closed),
            Some(vec![])
        );
        assert_eq!(
            Bench::Plant(WaterPlant::default()).blocking_moves(&problem, 0.1, |_, _| true),
            None
        );
    }

    #[test]
    fn every_cell_is_judged_with_every_move_the_model_allows() {
        let (bench, _) = gap_bench();
        let all = bench.all_state_actions();
        // 15 cells × 4 moves, less the moves off the edge: 5 + 5 along x, 3 + 3 along y.
        assert_eq!(all.len(), 15 * 4 - 16);
        assert!(
            all.iter().any(|(s, _)| s == &vec![2.0, 0.0]),
            "walls included"
        );
        assert!(
            Bench::Plant(WaterPlant::default())
                .all_state_actions()
                .is_empty()
        );
    }
}
