//! The command line: `precond serve` and friends. `main` only parses and calls [`run`].

use crate::http::{AppState, HttpConfig, serve};
use crate::remote_model::ModelUrlPolicy;
use crate::service::Service;
use crate::store::Store;
use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use tracing_subscriber::EnvFilter;

/// precond: learns where an inaccurate dynamics model can be trusted.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
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
    /// Run the paper's evaluation (strategies × seeds × iterations) against the service and
    /// write results and plots.
    Experiment(crate::experiment::ExperimentArgs),
}

/// Benchmarks.
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// GP fit time, single-point latency and batched throughput for n = 500 … 4000 in d = 6,
    /// side by side with scikit-learn where `python3` can import it.
    Gp(GpBenchArgs),
    /// A 20-candidate, 5000-extension proposal and a test-time plan on the icy gridworld with the
    /// MDE fitted on 1000 transitions; then the same with a model served over HTTP on loopback
    /// (model calls and points per proposal).
    Planning,
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
    /// SQLite database: a path or a `sqlite://` URL; created if missing.
    #[arg(long, env = "PRECOND_DATABASE_URL", default_value = "precond.db")]
    pub database_url: String,
    /// Log format (the level comes from `RUST_LOG`, default `info`).
    #[arg(long, env = "PRECOND_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,
    /// Largest accepted request body, in bytes.
    #[arg(long, env = "PRECOND_MAX_BODY_BYTES", default_value_t = 4 * 1024 * 1024)]
    pub max_body_bytes: usize,
    /// Allow experiments whose dynamics model is served at URLs under this prefix (e.g.
    /// `http://robot-pc:9000/`); repeatable. Without one, remote models are refused.
    #[arg(
        long = "allow-model-url",
        value_name = "PREFIX",
        env = "PRECOND_ALLOW_MODEL_URLS",
        value_delimiter = ','
    )]
    pub allow_model_urls: Vec<String>,
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

/// Installs the global tracing subscriber.
pub fn init_tracing(format: LogFormat) {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt().with_env_filter(filter);
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
            let store = Store::open(&args.database_url).await?;
            let listener = tokio::net::TcpListener::bind(&args.addr)
                .await
                .with_context(|| format!("binding {}", args.addr))?;
            let state = AppState::with_service(
                Service::with_model_urls(store, model_urls),
                HttpConfig {
                    max_body_bytes: args.max_body_bytes,
                    cors_allow_origins: args.cors_allow_origins,
                },
            );
            serve(listener, state, shutdown_signal()).await
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
                ..defaults
            })?;
            Ok(())
        }
        Command::Bench(BenchCommand::Planning) => {
            tokio::task::spawn_blocking(crate::bench::planning::run_default).await??;
            crate::bench::remote::run(5).await
        }
        Command::Experiment(args) => {
            crate::experiment::init_tracing();
            crate::experiment::run(args).await.map(|_| ())
        }
    }
}
