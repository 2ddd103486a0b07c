//! `precond bench gp --sparse`: the sparse GP at sizes the exact GP cannot reach, beside the
//! exact GP where it fits and beside a reference sparse GP (GPyTorch's SGPR) in the same run.
//!
//! For each input dimension and training-set size (the seeded [`bench_data`] of `bench gp`;
//! held-out points from another seed of the same distribution, noise included) and each
//! estimator, one child process (this binary again, `bench gp --child SPEC`) fits and measures,
//! so that each peak RSS is that fit's alone:
//! - fit time and the bound (sparse) or LML (exact), natural log, whole data set;
//! - peak RSS of the child (`VmHWM`, data included);
//! - single-point μ+σ latency (median of repeated calls) and batched throughput (best of three);
//! - online update of a 50-point trajectory at fixed hyperparameters (median; sparse only);
//! - RMSE and mean negative log predictive density (NLL) of the held-out targets.
//!
//! The reference is GPyTorch's SGPR (`InducingPointKernel` over `ScaleKernel(MaternKernel(ν,
//! ARD))`, zero prior mean, Gaussian likelihood, float64, CPU, 2 threads), with the same `m`,
//! inducing points initialised at a seeded random subset of the training inputs and trained
//! (inducing locations included) with Adam, learning rate 0.1, as in GPyTorch's SGPR example,
//! with kernels evaluated eagerly so that GPyTorch solves by Woodbury identities.
//! It is installed by the benchmark into a venv under `target/` on first use (`pip install
//! gpytorch`, several GB with the CUDA libraries PyPI's torch wheel pulls in; only the CPU is
//! used).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use super::gp::bench_data;
use precond_core::gp::{GpModel, GpParams, Kernel, NoiseMode, SparseGp, SparseParams};

/// What to benchmark.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SparseBenchOptions {
    /// Training-set sizes. Default `[2000, 10000, 50000, 100000]`.
    pub sizes: Vec<usize>,
    /// Input dimensions. Default `[6, 21]`.
    pub dims: Vec<usize>,
    /// Inducing points (ours and the reference's). Default 256.
    pub inducing: usize,
    /// Noise model of our sparse GP and of the exact GP. Default homoscedastic (the reference's).
    pub noise: NoiseMode,
    /// Optimiser restarts beyond the first (ours). Default 2.
    pub restarts: usize,
    /// Query points per batched prediction, and held-out points. Default 10 000.
    pub batch: usize,
    /// Repetitions for the single-point latency (median reported). Default 200.
    pub single_reps: usize,
    /// Largest `n` at which the exact GP is run. Default 4000.
    pub exact_max_n: usize,
    /// Whether to run the reference (GPyTorch SGPR). Default true.
    pub reference: bool,
    /// Largest `n` at which the reference is run. Default 100 000.
    pub reference_max_n: usize,
    /// Adam iterations of the reference. Default 100.
    pub reference_iterations: usize,
    /// Python interpreter that creates the reference's venv. Default `python3`.
    pub python: String,
    /// The venv of the reference. Default `target/venv-sgpr-reference`.
    pub venv: PathBuf,
    /// Seed of the data and of the fits. Default 0.
    pub seed: u64,
    /// The kernel (ours and the reference's). Default [`Kernel::Matern52`].
    pub kernel: Kernel,
}

impl Default for SparseBenchOptions {
    fn default() -> Self {
        SparseBenchOptions {
            sizes: vec![2000, 10_000, 50_000, 100_000],
            dims: vec![6, 21],
            inducing: 256,
            noise: NoiseMode::Homoscedastic,
            restarts: 2,
            batch: 10_000,
            single_reps: 200,
            exact_max_n: 4000,
            reference: true,
            reference_max_n: 100_000,
            reference_iterations: 100,
            python: "python3".into(),
            venv: PathBuf::from("target/venv-sgpr-reference"),
            seed: 0,
            kernel: Kernel::Matern52,
        }
    }
}

