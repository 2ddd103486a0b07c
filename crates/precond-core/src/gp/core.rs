//! [`Core`]: one conditioned GP (scaled inputs, `L⁻¹`, `α`), the building block of both the
//! main GP and the heteroscedastic noise GP.

use faer::Par;
use nalgebra::DMatrix;

use super::export::{self, GpPredictor};
use super::kernel::{self, Inputs, Kernel};
use super::linalg;
use super::lml::{self, Jitter};
use super::{GpError, Hyperparameters};

/// A GP prior: kernel, constant mean, ARD length scales and signal variance, what a conditioned
/// GP ([`Core`], the sparse core) is built from besides its data and noise.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Prior {
    pub kernel: Kernel,
    pub mean: f64,
    pub length_scales: Vec<f64>,
    pub s2: f64,
}

impl Prior {
    /// From the optimiser's log hyperparameters `[log ℓ_1, …, log ℓ_d, log s²]`.
    pub fn from_log(kernel: Kernel, mean: f64, log: &[f64]) -> Prior {
        let (log_s2, log_ls) = log.split_last().expect("a signal variance");
        Prior {
            kernel,
            mean,
            length_scales: log_ls.iter().map(|v| v.exp()).collect(),
            s2: log_s2.exp(),
        }
    }

    /// The hyperparameters of this prior with homoscedastic noise variance `noise_variance`.
    pub fn with_noise(self, noise_variance: f64) -> Hyperparameters {
        Hyperparameters {
            length_scales: self.length_scales,
            signal_variance: self.s2,
            noise_variance,
            prior_mean: self.mean,
            kernel: self.kernel,
        }
    }

    /// The prior of fitted hyperparameters.
    pub fn of(h: &Hyperparameters) -> Prior {
        Prior {
            kernel: h.kernel,
            mean: h.prior_mean,
            length_scales: h.length_scales.clone(),
            s2: h.signal_variance,
        }
    }
}

/// Query points prepared once by a conditioned core ([`Core::fantasy`], the sparse core's):
/// their latent variances after each of several alternative pending sets `(points, noise
/// variances)`.
pub(crate) trait PreparedQueries {
    fn variances_each(&self, sets: &[(&Inputs, &[f64])]) -> Vec<Vec<f64>>;
}

/// Query points prepared for fantasised variances ([`Core::fantasy`]): the latent variance at
/// them now, and `L⁻¹ k(X, q)`, which every pending set's answer reuses.
pub(crate) struct Fantasy<'a> {
    core: &'a Core,
    /// The query points, scaled by the length scales (column-major `m × d`).
    qs: Vec<f64>,
    /// `V_q = L⁻¹ k(X, q)` (`n × m`).
    vq: DMatrix<f64>,
    /// The latent posterior variance at the query points, before any pending point.
    var: Vec<f64>,
}

impl PreparedQueries for Fantasy<'_> {
    /// The latent variances at the query points as if the points `p` of a pending set `(p,
    /// noise_p)` had been observed as well, with noise variances `noise_p`, for each of
    /// several alternative sets: `v(q) − c_qᵀ S⁻¹ c_q` with `V = L⁻¹ k(X, ·)`,
    /// `c = k(P, q) − V_Pᵀ V_q` (the posterior covariance) and
    /// `S = k(P, P) + diag(noise_p) − V_Pᵀ V_P`; `O(n² k + n k m)` for `k` pending points. Every
    /// set's `V_P` comes from one product with `L⁻¹`, which reads the `n × n` triangle once
    /// for all of them rather than once per set. An empty set (or noise of the wrong
    /// length): the variances now.
    fn variances_each(&self, sets: &[(&Inputs, &[f64])]) -> Vec<Vec<f64>> {
        let core = self.core;
        let n = core.n;
        let valid = |p: &Inputs, noise_p: &[f64]| p.n > 0 && noise_p.len() == p.n;
        let scaled: Vec<Option<Vec<f64>>> = sets
            .iter()
            .map(|&(p, noise_p)| valid(p, noise_p).then(|| p.scaled(&core.length_scales)))
            .collect();
        let total: usize = sets
            .iter()
            .zip(&scaled)
            .filter(|(_, s)| s.is_some())
            .map(|((p, _), _)| p.n)
            .sum();
        let mut ks = vec![0.0; n * total];
        let mut at = 0;
        for (&(p, _), ps) in sets.iter().zip(&scaled) {
            if let Some(ps) = ps {
                let block = &mut ks[at * n..(at + p.n) * n];
                kernel::build_cross(core.kernel, &core.xs, n, ps, p.n, core.d, core.s2, block);
                at += p.n;
            }
        }
        let mut v = vec![0.0; n * total];
        linalg::lower_matmul(&core.linv, n, &ks, total, &mut v, linalg::par_for(n));
        let mut at = 0;
        sets.iter()
            .zip(&scaled)
            .map(|(&(p, noise_p), ps)| match ps {
                Some(ps) => {
                    let vp = DMatrix::from_column_slice(n, p.n, &v[at * n..(at + p.n) * n]);
                    at += p.n;
                    self.after(ps, &vp, noise_p)
                }
                None => self.var.clone(),
            })
            .collect()
    }
}

