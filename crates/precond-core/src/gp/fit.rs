//! Hyperparameter optimisation: maximise the LML over the log-parameters with projected L-BFGS
//! from several seeded starts, optionally screening the starts on a data subset.

use rand::seq::index::sample;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::kernel::{Inputs, Kernel};
use super::lbfgs::{self, Settings};
use super::lml::{Jitter, NoiseSpec, Objective};
use super::{Bounds, GpError, GpParams};

/// The result of optimising one GP's hyperparameters.
#[derive(Clone, Debug)]
pub(crate) struct Optimum {
    /// Best log-parameters `[log ℓ.., log s², (log σ²)]`.
    pub theta: Vec<f64>,
    /// Total objective evaluations (all starts, screening included).
    pub evaluations: usize,
    /// Whether the final full-data run met a convergence test (not the iteration cap).
    pub converged: bool,
    /// The final L-BFGS correction pairs (to warm-start a related optimisation).
    pub memory: lbfgs::Memory,
}

/// A warm start: a point and, optionally, L-BFGS correction pairs from a related run.
pub(crate) struct Warm<'a> {
    /// Starting log-parameters.
    pub theta: &'a [f64],
    /// Correction pairs `(s, y)`, oldest first.
    pub memory: lbfgs::Memory,
}

/// Where an optimisation starts and how closely it converges; see [`optimise`].
pub(crate) struct Starts<'a> {
    /// A warm start: then it is the only start and nothing is screened.
    pub warm: Option<Warm<'a>>,
    /// Seeded random starts beside the default one (without `warm`).
    pub restarts: usize,
    /// Replaces the deterministic default start (without `warm`).
    pub first: Option<&'a [f64]>,
    /// Seeds the random starts and the screening subset.
    pub seed: u64,
    /// Loosens the relative function tolerance to at least this.
    pub ftol_floor: f64,
    /// Whether the default start skips screening and always runs on all the data.
    pub default_on_full_data: bool,
}

impl<'a> Starts<'a> {
    /// A new fit: the default start (always on all the data) and `restarts` random ones.
    pub fn new(restarts: usize, seed: u64) -> Self {
        Self {
            warm: None,
            restarts,
            first: None,
            seed,
            ftol_floor: 0.0,
            default_on_full_data: true,
        }
    }

    /// From `warm` alone (a refinement of a previous optimum).
    pub fn warm(warm: Warm<'a>, seed: u64) -> Self {
        Self {
            warm: Some(warm),
            ..Self::new(0, seed)
        }
    }

    /// From `warm` when there is one, otherwise as [`Starts::new`].
    pub fn warm_or_new(warm: Option<Warm<'a>>, restarts: usize, seed: u64) -> Self {
        Self {
            warm,
            ..Self::new(restarts, seed)
        }
    }

    /// With `first` in place of the deterministic default start.
    pub fn first(self, first: &'a [f64]) -> Self {
        Self {
            first: Some(first),
            ..self
        }
    }

    /// With the relative function tolerance loosened to at least `ftol_floor`.
    pub fn ftol_floor(self, ftol_floor: f64) -> Self {
        Self { ftol_floor, ..self }
    }

    /// With the default start screened like the random ones (cheaper; the noise GP's).
    pub fn default_screened(self) -> Self {
        Self {
            default_on_full_data: false,
            ..self
        }
    }
}

/// Lower and upper log-bounds for `θ`.
pub(crate) fn log_bounds(d: usize, b: &Bounds, homoscedastic: bool) -> (Vec<f64>, Vec<f64>) {
    let mut lo = vec![b.length_scale.0.ln(); d];
    let mut hi = vec![b.length_scale.1.ln(); d];
    lo.push(b.signal_variance.0.ln());
    hi.push(b.signal_variance.1.ln());
    if homoscedastic {
        lo.push(b.noise_variance.0.ln());
        hi.push(b.noise_variance.1.ln());
    }
    (lo, hi)
}

/// Mean square of the centred targets (the scale of the signal), floored at `1e-12`.
pub(crate) fn target_scale(r: &[f64]) -> f64 {
    (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).max(1e-12)
}

/// The deterministic first start: every length scale 0.5 (a quarter to half of the unit box),
/// `s²` = mean square of the targets, `σ²` = a tenth of it; clipped into the bounds.
pub(crate) fn default_start(d: usize, r: &[f64], homoscedastic: bool) -> Vec<f64> {
    let v = target_scale(r);
    let mut t = vec![0.5f64.ln(); d];
    t.push(v.ln());
    if homoscedastic {
        t.push((0.1 * v).ln());
    }
    t
}

