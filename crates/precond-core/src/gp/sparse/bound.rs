//! The collapsed bound `F` as an objective of the log-parameters, with its analytic gradient.
//!
//! Write `U = K_mm + εI = LLᵀ` (`ε ∝ s²`), `K = K_mn`, `P = K Λ⁻¹ Kᵀ`, `Σ = U + P`,
//! `b = K Λ⁻¹ r`. By Woodbury,
//!
//! `F = −n/2 log 2π − ½ log|Σ| + ½ log|U| − ½ Σ log λ_i − ½ rᵀΛ⁻¹r + ½ bᵀΣ⁻¹b − ½ Σ k_ii/λ_i + ½ tr(U⁻¹P)`.
//!
//! Differentiating (`β = Σ⁻¹b`):
//!
//! - `∂F/∂K = 2 C K Λ⁻¹ + β (Λ⁻¹ r)ᵀ` with `C = −½Σ⁻¹ − ½ββᵀ + ½U⁻¹ = L⁻ᵀ H L⁻¹`,
//!   `H = ½(I − B⁻¹ − γγᵀ)`, `γ = L_B⁻ᵀ c` (so `β = L⁻ᵀγ`);
//! - `∂F/∂U = C − ½ U⁻¹PU⁻¹ = L⁻ᵀ (H − ½ AAᵀ) L⁻¹`;
//! - `∂F/∂λ_i = (−k_iᵀ C k_i − (Kᵀβ)_i r_i + ½ r_i² + ½ k_ii) / λ_i² − ½ / λ_i`.
//!
//! Every kernel derivative is elementwise (`∂k/∂log ℓ_k = G Δ_k²`, `∂k/∂log s² = k`, and
//! `∂U/∂log s² = U` because the jitter is relative to `s²`), so the gradient is a contraction of
//! these adjoints with `G` and the squared scaled differences. For `K` it runs chunk by chunk in a
//! second pass over the data: `Σ_ij W_ij (z_ik − x_jk)² = Σ_i z_ik² Σ_j W_ij − 2 Σ_i z_ik (W X)_ik
//! + Σ_j x_jk² Σ_i W_ij` with `W = ∂F/∂K ∘ G`, one small GEMM per chunk.
//!
//! Cost per evaluation: about `2 n m²` multiply-adds (a triangular solve and a rank update in the
//! first pass, a GEMM in the second), O(m³) for the `m × m` algebra, O(n m d) for kernels.

use faer::Par;

use super::super::kernel::{Inputs, Kernel, cross_seq, length_scale_gradient};
use super::super::linalg;
use super::super::lml::NoiseSpec;
use super::core::{
    Ladder, Lambda, Stats, accumulate, bound_value, chunk_len, copy_points, factor_b, factor_kmm,
    over_groups, scaled, trace,
};

/// `−F` and its gradient as a function of `θ = [log ℓ_1 … log ℓ_d, log s², (log σ² if
/// homoscedastic)]`, for fixed inducing inputs.
pub(crate) struct Bound<'a> {
    x: &'a Inputs,
    z: &'a Inputs,
    r: &'a [f64],
    noise: NoiseSpec<'a>,
    kernel: Kernel,
    ladder: Ladder,
    /// Number of evaluations so far.
    pub evaluations: usize,
}

/// Fills the upper triangle of a column-major `m × m` matrix from its lower triangle.
fn symmetrise_from_lower(a: &mut [f64], m: usize) {
    for j in 0..m {
        for i in j + 1..m {
            a[i * m + j] = a[j * m + i];
        }
    }
}

/// `L⁻ᵀ H L⁻¹` for a symmetric `H` (full, column-major), returned symmetric.
fn congruence(l: &[f64], m: usize, h: &[f64]) -> Vec<f64> {
    let mut y = h.to_vec();
    linalg::solve_upper_transpose_in_place(l, m, &mut y, m, Par::Seq);
    // y = L⁻ᵀ H; (L⁻ᵀ H L⁻¹) = L⁻ᵀ yᵀ.
    let mut yt = vec![0.0; m * m];
    for j in 0..m {
        for i in 0..m {
            yt[i * m + j] = y[j * m + i];
        }
    }
    linalg::solve_upper_transpose_in_place(l, m, &mut yt, m, Par::Seq);
    for j in 0..m {
        for i in j + 1..m {
            let v = 0.5 * (yt[j * m + i] + yt[i * m + j]);
            yt[j * m + i] = v;
            yt[i * m + j] = v;
        }
    }
    yt
}

