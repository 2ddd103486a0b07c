//! `precond bench refit`: what a refit after one more batch costs, from scratch (model selection
//! over every candidate kernel and label cap, each from several starts: how every refit ran
//! before warm refits) and warm (the previous version's kernel and cap, its optimum as the
//! only start), on the same data, with the same held-out judgement of both.
//!
//! The data are a continuous world's (its simulator gives each held-out state-action's true
//! deviation): `n` transitions drawn uniformly over the space in trajectories of ten, then one
//! batch of `batch` more. Version 1 is fitted from scratch on the first `n`; the refit on all
//! `n + batch` is then made both ways. Quality is judged on uniform held-out state-actions at
//! β = 2: TPR, TNR and the held-out log score (the mean `log Φ(±(d_max − μ)/σ)` of the side of
//! `d_max` each fell on; 0 is perfect).

use nalgebra::DMatrix;
use precond::settings::{AUTO_LABEL_CAPS, KernelChoice};
use precond_core::domain::{Domain, LocalModel};
use precond_core::gp::Prediction;
use precond_core::gp::{NoiseMode, WarmStart};
use precond_core::mde::{
    Carry, EstimatorKind, EstimatorParams, Training, fit_choosing_label_cap, gp_params,
    normal_tail, refit_warm,
};
use precond_core::planning::{Agreement, Precondition};
use precond_core::sim::ContinuousWorld;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

/// What to measure.
#[derive(Debug, Clone)]
pub struct RefitBenchOptions {
    /// The world whose data are fitted.
    pub world: ContinuousWorld,
    /// Transitions of the first version.
    pub n: usize,
    /// Transitions of the batch that follows.
    pub batch: usize,
    /// Held-out state-actions.
    pub held_out: usize,
    /// Seeds the data and the fits.
    pub seed: u64,
}

/// One refit's cost and quality.
#[derive(Debug, Clone)]
pub struct RefitFigures {
    /// Wall seconds.
    pub seconds: f64,
    /// The phases it reported.
    pub phases: Vec<(String, f64)>,
    /// True-positive rate on the held-out state-actions (β = 2).
    pub tpr: f64,
    /// True-negative rate.
    pub tnr: f64,
    /// Held-out log score.
    pub log_score: f64,
    /// The kernel and label cap it answered with.
    pub kernel: String,
    /// The label cap.
    pub label_cap: f64,
}

/// Uniform state-actions of `world` with their features and true deviations.
fn sample(
    world: &ContinuousWorld,
    domain: &dyn LocalModel,
    n: usize,
    rng: &mut ChaCha8Rng,
) -> (Vec<f64>, Vec<f64>) {
    let (mut features, mut deviations) = (Vec::new(), Vec::new());
    while deviations.len() < n {
        let s = domain.sample_state(rng);
        if !world.possible(&s) {
            continue;
        }
        let a = domain.sample_action(&s, rng);
        let d = domain.distance(&domain.predict(&s, &a), &world.step(&s, &a));
        features.extend(domain.features(&s, &a, &[]));
        deviations.push(d);
    }
    (features, deviations)
}

/// Judges `p` against the held-out truth.
fn judge(p: &Prediction, truth: &[f64], precondition: Precondition) -> (f64, f64, f64) {
    let mut agreement = Agreement::default();
    let mut score = 0.0;
    let d_max = precondition.d_max();
    for (k, d) in truth.iter().enumerate() {
        let sd = (p.latent_variance[k] + p.noise_variance[k])
            .max(1e-300)
            .sqrt();
        agreement.count(*d, d_max, precondition.inside(p.mean[k], sd));
        let z = (d_max - p.mean[k]) / sd;
        score += if *d < d_max {
            normal_tail(-z).max(1e-300).ln()
        } else {
            normal_tail(z).max(1e-300).ln()
        };
    }
    (
        agreement.tpr().unwrap_or(f64::NAN),
        agreement.tnr().unwrap_or(f64::NAN),
        score / truth.len().max(1) as f64,
    )
}