/// A random start: log-uniform length scales in `[0.05, 2]`, `s²` in `[0.1 v, 10 v]` and `σ²` in
/// `[10⁻³ v, v]` (`v` the targets' mean square). Narrower than the bounds on purpose: starts far
/// out in a flat region of the LML waste iterations. Clipped into the bounds by the optimiser.
fn random_start(rng: &mut ChaCha8Rng, d: usize, r: &[f64], homoscedastic: bool) -> Vec<f64> {
    let v = target_scale(r);
    let mut t: Vec<f64> = (0..d)
        .map(|_| rng.random_range(0.05f64.ln()..2.0f64.ln()))
        .collect();
    t.push(rng.random_range((0.1 * v).ln()..(10.0 * v).ln()));
    if homoscedastic {
        t.push(rng.random_range((1e-3 * v).ln()..v.ln()));
    }
    t
}

pub(crate) fn settings(p: &GpParams, ftol_floor: f64) -> Settings {
    Settings {
        max_iter: p.max_iterations,
        ftol: p.function_tolerance.max(ftol_floor),
        gtol: p.gradient_tolerance,
        memory: 10,
        max_step: 3.0,
    }
}

pub(crate) fn jitter(p: &GpParams) -> Jitter {
    Jitter {
        initial: p.jitter_initial,
        max: p.jitter_max,
    }
}

/// Runs one L-BFGS start on `(x, r)`; `None` if the start is infeasible.
#[allow(clippy::too_many_arguments)]
fn run(
    x: &Inputs,
    r: &[f64],
    noise: NoiseSpec<'_>,
    kernel: Kernel,
    p: &GpParams,
    settings: &Settings,
    (lo, hi): (&[f64], &[f64]),
    start: &[f64],
    warm: lbfgs::Memory,
    evals: &mut usize,
) -> Option<lbfgs::Outcome> {
    let mut obj = Objective::new(x, r, noise, kernel, jitter(p));
    let mut fg = |t: &[f64], g: &mut [f64]| obj.eval(t, g);
    let out = lbfgs::minimize(&mut fg, start, lo, hi, settings, warm);
    *evals += obj.evaluations;
    out
}

/// One optimiser run of some objective (the exact LML or the sparse bound) on data `(x, r)` with
/// noise `noise`: L-BFGS `settings`, log-bounds, start, warm correction pairs. Returns the
/// outcome (`None` if the start is infeasible) and the number of objective evaluations.
pub(crate) type Runner<'r> = dyn FnMut(
        &Inputs,
        &[f64],
        NoiseSpec<'_>,
        &Settings,
        (&[f64], &[f64]),
        &[f64],
        lbfgs::Memory,
    ) -> (Option<lbfgs::Outcome>, usize)
    + 'r;

/// Maximises the LML of a GP with inputs `x`, centred targets `r` and noise `noise`.
///
/// Starts ([`Starts`]): `warm` if given (then no random starts are added, and no screening),
/// otherwise the default start plus `restarts` seeded random ones. With `p.screen_subset > 0` and
/// `n > screen_subset` and at least one random start, the random starts are first optimised on a
/// seeded random subset (with the matching part of a fixed noise vector), and only the best is
/// refined on all the data — from a point near
/// the optimum, so the expensive full-data run needs few iterations; it also inherits the subset
/// run's L-BFGS correction pairs with `y` scaled by `n / subset` (the LML's curvature grows about
/// linearly with `n`), so it does not restart from steepest descent.
///
/// With `default_on_full_data` the deterministic default start skips screening and always runs on
/// all the data (robust: see the comment in the body); without it, it is screened like the others
/// (cheaper; used for the noise GP).
///
/// `ftol_floor` loosens the relative function tolerance (used for the noise GP, whose targets are
/// themselves very noisy estimates).
pub(crate) fn optimise(
    x: &Inputs,
    r: &[f64],
    noise: NoiseSpec<'_>,
    bounds: &Bounds,
    kernel: Kernel,
    p: &GpParams,
    starts: Starts<'_>,
) -> Result<Optimum, GpError> {
    let mut runner = |x: &Inputs,
                      r: &[f64],
                      noise: NoiseSpec<'_>,
                      settings: &Settings,
                      bounds: (&[f64], &[f64]),
                      start: &[f64],
                      memory: lbfgs::Memory| {
        let mut evals = 0;
        let out = run(
            x, r, noise, kernel, p, settings, bounds, start, memory, &mut evals,
        );
        (out, evals)
    };
    optimise_with(&mut runner, x, r, noise, bounds, p, p.screen_subset, starts)
}

/// The homoscedastic optimum of a new fit on `(x, r)` with `p`'s bounds, kernel, restarts and
/// seed, the default start always on all the data: the exact GP's first fit, and the sparse
/// GP's start from an exact fit on a subset.
pub(crate) fn optimise_homoscedastic(
    x: &Inputs,
    r: &[f64],
    p: &GpParams,
) -> Result<Optimum, GpError> {
    let warm = p
        .warm
        .as_ref()
        .and_then(|w| super::WarmStart::within(&w.main, x.d, &p.bounds));
    let starts = match &warm {
        Some(theta) => Starts::warm(
            Warm {
                theta,
                memory: Vec::new(),
            },
            p.seed,
        ),
        None => Starts::new(p.restarts, p.seed),
    };
    optimise(
        x,
        r,
        NoiseSpec::Homoscedastic,
        &p.bounds,
        p.kernel,
        p,
        starts,
    )
}

