//! The command line: `precond serve` and friends. `main` only parses and calls [`run`].

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use precond::http::auth::TokenTable;
use precond::http::{AppState, HttpConfig, serve};
use precond::remote_model::{ModelCallLimits, ModelUrlPolicy};
use precond::service::{Limits, Service};
use precond::store::Store;
use tracing_subscriber::EnvFilter;

/// precond: learns where an inaccurate dynamics model can be trusted.
#[derive(Debug, Parser)]
// The name and the about line are the server's (`precond`), not this package's.
#[command(
    name = "precond",
    version,
    about = "A service that actively learns where an inaccurate dynamics model can be trusted (its model precondition).",
    long_about = None
)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run the HTTP/JSON service.
    Serve(ServeArgs),
    /// Print speed benchmarks (build with `--release`).
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Copy the database to a new file while the server keeps serving (a consistent snapshot;
    /// writers are not blocked).
    Backup(BackupArgs),
    /// Run the paper's evaluation (strategies × seeds × iterations) against the service and
    /// write results and plots.
    Experiment(crate::experiment::ExperimentArgs),
    /// Import logged transitions (CSV or Parquet files) into an experiment of a running
    /// server: one trajectory per episode, labelled by the experiment's model, with its source;
    /// safe to run again (nothing is stored twice).
    Import(crate::import::ImportArgs),
    /// Regenerate the schemas of `api/openapi.yaml` from the wire types and
    /// `api/schemas.yaml` (run in the repository; `--check`: only say whether they differ).
    Openapi(crate::openapi::OpenapiArgs),
}

/// Options of `precond backup`.
#[derive(Debug, Clone, clap::Args)]
pub struct BackupArgs {
    /// The database being served: a path or a `sqlite://` URL. It must exist; it is only read.
    #[arg(long, env = "PRECOND_DATABASE_URL", default_value = "precond.db")]
    pub database_url: String,
    /// The new file to write (must not exist). The copy is written under a temporary name
    /// beside it and takes this name only once complete and checked.
    #[arg(long, value_name = "FILE")]
    pub to: std::path::PathBuf,
}

/// Benchmarks.
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// GP fit time, single-point latency and batched throughput for n = 500 … 4000 in d = 6,
    /// side by side with scikit-learn where `python3` can import it; with `--sparse`, the
    /// sparse GP up to n = 100 000 beside the exact GP and GPyTorch's SGPR.
    Gp(GpBenchArgs),
    /// A 20-candidate, 5000-extension proposal and a test-time plan on the icy gridworld with the
    /// MDE fitted on 1000 transitions; then the same with a model served over HTTP on loopback
    /// (model calls and points per proposal).
    Planning,
    /// Latency of `/healthz` and a cheap read, idle and while concurrent clients saturate the
    /// planner with proposals that run into their deadline.
    Saturation(SaturationArgs),
    /// Proposals per second and their latency with 1, 2, 4 … replicas of this binary over one
    /// PostgreSQL database (a new database per count on the given server).
    Replicas(ReplicasArgs),
    /// The continuous worlds before any learning: the share of state-actions truly within
    /// `d_max`, the simulator's cost, and the oracle and the no-precondition baseline on random
    /// problems.
    Worlds(WorldsArgs),
    /// Refits a harness run's training transitions (a continuous world's) under each MDE
    /// setting — kernel, noise model, label cap — and judges uniform held-out state-actions
    /// against their true deviations.
    Mde(MdeArgs),
    /// The exported model's evaluator (`GET …/model/export`) against the server's own
    /// prediction: time per point, largest differences of `μ` and `σ`, document size.
    Export(ExportBenchArgs),
    /// A refit after one more batch, from scratch (model selection over every kernel and label
    /// cap) and warm (the previous choice, its optimum as the start), on a continuous world's
    /// data: seconds, phases and held-out TPR, TNR and log score of both.
    Refit(RefitBenchArgs),
}