/// One estimator's figures at one size (one child process).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SparseBenchRow {
    /// `sparse`, `exact` or `gpytorch-sgpr`.
    pub estimator: String,
    /// Input dimension.
    pub d: usize,
    /// Training points.
    pub n: usize,
    /// Inducing points (0 for the exact GP).
    pub m: usize,
    /// Fit time, seconds.
    pub fit_seconds: f64,
    /// The sparse bound, or the exact LML (natural log, whole data set).
    pub objective: f64,
    /// Peak RSS of the process, bytes (`VmHWM`, or `ru_maxrss` for the reference).
    pub peak_rss_bytes: f64,
    /// Peak RSS before the fit (data generated, libraries loaded), bytes.
    pub base_rss_bytes: f64,
    /// Single-point μ+σ latency, milliseconds (median).
    pub single_ms: f64,
    /// Batched μ+σ throughput, points per second.
    pub batch_points_per_second: f64,
    /// Online update of a 50-point trajectory, milliseconds (median; sparse only).
    pub update_ms: Option<f64>,
    /// RMSE of the held-out targets.
    pub rmse: f64,
    /// Mean negative log predictive density of the held-out targets.
    pub nll: f64,
}

fn vm_hwm() -> f64 {
    precond_core::gp::cost::peak_rss_bytes().unwrap_or(f64::NAN)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// RMSE and mean Gaussian NLL of targets `y` under predictive means and variances.
fn scores(mean: &[f64], var: &[f64], y: &DVector<f64>) -> (f64, f64) {
    let n = y.len() as f64;
    let mut se = 0.0;
    let mut nll = 0.0;
    for ((m, v), t) in mean.iter().zip(var).zip(y.iter()) {
        let v = v.max(1e-300);
        se += (t - m) * (t - m);
        nll += 0.5 * ((2.0 * std::f64::consts::PI * v).ln() + (t - m) * (t - m) / v);
    }
    ((se / n).sqrt(), nll / n)
}

/// A child's job.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct ChildSpec {
    estimator: String,
    d: usize,
    n: usize,
    opts: SparseBenchOptions,
}

/// Anything that predicts.
trait Predictor {
    fn predict(&self, x: &DMatrix<f64>) -> precond_core::gp::Prediction;
}
impl Predictor for SparseGp {
    fn predict(&self, x: &DMatrix<f64>) -> precond_core::gp::Prediction {
        SparseGp::predict(self, x)
    }
}
impl Predictor for GpModel {
    fn predict(&self, x: &DMatrix<f64>) -> precond_core::gp::Prediction {
        GpModel::predict(self, x)
    }
}

