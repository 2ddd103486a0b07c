//! The planning speed benchmark: a proposal with 20 candidates and a 5000-extension budget on
//! the icy gridworld with the real MDE (the service's default GP) fitted on 1000 transitions of
//! the true world, and a test-time plan, each timed (median over several runs) and printed.

use precond_core::domain::Problem;
use precond_core::domain::{Domain, IcyGridworld, LabelledTransition, LocalModel, Transition};
use precond_core::gp::{GpModel, GpParams};
use precond_core::mde::{Estimator, ServedModel, training_data};
use precond_core::planning::{
    AcquisitionKind, AcquisitionSettings, DeviationModel, Planner, PlannerSettings,
    PlanningSettings, Precondition, Strategy,
};
use precond_core::sim::Simulated;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::{Duration, Instant};

/// `n` transitions from uniformly drawn open cells and moves, executed in the true world and
/// labelled by the model.
pub fn icy_transitions(grid: &IcyGridworld, n: usize, seed: u64) -> Vec<LabelledTransition> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut world = grid.world();
    let open = grid.open_cells();
    (0..n)
        .map(|_| {
            let s = open[rng.random_range(0..open.len())].to_vec();
            let a = grid.sample_action(&s, &mut rng);
            let s_next = world.step(&s, &a);
            let s_pred = grid.predict(&s, &a);
            LabelledTransition {
                deviation: grid.distance(&s_pred, &s_next),
                observed: Transition::new(s, a, s_next),
                s_pred,
            }
        })
        .collect()
}

/// What the benchmark does.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    /// Timed repetitions of each measurement (the median is reported); each uses its own seed.
    pub repeats: usize,
    /// Start cell.
    pub start: Vec<f64>,
    /// Goal cell.
    pub goal: Vec<f64>,
    /// The β values to time a proposal at (default −2, 0, 2: the start, middle and end of the
    /// learning schedule).
    pub proposal_betas: Vec<f64>,
    /// β of the test-time plan.
    pub test_beta: f64,
    /// Planner settings (default: 20 candidates, 5000 extensions).
    pub planner: PlannerSettings,
}

impl Default for BenchOptions {
    fn default() -> Self {
        Self {
            repeats: 9,
            start: vec![0.0, 0.0],
            goal: vec![11.0, 11.0],
            proposal_betas: vec![-2.0, 0.0, 2.0],
            test_beta: 2.0,
            planner: PlannerSettings::default(),
        }
    }
}

/// The measured figures.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchFigures {
    /// Median wall time of one `active` proposal, per β of `BenchOptions::proposal_betas`.
    pub proposal: Vec<Duration>,
    /// Median wall time of one test-time plan.
    pub plan: Duration,
    /// Median wall time of one random-strategy proposal.
    pub random: Duration,
    /// Median wall time of one `active` proposal with the `spread` acquisition at β = 0: its
    /// reference state-actions prepared once for every candidate, and (the reference) asked
    /// about anew for each candidate.
    pub spread: (Duration, Duration),
}

/// A model that prepares nothing for fantasised predictions: every pending set is answered by
/// [`DeviationModel::predict_fantasised`] anew (the trait's default), as the `spread`
/// acquisition asked before its references were prepared once.
struct Unprepared<'a>(&'a dyn DeviationModel);

impl DeviationModel for Unprepared<'_> {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        self.0.predict(features, dim)
    }

    fn predict_fantasised(&self, features: &[f64], pending: &[f64], dim: usize) -> Vec<(f64, f64)> {
        self.0.predict_fantasised(features, pending, dim)
    }
}

