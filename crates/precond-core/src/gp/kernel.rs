//! The Matérn ARD kernels (ν = 1/2, 3/2, 5/2) and the dense matrices built from them.
//!
//! With `r² = Σ_k ((x_k − x'_k) / ℓ_k)²`:
//! - ν = 5/2: `k = s² (1 + √5 r + 5/3 r²) exp(−√5 r)` (twice differentiable sample paths);
//! - ν = 3/2: `k = s² (1 + √3 r) exp(−√3 r)` (once differentiable);
//! - ν = 1/2: `k = s² exp(−r)` (the exponential kernel: continuous, nowhere differentiable paths,
//!   which follow a jump with long length scales where the smoother kernels need short ones).
//!
//! The derivative with respect to a log length scale is `∂k/∂log ℓ_k = G(r) · ((x_k − x'_k) / ℓ_k)²`
//! with `G = 5/3 s² (1 + √5 r) exp(−√5 r)`, `3 s² exp(−√3 r)` and `s² exp(−r) / r` respectively;
//! [`build_train`] stores `G`. For ν = 1/2 `G` grows like `1/r`, but the squared scaled difference
//! it multiplies is at most `r²`, so the product vanishes at `r = 0`, where `G` is stored as 0.
//!
//! Matrices are plain column-major `Vec<f64>` (column stride = number of rows), so they can be
//! split between threads by columns and viewed as faer matrices without copies. Only the lower
//! triangle of symmetric matrices is ever written or read.

use std::sync::OnceLock;

use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

/// `√5`.
pub(crate) const SQRT5: f64 = 2.236_067_977_499_79;
/// `√3`.
const SQRT3: f64 = 1.732_050_807_568_877_2;

/// The Matérn kernel's smoothness `ν`: how rough the deviation function may be.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(rename_all = "lowercase")]
pub enum Kernel {
    /// ν = 1/2, the exponential kernel `s² exp(−r)`: continuous but rough sample paths. A
    /// deviation that jumps (a wall, a patch of ice, a contact) is fitted with long length
    /// scales, so what is learned on either side of a jump still spreads along it.
    Matern12,
    /// ν = 3/2, `s² (1 + √3 r) exp(−√3 r)`: once-differentiable sample paths.
    Matern32,
    /// ν = 5/2, `s² (1 + √5 r + 5/3 r²) exp(−√5 r)`: twice-differentiable sample paths (the
    /// paper's kernel). A jump forces its length scales down to the jump's width.
    #[default]
    Matern52,
}

impl Kernel {
    /// Every kernel, roughest first.
    pub const ALL: [Kernel; 3] = [Kernel::Matern12, Kernel::Matern32, Kernel::Matern52];

    /// The kernel's name as the API spells it (`matern12`, `matern32`, `matern52`).
    pub fn name(self) -> &'static str {
        match self {
            Kernel::Matern12 => "matern12",
            Kernel::Matern32 => "matern32",
            Kernel::Matern52 => "matern52",
        }
    }

    /// Covariance for a squared scaled distance `r2` and signal variance `s2`.
    #[inline(always)]
    pub fn value(self, r2: f64, s2: f64) -> f64 {
        match self {
            Kernel::Matern12 => M12::k(r2, s2),
            Kernel::Matern32 => M32::k(r2, s2),
            Kernel::Matern52 => M52::k(r2, s2),
        }
    }
}

impl std::str::FromStr for Kernel {
    type Err = String;

    /// Parses the API's name of a kernel (`matern12`, `matern32`, `matern52`).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Kernel::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| format!("{s:?} is not a kernel; use matern12, matern32 or matern52"))
    }
}

impl std::fmt::Display for Kernel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One Matérn kernel's shape: with `t = C r`, `k = s² P(t, r²) e^{−t}` and
/// `G = s² Q(t, r) e^{−t}` (see the module documentation). A generic parameter, so that each
/// kernel's loops are compiled (and vectorised) apart.
trait Form {
    /// `√(2ν)`, the scale of the exponent.
    const C: f64;
    /// `P(t, r²)`.
    fn k_poly(t: f64, q: f64) -> f64;
    /// `Q(t, r)`.
    fn g_poly(t: f64, r: f64) -> f64;

    /// Covariance and `G` at squared scaled distance `q`.
    #[inline(always)]
    fn kg(q: f64, s2: f64) -> (f64, f64) {
        let r = q.sqrt();
        let t = Self::C * r;
        let e = if q > FAR_R2 {
            0.0
        } else {
            s2 * exp_nonpositive(-t)
        };
        (Self::k_poly(t, q) * e, Self::g_poly(t, r) * e)
    }

