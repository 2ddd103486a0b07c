//! A seeded synthetic regression problem: what `precond bench gp`, `bench sparse` and the cost
//! model's tests fit, so that their figures are measured on the same data.

use nalgebra::{DMatrix, DVector};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// Seeded benchmark data: `n` points in `[0,1]^d`, a smooth target with noise std `0.05 + 0.2 x₀`.
pub fn bench_data(n: usize, d: usize, seed: u64) -> (DMatrix<f64>, DVector<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let x = DMatrix::from_fn(n, d, |_, _| rng.random::<f64>());
    let y = DVector::from_fn(n, |i, _| {
        let c = |k: usize| if k < d { x[(i, k)] } else { 0.0 };
        (3.0 * c(0)).sin() + 0.5 * (5.0 * c(1)).cos() + c(2) * c(2) - 0.5 * c(3)
            + 0.2 * (7.0 * c(4) * c(5)).sin()
            + (0.05 + 0.2 * c(0)) * rng.sample::<f64, _>(StandardNormal)
    });
    (x, y)
}
