//! [`SparseGp`]: a fitted sparse GP — fit, online update, batched prediction, save and restore.

use nalgebra::{DMatrix, DVector};
use rand::SeedableRng;
use rand::seq::index::sample;
use rand_chacha::ChaCha8Rng;

use super::super::core::{PreparedQueries, Prior, mean};
use super::super::export::{NoisePredictor, Predictor};
use super::super::fit::{self, Optimum, Starts, Warm, default_start, optimise_with};
use super::super::hetero::{
    NOISE_MODEL_KERNEL, log_residual_bias, noise_clip, noise_gp_starts, round_seed,
};
use super::super::kernel::{Inputs, Kernel};
use super::super::lbfgs::{self, Settings};
use super::super::lml::NoiseSpec;
use super::super::model::{
    FantasyOf, FantasyQueries, check_data, check_finite_matrix, check_query, predict_rows,
};
use super::super::{
    Bounds, FitStats, GpError, GpModel, GpParams, Hyperparameters, ModelState, NoiseMode,
    NoiseSummary, Prediction,
};
use super::bound::Bound;
use super::core::{Ladder, Lambda, SparseCore};
use super::inducing::greedy_variance;
use super::{SparseNoiseState, SparseParams, SparseState, ValidSparseParams};

/// Relative function tolerance floor of the main GP's optimiser in the refinement on all the
/// data after a presolve ([`SparseParams::presolve_subset`]). The refinement starts at the
/// subset's optimum, and an iteration there gains little: at n = 100 000 (d = 6) the bound is
/// about 4·10⁴, so it stops once a step gains less than about 0.004 nats (the default `1e-9`
/// asks for 4·10⁻⁵). Measured (`precond bench gp --sparse --sparse-sizes 100000 --dims 6`):
/// 53 → 36 full-data evaluations, fit 57 → 43 s, the bound equal to 0.01 nat and the held-out
/// RMSE and NLL unchanged.
const REFINE_FTOL: f64 = 1e-7;

/// The sparse noise GP and its clip.
#[derive(Clone, Debug)]
struct SparseNoise {
    core: SparseCore,
    /// Its homoscedastic noise variance (on log-variance targets).
    noise: f64,
    clip: (f64, f64),
    /// Min, mean, max of the training points' noise variances at fit time.
    train: (f64, f64, f64),
}

impl SparseNoise {
    fn predict(&self, q: &Inputs) -> Vec<f64> {
        self.core
            .predict_parts(q, false)
            .0
            .iter()
            .map(|z| z.exp().clamp(self.clip.0, self.clip.1))
            .collect()
    }
}

/// A fitted sparse GP model deviation estimator (SGPR/VFE with `m` inducing points; see the
/// [module documentation](super)).
///
/// Holds the inducing points, `chol(K_mm)`, the factor `L_B` and the sufficient statistics — not
/// the training data: O(m²) memory whatever `n`. `Send + Sync`.
#[derive(Clone, Debug)]
pub struct SparseGp {
    mode: NoiseMode,
    main: SparseCore,
    noise_model: Option<SparseNoise>,
    hyper: Hyperparameters,
    homo_bound: f64,
    rounds: usize,
    stats: Option<FitStats>,
}

/// Everything the optimisation of one sparse GP needs besides the data.
struct Setup<'a> {
    p: &'a SparseParams,
    z: &'a Inputs,
    kernel: Kernel,
    bounds: &'a Bounds,
    ladder: Ladder,
}

/// Maximises the bound for inducing inputs `z` (see `fit::optimise_with` for the starts and the
/// screening).
fn optimise_sparse(
    s: &Setup<'_>,
    x: &Inputs,
    r: &[f64],
    noise: NoiseSpec<'_>,
    starts: Starts<'_>,
) -> Result<Optimum, GpError> {
    let (z, kernel, ladder) = (s.z, s.kernel, s.ladder);
    let mut runner = |x: &Inputs,
                      r: &[f64],
                      noise: NoiseSpec<'_>,
                      settings: &Settings,
                      (lo, hi): (&[f64], &[f64]),
                      start: &[f64],
                      memory: lbfgs::Memory| {
        let mut obj = Bound::new(x, z, r, noise, kernel, ladder);
        let mut fg = |t: &[f64], g: &mut [f64]| obj.eval(t, g);
        let out = lbfgs::minimize(&mut fg, start, lo, hi, settings, memory);
        (out, obj.evaluations)
    };
    optimise_with(
        &mut runner,
        x,
        r,
        noise,
        s.bounds,
        &s.p.gp,
        s.p.screen_subset,
        starts,
    )
}

/// An optimum `θ` with its final L-BFGS correction pairs.
type Point = (Vec<f64>, lbfgs::Memory);

/// A fit's model with what a warm-started refinement on more data needs.
struct Fitted {
    model: SparseGp,
    z: Inputs,
    /// Homoscedastic optimum and its L-BFGS pairs.
    homo: (Vec<f64>, lbfgs::Memory),
    /// Heteroscedastic noise GP and main GP optima (heteroscedastic mode).
    hetero: Option<(Point, Point)>,
    /// Number of points fitted.
    n: usize,
}

/// L-BFGS pairs from a fit on `from` points, for a run on `to` points: the bound's curvature
/// grows about linearly with `n`, so `y` is scaled by `to / from`.
fn rescale(memory: &lbfgs::Memory, from: usize, to: usize) -> lbfgs::Memory {
    let scale = to as f64 / from.max(1) as f64;
    memory
        .iter()
        .map(|(s, y)| (s.clone(), y.iter().map(|v| v * scale).collect()))
        .collect()
}

