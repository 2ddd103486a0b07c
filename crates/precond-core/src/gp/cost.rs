//! What a fit will cost, known before anything is allocated: peak memory and work of the exact
//! GP ([`exact_fit_cost`]) and of the sparse GP ([`sparse_fit_cost`]), from the problem's sizes.
//!
//! The memory figure is what the fit's buffers allocate at their peak; it is the one to hold
//! against a budget. The exact GP's dominant buffers are `n × n` matrices of 8-byte floats:
//!
//! - while hyperparameters are optimised, the objective holds three (`K`/`L`/`K⁻¹`, `G`, `L⁻¹`;
//!   `lml::Objective`), so a homoscedastic fit peaks at `3 n²`;
//! - a heteroscedastic fit keeps the homoscedastic model's `L⁻¹` and the best round's `L⁻¹` while
//!   the next round's objective runs: `5 n²` (`4 n²` with a single round).
//!
//! Measured peak RSS growth of release fits (d = 6, 2 cores) against these estimates: n = 2000,
//! 84 MB vs 96 MB homoscedastic and 197 MB vs 160 MB heteroscedastic; n = 3000, 169 MB vs 216 MB
//! and 315 MB vs 360 MB; in the tests' child processes (3 iterations), n = 1500 homoscedastic
//! 53 MB vs 54 MB, n = 2500 homoscedastic 121 MB vs 151 MB and heteroscedastic 222 MB vs 251 MB.
//! The resident figure can be lower (the lower-triangular buffers start
//! zeroed and their upper halves are never touched) or a little higher (the allocator's
//! fragmentation between matrices of about 32 MB).
//!
//! The sparse GP holds no `n × n` nor `n × m` matrix: O(n d) for copies of the data and a few
//! vectors, about forty `m × m` matrices, the greedy selection's `candidates × m` factor and
//! `m × 1024`-sized chunks.
//!
//! The work figure counts floating-point operations of a typical fit (the number of L-BFGS
//! evaluations varies with the data; the counts used are typical of the benchmark's data and
//! right within a factor of about 2) and converts them to seconds at [`ASSUMED_FLOPS`], the
//! sustained rate of these kernels measured on the 2-core reference machine.

use super::NoiseMode;
use super::sparse::SparseParams;

/// Sustained floating-point rate assumed by the time estimates: 60 GFLOP/s (measured on the
/// 2-core reference machine: an exact LML evaluation at n = 3000 and a sparse bound evaluation at
/// n = 100 000, m = 256 both run at 60–90 GFLOP/s).
pub const ASSUMED_FLOPS: f64 = 60e9;

/// Most bytes faer's matrix product reserves on a thread, once, the first time the thread runs
/// a product: its packing workspace, twice the L3 cache size it blocks for, which the vendored
/// private-gemm-x86 caps at 32 MiB whatever the system reports (`MAX_CACHE_BYTES` in
/// `vendor/private-gemm-x86/src/cache.rs`; unpatched, it reserved twice the whole machine's L3:
/// 960 MiB on a VM reporting 480 MiB). Only the part a product packs becomes resident, so it is
/// mostly address space and is not part of [`FitCost::peak_bytes`]; its total is bounded by the
/// threads that run products: the work gate's searches, fits and evaluations, rayon's one
/// thread per core.
pub const PRODUCT_WORKSPACE_BYTES: usize = 64 << 20;

/// Bytes of one matrix entry.
const F64: f64 = 8.0;

/// A fit's estimated cost.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitCost {
    /// Peak bytes allocated by the fit's own buffers (not counting the caller's copy of the data).
    pub peak_bytes: f64,
    /// Floating-point operations of a typical fit.
    pub flops: f64,
    /// `flops` at [`ASSUMED_FLOPS`], seconds.
    pub seconds: f64,
}

impl FitCost {
    fn new(peak_bytes: f64, flops: f64) -> Self {
        FitCost {
            peak_bytes,
            flops,
            seconds: flops / ASSUMED_FLOPS,
        }
    }