/// Options of `precond bench refit`.
#[derive(Debug, Clone, clap::Args)]
pub struct RefitBenchArgs {
    /// The world: `arm`, `base` or `pusher`.
    #[arg(long, default_value = "base")]
    pub world: String,
    /// Transitions of the version before the refit.
    #[arg(long, default_value_t = 1000)]
    pub n: usize,
    /// Transitions of the batch the refit adds.
    #[arg(long, default_value_t = 50)]
    pub batch: usize,
    /// Held-out state-actions.
    #[arg(long, default_value_t = 2000)]
    pub held_out: usize,
    /// Seed of the data and the fits.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Options of `precond bench export`.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportBenchArgs {
    /// Training-set sizes of the exact GPs, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "100,500,2000")]
    pub exact_sizes: Vec<usize>,
    /// Training-set sizes of the sparse GPs.
    #[arg(long, value_delimiter = ',', default_value = "5000")]
    pub sparse_sizes: Vec<usize>,
    /// Inducing points of the sparse GPs.
    #[arg(long, default_value_t = 256)]
    pub inducing: usize,
}

/// Options of `precond bench mde`.
#[derive(Debug, Clone, clap::Args)]
pub struct MdeArgs {
    /// The harness database (`<out>/<world>/precond.db`; work on a copy, migrations may run).
    #[arg(long)]
    pub db: String,
    /// The experiment whose transitions to refit.
    #[arg(long)]
    pub experiment: i64,
    /// Its first N transitions (default all).
    #[arg(long)]
    pub n: Option<i64>,
    /// The world: `arm`, `base`, `pusher` or `icy_gridworld` (the default map).
    #[arg(long)]
    pub world: String,
    /// Held-out state-actions.
    #[arg(long, default_value_t = 2000)]
    pub held_out: usize,
    /// The estimators to fit each setting with, comma-separated: `exact`, `sparse`.
    #[arg(long, value_delimiter = ',', default_value = "exact,sparse", value_parser = parse_estimator_kind)]
    pub estimators: Vec<precond_core::mde::EstimatorKind>,
    /// Inducing points of the sparse GP.
    #[arg(long, default_value_t = precond_core::gp::DEFAULT_INDUCING_POINTS)]
    pub inducing_points: usize,
    /// The noise models to fit, comma-separated: `homoscedastic`, `heteroscedastic`.
    #[arg(long, value_delimiter = ',', default_value = "heteroscedastic", value_parser = parse_noise_mode)]
    pub noise: Vec<precond_core::gp::NoiseMode>,
    /// The label caps to fit, comma-separated, in units of `d_max` (0 = raw labels, else 1 to
    /// 1000, as `mde.label_cap`): one row each.
    #[arg(long, value_delimiter = ',', default_value = "2", value_parser = parse_label_cap)]
    pub label_caps: Vec<f64>,
    /// Instead of the settings table: the test β certified by leaving training state-actions
    /// out in groups of several kinds (copies, trajectories, feature-space blocks), and the
    /// false trust met at each on the held-out state-actions.
    #[arg(long)]
    pub calibration: bool,
}

/// A fixed label cap, as `mde.label_cap` accepts one ([`precond::settings::LabelCap::check_fixed`]).
fn parse_label_cap(s: &str) -> Result<f64, String> {
    let cap: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("{s:?} is not a label cap: a number, in units of d_max"))?;
    precond::settings::LabelCap::check_fixed(cap)
        .map(|()| cap)
        .map_err(|accepted| format!("must be {accepted}"))
}

/// `homoscedastic` or `heteroscedastic`.
fn parse_noise_mode(s: &str) -> Result<precond_core::gp::NoiseMode, String> {
    match s {
        "homoscedastic" => Ok(precond_core::gp::NoiseMode::Homoscedastic),
        "heteroscedastic" => Ok(precond_core::gp::NoiseMode::Heteroscedastic),
        other => Err(format!(
            "{other:?} is not a noise model; use homoscedastic or heteroscedastic"
        )),
    }
}

/// `exact`, `sparse` or `local_experts`.
fn parse_estimator_kind(s: &str) -> Result<precond_core::mde::EstimatorKind, String> {
    precond_core::mde::EstimatorKind::from_name(s)
        .ok_or_else(|| format!("{s:?} is not an estimator; use exact, sparse or local_experts"))
}

/// Options of `precond bench worlds`.
#[derive(Debug, Clone, clap::Args)]
pub struct WorldsArgs {
    /// Uniform state-actions sampled per world.
    #[arg(long, default_value_t = 4000)]
    pub samples: usize,
    /// Random problems per world.
    #[arg(long, default_value_t = 100)]
    pub problems: usize,
    /// Extension budget of the baseline's plans (the oracle's is twice this).
    #[arg(long, default_value_t = 5000)]
    pub max_extensions: u32,
    /// Cautious oracles to measure beside the oracle, as fractions `m` of `d_max`
    /// (comma-separated, each in (0, 1]): each trusts only moves whose true deviation is
    /// below `m · d_max`.
    #[arg(long, value_delimiter = ',', value_parser = margin)]
    pub margins: Vec<f64>,
}

