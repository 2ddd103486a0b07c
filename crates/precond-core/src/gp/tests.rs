//! Unit and property tests of the GP core: factorisation, gradients, invariants, round trips,
//! determinism and error handling.

use approx::assert_relative_eq;
use nalgebra::{DMatrix, DVector};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::hetero::{LOG_RESIDUAL_BIAS, log_residual_bias};
use super::kernel::{Inputs, build_train, matern52};
use super::lml::{Jitter, NoiseSpec, Objective, factorise};
use super::*;

const JITTER: Jitter = Jitter {
    initial: 1e-10,
    max: 1e-4,
};

/// `n` seeded random points in `[0, 1]^d` and smooth, slightly noisy targets at them (the sparse
/// GP's tests use them too).
pub(super) fn data(n: usize, d: usize, seed: u64) -> (DMatrix<f64>, DVector<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let x = DMatrix::from_fn(n, d, |_, _| rng.random::<f64>());
    let y = DVector::from_fn(n, |i, _| {
        (4.0 * x[(i, 0)]).sin() + x.row(i).sum() * 0.3 + 0.05 * (rng.random::<f64>() - 0.5)
    });
    (x, y)
}

/// GP settings with `noise`, `restarts` and `seed`, the rest default (the sparse GP's tests use
/// them too).
pub(super) fn gp_params(noise: NoiseMode, restarts: usize, seed: u64) -> GpParams {
    GpParams {
        noise,
        restarts,
        seed,
        ..GpParams::default()
    }
}

fn homo_params() -> ValidGpParams {
    gp_params(NoiseMode::Homoscedastic, 1, 5).check().unwrap()
}

#[test]
fn cholesky_factor_reproduces_the_covariance() {
    let (x, y) = data(60, 3, 1);
    let inputs = Inputs::from_matrix(&x);
    let ls = [0.3, 0.7, 1.1];
    let xs = inputs.scaled(&ls);
    let n = inputs.n;
    let noise = vec![0.01; n];
    let mut k = vec![0.0; n * n];
    build_train(Kernel::Matern52, &xs, n, 3, 0.9, &noise, &mut k, None);
    let fac = factorise(
        Kernel::Matern52,
        &xs,
        n,
        3,
        0.9,
        &noise,
        y.as_slice(),
        JITTER,
        0.0,
        vec![0.0; n * n],
        None,
    )
    .ok()
    .unwrap();
    assert_eq!(fac.jitter, 0.0);
    for j in 0..n {
        for i in j..n {
            let llt: f64 = (0..=j).map(|c| fac.l[c * n + i] * fac.l[c * n + j]).sum();
            assert_relative_eq!(llt, k[j * n + i], epsilon = 1e-12, max_relative = 1e-10);
        }
    }
    // K α = r
    for i in 0..n {
        let ka: f64 = (0..n)
            .map(|j| if i >= j { k[j * n + i] } else { k[i * n + j] } * fac.alpha[j])
            .sum();
        assert_relative_eq!(ka, y[i], epsilon = 1e-9);
    }
}

#[test]
fn kernel_matches_the_matern_formula() {
    let r: f64 = 0.37;
    let expected = 1.7 * (1.0 + 5f64.sqrt() * r + 5.0 / 3.0 * r * r) * (-(5f64.sqrt()) * r).exp();
    assert_relative_eq!(matern52(r * r, 1.7), expected, max_relative = 1e-14);
    assert_eq!(matern52(0.0, 2.5), 2.5);
    let m32 = 1.7 * (1.0 + 3f64.sqrt() * r) * (-(3f64.sqrt()) * r).exp();
    assert_relative_eq!(
        Kernel::Matern32.value(r * r, 1.7),
        m32,
        max_relative = 1e-14
    );
    assert_relative_eq!(
        Kernel::Matern12.value(r * r, 1.7),
        1.7 * (-r).exp(),
        max_relative = 1e-14
    );
    assert_eq!(Kernel::Matern52.value(r * r, 1.7), matern52(r * r, 1.7));
    for k in Kernel::ALL {
        assert_eq!(k.value(0.0, 2.5), 2.5);
        assert_eq!(k.value(f64::INFINITY, 2.5), 0.0);
        // Correlation falls with distance, and the rougher kernel falls faster at first.
        assert!(k.value(0.01, 1.0) > k.value(0.04, 1.0));
    }
    assert!(Kernel::Matern12.value(0.01, 1.0) < Kernel::Matern52.value(0.01, 1.0));
}

