//! What the learned precondition is measured against, on the continuous worlds:
//! - **the oracle**: the same planner over the *true* precondition — a deviation model that
//!   answers every state-action's true deviation (from the simulator) with no uncertainty — so
//!   "solvable" means a plan whose every step truly stays within `d_max` exists and the planner
//!   finds it;
//! - **the baseline**: the model's own plan with no precondition at all (every step trusted),
//!   executed as it is — what a robot does without precond.
//!
//! Both run the service's planner in-process, with the harness's budget doubled for the oracle
//! (its answer bounds what a learned precondition can reach). Executions are open loop (the
//! paper's protocol) or closed loop: after each step, if the robot is farther than `d_max` from
//! where the plan said it would be, or the plan has run out, it plans again from where it is.

use precond_core::domain::{Domain, Kinematic, Problem};
use precond_core::planning::{
    DeviationModel, Planner, PlannerSettings, PlanningSettings, Precondition, Trajectory,
};
use precond_core::sim::{ContinuousWorld, World};

/// The true deviation of each state-action, `σ = 0`: a planner over the true precondition.
pub struct TrueDeviation<'a> {
    world: &'a ContinuousWorld,
    domain: &'a Kinematic,
}

impl<'a> TrueDeviation<'a> {
    /// The true deviations of `world`, whose robot models itself as `domain`.
    pub fn new(world: &'a ContinuousWorld, domain: &'a Kinematic) -> Self {
        Self { world, domain }
    }
}

impl DeviationModel for TrueDeviation<'_> {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        let (st, ac) = (self.domain.state_space(), self.domain.action_space());
        let n = st.dim();
        let from_unit = |u: f64, lo: f64, hi: f64| lo + u * (hi - lo);
        features
            .chunks(dim.max(1))
            .map(|f| {
                let s: Vec<f64> = (0..n)
                    .map(|i| from_unit(f[i], st.low[i], st.high[i]))
                    .collect();
                let a: Vec<f64> = (0..ac.dim())
                    .map(|i| from_unit(f[n + i], ac.low[i], ac.high[i]))
                    .collect();
                (self.world.true_deviation(self.domain, &s, &a), 0.0)
            })
            .collect()
    }
}

/// Trusts every state-action (`μ = σ = 0`): the model's own plan.
pub struct TrustAll;

impl DeviationModel for TrustAll {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        vec![(0.0, 0.0); features.len() / dim.max(1)]
    }
}

/// The planner settings of a reference plan: one RRT run of `max_extensions`.
pub fn settings(max_extensions: u32) -> PlanningSettings {
    PlanningSettings::new(
        PlannerSettings {
            max_extensions: max_extensions as usize,
            n_candidates: 1,
            ..PlannerSettings::default()
        },
        Default::default(),
    )
    .expect("a reference plan's settings are valid")
}

/// A plan for `problem` inside the precondition of `model` (β = 0, the world's `d_max`), or
/// `None`.
pub fn plan(
    domain: &dyn Domain,
    model: &dyn DeviationModel,
    settings: &PlanningSettings,
    problem: &Problem,
    d_max: f64,
    seed: u64,
) -> Option<Trajectory> {
    let precondition = Precondition::new(0.0, d_max).ok()?;
    Planner::new(domain, model, settings)
        .plan(problem, precondition, seed)
        .ok()?
        .trajectory
}

/// How an execution went.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Executed {
    /// It ended at the goal.
    pub success: bool,
    /// Plans made after the first (closed loop only).
    pub replans: usize,
    /// Actions executed.
    pub steps: usize,
}

/// Executes `plan` open loop from the problem's start in `world` (already reset).
pub fn open_loop(
    world: &mut dyn World,
    domain: &dyn Domain,
    problem: &Problem,
    plan: &Trajectory,
) -> Executed {
    let mut s = problem.start().to_vec();
    for a in &plan.actions {
        s = world.step(&s, a);
    }
    Executed {
        success: domain.is_goal(&s, problem.goal()),
        replans: 0,
        steps: plan.actions.len(),
    }
}

/// The most actions a closed-loop execution takes: four times the first plan's length, and at
/// least 20.
pub fn closed_loop_steps(first_plan: usize) -> usize {
    (4 * first_plan).max(20)
}

/// The most plans a closed-loop execution makes after the first.
pub const MAX_REPLANS: usize = 20;

/// A closed-loop execution of a plan, driven by its caller: [`advance`](Self::advance)
/// executes steps until the robot needs a new plan — it is more than `d_max` from the plan's
/// predicted state, or the plan has run out — and returns the state to plan from (clamped into
/// the state bounds); the caller plans however it plans and hands the plan to
/// [`replanned`](Self::replanned). The execution ends at the goal, when no plan is found, or
/// after [`closed_loop_steps`] actions or [`MAX_REPLANS`] plans.
#[derive(Debug, Clone)]
pub struct ClosedLoop {
    plan: Trajectory,
    k: usize,
    s: Vec<f64>,
    d_max: f64,
    max_steps: usize,
    done: bool,
    out: Executed,
}

impl ClosedLoop {
    /// Starts executing `first` from the problem's start.
    pub fn new(problem: &Problem, first: Trajectory, d_max: f64) -> Self {
        Self {
            max_steps: closed_loop_steps(first.actions.len()),
            plan: first,
            k: 0,
            s: problem.start().to_vec(),
            d_max,
            done: false,
            out: Executed {
                success: false,
                replans: 0,
                steps: 0,
            },
        }
    }

