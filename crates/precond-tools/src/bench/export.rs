//! `precond bench export`: the exported model ([`ExportedModel`]) against the server's own
//! prediction path, on the kinematic domain (4 features) with heteroscedastic noise — time per
//! point of `ExportedModel::evaluate_with` and of the server's one-point `answer`, the largest
//! relative differences of `μ` and `σ` on random state-actions, and the document's size.

use nalgebra::{DMatrix, DVector};
use precond_core::domain::{Domain, Kinematic, KinematicParams};
use precond_core::gp::{GpModel, GpParams, NoiseMode, SparseGp, SparseParams};
use precond_core::mde::export::Scratch;
use precond_core::mde::{Estimator, ExportedModel, Regressor, ServedModel};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

/// Runs the benchmark for exact GPs of `exact_sizes` training points and sparse GPs of
/// `sparse_sizes` points with `inducing` inducing points, and prints one line each.
pub fn run(exact_sizes: &[usize], sparse_sizes: &[usize], inducing: usize) -> anyhow::Result<()> {
    let domain = Kinematic::new(KinematicParams::default())?;
    println!(
        "estimator      n     m   doc MB   export µs/pt   server µs/pt   max rel Δμ   max rel Δσ"
    );
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for (sparse, n) in exact_sizes
        .iter()
        .map(|n| (false, *n))
        .chain(sparse_sizes.iter().map(|n| (true, *n)))
    {
        let (x, y) = data(&domain, n, &mut rng);
        let gp = GpParams {
            noise: NoiseMode::Heteroscedastic,
            restarts: 0,
            ..GpParams::default()
        };
        let regressor: Box<dyn Regressor> = if sparse {
            let params = SparseParams {
                gp,
                inducing_points: inducing,
                ..SparseParams::default()
            };
            Box::new(SparseGp::fit(&x, &y, &params.check()?)?)
        } else {
            Box::new(GpModel::fit(&x, &y, &gp.check()?)?)
        };
        let m = if sparse { inducing.min(n) } else { n };
        let served = ServedModel {
            version: 1,
            estimator: Estimator::Fitted(regressor),
            fit: None,
            further: Default::default(),
        };
        let exported = ExportedModel::of(1, &served, &domain, 0.05, 2.0)
            .ok_or_else(|| anyhow::anyhow!("a fitted model exports"))?;
        let doc = serde_json::to_string(&exported)?;
        let exported: ExportedModel = serde_json::from_str(&doc)?;
        exported.check().map_err(|e| anyhow::anyhow!(e))?;
        let points: Vec<(Vec<f64>, Vec<f64>)> = (0..1000)
            .map(|_| {
                let s = domain.sample_state(&mut rng);
                let a = domain.sample_action(&s, &mut rng);
                (s, a)
            })
            .collect();
        let dim = domain.feature_dim();
        let mut scratch = Scratch::default();
        let (mut worst_mu, mut worst_sigma) = (0.0f64, 0.0f64);
        let started = Instant::now();
        let mine: Vec<(f64, f64)> = points
            .iter()
            .map(|(s, a)| exported.evaluate_with(s, a, &[], &mut scratch))
            .collect();
        let export_time = started.elapsed().as_secs_f64() / points.len() as f64;
        let started = Instant::now();
        let theirs: Vec<_> = points
            .iter()
            .map(|(s, a)| served.answer(&domain.features(s, a, &[]), dim)[0].clone())
            .collect();
        let server_time = started.elapsed().as_secs_f64() / points.len() as f64;
        for ((mu, sigma), want) in mine.iter().zip(&theirs) {
            worst_mu = worst_mu.max((mu - want.mu).abs() / (1.0 + want.mu.abs()));
            worst_sigma = worst_sigma.max((sigma - want.sigma).abs() / (1.0 + want.sigma));
        }
        println!(
            "{:<9} {n:>6} {m:>5} {:>8.2} {:>14.2} {:>14.2} {worst_mu:>12.1e} {worst_sigma:>12.1e}",
            if sparse { "sparse" } else { "exact" },
            doc.len() as f64 / 1e6,
            export_time * 1e6,
            server_time * 1e6,
        );
    }
    Ok(())
}

/// `n` random kinematic state-actions and a deviation that grows to the right, with noise.
fn data(domain: &Kinematic, n: usize, rng: &mut ChaCha8Rng) -> (DMatrix<f64>, DVector<f64>) {
    let dim = domain.feature_dim();
    let mut features = Vec::with_capacity(n * dim);
    let mut labels = Vec::with_capacity(n);
    for _ in 0..n {
        let s = domain.sample_state(rng);
        let a = domain.sample_action(&s, rng);
        features.extend(domain.features(&s, &a, &[]));
        let push = if s[0] > 0.5 { 0.08 } else { 0.0 };
        labels.push(push + 0.01 * rng.random::<f64>());
    }
    (
        DMatrix::from_row_slice(n, dim, &features),
        DVector::from_vec(labels),
    )
}