/// The `m × d` matrix of an [`Inputs`] (rows are points).
fn to_matrix(x: &Inputs) -> DMatrix<f64> {
    DMatrix::from_column_slice(x.n, x.d, &x.cols)
}

/// `z_i = log e_i + b(ρ_i)` with `e_i = (y_i − μ_i)² + k_iᵀΣ⁻¹k_i` and
/// `ρ_i = 1 − k_iᵀΣ⁻¹k_i / λ_i` (see the module documentation).
fn log_noise_targets(core: &SparseCore, x: &Inputs, y: &[f64], lambda: Lambda<'_>) -> Vec<f64> {
    let (mu, _, v2) = core.predict_parts(x, true);
    let n = y.len();
    let target = |i: usize| {
        let res = y[i] - mu[i];
        let rho = (1.0 - v2[i] / lambda.at(i)).clamp(0.0, 1.0);
        (res * res + v2[i]).max(1e-300).ln() + log_residual_bias(rho)
    };
    // b(ρ) is a 397-node quadrature: split large sets between threads.
    let threads = super::super::kernel::threads_for(n * 400);
    if threads <= 1 {
        return (0..n).map(target).collect();
    }
    let per = n.div_ceil(threads);
    let mut out = vec![0.0; n];
    std::thread::scope(|scope| {
        for (t, part) in out.chunks_mut(per).enumerate() {
            let target = &target;
            scope.spawn(move || {
                for (j, v) in part.iter_mut().enumerate() {
                    *v = target(t * per + j);
                }
            });
        }
    });
    out
}

/// Min, mean and max of a non-empty slice.
fn min_mean_max(v: &[f64]) -> (f64, f64, f64) {
    (
        v.iter().copied().fold(f64::INFINITY, f64::min),
        mean(v),
        v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    )
}

/// Points of the exact fit that gives the sparse fit its first start.
const EXACT_START_POINTS: usize = 512;

/// The exact GP's homoscedastic optimum `[log ℓ, log s², log σ²]` on a seeded subset of at most
/// [`EXACT_START_POINTS`] points (with `p.restarts`); `None` if that fit fails.
fn exact_start(x: &Inputs, r: &[f64], p: &GpParams) -> Option<Vec<f64>> {
    let (xs, rs) = if x.n <= EXACT_START_POINTS {
        (x.clone(), r.to_vec())
    } else {
        let mut rng = ChaCha8Rng::seed_from_u64(p.seed ^ 0x0E8A_C757_A127_0000);
        let mut idx = sample(&mut rng, x.n, EXACT_START_POINTS).into_vec();
        idx.sort_unstable();
        (x.subset(&idx), idx.iter().map(|&i| r[i]).collect())
    };
    fit::optimise_homoscedastic(&xs, &rs, p)
        .ok()
        .map(|o| o.theta)
}

fn setup<'a>(sp: &'a SparseParams, z: &'a Inputs, ladder: Ladder) -> Setup<'a> {
    Setup {
        p: sp,
        z,
        kernel: sp.gp.kernel,
        bounds: &sp.gp.bounds,
        ladder,
    }
}

/// `K_mm`'s jitter ladder: `jitter · s²` up to `max(gp.jitter_max, jitter) · s²`.
fn ladder(sp: &SparseParams) -> Ladder {
    Ladder::Relative {
        initial: sp.jitter,
        max: sp.gp.jitter_max.max(sp.jitter),
    }
}

/// The homoscedastic core at `θ = [log ℓ, log s², log σ²]`.
fn build_homo(
    x: &Inputs,
    y: &[f64],
    sp: &SparseParams,
    z: &Inputs,
    theta: &[f64],
) -> Result<SparseCore, GpError> {
    let d = x.d;
    let prior = Prior::from_log(sp.gp.kernel, sp.gp.prior_mean, &theta[..=d]);
    let noise = Lambda::Homo(theta[d + 1].exp());
    SparseCore::build(&prior, x, y, z, noise, ladder(sp))
}

/// Where the heteroscedastic rounds start.
struct Rounds {
    /// The model whose residuals give the first round's noise targets, and its per-point noise
    /// (`None`: homoscedastic, `σ²` passed separately).
    targets_from: (SparseCore, Option<Vec<f64>>),
    /// Warm start of the noise GP (`None`: default start plus restarts).
    noise: Option<(Vec<f64>, lbfgs::Memory)>,
    /// Warm start of the main GP, `[log ℓ, log s²]`.
    main: (Vec<f64>, lbfgs::Memory),
    /// At most this many rounds.
    rounds: usize,
    /// The main GP optimiser's relative function tolerance floor (0: the settings' own).
    main_ftol: f64,
}

/// What the heteroscedastic rounds produced.
struct RoundsOut {
    model: SparseGp,
    optima: Option<(Point, Point)>,
}