    /// Covariance at squared scaled distance `q`.
    #[inline(always)]
    fn k(q: f64, s2: f64) -> f64 {
        let t = Self::C * q.sqrt();
        let k = s2 * Self::k_poly(t, q) * exp_nonpositive(-t);
        // Beyond r = 300 the true value underflows to 0; the clamped exponential would instead
        // give `poly · e^−708` (and inf · 0 = NaN for q = inf). A select keeps loops vectorised.
        if q > FAR_R2 { 0.0 } else { k }
    }
}

struct M12;
struct M32;
struct M52;

impl Form for M12 {
    const C: f64 = 1.0;
    #[inline(always)]
    fn k_poly(_: f64, _: f64) -> f64 {
        1.0
    }
    #[inline(always)]
    fn g_poly(_: f64, r: f64) -> f64 {
        if r > 0.0 { 1.0 / r } else { 0.0 }
    }
}

impl Form for M32 {
    const C: f64 = SQRT3;
    #[inline(always)]
    fn k_poly(t: f64, _: f64) -> f64 {
        1.0 + t
    }
    #[inline(always)]
    fn g_poly(_: f64, _: f64) -> f64 {
        3.0
    }
}

impl Form for M52 {
    const C: f64 = SQRT5;
    #[inline(always)]
    fn k_poly(t: f64, q: f64) -> f64 {
        1.0 + t + (5.0 / 3.0) * q
    }
    #[inline(always)]
    fn g_poly(t: f64, _: f64) -> f64 {
        (5.0 / 3.0) * (1.0 + t)
    }
}

/// Training or query inputs, column-major `n × d` (dimension `k` is the contiguous slice
/// `cols[k*n .. (k+1)*n]`), exactly nalgebra's layout.
#[derive(Clone, Debug)]
pub(crate) struct Inputs {
    /// Number of points.
    pub n: usize,
    /// Input dimension.
    pub d: usize,
    /// The coordinates, column-major.
    pub cols: Vec<f64>,
}

impl Inputs {
    /// Copies a nalgebra matrix whose rows are points.
    pub fn from_matrix(x: &DMatrix<f64>) -> Self {
        Inputs {
            n: x.nrows(),
            d: x.ncols(),
            cols: x.as_slice().to_vec(),
        }
    }

    /// The points at `idx`, in that order.
    pub fn subset(&self, idx: &[usize]) -> Inputs {
        let m = idx.len();
        let mut cols = Vec::with_capacity(m * self.d);
        for k in 0..self.d {
            let col = &self.cols[k * self.n..(k + 1) * self.n];
            cols.extend(idx.iter().map(|&i| col[i]));
        }
        Inputs {
            n: m,
            d: self.d,
            cols,
        }
    }

    /// The coordinates divided by the length scales (`x_k / ℓ_k`), column-major.
    pub fn scaled(&self, length_scales: &[f64]) -> Vec<f64> {
        let mut out = self.cols.clone();
        for (k, &l) in length_scales.iter().enumerate() {
            let inv = 1.0 / l;
            out[k * self.n..(k + 1) * self.n]
                .iter_mut()
                .for_each(|v| *v *= inv);
        }
        out
    }
}

/// `eˣ` for `x ≤ 0`, written so that loops over slices auto-vectorise (libm's `exp` is a scalar
/// call and dominated the kernel builds). Cody–Waite reduction `x = k ln 2 + r`, `|r| ≤ ln2/2`,
/// degree-12 Taylor polynomial (truncation < 2e-16 relative), `2ᵏ` assembled from bits.
/// Relative error a few ulp; arguments below −708 give `e^−708` (≈ 3e-308) instead of a subnormal
/// or zero, which is far below anything the kernel can resolve.
#[inline(always)]
pub(crate) fn exp_nonpositive(x: f64) -> f64 {
    const LOG2E: f64 = std::f64::consts::LOG2_E;
    const LN2_HI: f64 = 6.931_471_803_691_238e-1;
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    // 1.5·2⁵²: adding it rounds to an integer held in the low mantissa bits.
    const SHIFT: f64 = 6_755_399_441_055_744.0;
    let x = x.clamp(-708.0, 0.0);
    let shifted = x * LOG2E + SHIFT;
    let k = (shifted.to_bits() as i64).wrapping_sub(SHIFT.to_bits() as i64);
    let kf = shifted - SHIFT;
    let r = (x - kf * LN2_HI) - kf * LN2_LO;
    let mut p = 1.0 / 479_001_600.0;
    p = p * r + 1.0 / 39_916_800.0;
    p = p * r + 1.0 / 3_628_800.0;
    p = p * r + 1.0 / 362_880.0;
    p = p * r + 1.0 / 40_320.0;
    p = p * r + 1.0 / 5_040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * r + 1.0;
    p = p * r + 1.0;
    p * f64::from_bits(((k + 1023) as u64) << 52)
}

