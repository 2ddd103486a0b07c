//! `precond bench gp`: fit and prediction speed of the GP, side by side with scikit-learn.
//!
//! For each training-set size `n` (inputs uniform in the unit box of dimension `d`, a smooth
//! target plus input-dependent noise, all seeded) it measures:
//! - the homoscedastic and heteroscedastic fit times (with the stated number of restarts) and LMLs;
//! - single-point prediction latency (median of repeated calls, μ and σ);
//! - batched prediction throughput (μ and σ for a batch of query points, best of three);
//! - when `python3 -c "import sklearn"` works and `n ≤ sklearn_max_n`: the same for scikit-learn's
//!   `GaussianProcessRegressor` with `ConstantKernel * Matern(ν, ARD) + WhiteKernel` (ν = 2.5
//!   unless `--kernel` says otherwise), the same bounds, `n_restarts_optimizer = restarts`,
//!   `alpha = 0`, on the same data, in the same run, and the ratios.
//!
//! The table goes to stdout; the figures are returned as a [`GpBenchReport`].

use std::io::Write;
use std::process::Command;
use std::time::Instant;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use precond_core::gp::{GpError, GpModel, GpParams, Kernel, NoiseMode};

/// What to benchmark.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct GpBenchOptions {
    /// Training-set sizes. Default `[500, 1000, 2000, 4000]`.
    pub sizes: Vec<usize>,
    /// Input dimension. Default 6.
    pub dim: usize,
    /// Optimiser restarts beyond the first, for us and for scikit-learn. Default 2.
    pub restarts: usize,
    /// Query points per batched prediction. Default 2000.
    pub batch: usize,
    /// Repetitions for the single-point latency (median reported). Default 200.
    pub single_reps: usize,
    /// Whether to run scikit-learn (if importable). Default true.
    pub sklearn: bool,
    /// Largest `n` for which scikit-learn is run (its fit is O(n³) per evaluation with a slow
    /// gradient; n = 4000 with restarts takes many minutes). Default 2000.
    pub sklearn_max_n: usize,
    /// Python interpreter. Default `python3`.
    pub python: String,
    /// Seed of the data and of the fits. Default 0.
    pub seed: u64,
    /// The kernel, ours and scikit-learn's (`Matern(nu=…)`). Default [`Kernel::Matern52`].
    pub kernel: Kernel,
}

impl Default for GpBenchOptions {
    fn default() -> Self {
        GpBenchOptions {
            sizes: vec![500, 1000, 2000, 4000],
            dim: 6,
            restarts: 2,
            batch: 2000,
            single_reps: 200,
            sklearn: true,
            sklearn_max_n: 2000,
            python: "python3".into(),
            seed: 0,
            kernel: Kernel::Matern52,
        }
    }
}

impl GpBenchOptions {
    /// The default options without n = 4000 (a quick run).
    pub fn quick() -> Self {
        GpBenchOptions {
            sizes: vec![500, 1000, 2000],
            ..GpBenchOptions::default()
        }
    }
}

/// scikit-learn's figures for one size.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SklearnFigures {
    /// Fit time in seconds.
    pub fit_seconds: f64,
    /// LML of the fitted model.
    pub lml: f64,
    /// Batched μ+σ throughput, points per second.
    pub batch_points_per_second: f64,
    /// Single-point μ+σ latency, milliseconds (median).
    pub single_ms: f64,
}

/// Our figures (and scikit-learn's, when run) for one training-set size.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct GpBenchRow {
    /// Training points.
    pub n: usize,
    /// Homoscedastic fit time, seconds.
    pub homo_fit_seconds: f64,
    /// Homoscedastic LML.
    pub homo_lml: f64,
    /// Heteroscedastic fit time, seconds.
    pub hetero_fit_seconds: f64,
    /// Heteroscedastic LML.
    pub hetero_lml: f64,
    /// Heteroscedastic rounds kept.
    pub hetero_rounds: usize,
    /// Single-point μ+σ latency of the homoscedastic model, milliseconds (median).
    pub single_ms: f64,
    /// Single-point latency of the heteroscedastic model, milliseconds (median).
    pub hetero_single_ms: f64,
    /// Batched μ+σ throughput of the homoscedastic model, points per second.
    pub batch_points_per_second: f64,
    /// Batched throughput of the heteroscedastic model, points per second.
    pub hetero_batch_points_per_second: f64,
    /// scikit-learn's figures, when it ran.
    pub sklearn: Option<SklearnFigures>,
}