fn timings(model: &dyn Predictor, q: &DMatrix<f64>, yq: &DVector<f64>, reps: usize) -> [f64; 4] {
    let single = median(
        (0..reps.max(1))
            .map(|i| {
                let row = q.rows(i % q.nrows(), 1).into_owned();
                let t = Instant::now();
                std::hint::black_box(model.predict(&row));
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect(),
    );
    let mut best = f64::INFINITY;
    let mut pred = None;
    for _ in 0..3 {
        let t = Instant::now();
        let p = model.predict(q);
        best = best.min(t.elapsed().as_secs_f64());
        pred = Some(p);
    }
    let pred = pred.unwrap_or_else(|| model.predict(q));
    let (rmse, nll) = scores(&pred.mean, &pred.variance(), yq);
    [single, q.nrows() as f64 / best, rmse, nll]
}

/// The child side: fits one estimator at one size and prints `ROW <json>`.
///
/// # Errors
/// A malformed spec or a failed fit.
pub fn run_child(spec: &str) -> Result<(), String> {
    let spec: ChildSpec = serde_json::from_str(spec).map_err(|e| format!("bad spec: {e}"))?;
    let o = &spec.opts;
    let (x, y) = bench_data(spec.n, spec.d, o.seed);
    let (q, yq) = bench_data(o.batch.max(1), spec.d, o.seed.wrapping_add(1));
    let gp = GpParams {
        noise: o.noise,
        kernel: o.kernel,
        restarts: o.restarts,
        seed: o.seed,
        ..GpParams::default()
    };
    let base = vm_hwm();
    let t = Instant::now();
    let row = match spec.estimator.as_str() {
        "sparse" => {
            let p = SparseParams {
                gp,
                inducing_points: o.inducing,
                ..SparseParams::default()
            }
            .check()
            .map_err(|e| e.to_string())?;
            let model = SparseGp::fit(&x, &y, &p).map_err(|e| e.to_string())?;
            let fit_seconds = t.elapsed().as_secs_f64();
            let peak = vm_hwm();
            let (xb, yb) = bench_data(50, spec.d, o.seed.wrapping_add(2));
            let update_ms = median(
                (0..20)
                    .map(|_| {
                        let mut m = model.clone();
                        let t = Instant::now();
                        let ok = m.update(&xb, &yb).is_ok();
                        let ms = t.elapsed().as_secs_f64() * 1e3;
                        if ok { ms } else { f64::NAN }
                    })
                    .collect(),
            );
            let [single_ms, batch, rmse, nll] = timings(&model, &q, &yq, o.single_reps);
            SparseBenchRow {
                estimator: spec.estimator.clone(),
                d: spec.d,
                n: spec.n,
                m: model.n_inducing(),
                fit_seconds,
                objective: model.bound(),
                peak_rss_bytes: peak,
                base_rss_bytes: base,
                single_ms,
                batch_points_per_second: batch,
                update_ms: Some(update_ms),
                rmse,
                nll,
            }
        }
        "exact" => {
            let model = GpModel::fit(&x, &y, &gp.check().map_err(|e| e.to_string())?)
                .map_err(|e| e.to_string())?;
            let fit_seconds = t.elapsed().as_secs_f64();
            let peak = vm_hwm();
            let [single_ms, batch, rmse, nll] = timings(&model, &q, &yq, o.single_reps);
            SparseBenchRow {
                estimator: spec.estimator.clone(),
                d: spec.d,
                n: spec.n,
                m: 0,
                fit_seconds,
                objective: model.log_marginal_likelihood(),
                peak_rss_bytes: peak,
                base_rss_bytes: base,
                single_ms,
                batch_points_per_second: batch,
                update_ms: None,
                rmse,
                nll,
            }
        }
        other => return Err(format!("unknown estimator {other}")),
    };
    println!(
        "ROW {}",
        serde_json::to_string(&row).map_err(|e| e.to_string())?
    );
    Ok(())
}

fn spawn_child(spec: &ChildSpec) -> Result<SparseBenchRow, String> {
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    let json = serde_json::to_string(spec).map_err(|e| e.to_string())?;
    let out = Command::new(exe)
        .args(["bench", "gp", "--child", &json])
        .output()
        .map_err(|e| format!("spawning the child: {e}"))?;
    read_row(&out, &format!("child failed ({})", out.status))
}

/// The row on the `ROW ` line of a child's or the reference's output; else the error `failed:`
/// what it wrote on stderr.
fn read_row(out: &std::process::Output, failed: &str) -> Result<SparseBenchRow, String> {
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find(|l| l.starts_with("ROW "))
        .ok_or_else(|| format!("{failed}: {}", String::from_utf8_lossy(&out.stderr).trim()))?;
    serde_json::from_str(&line[4..]).map_err(|e| e.to_string())
}

/// The reference's side: reads the job (`argv[1]`, JSON) and raw float64 files, prints `ROW`.
const GPYTORCH_SCRIPT: &str = r#"
import json, resource, sys, time, warnings
warnings.filterwarnings("ignore")
import numpy as np, torch, gpytorch
torch.set_default_dtype(torch.float64)
torch.set_num_threads(2)
# Evaluate kernels eagerly: InducingPointKernel then yields a LowRankRootLinearOperator, whose sum
# with the noise is solved by Woodbury (m × m) instead of by iterative methods on the n × n
# operator (about 10× faster per iteration at n = 2000).
gpytorch.settings.lazily_evaluate_kernels(False).__enter__()
job = json.load(open(sys.argv[1]))
n, d, nq, m = job["n"], job["d"], job["nq"], job["m"]
load = lambda k, shape: torch.from_numpy(np.fromfile(job[k], dtype="<f8").reshape(shape))
x, y, q, yq = load("x", (n, d)), load("y", (n,)), load("q", (nq, d)), load("yq", (nq,))
xb, yb = load("xb", (50, d)), load("yb", (50,))
torch.manual_seed(job["seed"])
z0 = x[torch.randperm(n)[:m]].clone()
class SGPR(gpytorch.models.ExactGP):
    def __init__(self, x, y, lik):
        super().__init__(x, y, lik)
        self.mean_module = gpytorch.means.ZeroMean()
        base = gpytorch.kernels.ScaleKernel(gpytorch.kernels.MaternKernel(nu=job["nu"], ard_num_dims=d))
        self.covar_module = gpytorch.kernels.InducingPointKernel(base, inducing_points=z0, likelihood=lik)
    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))
