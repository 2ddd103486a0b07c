//! A projected L-BFGS minimiser for box-constrained smooth problems.
//!
//! Hand-written because no maintained pure-Rust crate offers box-bounded L-BFGS (argmin's L-BFGS
//! is unconstrained; the L-BFGS-B crates wrap Fortran/C or are unmaintained ports), and the
//! problem here is small (d + 2 ≤ a few dozen log-parameters) with an expensive objective, so a
//! compact method is enough. Each iteration:
//!
//! 1. splits the variables into *active* (at a bound with the gradient pushing outwards; held
//!    fixed) and *free*;
//! 2. takes the L-BFGS direction on the free subspace (two-loop recursion with the stored
//!    `(s, y)` pairs restricted to the free variables, pairs with `sᵀy ≤ 0` skipped);
//! 3. backtracks along the *projected* path `P(x + t d)` until the Armijo condition
//!    `f(x_t) ≤ f(x) + 10⁻⁴ ∇f(x)ᵀ(x_t − x)` holds (quadratic interpolation, safeguarded);
//! 4. stops when the projected gradient's infinity norm is below `gtol`, the relative decrease is
//!    below `ftol` (SciPy's `factr` criterion), the line search fails (counted as converged when
//!    the predicted decrease `−∇fᵀd` is itself below `ftol · |f|`), or after `max_iter`.

use std::collections::VecDeque;

/// L-BFGS correction pairs `(s, y)` = (step, gradient change), oldest first.
pub(crate) type Memory = Vec<(Vec<f64>, Vec<f64>)>;

/// Stopping rules and memory of [`minimize`].
#[derive(Clone, Copy, Debug)]
pub(crate) struct Settings {
    /// Maximum iterations.
    pub max_iter: usize,
    /// Relative function decrease threshold.
    pub ftol: f64,
    /// Projected-gradient infinity-norm threshold.
    pub gtol: f64,
    /// Number of stored correction pairs.
    pub memory: usize,
    /// Largest change of any variable in one step (log units).
    pub max_step: f64,
}

/// What [`minimize`] found.
#[derive(Clone, Debug)]
pub(crate) struct Outcome {
    /// The best point (inside the box).
    pub x: Vec<f64>,
    /// Objective at `x`.
    pub f: f64,
    /// Whether a convergence test (rather than the iteration cap or a failed line search) stopped it.
    pub converged: bool,
    /// The correction pairs `(s, y)` held at the end, oldest first (to warm-start a related run).
    pub memory: Memory,
}

fn dot_masked(a: &[f64], b: &[f64], free: &[bool]) -> f64 {
    a.iter()
        .zip(b)
        .zip(free)
        .filter(|(_, f)| **f)
        .map(|((x, y), _)| x * y)
        .sum()
}

