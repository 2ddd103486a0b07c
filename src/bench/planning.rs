//! The planning speed benchmark (issue 4, item 6): a proposal with 20 candidates and a
//! 5000-extension budget on the icy gridworld with a model trained on 1000 transitions, and a
//! test-time plan, each timed (median over several runs) and printed.
//!
//! The deviation model is a parameter, so the real GP can be benchmarked in place of the
//! stand-in. [`GpStandIn`] is an exact GP posterior (Matérn 5/2, ARD, fixed hyperparameters, no
//! fitting of them) on the same kind of data: per point it does the O(n d) kernel vector, the
//! O(n) mean and the O(n²) triangular solve of an exact predictive variance, so its cost per point
//! is that of a real GP prediction at the same n.

use crate::domain::{Domain, IcyGridworld};
use crate::planning::synthetic::{icy_true_deviation, icy_true_step};
use crate::planning::{
    AcquisitionSettings, DeviationModel, PlannerSettings, Strategy, plan, propose,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::{Duration, Instant};

/// One executed transition of the true icy gridworld.
#[derive(Debug, Clone, PartialEq)]
pub struct Transition {
    /// State before.
    pub s: Vec<f64>,
    /// Action.
    pub a: Vec<f64>,
    /// True next state.
    pub s_next: Vec<f64>,
    /// Its deviation label `d(f̂(s, a), s')`.
    pub deviation: f64,
}

/// `n` transitions from uniformly drawn open cells and moves, executed in the true world.
pub fn icy_transitions(grid: &IcyGridworld, n: usize, seed: u64) -> Vec<Transition> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let open = grid.open_cells();
    (0..n)
        .map(|_| {
            let s = open[rng.random_range(0..open.len())].to_vec();
            let a = grid.sample_action(&s, &mut rng);
            let s_next = icy_true_step(grid, &s, &a);
            let deviation = icy_true_deviation(grid, &s, &a);
            Transition {
                s,
                a,
                s_next,
                deviation,
            }
        })
        .collect()
}

/// An exact GP posterior with fixed hyperparameters (see the module docs): a stand-in for the
/// real MDE with the same cost per predicted point.
pub struct GpStandIn {
    dim: usize,
    /// Training inputs, `n × dim` row-major.
    x: Vec<f64>,
    length_scales: Vec<f64>,
    signal_variance: f64,
    noise_variance: f64,
    /// `(K + σ_n² I)⁻¹ y`.
    weights: Vec<f64>,
    /// Lower Cholesky factor of `K + σ_n² I`, `n × n` row-major.
    chol: Vec<f64>,
}

impl GpStandIn {
    /// Conditions the GP on `features` (`n × dim`) and `targets`; `None` if the kernel matrix
    /// is not positive definite.
    pub fn fit(
        features: &[f64],
        targets: &[f64],
        dim: usize,
        length_scales: &[f64],
        signal_variance: f64,
        noise_variance: f64,
    ) -> Option<Self> {
        let n = targets.len();
        let mut gp = Self {
            dim,
            x: features.to_vec(),
            length_scales: length_scales.to_vec(),
            signal_variance,
            noise_variance,
            weights: Vec::new(),
            chol: vec![0.0; n * n],
        };
        for i in 0..n {
            for j in 0..=i {
                let k = gp.kernel(&features[i * dim..][..dim], &features[j * dim..][..dim]);
                gp.chol[i * n + j] = k + if i == j { noise_variance } else { 0.0 };
            }
        }
        // In-place Cholesky, row by row (dot products of contiguous rows).
        for i in 0..n {
            for j in 0..=i {
                let (ri, rj) = (i * n, j * n);
                let v = gp.chol[ri + j] - dot(&gp.chol[ri..ri + j], &gp.chol[rj..rj + j]);
                if i == j {
                    if v <= 0.0 {
                        return None;
                    }
                    gp.chol[ri + i] = v.sqrt();
                } else {
                    gp.chol[ri + j] = v / gp.chol[rj + j];
                }
            }
        }
        let z = gp.forward(targets, 1);
        gp.weights = gp.backward(&z);
        Some(gp)
    }