/// The heteroscedastic rounds (see `hetero` for the procedure) with sparse GPs, from `start`;
/// the LML-best round is kept, as in the exact GP.
fn hetero_rounds(
    x: &Inputs,
    y: &[f64],
    sp: &SparseParams,
    z: &Inputs,
    start: Rounds,
    sigma2: f64,
) -> Result<RoundsOut, GpError> {
    let p = &sp.gp;
    let d = x.d;
    let ladder = ladder(sp);
    let r: Vec<f64> = y.iter().map(|v| v - p.prior_mean).collect();
    let clip = noise_clip(y, p.bounds.noise_variance);
    let noise_z = z.subset(&(0..z.n.min(sp.noise_inducing_points)).collect::<Vec<_>>());
    let noise_setup = Setup {
        p: sp,
        z: &noise_z,
        kernel: NOISE_MODEL_KERNEL,
        bounds: &p.noise_model_bounds,
        ladder,
    };
    let main_setup = setup(sp, z, ladder);
    type Best = (SparseCore, SparseNoise, Vec<f64>, usize);
    let mut best: Option<Best> = None;
    let (mut current_theta, mut main_memory) = start.main;
    let (mut noise_theta, mut noise_memory) = match start.noise {
        Some((t, m)) => (Some(t), m),
        None => (None, Vec::new()),
    };
    let mut optima = None;
    let mut evaluations = 0;
    let mut converged = true;
    let first = start.targets_from;
    for round in 0..start.rounds {
        let targets = match (&best, &first) {
            (None, (core, None)) => log_noise_targets(core, x, y, Lambda::Homo(sigma2)),
            (None, (core, Some(l))) => log_noise_targets(core, x, y, Lambda::Per(l)),
            (Some((core, _, lambda, _)), _) => log_noise_targets(core, x, y, Lambda::Per(lambda)),
        };
        let mz = mean(&targets);
        let rz: Vec<f64> = targets.iter().map(|v| v - mz).collect();
        let seed = round_seed(p.seed, round);
        let g = optimise_sparse(
            &noise_setup,
            x,
            &rz,
            NoiseSpec::Homoscedastic,
            noise_gp_starts(noise_theta.as_deref(), &noise_memory, p.restarts, seed),
        )?;
        let noise_prior = Prior::from_log(NOISE_MODEL_KERNEL, mz, &g.theta[..=d]);
        let gn = g.theta[d + 1].exp();
        let ncore = SparseCore::build(
            &noise_prior,
            x,
            &targets,
            &noise_z,
            Lambda::Homo(gn),
            ladder,
        )?;
        let mut nm = SparseNoise {
            core: ncore,
            noise: gn,
            clip,
            train: (0.0, 0.0, 0.0),
        };
        let lambda = nm.predict(x);
        nm.train = min_mean_max(&lambda);
        let f = optimise_sparse(
            &main_setup,
            x,
            &r,
            NoiseSpec::Fixed(&lambda),
            Starts::warm(
                Warm {
                    theta: &current_theta,
                    memory: main_memory.clone(),
                },
                p.seed,
            )
            .ftol_floor(start.main_ftol),
        )?;
        let prior = Prior::from_log(p.kernel, p.prior_mean, &f.theta[..=d]);
        let main = SparseCore::build(&prior, x, y, z, Lambda::Per(&lambda), ladder)?;
        evaluations += g.evaluations + f.evaluations;
        let improved = match &best {
            None => true,
            Some((b, ..)) => main.bound > b.bound + p.hetero_tolerance * b.bound.abs(),
        };
        if !improved {
            break;
        }
        noise_theta = Some(g.theta.clone());
        noise_memory = g.memory.clone();
        current_theta = f.theta.clone();
        main_memory = f.memory.clone();
        optima = Some(((g.theta, g.memory), (f.theta, f.memory)));
        converged &= g.converged && f.converged;
        best = Some((main, nm, lambda, round + 1));
    }
    let (main, nm, _, rounds) = best
        .ok_or_else(|| GpError::OptimisationFailed("no heteroscedastic round succeeded".into()))?;
    Ok(RoundsOut {
        model: SparseGp {
            mode: NoiseMode::Heteroscedastic,
            hyper: main.hyperparameters(nm.train.1),
            main,
            noise_model: Some(nm),
            homo_bound: f64::NAN,
            rounds,
            stats: Some(FitStats {
                evaluations,
                converged,
            }),
        },
        optima,
    })
}

/// A GP with hyperparameters `h` conditioned on `(x, y)` with noise `lambda` (smallest
/// `noise_min`), whose inducing points are every input of `x` not already determined by those
/// before it: the greedy selection runs over all of `x` and stops below a conditional variance
/// of `10⁻⁶ noise_min`, which is also `K_mm`'s first jitter (relative to `s²`, between `1e-12`
/// and `sp.jitter`). Both perturb the bound by about `n · 10⁻⁶ / 2`, so it is the exact log
/// marginal likelihood; a jitter relative to `s²` alone (`sp.jitter`) would not be, when the
/// noise is 10⁻⁴ of the signal as the MDE's often is.
fn full_rank_core(
    x: &Inputs,
    y: &[f64],
    h: &Hyperparameters,
    lambda: Lambda<'_>,
    noise_min: f64,
    sp: &SparseParams,
) -> Result<SparseCore, GpError> {
    let s2 = h.signal_variance;
    let rel = (1e-6 * noise_min / s2).clamp(1e-12, sp.jitter);
    let all = greedy_variance(h.kernel, x, &h.length_scales, s2, x.n, x.n, rel, sp.gp.seed);
    SparseCore::build(
        &Prior::of(h),
        x,
        y,
        &x.subset(&all),
        lambda,
        Ladder::Relative {
            initial: rel,
            max: sp.gp.jitter_max.max(sp.jitter),
        },
    )
}