/// Everything [`run`] measured.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct GpBenchReport {
    /// The options used.
    pub options: GpBenchOptions,
    /// One row per size.
    pub rows: Vec<GpBenchRow>,
    /// Why scikit-learn did not run, if it did not.
    pub sklearn_note: Option<String>,
}

pub use precond_core::gp::synthetic::bench_data;

fn time<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t = Instant::now();
    let v = f();
    (v, t.elapsed().as_secs_f64())
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn single_latency_ms(model: &GpModel, q: &DMatrix<f64>, reps: usize) -> f64 {
    let reps = reps.max(1);
    let samples: Vec<f64> = (0..reps)
        .map(|i| {
            let row = DMatrix::from_fn(1, q.ncols(), |_, j| q[(i % q.nrows(), j)]);
            let (p, t) = time(|| model.predict(&row));
            std::hint::black_box(p);
            t * 1e3
        })
        .collect();
    median(samples)
}

fn batch_throughput(model: &GpModel, q: &DMatrix<f64>) -> f64 {
    let best = (0..3)
        .map(|_| time(|| std::hint::black_box(model.predict(q))).1)
        .fold(f64::INFINITY, f64::min);
    q.nrows() as f64 / best
}

/// The scikit-learn side: reads a JSON job from the file named by `argv[1]`, prints a JSON result.
const SKLEARN_SCRIPT: &str = r#"
import json, sys, time, warnings
import numpy as np
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel
warnings.filterwarnings("ignore")
job = json.load(open(sys.argv[1]))
x = np.array(job["x"]); y = np.array(job["y"]); q = np.array(job["q"]); d = x.shape[1]
v = float(np.mean(y ** 2))
k = ConstantKernel(v, tuple(job["signal_bounds"])) * Matern([0.5] * d, tuple(job["ls_bounds"]), nu=job["nu"]) \
    + WhiteKernel(0.1 * v, tuple(job["noise_bounds"]))
gp = GaussianProcessRegressor(k, alpha=0.0, normalize_y=False, n_restarts_optimizer=job["restarts"], random_state=job["seed"])
t = time.perf_counter(); gp.fit(x, y); fit = time.perf_counter() - t
best = min((lambda t0: (gp.predict(q, return_std=True), time.perf_counter() - t0)[1])(time.perf_counter()) for _ in range(3))
lat = []
for i in range(job["single_reps"]):
    row = q[i % len(q)][None, :]
    t0 = time.perf_counter(); gp.predict(row, return_std=True); lat.append(time.perf_counter() - t0)
print(json.dumps({"fit_seconds": fit, "lml": float(gp.log_marginal_likelihood_value_),
                  "batch_points_per_second": len(q) / best, "single_ms": 1e3 * float(np.median(lat))}))
"#;

fn sklearn_available(python: &str) -> Result<(), String> {
    match Command::new(python).args(["-c", "import sklearn"]).output() {
        Ok(o) if o.status.success() => Ok(()),
        Ok(o) => Err(format!(
            "`{python} -c \"import sklearn\"` failed: {}",
            String::from_utf8_lossy(&o.stderr).trim()
        )),
        Err(e) => Err(format!("cannot run `{python}`: {e}")),
    }
}