/// What the second pass returns per group: `∂F/∂log ℓ` (K part), `∂F/∂log s²` (K part),
/// `Σ_i ∂F/∂λ_i` (homoscedastic only).
struct Partial {
    ls: Vec<f64>,
    s2: f64,
    noise: f64,
}

impl<'a> Bound<'a> {
    /// A new objective for inputs `x`, centred targets `r`, inducing inputs `z`.
    pub fn new(
        x: &'a Inputs,
        z: &'a Inputs,
        r: &'a [f64],
        noise: NoiseSpec<'a>,
        kernel: Kernel,
        ladder: Ladder,
    ) -> Self {
        Bound {
            x,
            z,
            r,
            noise,
            kernel,
            ladder,
            evaluations: 0,
        }
    }

    /// Length of `θ`.
    #[cfg(test)]
    pub fn n_params(&self) -> usize {
        self.noise.n_params(self.x.d)
    }

    /// `−F(θ)`, writing `−∇F` into `grad`. `+∞` when `K_mm` cannot be factorised.
    pub fn eval(&mut self, theta: &[f64], grad: &mut [f64]) -> f64 {
        self.evaluations += 1;
        match self.eval_inner(theta, grad) {
            Some(f) if f.is_finite() && grad.iter().all(|g| g.is_finite()) => -f,
            _ => {
                grad.iter_mut().for_each(|v| *v = 0.0);
                f64::INFINITY
            }
        }
    }