#[test]
fn every_kernel_builds_the_matrix_of_its_formula() {
    let (x, _) = data(20, 2, 4);
    let inputs = Inputs::from_matrix(&x);
    let xs = inputs.scaled(&[0.3, 0.6]);
    let n = inputs.n;
    for kernel in Kernel::ALL {
        let mut k = vec![0.0; n * n];
        let mut g = vec![0.0; n * n];
        build_train(kernel, &xs, n, 2, 0.8, &vec![0.0; n], &mut k, Some(&mut g));
        let mut c = vec![0.0; n * n];
        super::kernel::build_cross(kernel, &xs, n, &xs, n, 2, 0.8, &mut c);
        for j in 0..n {
            for i in j..n {
                let r2: f64 = (0..2)
                    .map(|d| (xs[d * n + i] - xs[d * n + j]).powi(2))
                    .sum();
                assert_relative_eq!(k[j * n + i], kernel.value(r2, 0.8), max_relative = 1e-13);
                assert_relative_eq!(c[j * n + i], kernel.value(r2, 0.8), max_relative = 1e-13);
            }
        }
    }
}

/// `f(θ)` and, per component of `θ`, the gradient `f` writes into its second argument beside
/// the central finite difference (step 1e-5) of `f` there (the sparse GP's tests use it too).
pub(super) fn gradient_vs_finite_differences(
    mut f: impl FnMut(&[f64], &mut [f64]) -> f64,
    theta: &[f64],
) -> (f64, Vec<(f64, f64)>) {
    let p = theta.len();
    let mut g = vec![0.0; p];
    let value = f(theta, &mut g);
    let mut scratch = vec![0.0; p];
    let pairs = (0..p)
        .map(|k| {
            let h = 1e-5;
            let mut tp = theta.to_vec();
            tp[k] += h;
            let fp = f(&tp, &mut scratch);
            tp[k] -= 2.0 * h;
            let fm = f(&tp, &mut scratch);
            (g[k], (fp - fm) / (2.0 * h))
        })
        .collect();
    (value, pairs)
}

fn check_gradient(kernel: Kernel, noise: NoiseSpec<'_>, x: &Inputs, r: &[f64], theta: &[f64]) {
    assert_eq!(noise.n_params(x.d), theta.len());
    let mut obj = Objective::new(x, r, noise, kernel, JITTER);
    let (f, pairs) = gradient_vs_finite_differences(|t, g| obj.eval(t, g), theta);
    assert!(f.is_finite());
    for (analytic, fd) in pairs {
        assert_relative_eq!(analytic, fd, epsilon = 1e-6, max_relative = 1e-5);
    }
}

#[test]
fn gradient_matches_finite_differences() {
    let (x, y) = data(70, 3, 2);
    let inputs = Inputs::from_matrix(&x);
    let r: Vec<f64> = y.iter().map(|v| v - 0.2).collect();
    let fixed: Vec<f64> = (0..70).map(|i| 0.005 + 0.001 * i as f64).collect();
    for kernel in Kernel::ALL {
        check_gradient(
            kernel,
            NoiseSpec::Homoscedastic,
            &inputs,
            &r,
            &[
                (0.4f64).ln(),
                (0.9f64).ln(),
                (2.0f64).ln(),
                (0.7f64).ln(),
                (0.02f64).ln(),
            ],
        );
        check_gradient(
            kernel,
            NoiseSpec::Fixed(&fixed),
            &inputs,
            &r,
            &[(0.2f64).ln(), (1.5f64).ln(), (0.6f64).ln(), (1.3f64).ln()],
        );
    }
}

#[test]
fn gradient_is_right_for_large_matrices_too() {
    // Above the thresholds where kernel builds and gradient sums run on several threads and
    // faer switches to its parallel kernels.
    let (x, y) = data(1300, 2, 3);
    let inputs = Inputs::from_matrix(&x);
    for kernel in [Kernel::Matern12, Kernel::Matern52] {
        check_gradient(
            kernel,
            NoiseSpec::Homoscedastic,
            &inputs,
            y.as_slice(),
            &[(0.3f64).ln(), (0.8f64).ln(), 0.0, (0.01f64).ln()],
        );
    }
}

#[test]
fn log_residual_bias_matches_quadrature_references() {
    // References from scipy.integrate.quad of −E[log(1 − ρ + ρu²)].
    assert_relative_eq!(
        log_residual_bias(1.0),
        LOG_RESIDUAL_BIAS,
        max_relative = 1e-12
    );
    assert_relative_eq!(
        log_residual_bias(0.99),
        1.038_180_838_349_033,
        max_relative = 1e-10
    );
    assert_relative_eq!(
        log_residual_bias(0.95),
        0.794_608_231_804_137,
        max_relative = 1e-10
    );
    assert_relative_eq!(
        log_residual_bias(0.5),
        0.159_694_000_715_810_7,
        max_relative = 1e-10
    );
    assert_eq!(log_residual_bias(0.0), 0.0);
}