/// Matérn 5/2 covariance for a squared scaled distance `r2`, signal variance `s2`.
#[cfg(test)]
pub(crate) fn matern52(r2: f64, s2: f64) -> f64 {
    M52::k(r2, s2)
}

/// Squared scaled distance beyond which the kernel is exactly 0 (`r = 300`).
const FAR_R2: f64 = 9.0e4;

/// Worker threads for a job of `work` elementary kernel evaluations (1 below ~2·10⁵, where
/// spawning costs more than it saves).
pub(crate) fn threads_for(work: usize) -> usize {
    static AVAILABLE: OnceLock<usize> = OnceLock::new();
    let avail = *AVAILABLE.get_or_init(|| {
        std::thread::available_parallelism()
            .map_or(1, |p| p.get())
            .min(16)
    });
    if work < 200_000 { 1 } else { avail }
}

/// Column boundaries `0 = b_0 < … < b_parts = n` that split the lower triangle of an `n × n`
/// matrix into `parts` pieces of about equal area. Depends only on `n` and `parts`.
pub(crate) fn triangle_blocks(n: usize, parts: usize) -> Vec<usize> {
    let parts = parts.max(1).min(n.max(1));
    let total = n as f64 * (n as f64 + 1.0) / 2.0;
    let mut bounds = vec![0usize];
    let mut c = 0usize;
    let mut area = 0.0;
    for p in 1..parts {
        let target = total * p as f64 / parts as f64;
        while c < n && area + (n - c) as f64 <= target {
            area += (n - c) as f64;
            c += 1;
        }
        if c > *bounds.last().unwrap_or(&0) {
            bounds.push(c);
        }
    }
    bounds.push(n);
    bounds.dedup();
    bounds
}

/// Splits a column-major `n × n` buffer into the column ranges of `bounds`.
fn split_columns<'a>(mut buf: &'a mut [f64], n: usize, bounds: &[usize]) -> Vec<&'a mut [f64]> {
    let mut out = Vec::with_capacity(bounds.len());
    for w in bounds.windows(2) {
        let (head, tail) = buf.split_at_mut((w[1] - w[0]) * n);
        out.push(head);
        buf = tail;
    }
    out
}

/// Calls the generic `$f::<K>($args)` with `K` the [`Form`] of `$kernel`: one compiled copy of
/// the loops per kernel.
macro_rules! with_form {
    ($kernel:expr, $f:ident($($arg:expr),* $(,)?)) => {
        match $kernel {
            Kernel::Matern12 => $f::<M12>($($arg),*),
            Kernel::Matern32 => $f::<M32>($($arg),*),
            Kernel::Matern52 => $f::<M52>($($arg),*),
        }
    };
}

/// Fills the lower triangle (diagonal included) of the training covariance
/// `a = s² R + diag(diag_add)` and, when `g` is given, the strict lower triangle of
/// `G_ij = 5/3 s² (1 + √5 r_ij) exp(−√5 r_ij)`.
///
/// `xs` are the length-scale-scaled inputs (`n × d`, column-major). Parallel over balanced
/// column blocks; every element is computed independently, so the result does not depend on the
/// number of threads.
#[allow(clippy::too_many_arguments)]
pub(crate) fn build_train(
    kernel: Kernel,
    xs: &[f64],
    n: usize,
    d: usize,
    s2: f64,
    diag_add: &[f64],
    a: &mut [f64],
    g: Option<&mut [f64]>,
) {
    with_form!(kernel, build_train_with(xs, n, d, s2, diag_add, a, g))
}