/// A fraction of `d_max` in (0, 1].
fn margin(s: &str) -> Result<f64, String> {
    let m: f64 = s
        .parse()
        .map_err(|e| format!("{s:?} is not a number: {e}"))?;
    if m > 0.0 && m <= 1.0 {
        Ok(m)
    } else {
        Err(format!("{m} is not in (0, 1]"))
    }
}

/// Options of `precond bench saturation`.
#[derive(Debug, Clone, clap::Args)]
pub struct SaturationArgs {
    /// Concurrent clients asking for proposals.
    #[arg(long, default_value_t = 16)]
    pub clients: usize,
    /// Seconds of each phase (idle, saturated).
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Planning deadline in milliseconds.
    #[arg(long, default_value_t = 2000)]
    pub plan_timeout_ms: u64,
}

/// Options of `precond bench replicas`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReplicasArgs {
    /// A PostgreSQL URL whose user may create databases (`scripts/postgres.sh start DIR`
    /// prints one for a throwaway server).
    #[arg(long, env = "PRECOND_BENCH_POSTGRES")]
    pub database_url: String,
    /// Replica counts, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
    pub replicas: Vec<usize>,
    /// Concurrent clients (robots asking, executing and posting).
    #[arg(long, default_value_t = 16)]
    pub clients: usize,
    /// Seconds of measurement per replica count.
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Experiments the clients share.
    #[arg(long, default_value_t = 8)]
    pub experiments: usize,
    /// Each replica's `--max-concurrent-plans` (default: one per core), e.g. 1 to see
    /// replicas add cores on a small machine.
    #[arg(long)]
    pub plans_per_replica: Option<usize>,
}

/// Options of `precond bench gp`.
#[derive(Debug, Clone, clap::Args)]
pub struct GpBenchArgs {
    /// Training-set sizes, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "500,1000,2000,4000")]
    pub sizes: Vec<usize>,
    /// Skip n = 4000 (same as `--sizes 500,1000,2000`).
    #[arg(long)]
    pub quick: bool,
    /// Optimiser restarts beyond the first, for both libraries.
    #[arg(long, default_value_t = 2)]
    pub restarts: usize,
    /// Do not run scikit-learn even if it is importable.
    #[arg(long)]
    pub no_sklearn: bool,
    /// Largest n at which scikit-learn is run.
    #[arg(long, default_value_t = 2000)]
    pub sklearn_max_n: usize,
    /// The kernel (`matern12`, `matern32` or `matern52`), for both libraries.
    #[arg(long, default_value = "matern52")]
    pub kernel: precond_core::gp::Kernel,
    /// Benchmark the sparse GP instead (`--sparse-sizes`, `--dims`, `--inducing`, `--noise`),
    /// beside the exact GP up to `--exact-max-n` and GPyTorch's SGPR (installed into
    /// target/venv-sgpr-reference on first use; `--no-reference` skips it). Each fit runs in
    /// its own process so that its peak RSS is its own.
    #[arg(long)]
    pub sparse: bool,
    /// Training-set sizes of the sparse benchmark, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "2000,10000,50000,100000")]
    pub sparse_sizes: Vec<usize>,
    /// Input dimensions of the sparse benchmark, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "6,21")]
    pub dims: Vec<usize>,
    /// Inducing points of the sparse benchmark (ours and the reference's).
    #[arg(long, default_value_t = 256)]
    pub inducing: usize,
    /// Noise model of the sparse benchmark's own fits (`homoscedastic` or `heteroscedastic`;
    /// the reference is always homoscedastic).
    #[arg(long, default_value = "homoscedastic")]
    pub noise: String,
    /// Largest n at which the sparse benchmark also runs the exact GP.
    #[arg(long, default_value_t = 4000)]
    pub exact_max_n: usize,
    /// Do not run the reference sparse GP (GPyTorch).
    #[arg(long)]
    pub no_reference: bool,
    /// Largest n at which the reference is run.
    #[arg(long, default_value_t = 100_000)]
    pub reference_max_n: usize,
    /// Adam iterations of the reference.
    #[arg(long, default_value_t = 100)]
    pub reference_iterations: usize,
    /// Internal: run one fit of the sparse benchmark (a JSON spec) and print its figures.
    #[arg(long, hide = true)]
    pub child: Option<String>,
}