/// Runs the benchmark on `grid` with `model` and prints the figures; an error when the
/// options' problem or settings are not acceptable.
pub fn run(
    grid: &IcyGridworld,
    model: &dyn DeviationModel,
    options: &BenchOptions,
) -> anyhow::Result<BenchFigures> {
    let settings = PlanningSettings::new(options.planner.clone(), AcquisitionSettings::default())?;
    let planner = Planner::new(grid, model, &settings);
    let problem = Problem::new(grid, options.start.clone(), options.goal.clone())?;
    let d_max = grid.default_d_max();
    let repeats = options.repeats.max(1);
    println!(
        "planning benchmark: icy gridworld {}×{}, {} → {}, {} candidates × {} extensions, median of {repeats}",
        grid.width(),
        grid.height(),
        fmt_vec(&options.start),
        fmt_vec(&options.goal),
        options.planner.n_candidates,
        options.planner.max_extensions,
    );

    let mut proposal = Vec::new();
    for &beta in &options.proposal_betas {
        let at = Precondition::new(beta, d_max)?;
        let mut times = Vec::new();
        let mut last = None;
        for seed in 0..repeats as u64 {
            let t0 = Instant::now();
            let p = planner.propose(Strategy::Active, &problem, at, seed);
            times.push(t0.elapsed());
            last = Some(p);
        }
        let time = median(&mut times);
        proposal.push(time);
        match last {
            Some(Ok(p)) => println!(
                "  proposal (active, β = {beta:>4}): {:>8.2} ms  [{} runs, {} candidates, {} extensions, {} model points in {} calls, chosen length {}, α = {:.4}]",
                ms(time),
                p.runs,
                p.candidates.len(),
                p.extensions,
                p.model_points,
                p.model_calls,
                p.trajectory.len(),
                p.alpha
            ),
            Some(Err(e)) => println!(
                "  proposal (active, β = {beta:>4}): {:>8.2} ms  [{e}]",
                ms(time)
            ),
            None => {}
        }
    }

    let mut times = Vec::new();
    let mut last = None;
    for seed in 0..repeats as u64 {
        let t0 = Instant::now();
        let out = planner.plan(&problem, Precondition::new(options.test_beta, d_max)?, seed);
        times.push(t0.elapsed());
        last = Some(out);
    }
    let plan_time = median(&mut times);
    match last {
        Some(Ok(out)) => println!(
            "  test-time plan (β = {:>4}):     {:>8.2} ms  [found: {}, {} extensions, tree of {} nodes{}]",
            options.test_beta,
            ms(plan_time),
            out.trajectory.is_some(),
            out.extensions,
            out.tree_size,
            out.trajectory
                .map(|t| format!(", length {}", t.len()))
                .unwrap_or_default()
        ),
        Some(Err(e)) => println!(
            "  test-time plan (β = {}): {:>8.2} ms  [{e}]",
            options.test_beta,
            ms(plan_time)
        ),
        None => {}
    }

    let mut times = Vec::new();
    for seed in 0..repeats as u64 {
        let t0 = Instant::now();
        let _ = planner.propose(
            Strategy::Random,
            &problem,
            Precondition::new(0.0, d_max)?,
            seed,
        );
        times.push(t0.elapsed());
    }
    let random = median(&mut times);
    println!("  proposal (random, β =    0):   {:>8.2} ms", ms(random));

    let spread = AcquisitionSettings {
        kind: AcquisitionKind::Spread,
        ..AcquisitionSettings::default()
    };
    let spread = PlanningSettings::new(options.planner.clone(), spread)?;
    let at = Precondition::new(0.0, d_max)?;
    let unprepared = Unprepared(model);
    let mut figures = Vec::new();
    for (how, model) in [
        ("references prepared once", model),
        (
            "anew per candidate (reference)",
            &unprepared as &dyn DeviationModel,
        ),
    ] {
        let planner = Planner::new(grid, model, &spread);
        let mut times = Vec::new();
        let mut chosen = Vec::new();
        for seed in 0..repeats as u64 {
            let t0 = Instant::now();
            let p = planner.propose(Strategy::Active, &problem, at, seed);
            times.push(t0.elapsed());
            chosen.push(p.ok().map(|p| p.trajectory.actions));
        }
        let time = median(&mut times);
        println!(
            "  proposal (spread, β =    0):   {:>8.2} ms  [{how}]",
            ms(time)
        );
        figures.push((time, chosen));
    }
    let same = figures[0].1 == figures[1].1;
    println!("  spread: the same trajectories chosen both ways: {same}");

    Ok(BenchFigures {
        proposal,
        plan: plan_time,
        random,
        spread: (figures[0].0, figures[1].0),
    })
}

/// Times `model` alone: microseconds per point, one point per call and in batches of 64.
pub fn time_model(grid: &IcyGridworld, model: &dyn DeviationModel) -> (f64, f64) {
    let dim = grid.feature_dim();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let points: Vec<f64> = (0..256)
        .flat_map(|_| {
            let s = grid.sample_state(&mut rng);
            let a = grid.sample_action(&s, &mut rng);
            grid.features(&s, &a, &[])
        })
        .collect();
    let t0 = Instant::now();
    for p in points.chunks(dim) {
        std::hint::black_box(model.predict(p, dim));
    }
    let single = t0.elapsed().as_secs_f64() * 1e6 / 256.0;
    let t0 = Instant::now();
    for p in points.chunks(64 * dim) {
        std::hint::black_box(model.predict(p, dim));
    }
    let batched = t0.elapsed().as_secs_f64() * 1e6 / 256.0;
    (single, batched)
}

/// The service's MDE (default settings: heteroscedastic, 2 restarts) fitted on `n` transitions
/// of the true world, as the service would serve it.
pub fn fitted_model(
    grid: &IcyGridworld,
    n: usize,
    seed: u64,
) -> Result<ServedModel, precond_core::gp::GpError> {
    fit_mde(grid, &icy_transitions(grid, n, seed), seed)
}

/// The service's MDE (default settings) fitted on `data`.
pub fn fit_mde(
    domain: &dyn Domain,
    data: &[LabelledTransition],
    seed: u64,
) -> Result<ServedModel, precond_core::gp::GpError> {
    let features: Vec<f64> = data
        .iter()
        .flat_map(|t| domain.features(&t.observed.s, &t.observed.a, &t.s_pred))
        .collect();
    let labels: Vec<f64> = data.iter().map(|t| t.deviation).collect();
    let (x, y) = training_data(features, labels, domain.feature_dim());
    let params = GpParams {
        seed,
        ..GpParams::default()
    }
    .check()?;
    let gp = GpModel::fit(&x, &y, &params)?;
    Ok(ServedModel {
        version: 1,
        estimator: Estimator::Fitted(Box::new(gp)),
        fit: None,
        further: Default::default(),
    })
}

/// The whole benchmark with the real MDE fitted on 1000 transitions of the default layout.
pub fn run_default() -> anyhow::Result<BenchFigures> {
    let grid = IcyGridworld::default_layout();
    let t0 = Instant::now();
    let model = fitted_model(&grid, 1000, 7)?;
    println!(
        "MDE (heteroscedastic GP, default settings) fitted on 1000 transitions in {:.0} ms",
        ms(t0.elapsed())
    );
    let (single, batched) = time_model(&grid, &model);
    println!(
        "  model cost: {single:.1} µs/point one at a time, {batched:.1} µs/point in batches of 64"
    );
    run(&grid, &model, &BenchOptions::default())
}

fn median(times: &mut [Duration]) -> Duration {
    times.sort();
    times[times.len() / 2]
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn fmt_vec(v: &[f64]) -> String {
    format!("{v:?}")
}