#[test]
fn state_round_trips_exactly_through_json() {
    let (x, y) = data(40, 2, 4);
    for noise in [NoiseMode::Homoscedastic, NoiseMode::Heteroscedastic] {
        let params = gp_params(noise, 1, 9).check().unwrap();
        let model = GpModel::fit(&x, &y, &params).unwrap();
        assert_eq!(model.noise_mode(), noise);
        let (q, _) = data(25, 2, 5);
        let a = model.predict(&q);
        // The stored state itself rebuilds the model bit for bit.
        let exact = GpModel::from_state(&x, &y, &model.state()).unwrap();
        assert_eq!(exact.predict(&q), a);
        assert_eq!(
            exact.log_marginal_likelihood(),
            model.log_marginal_likelihood()
        );
        // Through JSON, serde_json (without its `float_roundtrip` feature) may misround a float
        // by one ulp; the model then agrees to ~1e-10 relative.
        let json = serde_json::to_string(&model.state()).unwrap();
        let state: ModelState = serde_json::from_str(&json).unwrap();
        let rebuilt = GpModel::from_state(&x, &y, &state).unwrap();
        let b = rebuilt.predict(&q);
        for j in 0..25 {
            assert_relative_eq!(a.mean[j], b.mean[j], max_relative = 1e-10, epsilon = 1e-10);
            assert_relative_eq!(
                a.latent_variance[j],
                b.latent_variance[j],
                max_relative = 1e-8,
                epsilon = 1e-10
            );
            assert_relative_eq!(
                a.noise_variance[j],
                b.noise_variance[j],
                max_relative = 1e-10
            );
        }
        assert_relative_eq!(
            model.log_marginal_likelihood(),
            rebuilt.log_marginal_likelihood(),
            max_relative = 1e-10
        );
    }
}

#[test]
fn same_seed_same_model() {
    let (x, y) = data(50, 3, 6);
    let params = GpParams {
        restarts: 2,
        seed: 42,
        ..GpParams::default()
    }
    .check()
    .unwrap();
    let a = GpModel::fit(&x, &y, &params).unwrap();
    let b = GpModel::fit(&x, &y, &params).unwrap();
    assert_eq!(a.state(), b.state());
    let (q, _) = data(10, 3, 7);
    assert_eq!(a.predict(&q), b.predict(&q));
}

#[test]
fn screening_on_a_subset_still_fits_well() {
    // n above screen_subset: the starts are screened on a subset, then refined on all data.
    let (x, y) = data(260, 2, 8);
    let screened = GpParams {
        noise: NoiseMode::Homoscedastic,
        restarts: 2,
        screen_subset: 64,
        ..GpParams::default()
    };
    let full = GpParams {
        screen_subset: 0,
        ..screened.clone()
    };
    let a = GpModel::fit(&x, &y, &screened.check().unwrap()).unwrap();
    let b = GpModel::fit(&x, &y, &full.check().unwrap()).unwrap();
    let (la, lb) = (a.log_marginal_likelihood(), b.log_marginal_likelihood());
    assert!(la >= lb - 1e-3 * lb.abs(), "screened {la} vs full {lb}");
}

#[test]
fn single_and_batched_predictions_agree() {
    let (x, y) = data(80, 2, 10);
    let model = GpModel::fit(&x, &y, &homo_params()).unwrap();
    let (q, _) = data(30, 2, 11);
    let batch = model.predict(&q);
    for j in 0..30 {
        let one = model.predict(&q.rows(j, 1).into_owned());
        assert_relative_eq!(
            one.mean[0],
            batch.mean[j],
            max_relative = 1e-12,
            epsilon = 1e-14
        );
        assert_relative_eq!(
            one.latent_variance[0],
            batch.latent_variance[j],
            max_relative = 1e-8,
            epsilon = 1e-13
        );
    }
}

/// Water-plant-like labels: exact zeros where the model is right, a cluster of spills (≈ 0.5,
/// noisy) in one corner, and a few spills scattered among the zeros.
fn zeros_and_spills(n: usize, seed: u64) -> (DMatrix<f64>, DVector<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let x = DMatrix::from_fn(n, 3, |_, _| rng.random::<f64>());
    let y = DVector::from_fn(n, |i, _| {
        let spill = x[(i, 0)] > 0.6 && x[(i, 1)] > 0.5;
        if spill || rng.random::<f64>() < 0.05 {
            0.5 + 0.3 * (rng.random::<f64>() - 0.5)
        } else {
            0.0
        }
    });
    (x, y)
}

