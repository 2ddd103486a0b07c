//! `precond bench mde`: how the MDE's settings judge a continuous world, on a run's own training
//! data. Reads the first `n` transitions an experiment of a harness database was trained on,
//! refits them under each candidate setting (kernel, noise model, label cap), and judges
//! uniform held-out state-actions whose true deviation the world's simulator gives: the share
//! of truly safe ones trusted (TPR) and of unsafe ones refused (TNR) at β = 2, with σ as served
//! (latent and noise) and with the latent part alone, and the median σ.
//!
//! Each setting is fitted by every requested estimator (the exact GP and the sparse GP, on the
//! same labels with the same kernel and cap), so the two can be compared on identical training
//! sets: besides the judgements, the fitted signal and noise variances, the median noise part
//! of σ, and the held-out log score — the mean `log Φ(±(d_max − μ)/σ)` the model gives to the
//! side of `d_max` each held-out state-action truly fell on (0 is perfect), which needs no
//! closed-form leave-out and so scores the sparse GP too.

use nalgebra::DMatrix;
use precond::store::Store;
use precond_core::domain::{Domain, IcyGridworld, LocalModel, MOVES};
use precond_core::gp::{Fold, Kernel, NoiseMode, Prediction};
use precond_core::mde::{
    BetaChoice, EstimatorKind, EstimatorParams, HeldOutTrust, Training, blocks, capped_labels,
    fit_choosing_label_cap, gp_params, identical_rows, normal_tail, trajectory_folds,
};
use precond_core::planning::{Agreement, Precondition};
use precond_core::sim::ContinuousWorld;
use precond_core::sim::Simulated;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

/// What to refit.
#[derive(Debug, Clone)]
pub struct MdeBenchOptions {
    /// The harness database (opened read-write on a copy is safest: migrations may run).
    pub db: String,
    /// The experiment whose transitions to refit.
    pub experiment: i64,
    /// Its first `n` transitions (all when `None`).
    pub n: Option<i64>,
    /// The world that produced them: a continuous world, or `None` for the icy gridworld's
    /// default map (held out: every cell's every move).
    pub world: Option<ContinuousWorld>,
    /// Held-out state-actions.
    pub held_out: usize,
    /// The estimators to fit each setting with.
    pub estimators: Vec<EstimatorKind>,
    /// Inducing points of the sparse GP.
    pub inducing_points: usize,
    /// The noise models to fit.
    pub noise: Vec<NoiseMode>,
    /// The label caps to fit (units of `d_max`; 0 = raw labels), one row each.
    pub label_caps: Vec<f64>,
    /// Instead of the settings table: the test β each way of grouping the training
    /// state-actions for leave-out certifies, and what the served model trusts at it on the
    /// uniform held-out state-actions ([`calibration`]).
    pub calibration: bool,
}