fn build_train_with<K: Form>(
    xs: &[f64],
    n: usize,
    d: usize,
    s2: f64,
    diag_add: &[f64],
    a: &mut [f64],
    g: Option<&mut [f64]>,
) {
    let threads = threads_for(n * n / 2 * (d + 4));
    let bounds = triangle_blocks(n, threads);
    let a_parts = split_columns(a, n, &bounds);
    let mut g_parts: Vec<Option<&mut [f64]>> = match g {
        Some(g) => split_columns(g, n, &bounds).into_iter().map(Some).collect(),
        None => (0..bounds.len() - 1).map(|_| None).collect(),
    };
    // Element-wise loops, dispatched to the CPU's vector width as in `cross_seq_with`.
    let work = |c0: usize, a_part: &mut [f64], g_part: Option<&mut [f64]>| {
        pulp::Arch::new()
            .dispatch(|| train_columns::<K>(xs, n, d, s2, diag_add, c0, a_part, g_part))
    };
    if bounds.len() == 2 {
        let a0 = a_parts.into_iter().next().unwrap_or_default();
        work(0, a0, g_parts.pop().flatten());
        return;
    }
    std::thread::scope(|scope| {
        for ((w, a_part), g_part) in bounds.windows(2).zip(a_parts).zip(g_parts) {
            let c0 = w[0];
            let work = &work;
            scope.spawn(move || work(c0, a_part, g_part));
        }
    });
}

/// Columns `c0 ..` of the training covariance (and `G`) for [`build_train_with`]: one
/// thread's share, the element-wise loops inlined into the dispatched caller.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn train_columns<K: Form>(
    xs: &[f64],
    n: usize,
    d: usize,
    s2: f64,
    diag_add: &[f64],
    c0: usize,
    a_part: &mut [f64],
    mut g_part: Option<&mut [f64]>,
) {
    let mut r2 = vec![0.0; n];
    let ncols = a_part.len() / n;
    for jc in 0..ncols {
        let c = c0 + jc;
        let r2 = &mut r2[c..n];
        r2.iter_mut().for_each(|v| *v = 0.0);
        for k in 0..d {
            let col = &xs[k * n + c..(k + 1) * n];
            let xc = col[0];
            for (acc, &v) in r2.iter_mut().zip(col) {
                let t = v - xc;
                *acc += t * t;
            }
        }
        let acol = &mut a_part[jc * n + c..(jc + 1) * n];
        match g_part.as_deref_mut() {
            Some(gp) => {
                let gcol = &mut gp[jc * n + c..(jc + 1) * n];
                for ((av, gv), &q) in acol.iter_mut().zip(gcol.iter_mut()).zip(r2.iter()) {
                    (*av, *gv) = K::kg(q, s2);
                }
            }
            None => {
                for (av, &q) in acol.iter_mut().zip(r2.iter()) {
                    *av = K::k(q, s2);
                }
            }
        }
        acol[0] = s2 + diag_add[c];
    }
}

/// Cross covariance `K*` between training inputs `xs` (`n × d`, scaled) and query inputs `qs`
/// (`m × d`, scaled), written column-major `n × m` into `out` (query `j` is column `j`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn build_cross(
    kernel: Kernel,
    xs: &[f64],
    n: usize,
    qs: &[f64],
    m: usize,
    d: usize,
    s2: f64,
    out: &mut [f64],
) {
    let threads = threads_for(n * m * (d + 4)).min(m.max(1));
    // Query `j0 + j` is point `j` of `qs[j0..]` (coordinate stride `m`).
    let work = |j0: usize, part: &mut [f64]| {
        cross_seq(
            kernel,
            xs,
            n,
            &qs[j0..],
            m,
            part.len() / n,
            d,
            s2,
            part,
            None,
        );
    };
    if threads <= 1 {
        work(0, out);
        return;
    }
    let per = m.div_ceil(threads);
    std::thread::scope(|scope| {
        for (t, part) in out.chunks_mut(per * n).enumerate() {
            let work = &work;
            scope.spawn(move || work(t * per, part));
        }
    });
}

/// Cross covariance (and, when `g` is given, `G`) between `m` points `zs` (scaled, column-major
/// `m × d`) and `c` points `qs` (scaled; coordinate `k` of point `j` at `qs[k * q_stride + j]`),
/// written column-major `m × c` (point `j` is column `j`). Sequential: for callers that already
/// split the work between threads (the sparse GP's chunked passes).
#[allow(clippy::too_many_arguments)]
pub(crate) fn cross_seq(
    kernel: Kernel,
    zs: &[f64],
    m: usize,
    qs: &[f64],
    q_stride: usize,
    c: usize,
    d: usize,
    s2: f64,
    k_out: &mut [f64],
    g_out: Option<&mut [f64]>,
) {
    with_form!(
        kernel,
        cross_seq_with(zs, m, qs, q_stride, c, d, s2, k_out, g_out)
    )
}