#[test]
fn heteroscedastic_noise_never_exceeds_the_labels_variance() {
    for seed in 0..4 {
        let (x, y) = zeros_and_spills(120, seed);
        let n = y.len() as f64;
        let my = y.sum() / n;
        let var_y = y.iter().map(|v| (v - my) * (v - my)).sum::<f64>() / n;
        let model = GpModel::fit(&x, &y, &GpParams::default().check().unwrap()).unwrap();
        let summary = model.noise_summary().expect("heteroscedastic");
        assert!(
            summary.max_noise_variance <= var_y * (1.0 + 1e-9),
            "seed {seed}: a point's noise {} exceeds the labels' variance {var_y}",
            summary.max_noise_variance
        );
        assert!(
            model.hyperparameters().signal_variance > 1e-3,
            "seed {seed}: pure-noise fit"
        );
    }
}

#[test]
fn heteroscedastic_falls_back_on_tiny_data() {
    let (x, y) = data(5, 2, 12);
    let model = GpModel::fit(&x, &y, &GpParams::default().check().unwrap()).unwrap();
    assert_eq!(model.noise_mode(), NoiseMode::Homoscedastic);
    assert!(model.noise_summary().is_none());
    let (x, y) = data(1, 2, 12);
    let model = GpModel::fit(&x, &y, &GpParams::default().check().unwrap()).unwrap();
    assert_eq!(model.n_train(), 1);
    assert!(model.predict(&x).std()[0].is_finite());
}

#[test]
fn duplicate_points_without_noise_use_jitter_or_fail_cleanly() {
    let x = DMatrix::from_row_slice(4, 1, &[0.2, 0.2, 0.2, 0.7]);
    let y = DVector::from_row_slice(&[0.1, 0.1, 0.1, 0.5]);
    let h = Hyperparameters {
        length_scales: vec![0.5],
        signal_variance: 1.0,
        noise_variance: 0.0,
        prior_mean: 0.0,
        kernel: Kernel::Matern52,
    };
    let state = ModelState {
        format: 1,
        noise: NoiseMode::Homoscedastic,
        n_train: 4,
        hyperparameters: h,
        jitter: 0.0,
        log_marginal_likelihood: 0.0,
        noise_model: None,
    };
    // A rebuild uses exactly the stored jitter: a singular matrix is an error value.
    assert!(matches!(
        GpModel::from_state(&x, &y, &state),
        Err(GpError::NotPositiveDefinite { .. })
    ));
    // A fit with a tiny noise floor climbs the jitter ladder instead.
    let p = GpParams {
        noise: NoiseMode::Homoscedastic,
        bounds: Bounds {
            noise_variance: (1e-300, 1e-300),
            ..Bounds::MAIN
        },
        ..GpParams::default()
    };
    let model = GpModel::fit(&x, &y, &p.check().unwrap()).unwrap();
    assert!(model.jitter() > 0.0);
    let rebuilt = GpModel::from_state(&x, &y, &model.state()).unwrap();
    assert_eq!(rebuilt.predict(&x), model.predict(&x));
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let p = homo_params();
    let (x, y) = data(10, 2, 13);
    assert!(matches!(
        GpModel::fit(&DMatrix::zeros(0, 2), &DVector::zeros(0), &p),
        Err(GpError::EmptyData(_))
    ));
    assert!(matches!(
        GpModel::fit(&DMatrix::zeros(3, 0), &DVector::zeros(3), &p),
        Err(GpError::EmptyData(_))
    ));
    assert!(matches!(
        GpModel::fit(&x, &DVector::zeros(9), &p),
        Err(GpError::DimensionMismatch { .. })
    ));
    let mut xn = x.clone();
    xn[(3, 1)] = f64::NAN;
    assert_eq!(
        GpModel::fit(&xn, &y, &p).unwrap_err(),
        GpError::NonFinite {
            what: "x",
            index: 7
        }
    );
    let mut yn = y.clone();
    yn[4] = f64::INFINITY;
    assert_eq!(
        GpModel::fit(&x, &yn, &p).unwrap_err(),
        GpError::NonFinite {
            what: "y",
            index: 4
        }
    );

    let model = GpModel::fit(&x, &y, &p).unwrap();
    let wrong = DMatrix::zeros(3, 5);
    assert!(model.predict(&wrong).mean.iter().all(|v| v.is_nan()));
    assert!(matches!(
        model.try_predict(&wrong),
        Err(GpError::DimensionMismatch { .. })
    ));
    assert!(matches!(
        model.try_predict(&xn),
        Err(GpError::NonFinite { .. })
    ));
    let p_nan = model.predict(&xn);
    assert!(p_nan.mean[3].is_nan() && p_nan.mean[2].is_finite());
    assert!(model.predict(&DMatrix::zeros(0, 2)).is_empty());

    let mut state = model.state();
    state.n_train = 11;
    assert!(matches!(
        GpModel::from_state(&x, &y, &state),
        Err(GpError::DimensionMismatch { .. })
    ));
    let mut state = model.state();
    state.hyperparameters.length_scales = vec![0.5];
    assert!(GpModel::from_state(&x, &y, &state).is_err());
    let mut state = model.state();
    state.hyperparameters.signal_variance = -1.0;
    assert!(matches!(
        GpModel::from_state(&x, &y, &state),
        Err(GpError::InvalidState(_))
    ));
    let mut state = model.state();
    state.noise = NoiseMode::Heteroscedastic;
    assert!(matches!(
        GpModel::from_state(&x, &y, &state),
        Err(GpError::InvalidState(_))
    ));
}