impl Fantasy<'_> {
    /// The variances after one pending set: its points scaled (`ps`, column-major), whitened
    /// (`vp = L⁻¹ k(X, P)`), and their noise.
    fn after(&self, ps: &[f64], vp: &DMatrix<f64>, noise_p: &[f64]) -> Vec<f64> {
        let core = self.core;
        let (d, k, m) = (core.d, noise_p.len(), self.var.len());
        let mut kpp = vec![0.0; k * k];
        kernel::build_cross(core.kernel, ps, k, ps, k, d, core.s2, &mut kpp);
        let mut kpq = vec![0.0; k * m];
        kernel::build_cross(core.kernel, ps, k, &self.qs, m, d, core.s2, &mut kpq);
        let n = core.n;
        let s = DMatrix::from_vec(k, k, kpp) - vp.tr_mul(vp);
        // c = k(P, q) − V_Pᵀ V_q, the one product here of the queries' size: a GEMM.
        linalg::gemm(
            &mut kpq,
            (vp.as_slice(), n, k, true),
            (self.vq.as_slice(), n, m, false),
            -1.0,
            true,
            Par::Seq,
        );
        let c = DMatrix::from_vec(k, m, kpq);
        // The pending points' noise keeps `S` positive definite; repeated pending points
        // without noise need the jitter ladder.
        let mut eps = core.jitter.max(1e-12 * core.s2);
        let chol = loop {
            let mut si = s.clone();
            for (i, nv) in noise_p.iter().enumerate() {
                si[(i, i)] += nv + eps;
            }
            if let Some(ch) = si.cholesky() {
                break Some(ch);
            }
            if eps > 1e-4 * core.s2 {
                break None;
            }
            eps *= 100.0;
        };
        let Some(w) = chol.and_then(|ch| ch.l().solve_lower_triangular(&c)) else {
            return self.var.clone();
        };
        self.var
            .iter()
            .zip(w.column_iter())
            .map(|(v, col)| (v - col.norm_squared()).max(0.0))
            .collect()
    }
}

/// One conditioned GP: scaled training inputs, `L⁻¹` and `α = K⁻¹(y − m)`.
#[derive(Clone, Debug)]
pub(crate) struct Core {
    pub kernel: Kernel,
    pub n: usize,
    pub d: usize,
    /// Training inputs divided by the length scales, column-major `n × d`.
    pub xs: Vec<f64>,
    pub length_scales: Vec<f64>,
    pub s2: f64,
    pub mean: f64,
    /// Per-point noise variances on the diagonal (without jitter).
    pub noise: Vec<f64>,
    /// Absolute jitter added to the diagonal.
    pub jitter: f64,
    /// `L⁻¹` stored row-major (`n × n`; row `i` is `linv[i*n ..= i*n + i]`), so a single point's
    /// `‖L⁻¹k‖²` is `n` contiguous dot products and batches use it as a transposed GEMM operand.
    pub linv: Vec<f64>,
    pub alpha: Vec<f64>,
    pub lml: f64,
}

impl Core {
    /// Conditions `prior` on `(x, y)` with per-point noise variances `noise`. `jitter` is the
    /// ladder; `first_eps` the first absolute jitter tried (0 for a new fit, the stored value
    /// for a rebuild).
    pub fn build(
        prior: &Prior,
        x: &Inputs,
        y: &[f64],
        noise: Vec<f64>,
        jitter: Jitter,
        first_eps: f64,
    ) -> Result<Core, GpError> {
        let (n, d, kernel, s2) = (x.n, x.d, prior.kernel, prior.s2);
        let r: Vec<f64> = y.iter().map(|v| v - prior.mean).collect();
        let xs = x.scaled(&prior.length_scales);
        let fac = lml::factorise(
            kernel,
            &xs,
            n,
            d,
            s2,
            &noise,
            &r,
            jitter,
            first_eps,
            vec![0.0; n * n],
            None,
        )
        .map_err(|(e, _)| e)?;
        let lml = fac.lml(&r);
        let mut linv = fac.l.clone();
        linalg::invert_lower_row_major(&fac.l, n, &mut linv);
        Ok(Core {
            kernel,
            n,
            d,
            xs,
            length_scales: prior.length_scales.clone(),
            s2,
            mean: prior.mean,
            noise,
            jitter: fac.jitter,
            linv,
            alpha: fac.alpha,
            lml,
        })
    }