/// [`optimise`] for any objective: `runner` performs one optimiser run, `screen_subset` replaces
/// `p.screen_subset` (the sparse GP screens on larger subsets than the exact one), and
/// `starts.first`, when given, replaces the deterministic default start (the sparse GP starts
/// from an exact fit on a small subset).
#[allow(clippy::too_many_arguments)] // internal; each call site names its arguments
pub(crate) fn optimise_with(
    runner: &mut Runner<'_>,
    x: &Inputs,
    r: &[f64],
    noise: NoiseSpec<'_>,
    bounds: &Bounds,
    p: &GpParams,
    screen_subset: usize,
    starts: Starts<'_>,
) -> Result<Optimum, GpError> {
    let Starts {
        warm,
        restarts,
        first,
        seed,
        ftol_floor,
        default_on_full_data,
    } = starts;
    // The starts are drawn around the targets' mean square: one that overflows (labels near
    // ±1e154 from the prior mean) leaves no range to draw from.
    let scale = target_scale(r);
    if !(10.0 * scale).is_finite() {
        return Err(GpError::OptimisationFailed(format!(
            "the targets' mean square ({scale:e}) overflows: the labels lie too far from the \
             prior mean"
        )));
    }
    let settings = settings(p, ftol_floor);
    let homo = matches!(noise, NoiseSpec::Homoscedastic);
    let (lo, hi) = log_bounds(x.d, bounds, homo);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let screen = screen_subset > 0 && x.n > screen_subset && warm.is_none() && restarts > 0;
    let mut warm_memory = Vec::new();
    let starts: Vec<Vec<f64>> = match warm {
        Some(w) => {
            warm_memory = w.memory;
            vec![w.theta.to_vec()]
        }
        None => {
            let mut s = vec![first.map_or_else(|| default_start(x.d, r, homo), <[f64]>::to_vec)];
            for _ in 0..restarts {
                s.push(random_start(&mut rng, x.d, r, homo));
            }
            s
        }
    };
    let mut evaluations = 0;
    let bounds = (lo.as_slice(), hi.as_slice());
    // Full-data candidates: (start, warm correction pairs).
    let candidates: Vec<(Vec<f64>, lbfgs::Memory)> = if screen {
        let mut idx = sample(&mut rng, x.n, screen_subset).into_vec();
        idx.sort_unstable();
        let xs = x.subset(&idx);
        let rs: Vec<f64> = idx.iter().map(|&i| r[i]).collect();
        let fixed: Vec<f64>;
        let sub_noise = match noise {
            NoiseSpec::Homoscedastic => NoiseSpec::Homoscedastic,
            NoiseSpec::Fixed(v) => {
                fixed = idx.iter().map(|&i| v[i]).collect();
                NoiseSpec::Fixed(&fixed)
            }
        };
        let screened = if default_on_full_data {
            &starts[1..]
        } else {
            &starts[..]
        };
        let mut best: Option<lbfgs::Outcome> = None;
        for s in screened {
            let (out, evals) = runner(&xs, &rs, sub_noise, &settings, bounds, s, Vec::new());
            evaluations += evals;
            if let Some(o) = out
                && best.as_ref().is_none_or(|b| o.f < b.f)
            {
                best = Some(o);
            }
        }
        // The default start always runs on all the data: on a subset, weakly relevant inputs
        // look irrelevant, and a subset optimum with long length scales for them sits in a flat
        // region the full-data run cannot leave (measured: LML 239.4 vs 252.8 at n = 1000, d = 6).
        let mut c = if default_on_full_data {
            vec![(starts[0].clone(), Vec::new())]
        } else {
            Vec::new()
        };
        if let Some(b) = best {
            let scale = x.n as f64 / screen_subset as f64;
            let memory = b
                .memory
                .into_iter()
                .map(|(s, y)| (s, y.into_iter().map(|v| v * scale).collect()))
                .collect();
            c.push((b.x, memory));
        }
        if c.is_empty() {
            // Every screened start failed on the subset: try them all on the full data.
            c = starts.into_iter().map(|s| (s, Vec::new())).collect();
        }
        c
    } else {
        starts
            .into_iter()
            .map(|s| (s, std::mem::take(&mut warm_memory)))
            .collect()
    };
    let mut best: Option<lbfgs::Outcome> = None;
    for (s, memory) in candidates.iter().cloned() {
        let (out, evals) = runner(x, r, noise, &settings, bounds, &s, memory);
        evaluations += evals;
        if let Some(o) = out
            && best.as_ref().is_none_or(|b| o.f < b.f)
        {
            best = Some(o);
        }
    }
    let best = best.ok_or_else(|| {
        GpError::OptimisationFailed(format!(
            "none of {} start(s) gave a finite log marginal likelihood",
            candidates.len()
        ))
    })?;
    Ok(Optimum {
        theta: best.x,
        evaluations,
        converged: best.converged,
        memory: best.memory,
    })
}