#[test]
fn invalid_params_name_the_field() {
    let name = |p: GpParams| match p.check() {
        Err(GpError::InvalidParameter { name, .. }) => name,
        other => panic!("expected an invalid parameter, got {other:?}"),
    };
    let d = GpParams::default;
    assert_eq!(
        name(GpParams {
            prior_mean: f64::NAN,
            ..d()
        }),
        "prior_mean"
    );
    assert_eq!(
        name(GpParams {
            restarts: 65,
            ..d()
        }),
        "restarts"
    );
    assert_eq!(
        name(GpParams {
            bounds: Bounds {
                length_scale: (0.0, 1.0),
                ..Bounds::MAIN
            },
            ..d()
        }),
        "bounds.length_scale"
    );
    assert_eq!(
        name(GpParams {
            bounds: Bounds {
                noise_variance: (2.0, 1.0),
                ..Bounds::MAIN
            },
            ..d()
        }),
        "bounds.noise_variance"
    );
    assert_eq!(
        name(GpParams {
            noise_model_bounds: Bounds {
                signal_variance: (1.0, f64::INFINITY),
                ..Bounds::NOISE_MODEL
            },
            ..d()
        }),
        "noise_model_bounds.signal_variance"
    );
    assert_eq!(
        name(GpParams {
            max_iterations: 0,
            ..d()
        }),
        "max_iterations"
    );
    assert_eq!(
        name(GpParams {
            function_tolerance: 0.0,
            ..d()
        }),
        "function_tolerance"
    );
    assert_eq!(
        name(GpParams {
            gradient_tolerance: -1.0,
            ..d()
        }),
        "gradient_tolerance"
    );
    assert_eq!(
        name(GpParams {
            screen_subset: 10,
            ..d()
        }),
        "screen_subset"
    );
    assert_eq!(
        name(GpParams {
            jitter_initial: 1.0,
            ..d()
        }),
        "jitter_initial"
    );
    assert_eq!(
        name(GpParams {
            jitter_max: 0.5,
            ..d()
        }),
        "jitter_max"
    );
    assert_eq!(
        name(GpParams {
            hetero_rounds: 0,
            ..d()
        }),
        "hetero_rounds"
    );
    assert_eq!(
        name(GpParams {
            hetero_tolerance: 1.0,
            ..d()
        }),
        "hetero_tolerance"
    );
    assert_eq!(
        name(GpParams {
            hetero_min_points: 1,
            ..d()
        }),
        "hetero_min_points"
    );
    assert!(GpParams::default().check().is_ok());
}