impl SparseGp {
    /// Fits a sparse GP to training inputs `x` (rows are points, already scaled to the unit box)
    /// and targets `y`: selects inducing points, maximises the collapsed bound over the
    /// hyperparameters, and (heteroscedastic mode, `n ≥ gp.hetero_min_points`) runs the
    /// heteroscedastic rounds. O(n m²) time per bound evaluation, O(n + m²) memory beyond the
    /// data. Same data and seed, same model.
    ///
    /// With at most [`SparseParams::full_rank_up_to`] points the fit is full rank: the exact
    /// GP's fit in sparse form ([`from_exact_state`](Self::from_exact_state)), every distinct
    /// training input an inducing point.
    ///
    /// # Errors
    /// As [`GpModel::fit`](super::super::GpModel::fit).
    pub fn fit(
        x: &DMatrix<f64>,
        y: &DVector<f64>,
        params: &ValidSparseParams,
    ) -> Result<SparseGp, GpError> {
        let xi = check_data(x, y)?;
        if xi.n <= params.full_rank_up_to {
            let exact = GpModel::fit(x, y, &params.gp.check()?)?;
            let (state, stats) = (exact.state(), exact.fit_stats().cloned());
            // Its n × n factors are not needed for the conversion.
            drop(exact);
            let mut model = Self::from_exact_state(x, y, &state, params)?;
            model.stats = stats;
            return Ok(model);
        }
        Self::fit_inner(&xi, y.as_slice(), params, None)
    }

    /// The exact GP `state`, fitted on `(x, y)`, in sparse form: the hyperparameters and the
    /// noise GP's targets are the exact GP's, and every training input is an inducing point of
    /// the main GP and of the noise GP except those the ones before them already determine —
    /// by greedy variance selection under each GP's kernel, an input whose conditional
    /// variance is below a millionth of that GP's smallest noise variance counts as determined
    /// (so repeated inputs count once), and `K_mm` takes a jitter of that size. Each such
    /// difference moves the bound by about its size over twice the noise, so the bound is the
    /// exact log marginal likelihood and the predictions are the exact GP's (to about 1e-6
    /// relative), from `O(m²)` numbers that need no training data. `O(n³)` time.
    ///
    /// # Errors
    /// Data errors as for [`fit`](Self::fit); [`GpError::DimensionMismatch`] or
    /// [`GpError::InvalidState`] when `state` was not fitted on `n` points of this dimension;
    /// [`GpError::NotPositiveDefinite`] if `K_mm` does not factorise within the jitter ladder.
    pub fn from_exact_state(
        x: &DMatrix<f64>,
        y: &DVector<f64>,
        state: &ModelState,
        params: &ValidSparseParams,
    ) -> Result<SparseGp, GpError> {
        let xi = check_data(x, y)?;
        if state.n_train != xi.n {
            return Err(GpError::DimensionMismatch {
                what: "exact model's training points vs rows of x",
                expected: state.n_train,
                found: xi.n,
            });
        }
        let sp = params.params();
        let h = &state.hyperparameters;
        h.check(xi.d, "exact model hyperparameters")?;
        match (state.noise, &state.noise_model) {
            (NoiseMode::Homoscedastic, None) => {
                let core = full_rank_core(
                    &xi,
                    y.as_slice(),
                    h,
                    Lambda::Homo(h.noise_variance),
                    h.noise_variance,
                    sp,
                )?;
                Ok(SparseGp {
                    mode: NoiseMode::Homoscedastic,
                    hyper: core.hyperparameters(h.noise_variance),
                    homo_bound: core.bound,
                    main: core,
                    noise_model: None,
                    rounds: 0,
                    stats: None,
                })
            }
            (NoiseMode::Heteroscedastic, Some(ns)) => {
                let g = &ns.hyperparameters;
                g.check(xi.d, "exact model's noise GP hyperparameters")?;
                if ns.log_noise_targets.len() != xi.n {
                    return Err(GpError::DimensionMismatch {
                        what: "noise GP targets vs rows of x",
                        expected: xi.n,
                        found: ns.log_noise_targets.len(),
                    });
                }
                let core = full_rank_core(
                    &xi,
                    &ns.log_noise_targets,
                    g,
                    Lambda::Homo(g.noise_variance),
                    g.noise_variance,
                    sp,
                )?;
                let mut nm = SparseNoise {
                    core,
                    noise: g.noise_variance,
                    clip: ns.noise_variance_clip,
                    train: (0.0, 0.0, 0.0),
                };
                let lambda = nm.predict(&xi);
                nm.train = min_mean_max(&lambda);
                let core =
                    full_rank_core(&xi, y.as_slice(), h, Lambda::Per(&lambda), nm.train.0, sp)?;
                Ok(SparseGp {
                    mode: NoiseMode::Heteroscedastic,
                    hyper: core.hyperparameters(nm.train.1),
                    main: core,
                    noise_model: Some(nm),
                    homo_bound: ns.homoscedastic_lml,
                    rounds: ns.rounds,
                    stats: None,
                })
            }
            _ => Err(GpError::InvalidState(
                "exact model's noise mode and noise model disagree".into(),
            )),
        }
    }