/// Minimises `fg` (which returns `f(x)` and writes `∇f(x)`; a non-finite value means "infeasible,
/// back off") over the box `[lo, hi]`, starting from `x0` (projected into the box). `None` when
/// `f(x0)` itself is not finite. `warm` pre-loads correction pairs (e.g. from a run on a data
/// subset, with `y` rescaled), so the first steps already use curvature information.
pub(crate) fn minimize(
    fg: &mut dyn FnMut(&[f64], &mut [f64]) -> f64,
    x0: &[f64],
    lo: &[f64],
    hi: &[f64],
    s: &Settings,
    warm: Memory,
) -> Option<Outcome> {
    let p = x0.len();
    let project = |v: &mut [f64]| {
        for i in 0..p {
            v[i] = v[i].clamp(lo[i], hi[i]);
        }
    };
    let mut x = x0.to_vec();
    project(&mut x);
    let mut g = vec![0.0; p];
    let mut f = fg(&x, &mut g);
    if !f.is_finite() {
        return None;
    }
    let mut mem: VecDeque<(Vec<f64>, Vec<f64>)> = VecDeque::with_capacity(s.memory);
    for pair in warm
        .into_iter()
        .filter(|(a, b)| a.len() == p && b.len() == p)
    {
        if mem.len() == s.memory {
            mem.pop_front();
        }
        mem.push_back(pair);
    }
    let mut xn = vec![0.0; p];
    let mut gn = vec![0.0; p];
    let mut converged = false;
    let mut iterations = 0;
    while iterations < s.max_iter {
        iterations += 1;
        let free: Vec<bool> = (0..p)
            .map(|i| !((x[i] <= lo[i] && g[i] > 0.0) || (x[i] >= hi[i] && g[i] < 0.0)))
            .collect();
        let pg = (0..p)
            .filter(|&i| free[i])
            .map(|i| g[i].abs())
            .fold(0.0, f64::max);
        if pg <= s.gtol {
            converged = true;
            break;
        }
        // Two-loop recursion on the free subspace.
        let mut q: Vec<f64> = (0..p).map(|i| if free[i] { g[i] } else { 0.0 }).collect();
        let mut coefs = Vec::with_capacity(mem.len());
        let mut gamma = None;
        for (sv, yv) in mem.iter().rev() {
            let sy = dot_masked(sv, yv, &free);
            if sy <= 1e-12 * dot_masked(yv, yv, &free).sqrt() * dot_masked(sv, sv, &free).sqrt()
                || sy <= 0.0
            {
                coefs.push(None);
                continue;
            }
            let rho = 1.0 / sy;
            if gamma.is_none() {
                gamma = Some(sy / dot_masked(yv, yv, &free));
            }
            let a = rho * dot_masked(sv, &q, &free);
            for i in 0..p {
                if free[i] {
                    q[i] -= a * yv[i];
                }
            }
            coefs.push(Some((rho, a)));
        }
        let gamma = gamma.unwrap_or(1.0);
        q.iter_mut().for_each(|v| *v *= gamma);
        for ((sv, yv), c) in mem.iter().zip(coefs.iter().rev()) {
            if let Some((rho, a)) = c {
                let b = rho * dot_masked(yv, &q, &free);
                for i in 0..p {
                    if free[i] {
                        q[i] += sv[i] * (a - b);
                    }
                }
            }
        }
        let mut dir: Vec<f64> = q.iter().map(|v| -v).collect();
        let mut dg: f64 = dir.iter().zip(&g).map(|(a, b)| a * b).sum();
        let mut first = mem.is_empty();
        if dg >= 0.0 || dg.is_nan() {
            mem.clear();
            first = true;
            dir = (0..p).map(|i| if free[i] { -g[i] } else { 0.0 }).collect();
            dg = dir.iter().zip(&g).map(|(a, b)| a * b).sum();
        }
        let dmax = dir.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        if dmax <= 0.0 || dmax.is_nan() {
            converged = true;
            break;
        }
        let mut t = if first { (1.0 / dmax).min(1.0) } else { 1.0 };
        if t * dmax > s.max_step {
            t = s.max_step / dmax;
        }
        let mut accepted = None;
        for _ in 0..40 {
            for i in 0..p {
                xn[i] = (x[i] + t * dir[i]).clamp(lo[i], hi[i]);
            }
            let fnew = fg(&xn, &mut gn);
            let decrease: f64 = g
                .iter()
                .zip(xn.iter().zip(&x))
                .map(|(gi, (a, b))| gi * (a - b))
                .sum();
            if fnew.is_finite() && fnew <= f + 1e-4 * decrease {
                accepted = Some(fnew);
                break;
            }
            t = if fnew.is_finite() {
                let denom = 2.0 * (fnew - f - dg * t);
                let tq = if denom > 0.0 {
                    -dg * t * t / denom
                } else {
                    0.5 * t
                };
                tq.clamp(0.1 * t, 0.5 * t)
            } else {
                0.1 * t
            };
            if t * dmax < 1e-14 {
                break;
            }
        }
        let Some(fnew) = accepted else {
            // No decrease found. If even the model's predicted decrease is below the function
            // tolerance, this is convergence at the limit of floating-point resolution.
            converged = -dg <= s.ftol * f.abs().max(1.0);
            break;
        };
        let sv: Vec<f64> = xn.iter().zip(&x).map(|(a, b)| a - b).collect();
        let yv: Vec<f64> = gn.iter().zip(&g).map(|(a, b)| a - b).collect();
        if sv.iter().zip(&yv).map(|(a, b)| a * b).sum::<f64>() > 0.0 {
            if mem.len() == s.memory {
                mem.pop_front();
            }
            mem.push_back((sv, yv));
        }
        let rel = (f - fnew) / f.abs().max(fnew.abs()).max(1.0);
        std::mem::swap(&mut x, &mut xn);
        std::mem::swap(&mut g, &mut gn);
        f = fnew;
        if rel <= s.ftol {
            converged = true;
            break;
        }
    }
    Some(Outcome {
        x,
        f,
        converged,
        memory: mem.into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings() -> Settings {
        Settings {
            max_iter: 500,
            ftol: 1e-15,
            gtol: 1e-9,
            memory: 10,
            max_step: 10.0,
        }
    }

    #[test]
    fn finds_rosenbrock_minimum() {
        let mut fg = |x: &[f64], g: &mut [f64]| {
            let (a, b) = (x[0], x[1]);
            g[0] = -2.0 * (1.0 - a) - 400.0 * a * (b - a * a);
            g[1] = 200.0 * (b - a * a);
            (1.0 - a).powi(2) + 100.0 * (b - a * a).powi(2)
        };
        let out = minimize(
            &mut fg,
            &[-1.2, 1.0],
            &[-5.0, -5.0],
            &[5.0, 5.0],
            &settings(),
            Vec::new(),
        )
        .unwrap();
        assert!(
            (out.x[0] - 1.0).abs() < 1e-5 && (out.x[1] - 1.0).abs() < 1e-5,
            "{out:?}"
        );
    }

    #[test]
    fn respects_active_bounds() {
        // Unconstrained minimum at (3, -2); box [0,1]×[-1,1] → (1, -1).
        let mut fg = |x: &[f64], g: &mut [f64]| {
            g[0] = 2.0 * (x[0] - 3.0) + 0.5 * x[1];
            g[1] = 2.0 * (x[1] + 2.0) + 0.5 * x[0];
            (x[0] - 3.0).powi(2) + (x[1] + 2.0).powi(2) + 0.5 * x[0] * x[1]
        };
        let out = minimize(
            &mut fg,
            &[0.5, 0.5],
            &[0.0, -1.0],
            &[1.0, 1.0],
            &settings(),
            Vec::new(),
        )
        .unwrap();
        assert!(
            (out.x[0] - 1.0).abs() < 1e-12 && (out.x[1] + 1.0).abs() < 1e-12,
            "{out:?}"
        );
        assert!(out.converged);
    }

    #[test]
    fn infeasible_start_is_none() {
        let mut fg = |_: &[f64], _: &mut [f64]| f64::NAN;
        assert!(minimize(&mut fg, &[0.0], &[-1.0], &[1.0], &settings(), Vec::new()).is_none());
    }
}