#[test]
fn params_serde_uses_lowercase_modes_and_defaults() {
    let p: GpParams = serde_json::from_str(r#"{"noise": "homoscedastic", "restarts": 0}"#).unwrap();
    assert_eq!(p.noise, NoiseMode::Homoscedastic);
    assert_eq!(p.restarts, 0);
    assert_eq!(p.max_iterations, GpParams::default().max_iterations);
    assert_eq!(
        serde_json::to_string(&NoiseMode::Heteroscedastic).unwrap(),
        r#""heteroscedastic""#
    );
}

#[test]
fn prior_answers_before_any_data() {
    let h = Hyperparameters::prior(4, 0.25);
    assert_eq!(h.length_scales.len(), 4);
    assert_eq!(h.prior_std(), DEFAULT_PRIOR_SIGNAL_VARIANCE.sqrt());
    let p = h.prior_prediction(3);
    assert_eq!(p.mean, vec![0.25; 3]);
    assert_eq!(p.std(), vec![1.0; 3]);
}

#[test]
fn model_is_send_and_sync() {
    fn assert_send_sync<T: Send + Sync>() {}
    assert_send_sync::<GpModel>();
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, .. ProptestConfig::default() })]

    /// Variances are never negative (nor NaN), whatever the hyperparameters and query points,
    /// including queries on top of training points and far outside the box.
    #[test]
    fn variances_are_nonnegative(
        seed in 0u64..1000,
        n in 1usize..40,
        ls in 0.01f64..10.0,
        s2 in 1e-4f64..1e2,
        noise in 1e-6f64..1.0,
        scale in 0.5f64..20.0,
    ) {
        let (x, y) = data(n, 2, seed);
        let state = ModelState {
            format: 1,
            noise: NoiseMode::Homoscedastic,
            n_train: n,
            hyperparameters: Hyperparameters { length_scales: vec![ls, ls * 2.0], signal_variance: s2, noise_variance: noise, prior_mean: 0.1, kernel: Kernel::Matern52 },
            jitter: 0.0,
            log_marginal_likelihood: 0.0,
            noise_model: None,
        };
        if let Ok(model) = GpModel::from_state(&x, &y, &state) {
            let mut q = DMatrix::from_fn(n + 20, 2, |i, j| if i < n { x[(i, j)] } else { (i as f64 / 7.0).sin() * scale });
            q[(0, 0)] += 1e-9;
            let p = model.predict(&q);
            for j in 0..q.nrows() {
                prop_assert!(p.latent_variance[j] >= 0.0 && p.latent_variance[j] <= s2 * (1.0 + 1e-9));
                prop_assert!(p.noise_variance[j] >= 0.0);
                prop_assert!(p.mean[j].is_finite());
            }
        }
    }

    /// L·Lᵀ reproduces K for random kernels (checked on the diagonal and first column).
    #[test]
    fn factor_reproduces_random_kernels(seed in 0u64..1000, n in 2usize..30, ls in 0.05f64..3.0, noise in 1e-4f64..1.0) {
        let (x, y) = data(n, 3, seed);
        let inputs = Inputs::from_matrix(&x);
        let xs = inputs.scaled(&[ls, ls, ls]);
        let nv = vec![noise; n];
        let mut k = vec![0.0; n * n];
        build_train(Kernel::Matern52, &xs, n, 3, 1.0, &nv, &mut k, None);
        let fac = factorise(Kernel::Matern52, &xs, n, 3, 1.0, &nv, y.as_slice(), JITTER, 0.0, vec![0.0; n * n], None).ok().unwrap();
        for i in 0..n {
            let diag: f64 = (0..=i).map(|c| fac.l[c * n + i].powi(2)).sum();
            prop_assert!((diag - k[i * n + i] - fac.jitter).abs() <= 1e-10 * k[i * n + i]);
            let first: f64 = fac.l[i] * fac.l[0];
            if i > 0 {
                prop_assert!((first - k[i]).abs() <= 1e-10);
            }
        }
    }
}

#[test]
fn leave_one_out_matches_refitting_without_the_point() {
    let (x, y) = data(30, 2, 11);
    let model = GpModel::fit(&x, &y, &homo_params()).unwrap();
    let loo = model.leave_one_out().expect("the factor is kept");
    assert_eq!(loo.len(), 30);
    let noise = model.hyperparameters().noise_variance + model.jitter();
    for i in [0, 7, 29] {
        // The same hyperparameters conditioned on every other point, predicting y_i.
        let keep: Vec<usize> = (0..30).filter(|&k| k != i).collect();
        let xs = x.select_rows(&keep);
        let ys = DVector::from_iterator(29, keep.iter().map(|&k| y[k]));
        let mut state = model.state();
        state.n_train = 29;
        let without = GpModel::from_state(&xs, &ys, &state).unwrap();
        let p = without.predict(&x.rows(i, 1).into_owned());
        let (residual, sd) = loo[i];
        assert_relative_eq!(y[i] - residual, p.mean[0], epsilon = 1e-7);
        let sd_ref = (p.latent_variance[0] + noise).sqrt();
        assert_relative_eq!(sd, sd_ref, max_relative = 1e-6);
    }
}