    /// `k` such fits one after the other: the work adds up, the peak does not.
    pub fn times(self, k: usize) -> Self {
        Self::new(self.peak_bytes, self.flops * k as f64)
    }

    /// The same work with `k` fits held in memory at once (run concurrently): the peak is
    /// `k` times one fit's.
    pub fn alongside(self, k: usize) -> Self {
        Self::new(self.peak_bytes * k.max(1) as f64, self.flops)
    }

    /// This fit, then `other`.
    pub fn then(self, other: Self) -> Self {
        Self::new(
            self.peak_bytes.max(other.peak_bytes),
            self.flops + other.flops,
        )
    }
}

/// Flops of one exact LML-and-gradient evaluation: Cholesky (`n³/3`), triangular inverse
/// (`n³/3`), `L⁻ᵀL⁻¹` (`n³/3`), kernel and gradient sums over the triangle.
fn exact_eval_flops(n: f64, d: f64) -> f64 {
    n * n * n + n * n * (2.0 * d + 15.0)
}

/// Estimated peak memory and work of [`GpModel::fit`](super::GpModel::fit) on `n` points of
/// dimension `d` with `restarts` extra starts and the given noise mode (heteroscedastic with
/// `hetero_rounds` rounds at most; it falls back to homoscedastic below 8 points).
///
/// Typical full-data evaluation counts: 35 for the homoscedastic optimum plus 5 per restart
/// (restarts are screened on a 512-point subset; the best is refined on all data), and 40 more
/// per heteroscedastic round.
pub fn exact_fit_cost(
    n: usize,
    d: usize,
    restarts: usize,
    noise: NoiseMode,
    hetero_rounds: usize,
) -> FitCost {
    let (nf, df) = (n as f64, d as f64);
    let hetero = noise == NoiseMode::Heteroscedastic && n >= 8;
    let matrices = match (hetero, hetero_rounds) {
        (false, _) => 3.0,
        (true, 0 | 1) => 4.0,
        (true, _) => 5.0,
    };
    // n × n matrices, plus O(n d) copies of the data and a few n-vectors.
    let peak = F64 * (matrices * nf * nf + nf * (3.0 * df + 16.0));
    let screen = 512f64.min(nf);
    let mut evals_full = 35.0 + 5.0 * restarts as f64;
    if hetero {
        evals_full += 40.0 * hetero_rounds.max(1) as f64;
    }
    let flops = evals_full * exact_eval_flops(nf, df)
        + 30.0 * restarts as f64 * exact_eval_flops(screen, df);
    FitCost::new(peak, flops)
}

/// Flops of one sparse bound-and-gradient evaluation: `2 n m²` multiply-adds in the two passes,
/// kernels with their derivatives (`n m (d + 30)` twice), and the `m × m` algebra (about `12 m³`).
fn sparse_eval_flops(n: f64, m: f64, d: f64) -> f64 {
    4.0 * n * m * m + 2.0 * n * m * (d + 30.0) + 12.0 * m * m * m
}