/// Runs the comparison; prints and returns `(cold, warm)`.
pub fn run(o: &RefitBenchOptions) -> anyhow::Result<(RefitFigures, RefitFigures)> {
    let domain = o.world.domain();
    let dim = domain.feature_dim();
    let d_max = o.world.d_max();
    let precondition = Precondition::new(2.0, d_max)?;
    let mut rng = ChaCha8Rng::seed_from_u64(o.seed);
    let total = o.n + o.batch;
    let (features, deviations) = sample(&o.world, &domain, total, &mut rng);
    let (held_features, held_truth) = sample(&o.world, &domain, o.held_out, &mut rng);
    let held = DMatrix::from_row_slice(held_truth.len(), dim, &held_features);
    let trajectories: Vec<i64> = (0..total).map(|i| (i / 10) as i64).collect();
    let kernels = KernelChoice::Auto.candidates();
    let caps: Vec<f64> = AUTO_LABEL_CAPS.iter().copied().chain([0.0]).collect();
    let params = EstimatorParams::new(
        gp_params(NoiseMode::Heteroscedastic, kernels[0], 0.0, 2, o.seed),
        precond_core::gp::DEFAULT_INDUCING_POINTS,
    )?;
    let training = |n: usize, x: &DMatrix<f64>| {
        (
            x.rows(0, n).into_owned(),
            deviations[..n].to_vec(),
            trajectories[..n].to_vec(),
        )
    };
    let all = DMatrix::from_row_slice(total, dim, &features);
    let (x1, d1, t1) = training(o.n, &all);
    let first = fit_choosing_label_cap(
        Training {
            x: &x1,
            deviations: &d1,
            trajectories: &t1,
        },
        precondition,
        &kernels,
        &caps,
        EstimatorKind::Exact,
        &params,
    )?;
    let h = first
        .gp
        .hyperparameters()
        .ok_or_else(|| {
            precond_core::gp::GpError::InvalidState("an exact GP has hyperparameters".into())
        })?
        .clone();
    let noise = first.gp.noise_summary().map(|s| s.noise_model);
    let carry = Carry {
        kernel: h.kernel,
        label_cap: first.label_cap,
        warm: WarmStart::of(&h, noise.as_ref()),
    };
    let (x2, d2, t2) = training(total, &all);
    let data = || Training {
        x: &x2,
        deviations: &d2,
        trajectories: &t2,
    };
    let figures = |started: Instant, c: precond_core::mde::CapChoice| {
        let seconds = started.elapsed().as_secs_f64();
        let (tpr, tnr, log_score) = judge(&c.gp.predict(&held), &held_truth, precondition);
        RefitFigures {
            seconds,
            phases: c
                .phases
                .iter()
                .map(|p| (p.phase.clone(), p.seconds))
                .collect(),
            tpr,
            tnr,
            log_score,
            kernel: c
                .gp
                .hyperparameters()
                .map_or("(per expert)", |h| h.kernel.name())
                .to_string(),
            label_cap: c.label_cap,
        }
    };
    let started = Instant::now();
    let cold = figures(
        started,
        fit_choosing_label_cap(
            data(),
            precondition,
            &kernels,
            &caps,
            EstimatorKind::Exact,
            &params,
        )?,
    );
    let started = Instant::now();
    let warm = figures(
        started,
        refit_warm(data(), precondition, &carry, EstimatorKind::Exact, &params)?,
    );
    println!(
        "{} world, {} transitions then one batch of {}, exact GP, default model selection \
         (kernels {}, label caps 2, 5 and raw); {} held-out state-actions, β = 2",
        o.world.name(),
        o.n,
        o.batch,
        kernels.len(),
        held_truth.len()
    );
    println!(
        "{:<26} {:>8} {:>6} {:>6} {:>9} {:>9} {:>5}",
        "refit", "seconds", "TPR", "TNR", "log score", "kernel", "cap"
    );
    for (name, f) in [("from scratch (before)", &cold), ("warm (today)", &warm)] {
        println!(
            "{name:<26} {:>8.2} {:>6.3} {:>6.3} {:>9.4} {:>9} {:>5}",
            f.seconds, f.tpr, f.tnr, f.log_score, f.kernel, f.label_cap
        );
        for (phase, secs) in &f.phases {
            println!("    {phase:<40} {secs:>7.2} s");
        }
    }
    println!(
        "warm / from scratch: {:.3} of the time",
        warm.seconds / cold.seconds.max(1e-9)
    );
    Ok((cold, warm))
}