#[test]
fn leaving_a_group_out_matches_refitting_without_it() {
    // 24 distinct points, four of them repeated (a robot that executed the same state-action
    // again), so that a group is every copy of one input.
    let (x0, y0) = data(24, 2, 13);
    let copies = [(3, 2), (10, 3), (17, 1), (23, 2)];
    let mut rows: Vec<usize> = (0..24).collect();
    for &(i, extra) in &copies {
        rows.extend(std::iter::repeat_n(i, extra));
    }
    let x = x0.select_rows(&rows);
    let n = rows.len();
    let y = DVector::from_iterator(
        n,
        rows.iter()
            .enumerate()
            .map(|(k, &i)| y0[i] + 0.01 * k as f64),
    );
    let model = GpModel::fit(&x, &y, &homo_params()).unwrap();
    let groups: Vec<Vec<usize>> = (0..24)
        .map(|i| (0..n).filter(|&k| rows[k] == i).collect())
        .collect();
    let lgo = model.leave_groups_out(&groups).expect("the factor is kept");
    assert_eq!(lgo.len(), n);
    let noise = model.hyperparameters().noise_variance + model.jitter();
    for group in groups.iter().filter(|g| g.len() > 1).chain([&groups[0]]) {
        let keep: Vec<usize> = (0..n).filter(|k| !group.contains(k)).collect();
        let xs = x.select_rows(&keep);
        let ys = DVector::from_iterator(keep.len(), keep.iter().map(|&k| y[k]));
        let mut state = model.state();
        state.n_train = keep.len();
        let without = GpModel::from_state(&xs, &ys, &state).unwrap();
        for &i in group {
            let p = without.predict(&x.rows(i, 1).into_owned());
            let (residual, sd) = lgo[i];
            assert_relative_eq!(y[i] - residual, p.mean[0], epsilon = 1e-6);
            let sd_ref = (p.latent_variance[0] + noise).sqrt();
            assert_relative_eq!(sd, sd_ref, max_relative = 1e-5);
        }
    }
    // Singletons are exactly leave-one-out; a copy left out alone is predicted by its twins.
    let loo = model.leave_one_out().unwrap();
    assert_eq!(lgo[0], loo[0]);
    assert!(lgo[3].1 > loo[3].1, "{:?} vs {:?}", lgo[3], loo[3]);
    assert!(model.leave_groups_out(&[vec![0, n]]).is_none());
}

#[test]
fn a_fold_judges_its_first_rows_without_any_of_its_rows() {
    // Overlapping folds: rows 0..3 judged without rows 3..6 either, and rows 3..6 judged
    // without rows 0..2; each judged row matches a refit without its whole fold.
    let (x, y) = data(20, 2, 5);
    let model = GpModel::fit(&x, &y, &homo_params()).unwrap();
    let folds = [
        Fold {
            rows: vec![0, 1, 2, 3, 4, 5],
            judged: 3,
        },
        Fold {
            rows: vec![3, 4, 5, 0, 1],
            judged: 3,
        },
    ];
    let out = model.leave_folds_out(&folds).expect("the factor is kept");
    let noise = model.hyperparameters().noise_variance + model.jitter();
    for fold in &folds {
        let keep: Vec<usize> = (0..20).filter(|k| !fold.rows.contains(k)).collect();
        let xs = x.select_rows(&keep);
        let ys = DVector::from_iterator(keep.len(), keep.iter().map(|&k| y[k]));
        let mut state = model.state();
        state.n_train = keep.len();
        let without = GpModel::from_state(&xs, &ys, &state).unwrap();
        for &i in &fold.rows[..fold.judged] {
            let p = without.predict(&x.rows(i, 1).into_owned());
            let (residual, sd) = out[i];
            assert_relative_eq!(y[i] - residual, p.mean[0], epsilon = 1e-6);
            assert_relative_eq!(
                sd,
                (p.latent_variance[0] + noise).sqrt(),
                max_relative = 1e-5
            );
        }
    }
    // A row no fold judges is left out alone.
    assert_eq!(out[10], model.leave_one_out().unwrap()[10]);
    // Folds that together cost more than any partition could are refused, not computed: every
    // fold holding every row costs 20 · 20² where a partition costs at most 20².
    let all = Fold {
        rows: (0..20).collect(),
        judged: 1,
    };
    assert!(model.leave_folds_out(&vec![all; 20]).is_none());
}

#[test]
fn targets_whose_mean_square_overflows_are_an_error_not_a_panic() {
    // Labels 1e300 away from the prior mean: their mean square is infinite, so there is no
    // range to draw random starts from (this panicked in `random_range`).
    let (x, _) = data(20, 2, 3);
    let y = DVector::from_element(20, 1e300);
    for noise in [NoiseMode::Homoscedastic, NoiseMode::Heteroscedastic] {
        let params = gp_params(noise, 2, 5).check().unwrap();
        let e = GpModel::fit(&x, &y, &params).unwrap_err();
        assert!(
            matches!(e, GpError::OptimisationFailed(ref m) if m.contains("overflows")),
            "{e}"
        );
    }
}