    /// Executes steps in `world` until a plan is needed (the state to plan from) or the
    /// execution is over (`None`).
    pub fn advance(
        &mut self,
        world: &mut dyn World,
        domain: &dyn Domain,
        problem: &Problem,
    ) -> Option<Vec<f64>> {
        while !self.done && self.out.steps < self.max_steps {
            if domain.is_goal(&self.s, problem.goal()) {
                break;
            }
            if self.k >= self.plan.actions.len() {
                if self.out.replans >= MAX_REPLANS {
                    break;
                }
                self.out.replans += 1;
                return Some(self.s.clone());
            }
            let next = world.step(&self.s, &self.plan.actions[self.k]);
            self.out.steps += 1;
            let off = domain.distance(&self.plan.states[self.k + 1], &next) > self.d_max;
            self.s = next;
            domain.state_space().clamp(&mut self.s);
            self.k += 1;
            if off {
                // Plan again before the next step.
                self.k = self.plan.actions.len();
            }
        }
        self.done = true;
        self.out.success = domain.is_goal(&self.s, problem.goal());
        None
    }

    /// The plan made from the state [`advance`](Self::advance) returned, or `None` when none
    /// was found (the execution is then over).
    pub fn replanned(&mut self, plan: Option<Trajectory>) {
        match plan {
            Some(p) if !p.actions.is_empty() => {
                self.plan = p;
                self.k = 0;
            }
            _ => self.done = true,
        }
    }

    /// How it went (final once [`advance`](Self::advance) returned `None`).
    pub fn executed(&self) -> Executed {
        self.out
    }
}

/// A problem whose start is `s` and whose goal is `problem`'s (both checked by the domain).
pub fn from_here(domain: &dyn Domain, s: &[f64], problem: &Problem) -> Option<Problem> {
    Problem::new(domain, s.to_vec(), problem.goal().to_vec()).ok()
}

/// The oracle's and the baseline's answers to one test problem.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct References {
    /// The oracle found a plan inside the true precondition.
    pub oracle_solvable: bool,
    /// The oracle's plan executed open loop reached the goal.
    pub oracle_open_loop: bool,
    /// The oracle executed closed loop reached the goal.
    pub oracle_closed_loop: bool,
    /// The model's own plan, no precondition, executed open loop reached the goal.
    pub baseline: bool,
}

/// The model's own plan for `problem` with no precondition, executed open loop in `world`
/// (already reset): whether it reached the goal.
pub fn baseline(
    world: &mut dyn World,
    domain: &dyn Domain,
    problem: &Problem,
    d_max: f64,
    max_extensions: u32,
    seed: u64,
) -> bool {
    plan(
        domain,
        &TrustAll,
        &settings(max_extensions),
        problem,
        d_max,
        seed,
    )
    .is_some_and(|p| open_loop(world, domain, problem, &p).success)
}

/// What an oracle planning over `threshold` achieved on one problem.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OracleRun {
    /// It found a plan whose every step's true deviation is below the threshold.
    pub solvable: bool,
    /// That plan executed open loop reached the goal.
    pub open_loop: bool,
    /// Executed closed loop (replanning over the same threshold) it reached the goal.
    pub closed_loop: bool,
}

/// The oracle of a continuous world with a stricter threshold: a planner that trusts exactly
/// the state-actions whose *true* deviation is below `threshold` (`d_max` for the oracle of the
/// harness; `m · d_max` for a cautious one, which measures how many of a world's problems need
/// steps close to `d_max` — those a learner that must be confident cannot trust). Closed-loop
/// execution replans when the robot strays more than the world's `d_max` from the plan, as for
/// every reference.
pub fn oracle(
    world: &ContinuousWorld,
    domain: &Kinematic,
    problem: &Problem,
    threshold: f64,
    max_extensions: u32,
    seed: u64,
) -> OracleRun {
    let truth = TrueDeviation::new(world, domain);
    let oracle_settings = settings(max_extensions.saturating_mul(2));
    let mut sim = world.world();
    let Some(first) = plan(domain, &truth, &oracle_settings, problem, threshold, seed) else {
        return OracleRun {
            solvable: false,
            open_loop: false,
            closed_loop: false,
        };
    };
    let open = open_loop(sim.as_mut(), domain, problem, &first);
    let mut closed = ClosedLoop::new(problem, first, world.d_max());
    while let Some(s) = closed.advance(sim.as_mut(), domain, problem) {
        closed.replanned(
            from_here(domain, &s, problem)
                .and_then(|p| plan(domain, &truth, &oracle_settings, &p, threshold, seed)),
        );
    }
    OracleRun {
        solvable: true,
        open_loop: open.success,
        closed_loop: closed.executed().success,
    }
}

/// The oracle's and the baseline's answers to `problem` in a continuous world (see the module
/// docs).
pub fn continuous(
    world: &ContinuousWorld,
    domain: &Kinematic,
    problem: &Problem,
    max_extensions: u32,
    seed: u64,
) -> References {
    let d_max = world.d_max();
    let mut sim = world.world();
    let baseline = baseline(sim.as_mut(), domain, problem, d_max, max_extensions, seed);
    let o = oracle(world, domain, problem, d_max, max_extensions, seed);
    References {
        oracle_solvable: o.solvable,
        oracle_open_loop: o.open_loop,
        oracle_closed_loop: o.closed_loop,
        baseline,
    }
}
