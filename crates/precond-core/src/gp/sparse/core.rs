//! [`SparseCore`]: one conditioned sparse GP (inducing points, `L = chol(K_mm)`, `L_B`,
//! `A Λ^{-1/2} r` and the scalar statistics), and the chunked passes over the data shared with
//! the bound's objective.

use std::sync::OnceLock;

use faer::Par;
use nalgebra::DMatrix;

use super::super::core::{PreparedQueries, Prior};
use super::super::export::{self, GpPredictor};
use super::super::kernel::{self, Inputs, Kernel, build_train, cross_seq};
use super::super::linalg;
use super::super::{GpError, Hyperparameters};
use super::SparseCoreState;

/// `½ log 2π`.
const HALF_LN_2PI: f64 = 0.918_938_533_204_672_8;

/// Smallest accepted squared pivot of `chol(K_mm)` relative to `s²` (as in the exact GP).
const MIN_PIVOT: f64 = 1e-13;

/// Per-point noise variances: one for all points, or one each.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Lambda<'a> {
    /// Homoscedastic `σ²`.
    Homo(f64),
    /// `λ_i` per point.
    Per(&'a [f64]),
}

impl Lambda<'_> {
    #[inline]
    pub fn at(&self, i: usize) -> f64 {
        match self {
            Lambda::Homo(v) => *v,
            Lambda::Per(v) => v[i],
        }
    }
}

/// The jitter ladder for `K_mm`: `initial · s²`, ×10 per failure up to `max · s²`; or exactly a
/// stored absolute value (rebuilds).
#[derive(Clone, Copy, Debug)]
pub(crate) enum Ladder {
    /// Relative rungs.
    Relative {
        /// First relative jitter.
        initial: f64,
        /// Largest relative jitter.
        max: f64,
    },
    /// Exactly this absolute jitter, no ladder.
    Exact(f64),
}

/// Input coordinates centred on the unit box and divided by the length scales, column-major.
/// The kernel depends only on differences; centring keeps the gradient's `z² − 2zx + x²`
/// contraction free of cancellation.
pub(crate) fn scaled(x: &Inputs, length_scales: &[f64]) -> Vec<f64> {
    let mut out = x.cols.clone();
    for (k, &l) in length_scales.iter().enumerate() {
        let inv = 1.0 / l;
        out[k * x.n..(k + 1) * x.n]
            .iter_mut()
            .for_each(|v| *v = (*v - 0.5) * inv);
    }
    out
}

/// `chol(K_mm + εI)` by the jitter ladder. Returns `(L, ε, U)` with `U` the factorised matrix's
/// lower triangle (kept for the gradient) when `keep_u`, and fills `g` (strict lower triangle of
/// the kernel's `G`, see `kernel`) when given.
#[allow(clippy::too_many_arguments)]
pub(crate) fn factor_kmm(
    kernel: Kernel,
    zs: &[f64],
    m: usize,
    d: usize,
    s2: f64,
    ladder: Ladder,
    mut g: Option<&mut [f64]>,
    keep_u: bool,
) -> Result<(Vec<f64>, f64, Vec<f64>), GpError> {
    let (mut eps, max) = match ladder {
        Ladder::Relative { initial, max } => (initial * s2, max.max(initial) * s2),
        Ladder::Exact(e) => (e, e),
    };
    let mut l = vec![0.0; m * m];
    loop {
        build_train(
            kernel,
            zs,
            m,
            d,
            s2,
            &vec![eps; m],
            &mut l,
            g.as_deref_mut(),
        );
        let u = if keep_u { l.clone() } else { Vec::new() };
        if linalg::cholesky_in_place(&mut l, m)
            && (0..m).all(|i| l[i * m + i] * l[i * m + i] >= MIN_PIVOT * s2)
        {
            // The strict upper triangle is garbage from the factorisation: zero it, so `l`
            // can be used as a dense triangular matrix.
            for j in 1..m {
                l[j * m..j * m + j].iter_mut().for_each(|v| *v = 0.0);
            }
            return Ok((l, eps, u));
        }
        let next = eps * 10.0;
        if !(next.is_finite() && next <= max * (1.0 + 1e-9)) || matches!(ladder, Ladder::Exact(_)) {
            return Err(GpError::NotPositiveDefinite { jitter: eps });
        }
        eps = next;
    }
}

/// Points per chunk of a pass over the data: `m × chunk` blocks of about 1 MB.
pub(crate) fn chunk_len(m: usize) -> usize {
    ((1usize << 17) / m.max(1)).clamp(64, 4096)
}

