//! Tests of the sparse GP: the bound's gradient, agreement with the exact GP when the inducing
//! inputs are the training inputs, online updates, save/restore, scale and degenerate data.

use approx::assert_relative_eq;
use nalgebra::{DMatrix, DVector};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::super::kernel::Inputs;
use super::super::lml::{Jitter, NoiseSpec, Objective};
use super::super::{GpModel, GpParams, Hyperparameters, Kernel, ModelState, NoiseMode};
use super::bound::Bound;
use super::core::Ladder;
use super::*;

fn data(n: usize, d: usize, seed: u64) -> (DMatrix<f64>, DVector<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let x = DMatrix::from_fn(n, d, |_, _| rng.random::<f64>());
    let y = DVector::from_fn(n, |i, _| {
        (4.0 * x[(i, 0)]).sin() + x.row(i).sum() * 0.3 + 0.05 * (rng.random::<f64>() - 0.5)
    });
    (x, y)
}

/// The first `m` rows of `x` as inducing inputs (they are random, hence spread out).
fn first_rows(x: &DMatrix<f64>, m: usize) -> Inputs {
    Inputs::from_matrix(&x.rows(0, m).into_owned())
}

fn check_gradient(bound: &mut Bound<'_>, theta: &[f64], what: &str) {
    let p = bound.n_params();
    assert_eq!(p, theta.len());
    let mut g = vec![0.0; p];
    let f = bound.eval(theta, &mut g);
    assert!(f.is_finite(), "{what}: f = {f}");
    let mut scratch = vec![0.0; p];
    for k in 0..p {
        let h = 1e-5;
        let mut tp = theta.to_vec();
        tp[k] += h;
        let fp = bound.eval(&tp, &mut scratch);
        tp[k] -= 2.0 * h;
        let fm = bound.eval(&tp, &mut scratch);
        let fd = (fp - fm) / (2.0 * h);
        assert!(
            (g[k] - fd).abs() <= 1e-6 + 2e-5 * fd.abs(),
            "{what}: ∂/∂θ_{k} analytic {} vs finite differences {fd}",
            g[k]
        );
    }
}

const LADDER: Ladder = Ladder::Relative {
    initial: 1e-6,
    max: 1e-4,
};

#[test]
fn bound_gradient_matches_finite_differences() {
    let (x, y) = data(90, 3, 2);
    let inputs = Inputs::from_matrix(&x);
    let z = first_rows(&x, 25);
    let r: Vec<f64> = y.iter().map(|v| v - 0.2).collect();
    let fixed: Vec<f64> = (0..90).map(|i| 0.005 + 0.001 * i as f64).collect();
    for kernel in Kernel::ALL {
        let mut b = Bound::new(&inputs, &z, &r, NoiseSpec::Homoscedastic, kernel, LADDER);
        let theta = [
            0.4f64.ln(),
            0.9f64.ln(),
            2.0f64.ln(),
            0.7f64.ln(),
            0.02f64.ln(),
        ];
        check_gradient(&mut b, &theta, &format!("{kernel} homoscedastic"));
        let mut b = Bound::new(&inputs, &z, &r, NoiseSpec::Fixed(&fixed), kernel, LADDER);
        let theta = [0.2f64.ln(), 1.5f64.ln(), 0.6f64.ln(), 1.3f64.ln()];
        check_gradient(&mut b, &theta, &format!("{kernel} per-point noise"));
    }
}

#[test]
fn bound_gradient_is_right_over_many_chunks_and_threads() {
    // Enough points for several chunks per group and for the passes to run on all threads.
    let (x, y) = data(6000, 2, 3);
    let inputs = Inputs::from_matrix(&x);
    let z = first_rows(&x, 40);
    for kernel in [Kernel::Matern12, Kernel::Matern52] {
        let mut b = Bound::new(
            &inputs,
            &z,
            y.as_slice(),
            NoiseSpec::Homoscedastic,
            kernel,
            LADDER,
        );
        let theta = [0.3f64.ln(), 0.8f64.ln(), 0.0, 0.01f64.ln()];
        check_gradient(&mut b, &theta, &format!("{kernel} n = 6000"));
    }
}

