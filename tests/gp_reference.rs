//! The GP against scikit-learn fixtures (made by `scripts/make_gp_fixtures.py`), and the
//! heteroscedastic fit against known noise levels.

use nalgebra::{DMatrix, DVector};
use precond_core::gp::{GpModel, GpParams, Hyperparameters, Kernel, ModelState, NoiseMode};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::Deserialize;

#[derive(Deserialize)]
struct Fixed {
    length_scales: Vec<f64>,
    signal_variance: f64,
    noise_variance: f64,
    lml: f64,
    mean: Vec<f64>,
    std: Vec<f64>,
}

#[derive(Deserialize)]
struct Fitted {
    restarts: usize,
    lml: f64,
}

#[derive(Deserialize)]
struct Fixture {
    name: String,
    /// The Matérn smoothness (2.5 when absent).
    #[serde(default = "paper_nu")]
    nu: f64,
    prior_mean: f64,
    x: Vec<Vec<f64>>,
    y: Vec<f64>,
    x_test: Vec<Vec<f64>>,
    fixed: Fixed,
    fitted: Fitted,
}

fn paper_nu() -> f64 {
    2.5
}

impl Fixture {
    fn kernel(&self) -> Kernel {
        match self.nu {
            0.5 => Kernel::Matern12,
            1.5 => Kernel::Matern32,
            2.5 => Kernel::Matern52,
            other => panic!("{}: no kernel with nu = {other}", self.name),
        }
    }
}

const FIXTURES: [&str; 5] = [
    include_str!("fixtures/gp/d2_n40.json"),
    include_str!("fixtures/gp/d3_n60_mean.json"),
    include_str!("fixtures/gp/d4_n80_small_noise.json"),
    include_str!("fixtures/gp/d2_n40_nu05.json"),
    include_str!("fixtures/gp/d3_n60_nu15.json"),
];

fn fixtures() -> Vec<Fixture> {
    FIXTURES
        .iter()
        .map(|s| serde_json::from_str(s).expect("fixture parses"))
        .collect()
}

fn matrix(rows: &[Vec<f64>]) -> DMatrix<f64> {
    DMatrix::from_fn(rows.len(), rows[0].len(), |i, j| rows[i][j])
}

fn assert_rel(ours: f64, theirs: f64, rel: f64, what: &str) {
    let tol = rel * theirs.abs().max(1e-3);
    assert!(
        (ours - theirs).abs() <= tol,
        "{what}: ours {ours} vs sklearn {theirs} (tolerance {tol:e})"
    );
}

#[test]
fn predictions_and_lml_match_sklearn_at_fixed_hyperparameters() {
    for f in fixtures() {
        let x = matrix(&f.x);
        let y = DVector::from_vec(f.y.clone());
        let state = ModelState {
            format: 1,
            noise: NoiseMode::Homoscedastic,
            n_train: f.y.len(),
            hyperparameters: Hyperparameters {
                length_scales: f.fixed.length_scales.clone(),
                signal_variance: f.fixed.signal_variance,
                noise_variance: f.fixed.noise_variance,
                prior_mean: f.prior_mean,
                kernel: f.kernel(),
            },
            jitter: 0.0,
            log_marginal_likelihood: f64::NAN,
            noise_model: None,
        };
        let model = GpModel::from_state(&x, &y, &state).expect("model builds");
        assert_rel(
            model.log_marginal_likelihood(),
            f.fixed.lml,
            1e-6,
            &format!("{} LML", f.name),
        );
        let pred = model.predict(&matrix(&f.x_test));
        let std = pred.std();
        for (j, (m, sd)) in pred.mean.iter().zip(&std).enumerate() {
            assert_rel(*m, f.fixed.mean[j], 1e-6, &format!("{} mean[{j}]", f.name));
            assert_rel(*sd, f.fixed.std[j], 1e-6, &format!("{} std[{j}]", f.name));
        }
    }
}