    /// Like [`fit`](Self::fit) with the inducing inputs given (rows are points, unit box) instead
    /// of selected; [`SparseParams::inducing_rounds`] is then ignored.
    ///
    /// # Errors
    /// As [`fit`](Self::fit), and [`GpError::DimensionMismatch`] / [`GpError::NonFinite`] /
    /// [`GpError::EmptyData`] for bad inducing inputs.
    pub fn fit_with_inducing(
        x: &DMatrix<f64>,
        y: &DVector<f64>,
        z: &DMatrix<f64>,
        params: &ValidSparseParams,
    ) -> Result<SparseGp, GpError> {
        let xi = check_data(x, y)?;
        if z.nrows() == 0 {
            return Err(GpError::EmptyData("no inducing points"));
        }
        if z.ncols() != x.ncols() {
            return Err(GpError::DimensionMismatch {
                what: "columns of inducing points vs input dimension",
                expected: x.ncols(),
                found: z.ncols(),
            });
        }
        check_finite_matrix(z, "inducing points")?;
        Self::fit_inner(&xi, y.as_slice(), params, Some(Inputs::from_matrix(z)))
    }

    /// With `presolve_subset` set and `n > 2 · presolve_subset`: the whole procedure on a seeded
    /// subset, then one warm-started refinement on all the data ([`refine`](Self::refine)).
    fn fit_inner(
        x: &Inputs,
        y: &[f64],
        params: &ValidSparseParams,
        fixed_z: Option<Inputs>,
    ) -> Result<SparseGp, GpError> {
        let sp = params.params();
        let sub = sp.presolve_subset;
        if sub == 0 || x.n <= 2 * sub {
            return Ok(Self::fit_all(x, y, sp, fixed_z)?.model);
        }
        let mut rng = ChaCha8Rng::seed_from_u64(sp.gp.seed ^ 0x5EED_5EED_5EED_5EED);
        let mut idx = sample(&mut rng, x.n, sub).into_vec();
        idx.sort_unstable();
        let xs = x.subset(&idx);
        let ys: Vec<f64> = idx.iter().map(|&i| y[i]).collect();
        let pre = Self::fit_all(&xs, &ys, sp, fixed_z)?;
        Self::refine(x, y, sp, pre)
    }

    /// The full procedure on `(x, y)`: inducing selection rounds with restarts, then the
    /// heteroscedastic rounds.
    fn fit_all(
        x: &Inputs,
        y: &[f64],
        sp: &SparseParams,
        fixed_z: Option<Inputs>,
    ) -> Result<Fitted, GpError> {
        let p = &sp.gp;
        let d = x.d;
        let r: Vec<f64> = y.iter().map(|v| v - p.prior_mean).collect();
        let ladder = ladder(sp);
        let select = |ls: &[f64], s2: f64, round: u64| -> Inputs {
            let pool = sp.selection_candidates.max(4 * sp.inducing_points);
            let seed = p
                .seed
                .wrapping_add(0xD1B5_4A32_D192_ED03u64.wrapping_mul(round + 1));
            let idx = greedy_variance(
                p.kernel,
                x,
                ls,
                s2,
                sp.inducing_points,
                pool,
                sp.jitter.max(1e-10),
                seed,
            );
            x.subset(&idx)
        };
        // The first start, and the hyperparameters of the first selection: the exact GP's
        // optimum on a seeded subset of at most 512 points. It finds which inputs matter, so the
        // inducing points spread over those (measured at d = 21 with 6 relevant inputs, n = 2000:
        // held-out NLL −0.218 from the default start, see the sparse benchmark).
        let theta0 = exact_start(x, &r, p).unwrap_or_else(|| default_start(d, &r, true));
        let ls0: Vec<f64> = theta0[..d].iter().map(|v| v.exp()).collect();
        let reselect = fixed_z.is_none();
        let mut z = match fixed_z {
            Some(z) => z,
            None => select(&ls0, theta0[d].exp(), 0),
        };
        // A warm refit starts from its subset optimum alone (itself warm-started).
        let starts = if p.warm.is_some() {
            Starts::warm(
                Warm {
                    theta: &theta0,
                    memory: Vec::new(),
                },
                p.seed,
            )
        } else {
            Starts::new(p.restarts, p.seed).first(&theta0)
        };
        let mut opt = optimise_sparse(
            &setup(sp, &z, ladder),
            x,
            &r,
            NoiseSpec::Homoscedastic,
            starts,
        )?;
        let mut evaluations = opt.evaluations;
        let mut homo = build_homo(x, y, sp, &z, &opt.theta)?;
        if reselect {
            for round in 1..sp.inducing_rounds {
                let ls: Vec<f64> = opt.theta[..d].iter().map(|v| v.exp()).collect();
                let z2 = select(&ls, opt.theta[d].exp(), round as u64);
                let o2 = optimise_sparse(
                    &setup(sp, &z2, ladder),
                    x,
                    &r,
                    NoiseSpec::Homoscedastic,
                    Starts::warm(
                        Warm {
                            theta: &opt.theta,
                            memory: opt.memory.clone(),
                        },
                        p.seed,
                    ),
                )?;
                evaluations += o2.evaluations;
                let c2 = build_homo(x, y, sp, &z2, &o2.theta)?;
                if c2.bound > homo.bound {
                    (z, opt, homo) = (z2, o2, c2);
                } else {
                    break;
                }
            }
        }
        let converged = opt.converged;
        let homo_opt = (opt.theta, opt.memory);
        let hetero = p.noise == NoiseMode::Heteroscedastic && x.n >= p.hetero_min_points;
        if !hetero {
            return Ok(Fitted {
                model: SparseGp::homoscedastic(homo, &homo_opt.0, evaluations, converged),
                z,
                homo: homo_opt,
                hetero: None,
                n: x.n,
            });
        }
        let sigma2 = homo_opt.0[d + 1].exp();
        let start = Rounds {
            targets_from: (homo, None),
            noise: None,
            main: (homo_opt.0[..d + 1].to_vec(), Vec::new()),
            rounds: p.hetero_rounds,
            main_ftol: 0.0,
        };
        let homo_bound = start.targets_from.0.bound;
        let mut out = hetero_rounds(x, y, sp, &z, start, sigma2)?;
        out.model.homo_bound = homo_bound;
        if let Some(s) = out.model.stats.as_mut() {
            s.evaluations += evaluations;
            s.converged &= converged;
        }
        Ok(Fitted {
            model: out.model,
            z,
            homo: homo_opt,
            hetero: out.optima,
            n: x.n,
        })
    }