    fn n(&self) -> usize {
        self.x.len() / self.dim.max(1)
    }

    fn kernel(&self, a: &[f64], b: &[f64]) -> f64 {
        let r2: f64 = a
            .iter()
            .zip(b)
            .zip(&self.length_scales)
            .map(|((p, q), l)| ((p - q) / l).powi(2))
            .sum();
        let r5 = (5.0 * r2).sqrt();
        self.signal_variance * (1.0 + r5 + 5.0 * r2 / 3.0) * (-r5).exp()
    }

    /// Solves `L v_p = b_p` for `m` right-hand sides stored point-major (`m × n`, row `p` is
    /// `b_p`), row by row of `L` so that `L` streams through memory once per batch.
    fn forward(&self, b: &[f64], m: usize) -> Vec<f64> {
        let n = self.n();
        let mut v = b.to_vec();
        for i in 0..n {
            let row = &self.chol[i * n..][..i];
            let d = self.chol[i * n + i];
            for p in 0..m {
                let vp = &mut v[p * n..][..n];
                let s = dot(row, &vp[..i]);
                vp[i] = (vp[i] - s) / d;
            }
        }
        v
    }

    /// Solves `Lᵀ w = z` for one vector.
    fn backward(&self, z: &[f64]) -> Vec<f64> {
        let n = self.n();
        let mut w = z.to_vec();
        for i in (0..n).rev() {
            w[i] /= self.chol[i * n + i];
            let wi = w[i];
            for (wk, l) in w[..i].iter_mut().zip(&self.chol[i * n..][..i]) {
                *wk -= l * wi;
            }
        }
        w
    }
}

impl DeviationModel for GpStandIn {
    fn predict(&self, features: &[f64], dim: usize) -> Vec<(f64, f64)> {
        let n = self.n();
        // Cross-covariances, point-major: row p is k(X, x_p).
        let k: Vec<f64> = features
            .chunks(dim.max(1))
            .flat_map(|f| self.x.chunks(self.dim).map(move |xi| self.kernel(xi, f)))
            .collect();
        let m = k.len() / n.max(1);
        let v = self.forward(&k, m);
        (0..m)
            .map(|p| {
                let mu = dot(&k[p * n..][..n], &self.weights);
                let vp = &v[p * n..][..n];
                let explained = dot(vp, vp);
                let var = (self.signal_variance - explained).max(0.0) + self.noise_variance;
                (mu, var.sqrt())
            })
            .collect()
    }
}

/// A dot product with four independent accumulators, so that it vectorises.
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..4 {
            acc[k] += x[k] * y[k];
        }
    }
    acc[0] + acc[1] + acc[2] + acc[3] + tail
}

/// The stand-in model on `n` transitions of `grid` (length scales 0.08 on the cell, 0.3 on
/// the move, in unit-box features; signal variance 1; noise standard deviation 0.01).
pub fn stand_in_model(grid: &IcyGridworld, n: usize, seed: u64) -> Option<GpStandIn> {
    let data = icy_transitions(grid, n, seed);
    let features: Vec<f64> = data
        .iter()
        .flat_map(|t| grid.features(&t.s, &t.a))
        .collect();
    let targets: Vec<f64> = data.iter().map(|t| t.deviation).collect();
    GpStandIn::fit(
        &features,
        &targets,
        grid.feature_dim(),
        &[0.08, 0.08, 0.3, 0.3],
        1.0,
        1e-4,
    )
}