    /// This GP as plain numbers, with `x` its training inputs (unscaled): `α` as the weights
    /// and, `with_variance`, `L⁻¹` as the factor.
    pub fn predictor(&self, x: &Inputs, with_variance: bool) -> GpPredictor {
        let n = self.n;
        GpPredictor {
            kernel: self.kernel,
            length_scales: self.length_scales.clone(),
            signal_variance: self.s2,
            prior_mean: self.mean,
            points: export::rows(x),
            weights: self.alpha.clone(),
            factor: (with_variance && self.linv.len() == n * n)
                .then(|| export::pack_lower_row_major(&self.linv, n)),
            correction: None,
        }
    }

    /// Frees `L⁻¹` (n² floats) when only means will be asked for (the noise GP); variances
    /// are then reported as NaN.
    pub fn drop_inverse_factor(&mut self) {
        self.linv = Vec::new();
    }

    /// `(K⁻¹)_ii = Σ_{k≥i} (L⁻¹)_ki²` (a sweep over the rows of `L⁻¹`).
    pub fn kinv_diag(&self) -> Vec<f64> {
        let n = self.n;
        let mut out = vec![0.0; n];
        for k in 0..n {
            for (o, v) in out.iter_mut().zip(&self.linv[k * n..k * n + k + 1]) {
                *o += v * v;
            }
        }
        out
    }

    /// Posterior mean of the latent function at the training inputs: `y_i − D'_i α_i`.
    pub fn train_mean(&self, y: &[f64]) -> Vec<f64> {
        y.iter()
            .zip(&self.noise)
            .zip(&self.alpha)
            .map(|((yi, di), ai)| yi - (di + self.jitter) * ai)
            .collect()
    }

    /// Mean and (optionally) latent variance at query points `q`.
    pub fn predict(&self, q: &Inputs, want_var: bool) -> (Vec<f64>, Vec<f64>) {
        let (n, m, d) = (self.n, q.n, self.d);
        let without_factor = want_var && self.linv.len() != n * n;
        let want_var = want_var && !without_factor;
        let qs = q.scaled(&self.length_scales);
        let mut mean = Vec::with_capacity(m);
        let mut var = Vec::with_capacity(if want_var { m } else { 0 });
        // Chunks of about 16 MB of cross covariances keep memory bounded and GEMMs efficient.
        let chunk = ((1usize << 21) / n.max(1)).clamp(16, 4096);
        let mut ks = Vec::new();
        let mut v = Vec::new();
        let mut j0 = 0;
        while j0 < m {
            let mc = chunk.min(m - j0);
            let mut qc = Vec::with_capacity(mc * d);
            for k in 0..d {
                qc.extend_from_slice(&qs[k * m + j0..k * m + j0 + mc]);
            }
            ks.resize(n * mc, 0.0);
            kernel::build_cross(self.kernel, &self.xs, n, &qc, mc, d, self.s2, &mut ks);
            for col in ks.chunks_exact(n) {
                mean.push(self.mean + col.iter().zip(&self.alpha).map(|(a, b)| a * b).sum::<f64>());
            }
            if want_var {
                if mc == 1 {
                    var.push((self.s2 - self.quad_single(&ks)).max(0.0));
                } else if mc <= SMALL_BATCH {
                    for q in self.quad_few(&ks, mc) {
                        var.push((self.s2 - q).max(0.0));
                    }
                } else {
                    v.resize(n * mc, 0.0);
                    let par = if n * n * mc >= 50_000_000 {
                        Par::rayon(0)
                    } else {
                        Par::Seq
                    };
                    linalg::lower_matmul(&self.linv, n, &ks, mc, &mut v, par);
                    for col in v.chunks_exact(n) {
                        var.push((self.s2 - col.iter().map(|t| t * t).sum::<f64>()).max(0.0));
                    }
                }
            }
            j0 += mc;
        }
        if without_factor {
            var = vec![f64::NAN; m];
        }
        (mean, var)
    }