    /// Refines a fit `pre` (on a subset) on all of `(x, y)` with its inducing points: the
    /// homoscedastic optimum warm-started from the subset's; in heteroscedastic mode, one round
    /// whose noise targets come from the subset's final model conditioned on all the data, with
    /// the noise GP and the main GP warm-started from the subset's optima.
    fn refine(x: &Inputs, y: &[f64], sp: &SparseParams, pre: Fitted) -> Result<SparseGp, GpError> {
        let p = &sp.gp;
        let ladder = ladder(sp);
        let z = &pre.z;
        let r: Vec<f64> = y.iter().map(|v| v - p.prior_mean).collect();
        let pre_evals = pre.model.stats.as_ref().map_or(0, |s| s.evaluations);
        match pre.hetero {
            None => {
                let o = optimise_sparse(
                    &setup(sp, z, ladder),
                    x,
                    &r,
                    NoiseSpec::Homoscedastic,
                    Starts::warm(
                        Warm {
                            theta: &pre.homo.0,
                            memory: rescale(&pre.homo.1, pre.n, x.n),
                        },
                        p.seed,
                    )
                    .ftol_floor(REFINE_FTOL),
                )?;
                let core = build_homo(x, y, sp, z, &o.theta)?;
                Ok(SparseGp::homoscedastic(
                    core,
                    &o.theta,
                    pre_evals + o.evaluations,
                    o.converged,
                ))
            }
            Some((noise_opt, main_opt)) => {
                // The subset's final model, conditioned on all the data.
                let conditioned = pre.model.condition_inputs(x, y)?;
                let lambda = pre.model.noise_at(x);
                let homo_bound = build_homo(x, y, sp, z, &pre.homo.0)?.bound;
                let start = Rounds {
                    targets_from: (conditioned.main, Some(lambda)),
                    noise: Some((noise_opt.0, rescale(&noise_opt.1, pre.n, x.n))),
                    main: (main_opt.0, rescale(&main_opt.1, pre.n, x.n)),
                    rounds: 1,
                    main_ftol: REFINE_FTOL,
                };
                let mut out = hetero_rounds(x, y, sp, z, start, f64::NAN)?;
                out.model.homo_bound = homo_bound;
                out.model.rounds = pre.model.rounds;
                if let Some(s) = out.model.stats.as_mut() {
                    s.evaluations += pre_evals;
                }
                Ok(out.model)
            }
        }
    }

    /// A homoscedastic model from its core and optimum.
    fn homoscedastic(core: SparseCore, theta: &[f64], evaluations: usize, converged: bool) -> Self {
        let sigma2 = theta[core.d + 1].exp();
        SparseGp {
            mode: NoiseMode::Homoscedastic,
            hyper: core.hyperparameters(sigma2),
            homo_bound: core.bound,
            main: core,
            noise_model: None,
            rounds: 0,
            stats: Some(FitStats {
                evaluations,
                converged,
            }),
        }
    }

    /// [`condition`](Self::condition) on checked inputs.
    fn condition_inputs(&self, xi: &Inputs, y: &[f64]) -> Result<SparseGp, GpError> {
        let lambda = self.noise_at(xi);
        let l = match self.mode {
            NoiseMode::Homoscedastic => Lambda::Homo(self.hyper.noise_variance),
            NoiseMode::Heteroscedastic => Lambda::Per(&lambda),
        };
        let c = &self.main;
        let main = SparseCore::build(&c.prior(), xi, y, &c.z, l, Ladder::Exact(c.jitter))?;
        Ok(SparseGp {
            main,
            stats: None,
            ..self.clone()
        })
    }

    /// Per-point noise variances at `x` under this model's noise model.
    fn noise_at(&self, x: &Inputs) -> Vec<f64> {
        match &self.noise_model {
            Some(nm) => nm.predict(x),
            None => vec![self.hyper.noise_variance; x.n],
        }
    }

    /// Checks new data against the model's input dimension.
    fn check_new(&self, x: &DMatrix<f64>, y: &DVector<f64>) -> Result<Inputs, GpError> {
        if x.ncols() != self.main.d {
            return Err(GpError::DimensionMismatch {
                what: "columns of x vs input dimension",
                expected: self.main.d,
                found: x.ncols(),
            });
        }
        check_data(x, y)
    }

    /// Absorbs a batch of new points (e.g. one executed trajectory) at fixed hyperparameters,
    /// inducing points and noise model: `L_B` takes a rank-k Cholesky update and the statistics
    /// grow by sums. Afterwards the model equals [`condition`](Self::condition) on all the
    /// data at once (to rounding). O(k m²) time; the bound is updated too. An empty batch is a
    /// no-op; on error the model is unchanged.
    ///
    /// # Errors
    /// Data errors as for [`fit`](Self::fit) (a wrong column count is a
    /// [`GpError::DimensionMismatch`]).
    pub fn update(&mut self, x: &DMatrix<f64>, y: &DVector<f64>) -> Result<(), GpError> {
        if x.nrows() == 0 && y.is_empty() {
            return Ok(());
        }
        let xi = self.check_new(x, y)?;
        let lambda = self.noise_at(&xi);
        let l = match self.mode {
            NoiseMode::Homoscedastic => Lambda::Homo(self.hyper.noise_variance),
            NoiseMode::Heteroscedastic => Lambda::Per(&lambda),
        };
        self.main.update(&xi, y.as_slice(), l)
    }