/// Runs the comparison and prints a table.
pub async fn run(o: MdeBenchOptions) -> anyhow::Result<()> {
    let store = Store::open(&o.db).await?;
    let transitions = store.transitions(o.experiment, 0, o.n).await?;
    anyhow::ensure!(
        !transitions.is_empty(),
        "experiment {} has no transitions",
        o.experiment
    );
    let grid = IcyGridworld::default_layout();
    let continuous = o.world.as_ref().map(|w| (w, w.domain()));
    let domain: &dyn LocalModel = match &continuous {
        Some((_, d)) => d,
        None => &grid,
    };
    let name = continuous
        .as_ref()
        .map_or("icy_gridworld", |(w, _)| w.name());
    let dim = domain.feature_dim();
    let d_max = continuous
        .as_ref()
        .map_or(grid.default_d_max(), |(w, _)| w.d_max());
    let mut features = Vec::with_capacity(transitions.len() * dim);
    let mut deviations = Vec::with_capacity(transitions.len());
    for t in &transitions {
        features.extend(domain.features(&t.s, &t.a, &t.s_pred));
        deviations.push(t.deviation);
    }
    let x = DMatrix::from_row_slice(deviations.len(), dim, &features);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut held = Vec::with_capacity(o.held_out);
    match &continuous {
        Some((world, domain)) => {
            while held.len() < o.held_out {
                let s = domain.sample_state(&mut rng);
                if !world.possible(&s) {
                    continue;
                }
                let a = domain.sample_action(&s, &mut rng);
                let d = domain.distance(&domain.predict(&s, &a), &world.step(&s, &a));
                held.push((domain.features(&s, &a, &[]), d));
            }
        }
        None => {
            let mut sim = grid.world();
            for cell in grid.open_cells() {
                for m in MOVES {
                    let s = cell.to_vec();
                    let pred = grid.predict(&s, &m);
                    if !grid.edge_allowed(&s, &m, &pred) {
                        continue;
                    }
                    let next = sim.step(&s, &m);
                    held.push((grid.features(&s, &m, &pred), grid.distance(&pred, &next)));
                }
            }
        }
    }
    let q = DMatrix::from_row_slice(
        held.len(),
        dim,
        &held.iter().flat_map(|(f, _)| f.clone()).collect::<Vec<_>>(),
    );
    let safe_share = held.iter().filter(|(_, d)| *d < d_max).count() as f64 / held.len() as f64;
    let trajectories: Vec<i64> = transitions.iter().map(|t| t.trajectory_id).collect();
    if o.calibration {
        return calibration(x, deviations, trajectories, &held, q, d_max).await;
    }
    println!(
        "{} experiment {}: {} training transitions ({:.2} within d_max = {d_max}), {} held-out \
         state-actions ({safe_share:.2} within)",
        name,
        o.experiment,
        deviations.len(),
        deviations.iter().filter(|d| **d < d_max).count() as f64 / deviations.len() as f64,
        held.len()
    );
    println!(
        "{:<10} {:<6} {:<15} {:>6} | {:>5} {:>5} {:>7} | {:>5} {:>5} {:>7} {:>7} | {:>9} {:>9} \
         {:>9} {:>7} {:>9} {:>7} {:>7} {:>7} {:>6}",
        "kernel",
        "est",
        "noise",
        "cap",
        "TPR",
        "TNR",
        "σ med",
        "TPR·l",
        "TNR·l",
        "σl med",
        "σn med",
        "s²",
        "noise var",
        "min ℓ",
        "LOO lp",
        "LML",
        "blk3 lp",
        "blk5 lp",
        "test lp",
        "s"
    );
    let precondition = Precondition::new(2.0, d_max)?;
    for kernel in [Kernel::Matern12, Kernel::Matern32, Kernel::Matern52] {
        for &noise in &o.noise {
            for (caps, &kind) in o
                .label_caps
                .iter()
                .flat_map(|&cap| o.estimators.iter().map(move |kind| (vec![cap], kind)))
            {
                let params =
                    EstimatorParams::new(gp_params(noise, kernel, 0.0, 2, 7), o.inducing_points)?;
                let t0 = Instant::now();
                let (x_all, deviations_all) = (x.clone(), deviations.clone());
                let (x, deviations, caps) = (x.clone(), deviations.clone(), caps.clone());
                let trajectories = trajectories.clone();
                let auto = caps.len() > 1;
                let choice = tokio::task::spawn_blocking(move || {
                    fit_choosing_label_cap(
                        Training {
                            x: &x,
                            deviations: &deviations,
                            trajectories: &trajectories,
                        },
                        precondition,
                        &[kernel],
                        &caps,
                        kind,
                        &params,
                    )
                })
                .await??;
                let seconds = t0.elapsed().as_secs_f64();
                let p = choice.gp.predict(&q);
                let judge = |latent_only: bool| {
                    let mut agreement = Agreement::default();
                    let mut sigmas: Vec<f64> = Vec::with_capacity(held.len());
                    for (k, (_, d)) in held.iter().enumerate() {
                        let var = p.latent_variance[k]
                            + if latent_only {
                                0.0
                            } else {
                                p.noise_variance[k]
                            };
                        let sd = var.max(0.0).sqrt();
                        sigmas.push(sd);
                        agreement.count(*d, d_max, precondition.inside(p.mean[k], sd));
                    }
                    sigmas.sort_by(f64::total_cmp);
                    (
                        agreement.tpr().unwrap_or(0.0),
                        agreement.tnr().unwrap_or(0.0),
                        sigmas[sigmas.len() / 2],
                    )
                };
                let (tpr, tnr, med) = judge(false);
                let (tpr_l, tnr_l, med_l) = judge(true);
                let med_n = median_noise_sd(&p);
                let test_lp = held_out_log_score(&p, &held, d_max);
                let h = choice.gp.hyperparameters().ok_or_else(|| {
                    anyhow::anyhow!("the bench fits exact GPs, which have hyperparameters")
                })?;
                let min_l = h
                    .length_scales
                    .iter()
                    .copied()
                    .fold(f64::INFINITY, f64::min);
                let loo = choice
                    .trials
                    .iter()
                    .find(|t| t.label_cap == choice.label_cap)
                    .map_or(f64::NAN, |t| t.log_score);
                let lml = choice.gp.log_marginal_likelihood();
                let labels = capped_labels(&deviations_all, choice.label_cap, d_max);
                let block_lp = |bins: usize| {
                    HeldOutTrust::of(
                        choice.gp.as_ref(),
                        choice.label_cap,
                        &labels,
                        &deviations_all,
                        &blocks(&x_all, bins),
                        precondition,
                    )
                    .map_or(f64::NAN, |(t, _)| t.log_score)
                };
                let (b3, b5) = (block_lp(3), block_lp(5));
                println!(
                    "{:<10} {:<6} {:<15} {:>6} | {tpr:>5.2} {tnr:>5.2} {med:>7.4} | \
                     {tpr_l:>5.2} {tnr_l:>5.2} {med_l:>7.4} {med_n:>7.4} | {:>9.2e} {:>9.2e} \
                     {min_l:>9.3} {loo:>7.4} {lml:>9.1} {b3:>7.4} {b5:>7.4} {test_lp:>7.4} \
                     {seconds:>6.1}",
                    kernel.name(),
                    kind.as_str(),
                    format!("{noise:?}").to_lowercase(),
                    if auto {
                        format!("a:{}", choice.label_cap)
                    } else if choice.label_cap > 0.0 {
                        format!("{}", choice.label_cap)
                    } else {
                        "raw".into()
                    },
                    h.signal_variance,
                    h.noise_variance,
                );
            }
        }
    }
    Ok(())
}