/// `model` (fitted on `(x, y)`) at the same hyperparameters conditioned on the `pending` rows
/// too, with any labels (a GP's variance does not depend on them).
fn conditioned_on_pending_too(
    model: &GpModel,
    x: &DMatrix<f64>,
    y: &DVector<f64>,
    pending: &DMatrix<f64>,
) -> GpModel {
    let (n, k) = (x.nrows(), pending.nrows());
    let xa = DMatrix::from_fn(n + k, x.ncols(), |i, j| {
        if i < n {
            x[(i, j)]
        } else {
            pending[(i - n, j)]
        }
    });
    let ya = DVector::from_fn(n + k, |i, _| if i < n { y[i] } else { 0.0 });
    let mut state = model.state();
    state.n_train = n + k;
    GpModel::from_state(&xa, &ya, &state).unwrap()
}

#[test]
fn fantasised_variances_equal_conditioning_on_the_pending_points_too() {
    let (x, y) = data(40, 2, 21);
    let model = GpModel::fit(&x, &y, &homo_params()).unwrap();
    let (pending, _) = data(6, 2, 22);
    let (q, _) = data(15, 2, 23);
    let fantasy = model.predict_fantasised(&q, &pending);
    let plain = model.predict(&q);
    let reference = conditioned_on_pending_too(&model, &x, &y, &pending).predict(&q);
    for i in 0..15 {
        assert_relative_eq!(fantasy.mean[i], plain.mean[i], epsilon = 1e-12);
        assert_relative_eq!(
            fantasy.latent_variance[i],
            reference.latent_variance[i],
            epsilon = 1e-9,
            max_relative = 1e-6
        );
        assert!(fantasy.latent_variance[i] <= plain.latent_variance[i] + 1e-12);
        assert_eq!(fantasy.noise_variance[i], plain.noise_variance[i]);
    }
    // One pending point, predicted at itself: `v σ²/(v + σ²)` (one more noisy observation).
    let p0 = pending.rows(0, 1).into_owned();
    let at = model.predict_fantasised(&p0, &p0);
    let before = model.predict(&p0);
    let (v, s2) = (
        before.latent_variance[0],
        before.noise_variance[0] + model.jitter(),
    );
    assert_relative_eq!(
        at.latent_variance[0],
        v * s2 / (v + s2),
        max_relative = 1e-6
    );
    // Nothing pending, or pending points of the wrong width: the plain prediction.
    let none = model.predict_fantasised(&q, &DMatrix::zeros(0, 2));
    assert_eq!(none.latent_variance, plain.latent_variance);
    let wrong = model.predict_fantasised(&q, &DMatrix::zeros(3, 5));
    assert_eq!(wrong.latent_variance, plain.latent_variance);
}

#[test]
fn one_preparation_of_the_queries_answers_every_pending_set_as_conditioning_would() {
    let (x, y) = data(40, 2, 21);
    let model = GpModel::fit(&x, &y, &homo_params()).unwrap();
    let (q, _) = data(15, 2, 23);
    let prepared = model.fantasy(q.clone());
    let (six, _) = data(6, 2, 22);
    let (three, _) = data(3, 2, 24);
    let sets = [
        six.clone(),
        three.clone(),
        six.rows(0, 2).into_owned(),
        six.clone(),
    ];
    // The sets one per call, the first again, and all in one call: each answer is its own
    // conditioning's.
    let together = prepared.predict_each(&sets);
    assert_eq!(together.len(), sets.len());
    for (pending, joint) in sets.iter().zip(&together) {
        let answer = prepared.predict(pending);
        let reference = conditioned_on_pending_too(&model, &x, &y, pending).predict(&q);
        for i in 0..15 {
            for variance in [answer.latent_variance[i], joint.latent_variance[i]] {
                assert_relative_eq!(
                    variance,
                    reference.latent_variance[i],
                    epsilon = 1e-9,
                    max_relative = 1e-6
                );
            }
        }
        assert_eq!(answer.mean, joint.mean);
        assert_eq!(answer, model.predict_fantasised(&q, pending));
    }
    // An empty set among others answers the plain prediction in its place.
    let mixed = prepared.predict_each(&[three.clone(), DMatrix::zeros(0, 2), six.clone()]);
    assert_eq!(mixed[1], model.predict(&q));
    assert_eq!(mixed[0].latent_variance.len(), 15);
    assert_relative_eq!(
        mixed[2].latent_variance[7],
        together[0].latent_variance[7],
        max_relative = 1e-12
    );
    // A query row that is not a number answers NaN there, as the plain prediction does.
    let mut bad = q.clone();
    bad[(4, 1)] = f64::NAN;
    let answer = model.fantasy(bad).predict(&three);
    assert!(answer.mean[4].is_nan() && answer.latent_variance[4].is_nan());
    assert!(answer.latent_variance[3].is_finite());
}