    /// The same hyperparameters, inducing points and noise model conditioned afresh on `(x, y)`
    /// (no optimisation): what [`update`](Self::update)s add up to, or a rebuild after the data
    /// changed. O(n m²).
    ///
    /// # Errors
    /// Data errors as for [`fit`](Self::fit); [`GpError::NotPositiveDefinite`] if `K_mm` no longer
    /// factorises with the stored jitter (it always does for a model this crate fitted).
    pub fn condition(&self, x: &DMatrix<f64>, y: &DVector<f64>) -> Result<SparseGp, GpError> {
        let xi = self.check_new(x, y)?;
        self.condition_inputs(&xi, y.as_slice())
    }

    /// Predicts at the rows of `x`: mean, latent variance and noise variance per point.
    /// O(m²) per point after the fit; batches run on several threads.
    ///
    /// Never panics: a wrong column count gives NaN everywhere, a row with a non-finite
    /// coordinate NaN for that row ([`try_predict`](Self::try_predict) returns errors instead).
    pub fn predict(&self, x: &DMatrix<f64>) -> Prediction {
        predict_rows(x, self.main.d, |q| {
            let (mean, latent_variance) = self.main.predict(q);
            Prediction {
                mean,
                latent_variance,
                noise_variance: self.noise_at(q),
            }
        })
    }

    /// Like [`predict`](Self::predict) but rejects a wrong column count or non-finite inputs.
    pub fn try_predict(&self, x: &DMatrix<f64>) -> Result<Prediction, GpError> {
        check_query(x, self.main.d)?;
        Ok(self.predict(x))
    }

    /// Forms what [`predict`](Self::predict) would otherwise form on its first call after a
    /// fit, a restore or an update (the variance factor, `O(m³)`: about a second at the cap of
    /// 4096 inducing points), so that a caller can pay for it where long work belongs — the
    /// service does so on its blocking threads before a version answers, and a small query
    /// answered on an async worker then costs only its products.
    pub fn prepare(&self) {
        let _ = self.main.variance_factor();
    }

    /// Floats this model keeps in memory: the main conditioning's (its variance factor
    /// included) and the noise model's.
    pub fn floats(&self) -> usize {
        self.main.floats() + self.noise_model.as_ref().map_or(0, |nm| nm.core.floats())
    }

    /// Whether [`predict`](Self::predict) computes the latent variance by one triangular
    /// product (tests).
    #[cfg(test)]
    pub(crate) fn has_variance_factor(&self) -> bool {
        self.main.variance_factor().is_some()
    }

    /// Whether the variance factor is formed already, without forming it (tests).
    #[cfg(test)]
    pub(crate) fn variance_factor_formed(&self) -> bool {
        self.main.variance_factor_formed()
    }

    /// The latent variances at the rows of `x` by the two triangular solves (tests).
    #[cfg(test)]
    pub(crate) fn latent_variance_by_solves(&self, x: &DMatrix<f64>) -> Vec<f64> {
        let (_, v1, v2) = self.main.predict_parts(&Inputs::from_matrix(x), true);
        let s2 = self.main.s2;
        v1.iter()
            .zip(&v2)
            .map(|(a, b)| (s2 - a + b).clamp(0.0, s2))
            .collect()
    }

    /// Like [`predict`](Self::predict), as if the rows of `pending` had been observed too at
    /// this model's hyperparameters, inducing points and noise (a batch executed but not yet
    /// fitted): the same mean, and the latent variance an [`update`](Self::update) with them
    /// would leave (the variance does not depend on the labels; see
    /// [`fantasy`](Self::fantasy)). A `pending` with the wrong column count or a non-finite
    /// coordinate gives the plain prediction.
    pub fn predict_fantasised(&self, x: &DMatrix<f64>, pending: &DMatrix<f64>) -> Prediction {
        self.fantasy(x.clone()).predict(pending)
    }