/// What the benchmark does.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    /// Timed repetitions of each measurement (the median is reported); each uses its own seed.
    pub repeats: usize,
    /// Start cell.
    pub start: Vec<f64>,
    /// Goal cell.
    pub goal: Vec<f64>,
    /// The β values to time a proposal at (default −2, 0, 2: the start, middle and end of the
    /// learning schedule).
    pub proposal_betas: Vec<f64>,
    /// β of the test-time plan.
    pub test_beta: f64,
    /// Planner settings (default: 20 candidates, 5000 extensions).
    pub planner: PlannerSettings,
}

impl Default for BenchOptions {
    fn default() -> Self {
        Self {
            repeats: 9,
            start: vec![0.0, 0.0],
            goal: vec![11.0, 11.0],
            proposal_betas: vec![-2.0, 0.0, 2.0],
            test_beta: 2.0,
            planner: PlannerSettings::default(),
        }
    }
}

/// The measured figures.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchFigures {
    /// Median wall time of one `active` proposal, per β of `BenchOptions::proposal_betas`.
    pub proposal: Vec<Duration>,
    /// Median wall time of one test-time plan.
    pub plan: Duration,
    /// Median wall time of one random-strategy proposal.
    pub random: Duration,
}

/// Runs the benchmark on `grid` with `model` and prints the figures.
pub fn run(
    grid: &IcyGridworld,
    model: &dyn DeviationModel,
    options: &BenchOptions,
) -> BenchFigures {
    let acq = AcquisitionSettings::default();
    let d_max = grid.default_d_max();
    let repeats = options.repeats.max(1);
    println!(
        "planning benchmark: icy gridworld {}×{}, {} → {}, {} candidates × {} extensions, median of {repeats}",
        grid.width(),
        grid.height(),
        fmt_vec(&options.start),
        fmt_vec(&options.goal),
        options.planner.n_candidates,
        options.planner.max_extensions,
    );

    let mut proposal = Vec::new();
    for &beta in &options.proposal_betas {
        let mut times = Vec::new();
        let mut last = None;
        for seed in 0..repeats as u64 {
            let t0 = Instant::now();
            let p = propose(
                Strategy::Active,
                grid,
                model,
                &options.start,
                &options.goal,
                beta,
                d_max,
                &options.planner,
                &acq,
                seed,
            );
            times.push(t0.elapsed());
            last = Some(p);
        }
        let time = median(&mut times);
        proposal.push(time);
        match last {
            Some(Ok(p)) => println!(
                "  proposal (active, β = {beta:>4}): {:>8.2} ms  [{} runs, {} candidates, {} extensions, {} model points in {} calls, chosen length {}, α = {:.4}]",
                ms(time),
                p.runs,
                p.candidates.len(),
                p.extensions,
                p.model_points,
                p.model_calls,
                p.trajectory.len(),
                p.alpha
            ),
            Some(Err(e)) => println!(
                "  proposal (active, β = {beta:>4}): {:>8.2} ms  [{e}]",
                ms(time)
            ),
            None => {}
        }
    }

    let mut times = Vec::new();
    let mut last = None;
    for seed in 0..repeats as u64 {
        let t0 = Instant::now();
        let out = plan(
            grid,
            model,
            &options.start,
            &options.goal,
            options.test_beta,
            d_max,
            &options.planner,
            seed,
        );
        times.push(t0.elapsed());
        last = Some(out);
    }
    let plan_time = median(&mut times);
    match last {
        Some(Ok(out)) => println!(
            "  test-time plan (β = {:>4}):     {:>8.2} ms  [found: {}, {} extensions, tree of {} nodes{}]",
            options.test_beta,
            ms(plan_time),
            out.trajectory.is_some(),
            out.extensions,
            out.tree_size,
            out.trajectory
                .map(|t| format!(", length {}", t.len()))
                .unwrap_or_default()
        ),
        Some(Err(e)) => println!(
            "  test-time plan (β = {}): {:>8.2} ms  [{e}]",
            options.test_beta,
            ms(plan_time)
        ),
        None => {}
    }

    let mut times = Vec::new();
    for seed in 0..repeats as u64 {
        let t0 = Instant::now();
        let _ = propose(
            Strategy::Random,
            grid,
            model,
            &options.start,
            &options.goal,
            0.0,
            d_max,
            &options.planner,
            &acq,
            seed,
        );
        times.push(t0.elapsed());
    }
    let random = median(&mut times);
    println!("  proposal (random, β =    0):   {:>8.2} ms", ms(random));

    BenchFigures {
        proposal,
        plan: plan_time,
        random,
    }
}