    /// The query points `q` prepared for their latent variances as if the points of any
    /// number of alternative pending sets had been observed as well ([`Fantasy::variances_each`]):
    /// `k(X, q)` and `V_q = L⁻¹ k(X, q)`, the `O(n² m)` part of each answer, computed once. A
    /// GP's variance does not depend on the labels, so the answers are exact for any labels
    /// (and the mean is unchanged for labels equal to it — a "fantasised" observation). `None`
    /// without `L⁻¹` (a noise GP) or without query points; with it, the posterior mean at
    /// `q` beside the preparation.
    pub fn fantasy(&self, q: &Inputs) -> Option<(Vec<f64>, Fantasy<'_>)> {
        let (n, m) = (self.n, q.n);
        if m == 0 || self.linv.len() != n * n {
            return None;
        }
        let qs = q.scaled(&self.length_scales);
        let (kq, vq) = self.cross_and_whitened(&qs, m);
        let mean: Vec<f64> = kq
            .chunks_exact(n)
            .map(|col| self.mean + col.iter().zip(&self.alpha).map(|(a, b)| a * b).sum::<f64>())
            .collect();
        let var = vq
            .column_iter()
            .map(|col| (self.s2 - col.norm_squared()).max(0.0))
            .collect();
        Some((
            mean,
            Fantasy {
                core: self,
                qs,
                vq,
                var,
            },
        ))
    }

    /// `k(X, ·)` and `L⁻¹ k(X, ·)` of the scaled points `pts` (`cnt` of them, column-major).
    fn cross_and_whitened(&self, pts: &[f64], cnt: usize) -> (Vec<f64>, DMatrix<f64>) {
        let (n, d) = (self.n, self.d);
        let mut ks = vec![0.0; n * cnt];
        kernel::build_cross(self.kernel, &self.xs, n, pts, cnt, d, self.s2, &mut ks);
        let mut v = vec![0.0; n * cnt];
        linalg::lower_matmul(&self.linv, n, &ks, cnt, &mut v, linalg::par_for(n));
        (ks, DMatrix::from_vec(n, cnt, v))
    }

    /// `‖L⁻¹ k_j‖²` for a few points `ks` (`mc` columns of `n`): the planner's rounds ask about
    /// a handful of state-actions at a time, where packing `L⁻¹` for a GEMM costs more than the
    /// products. Reads each row of the triangle once and takes its dot product with every
    /// column, in the same order as [`quad_single`](Self::quad_single) per column.
    fn quad_few(&self, ks: &[f64], mc: usize) -> Vec<f64> {
        let n = self.n;
        let mut out = vec![0.0; mc];
        for i in 0..n {
            let row = &self.linv[i * n..i * n + i + 1];
            for (j, o) in out.iter_mut().enumerate() {
                let t = linalg::dot(row, &ks[j * n..j * n + i + 1]);
                *o += t * t;
            }
        }
        out
    }

    /// `‖L⁻¹ k‖²` for one point: one dot product per row of `L⁻¹` (memory-bound: reads the
    /// triangle once, contiguously). Large models split the rows between two threads.
    fn quad_single(&self, k: &[f64]) -> f64 {
        let n = self.n;
        let rows = |r0: usize, r1: usize| -> f64 {
            (r0..r1)
                .map(|i| {
                    let t = linalg::dot(&self.linv[i * n..i * n + i + 1], &k[..i + 1]);
                    t * t
                })
                .sum()
        };
        if n < 1500 || kernel::threads_for(usize::MAX) < 2 {
            return rows(0, n);
        }
        // Rows [split, n) hold as many entries as rows [0, split). A scoped thread (≈30 µs to
        // spawn) measured faster here than faer's pool (`join_raw`) for this memory-bound sweep.
        let split = ((n as f64) * std::f64::consts::FRAC_1_SQRT_2) as usize;
        std::thread::scope(|s| {
            let h = s.spawn(|| rows(split, n));
            let a = rows(0, split);
            // The closure cannot panic; fall back to computing the half here if it somehow did.
            a + h.join().unwrap_or_else(|_| rows(split, n))
        })
    }
}

/// Batches of at most this many query points get their variances from [`Core::quad_few`]
/// rather than a GEMM.
const SMALL_BATCH: usize = 16;

/// The arithmetic mean (0 for an empty slice).
pub(crate) fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}