base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
t0 = time.perf_counter()
lik = gpytorch.likelihoods.GaussianLikelihood()
model = SGPR(x, y, lik)
model.train(); lik.train()
opt = torch.optim.Adam(model.parameters(), lr=0.1)
mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, model)
for i in range(job["iterations"]):
    opt.zero_grad()
    loss = -mll(model(x), y)
    loss.backward()
    opt.step()
model.eval(); lik.eval()
with torch.no_grad():
    model.train(); lik.train()
    bound = float(mll(model(x), y)) * n
    model.eval(); lik.eval()
fit = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
def predict(a):
    with torch.no_grad(), gpytorch.settings.fast_pred_var():
        p = lik(model(a))
        return p.mean, p.variance
predict(q[:10])
best = float("inf")
for _ in range(3):
    t = time.perf_counter(); mu, var = predict(q); best = min(best, time.perf_counter() - t)
lat = []
for i in range(job["single_reps"]):
    row = q[i % nq][None, :]
    t = time.perf_counter(); predict(row); lat.append(time.perf_counter() - t)
var = var.clamp_min(1e-300)
rmse = float(((mu - yq) ** 2).mean().sqrt())
nll = float((0.5 * (torch.log(2 * torch.pi * var) + (yq - mu) ** 2 / var)).mean())
print("ROW " + json.dumps({"estimator": "gpytorch-sgpr", "d": d, "n": n, "m": m, "fit_seconds": fit,
    "objective": bound, "peak_rss_bytes": peak, "base_rss_bytes": base_rss,
    "single_ms": 1e3 * float(np.median(lat)), "batch_points_per_second": nq / best,
    "update_ms": None, "rmse": rmse, "nll": nll}))
"#;

/// Creates the reference's venv and installs GPyTorch into it if it cannot import it yet.
fn ensure_reference(opts: &SparseBenchOptions) -> Result<PathBuf, String> {
    let py = opts.venv.join("bin").join("python");
    let importable = |py: &Path| {
        Command::new(py)
            .args(["-c", "import gpytorch, torch"])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if importable(&py) {
        return Ok(py);
    }
    println!(
        "installing the reference (gpytorch) into {} (once; several GB) …",
        opts.venv.display()
    );
    let status = Command::new(&opts.python)
        .args(["-m", "venv"])
        .arg(&opts.venv)
        .status()
        .map_err(|e| format!("{} -m venv: {e}", opts.python))?;
    if !status.success() {
        return Err(format!("{} -m venv failed", opts.python));
    }
    let status = Command::new(&py)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "gpytorch",
        ])
        .status()
        .map_err(|e| format!("pip install gpytorch: {e}"))?;
    if !status.success() || !importable(&py) {
        return Err("pip install gpytorch failed".into());
    }
    Ok(py)
}

fn write_f64(path: &Path, v: impl Iterator<Item = f64>) -> Result<(), String> {
    let bytes: Vec<u8> = v.flat_map(|x| x.to_le_bytes()).collect();
    std::fs::File::create(path)
        .and_then(|mut f| f.write_all(&bytes))
        .map_err(|e| format!("writing {}: {e}", path.display()))
}

fn rows_of(m: &DMatrix<f64>) -> impl Iterator<Item = f64> + '_ {
    (0..m.nrows()).flat_map(move |i| (0..m.ncols()).map(move |j| m[(i, j)]))
}