/// Exact-GP settings with tiny jitter, matching the sparse one's.
fn exact_lml(x: &Inputs, r: &[f64], kernel: Kernel, theta: &[f64]) -> (f64, Vec<f64>) {
    let mut obj = Objective::new(
        x,
        r,
        NoiseSpec::Homoscedastic,
        kernel,
        Jitter {
            initial: 1e-10,
            max: 1e-4,
        },
    );
    let mut g = vec![0.0; theta.len()];
    let f = obj.eval(theta, &mut g);
    (-f, g.iter().map(|v| -v).collect())
}

#[test]
fn bound_equals_the_exact_lml_when_inducing_inputs_are_the_training_inputs() {
    let (x, y) = data(60, 2, 4);
    let inputs = Inputs::from_matrix(&x);
    let r: Vec<f64> = y.iter().map(|v| v - 0.1).collect();
    let tiny = Ladder::Relative {
        initial: 1e-12,
        max: 1e-4,
    };
    for kernel in Kernel::ALL {
        let theta = [0.5f64.ln(), 0.8f64.ln(), 0.7f64.ln(), 0.05f64.ln()];
        let mut b = Bound::new(&inputs, &inputs, &r, NoiseSpec::Homoscedastic, kernel, tiny);
        let mut g = vec![0.0; 4];
        let f = -b.eval(&theta, &mut g);
        let (lml, lml_grad) = exact_lml(&inputs, &r, kernel, &theta);
        assert_relative_eq!(f, lml, max_relative = 1e-7);
        for k in 0..4 {
            assert_relative_eq!(-g[k], lml_grad[k], epsilon = 1e-5, max_relative = 1e-5);
        }
    }
}

fn homo_sparse(m: usize) -> SparseParams {
    SparseParams {
        gp: GpParams {
            noise: NoiseMode::Homoscedastic,
            restarts: 1,
            seed: 5,
            ..GpParams::default()
        },
        inducing_points: m,
        ..SparseParams::default()
    }
}

#[test]
fn predictions_match_the_exact_gp_when_inducing_inputs_are_the_training_inputs() {
    let (x, y) = data(50, 2, 6);
    let p = SparseParams {
        jitter: 1e-12,
        ..homo_sparse(50)
    }
    .check()
    .unwrap();
    let sparse = SparseGp::fit_with_inducing(&x, &y, &x, &p).unwrap();
    // The exact GP with the sparse fit's hyperparameters.
    let state = ModelState {
        format: 1,
        noise: NoiseMode::Homoscedastic,
        n_train: 50,
        hyperparameters: sparse.hyperparameters().clone(),
        jitter: 0.0,
        log_marginal_likelihood: 0.0,
        noise_model: None,
    };
    let exact = GpModel::from_state(&x, &y, &state).unwrap();
    assert_relative_eq!(
        sparse.bound(),
        exact.log_marginal_likelihood(),
        max_relative = 1e-7
    );
    let (q, _) = data(40, 2, 7);
    let (a, b) = (sparse.predict(&q), exact.predict(&q));
    for j in 0..40 {
        assert_relative_eq!(a.mean[j], b.mean[j], epsilon = 1e-6);
        assert_relative_eq!(a.latent_variance[j], b.latent_variance[j], epsilon = 1e-6);
        assert_eq!(a.noise_variance[j], b.noise_variance[j]);
    }
    // And the fitted hyperparameters are the exact GP's optimum (same objective).
    let exact_fit = GpModel::fit(&x, &y, &p.gp.check().unwrap()).unwrap();
    assert_relative_eq!(
        sparse.bound(),
        exact_fit.log_marginal_likelihood(),
        max_relative = 1e-5
    );
}

#[allow(dead_code)]
fn unused(_: Hyperparameters) {}