    /// The rows of `x` prepared for [`predict_fantasised`](Self::predict_fantasised) with many
    /// alternative `pending` sets ([`FantasyQueries::predict_each`]): `O(m_z² · m)` here for `m`
    /// rows and `m_z` inducing points, then `O(m_z² k + m_z k m)` a set of `k` rows, no copy
    /// of the model (Woodbury on the update's `B`).
    pub fn fantasy(&self, x: DMatrix<f64>) -> FantasyQueries<'_> {
        let of_model = FantasyOf {
            dim: self.main.d,
            plain: Box::new(|x| self.predict(x)),
            noise_at: Box::new(|q| self.noise_at(q)),
        };
        FantasyQueries::new(of_model, x, |q| {
            let (mean, fantasy) = self.main.fantasy(q);
            Some((mean, Box::new(fantasy) as Box<dyn PreparedQueries>))
        })
    }

    /// The fitted GP as plain numbers ([`Predictor`]): inducing inputs, `w`, the inverses of
    /// the two triangles its variance solves with, and the noise. `O(m²)` numbers.
    pub fn predictor(&self) -> Predictor {
        Predictor {
            main: self.main.predictor(true),
            noise: NoisePredictor::new(
                self.hyper.noise_variance,
                self.noise_model
                    .as_ref()
                    .map(|nm| (nm.core.predictor(false), nm.clip)),
            ),
        }
    }

    /// The state to store; [`from_state`](Self::from_state) rebuilds this model from it alone
    /// (no training data), predicting exactly as this one (serde_json round-trips floats
    /// exactly with this crate's `float_roundtrip` feature).
    pub fn state(&self) -> SparseState {
        SparseState {
            format: 1,
            noise: self.mode,
            main: self.main.state(self.hyper.noise_variance),
            noise_model: self.noise_model.as_ref().map(|nm| SparseNoiseState {
                core: nm.core.state(nm.noise),
                noise_variance_clip: nm.clip,
                rounds: self.rounds,
                homoscedastic_bound: self.homo_bound,
                train_noise_variance: nm.train,
            }),
        }
    }

    /// Rebuilds a model from its [`SparseState`] (no data, no optimisation): `K_mm` is
    /// refactorised with the stored jitter, everything else is taken as stored.
    ///
    /// # Errors
    /// [`GpError::InvalidState`], [`GpError::DimensionMismatch`] or [`GpError::NonFinite`] for a
    /// malformed or inconsistent state; [`GpError::NotPositiveDefinite`] if `K_mm` does not
    /// factorise with the stored jitter.
    pub fn from_state(state: &SparseState) -> Result<SparseGp, GpError> {
        if state.format != 1 {
            return Err(GpError::InvalidState(format!(
                "unsupported sparse format {}",
                state.format
            )));
        }
        let main = SparseCore::from_state(&state.main, "sparse main GP")?;
        let hyper = state.main.hyperparameters.clone();
        let (noise_model, rounds, homo_bound) = match (state.noise, &state.noise_model) {
            (NoiseMode::Homoscedastic, None) => (None, 0, main.bound),
            (NoiseMode::Heteroscedastic, Some(ns)) => {
                let core = SparseCore::from_state(&ns.core, "sparse noise GP")?;
                if core.d != main.d {
                    return Err(GpError::DimensionMismatch {
                        what: "noise GP vs main GP input dimension",
                        expected: main.d,
                        found: core.d,
                    });
                }
                let (lo, hi) = ns.noise_variance_clip;
                if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && lo <= hi) {
                    return Err(GpError::InvalidState(
                        "noise_variance_clip must satisfy 0 < low <= high < inf".into(),
                    ));
                }
                let nm = SparseNoise {
                    core,
                    noise: ns.core.hyperparameters.noise_variance,
                    clip: ns.noise_variance_clip,
                    train: ns.train_noise_variance,
                };
                (Some(nm), ns.rounds, ns.homoscedastic_bound)
            }
            _ => {
                return Err(GpError::InvalidState(
                    "noise mode and noise model disagree".into(),
                ));
            }
        };
        Ok(SparseGp {
            mode: state.noise,
            main,
            noise_model,
            hyper,
            homo_bound,
            rounds,
            stats: None,
        })
    }

    /// The collapsed variational bound `F ≤ log p(y)` of the data absorbed so far (natural
    /// log; comparable with [`GpModel::log_marginal_likelihood`](super::super::GpModel::log_marginal_likelihood),
    /// which it equals when the inducing inputs are the training inputs).
    pub fn bound(&self) -> f64 {
        self.main.bound
    }

    /// The main GP's hyperparameters (for heteroscedastic models `noise_variance` is the mean
    /// per-point training noise variance at fit time).
    pub fn hyperparameters(&self) -> &Hyperparameters {
        &self.hyper
    }

    /// The noise model actually used (heteroscedastic requests fall back to homoscedastic when
    /// `n < gp.hetero_min_points`).
    pub fn noise_mode(&self) -> NoiseMode {
        self.mode
    }

    /// The inducing inputs, rows are points (unit box).
    pub fn inducing_points(&self) -> DMatrix<f64> {
        to_matrix(&self.main.z)
    }

    /// Number of inducing points `m`.
    pub fn n_inducing(&self) -> usize {
        self.main.m
    }

    /// Training points absorbed (by the fit and by [`update`](Self::update)s).
    pub fn n_train(&self) -> usize {
        self.main.stats.n
    }

    /// Input dimension.
    pub fn input_dim(&self) -> usize {
        self.main.d
    }

    /// Absolute jitter on `K_mm`'s diagonal.
    pub fn jitter(&self) -> f64 {
        self.main.jitter
    }

    /// How the optimisation went; `None` for a model rebuilt from a state or conditioned anew.
    pub fn fit_stats(&self) -> Option<&FitStats> {
        self.stats.as_ref()
    }

    /// For heteroscedastic models: the training noise variances' min/mean/max at fit time, the
    /// noise GP's hyperparameters, the rounds kept and the homoscedastic fit's bound (in the
    /// `homoscedastic_lml` field). `None` for homoscedastic models.
    pub fn noise_summary(&self) -> Option<NoiseSummary> {
        let nm = self.noise_model.as_ref()?;
        Some(NoiseSummary {
            min_noise_variance: nm.train.0,
            mean_noise_variance: nm.train.1,
            max_noise_variance: nm.train.2,
            noise_model: nm.core.hyperparameters(nm.noise),
            rounds: self.rounds,
            homoscedastic_lml: self.homo_bound,
        })
    }
}