/// Log output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line.
    Json,
}

/// Options of `precond serve`; each falls back to an environment variable.
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// Address to listen on.
    #[arg(long, env = "PRECOND_ADDR", default_value = "127.0.0.1:8080")]
    pub addr: String,
    /// The database: a SQLite file (a path or a `sqlite://` URL; created if missing; one
    /// server per file), or a PostgreSQL database (`postgres://user:password@host:port/db`;
    /// it must exist) that several replicas may serve together.
    #[arg(long, env = "PRECOND_DATABASE_URL", default_value = "precond.db")]
    pub database_url: String,
    /// Milliseconds a request waits for a PostgreSQL connection before it is answered `503
    /// unavailable` with `Retry-After` (the database down, or every connection busy); also
    /// readiness's bound (100 ..= 60 000). At start-up the server waits up to 30 s for the
    /// database to come up.
    #[arg(long, env = "PRECOND_DATABASE_TIMEOUT_MS", default_value_t = 2000)]
    pub database_timeout_ms: u64,
    /// Seconds a replica's claim on a fit lasts without a heartbeat: a replica that died
    /// mid-fit has its fit taken over by another after this long (2 ..= 3600).
    #[arg(long, env = "PRECOND_FIT_LEASE_SECS", default_value_t = 15)]
    pub fit_lease_secs: u64,
    /// Milliseconds between a replica's looks at the database for fits other replicas
    /// requested and (PostgreSQL) model versions they fitted (10 ..= 60 000).
    #[arg(long, env = "PRECOND_REPLICA_POLL_MS", default_value_t = 500)]
    pub replica_poll_ms: u64,
    /// Log format (the level comes from `RUST_LOG`, default `info`).
    #[arg(long, env = "PRECOND_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,
    /// Largest accepted request body, in bytes.
    #[arg(long, env = "PRECOND_MAX_BODY_BYTES", default_value_t = precond::limits::DEFAULT_MAX_BODY_BYTES)]
    pub max_body_bytes: usize,
    /// Largest file `POST /v1/experiments/{id}/imports` accepts, in bytes (written to a
    /// temporary file while it arrives; larger logs: `precond import`, which streams).
    #[arg(long, env = "PRECOND_MAX_IMPORT_BYTES", default_value_t = 256 * 1024 * 1024)]
    pub max_import_bytes: usize,
    /// Allow experiments whose dynamics model is served at URLs under this prefix (e.g.
    /// `http://robot-pc:9000/`); repeatable. Without one, remote models are refused.
    #[arg(
        long = "allow-model-url",
        value_name = "PREFIX",
        env = "PRECOND_ALLOW_MODEL_URLS",
        value_delimiter = ','
    )]
    pub allow_model_urls: Vec<String>,
    /// Calls to remote models running at once, over all model URLs (1 ..= 1024). A call
    /// beyond it waits, within its deadline, then gets `503 model_busy`.
    #[arg(long, env = "PRECOND_MAX_MODEL_CALLS", default_value_t = 32)]
    pub max_model_calls: usize,
    /// Calls to one remote model URL running at once (1 ..= 1024).
    #[arg(long, env = "PRECOND_MAX_MODEL_CALLS_PER_URL", default_value_t = 8)]
    pub max_model_calls_per_url: usize,
    /// The longest one remote model call may take, whatever `timeout_ms` its experiment
    /// declares, waiting for a free call included, in milliseconds (1 ..= 600 000).
    #[arg(long, env = "PRECOND_MAX_MODEL_TIMEOUT_MS", default_value_t = 30_000)]
    pub max_model_timeout_ms: u64,
    /// Access tokens, one a line: `token role [experiment-ids|*]` with role `read`, `write` or
    /// `admin` (see the README's "Deploying for a lab"). Without it every request is let
    /// through, so the server then refuses a non-loopback address unless
    /// `--insecure-no-auth` is given.
    #[arg(long, env = "PRECOND_TOKEN_FILE", value_name = "FILE")]
    pub token_file: Option<std::path::PathBuf>,
    /// Serve without tokens on a non-loopback address (a trusted network only).
    #[arg(long, env = "PRECOND_INSECURE_NO_AUTH")]
    pub insecure_no_auth: bool,
    /// Planning searches and fits running at once (1 ..= 256; default: the number of cores);
    /// as many evaluations of maps, diagnostics and large precondition queries, in slots of
    /// their own.
    #[arg(long, env = "PRECOND_MAX_CONCURRENT_PLANS")]
    pub max_concurrent_plans: Option<usize>,
    /// Planning searches (and model rebuilds) of one experiment running at once, so that one
    /// client flooding one experiment cannot take every slot (1 ..= 256; default: half of
    /// max-concurrent-plans, at least 1).
    #[arg(long, env = "PRECOND_MAX_PLANS_PER_EXPERIMENT")]
    pub max_plans_per_experiment: Option<usize>,
    /// Planning requests waiting for a slot before new ones get `429` (0 ..= 10 000; default:
    /// 8 × max-concurrent-plans); as many evaluations may wait for theirs.
    #[arg(long, env = "PRECOND_MAX_QUEUED_PLANS")]
    pub max_queued_plans: Option<usize>,
    /// Wall-clock budget of one proposal or plan, queueing included, in milliseconds
    /// (100 ..= 600 000); past it the client gets `503` with `Retry-After`.
    #[arg(long, env = "PRECOND_PLAN_TIMEOUT_MS", default_value_t = 30_000)]
    pub plan_timeout_ms: u64,
    /// Experiments this server holds (1 ..= 1 000 000).
    #[arg(long, env = "PRECOND_MAX_EXPERIMENTS", default_value_t = 1000)]
    pub max_experiments: usize,
    /// Transitions in one posted trajectory (1 ..= 10 000).
    #[arg(long, env = "PRECOND_MAX_TRANSITIONS", default_value_t = precond_core::limits::MAX_TRANSITIONS)]
    pub max_transitions: usize,
    /// Memory one MDE fit may use at its peak, in MiB (64 ..= 1 048 576; default a quarter of
    /// the machine's memory): a fit estimated beyond it is not attempted but recorded as
    /// refused, and `mde.estimator: auto` switches to the sparse GP first.
    #[arg(long, env = "PRECOND_MAX_FIT_MEMORY_MIB")]
    pub max_fit_memory_mib: Option<u64>,
    /// Seconds one MDE fit may take by its estimate, model selection included (10 ..= 86 400):
    /// a fit beyond it is not attempted but recorded as refused (`mde.estimator: auto` turns
    /// to the sparse GP first), so that one experiment's fit cannot hold a fit slot for hours.
    #[arg(long, env = "PRECOND_MAX_FIT_SECONDS", default_value_t = 900)]
    pub max_fit_seconds: u64,
    /// Large transfers at once — model exports and CSV exports of every transition written,
    /// imports received (1 ..= 256); one beyond waits 2 s for a slot, then gets `429`.
    #[arg(long, env = "PRECOND_MAX_CONCURRENT_EXPORTS", default_value_t = 4)]
    pub max_concurrent_exports: usize,
    /// Seconds a client has to send a request's headers; also how long a kept-alive connection
    /// may stay idle (1 ..= 600).
    #[arg(long, env = "PRECOND_HEADER_READ_TIMEOUT_SECS", default_value_t = 30)]
    pub header_read_timeout_secs: u64,
    /// Seconds a client has to send a request's whole body; past them `408` (1 ..= 3600).
    #[arg(long, env = "PRECOND_BODY_READ_TIMEOUT_SECS", default_value_t = 60)]
    pub body_read_timeout_secs: u64,
    /// Seconds in-flight requests may run on after SIGTERM before they are dropped.
    #[arg(long, env = "PRECOND_SHUTDOWN_GRACE_SECS", default_value_t = 20)]
    pub shutdown_grace_secs: u64,
    /// Let the dashboard (or any browser page) served from this origin read the API, e.g.
    /// `http://lab-pc:8080` for a dashboard there pointed at this server with `?api=`;
    /// repeatable. Without one, browsers only let this server's own pages call it.
    #[arg(
        long = "cors-allow-origin",
        value_name = "ORIGIN",
        env = "PRECOND_CORS_ALLOW_ORIGINS",
        value_delimiter = ','
    )]
    pub cors_allow_origins: Vec<String>,
}