/// The test β certified ([`BetaChoice`]) by the model the default settings fit (every kernel,
/// the automatic label caps, heteroscedastic noise), with the training state-actions left out
/// in groups of each kind — every copy of a state-action (what fits record), a whole executed
/// trajectory with every copy of its state-actions, a block of a regular grid of 2, 3 or 4
/// cells per feature — and what the model trusts at each certified β on the uniform held-out
/// state-actions: the certified false-trust rate against the one met on unseen moves.
async fn calibration(
    x: DMatrix<f64>,
    deviations: Vec<f64>,
    trajectories: Vec<i64>,
    held: &[(Vec<f64>, f64)],
    q: DMatrix<f64>,
    d_max: f64,
) -> anyhow::Result<()> {
    let precondition = Precondition::new(2.0, d_max)?;
    let params = EstimatorParams::new(
        gp_params(NoiseMode::Heteroscedastic, Kernel::Matern12, 0.0, 2, 7),
        precond_core::gp::DEFAULT_INDUCING_POINTS,
    )?;
    let mut caps = precond::settings::AUTO_LABEL_CAPS.to_vec();
    caps.push(0.0);
    let (xf, df, tf) = (x.clone(), deviations.clone(), trajectories.clone());
    let choice = tokio::task::spawn_blocking(move || {
        fit_choosing_label_cap(
            Training {
                x: &xf,
                deviations: &df,
                trajectories: &tf,
            },
            precondition,
            &Kernel::ALL,
            &caps,
            EstimatorKind::Exact,
            &params,
        )
    })
    .await??;
    let labels = capped_labels(&deviations, choice.label_cap, d_max);
    let p = choice.gp.predict(&q);
    let sd = p.std();
    println!(
        "served fit: kernel {}, label cap {}",
        choice
            .gp
            .hyperparameters()
            .map_or("(per expert)", |h| h.kernel.name()),
        choice.label_cap
    );
    println!(
        "{:<12} {:>7} {:>6} | {:>5} {:>8} {:>9} | {:>5} {:>5} {:>11}",
        "groups", "groups", "β", "unsafe", "trusted", "certified", "TPR", "TNR", "false trust"
    );
    let by: Vec<(String, Option<Vec<Fold>>)> = vec![
        ("copies".into(), Some(Fold::whole(&identical_rows(&x)))),
        ("trajectory".into(), trajectory_folds(&x, &trajectories)),
        ("blocks 2".into(), Some(Fold::whole(&blocks(&x, 2)))),
        ("blocks 3".into(), Some(Fold::whole(&blocks(&x, 3)))),
        ("blocks 4".into(), Some(Fold::whole(&blocks(&x, 4)))),
    ];
    for (name, folds) in by {
        let Some(folds) = folds else {
            println!("{name:<12} folds beyond the leave-out's budget");
            continue;
        };
        let Some(h) = choice.gp.leave_folds_out(&folds) else {
            println!("{name:<12} no closed-form leave-out");
            continue;
        };
        let c = BetaChoice::from_held_out(&h, &labels, &deviations, d_max, 2.0);
        let mut agreement = Agreement::default();
        for (k, (_, d)) in held.iter().enumerate() {
            agreement.count(*d, d_max, p.mean[k] + c.beta * sd[k] < d_max);
        }
        let tnr = agreement.tnr().unwrap_or(f64::NAN);
        println!(
            "{name:<12} {:>7} {:>6.1} | {:>5} {:>8} {:>9.3} | {:>5.2} {:>5.3} {:>11.3}",
            folds.len(),
            c.beta,
            c.unsafe_transitions,
            c.trusted_unsafe,
            (c.trusted_unsafe as f64 + 1.0) / (c.unsafe_transitions as f64 + 2.0),
            agreement.tpr().unwrap_or(f64::NAN),
            tnr,
            1.0 - tnr,
        );
    }
    Ok(())
}

/// The median noise part `√noise` of the predictions' σ.
fn median_noise_sd(p: &Prediction) -> f64 {
    let mut sd: Vec<f64> = p.noise_variance.iter().map(|v| v.max(0.0).sqrt()).collect();
    sd.sort_by(f64::total_cmp);
    sd.get(sd.len() / 2).copied().unwrap_or(f64::NAN)
}

/// The mean log probability predictions `p` give to the side of `d_max` each held-out
/// state-action's true deviation fell on: `log Φ((d_max − μ)/σ)` for a safe one,
/// `log Φ((μ − d_max)/σ)` for an unsafe one (0 is perfect).
fn held_out_log_score(p: &Prediction, held: &[(Vec<f64>, f64)], d_max: f64) -> f64 {
    let sd = p.std();
    let total: f64 = held
        .iter()
        .enumerate()
        .map(|(k, (_, d))| {
            let z = (d_max - p.mean[k]) / sd[k];
            let correct = if *d < d_max {
                normal_tail(-z)
            } else {
                normal_tail(z)
            };
            correct.max(1e-300).ln()
        })
        .sum();
    total / held.len().max(1) as f64
}