/// Times `model` alone: microseconds per point, one point per call and in batches of 64.
pub fn time_model(grid: &IcyGridworld, model: &dyn DeviationModel) -> (f64, f64) {
    let dim = grid.feature_dim();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let points: Vec<f64> = (0..256)
        .flat_map(|_| {
            let s = grid.sample_state(&mut rng);
            let a = grid.sample_action(&s, &mut rng);
            grid.features(&s, &a)
        })
        .collect();
    let t0 = Instant::now();
    for p in points.chunks(dim) {
        std::hint::black_box(model.predict(p, dim));
    }
    let single = t0.elapsed().as_secs_f64() * 1e6 / 256.0;
    let t0 = Instant::now();
    for p in points.chunks(64 * dim) {
        std::hint::black_box(model.predict(p, dim));
    }
    let batched = t0.elapsed().as_secs_f64() * 1e6 / 256.0;
    (single, batched)
}

/// The whole benchmark with the stand-in model on 1000 transitions of the default layout.
pub fn run_default() -> BenchFigures {
    let grid = IcyGridworld::default_layout();
    let t0 = Instant::now();
    let model =
        stand_in_model(&grid, 1000, 7).expect("the stand-in kernel matrix is positive definite");
    println!(
        "stand-in GP on 1000 transitions conditioned in {:.0} ms",
        ms(t0.elapsed())
    );
    let (single, batched) = time_model(&grid, &model);
    println!(
        "  model cost: {single:.1} µs/point one at a time, {batched:.1} µs/point in batches of 64"
    );
    run(&grid, &model, &BenchOptions::default())
}

fn median(times: &mut [Duration]) -> Duration {
    times.sort();
    times[times.len() / 2]
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn fmt_vec(v: &[f64]) -> String {
    format!("{v:?}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_abs_diff_eq;

    #[test]
    fn the_stand_in_is_an_exact_gp_posterior() {
        // Two 1-D points; by hand: K = [[1, k], [k, 1]] + s²I with k = k(0, 0.5).
        let (x, y) = ([0.0, 0.5], [1.0, -1.0]);
        let s2 = 0.01;
        let gp = GpStandIn::fit(&x, &y, 1, &[0.3], 1.0, s2).unwrap();
        let k = gp.kernel(&[0.0], &[0.5]);
        let det = (1.0 + s2) * (1.0 + s2) - k * k;
        let inv = [[(1.0 + s2) / det, -k / det], [-k / det, (1.0 + s2) / det]];
        let q = 0.2;
        let ks = [gp.kernel(&[q], &[0.0]), gp.kernel(&[q], &[0.5])];
        let w = [
            inv[0][0] * y[0] + inv[0][1] * y[1],
            inv[1][0] * y[0] + inv[1][1] * y[1],
        ];
        let mu = ks[0] * w[0] + ks[1] * w[1];
        let quad = ks[0] * (inv[0][0] * ks[0] + inv[0][1] * ks[1])
            + ks[1] * (inv[1][0] * ks[0] + inv[1][1] * ks[1]);
        let sigma = (1.0 - quad + s2).sqrt();
        let batch = gp.predict(&[q, 0.0, q], 1);
        for (m, s) in [batch[0], batch[2]] {
            assert_abs_diff_eq!(m, mu, epsilon = 1e-10);
            assert_abs_diff_eq!(s, sigma, epsilon = 1e-10);
        }
        assert_eq!(gp.predict(&[q], 1)[0], batch[0]);
    }
}