impl ServeArgs {
    /// The service limits these options set, checked.
    pub fn limits(&self) -> anyhow::Result<Limits> {
        let defaults = Limits::default();
        let concurrent = self
            .max_concurrent_plans
            .unwrap_or(defaults.max_concurrent_plans);
        let limits = Limits {
            max_concurrent_plans: concurrent,
            max_plans_per_experiment: self
                .max_plans_per_experiment
                .unwrap_or(Limits::default_per_experiment(concurrent)),
            max_queued_plans: self.max_queued_plans.unwrap_or(8 * concurrent),
            plan_timeout: std::time::Duration::from_millis(self.plan_timeout_ms),
            max_experiments: self.max_experiments,
            max_transitions: self.max_transitions,
            max_fit_memory: self
                .max_fit_memory_mib
                .map_or(defaults.max_fit_memory, |m| m.saturating_mul(1 << 20)),
            max_fit_seconds: self.max_fit_seconds,
            max_concurrent_exports: self.max_concurrent_exports,
        };
        limits.check().map_err(anyhow::Error::msg)?;
        Ok(limits)
    }
}

impl ServeArgs {
    /// The limits on remote model calls these options set, checked.
    pub fn model_limits(&self) -> anyhow::Result<ModelCallLimits> {
        let limits = ModelCallLimits {
            max_calls: self.max_model_calls,
            max_calls_per_url: self.max_model_calls_per_url,
            max_timeout: std::time::Duration::from_millis(self.max_model_timeout_ms),
        };
        limits.check().map_err(anyhow::Error::msg)?;
        Ok(limits)
    }

