//! Dense linear algebra on column-major buffers, delegated to faer's blocked kernels.
//!
//! nalgebra's own Cholesky is unblocked (≈11 GFLOP/s on the reference machine); faer's blocked
//! one runs at 70–150 GFLOP/s. faer parallelises through rayon, which *slows down* small problems,
//! so [`par_for`] picks the parallelism per call from the matrix size.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor;
use faer::linalg::matmul::triangular::BlockStructure;
use faer::{Accum, MatMut, MatRef, Par};

/// Matrices with at least this many rows are factorised/inverted with all threads; smaller ones
/// sequentially (measured crossover on 2 cores: between n = 1000 and 2000).
pub(crate) const PARALLEL_MIN_N: usize = 1200;

/// faer parallelism for an `n × n` problem.
pub(crate) fn par_for(n: usize) -> Par {
    if n >= PARALLEL_MIN_N {
        Par::rayon(0)
    } else {
        Par::Seq
    }
}

fn view(a: &[f64], nrows: usize, ncols: usize) -> MatRef<'_, f64> {
    MatRef::from_column_major_slice(a, nrows, ncols)
}

fn view_mut(a: &mut [f64], nrows: usize, ncols: usize) -> MatMut<'_, f64> {
    MatMut::from_column_major_slice_mut(a, nrows, ncols)
}

/// In-place lower Cholesky factor of the lower triangle of `a` (`n × n`). `false` when a pivot
/// is not positive (or not finite); `a`'s lower triangle is then garbage.
pub(crate) fn cholesky_in_place(a: &mut [f64], n: usize) -> bool {
    let par = par_for(n);
    let mut mem = MemBuffer::new(factor::cholesky_in_place_scratch::<f64>(
        n,
        par,
        Default::default(),
    ));
    let ok = factor::cholesky_in_place(
        view_mut(a, n, n),
        Default::default(),
        par,
        MemStack::new(&mut mem),
        Default::default(),
    )
    .is_ok();
    // faer accepts any positive pivot; reject non-finite factors too (e.g. from huge entries).
    ok && (0..n).all(|i| a[i * n + i].is_finite() && a[i * n + i] > 0.0)
}

/// Solves `L X = B` in place (`B` is `n × m`).
pub(crate) fn solve_lower_in_place(l: &[f64], n: usize, b: &mut [f64], m: usize, par: Par) {
    faer::linalg::triangular_solve::solve_lower_triangular_in_place(
        view(l, n, n),
        view_mut(b, n, m),
        par,
    );
}

/// Solves `Lᵀ X = B` in place (`B` is `n × m`).
pub(crate) fn solve_upper_transpose_in_place(
    l: &[f64],
    n: usize,
    b: &mut [f64],
    m: usize,
    par: Par,
) {
    faer::linalg::triangular_solve::solve_upper_triangular_in_place(
        view(l, n, n).transpose(),
        view_mut(b, n, m),
        par,
    );
}

/// Writes `L⁻¹` into the lower triangle of `out` (`n × n`).
pub(crate) fn invert_lower(l: &[f64], n: usize, out: &mut [f64]) {
    faer::linalg::triangular_inverse::invert_lower_triangular(
        view_mut(out, n, n),
        view(l, n, n),
        par_for(n),
    );
}

/// Writes the lower triangle of `L⁻ᵀ L⁻¹ = K⁻¹` into `out`, given `L⁻¹` in the lower triangle of `linv`.
pub(crate) fn inverse_from_inverse_factor(linv: &[f64], n: usize, out: &mut [f64]) {
    let li = view(linv, n, n);
    faer::linalg::matmul::triangular::matmul(
        view_mut(out, n, n),
        BlockStructure::TriangularLower,
        Accum::Replace,
        li.transpose(),
        BlockStructure::TriangularUpper,
        li,
        BlockStructure::TriangularLower,
        1.0,
        par_for(n),
    );
}

/// Writes `L⁻¹` **row-major** (i.e. `L⁻ᵀ` column-major, upper triangle) into `out` (`n × n`):
/// row `i` of `L⁻¹` is then the contiguous slice `out[i*n ..= i*n + i]`.
pub(crate) fn invert_lower_row_major(l: &[f64], n: usize, out: &mut [f64]) {
    faer::linalg::triangular_inverse::invert_lower_triangular(
        view_mut(out, n, n).transpose_mut(),
        view(l, n, n),
        par_for(n),
    );
}