#[test]
fn fitted_lml_is_at_least_sklearns() {
    for f in fixtures() {
        let x = matrix(&f.x);
        let y = DVector::from_vec(f.y.clone());
        let params = GpParams {
            noise: NoiseMode::Homoscedastic,
            kernel: f.kernel(),
            prior_mean: f.prior_mean,
            restarts: f.fitted.restarts,
            seed: 7,
            ..GpParams::default()
        }
        .check()
        .expect("valid params");
        let model = GpModel::fit(&x, &y, &params).expect("fit succeeds");
        let ours = model.log_marginal_likelihood();
        let floor = f.fitted.lml - 1e-3 * f.fitted.lml.abs();
        assert!(
            ours >= floor,
            "{}: our fitted LML {ours} < sklearn's {} − 1e-3·|LML|",
            f.name,
            f.fitted.lml
        );
    }
}

/// Smooth target on [0,1]²; noise std 0.02 where x₀ < 0.5 and 0.3 where x₀ ≥ 0.5.
fn two_level_data(n: usize, rng: &mut ChaCha8Rng) -> (DMatrix<f64>, DVector<f64>) {
    let x = DMatrix::from_fn(n, 2, |_, _| rng.random::<f64>());
    let y = DVector::from_fn(n, |i, _| {
        let (a, b) = (x[(i, 0)], x[(i, 1)]);
        let sd = if a < 0.5 { 0.02 } else { 0.3 };
        (2.0 * a).sin() + 0.5 * (3.0 * b).cos() + sd * rng.sample::<f64, _>(StandardNormal)
    });
    (x, y)
}

fn nlpd(model: &GpModel, x: &DMatrix<f64>, y: &DVector<f64>) -> f64 {
    let p = model.predict(x);
    let var = p.variance();
    (0..y.len())
        .map(|i| {
            0.5 * (2.0 * std::f64::consts::PI * var[i]).ln()
                + (y[i] - p.mean[i]).powi(2) / (2.0 * var[i])
        })
        .sum::<f64>()
        / y.len() as f64
}

#[test]
fn heteroscedastic_fit_recovers_two_noise_levels_and_beats_homoscedastic() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (x, y) = two_level_data(300, &mut rng);
    let (xt, yt) = two_level_data(1000, &mut rng);
    let base = GpParams {
        restarts: 1,
        seed: 3,
        ..GpParams::default()
    };
    let hetero = GpModel::fit(&x, &y, &base.check().unwrap()).unwrap();
    let homo = GpModel::fit(
        &x,
        &y,
        &GpParams {
            noise: NoiseMode::Homoscedastic,
            ..base
        }
        .check()
        .unwrap(),
    )
    .unwrap();
    assert_eq!(hetero.noise_mode(), NoiseMode::Heteroscedastic);

    // Mean predicted noise standard deviation away from the boundary, per half.
    let probe = DMatrix::from_fn(400, 2, |i, j| {
        if j == 0 {
            if i < 200 {
                0.05 + 0.3 * (i as f64) / 200.0
            } else {
                0.65 + 0.3 * ((i - 200) as f64) / 200.0
            }
        } else {
            ((i * 37) % 200) as f64 / 200.0
        }
    });
    let p = hetero.predict(&probe);
    let low = p.noise_variance[..200]
        .iter()
        .map(|v| v.sqrt())
        .sum::<f64>()
        / 200.0;
    let high = p.noise_variance[200..]
        .iter()
        .map(|v| v.sqrt())
        .sum::<f64>()
        / 200.0;
    eprintln!(
        "recovered noise std: {low:.4} (true 0.02), {high:.4} (true 0.3); summary {:?}",
        hetero.noise_summary()
    );
    assert!(
        (low / 0.02 - 1.0).abs() <= 0.3,
        "low-noise half: {low} vs 0.02"
    );
    assert!(
        (high / 0.3 - 1.0).abs() <= 0.3,
        "high-noise half: {high} vs 0.3"
    );

    let (nh, no) = (nlpd(&hetero, &xt, &yt), nlpd(&homo, &xt, &yt));
    eprintln!("held-out NLPD: heteroscedastic {nh:.4}, homoscedastic {no:.4}");
    assert!(
        nh < no,
        "heteroscedastic NLPD {nh} not better than homoscedastic {no}"
    );
}