/// [`cross_seq_body`] compiled for the widest vector instructions the CPU has (pulp's runtime
/// dispatch: AVX2 or AVX-512 on x86-64, where the portable build targets SSE2). Bit-identical
/// on every CPU: the loops are element-wise, and Rust never fuses a multiply and an add by
/// itself, so only the width changes (a 256 × 512 block of Matérn 5/2 in d = 6 on the reference
/// machine: 1.34 ms with SSE2, 0.77 ms dispatched to AVX2).
#[allow(clippy::too_many_arguments)]
fn cross_seq_with<K: Form>(
    zs: &[f64],
    m: usize,
    qs: &[f64],
    q_stride: usize,
    c: usize,
    d: usize,
    s2: f64,
    k_out: &mut [f64],
    g_out: Option<&mut [f64]>,
) {
    pulp::Arch::new().dispatch(|| cross_seq_body::<K>(zs, m, qs, q_stride, c, d, s2, k_out, g_out))
}

#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn cross_seq_body<K: Form>(
    zs: &[f64],
    m: usize,
    qs: &[f64],
    q_stride: usize,
    c: usize,
    d: usize,
    s2: f64,
    k_out: &mut [f64],
    mut g_out: Option<&mut [f64]>,
) {
    for j in 0..c {
        let col = &mut k_out[j * m..(j + 1) * m];
        col.iter_mut().for_each(|v| *v = 0.0);
        for k in 0..d {
            let q = qs[k * q_stride + j];
            for (acc, &v) in col.iter_mut().zip(&zs[k * m..(k + 1) * m]) {
                let t = v - q;
                *acc += t * t;
            }
        }
        match g_out.as_deref_mut() {
            Some(g) => {
                let gcol = &mut g[j * m..(j + 1) * m];
                for (kv, gv) in col.iter_mut().zip(gcol.iter_mut()) {
                    (*kv, *gv) = K::kg(*kv, s2);
                }
            }
            None => {
                for v in col.iter_mut() {
                    *v = K::k(*v, s2);
                }
            }
        }
    }
}