/// Estimated peak memory and work of [`SparseGp::fit`](super::SparseGp::fit) on `n` points of
/// dimension `d` with the settings `p` (`p.inducing_points` is `m`, capped by `n`;
/// `p.gp.restarts`, the noise mode, the rounds, the candidate pool and the presolve subset are
/// taken from it).
///
/// Typical evaluation counts: 60 per inducing round and 35 per restart (on the screening
/// subset) on the points fitted (the presolve subset when it engages); per heteroscedastic
/// round 40 for the main GP and 40 for the noise GP; with the presolve, 30 more on all data
/// for the refinement (and 10 for the noise GP).
///
/// A full-rank fit (`n ≤ p.full_rank_up_to`) is the exact GP's fit ([`exact_fit_cost`]) and its
/// conversion: two greedy selections over all `n` points (`n³` each, an `n × n` factor) and two
/// sparse cores with `m = n` (`K_mm`'s factor, `AAᵀ` and `B`'s factor, about `2 n³` each); the
/// exact GP's buffers are freed before the conversion, so the peak is the larger of the two.
pub fn sparse_fit_cost(n: usize, d: usize, p: &SparseParams) -> FitCost {
    let (nf, df) = (n as f64, d as f64);
    if n <= p.full_rank_up_to {
        let exact = exact_fit_cost(n, d, p.gp.restarts, p.gp.noise, p.gp.hetero_rounds);
        let convert_peak = F64 * (4.0 * nf * nf + nf * (2.0 * df + 10.0));
        return FitCost::new(
            exact.peak_bytes.max(convert_peak),
            exact.flops + 6.0 * nf * nf * nf,
        );
    }
    let m = p.inducing_points.min(n).max(1) as f64;
    let mn = p.noise_inducing_points.min(n).max(1) as f64;
    let pool = p.selection_candidates.max(4 * p.inducing_points).min(n) as f64;
    let presolve = p.presolve_subset > 0 && n > 2 * p.presolve_subset;
    let n_fit = if presolve {
        p.presolve_subset as f64
    } else {
        nf
    };
    let screen = if p.screen_subset > 0 {
        (p.screen_subset as f64).min(n_fit)
    } else {
        n_fit
    };
    let hetero = p.gp.noise == NoiseMode::Heteroscedastic && n >= p.gp.hetero_min_points;
    let rounds = p.inducing_rounds as f64;
    let mut flops = 60.0 * rounds * sparse_eval_flops(n_fit, m, df)
        + 35.0 * p.gp.restarts as f64 * sparse_eval_flops(screen, m, df)
        + rounds * pool * m * m;
    if hetero {
        flops += p.gp.hetero_rounds as f64
            * (40.0 * sparse_eval_flops(n_fit, m, df) + 40.0 * sparse_eval_flops(n_fit, mn, df));
    }
    if presolve {
        flops += 30.0 * sparse_eval_flops(nf, m, df);
        if hetero {
            flops += 10.0 * sparse_eval_flops(nf, mn, df);
        }
    }
    // O(n) vectors and copies of the data; m × m matrices (about 30 in an evaluation, 8 partial
    // sums of the chunk groups); the selection's factor; chunk buffers of two threads.
    let chunk = ((1usize << 17) as f64 / m).clamp(64.0, 4096.0);
    let peak = F64
        * (nf * (2.0 * df + 10.0)
            + 38.0 * m * m
            + pool * (m + df)
            + 2.0 * 4.0 * m * chunk
            + n_fit.min(nf) * (df + 2.0));
    FitCost::new(peak, flops)
}