    /// `F` and `∇F` (written negated into `grad`).
    fn eval_inner(&mut self, theta: &[f64], grad: &mut [f64]) -> Option<f64> {
        let (n, d, m) = (self.x.n, self.x.d, self.z.n);
        let ls: Vec<f64> = theta[..d].iter().map(|v| v.exp()).collect();
        let s2 = theta[d].exp();
        let lambda = match self.noise {
            NoiseSpec::Homoscedastic => Lambda::Homo(theta[d + 1].exp()),
            NoiseSpec::Fixed(v) => Lambda::Per(v),
        };
        let (kernel, r) = (self.kernel, self.r);
        let zs = scaled(self.z, &ls);
        let xs = scaled(self.x, &ls);
        let mut gmm = vec![0.0; m * m];
        let (l, _eps, u) =
            factor_kmm(kernel, &zs, m, d, s2, self.ladder, Some(&mut gmm), true).ok()?;
        // First pass: AAᵀ and A Λ^{-1/2} r.
        let acc = accumulate(kernel, &zs, m, &l, &xs, n, d, s2, r, lambda);
        let mut stats = Stats::of(r, lambda);
        stats.trace_aat = trace(&acc.aat, m);
        let mut aat = acc.aat.clone();
        symmetrise_from_lower(&mut aat, m);
        let lb = factor_b(acc.aat, m).ok()?;
        let mut c = acc.ar;
        linalg::solve_lower_in_place(&lb, m, &mut c, 1, Par::Seq);
        let f = bound_value(&lb, m, &c, s2, &stats);
        if !f.is_finite() {
            return None;
        }
        // The m × m adjoints.
        let mut gamma = c;
        linalg::solve_upper_transpose_in_place(&lb, m, &mut gamma, 1, Par::Seq);
        let mut lbinv = vec![0.0; m * m];
        linalg::invert_lower(&lb, m, &mut lbinv);
        let mut binv = vec![0.0; m * m];
        linalg::gemm(
            &mut binv,
            (&lbinv, m, m, true),
            (&lbinv, m, m, false),
            1.0,
            false,
            Par::Seq,
        );
        let mut h = vec![0.0; m * m];
        for j in 0..m {
            for i in 0..m {
                let id = if i == j { 1.0 } else { 0.0 };
                h[j * m + i] = 0.5 * (id - binv[j * m + i] - gamma[i] * gamma[j]);
            }
        }
        let cp = congruence(&l, m, &h);
        for (hv, av) in h.iter_mut().zip(&aat) {
            *hv -= 0.5 * av;
        }
        let cu = congruence(&l, m, &h);
        let mut beta = gamma;
        linalg::solve_upper_transpose_in_place(&l, m, &mut beta, 1, Par::Seq);
        // Second pass: contract ∂F/∂K_mn with the kernel derivatives, chunk by chunk.
        let homo = matches!(lambda, Lambda::Homo(_));
        let parts = over_groups(n, m, m * (m + 2 * d + 12), |p0, p1| {
            let chunk = chunk_len(m);
            let cap = chunk.min(p1 - p0);
            let mut out = Partial {
                ls: vec![0.0; d],
                s2: 0.0,
                noise: 0.0,
            };
            let mut xc = Vec::new();
            let mut kc = vec![0.0; m * cap];
            let mut gc = vec![0.0; m * cap];
            let mut v = vec![0.0; m * cap];
            let mut t = vec![0.0; m * d];
            let mut rowsum = vec![0.0; m];
            let mut colsum = vec![0.0; cap];
            let mut c0 = p0;
            while c0 < p1 {
                let c = chunk.min(p1 - c0);
                copy_points(&xs, n, d, c0, c0 + c, &mut xc);
                let (kc, gc, v) = (&mut kc[..m * c], &mut gc[..m * c], &mut v[..m * c]);
                cross_seq(kernel, &zs, m, &xc, c, c, d, s2, kc, Some(gc));
                linalg::gemm(
                    v,
                    (&cp, m, m, false),
                    (kc, m, c, false),
                    1.0,
                    false,
                    Par::Seq,
                );
                rowsum.iter_mut().for_each(|x| *x = 0.0);
                for j in 0..c {
                    let (rj, lj) = (r[c0 + j], lambda.at(c0 + j));
                    let kcol = &kc[j * m..(j + 1) * m];
                    let vcol = &mut v[j * m..(j + 1) * m];
                    if homo {
                        let q: f64 = linalg::dot(kcol, vcol);
                        let tb: f64 = linalg::dot(kcol, &beta);
                        out.noise +=
                            (-q - tb * rj + 0.5 * rj * rj + 0.5 * s2) / (lj * lj) - 0.5 / lj;
                    }
                    // Ā = (2/λ) V + β r/λ, then W = Ā ∘ G.
                    let (a2, ar) = (2.0 / lj, rj / lj);
                    let gcol = &mut gc[j * m..(j + 1) * m];
                    let mut s2acc = 0.0;
                    let mut cs = 0.0;
                    for i in 0..m {
                        let abar = a2 * vcol[i] + beta[i] * ar;
                        s2acc += abar * kcol[i];
                        let w = abar * gcol[i];
                        gcol[i] = w;
                        cs += w;
                        rowsum[i] += w;
                    }
                    out.s2 += s2acc;
                    colsum[j] = cs;
                }
                // Σ_ij W_ij (z_ik − x_jk)² = Σ_i z² rowsum − 2 Σ_i z (W X)_ik + Σ_j x² colsum.
                linalg::gemm(
                    &mut t,
                    (gc, m, c, false),
                    (&xc, c, d, false),
                    1.0,
                    false,
                    Par::Seq,
                );
                for k in 0..d {
                    let zk = &zs[k * m..(k + 1) * m];
                    let xk = &xc[k * c..(k + 1) * c];
                    let mut s = 0.0;
                    for i in 0..m {
                        s += zk[i] * (zk[i] * rowsum[i] - 2.0 * t[k * m + i]);
                    }
                    for j in 0..c {
                        s += xk[j] * xk[j] * colsum[j];
                    }
                    out.ls[k] += s;
                }
                c0 += c;
            }
            out
        });
        let mut g_ls = vec![0.0; d];
        let (mut g_s2, mut g_noise) = (0.0, 0.0);
        for p in parts {
            for (a, b) in g_ls.iter_mut().zip(&p.ls) {
                *a += b;
            }
            g_s2 += p.s2;
            g_noise += p.noise;
        }
        // K_mm's part: Σ_ij (∂F/∂U)_ij ∂U_ij/∂θ over both triangles.
        let minus_two_cu: Vec<f64> = cu.iter().map(|v| -2.0 * v).collect();
        let gl = length_scale_gradient(&zs, m, d, &vec![0.0; m], &minus_two_cu, &gmm);
        for (a, b) in g_ls.iter_mut().zip(&gl) {
            *a += b;
        }
        let mut cu_u = 0.0;
        for j in 0..m {
            cu_u += cu[j * m + j] * u[j * m + j];
            for i in j + 1..m {
                cu_u += 2.0 * cu[j * m + i] * u[j * m + i];
            }
        }
        g_s2 += cu_u - 0.5 * s2 * stats.sum_inv_lambda;
        for k in 0..d {
            grad[k] = -g_ls[k];
        }
        grad[d] = -g_s2;
        if let Lambda::Homo(sigma2) = lambda {
            grad[d + 1] = -sigma2 * g_noise;
        }
        Some(f)
    }
}