/// `Σ_{i>j} W_ij G_ij ((x_ik − x_jk)/ℓ_k)²` for every dimension `k`, where
/// `W_ij = α_i α_j − (K⁻¹)_ij` and `kinv`, `g` hold lower triangles (column-major `n × n`).
///
/// This is `½ tr(W ∂K/∂log ℓ_k)`, the LML gradient w.r.t. the log length scales. The sum runs
/// over 16 fixed column blocks whose partial sums are added in order, so it is bit-identical for
/// any number of threads.
pub(crate) fn length_scale_gradient(
    xs: &[f64],
    n: usize,
    d: usize,
    alpha: &[f64],
    kinv: &[f64],
    g: &[f64],
) -> Vec<f64> {
    const BLOCKS: usize = 16;
    let bounds = triangle_blocks(n, BLOCKS);
    let nb = bounds.len() - 1;
    let block = |b: usize| -> Vec<f64> {
        let mut acc = vec![0.0; d];
        let mut t = vec![0.0; n];
        for c in bounds[b]..bounds[b + 1] {
            if c + 1 >= n {
                continue;
            }
            let ac = alpha[c];
            let t = &mut t[c + 1..n];
            let kcol = &kinv[c * n + c + 1..(c + 1) * n];
            let gcol = &g[c * n + c + 1..(c + 1) * n];
            for (((tv, &ai), &kv), &gv) in t.iter_mut().zip(&alpha[c + 1..n]).zip(kcol).zip(gcol) {
                *tv = (ai * ac - kv) * gv;
            }
            for (k, out) in acc.iter_mut().enumerate() {
                let col = &xs[k * n + c..(k + 1) * n];
                let xc = col[0];
                let mut s = 0.0;
                for (&tv, &v) in t.iter().zip(&col[1..]) {
                    let dlt = v - xc;
                    s += tv * dlt * dlt;
                }
                *out += s;
            }
        }
        acc
    };
    let threads = threads_for(n * n / 2 * (d + 3)).min(nb);
    let partials: Vec<Vec<f64>> = if threads <= 1 {
        (0..nb).map(block).collect()
    } else {
        let mut slots: Vec<Vec<f64>> = vec![Vec::new(); nb];
        std::thread::scope(|scope| {
            let handles: Vec<_> = (0..threads)
                .map(|t| {
                    let block = &block;
                    scope.spawn(move || {
                        (t..nb)
                            .step_by(threads)
                            .map(|b| (b, block(b)))
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            for h in handles {
                // A worker can only fail by panicking, which these loops cannot do.
                if let Ok(res) = h.join() {
                    for (b, v) in res {
                        slots[b] = v;
                    }
                }
            }
        });
        slots
    };
    let mut out = vec![0.0; d];
    for p in partials {
        for (o, v) in out.iter_mut().zip(p) {
            *o += v;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The dispatched kernel blocks (AVX2 or AVX-512 where the CPU has them), cross and training
    /// covariances, equal the portable build's bit for bit, `G` too, for every kernel.
    #[test]
    fn the_dispatched_kernel_blocks_are_the_portable_ones_bit_for_bit() {
        let (m, c, d) = (37, 23, 3);
        let zs: Vec<f64> = (0..m * d)
            .map(|i| ((i * 37) % 101) as f64 / 40.0 - 1.2)
            .collect();
        let mut qs: Vec<f64> = (0..c * d)
            .map(|i| ((i * 41) % 103) as f64 / 40.0 - 1.3)
            .collect();
        qs[0] = 1e3;
        for kernel in Kernel::ALL {
            let (mut k1, mut g1) = (vec![0.0; m * c], vec![0.0; m * c]);
            let (mut k2, mut g2) = (vec![0.0; m * c], vec![0.0; m * c]);
            cross_seq(kernel, &zs, m, &qs, c, c, d, 0.7, &mut k1, Some(&mut g1));
            with_form!(
                kernel,
                cross_seq_body(&zs, m, &qs, c, c, d, 0.7, &mut k2, Some(&mut g2))
            );
            let differ = |a: &[f64], b: &[f64]| {
                a.iter()
                    .zip(b)
                    .filter(|(x, y)| x.to_bits() != y.to_bits())
                    .count()
            };
            assert_eq!(differ(&k1, &k2), 0, "{kernel}: covariances");
            assert_eq!(differ(&g1, &g2), 0, "{kernel}: G");
            cross_seq(kernel, &zs, m, &qs, c, c, d, 0.7, &mut k1, None);
            with_form!(
                kernel,
                cross_seq_body(&zs, m, &qs, c, c, d, 0.7, &mut k2, None)
            );
            assert_eq!(differ(&k1, &k2), 0, "{kernel}: covariances without G");
            assert!(k1[..m].iter().all(|&v| v == 0.0), "{kernel}: a far point");
            assert!(k1.iter().any(|&v| v > 0.1), "{kernel}: some near points");
            // The training covariance, on enough points for several threads.
            let n = 300;
            let xs: Vec<f64> = (0..n * d).map(|i| ((i * 53) % 211) as f64 / 70.0).collect();
            let diag: Vec<f64> = (0..n).map(|i| 1e-3 * (i % 5) as f64).collect();
            let (mut a1, mut g1) = (vec![0.0; n * n], vec![0.0; n * n]);
            let (mut a2, mut g2) = (vec![0.0; n * n], vec![0.0; n * n]);
            build_train(kernel, &xs, n, d, 0.7, &diag, &mut a1, Some(&mut g1));
            with_form!(
                kernel,
                train_columns(&xs, n, d, 0.7, &diag, 0, &mut a2, Some(&mut g2))
            );
            assert_eq!(differ(&a1, &a2), 0, "{kernel}: training covariance");
            assert_eq!(differ(&g1, &g2), 0, "{kernel}: training G");
        }
    }

    #[test]
    fn fast_exp_matches_libm() {
        let mut worst: f64 = 0.0;
        for i in 0..200_000 {
            let x = -(i as f64) * 3.5e-3 - 1e-9 * (i % 7) as f64;
            let (a, b) = (exp_nonpositive(x), x.exp());
            worst = worst.max(((a - b) / b).abs());
        }
        assert!(worst < 1e-14, "worst relative error {worst:e}");
        assert_eq!(exp_nonpositive(0.0), 1.0);
        assert!(exp_nonpositive(-1e6) >= 0.0 && exp_nonpositive(-1e6) < 1e-300);
        assert_eq!(matern52(f64::INFINITY, 1.0), 0.0);
        assert_eq!(matern52(1e12, 1.0), 0.0);
    }

    #[test]
    fn triangle_blocks_cover_and_balance() {
        for n in [1usize, 2, 7, 100, 1001] {
            for parts in [1usize, 2, 3, 16] {
                let b = triangle_blocks(n, parts);
                assert_eq!(b[0], 0);
                assert_eq!(*b.last().unwrap(), n);
                assert!(b.windows(2).all(|w| w[0] < w[1]));
            }
        }
    }
}