/// The process's peak resident memory so far, bytes (`VmHWM` of `/proc/self/status`), against
/// which the estimates are measured; `None` where that is not readable (not Linux).
pub fn peak_rss_bytes() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb = line.split_whitespace().nth(1)?.parse::<f64>().ok()?;
    Some(kb * 1024.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::{GpModel, GpParams, SparseGp};

    /// Low-rank settings with `m` inducing points at every size.
    fn sparse(m: usize) -> SparseParams {
        SparseParams {
            inducing_points: m,
            full_rank_up_to: 0,
            ..SparseParams::default()
        }
    }

    #[test]
    fn estimates_grow_with_the_problem_and_scale_as_they_should() {
        let het = NoiseMode::Heteroscedastic;
        let mut last = exact_fit_cost(100, 6, 2, het, 4);
        for n in [200, 1000, 4000, 50_000] {
            let c = exact_fit_cost(n, 6, 2, het, 4);
            assert!(c.peak_bytes > last.peak_bytes && c.flops > last.flops && c.seconds > 0.0);
            last = c;
        }
        // The exact GP's memory is n²: doubling n quadruples it (asymptotically); n = 50 000
        // needs 100 GB, which is why it aborted.
        let (a, b) = (
            exact_fit_cost(20_000, 6, 2, het, 4),
            exact_fit_cost(40_000, 6, 2, het, 4),
        );
        assert!((b.peak_bytes / a.peak_bytes - 4.0).abs() < 0.01);
        assert!((b.flops / a.flops - 8.0).abs() < 0.1);
        assert!(exact_fit_cost(50_000, 6, 2, het, 4).peak_bytes > 9e10);
        assert!(
            exact_fit_cost(4000, 6, 2, NoiseMode::Homoscedastic, 4).peak_bytes
                < exact_fit_cost(4000, 6, 2, het, 4).peak_bytes
        );
        // The sparse GP's memory is linear in n and its work is n m² (with the presolve off
        // and the data term dominant).
        let no_presolve = |m| SparseParams {
            presolve_subset: 0,
            ..sparse(m)
        };
        let (a, b) = (
            sparse_fit_cost(1_000_000, 6, &no_presolve(256)),
            sparse_fit_cost(2_000_000, 6, &no_presolve(256)),
        );
        assert!((b.flops / a.flops - 2.0).abs() < 0.05);
        assert!(b.peak_bytes / a.peak_bytes > 1.8 && b.peak_bytes / a.peak_bytes < 2.0);
        let c = sparse_fit_cost(1_000_000, 6, &no_presolve(512));
        // n m² dominates; the kernels' n m (d + 30) is linear in m.
        let r = c.flops / a.flops;
        assert!((3.0..4.0).contains(&r), "{r}");
        let mut last = sparse_fit_cost(1000, 6, &sparse(256));
        for n in [2000, 10_000, 100_000, 1_000_000] {
            let c = sparse_fit_cost(n, 6, &sparse(256));
            assert!(c.peak_bytes > last.peak_bytes && c.flops > last.flops);
            last = c;
        }
        // At n = 100 000 the sparse fit needs well under 1 GiB; the exact one 400 GB.
        assert!(sparse_fit_cost(100_000, 6, &sparse(256)).peak_bytes < 2e8);
        assert!(exact_fit_cost(100_000, 6, 2, het, 4).peak_bytes > 3e11);
    }

    #[test]
    fn a_full_rank_sparse_fit_costs_the_exact_fit_and_a_little_more() {
        let full = SparseParams::default();
        let n = full.full_rank_up_to;
        let (sparse_cost, exact) = (
            sparse_fit_cost(n, 6, &full),
            exact_fit_cost(n, 6, 2, NoiseMode::Heteroscedastic, 4),
        );
        assert_eq!(sparse_cost.peak_bytes, exact.peak_bytes);
        let extra = sparse_cost.flops / exact.flops - 1.0;
        assert!((0.0..0.1).contains(&extra), "{extra}");
        // One point more and the fit is low rank again (m = 256), and cheaper.
        let low = sparse_fit_cost(n + 1, 6, &full);
        assert!(low.peak_bytes < exact.peak_bytes && low.flops < exact.flops);
        // Off, the same size is a low-rank fit.
        let off = SparseParams {
            full_rank_up_to: 0,
            ..SparseParams::default()
        };
        assert!(sparse_fit_cost(n, 6, &off).peak_bytes < exact.peak_bytes);
    }

    /// Peak RSS growth (bytes) of a fit run alone in a child process: this test binary again,
    /// running only [`rss_child`]. `None` where `/proc/self/status` is unavailable (not Linux);
    /// where it is, a child that does not report is a failure.
    fn measured_growth(spec: &str) -> Option<f64> {
        std::fs::read_to_string("/proc/self/status").ok()?;
        let measured = child_growth(spec);
        assert!(
            measured.is_some(),
            "the child process did not report for {spec}"
        );
        measured
    }

    fn child_growth(spec: &str) -> Option<f64> {
        let out = std::process::Command::new(std::env::current_exe().ok()?)
            .args([
                "--exact",
                "gp::cost::tests::rss_child",
                "--ignored",
                "--nocapture",
                "--test-threads=1",
            ])
            .env("PRECOND_RSS_CHILD", spec)
            .output()
            .ok()?;
        let text = String::from_utf8_lossy(&out.stdout);
        let at = text.find("RSS_GROWTH=")? + "RSS_GROWTH=".len();
        let value = text[at..].split_whitespace().next()?;
        Some(
            value
                .parse()
                .unwrap_or_else(|e| panic!("bad child output {value:?}: {e}")),
        )
    }

    fn vm_hwm() -> f64 {
        peak_rss_bytes().unwrap_or(0.0)
    }

    /// The child side of [`measured_growth`]: fits the model named by `PRECOND_RSS_CHILD`
    /// (`exact,n,homo|hetero` or `sparse,n,m`) with few iterations (the peak does not depend on
    /// how many there are) and prints its peak RSS growth. Does nothing when run directly.
    #[test]
    #[ignore = "run by the memory estimate tests in a child process"]
    fn rss_child() {
        let Ok(spec) = std::env::var("PRECOND_RSS_CHILD") else {
            return;
        };
        let parts: Vec<&str> = spec.split(',').collect();
        let n: usize = parts[1].parse().unwrap();
        let (x, y) = crate::gp::synthetic::bench_data(n, 6, 0);
        let gp = GpParams {
            noise: if parts.get(2) == Some(&"hetero") {
                NoiseMode::Heteroscedastic
            } else {
                NoiseMode::Homoscedastic
            },
            restarts: 0,
            max_iterations: 3,
            hetero_rounds: 2,
            hetero_tolerance: 0.0,
            ..GpParams::default()
        };
        let before = vm_hwm();
        if parts[0] == "exact" {
            std::hint::black_box(GpModel::fit(&x, &y, &gp.check().unwrap()).unwrap());
        } else {
            let p = SparseParams {
                gp: GpParams {
                    noise: NoiseMode::Homoscedastic,
                    ..gp
                },
                inducing_points: parts[2].parse().unwrap(),
                inducing_rounds: 1,
                ..SparseParams::default()
            };
            std::hint::black_box(SparseGp::fit(&x, &y, &p.check().unwrap()).unwrap());
        }
        println!("RSS_GROWTH={}", vm_hwm() - before);
    }

    #[test]
    fn exact_memory_estimate_is_within_a_factor_of_1_5_of_the_measured_peak() {
        for (n, mode, noise) in [
            (1500, "homo", NoiseMode::Homoscedastic),
            (2500, "hetero", NoiseMode::Heteroscedastic),
        ] {
            let Some(measured) = measured_growth(&format!("exact,{n},{mode}")) else {
                eprintln!("peak RSS not measurable here; skipped");
                return;
            };
            let est = exact_fit_cost(n, 6, 0, noise, 2).peak_bytes;
            let ratio = est / measured;
            eprintln!("exact n = {n} {mode}: estimate {est:.3e} B, measured {measured:.3e} B");
            assert!(
                (1.0 / 1.5..=1.5).contains(&ratio),
                "n = {n} {mode}: estimate {est:.3e} B vs measured {measured:.3e} B"
            );
        }
    }

    #[test]
    fn sparse_memory_estimate_bounds_the_measured_peak() {
        // 40 000 points (the presolve engages), m = 128: the growth is tens of MB, so the
        // comparison is looser than for the exact GP (thread stacks and allocator arenas are a
        // visible share), but the estimate must not be exceeded by much nor be far too high.
        let Some(measured) = measured_growth("sparse,40000,128") else {
            return;
        };
        let est = sparse_fit_cost(40_000, 6, &sparse(128)).peak_bytes;
        let ratio = est / measured;
        eprintln!("sparse n = 40000, m = 128: estimate {est:.3e} B, measured {measured:.3e} B");
        assert!(
            (0.7..=3.0).contains(&ratio),
            "estimate {est:.3e} B vs measured {measured:.3e} B"
        );
    }
}
