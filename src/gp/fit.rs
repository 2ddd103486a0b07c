//! Hyperparameter optimisation: maximise the LML over the log-parameters with projected L-BFGS
//! from several seeded starts, optionally screening the starts on a data subset.

use rand::seq::index::sample;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::kernel::Inputs;
use super::lbfgs::{self, Settings};
use super::lml::{Jitter, NoiseSpec, Objective};
use super::{Bounds, GpError, GpParams};

/// The result of optimising one GP's hyperparameters.
#[derive(Clone, Debug)]
pub(crate) struct Optimum {
    /// Best log-parameters `[log ℓ.., log s², (log σ²)]`.
    pub theta: Vec<f64>,
    /// LML at `theta` on the full data.
    pub lml: f64,
    /// Total objective evaluations (all starts, screening included).
    pub evaluations: usize,
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

fn settings(p: &GpParams) -> Settings {
    Settings {
        max_iter: p.max_iterations,
        ftol: p.function_tolerance,
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
fn run(
    x: &Inputs,
    r: &[f64],
    noise: NoiseSpec<'_>,
    p: &GpParams,
    lo: &[f64],
    hi: &[f64],
    start: &[f64],
    evals: &mut usize,
) -> Option<lbfgs::Outcome> {
    let mut obj = Objective::new(x, r, noise, jitter(p));
    let mut fg = |t: &[f64], g: &mut [f64]| obj.eval(t, g);
    let out = lbfgs::minimize(&mut fg, start, lo, hi, &settings(p));
    *evals += obj.evaluations;
    out
}

/// Maximises the LML of a GP with inputs `x`, centred targets `r` and noise `noise`.
///
/// Starts: `warm` if given (then no random starts are added, and no screening), otherwise the
/// default start plus `restarts` seeded random ones. With `p.screen_subset > 0` and
/// `n > screen_subset`, each start is first optimised on a seeded random subset (with the matching
/// part of a fixed noise vector), and only the best is refined on all the data — from a point near
/// the optimum, so the expensive full-data run needs few iterations.
pub(crate) fn optimise(
    x: &Inputs,
    r: &[f64],
    noise: NoiseSpec<'_>,
    bounds: &Bounds,
    p: &GpParams,
    restarts: usize,
    warm: Option<&[f64]>,
    seed: u64,
) -> Result<Optimum, GpError> {
    let homo = matches!(noise, NoiseSpec::Homoscedastic);
    let (lo, hi) = log_bounds(x.d, bounds, homo);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let starts: Vec<Vec<f64>> = match warm {
        Some(w) => vec![w.to_vec()],
        None => {
            let mut s = vec![default_start(x.d, r, homo)];
            for _ in 0..restarts {
                s.push(random_start(&mut rng, x.d, r, homo));
            }
            s
        }
    };
    let mut evaluations = 0;
    let screen = p.screen_subset > 0 && x.n > p.screen_subset && warm.is_none();
    let candidates: Vec<Vec<f64>> = if screen {
        let mut idx = sample(&mut rng, x.n, p.screen_subset).into_vec();
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
        let mut best: Option<lbfgs::Outcome> = None;
        for s in &starts {
            if let Some(o) = run(&xs, &rs, sub_noise, p, &lo, &hi, s, &mut evaluations)
                && best.as_ref().is_none_or(|b| o.f < b.f)
            {
                best = Some(o);
            }
        }
        match best {
            Some(b) => vec![b.x],
            None => starts,
        }
    } else {
        starts
    };
    let mut best: Option<lbfgs::Outcome> = None;
    for s in &candidates {
        if let Some(o) = run(x, r, noise, p, &lo, &hi, s, &mut evaluations)
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
        lml: -best.f,
        evaluations,
    })
}
