//! Greedy variance selection of inducing points (a pivoted Cholesky factorisation of the kernel
//! matrix over candidate points; Burt, Rasmussen & van der Wilk 2020, "conditional variance").

use rand::SeedableRng;
use rand::seq::index::sample;
use rand_chacha::ChaCha8Rng;

use super::super::kernel::{Inputs, Kernel, cross_seq};
use super::core::scaled;

/// Up to `m` indices into `x`, in selection order: each is the candidate with the largest
/// variance conditioned on those before it, under the kernel with `length_scales` and `s2`.
///
/// The candidates are a seeded random subset of `pool` points (all of them when `n ≤ pool`).
/// Selection stops early when no candidate's conditional variance exceeds `min_rel · s2`
/// (fewer distinct inputs than `m`, e.g. duplicates or `n < m`), so the chosen points are
/// distinct and `K_mm` is well conditioned at these hyperparameters. O(pool · m²) time,
/// O(pool · m) memory.
#[allow(clippy::too_many_arguments)]
pub(crate) fn greedy_variance(
    kernel: Kernel,
    x: &Inputs,
    length_scales: &[f64],
    s2: f64,
    m: usize,
    pool: usize,
    min_rel: f64,
    seed: u64,
) -> Vec<usize> {
    let n = x.n;
    let candidates: Vec<usize> = if n <= pool {
        (0..n).collect()
    } else {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut idx = sample(&mut rng, n, pool).into_vec();
        idx.sort_unstable();
        idx
    };
    let c = candidates.len();
    let sub = x.subset(&candidates);
    let xs = scaled(&sub, length_scales);
    let d = x.d;
    let m = m.min(c);
    let mut resid = vec![s2; c];
    // Column t of the partial factor: the selected point's row of L over all candidates.
    let mut lcols: Vec<f64> = Vec::with_capacity(c * m);
    let mut chosen = Vec::with_capacity(m);
    let mut kcol = vec![0.0; c];
    for t in 0..m {
        let (j, best) =
            resid
                .iter()
                .enumerate()
                .fold((0, f64::NEG_INFINITY), |(bj, bv), (i, &v)| {
                    if v > bv { (i, v) } else { (bj, bv) }
                });
        // NaN-safe: a NaN variance also stops the selection.
        if best.is_nan() || best <= min_rel * s2 {
            break;
        }
        cross_seq(kernel, &xs, c, &xs[j..], c, 1, d, s2, &mut kcol, None);
        for s in 0..t {
            let col = &lcols[s * c..(s + 1) * c];
            let f = col[j];
            if f != 0.0 {
                for (k, &v) in kcol.iter_mut().zip(col) {
                    *k -= f * v;
                }
            }
        }
        let inv = 1.0 / best.sqrt();
        for (i, k) in kcol.iter_mut().enumerate() {
            *k *= inv;
            resid[i] = (resid[i] - *k * *k).max(0.0);
        }
        resid[j] = 0.0;
        lcols.extend_from_slice(&kcol);
        chosen.push(candidates[j]);
    }
    chosen
}