/// Splits `n` points into at most 8 contiguous groups of whole chunks (fixed by `n` and `m`
/// alone), runs `f(p0, p1)` for each group on up to `threads` threads, and returns the results
/// in group order — so reductions over them do not depend on the number of threads.
pub(crate) fn over_groups<T: Send>(
    n: usize,
    m: usize,
    work_per_point: usize,
    f: impl Fn(usize, usize) -> T + Sync,
) -> Vec<T> {
    let chunk = chunk_len(m);
    let nchunks = n.div_ceil(chunk).max(1);
    let groups = nchunks.min(8);
    let bounds: Vec<usize> = (0..=groups)
        .map(|g| (g * nchunks / groups * chunk).min(n))
        .collect();
    let threads = kernel::threads_for(n.saturating_mul(work_per_point)).min(groups);
    if threads <= 1 {
        return bounds.windows(2).map(|w| f(w[0], w[1])).collect();
    }
    let mut slots: Vec<Option<T>> = (0..groups).map(|_| None).collect();
    std::thread::scope(|scope| {
        let handles: Vec<_> = (0..threads)
            .map(|t| {
                let (f, bounds) = (&f, &bounds);
                scope.spawn(move || {
                    (t..groups)
                        .step_by(threads)
                        .map(|g| (g, f(bounds[g], bounds[g + 1])))
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        for h in handles {
            // The workers run numeric loops that cannot panic; a missing slot is recomputed below.
            if let Ok(res) = h.join() {
                for (g, v) in res {
                    slots[g] = Some(v);
                }
            }
        }
    });
    slots
        .into_iter()
        .enumerate()
        .map(|(g, v)| v.unwrap_or_else(|| f(bounds[g], bounds[g + 1])))
        .collect()
}

/// Copies points `p0..p1` of column-major `xs` (`n × d`) into a contiguous `c × d` block.
pub(crate) fn copy_points(
    xs: &[f64],
    n: usize,
    d: usize,
    p0: usize,
    p1: usize,
    out: &mut Vec<f64>,
) {
    out.clear();
    for k in 0..d {
        out.extend_from_slice(&xs[k * n + p0..k * n + p1]);
    }
}

/// What a pass over the data accumulates.
#[derive(Clone, Debug, Default)]
pub(crate) struct Accumulated {
    /// Lower triangle of `A Aᵀ` (`m × m`, column-major).
    pub aat: Vec<f64>,
    /// `A Λ^{-1/2} r`.
    pub ar: Vec<f64>,
}

/// Accumulates `A Aᵀ` and `A Λ^{-1/2} r` with `A = L⁻¹ K(Z, X) Λ^{-1/2}` over the points of
/// `xs` (scaled, column-major `n × d`), in chunks, on several threads for large problems.
#[allow(clippy::too_many_arguments)]
pub(crate) fn accumulate(
    kernel: Kernel,
    zs: &[f64],
    m: usize,
    l: &[f64],
    xs: &[f64],
    n: usize,
    d: usize,
    s2: f64,
    r: &[f64],
    lambda: Lambda<'_>,
) -> Accumulated {
    let parts = over_groups(n, m, m * (m + d + 8), |p0, p1| {
        let chunk = chunk_len(m);
        let mut aat = vec![0.0; m * m];
        let mut ar = vec![0.0; m];
        let mut xc = Vec::new();
        let mut a = vec![0.0; m * chunk];
        let mut rc = vec![0.0; chunk];
        let mut c0 = p0;
        while c0 < p1 {
            let c = chunk.min(p1 - c0);
            copy_points(xs, n, d, c0, c0 + c, &mut xc);
            let a = &mut a[..m * c];
            cross_seq(kernel, zs, m, &xc, c, c, d, s2, a, None);
            linalg::solve_lower_in_place(l, m, a, c, Par::Seq);
            for j in 0..c {
                let inv = 1.0 / lambda.at(c0 + j).sqrt();
                a[j * m..(j + 1) * m].iter_mut().for_each(|v| *v *= inv);
                rc[j] = r[c0 + j] * inv;
            }
            linalg::syrk_lower_add(&mut aat, m, a, c, Par::Seq);
            linalg::gemm(
                &mut ar,
                (a, m, c, false),
                (&rc[..c], c, 1, false),
                1.0,
                true,
                Par::Seq,
            );
            c0 += c;
        }
        Accumulated { aat, ar }
    });
    let mut total = Accumulated {
        aat: vec![0.0; m * m],
        ar: vec![0.0; m],
    };
    for p in parts {
        for (t, v) in total.aat.iter_mut().zip(&p.aat) {
            *t += v;
        }
        for (t, v) in total.ar.iter_mut().zip(&p.ar) {
            *t += v;
        }
    }
    total
}

/// The scalar statistics of the bound.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Stats {
    pub n: usize,
    pub sum_log_lambda: f64,
    pub sum_r2_over_lambda: f64,
    pub sum_inv_lambda: f64,
    pub trace_aat: f64,
}

impl Stats {
    /// The statistics of points `r`, `lambda` (without `trace_aat`).
    pub fn of(r: &[f64], lambda: Lambda<'_>) -> Stats {
        let mut s = Stats {
            n: r.len(),
            ..Stats::default()
        };
        for (i, ri) in r.iter().enumerate() {
            let l = lambda.at(i);
            s.sum_log_lambda += l.ln();
            s.sum_r2_over_lambda += ri * ri / l;
            s.sum_inv_lambda += 1.0 / l;
        }
        s
    }

    fn add(&mut self, o: &Stats) {
        self.n += o.n;
        self.sum_log_lambda += o.sum_log_lambda;
        self.sum_r2_over_lambda += o.sum_r2_over_lambda;
        self.sum_inv_lambda += o.sum_inv_lambda;
        self.trace_aat += o.trace_aat;
    }
}

/// Trace of a column-major `m × m` matrix.
pub(crate) fn trace(a: &[f64], m: usize) -> f64 {
    (0..m).map(|i| a[i * m + i]).sum()
}

/// The bound from `L_B`, `c = L_B⁻¹ A Λ^{-1/2} r` and the statistics.
pub(crate) fn bound_value(lb: &[f64], m: usize, c: &[f64], s2: f64, st: &Stats) -> f64 {
    let log_det_b: f64 = (0..m).map(|i| lb[i * m + i].ln()).sum();
    let cc: f64 = c.iter().map(|v| v * v).sum();
    -(st.n as f64) * HALF_LN_2PI - log_det_b - 0.5 * st.sum_log_lambda - 0.5 * st.sum_r2_over_lambda
        + 0.5 * cc
        - 0.5 * s2 * st.sum_inv_lambda
        + 0.5 * st.trace_aat
}

/// `B = I + AAᵀ` factorised in place (lower triangle of `aat` in, `L_B` out, upper zeroed).
pub(crate) fn factor_b(mut b: Vec<f64>, m: usize) -> Result<Vec<f64>, GpError> {
    for i in 0..m {
        b[i * m + i] += 1.0;
    }
    if !linalg::cholesky_in_place(&mut b, m) {
        return Err(GpError::NotPositiveDefinite { jitter: 0.0 });
    }
    for j in 1..m {
        b[j * m..j * m + j].iter_mut().for_each(|v| *v = 0.0);
    }
    Ok(b)
}

/// One conditioned sparse GP.
#[derive(Clone, Debug)]
pub(crate) struct SparseCore {
    pub kernel: Kernel,
    pub d: usize,
    pub m: usize,
    /// Inducing inputs (unit box), column-major `m × d`.
    pub z: Inputs,
    /// Inducing inputs centred and scaled ([`scaled`]).
    zs: Vec<f64>,
    pub length_scales: Vec<f64>,
    pub s2: f64,
    pub mean: f64,
    /// Absolute jitter on `K_mm`'s diagonal.
    pub jitter: f64,
    /// `chol(K_mm + εI)`, column-major, upper triangle zero.
    l: Vec<f64>,
    /// `chol(I + AAᵀ)`, column-major, upper triangle zero.
    lb: Vec<f64>,
    /// `A Λ^{-1/2} r`.
    ar: Vec<f64>,
    pub stats: Stats,
    /// `L⁻ᵀ L_B⁻ᵀ c`: the predictive mean is `mean + k*ᵀ w`.
    w: Vec<f64>,
    /// The collapsed bound.
    pub bound: f64,
    /// [`variance_factor`], computed by the first prediction after a (re)conditioning; `None`
    /// inside when it could not be formed (predictions then take the two solves).
    var_factor: OnceLock<Option<Vec<f64>>>,
}

/// `H`, lower triangular (`m × m`, column-major), with `HᵀH = L⁻ᵀ (I − B⁻¹) L⁻¹`, so that the
/// latent variance `s² − ‖L⁻¹k*‖² + ‖L_B⁻¹L⁻¹k*‖²` is `s² − ‖H k*‖²`: one triangular product
/// per batch of query points instead of two triangular solves, half the multiply-adds and none
/// of a solve's row-by-row dependencies (at m = 256 on the reference machine, 1.3 against 3.1 ms
/// per 512 points). `O(m³)` once per conditioning, `m²` numbers.
///
/// `I − B⁻¹` has its eigenvalues `λ/(1 + λ)` in `[0, 1)` (`λ` those of `AAᵀ`), so it is
/// factorised well: as `UᵀU` with `U` lower triangular, by a Cholesky factorisation of the
/// matrix with its rows and columns reversed (`J E J = R Rᵀ` gives `U = J Rᵀ J`), and then
/// `H = U L⁻¹`. A jitter of up to 1e-10 on `E`'s diagonal (a variance change of at most
/// 1e-10 · s²) covers directions no data reach. `None` when even that fails or the factor is not
/// finite. Peak memory three `m × m` buffers (at the cap of 4096 inducing points 400 MB, below
/// the fit's own peak of about 38 of them).
fn variance_factor(l: &[f64], lb: &[f64], m: usize) -> Option<Vec<f64>> {
    let mut lbinv = vec![0.0; m * m];
    linalg::invert_lower(lb, m, &mut lbinv);
    let mut binv = vec![0.0; m * m];
    linalg::inverse_from_inverse_factor(&lbinv, m, &mut binv);
    drop(lbinv);
    let mut e = vec![0.0; m * m];
    for jitter in [0.0, 1e-14, 1e-12, 1e-10] {
        // `e`'s lower triangle: `(J E J)[i, j] = E[m−1−i, m−1−j] = E[m−1−j, m−1−i]`, with
        // `E = I − B⁻¹` read from `B⁻¹`'s lower triangle.
        for j in 0..m {
            for i in j..m {
                let v = -binv[(m - 1 - i) * m + (m - 1 - j)];
                e[j * m + i] = if i == j { 1.0 + v + jitter } else { v };
            }
        }
        if !linalg::cholesky_in_place(&mut e, m) {
            continue;
        }
        // `U[i, j] = R[m−1−j, m−1−i]`, lower triangular, in `B⁻¹`'s buffer (no longer
        // needed): at most three `m × m` buffers at a time.
        let mut u = binv;
        for j in 0..m {
            u[j * m..j * m + j].iter_mut().for_each(|v| *v = 0.0);
            for i in j..m {
                u[j * m + i] = e[(m - 1 - i) * m + (m - 1 - j)];
            }
        }
        let mut linv = vec![0.0; m * m];
        linalg::invert_lower(l, m, &mut linv);
        for j in 1..m {
            linv[j * m..j * m + j].iter_mut().for_each(|v| *v = 0.0);
        }
        linalg::lower_times_lower(&u, &linv, m, &mut e);
        return e.iter().all(|v| v.is_finite()).then_some(e);
    }
    None
}

/// Query points prepared by [`SparseCore::fantasy`].
pub(crate) struct SparseFantasy<'a> {
    core: &'a SparseCore,
    /// `g = L_B⁻¹ L⁻¹ k(Z, q)`, column-major `m × |q|`.
    g: Vec<f64>,
    /// `‖L⁻¹ k(Z, q)‖²` per point.
    v1: Vec<f64>,
    /// `‖g‖²` per point.
    v2: Vec<f64>,
}

impl PreparedQueries for SparseFantasy<'_> {
    /// The latent variances after each pending set `(p, λ_p)`: observing `p` turns `B` into
    /// `B + A_P A_Pᵀ` with `A_P = L⁻¹ k(Z, P) Λ_P^{-1/2}`, so by Woodbury the last norm of the
    /// variance loses `‖L_C⁻¹ Hᵀ g‖²` with `H = L_B⁻¹ A_P` and `L_C = chol(I + HᵀH)` (`k × k`
    /// for `k` pending points): `O(m² k + m k |q|)` a set, no copy of the model. An empty set
    /// (or noise of the wrong length): the variances now.
    fn variances_each(&self, sets: &[(&Inputs, &[f64])]) -> Vec<Vec<f64>> {
        let core = self.core;
        let (m, r) = (core.m, self.v1.len());
        let now = |lost: &dyn Fn(usize) -> f64| -> Vec<f64> {
            (0..r)
                .map(|i| (core.s2 - self.v1[i] + self.v2[i] - lost(i)).clamp(0.0, core.s2))
                .collect()
        };
        sets.iter()
            .map(|&(p, noise_p)| {
                let k = p.n;
                if k == 0 || noise_p.len() != k {
                    return now(&|_| 0.0);
                }
                // H = L_B⁻¹ A_P, A_P = L⁻¹ k(Z, P) Λ_P^{-1/2}.
                let mut h = core.projected(p);
                for (col, lambda) in h.chunks_exact_mut(m).zip(noise_p) {
                    let inv = 1.0 / lambda.sqrt();
                    col.iter_mut().for_each(|v| *v *= inv);
                }
                linalg::solve_lower_in_place(&core.lb, m, &mut h, k, Par::Seq);
                let hm = DMatrix::from_column_slice(m, k, &h);
                let mut c = hm.tr_mul(&hm);
                for i in 0..k {
                    c[(i, i)] += 1.0;
                }
                let mut hg = vec![0.0; k * r];
                linalg::gemm(
                    &mut hg,
                    (&h, m, k, true),
                    (&self.g, m, r, false),
                    1.0,
                    false,
                    Par::Seq,
                );
                let hg = DMatrix::from_vec(k, r, hg);
                match c
                    .cholesky()
                    .and_then(|ch| ch.l().solve_lower_triangular(&hg))
                {
                    Some(t) => now(&|i| t.column(i).norm_squared()),
                    None => now(&|_| 0.0),
                }
            })
            .collect()
    }
}

impl SparseCore {
    /// Conditions `prior` with inducing inputs `z` on `(x, y)` with noise `lambda`.
    pub fn build(
        prior: &Prior,
        x: &Inputs,
        y: &[f64],
        z: &Inputs,
        lambda: Lambda<'_>,
        ladder: Ladder,
    ) -> Result<SparseCore, GpError> {
        let (m, d, kernel, s2) = (z.n, z.d, prior.kernel, prior.s2);
        let zs = scaled(z, &prior.length_scales);
        let (l, jitter, _) = factor_kmm(kernel, &zs, m, d, s2, ladder, None, false)?;
        let r: Vec<f64> = y.iter().map(|v| v - prior.mean).collect();
        let xs = scaled(x, &prior.length_scales);
        let acc = accumulate(kernel, &zs, m, &l, &xs, x.n, d, s2, &r, lambda);
        let mut stats = Stats::of(&r, lambda);
        stats.trace_aat = trace(&acc.aat, m);
        let lb = factor_b(acc.aat, m)?;
        let mut core = SparseCore {
            kernel,
            d,
            m,
            z: z.clone(),
            zs,
            length_scales: prior.length_scales.clone(),
            s2,
            mean: prior.mean,
            jitter,
            l,
            lb,
            ar: acc.ar,
            stats,
            w: Vec::new(),
            bound: 0.0,
            var_factor: OnceLock::new(),
        };
        core.finish()?;
        Ok(core)
    }

    /// Recomputes `w` and the bound from `L_B`, `A Λ^{-1/2} r` and the statistics.
    fn finish(&mut self) -> Result<(), GpError> {
        let m = self.m;
        let mut c = self.ar.clone();
        linalg::solve_lower_in_place(&self.lb, m, &mut c, 1, Par::Seq);
        self.bound = bound_value(&self.lb, m, &c, self.s2, &self.stats);
        let mut w = c;
        linalg::solve_upper_transpose_in_place(&self.lb, m, &mut w, 1, Par::Seq);
        linalg::solve_upper_transpose_in_place(&self.l, m, &mut w, 1, Par::Seq);
        if !(self.bound.is_finite() && w.iter().all(|v| v.is_finite())) {
            return Err(GpError::InvalidState(
                "the sparse GP's statistics are not finite".into(),
            ));
        }
        self.w = w;
        self.var_factor = OnceLock::new();
        Ok(())
    }

    /// Absorbs new points at fixed hyperparameters and inducing points: a rank-`k` update of
    /// `L_B` and sums for the rest. O(k m²).
    pub fn update(&mut self, x: &Inputs, y: &[f64], lambda: Lambda<'_>) -> Result<(), GpError> {
        let (m, k) = (self.m, x.n);
        if k == 0 {
            return Ok(());
        }
        let r: Vec<f64> = y.iter().map(|v| v - self.mean).collect();
        let mut a = self.projected(x);
        let mut rs = vec![0.0; k];
        let mut st = Stats::of(&r, lambda);
        for j in 0..k {
            let inv = 1.0 / lambda.at(j).sqrt();
            a[j * m..(j + 1) * m].iter_mut().for_each(|v| *v *= inv);
            rs[j] = r[j] * inv;
            st.trace_aat += a[j * m..(j + 1) * m].iter().map(|v| v * v).sum::<f64>();
        }
        let mut ar = self.ar.clone();
        linalg::gemm(
            &mut ar,
            (&a, m, k, false),
            (&rs, k, 1, false),
            1.0,
            true,
            Par::Seq,
        );
        let mut lb = self.lb.clone();
        if !linalg::cholesky_rank_update(&mut lb, m, &mut a, k) {
            return Err(GpError::NotPositiveDefinite {
                jitter: self.jitter,
            });
        }
        let mut stats = self.stats;
        stats.add(&st);
        let old_lb = std::mem::replace(&mut self.lb, lb);
        let old_ar = std::mem::replace(&mut self.ar, ar);
        let old_stats = std::mem::replace(&mut self.stats, stats);
        if let Err(e) = self.finish() {
            // Leave the model as it was.
            (self.lb, self.ar, self.stats) = (old_lb, old_ar, old_stats);
            let _ = self.finish();
            return Err(e);
        }
        Ok(())
    }

    /// `f(kc, scratch, out)` on consecutive chunks of the query points `q`, split between
    /// threads: `kc` holds `k(Z, q_j)` for the chunk's points (column-major `m × c`), `scratch`
    /// is a buffer of the chunk's size, and `f` pushes one value per point onto `out`; the values
    /// come back in the points' order. `work` is the per-point cost that decides the threads.
    fn over_chunks<T: Send>(
        &self,
        q: &Inputs,
        work: usize,
        f: impl Fn(&mut [f64], &mut [f64], &mut Vec<T>) + Sync,
    ) -> Vec<T> {
        let (m, d, n) = (self.m, self.d, q.n);
        let qs = scaled(q, &self.length_scales);
        let parts = over_groups(n, m, work, |p0, p1| {
            let chunk = chunk_len(m);
            let mut out = Vec::with_capacity(p1 - p0);
            let mut qc = Vec::new();
            let mut kbuf = vec![0.0; m * chunk.min(p1 - p0)];
            let mut scratch = vec![0.0; kbuf.len()];
            let mut c0 = p0;
            while c0 < p1 {
                let c = chunk.min(p1 - c0);
                copy_points(&qs, n, d, c0, c0 + c, &mut qc);
                let kc = &mut kbuf[..m * c];
                cross_seq(self.kernel, &self.zs, m, &qc, c, c, d, self.s2, kc, None);
                f(kc, &mut scratch[..m * c], &mut out);
                c0 += c;
            }
            out
        });
        parts.into_iter().flatten().collect()
    }

    /// Mean, `‖L⁻¹k*‖²` and `‖L_B⁻¹L⁻¹k*‖²` at query points (the last two only `if want_var`).
    pub fn predict_parts(&self, q: &Inputs, want_var: bool) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let m = self.m;
        let work = if want_var {
            m * (m + self.d + 8)
        } else {
            m * (self.d + 8)
        };
        let parts = self.over_chunks(q, work, |kc, _, out| {
            let c = kc.len() / m;
            let start = out.len();
            for col in kc.chunks_exact(m) {
                out.push((self.mean + linalg::dot(col, &self.w), 0.0, 0.0));
            }
            if want_var {
                linalg::solve_lower_in_place(&self.l, m, kc, c, Par::Seq);
                for (o, col) in out[start..].iter_mut().zip(kc.chunks_exact(m)) {
                    o.1 = linalg::dot(col, col);
                }
                linalg::solve_lower_in_place(&self.lb, m, kc, c, Par::Seq);
                for (o, col) in out[start..].iter_mut().zip(kc.chunks_exact(m)) {
                    o.2 = linalg::dot(col, col);
                }
            }
        });
        let mean = parts.iter().map(|p| p.0).collect();
        if !want_var {
            return (mean, Vec::new(), Vec::new());
        }
        (
            mean,
            parts.iter().map(|p| p.1).collect(),
            parts.iter().map(|p| p.2).collect(),
        )
    }

    /// `k(Z, x)`, column-major `m × |x|`.
    fn cross(&self, x: &Inputs) -> Vec<f64> {
        let (m, k) = (self.m, x.n);
        let xs = scaled(x, &self.length_scales);
        let mut a = vec![0.0; m * k];
        let (kernel, zs, d, s2) = (self.kernel, &self.zs, self.d, self.s2);
        cross_seq(kernel, zs, m, &xs, k, k, d, s2, &mut a, None);
        a
    }

    /// `L⁻¹ k(Z, x)`, column-major `m × |x|`: the points `x` projected on the inducing points.
    fn projected(&self, x: &Inputs) -> Vec<f64> {
        let mut a = self.cross(x);
        linalg::solve_lower_in_place(&self.l, self.m, &mut a, x.n, Par::Seq);
        a
    }

    /// The query points `q` prepared for their latent variances as if the points of any
    /// number of alternative pending sets had been observed as well (an [`update`](Self::update)
    /// of a copy; the variance does not depend on the labels): `g = L_B⁻¹ L⁻¹ k(Z, q)` and the
    /// two norms of [`predict`](Self::predict), `O(m² · |q|)` once; beside it, the posterior
    /// mean at `q`.
    pub fn fantasy(&self, q: &Inputs) -> (Vec<f64>, SparseFantasy<'_>) {
        let (m, r) = (self.m, q.n);
        let mut g = self.cross(q);
        let mean: Vec<f64> = g
            .chunks_exact(m)
            .map(|col| self.mean + linalg::dot(col, &self.w))
            .collect();
        linalg::solve_lower_in_place(&self.l, m, &mut g, r, Par::Seq);
        let v1 = g.chunks_exact(m).map(|col| linalg::dot(col, col)).collect();
        linalg::solve_lower_in_place(&self.lb, m, &mut g, r, Par::Seq);
        let v2 = g.chunks_exact(m).map(|col| linalg::dot(col, col)).collect();
        (
            mean,
            SparseFantasy {
                core: self,
                g,
                v1,
                v2,
            },
        )
    }

    /// Floats this conditioning keeps: the inducing inputs twice, the two triangles, the
    /// vectors, and the [`variance_factor`]'s `m²` whether formed yet or not (the first
    /// prediction forms it; `None` inside is counted too, conservatively).
    pub fn floats(&self) -> usize {
        self.z.cols.len()
            + self.zs.len()
            + self.l.len()
            + self.lb.len()
            + self.ar.len()
            + self.w.len()
            + self.m * self.m
    }

    /// Whether the [`variance_factor`] has been formed (or found impossible) for this
    /// conditioning, without forming it (tests).
    #[cfg(test)]
    pub fn variance_factor_formed(&self) -> bool {
        self.var_factor.get().is_some()
    }

    /// The [`variance_factor`] of this conditioning, formed on the first call.
    pub fn variance_factor(&self) -> Option<&[f64]> {
        self.var_factor
            .get_or_init(|| variance_factor(&self.l, &self.lb, self.m))
            .as_deref()
    }

    /// Mean and latent variance `s² − ‖L⁻¹k*‖² + ‖L_B⁻¹L⁻¹k*‖²` (clamped to `[0, s²]`),
    /// computed as `s² − ‖H k*‖²` with the [`variance_factor`] `H` (formed on the first call
    /// after a conditioning), or by the two solves where it could not be formed.
    pub fn predict(&self, q: &Inputs) -> (Vec<f64>, Vec<f64>) {
        let m = self.m;
        let Some(h) = self.variance_factor() else {
            let (mean, v1, v2) = self.predict_parts(q, true);
            let var = v1
                .iter()
                .zip(&v2)
                .map(|(a, b)| (self.s2 - a + b).clamp(0.0, self.s2))
                .collect();
            return (mean, var);
        };
        let parts = self.over_chunks(q, m * (m / 2 + self.d + 8), |kc, hk, out| {
            let c = kc.len() / m;
            linalg::lower_times(h, m, kc, c, hk, Par::Seq);
            for (col, hcol) in kc.chunks_exact(m).zip(hk.chunks_exact(m)) {
                let var = (self.s2 - linalg::dot(hcol, hcol)).clamp(0.0, self.s2);
                out.push((self.mean + linalg::dot(col, &self.w), var));
            }
        });
        parts.into_iter().unzip()
    }

    /// This GP as plain numbers: the inducing inputs, `w` as the weights and, `with_variance`,
    /// `F = L⁻¹` and `C = L_B⁻¹ L⁻¹` (explicit inverses of the triangles [`predict`](Self::predict)
    /// solves with), so that the latent variance is `s² − ‖F k‖² + ‖C k‖²`.
    pub fn predictor(&self, with_variance: bool) -> GpPredictor {
        let m = self.m;
        let (factor, correction) = if with_variance {
            let mut f = vec![0.0; m * m];
            linalg::invert_lower(&self.l, m, &mut f);
            let mut c = f.clone();
            linalg::solve_lower_in_place(&self.lb, m, &mut c, m, Par::Seq);
            (
                Some(export::pack_lower_col_major(&f, m)),
                Some(export::pack_lower_col_major(&c, m)),
            )
        } else {
            (None, None)
        };
        GpPredictor {
            kernel: self.kernel,
            length_scales: self.length_scales.clone(),
            signal_variance: self.s2,
            prior_mean: self.mean,
            points: export::rows(&self.z),
            weights: self.w.clone(),
            factor,
            correction,
        }
    }

    /// The prior it was conditioned from.
    pub fn prior(&self) -> Prior {
        Prior {
            kernel: self.kernel,
            mean: self.mean,
            length_scales: self.length_scales.clone(),
            s2: self.s2,
        }
    }

    /// The hyperparameters with the given noise figure.
    pub fn hyperparameters(&self, noise_variance: f64) -> Hyperparameters {
        self.prior().with_noise(noise_variance)
    }

    /// The stored form (see [`SparseCoreState`]).
    pub fn state(&self, noise_variance: f64) -> SparseCoreState {
        let (m, d) = (self.m, self.d);
        let mut z = Vec::with_capacity(m * d);
        for i in 0..m {
            for k in 0..d {
                z.push(self.z.cols[k * m + i]);
            }
        }
        let mut packed = Vec::with_capacity(m * (m + 1) / 2);
        for i in 0..m {
            for j in 0..=i {
                packed.push(self.lb[j * m + i]);
            }
        }
        SparseCoreState {
            hyperparameters: self.hyperparameters(noise_variance),
            inducing_points: z,
            jitter: self.jitter,
            factor_b: packed,
            projected_targets: self.ar.clone(),
            n_train: self.stats.n,
            sum_log_noise: self.stats.sum_log_lambda,
            sum_sq_residual_over_noise: self.stats.sum_r2_over_lambda,
            sum_inv_noise: self.stats.sum_inv_lambda,
            trace_aat: self.stats.trace_aat,
        }
    }

    /// Rebuilds from a stored state (checked): `K_mm` is refactorised with the stored jitter,
    /// `L_B` and the statistics are taken as stored.
    pub fn from_state(s: &SparseCoreState, what: &'static str) -> Result<SparseCore, GpError> {
        let h = &s.hyperparameters;
        let d = h.length_scales.len();
        if d == 0 {
            return Err(GpError::InvalidState(format!(
                "{what}: no input dimensions"
            )));
        }
        h.check(d, what)?;
        let m = s.projected_targets.len();
        if m == 0 || s.inducing_points.len() != m * d {
            return Err(GpError::InvalidState(format!(
                "{what}: {} inducing coordinates for m = {m}, d = {d}",
                s.inducing_points.len()
            )));
        }
        if s.factor_b.len() != m * (m + 1) / 2 {
            return Err(GpError::DimensionMismatch {
                what: "packed factor_b vs m(m+1)/2",
                expected: m * (m + 1) / 2,
                found: s.factor_b.len(),
            });
        }
        let finite = |v: &[f64], what: &'static str| match v.iter().position(|x| !x.is_finite()) {
            Some(index) => Err(GpError::NonFinite { what, index }),
            None => Ok(()),
        };
        finite(&s.inducing_points, "inducing_points")?;
        finite(&s.factor_b, "factor_b")?;
        finite(&s.projected_targets, "projected_targets")?;
        let scalars = [
            s.jitter,
            s.sum_log_noise,
            s.sum_sq_residual_over_noise,
            s.sum_inv_noise,
            s.trace_aat,
        ];
        if scalars.iter().any(|v| !v.is_finite()) || s.jitter < 0.0 || s.n_train == 0 {
            return Err(GpError::InvalidState(format!(
                "{what}: statistics must be finite, jitter >= 0 and n_train > 0"
            )));
        }
        let mut cols = vec![0.0; m * d];
        for i in 0..m {
            for k in 0..d {
                cols[k * m + i] = s.inducing_points[i * d + k];
            }
        }
        let z = Inputs { n: m, d, cols };
        let zs = scaled(&z, &h.length_scales);
        let (l, jitter, _) = factor_kmm(
            h.kernel,
            &zs,
            m,
            d,
            h.signal_variance,
            Ladder::Exact(s.jitter),
            None,
            false,
        )?;
        let mut lb = vec![0.0; m * m];
        let mut it = s.factor_b.iter();
        for i in 0..m {
            for j in 0..=i {
                lb[j * m + i] = *it.next().unwrap_or(&0.0);
            }
            if lb[i * m + i] <= 0.0 {
                return Err(GpError::InvalidState(format!(
                    "{what}: factor_b has a non-positive diagonal"
                )));
            }
        }
        let mut core = SparseCore {
            kernel: h.kernel,
            d,
            m,
            z,
            zs,
            length_scales: h.length_scales.clone(),
            s2: h.signal_variance,
            mean: h.prior_mean,
            jitter,
            l,
            lb,
            ar: s.projected_targets.clone(),
            stats: Stats {
                n: s.n_train,
                sum_log_lambda: s.sum_log_noise,
                sum_r2_over_lambda: s.sum_sq_residual_over_noise,
                sum_inv_lambda: s.sum_inv_noise,
                trace_aat: s.trace_aat,
            },
            w: Vec::new(),
            bound: 0.0,
            var_factor: OnceLock::new(),
        };
        core.finish()?;
        Ok(core)
    }
}