    /// Checks the connection timeouts' ranges; the error names the option.
    pub fn check_timeouts(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            (1..=600).contains(&self.header_read_timeout_secs),
            "--header-read-timeout-secs must lie in 1 ..= 600, got {}",
            self.header_read_timeout_secs
        );
        anyhow::ensure!(
            (1..=3600).contains(&self.body_read_timeout_secs),
            "--body-read-timeout-secs must lie in 1 ..= 3600, got {}",
            self.body_read_timeout_secs
        );
        Ok(())
    }
}

/// Reads the token file, if any; the error names the file and the line, never a token.
pub fn load_tokens(
    path: Option<&std::path::Path>,
) -> anyhow::Result<Option<std::sync::Arc<TokenTable>>> {
    let Some(path) = path else { return Ok(None) };
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading the token file {}", path.display()))?;
    let table =
        TokenTable::parse(&text).with_context(|| format!("the token file {}", path.display()))?;
    Ok(Some(std::sync::Arc::new(table)))
}

/// Refuses to serve without tokens on a non-loopback address unless the operator insisted.
pub fn check_exposure(
    addr: std::net::SocketAddr,
    has_tokens: bool,
    insecure_no_auth: bool,
) -> anyhow::Result<()> {
    if has_tokens || addr.ip().is_loopback() {
        return Ok(());
    }
    if insecure_no_auth {
        tracing::warn!(
            %addr,
            "serving WITHOUT access tokens on a non-loopback address (--insecure-no-auth): \
             anyone who can reach it can create experiments and post data"
        );
        return Ok(());
    }
    anyhow::bail!(
        "refusing to serve on {addr} without access tokens: give --token-file FILE (or \
         PRECOND_TOKEN_FILE), listen on a loopback address, or pass --insecure-no-auth"
    )
}

/// Installs the global tracing subscriber.
pub fn init_tracing(format: LogFormat) {
    use std::io::IsTerminal;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    // Colours only on a terminal: escape sequences in a redirected log file are noise at best.
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::stdout().is_terminal());
    let _ = match format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
}

/// Resolves on SIGINT or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = terminate => {},
    }
    tracing::info!("shutdown requested; finishing in-flight requests");
}

