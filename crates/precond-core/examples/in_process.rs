//! precond's numeric core in-process, with no server: learn where a robot's model can be
//! trusted from executed transitions, ask whether a state-action is trusted, and plan inside
//! that precondition — what a Rust robot stack (a dora-rs or ROS 2 node) links `precond-core`
//! for.
//!
//! The robot here is the built-in pusher (a puck that slides on after each push, far on a wet
//! patch, bouncing off a post): its own model is kinematic, `f̂(s, a) = s + a`, and the
//! simulator plays the real robot. A lab's robot would implement [`Domain`] (or declare a
//! custom domain) and execute on hardware instead.
//!
//! ```text
//! cargo run -p precond-core --release --example in_process
//! ```

use nalgebra::DMatrix;
use precond_core::domain::Domain;
use precond_core::gp::{DEFAULT_INDUCING_POINTS, Kernel, NoiseMode};
use precond_core::mde::{
    Estimator, EstimatorKind, EstimatorParams, Training, fit_choosing_label_cap, gp_params,
};
use precond_core::planning::{Planner, PlanningSettings, Precondition};
use precond_core::sim::ContinuousWorld;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Transitions executed to learn from (here: random state-actions, the way a lab would log
/// them from teleoperation or earlier runs).
const TRANSITIONS: usize = 300;
/// The trust margin: a state-action is trusted when `μ + β σ < d_max`.
const BETA: f64 = 2.0;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let world = ContinuousWorld::pusher();
    let domain = world.domain();
    let d_max = world.d_max();
    let dim = domain.feature_dim();
    let mut rng = ChaCha8Rng::seed_from_u64(0);

    // 1. Execute: the model's prediction, the robot's outcome, the deviation between them.
    let mut features = Vec::with_capacity(TRANSITIONS * dim);
    let mut deviations = Vec::with_capacity(TRANSITIONS);
    for _ in 0..TRANSITIONS {
        let s = domain.sample_state(&mut rng);
        let a = domain.sample_action(&s, &mut rng);
        let predicted = domain
            .dynamics()
            .predict_batch(&[&s], &[&a])?
            .remove(0)
            .next;
        let observed = world.step(&s, &a);
        features.extend(domain.features(&s, &a, &predicted));
        deviations.push(domain.distance(&predicted, &observed));
    }

    // 2. Fit the model deviation estimator: an exact GP on the features, its kernel and the
    //    cap on its training labels chosen from held-out judgements (as the server does).
    let x = DMatrix::from_row_slice(TRANSITIONS, dim, &features);
    let trajectories: Vec<i64> = (0..TRANSITIONS as i64).collect();
    let precondition = Precondition::new(BETA, d_max)?;
    let params = EstimatorParams::new(
        gp_params(NoiseMode::Homoscedastic, Kernel::Matern52, 0.0, 1, 0),
        DEFAULT_INDUCING_POINTS,
    )?;
    let fitted = fit_choosing_label_cap(
        Training {
            x: &x,
            deviations: &deviations,
            trajectories: &trajectories,
        },
        precondition,
        &[Kernel::Matern12, Kernel::Matern52],
        &[2.0, 5.0],
        EstimatorKind::Exact,
        &params,
    )?;
    let estimator = Estimator::Fitted(fitted.gp);
    println!(
        "fitted on {TRANSITIONS} transitions (d_max {d_max}, label cap {} d_max)",
        fitted.label_cap
    );

    // 3. Query: is a state-action trusted? Checked against the simulator's true deviation on
    //    fresh state-actions.
    let (mut trusted, mut right, mut wrongly_trusted) = (0, 0, 0);
    let queries = 1000;
    for _ in 0..queries {
        let s = domain.sample_state(&mut rng);
        let a = domain.sample_action(&s, &mut rng);
        let predicted = domain
            .dynamics()
            .predict_batch(&[&s], &[&a])?
            .remove(0)
            .next;
        let answer = estimator
            .answer(&domain.features(&s, &a, &predicted), dim)
            .remove(0);
        let is_trusted = precondition.inside(answer.mu, answer.sigma);
        let truly_within = world.true_deviation(&domain, &s, &a) < d_max;
        trusted += usize::from(is_trusted);
        right += usize::from(is_trusted == truly_within);
        wrongly_trusted += usize::from(is_trusted && !truly_within);
    }
    println!(
        "{queries} fresh state-actions: {trusted} trusted, judged right {right}, \
         trusted but beyond d_max {wrongly_trusted}"
    );

    // 4. Plan inside the precondition, then execute the plan on the robot.
    let settings = PlanningSettings::default();
    let planner = Planner::new(&domain, &estimator, &settings);
    let (mut found, mut reached) = (0, 0);
    let problems = 10;
    for k in 0..problems {
        let problem = world.sample_problem(&domain, &mut rng);
        let Some(plan) = planner.plan(&problem, precondition, k)?.trajectory else {
            continue;
        };
        found += 1;
        let mut s = plan.states[0].clone();
        for a in &plan.actions {
            s = world.step(&s, a);
        }
        reached += usize::from(domain.is_goal(&s, problem.goal()));
    }
    println!("{problems} problems: {found} plans found, {reached} reached the goal open loop");
    Ok(())
}