fn run_sklearn(
    opts: &GpBenchOptions,
    x: &DMatrix<f64>,
    y: &DVector<f64>,
    q: &DMatrix<f64>,
) -> Result<SklearnFigures, String> {
    let rows = |m: &DMatrix<f64>| -> Vec<Vec<f64>> {
        (0..m.nrows())
            .map(|i| m.row(i).iter().copied().collect())
            .collect()
    };
    let p = GpParams::default();
    let job = serde_json_lite(&[
        ("x", JsonVal::Rows(rows(x))),
        ("y", JsonVal::Vec(y.iter().copied().collect())),
        ("q", JsonVal::Rows(rows(q))),
        ("restarts", JsonVal::Num(opts.restarts as f64)),
        (
            "nu",
            JsonVal::Num(match opts.kernel {
                Kernel::Matern12 => 0.5,
                Kernel::Matern32 => 1.5,
                Kernel::Matern52 => 2.5,
            }),
        ),
        ("seed", JsonVal::Num((opts.seed % 1_000_000) as f64)),
        (
            "single_reps",
            JsonVal::Num(opts.single_reps.clamp(1, 200) as f64),
        ),
        (
            "ls_bounds",
            JsonVal::Vec(vec![p.bounds.length_scale.0, p.bounds.length_scale.1]),
        ),
        (
            "signal_bounds",
            JsonVal::Vec(vec![p.bounds.signal_variance.0, p.bounds.signal_variance.1]),
        ),
        (
            "noise_bounds",
            JsonVal::Vec(vec![p.bounds.noise_variance.0, p.bounds.noise_variance.1]),
        ),
    ]);
    let path = std::env::temp_dir().join(format!(
        "precond-bench-gp-{}-{}.json",
        std::process::id(),
        x.nrows()
    ));
    std::fs::File::create(&path)
        .and_then(|mut f| f.write_all(job.as_bytes()))
        .map_err(|e| format!("writing {}: {e}", path.display()))?;
    let out = Command::new(&opts.python)
        .arg("-c")
        .arg(SKLEARN_SCRIPT)
        .arg(&path)
        .output();
    let _ = std::fs::remove_file(&path);
    let out = out.map_err(|e| format!("running {}: {e}", opts.python))?;
    if !out.status.success() {
        return Err(format!(
            "scikit-learn run failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let field = |name: &str| -> Result<f64, String> {
        let key = format!("\"{name}\": ");
        let start = text
            .find(&key)
            .ok_or_else(|| format!("no `{name}` in scikit-learn output: {text}"))?
            + key.len();
        let rest = &text[start..];
        let end = rest.find([',', '}']).unwrap_or(rest.len());
        rest[..end]
            .trim()
            .parse()
            .map_err(|e| format!("bad `{name}` in scikit-learn output: {e}"))
    };
    Ok(SklearnFigures {
        fit_seconds: field("fit_seconds")?,
        lml: field("lml")?,
        batch_points_per_second: field("batch_points_per_second")?,
        single_ms: field("single_ms")?,
    })
}

/// Minimal JSON writer for the job file (the library does not depend on serde_json).
enum JsonVal {
    Num(f64),
    Vec(Vec<f64>),
    Rows(Vec<Vec<f64>>),
}

fn serde_json_lite(fields: &[(&str, JsonVal)]) -> String {
    let vec = |v: &[f64]| {
        format!(
            "[{}]",
            v.iter()
                .map(|x| format!("{x:e}"))
                .collect::<Vec<_>>()
                .join(",")
        )
    };
    let body: Vec<String> = fields
        .iter()
        .map(|(k, v)| {
            let val = match v {
                JsonVal::Num(x) => format!("{x}"),
                JsonVal::Vec(v) => vec(v),
                JsonVal::Rows(r) => format!(
                    "[{}]",
                    r.iter().map(|row| vec(row)).collect::<Vec<_>>().join(",")
                ),
            };
            format!("\"{k}\":{val}")
        })
        .collect();
    format!("{{{}}}", body.join(","))
}

/// Runs the benchmark, printing a table to stdout as it goes, and returns the figures.
///
/// # Errors
/// A [`GpError`] if one of our fits fails. scikit-learn failures do not fail the run; they are
/// reported in [`GpBenchReport::sklearn_note`].
pub fn run(opts: &GpBenchOptions) -> Result<GpBenchReport, GpError> {
    let sk = if !opts.sklearn {
        Err("scikit-learn comparison disabled".to_string())
    } else {
        sklearn_available(&opts.python)
    };
    let mut note = sk.as_ref().err().cloned();
    println!(
        "GP benchmark: d = {}, {} ARD, restarts = {} (same for scikit-learn), batch = {} points, {} thread(s)",
        opts.dim,
        opts.kernel,
        opts.restarts,
        opts.batch,
        std::thread::available_parallelism().map_or(1, |p| p.get())
    );
    if let Some(n) = &note {
        println!("scikit-learn: not run ({n})");
    }
    println!(
        "{:>6} | {:>9} {:>11} | {:>9} {:>11} {:>2} | {:>9} {:>11} | {:>9} {:>11} | {:>9} {:>11} {:>11} {:>9} | {:>7} {:>7}",
        "n",
        "fit homo",
        "LML homo",
        "fit het",
        "LML het",
        "rd",
        "1pt ms",
        "batch pt/s",
        "het 1pt",
        "het pt/s",
        "sk fit",
        "sk LML",
        "sk pt/s",
        "sk 1pt",
        "fit x",
        "batch x"
    );
    let mut rows = Vec::new();
    for &n in &opts.sizes {
        let (x, y) = bench_data(n, opts.dim, opts.seed);
        let (q, _) = bench_data(opts.batch.max(1), opts.dim, opts.seed.wrapping_add(1));
        let base = GpParams {
            kernel: opts.kernel,
            restarts: opts.restarts,
            seed: opts.seed,
            ..GpParams::default()
        };
        let homo_p = GpParams {
            noise: NoiseMode::Homoscedastic,
            ..base.clone()
        }
        .check()?;
        let het_p = base.check()?;
        let (homo, homo_t) = time(|| GpModel::fit(&x, &y, &homo_p));
        let homo = homo?;
        let (het, het_t) = time(|| GpModel::fit(&x, &y, &het_p));
        let het = het?;
        let row = GpBenchRow {
            n,
            homo_fit_seconds: homo_t,
            homo_lml: homo.log_marginal_likelihood(),
            hetero_fit_seconds: het_t,
            hetero_lml: het.log_marginal_likelihood(),
            hetero_rounds: het.noise_summary().map_or(0, |s| s.rounds),
            single_ms: single_latency_ms(&homo, &q, opts.single_reps),
            hetero_single_ms: single_latency_ms(&het, &q, opts.single_reps),
            batch_points_per_second: batch_throughput(&homo, &q),
            hetero_batch_points_per_second: batch_throughput(&het, &q),
            sklearn: if sk.is_ok() && n <= opts.sklearn_max_n {
                match run_sklearn(opts, &x, &y, &q) {
                    Ok(f) => Some(f),
                    Err(e) => {
                        note = Some(e);
                        None
                    }
                }
            } else {
                None
            },
        };
        let sk_cols = match &row.sklearn {
            Some(s) => format!(
                "{:>9.3} {:>11.3} {:>11.0} {:>9.3} | {:>6.1}x {:>6.1}x",
                s.fit_seconds,
                s.lml,
                s.batch_points_per_second,
                s.single_ms,
                s.fit_seconds / row.homo_fit_seconds,
                row.batch_points_per_second / s.batch_points_per_second
            ),
            None => format!(
                "{:>9} {:>11} {:>11} {:>9} | {:>7} {:>7}",
                "-", "-", "-", "-", "-", "-"
            ),
        };
        println!(
            "{:>6} | {:>9.3} {:>11.3} | {:>9.3} {:>11.3} {:>2} | {:>9.4} {:>11.0} | {:>9.4} {:>11.0} | {}",
            n,
            row.homo_fit_seconds,
            row.homo_lml,
            row.hetero_fit_seconds,
            row.hetero_lml,
            row.hetero_rounds,
            row.single_ms,
            row.batch_points_per_second,
            row.hetero_single_ms,
            row.hetero_batch_points_per_second,
            sk_cols
        );
        rows.push(row);
    }
    println!(
        "fit x = scikit-learn fit time / our homoscedastic fit time; batch x = our / scikit-learn batched throughput"
    );
    if let Some(n) = &note
        && sk.is_ok()
    {
        println!("scikit-learn note: {n}");
    }
    Ok(GpBenchReport {
        options: opts.clone(),
        rows,
        sklearn_note: note,
    })
}