/// `out = A B` for `A` and `B` lower triangular (`n × n`, column-major); `out`'s strict upper
/// triangle is zero.
pub(crate) fn lower_times_lower(a: &[f64], b: &[f64], n: usize, out: &mut [f64]) {
    out.iter_mut().for_each(|v| *v = 0.0);
    faer::linalg::matmul::triangular::matmul(
        view_mut(out, n, n),
        BlockStructure::TriangularLower,
        Accum::Replace,
        view(a, n, n),
        BlockStructure::TriangularLower,
        view(b, n, n),
        BlockStructure::TriangularLower,
        1.0,
        par_for(n),
    );
}

/// `out = H B` with `H` lower triangular (`n × n`, column-major) and `B`, `out` column-major
/// `n × m`: half the multiply-adds of a dense product, and no triangular solve's dependencies.
pub(crate) fn lower_times(h: &[f64], n: usize, b: &[f64], m: usize, out: &mut [f64], par: Par) {
    faer::linalg::matmul::triangular::matmul(
        view_mut(out, n, m),
        BlockStructure::Rectangular,
        Accum::Replace,
        view(h, n, n),
        BlockStructure::TriangularLower,
        view(b, n, m),
        BlockStructure::Rectangular,
        1.0,
        par,
    );
}

/// `out = L⁻¹ B` with `L⁻¹` stored row-major in `linv_rm` (see [`invert_lower_row_major`]) and
/// `B`, `out` column-major `n × m`.
pub(crate) fn lower_matmul(
    linv_rm: &[f64],
    n: usize,
    b: &[f64],
    m: usize,
    out: &mut [f64],
    par: Par,
) {
    faer::linalg::matmul::triangular::matmul(
        view_mut(out, n, m),
        BlockStructure::Rectangular,
        Accum::Replace,
        view(linv_rm, n, n).transpose(),
        BlockStructure::TriangularLower,
        view(b, n, m),
        BlockStructure::Rectangular,
        1.0,
        par,
    );
}

/// `out (r × c) = α op(A) op(B) + (out if accumulate)`, all column-major; `op(A)` is `A` or `Aᵀ`
/// as `ta` says (`a` is stored `a_rows × a_cols` before transposition), likewise `B`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn gemm(
    out: &mut [f64],
    (a, a_rows, a_cols, ta): (&[f64], usize, usize, bool),
    (b, b_rows, b_cols, tb): (&[f64], usize, usize, bool),
    alpha: f64,
    accumulate: bool,
    par: Par,
) {
    let av = view(a, a_rows, a_cols);
    let bv = view(b, b_rows, b_cols);
    let av = if ta { av.transpose() } else { av };
    let bv = if tb { bv.transpose() } else { bv };
    let (r, c) = (av.nrows(), bv.ncols());
    faer::linalg::matmul::matmul(
        view_mut(out, r, c),
        if accumulate {
            Accum::Add
        } else {
            Accum::Replace
        },
        av,
        bv,
        alpha,
        par,
    );
}

/// Adds `A Aᵀ` to the lower triangle of `out` (`m × m`), `A` column-major `m × c`.
pub(crate) fn syrk_lower_add(out: &mut [f64], m: usize, a: &[f64], c: usize, par: Par) {
    let av = view(a, m, c);
    faer::linalg::matmul::triangular::matmul(
        view_mut(out, m, m),
        BlockStructure::TriangularLower,
        Accum::Add,
        av,
        BlockStructure::Rectangular,
        av.transpose(),
        BlockStructure::Rectangular,
        1.0,
        par,
    );
}

/// Updates the lower Cholesky factor `l` (`n × n`) of `M` to that of `M + W Wᵀ` (`W` is
/// `n × k`, clobbered). `false` when the update fails (it cannot for a positive definite `M`
/// and finite `W`, but a non-finite input would).
pub(crate) fn cholesky_rank_update(l: &mut [f64], n: usize, w: &mut [f64], k: usize) -> bool {
    let mut alpha = vec![1.0; k];
    faer::linalg::cholesky::llt::update::rank_r_update_clobber(
        view_mut(l, n, n),
        view_mut(w, n, k),
        faer::diag::DiagMut::from_slice_mut(&mut alpha),
    )
    .is_ok()
        && (0..n).all(|i| l[i * n + i].is_finite() && l[i * n + i] > 0.0)
}

/// Dot product with eight independent accumulators (vectorises; fixed summation order).
#[inline]
pub(crate) fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for t in 0..8 {
            acc[t] += x[t] * y[t];
        }
    }
    acc.iter().sum::<f64>() + tail
}
