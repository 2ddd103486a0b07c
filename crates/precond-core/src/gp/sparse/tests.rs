//! Tests of the sparse GP: the bound's gradient, agreement with the exact GP when the inducing
//! inputs are the training inputs, online updates, save/restore, scale and degenerate data.

use approx::assert_relative_eq;
use nalgebra::{DMatrix, DVector};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::super::kernel::Inputs;
use super::super::lml::{Jitter, NoiseSpec, Objective};
use super::super::tests::{data, gp_params, gradient_vs_finite_differences};
use super::super::{GpError, GpModel, GpParams, Kernel, ModelState, NoiseMode};
use super::bound::Bound;
use super::core::Ladder;
use super::*;

/// The first `m` rows of `x` as inducing inputs (they are random, hence spread out).
fn first_rows(x: &DMatrix<f64>, m: usize) -> Inputs {
    Inputs::from_matrix(&x.rows(0, m).into_owned())
}

fn check_gradient(bound: &mut Bound<'_>, theta: &[f64], what: &str) {
    assert_eq!(bound.n_params(), theta.len());
    let (f, pairs) = gradient_vs_finite_differences(|t, g| bound.eval(t, g), theta);
    assert!(f.is_finite(), "{what}: f = {f}");
    for (k, (analytic, fd)) in pairs.into_iter().enumerate() {
        assert!(
            (analytic - fd).abs() <= 1e-6 + 2e-5 * fd.abs(),
            "{what}: ∂/∂θ_{k} analytic {analytic} vs finite differences {fd}"
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
        gp: gp_params(NoiseMode::Homoscedastic, 1, 5),
        inducing_points: m,
        full_rank_up_to: 0,
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

fn rel_close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * a.abs().max(b.abs()).max(1e-3)
}

fn assert_predictions_close(a: &crate::gp::Prediction, b: &crate::gp::Prediction, tol: f64) {
    for j in 0..a.len() {
        assert!(
            rel_close(a.mean[j], b.mean[j], tol),
            "mean {j}: {} vs {}",
            a.mean[j],
            b.mean[j]
        );
        assert!(
            rel_close(a.latent_variance[j], b.latent_variance[j], tol),
            "latent variance {j}: {} vs {}",
            a.latent_variance[j],
            b.latent_variance[j]
        );
        assert!(rel_close(a.noise_variance[j], b.noise_variance[j], tol));
    }
}

/// 40 inducing points chosen in one round, never full rank, no restarts.
fn low_rank_40(noise: NoiseMode) -> ValidSparseParams {
    SparseParams {
        gp: gp_params(noise, 0, 3),
        inducing_points: 40,
        inducing_rounds: 1,
        full_rank_up_to: 0,
        ..SparseParams::default()
    }
    .check()
    .unwrap()
}

#[test]
fn online_updates_equal_conditioning_on_all_the_data() {
    let (x, y) = data(400, 3, 8);
    for noise in [NoiseMode::Homoscedastic, NoiseMode::Heteroscedastic] {
        let p = low_rank_40(noise);
        let first = x.rows(0, 200).into_owned();
        let y_first = y.rows(0, 200).into_owned();
        let mut online = SparseGp::fit(&first, &y_first, &p).unwrap();
        // Four 50-step trajectories, one at a time.
        for t in 0..4 {
            let xb = x.rows(200 + 50 * t, 50).into_owned();
            let yb = y.rows(200 + 50 * t, 50).into_owned();
            online.update(&xb, &yb).unwrap();
        }
        assert_eq!(online.n_train(), 400);
        let refit = online.condition(&x, &y).unwrap();
        let (q, _) = data(30, 3, 9);
        assert_predictions_close(&online.predict(&q), &refit.predict(&q), 1e-8);
        assert!(rel_close(online.bound(), refit.bound(), 1e-9));
        // An empty batch changes nothing; a bad one is an error and changes nothing either.
        let before = online.predict(&q);
        online
            .update(&DMatrix::zeros(0, 3), &DVector::zeros(0))
            .unwrap();
        assert!(
            online
                .update(&DMatrix::zeros(2, 4), &DVector::zeros(2))
                .is_err()
        );
        let mut bad = DMatrix::zeros(2, 3);
        bad[(1, 2)] = f64::NAN;
        assert!(online.update(&bad, &DVector::zeros(2)).is_err());
        assert_eq!(online.predict(&q), before);
    }
}

#[test]
fn state_round_trips_exactly_through_json() {
    let (x, y) = data(300, 2, 10);
    for noise in [NoiseMode::Homoscedastic, NoiseMode::Heteroscedastic] {
        let p = SparseParams {
            gp: gp_params(noise, 1, 11),
            inducing_points: 30,
            full_rank_up_to: 0,
            ..SparseParams::default()
        }
        .check()
        .unwrap();
        let mut model = SparseGp::fit(&x, &y, &p).unwrap();
        assert_eq!(model.noise_mode(), noise);
        let (xb, yb) = data(50, 2, 12);
        model.update(&xb, &yb).unwrap();
        let json = serde_json::to_string(&model.state()).unwrap();
        let state: SparseState = serde_json::from_str(&json).unwrap();
        assert_eq!(state, model.state());
        let rebuilt = SparseGp::from_state(&state).unwrap();
        let (q, _) = data(40, 2, 13);
        assert_eq!(rebuilt.predict(&q), model.predict(&q));
        assert_eq!(rebuilt.bound(), model.bound());
        assert_eq!(rebuilt.n_train(), 350);
        assert_eq!(rebuilt.state(), model.state());
        // Updates continue identically after a round trip.
        let (xc, yc) = data(20, 2, 14);
        let (mut a, mut b) = (model.clone(), rebuilt);
        a.update(&xc, &yc).unwrap();
        b.update(&xc, &yc).unwrap();
        assert_eq!(a.predict(&q), b.predict(&q));
    }
}

#[test]
fn malformed_states_are_errors() {
    let (x, y) = data(60, 2, 15);
    let model = SparseGp::fit(&x, &y, &homo_sparse(10).check().unwrap()).unwrap();
    let good = model.state();
    let mut s = good.clone();
    s.format = 2;
    assert!(matches!(
        SparseGp::from_state(&s),
        Err(GpError::InvalidState(_))
    ));
    let mut s = good.clone();
    s.main.factor_b.pop();
    assert!(matches!(
        SparseGp::from_state(&s),
        Err(GpError::DimensionMismatch { .. })
    ));
    let mut s = good.clone();
    s.main.inducing_points.pop();
    assert!(SparseGp::from_state(&s).is_err());
    let mut s = good.clone();
    s.main.projected_targets[0] = f64::NAN;
    assert!(matches!(
        SparseGp::from_state(&s),
        Err(GpError::NonFinite { .. })
    ));
    let mut s = good.clone();
    s.main.hyperparameters.signal_variance = -1.0;
    assert!(SparseGp::from_state(&s).is_err());
    let mut s = good.clone();
    s.main.factor_b[0] = -1.0;
    assert!(matches!(
        SparseGp::from_state(&s),
        Err(GpError::InvalidState(_))
    ));
    let mut s = good;
    s.noise = NoiseMode::Heteroscedastic;
    assert!(matches!(
        SparseGp::from_state(&s),
        Err(GpError::InvalidState(_))
    ));
}

#[test]
fn the_bound_is_below_the_exact_lml_and_rises_with_more_inducing_points() {
    let (x, y) = data(150, 2, 16);
    let inputs = Inputs::from_matrix(&x);
    let r = y.as_slice();
    let theta = [0.4f64.ln(), 0.6f64.ln(), 0.5f64.ln(), 0.01f64.ln()];
    let (lml, _) = exact_lml(&inputs, r, Kernel::Matern52, &theta);
    let mut last = f64::NEG_INFINITY;
    for m in [5, 20, 60, 150] {
        let z = first_rows(&x, m);
        let tiny = Ladder::Relative {
            initial: 1e-12,
            max: 1e-4,
        };
        let mut b = Bound::new(
            &inputs,
            &z,
            r,
            NoiseSpec::Homoscedastic,
            Kernel::Matern52,
            tiny,
        );
        let f = -b.eval(&theta, &mut [0.0; 4]);
        assert!(
            f <= lml + 1e-6 * lml.abs(),
            "m = {m}: bound {f} above the LML {lml}"
        );
        assert!(
            f >= last - 1e-9 * f.abs(),
            "m = {m}: bound {f} fell from {last}"
        );
        last = f;
    }
    assert_relative_eq!(last, lml, max_relative = 1e-7);
}

#[test]
fn a_large_fit_is_quick_and_predicts_well() {
    // 20 000 points in d = 4, m = 256 (the default): the default presolve would not engage below 32 768 points, so a
    // smaller subset is set to exercise the subset-then-refine path.
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let n = 20_000;
    let f = |x: &[f64]| (3.0 * x[0]).sin() + 0.5 * (5.0 * x[1]).cos() + x[2] * x[2] - 0.5 * x[3];
    let x = DMatrix::from_fn(n, 4, |_, _| rng.random::<f64>());
    let y = DVector::from_fn(n, |i, _| {
        let row: Vec<f64> = x.row(i).iter().copied().collect();
        f(&row) + 0.1 * (rng.random::<f64>() - 0.5) * 3.46
    });
    let p = SparseParams {
        gp: gp_params(NoiseMode::Homoscedastic, 1, 1),
        presolve_subset: 4096,
        ..SparseParams::default()
    }
    .check()
    .unwrap();
    let t = std::time::Instant::now();
    let model = SparseGp::fit(&x, &y, &p).unwrap();
    let secs = t.elapsed().as_secs_f64();
    assert!(secs < 30.0, "fit took {secs:.1} s");
    let q = DMatrix::from_fn(500, 4, |_, _| rng.random::<f64>());
    let pred = model.predict(&q);
    let rmse = ((0..500)
        .map(|i| {
            let row: Vec<f64> = q.row(i).iter().copied().collect();
            (pred.mean[i] - f(&row)).powi(2)
        })
        .sum::<f64>()
        / 500.0)
        .sqrt();
    // Noise sd 0.1; the latent function is recovered far better than that.
    assert!(rmse < 0.05, "rmse {rmse}");
    let noise = model.hyperparameters().noise_variance;
    assert!((0.007..0.013).contains(&noise), "noise variance {noise}");
    assert!(
        pred.latent_variance
            .iter()
            .all(|v| *v >= 0.0 && v.is_finite())
    );
}

#[test]
fn heteroscedastic_noise_follows_the_data() {
    // Noise sd 0.02 on the left half, 0.3 on the right.
    let mut rng = ChaCha8Rng::seed_from_u64(18);
    let n = 1500;
    let x = DMatrix::from_fn(n, 2, |_, _| rng.random::<f64>());
    let y = DVector::from_fn(n, |i, _| {
        let sd = if x[(i, 0)] < 0.5 { 0.02 } else { 0.3 };
        (3.0 * x[(i, 1)]).sin() + sd * 1.732 * (2.0 * rng.random::<f64>() - 1.0)
    });
    let p = SparseParams {
        gp: GpParams {
            restarts: 1,
            seed: 2,
            ..GpParams::default()
        },
        inducing_points: 48,
        noise_inducing_points: 24,
        ..SparseParams::default()
    }
    .check()
    .unwrap();
    let model = SparseGp::fit(&x, &y, &p).unwrap();
    assert_eq!(model.noise_mode(), NoiseMode::Heteroscedastic);
    let summary = model.noise_summary().unwrap();
    assert!(summary.rounds >= 1);
    let q = DMatrix::from_row_slice(2, 2, &[0.2, 0.5, 0.8, 0.5]);
    let pred = model.predict(&q);
    let (lo, hi) = (pred.noise_variance[0], pred.noise_variance[1]);
    assert!((0.0002..0.0008).contains(&lo), "left noise {lo}");
    assert!((0.06..0.14).contains(&hi), "right noise {hi}");
    assert!(model.bound() > summary.homoscedastic_lml);
}

#[test]
fn degenerate_data_give_models_or_errors_never_panics() {
    for full_rank_up_to in [0, DEFAULT_FULL_RANK_UP_TO] {
        degenerate_data(full_rank_up_to);
    }
}

/// [`degenerate_data_give_models_or_errors_never_panics`] with low-rank (`0`) or full-rank fits.
fn degenerate_data(full_rank_up_to: usize) {
    let p = SparseParams {
        full_rank_up_to,
        ..homo_sparse(16)
    }
    .check()
    .unwrap();
    let het = SparseParams {
        gp: GpParams {
            restarts: 1,
            ..GpParams::default()
        },
        inducing_points: 16,
        full_rank_up_to,
        ..SparseParams::default()
    }
    .check()
    .unwrap();
    let q = DMatrix::from_fn(5, 2, |i, j| 0.1 * (i + j) as f64);
    let sane = |m: &SparseGp| {
        let pr = m.predict(&q);
        assert!(
            pr.mean
                .iter()
                .chain(&pr.latent_variance)
                .all(|v| v.is_finite())
        );
        assert!(pr.latent_variance.iter().all(|v| *v >= 0.0));
    };
    // Every point the same input: one inducing point.
    let x = DMatrix::from_element(30, 2, 0.3);
    let y = DVector::from_fn(30, |i, _| 0.1 * (i % 3) as f64);
    for params in [&p, &het] {
        let m = SparseGp::fit(&x, &y, params).unwrap();
        assert_eq!(m.n_inducing(), 1);
        sane(&m);
    }
    // Constant targets.
    let (x, _) = data(40, 2, 19);
    let y = DVector::from_element(40, 0.7);
    for params in [&p, &het] {
        let m = SparseGp::fit(&x, &y, params).unwrap();
        sane(&m);
        assert!((m.predict(&q).mean[0] - 0.7).abs() < 1e-2);
    }
    // Fewer points than inducing points, and a single point.
    let (x, y) = data(6, 2, 20);
    let m = SparseGp::fit(&x, &y, &p).unwrap();
    assert_eq!(m.n_inducing(), 6);
    sane(&m);
    let m = SparseGp::fit(&x.rows(0, 1).into_owned(), &y.rows(0, 1).into_owned(), &het).unwrap();
    assert_eq!(m.noise_mode(), NoiseMode::Homoscedastic);
    sane(&m);
    // Duplicated rows among distinct ones.
    let (x0, y0) = data(20, 2, 21);
    let rows: Vec<usize> = (0..60).map(|i| i % 20).collect();
    let x = x0.select_rows(&rows);
    let y = DVector::from_fn(60, |i, _| y0[i % 20] + 0.01 * (i / 20) as f64);
    sane(&SparseGp::fit(&x, &y, &het).unwrap());
    // Bad inputs are errors.
    assert!(matches!(
        SparseGp::fit(&DMatrix::zeros(0, 2), &DVector::zeros(0), &p),
        Err(GpError::EmptyData(_))
    ));
    let mut xn = x.clone();
    xn[(0, 0)] = f64::INFINITY;
    assert!(matches!(
        SparseGp::fit(&xn, &y, &p),
        Err(GpError::NonFinite { .. })
    ));
    assert!(SparseGp::fit_with_inducing(&x, &y, &DMatrix::zeros(3, 5), &p).is_err());
    let model = SparseGp::fit(&x, &y, &p).unwrap();
    assert!(
        model
            .predict(&DMatrix::zeros(2, 3))
            .mean
            .iter()
            .all(|v| v.is_nan())
    );
    assert!(model.try_predict(&DMatrix::zeros(2, 3)).is_err());
    assert!(model.predict(&DMatrix::zeros(0, 2)).is_empty());
}

#[test]
fn invalid_sparse_params_name_the_field() {
    let name = |p: SparseParams| match p.check() {
        Err(GpError::InvalidParameter { name, .. }) => name,
        other => panic!("expected an invalid parameter, got {other:?}"),
    };
    let d = SparseParams::default;
    assert_eq!(
        name(SparseParams {
            inducing_points: 0,
            ..d()
        }),
        "inducing_points"
    );
    assert_eq!(
        name(SparseParams {
            noise_inducing_points: 5000,
            ..d()
        }),
        "noise_inducing_points"
    );
    assert_eq!(
        name(SparseParams {
            inducing_rounds: 0,
            ..d()
        }),
        "inducing_rounds"
    );
    assert_eq!(
        name(SparseParams {
            selection_candidates: 0,
            ..d()
        }),
        "selection_candidates"
    );
    assert_eq!(
        name(SparseParams {
            screen_subset: 10,
            ..d()
        }),
        "screen_subset"
    );
    assert_eq!(
        name(SparseParams {
            presolve_subset: 100,
            ..d()
        }),
        "presolve_subset"
    );
    assert_eq!(name(SparseParams { jitter: 0.0, ..d() }), "jitter");
    assert_eq!(
        name(SparseParams {
            full_rank_up_to: 4097,
            ..d()
        }),
        "full_rank_up_to"
    );
    let mut bad_gp = d();
    bad_gp.gp.restarts = 65;
    assert_eq!(name(bad_gp), "restarts");
    assert!(d().check().is_ok());
    let p: SparseParams =
        serde_json::from_str(r#"{"inducing_points": 64, "gp": {"restarts": 0}}"#).unwrap();
    assert_eq!((p.inducing_points, p.gp.restarts, p.jitter), (64, 0, 1e-6));
}

#[test]
fn sparse_model_is_send_and_sync_and_deterministic() {
    fn assert_send_sync<T: Send + Sync>() {}
    assert_send_sync::<SparseGp>();
    let (x, y) = data(200, 2, 22);
    for full_rank_up_to in [0, DEFAULT_FULL_RANK_UP_TO] {
        let p = SparseParams {
            inducing_points: 20,
            full_rank_up_to,
            ..SparseParams::default()
        }
        .check()
        .unwrap();
        let a = SparseGp::fit(&x, &y, &p).unwrap();
        let b = SparseGp::fit(&x, &y, &p).unwrap();
        assert_eq!(a.state(), b.state());
    }
}

/// Nearly noise-free data whose noise differs between the halves of the box, as the MDE's
/// deviations are: a smooth function of both inputs, noise sd 0.002 on the left half and 0.02
/// on the right.
fn nearly_noise_free(n: usize, seed: u64) -> (DMatrix<f64>, DVector<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let x = DMatrix::from_fn(n, 2, |_, _| rng.random::<f64>());
    let y = DVector::from_fn(n, |i, _| {
        let sd = if x[(i, 0)] < 0.5 { 0.002 } else { 0.02 };
        0.2 * (7.0 * x[(i, 1)]).sin() * (5.0 * x[(i, 0)]).cos()
            + sd * 1.732 * (2.0 * rng.random::<f64>() - 1.0)
    });
    (x, y)
}

#[test]
fn a_fit_of_at_most_full_rank_up_to_points_is_the_exact_gp_in_sparse_form() {
    let (x, y) = nearly_noise_free(240, 30);
    let (q, _) = nearly_noise_free(50, 31);
    for noise in [NoiseMode::Homoscedastic, NoiseMode::Heteroscedastic] {
        let gp = GpParams {
            noise,
            restarts: 1,
            seed: 4,
            ..GpParams::default()
        };
        // 24 inducing points asked for, far fewer than the 240 points.
        let low_rank = SparseParams {
            gp: gp.clone(),
            inducing_points: 24,
            noise_inducing_points: 12,
            full_rank_up_to: 0,
            ..SparseParams::default()
        };
        let full = SparseParams {
            full_rank_up_to: 240,
            ..low_rank.clone()
        };
        let exact = GpModel::fit(&x, &y, &gp.check().unwrap()).unwrap();
        let sparse = SparseGp::fit(&x, &y, &full.check().unwrap()).unwrap();
        assert_eq!(sparse.noise_mode(), noise);
        // Every input that the others do not already determine (to 1e-6 of the noise).
        assert!(
            sparse.n_inducing() > 100,
            "{noise:?}: {}",
            sparse.n_inducing()
        );
        let (h, he) = (sparse.hyperparameters(), exact.hyperparameters());
        assert_eq!(h.length_scales, he.length_scales);
        assert_eq!(h.signal_variance, he.signal_variance);
        assert_relative_eq!(
            sparse.bound(),
            exact.log_marginal_likelihood(),
            max_relative = 1e-6
        );
        let (a, b) = (sparse.predict(&q), exact.predict(&q));
        let sd = |p: &crate::gp::Prediction, j: usize| {
            (p.latent_variance[j] + p.noise_variance[j]).sqrt()
        };
        for j in 0..q.nrows() {
            assert!(
                (a.mean[j] - b.mean[j]).abs() < 1e-3 * sd(&b, j),
                "{noise:?} mean at {j}"
            );
            assert!(rel_close(sd(&a, j), sd(&b, j), 1e-3), "{noise:?} σ at {j}");
            assert!(rel_close(a.noise_variance[j], b.noise_variance[j], 1e-3));
        }
        // What it replaces: the low-rank fit of these nearly noise-free data pays for its 24
        // inducing points with a far lower bound (50 and 130 nats here) and, homoscedastic, a
        // larger noise (×1.6).
        let low = SparseGp::fit(&x, &y, &low_rank.check().unwrap()).unwrap();
        assert_eq!(low.n_inducing(), 24);
        assert!(low.bound() < exact.log_marginal_likelihood() - 25.0);
        if noise == NoiseMode::Homoscedastic {
            assert!(low.hyperparameters().noise_variance > 1.3 * he.noise_variance);
        }
        // One point more than full_rank_up_to and the fit is low rank.
        let (x1, y1) = nearly_noise_free(241, 30);
        let over = SparseGp::fit(&x1, &y1, &full.check().unwrap()).unwrap();
        assert_eq!(over.n_inducing(), 24);
    }
}

#[test]
fn the_sparse_form_of_an_exact_gp_counts_each_repeated_input_once() {
    let (x0, y0) = nearly_noise_free(40, 32);
    let rows: Vec<usize> = (0..120).map(|i| i % 40).collect();
    let x = x0.select_rows(&rows);
    let y = DVector::from_fn(120, |i, _| y0[i % 40] + 0.001 * (i / 40) as f64);
    let gp = GpParams {
        restarts: 1,
        ..GpParams::default()
    };
    let p = SparseParams {
        gp: gp.clone(),
        ..SparseParams::default()
    }
    .check()
    .unwrap();
    let exact = GpModel::fit(&x, &y, &gp.check().unwrap()).unwrap();
    let sparse = SparseGp::from_exact_state(&x, &y, &exact.state(), &p).unwrap();
    assert!(sparse.n_inducing() <= 40);
    assert_relative_eq!(
        sparse.bound(),
        exact.log_marginal_likelihood(),
        max_relative = 1e-6
    );
    // A state fitted on other data is refused, not converted.
    let (x2, y2) = nearly_noise_free(30, 33);
    assert!(matches!(
        SparseGp::from_exact_state(&x2, &y2, &exact.state(), &p),
        Err(GpError::DimensionMismatch { .. })
    ));
}

#[test]
fn fantasised_variances_equal_conditioning_on_the_pending_points_too() {
    let (x, y) = data(300, 3, 31);
    for noise in [NoiseMode::Homoscedastic, NoiseMode::Heteroscedastic] {
        let p = low_rank_40(noise);
        let model = SparseGp::fit(&x, &y, &p).unwrap();
        let (pending, _) = data(20, 3, 32);
        let (q, _) = data(25, 3, 33);
        let fantasy = model.predict_fantasised(&q, &pending);
        let plain = model.predict(&q);
        let mu_pending = model.predict(&pending).mean;
        let xa = DMatrix::from_fn(320, 3, |i, k| {
            if i < 300 {
                x[(i, k)]
            } else {
                pending[(i - 300, k)]
            }
        });
        let ya = DVector::from_fn(320, |i, _| if i < 300 { y[i] } else { mu_pending[i - 300] });
        let reference = model.condition(&xa, &ya).unwrap().predict(&q);
        assert_predictions_close(&fantasy, &reference, 1e-8);
        for i in 0..25 {
            assert!(fantasy.latent_variance[i] <= plain.latent_variance[i] + 1e-12);
            assert_eq!(fantasy.mean[i], plain.mean[i]);
        }
        // One preparation of the queries, several pending sets in one call: each answer is
        // its own update's.
        let (few, _) = data(4, 3, 34);
        let sets = [few.clone(), pending.clone(), DMatrix::zeros(0, 3)];
        let answers = model.fantasy(q.clone()).predict_each(&sets);
        for (set, answer) in sets.iter().zip(&answers) {
            let mu = model.predict(set).mean;
            let k = set.nrows();
            let xs = DMatrix::from_fn(300 + k, 3, |i, j| {
                if i < 300 {
                    x[(i, j)]
                } else {
                    set[(i - 300, j)]
                }
            });
            let ys = DVector::from_fn(300 + k, |i, _| if i < 300 { y[i] } else { mu[i - 300] });
            let reference = model.condition(&xs, &ys).unwrap().predict(&q);
            assert_predictions_close(answer, &reference, 1e-8);
        }
        assert_eq!(answers[2], plain);
        // The model itself is unchanged.
        assert_eq!(model.n_train(), 300);
    }
}

/// The latent variance by one triangular product with the precomputed factor equals the two
/// triangular solves' to rounding, relative to the signal variance — on a low-rank fit, a
/// heteroscedastic one, and a full-rank fit of nearly noise-free data (`K_mm` ill-conditioned,
/// the variance near the training points a small difference of large terms); at fresh points
/// and at the training points themselves.
#[test]
fn the_variance_by_one_product_equals_the_two_solves() {
    let (x, y) = data(600, 2, 21);
    let (xn, yn) = nearly_noise_free(700, 22);
    let full_rank = SparseParams {
        gp: gp_params(NoiseMode::Homoscedastic, 0, 3),
        ..SparseParams::default()
    }
    .check()
    .unwrap();
    // A rough function of all six inputs, so that all 128 inducing points are kept.
    let mut rng = ChaCha8Rng::seed_from_u64(24);
    let x6 = DMatrix::from_fn(2000, 6, |_, _| rng.random::<f64>());
    let y6 = DVector::from_fn(2000, |i, _| {
        (0..6).map(|k| (9.0 * x6[(i, k)]).sin()).sum::<f64>() + 0.01 * rng.random::<f64>()
    });
    let m128 = SparseParams {
        gp: gp_params(NoiseMode::Homoscedastic, 0, 3),
        inducing_points: 128,
        inducing_rounds: 1,
        full_rank_up_to: 0,
        ..SparseParams::default()
    }
    .check()
    .unwrap();
    let fits = [
        (
            "128 of 2000 in 6 dimensions",
            SparseGp::fit(&x6, &y6, &m128).unwrap(),
            &x6,
        ),
        (
            "low rank",
            SparseGp::fit(&x, &y, &low_rank_40(NoiseMode::Homoscedastic)).unwrap(),
            &x,
        ),
        (
            "heteroscedastic",
            SparseGp::fit(&x, &y, &low_rank_40(NoiseMode::Heteroscedastic)).unwrap(),
            &x,
        ),
        (
            "full rank, nearly noise-free",
            SparseGp::fit(&xn, &yn, &full_rank).unwrap(),
            &xn,
        ),
    ];
    for (what, gp, train) in &fits {
        assert!(gp.has_variance_factor(), "{what}: no factor");
        let s2 = gp.hyperparameters().signal_variance;
        let (fresh, _) = data(2000, train.ncols(), 23);
        let mut worst: f64 = 0.0;
        for q in [&fresh, *train] {
            let by_product = gp.predict(q).latent_variance;
            let by_solves = gp.latent_variance_by_solves(q);
            for (a, b) in by_product.iter().zip(&by_solves) {
                worst = worst.max((a - b).abs() / s2);
            }
        }
        eprintln!(
            "{what}: n_inducing {}, worst |Δvar| / s² = {worst:e}",
            gp.n_inducing()
        );
        assert!(worst <= 1e-9, "{what}: |Δvar| / s² up to {worst:e}");
    }
}

/// The variance factor is formed by `prepare` (where the service pays for it: on a blocking
/// thread after a fit, a restore or an online update), not left to the first query; an update
/// drops the old conditioning's factor and a clone keeps a formed one. The version cache
/// counts it: the floats cover both triangles and the factor of the main conditioning.
#[test]
fn prepare_forms_the_variance_factor_before_any_query() {
    let (x, y) = data(600, 2, 31);
    let gp = SparseGp::fit(&x, &y, &low_rank_40(NoiseMode::Heteroscedastic)).unwrap();
    assert!(!gp.variance_factor_formed(), "a fit forms it eagerly");
    let m = gp.n_inducing();
    assert!(
        gp.floats() >= 3 * m * m + 2 * m * x.ncols(),
        "{} floats for m = {m}",
        gp.floats()
    );
    gp.prepare();
    assert!(gp.variance_factor_formed());
    let kept = gp.clone();
    assert!(kept.variance_factor_formed(), "a clone dropped the factor");
    let mut updated = gp.clone();
    let (xn, yn) = data(50, 2, 32);
    updated.update(&xn, &yn).unwrap();
    assert!(
        !updated.variance_factor_formed(),
        "an update kept a stale factor"
    );
    updated.prepare();
    assert!(updated.variance_factor_formed());
    let restored = SparseGp::from_state(&updated.state()).unwrap();
    assert!(!restored.variance_factor_formed());
    restored.prepare();
    let (q, _) = data(300, 2, 33);
    assert_eq!(
        restored.predict(&q).latent_variance,
        updated.predict(&q).latent_variance
    );
}