/// Runs a parsed command line.
pub async fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Serve(args) => {
            init_tracing(args.log_format);
            let model_urls =
                ModelUrlPolicy::new(&args.allow_model_urls).map_err(anyhow::Error::msg)?;
            if !args.allow_model_urls.is_empty() {
                tracing::info!(prefixes = ?model_urls.prefixes(), "remote dynamics models allowed");
            }
            let limits = args.limits()?;
            let model_limits = args.model_limits()?;
            args.check_timeouts()?;
            anyhow::ensure!(
                (2..=3600).contains(&args.fit_lease_secs),
                "--fit-lease-secs {}: use 2 ..= 3600",
                args.fit_lease_secs
            );
            anyhow::ensure!(
                (10..=60_000).contains(&args.replica_poll_ms),
                "--replica-poll-ms {}: use 10 ..= 60000",
                args.replica_poll_ms
            );
            let tokens = load_tokens(args.token_file.as_deref())?;
            let listener = tokio::net::TcpListener::bind(&args.addr)
                .await
                .with_context(|| format!("binding {}", args.addr))?;
            check_exposure(
                listener.local_addr()?,
                tokens.is_some(),
                args.insecure_no_auth,
            )?;
            match &tokens {
                Some(t) => tracing::info!(tokens = t.len(), "access tokens required"),
                None => tracing::info!("no token file: every request is let through"),
            }
            // One server per SQLite file: held until this process ends.
            let serving = precond::store::lock_for_serving(&args.database_url)?;
            if let Some(lock) = &serving {
                tracing::info!(lock = %lock.path().display(), "holding the database's serving lock");
            }
            anyhow::ensure!(
                (100..=60_000).contains(&args.database_timeout_ms),
                "--database-timeout-ms must be in 100 ..= 60000 (got {})",
                args.database_timeout_ms
            );
            let store = Store::open_with_timeout(
                &args.database_url,
                std::time::Duration::from_millis(args.database_timeout_ms),
            )
            .await?;
            tracing::info!(
                database = %precond::store::redact(&args.database_url),
                backend = store.backend().as_str(),
                "database opened"
            );
            tracing::info!(?limits, ?model_limits, "limits");
            let state = AppState::with_service(
                Service::with_model_urls(store, model_urls)
                    .with_limits(limits)
                    .with_model_limits(model_limits)
                    .with_fit_lease(
                        std::time::Duration::from_secs(args.fit_lease_secs),
                        std::time::Duration::from_millis(args.replica_poll_ms),
                    ),
                HttpConfig {
                    max_body_bytes: args.max_body_bytes,
                    max_import_bytes: args.max_import_bytes,
                    tokens,
                    shutdown_grace: std::time::Duration::from_secs(args.shutdown_grace_secs),
                    header_read_timeout: std::time::Duration::from_secs(
                        args.header_read_timeout_secs,
                    ),
                    body_read_timeout: std::time::Duration::from_secs(args.body_read_timeout_secs),
                    cors_allow_origins: args.cors_allow_origins,
                    bound: None,
                },
            );
            let served = serve(listener, state, shutdown_signal()).await;
            drop(serving);
            served
        }
        Command::Bench(BenchCommand::Gp(args)) if args.child.is_some() => {
            crate::bench::sparse::run_child(args.child.as_deref().unwrap_or_default())
                .map_err(anyhow::Error::msg)
        }
        Command::Bench(BenchCommand::Gp(args)) if args.sparse => {
            let noise = match args.noise.as_str() {
                "homoscedastic" => precond_core::gp::NoiseMode::Homoscedastic,
                "heteroscedastic" => precond_core::gp::NoiseMode::Heteroscedastic,
                other => anyhow::bail!("--noise {other}: use homoscedastic or heteroscedastic"),
            };
            crate::bench::sparse::run(&crate::bench::sparse::SparseBenchOptions {
                sizes: args.sparse_sizes,
                dims: args.dims,
                inducing: args.inducing,
                noise,
                restarts: args.restarts,
                exact_max_n: args.exact_max_n,
                reference: !args.no_reference,
                reference_max_n: args.reference_max_n,
                reference_iterations: args.reference_iterations,
                kernel: args.kernel,
                ..crate::bench::sparse::SparseBenchOptions::default()
            })
            .map_err(anyhow::Error::msg)?;
            Ok(())
        }
        Command::Bench(BenchCommand::Gp(args)) => {
            let defaults = crate::bench::gp::GpBenchOptions::default();
            let sizes = if args.quick {
                args.sizes.into_iter().filter(|n| *n < 4000).collect()
            } else {
                args.sizes
            };
            crate::bench::gp::run(&crate::bench::gp::GpBenchOptions {
                sizes,
                restarts: args.restarts,
                sklearn: !args.no_sklearn,
                sklearn_max_n: args.sklearn_max_n,
                kernel: args.kernel,
                ..defaults
            })?;
            Ok(())
        }
        Command::Bench(BenchCommand::Planning) => {
            tokio::task::spawn_blocking(crate::bench::planning::run_default).await??;
            crate::bench::remote::run(5).await
        }
        Command::Bench(BenchCommand::Refit(args)) => {
            let world = match args.world.as_str() {
                "arm" => precond_core::sim::ContinuousWorld::arm(),
                "base" => precond_core::sim::ContinuousWorld::base(),
                "pusher" => precond_core::sim::ContinuousWorld::pusher(),
                other => anyhow::bail!(
                    "{other:?} is not a world of this benchmark; use arm, base or pusher"
                ),
            };
            let o = crate::bench::refit::RefitBenchOptions {
                world,
                n: args.n,
                batch: args.batch,
                held_out: args.held_out,
                seed: args.seed,
            };
            tokio::task::spawn_blocking(move || crate::bench::refit::run(&o).map(|_| ())).await?
        }
        Command::Bench(BenchCommand::Mde(args)) => {
            let world = match args.world.as_str() {
                "arm" => Some(precond_core::sim::ContinuousWorld::arm()),
                "base" => Some(precond_core::sim::ContinuousWorld::base()),
                "pusher" => Some(precond_core::sim::ContinuousWorld::pusher()),
                "icy_gridworld" => None,
                other => anyhow::bail!(
                    "{other:?} is not a world of this benchmark; use arm, base, pusher or \
                     icy_gridworld (default map)"
                ),
            };
            crate::bench::mde::run(crate::bench::mde::MdeBenchOptions {
                db: args.db,
                experiment: args.experiment,
                n: args.n,
                world,
                held_out: args.held_out,
                estimators: args.estimators,
                inducing_points: args.inducing_points,
                noise: args.noise,
                label_caps: args.label_caps,
                calibration: args.calibration,
            })
            .await
        }
        Command::Bench(BenchCommand::Export(args)) => {
            tokio::task::spawn_blocking(move || {
                crate::bench::export::run(&args.exact_sizes, &args.sparse_sizes, args.inducing)
            })
            .await?
        }
        Command::Bench(BenchCommand::Worlds(args)) => {
            tokio::task::spawn_blocking(move || {
                crate::bench::worlds::run(
                    args.samples,
                    args.problems,
                    args.max_extensions,
                    &args.margins,
                )
            })
            .await?;
            Ok(())
        }
        Command::Bench(BenchCommand::Saturation(args)) => {
            crate::bench::saturation::run(&crate::bench::saturation::SaturationOptions {
                clients: args.clients,
                seconds: args.seconds,
                plan_timeout_ms: args.plan_timeout_ms,
            })
            .await
        }
        Command::Bench(BenchCommand::Replicas(args)) => {
            crate::bench::replicas::run(&crate::bench::replicas::ReplicasOptions {
                database_url: args.database_url,
                replicas: args.replicas,
                clients: args.clients,
                seconds: args.seconds,
                experiments: args.experiments,
                plans_per_replica: args.plans_per_replica,
            })
            .await
        }
        Command::Openapi(args) => crate::openapi::run(&args),
        Command::Backup(args) => {
            let size = precond::store::backup(&args.database_url, &args.to).await?;
            println!(
                "backed up {} experiments, {} trajectories, {} transitions ({} bytes) to {}",
                size.experiments,
                size.trajectories,
                size.transitions,
                size.bytes,
                args.to.display()
            );
            Ok(())
        }
        Command::Experiment(args) => {
            crate::experiment::init_tracing();
            crate::experiment::run(args).await.map(|_| ())
        }
        Command::Import(args) => {
            crate::experiment::init_tracing();
            crate::import::run(args).await.map(|_| ())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn without_tokens_only_loopback_is_served_unless_insisted() {
        let loopback: std::net::SocketAddr = "127.0.0.1:8080".parse().unwrap();
        let v6: std::net::SocketAddr = "[::1]:8080".parse().unwrap();
        let open: std::net::SocketAddr = "0.0.0.0:8080".parse().unwrap();
        assert!(check_exposure(loopback, false, false).is_ok());
        assert!(check_exposure(v6, false, false).is_ok());
        let e = check_exposure(open, false, false).unwrap_err().to_string();
        assert!(
            e.contains("--token-file") && e.contains("--insecure-no-auth"),
            "{e}"
        );
        assert!(check_exposure(open, true, false).is_ok());
        assert!(check_exposure(open, false, true).is_ok());
    }

    #[test]
    fn serve_limits_are_checked() {
        let args = |extra: &[&str]| {
            let mut argv = vec!["precond", "serve"];
            argv.extend(extra);
            match Cli::parse_from(argv).command {
                Command::Serve(a) => a,
                _ => unreachable!(),
            }
        };
        let l = args(&["--max-concurrent-plans", "3"]).limits().unwrap();
        assert_eq!((l.max_concurrent_plans, l.max_queued_plans), (3, 24));
        assert!(args(&["--plan-timeout-ms", "5"]).limits().is_err());
        assert!(args(&["--max-transitions", "10001"]).limits().is_err());
    }
}