fn run_reference(
    py: &Path,
    opts: &SparseBenchOptions,
    d: usize,
    n: usize,
) -> Result<SparseBenchRow, String> {
    let dir =
        std::env::temp_dir().join(format!("precond-bench-sgpr-{}-{d}-{n}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
    let (x, y) = bench_data(n, d, opts.seed);
    let (q, yq) = bench_data(opts.batch.max(1), d, opts.seed.wrapping_add(1));
    let (xb, yb) = bench_data(50, d, opts.seed.wrapping_add(2));
    let mut files = Vec::new();
    for (name, data) in [
        ("x", rows_of(&x).collect::<Vec<_>>()),
        ("y", y.iter().copied().collect()),
        ("q", rows_of(&q).collect()),
        ("yq", yq.iter().copied().collect()),
        ("xb", rows_of(&xb).collect()),
        ("yb", yb.iter().copied().collect()),
    ] {
        let p = dir.join(format!("{name}.bin"));
        write_f64(&p, data.into_iter())?;
        files.push((name, p));
    }
    let mut job = serde_json::json!({
        "n": n, "d": d, "nq": q.nrows(), "m": opts.inducing.min(n), "seed": opts.seed,
        "iterations": opts.reference_iterations, "single_reps": opts.single_reps.clamp(1, 200),
        "nu": match opts.kernel { Kernel::Matern12 => 0.5, Kernel::Matern32 => 1.5, Kernel::Matern52 => 2.5 },
    });
    for (name, p) in &files {
        job[*name] = serde_json::Value::String(p.display().to_string());
    }
    let job_path = dir.join("job.json");
    std::fs::write(&job_path, job.to_string()).map_err(|e| e.to_string())?;
    let out = Command::new(py)
        .arg("-c")
        .arg(GPYTORCH_SCRIPT)
        .arg(&job_path)
        .env_remove("OPENBLAS_CORETYPE")
        .output();
    let _ = std::fs::remove_dir_all(&dir);
    let out = out.map_err(|e| format!("running the reference: {e}"))?;
    read_row(&out, "reference failed")
}

fn print_row(r: &SparseBenchRow) {
    let mb = |b: f64| b / 1048576.0;
    println!(
        "{:>3} {:>7} {:>14} {:>4} | {:>8.2} {:>13.2} | {:>8.0} {:>8.0} | {:>8.4} {:>11.0} | {:>8} | {:>7.4} {:>8.4}",
        r.d,
        r.n,
        r.estimator,
        r.m,
        r.fit_seconds,
        r.objective,
        mb(r.peak_rss_bytes),
        mb(r.base_rss_bytes),
        r.single_ms,
        r.batch_points_per_second,
        r.update_ms.map_or("-".to_string(), |v| format!("{v:.3}")),
        r.rmse,
        r.nll
    );
}

/// Runs the benchmark, printing a table to stdout as it goes, and returns the rows.
///
/// # Errors
/// Only when one of our own fits fails; reference failures are printed and skipped.
pub fn run(opts: &SparseBenchOptions) -> Result<Vec<SparseBenchRow>, String> {
    println!(
        "Sparse GP benchmark: {} ARD, {:?} noise, m = {}, restarts = {}, {} held-out / batch points, {} thread(s)",
        opts.kernel,
        opts.noise,
        opts.inducing,
        opts.restarts,
        opts.batch,
        std::thread::available_parallelism().map_or(1, |p| p.get())
    );
    let reference = if opts.reference {
        match ensure_reference(opts) {
            Ok(py) => {
                println!(
                    "reference: GPyTorch SGPR (InducingPointKernel), m = {}, Adam lr 0.1 × {} iterations, float64, CPU, 2 threads",
                    opts.inducing, opts.reference_iterations
                );
                Some(py)
            }
            Err(e) => {
                println!("reference: not run ({e})");
                None
            }
        }
    } else {
        println!("reference: not run (disabled)");
        None
    };
    println!(
        "{:>3} {:>7} {:>14} {:>4} | {:>8} {:>13} | {:>8} {:>8} | {:>8} {:>11} | {:>8} | {:>7} {:>8}",
        "d",
        "n",
        "estimator",
        "m",
        "fit s",
        "bound/LML",
        "peak MB",
        "base MB",
        "1pt ms",
        "batch pt/s",
        "upd50 ms",
        "RMSE",
        "NLL"
    );
    let mut rows = Vec::new();
    for &d in &opts.dims {
        for &n in &opts.sizes {
            let mut estimators = vec!["sparse"];
            if n <= opts.exact_max_n {
                estimators.push("exact");
            }
            for e in estimators {
                let r = spawn_child(&ChildSpec {
                    estimator: e.into(),
                    d,
                    n,
                    opts: opts.clone(),
                })?;
                print_row(&r);
                rows.push(r);
            }
            if let Some(py) = &reference
                && n <= opts.reference_max_n
            {
                match run_reference(py, opts, d, n) {
                    Ok(r) => {
                        print_row(&r);
                        rows.push(r);
                    }
                    Err(e) => println!("{d:>3} {n:>7} gpytorch-sgpr: {e}"),
                }
            }
        }
    }
    println!(
        "peak MB: the process's peak RSS (data included; the reference's includes Python and torch, see base MB: \
         the peak before the fit). NLL: mean negative log predictive density of {} held-out noisy targets.",
        opts.batch
    );
    Ok(rows)
}
