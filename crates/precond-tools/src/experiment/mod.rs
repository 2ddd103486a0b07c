//! `precond experiment`: the paper's evaluation, run end to end as an HTTP client of the service.
//!
//! For one domain, over strategies × seeds, each run creates its own experiment on the service
//! and, per iteration, executes a batch of proposed trajectories in the simulator and posts them,
//! waits for the service's background refit, then evaluates with the test β: plans for fresh
//! problems (found? executed successfully?) and the precondition's TPR and TNR on held-out
//! transitions from other seeds' executions ([`protocol`] has the details).
//!
//! - [`client`]: the HTTP client of the endpoints the harness drives.
//! - [`layouts`]: gridworld layouts — the default map, a map file, seeded random maps.
//! - [`protocol`]: held-out pools, one run's iterations, execution in the simulators.
//! - [`report`]: the CSV files and the JSON summary (mean and standard error).
//! - [`plot`]: the SVG figures (the paper's layout; the water plant's precondition maps).
//!
//! By default the service runs in-process on an ephemeral port with its database in the output
//! directory; `--server URL` drives a running one instead.

pub mod client;
pub mod layouts;
pub mod plot;
pub mod protocol;
pub mod reference;
pub mod report;

use anyhow::Context;
use clap::ValueEnum;
use client::ApiClient;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use layouts::Layout;
use precond::http::{AppState, HttpConfig, serve};
use precond::settings::{KernelChoice, LabelCap, Preset};
use precond::store::Store;
use precond_core::domain::{GridFeatures, KinematicFeatures};
use precond_core::gp::NoiseMode;
use precond_core::mde::EstimatorChoice;
use precond_core::planning::{AcquisitionKind, Aggregation, Strategy};
use protocol::{Bench, Labelled, RunResult, RunSpec};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The built-in worlds the harness can run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DomainKind {
    /// The icy gridworld (default map).
    #[value(name = "icy_gridworld")]
    IcyGridworld,
    /// The water plant (default scene).
    #[value(name = "water_plant")]
    WaterPlant,
    /// A three-joint arm under gravity with weak actuators and contact (`sim::arm`); the robot
    /// models it kinematically.
    #[value(name = "arm")]
    Arm,
    /// A mobile base with a slippery slope, a crosswind and a hidden box (`sim::base`).
    #[value(name = "base")]
    Base,
    /// A pushed puck that slides on after each push (`sim::pusher`).
    #[value(name = "pusher")]
    Pusher,
}

impl DomainKind {
    /// The domain's `kind` tag.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::IcyGridworld => "icy_gridworld",
            Self::WaterPlant => "water_plant",
            Self::Arm => "arm",
            Self::Base => "base",
            Self::Pusher => "pusher",
        }
    }
}

fn parse_strategy(s: &str) -> Result<Strategy, String> {
    s.parse()
        .map_err(|e: precond_core::planning::PlanningError| e.to_string())
}

/// A setting spelled as the API spells it (its serde name), or an error naming the choices.
fn parse_named<T: serde::de::DeserializeOwned>(
    s: &str,
    what: &str,
    choices: &str,
) -> Result<T, String> {
    serde_json::from_value(serde_json::Value::String(s.into()))
        .map_err(|_| format!("{s:?} is not {what}; use {choices}"))
}

/// `fn $parse(s) -> Result<$ty, String>` through [`parse_named`], for each setting the command line
/// spells as the API does: what it is and the choices, once each.
macro_rules! named_parsers {
    ($($parse:ident: $ty:ty, $what:literal, $choices:literal;)+) => {
        $(fn $parse(s: &str) -> Result<$ty, String> {
            parse_named(s, $what, $choices)
        })+
    };
}

named_parsers! {
    parse_noise: NoiseMode, "a noise model", "homoscedastic or heteroscedastic";
    parse_kernel: KernelChoice, "a kernel", "auto, matern12, matern32 or matern52";
    parse_estimator: EstimatorChoice, "an estimator", "auto, exact or sparse";
    parse_aggregation: Aggregation, "an aggregation", "max or sum";
    parse_acquisition: AcquisitionKind, "an acquisition", "lcb, level_set, bottleneck or spread";
    parse_preset: Preset, "a preset", "default or paper";
    parse_grid_features: GridFeatures, "a feature map", "scaled or per_move";
    parse_kinematic_features: KinematicFeatures, "a feature map",
        "state_action_prediction_length, state_action_prediction or state_action";
}

fn parse_label_cap(s: &str) -> Result<LabelCap, String> {
    if s == "auto" {
        return Ok(LabelCap::Auto);
    }
    s.parse()
        .map(LabelCap::Fixed)
        .map_err(|_| format!("{s:?} is not a label cap; use auto or a number of d_max (0: raw)"))
}

/// Options of `precond experiment`. Unset numbers take the paper's defaults, or the `--quick`
/// ones.
#[derive(Debug, Clone, clap::Args)]
pub struct ExperimentArgs {
    /// The world.
    #[arg(long, value_enum, default_value_t = DomainKind::IcyGridworld)]
    pub domain: DomainKind,
    /// A small run (2 seeds, 3 iterations, 3 test problems, 5 candidates, 1000 extensions).
    #[arg(long)]
    pub quick: bool,
    /// Drive the service at this URL instead of starting one in-process.
    #[arg(long)]
    pub server: Option<String>,
    /// Output directory; results go to `<out>/<domain>/`.
    #[arg(long, default_value = "results")]
    pub out: PathBuf,
    /// Number of seeds (seeds 0..N). Default 10 (quick: 2).
    #[arg(long)]
    pub seeds: Option<usize>,
    /// Learning iterations per run. Default 20 (quick: 3).
    #[arg(long)]
    pub iterations: Option<usize>,
    /// Strategies, comma-separated. Default `active,goal_conditioned,random`.
    #[arg(long, value_delimiter = ',', value_parser = parse_strategy)]
    pub strategies: Vec<Strategy>,
    /// Training trajectories per iteration. Default 5.
    #[arg(long)]
    pub batch_size: Option<usize>,
    /// Test problems per iteration. Default 20 (quick: 3).
    #[arg(long)]
    pub test_problems: Option<usize>,
    /// Candidate trajectories per proposal. Default 20 (quick: 5).
    #[arg(long)]
    pub n_candidates: Option<u32>,
    /// RRT extension budget. Default 5000 (quick: 1000).
    #[arg(long)]
    pub max_extensions: Option<u32>,
    /// Held-out pool trajectories per seed. Default 20 (quick: 6).
    #[arg(long)]
    pub pool_trajectories: Option<usize>,
    /// Problems a training slot tries before it is skipped when none has a plan. Default 5.
    #[arg(long, default_value_t = 5)]
    pub problem_tries: usize,
    /// Continuous worlds: a test problem the planner did not solve is searched again this many
    /// times longer to tell whether it is solvable inside the learned precondition
    /// (`learned_rate`); 0 skips that search (`learned_rate` is then left empty), which makes
    /// a run with many unsolved problems several times faster.
    #[arg(long, default_value_t = protocol::LONG_SEARCH_FACTOR)]
    pub long_search: u32,
    /// Runs (strategy × seed) in flight at once; each is independent and seeded, so results do
    /// not depend on it. Default 1.
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Seconds to wait for a background refit before forcing one.
    #[arg(long, default_value_t = 600)]
    pub fit_timeout: u64,
    /// No progress bar.
    #[arg(long)]
    pub no_progress: bool,
    /// Gridworld: run on the map in this file (rows of `.`, `#`, `~`, row y = 0 first) instead
    /// of the default map. Repeatable.
    #[arg(long = "map", value_name = "FILE")]
    pub maps: Vec<PathBuf>,
    /// Gridworld: also run on N seeded random maps (`random-0` … `random-{N-1}`: sides of
    /// 10–20, a wall with gaps, ice bands, obstacle blocks). Each layout's results go to
    /// `<out>/icy_gridworld/<layout>/`, and `layouts.csv` compares them.
    #[arg(long, default_value_t = 0)]
    pub random_maps: usize,
    /// The MDE's noise model (`homoscedastic` or `heteroscedastic`). Default: the service's.
    #[arg(long, value_parser = parse_noise)]
    pub noise: Option<NoiseMode>,
    /// The MDE's kernel (`auto`, `matern12`, `matern32` or `matern52`). Default: the preset's.
    #[arg(long, value_parser = parse_kernel)]
    pub kernel: Option<KernelChoice>,
    /// The MDE's regressor (`auto`, `exact` or `sparse`). Default: the service's (`auto`).
    #[arg(long, value_parser = parse_estimator)]
    pub estimator: Option<EstimatorChoice>,
    /// Gridworld: the MDE's features, `scaled` (the paper's) or `per_move`.
    #[arg(long, value_parser = parse_grid_features, default_value = "scaled")]
    pub grid_features: GridFeatures,
    /// Continuous worlds: the MDE's features, `state_action_prediction_length` (the default),
    /// `state_action_prediction` or `state_action`.
    #[arg(long, value_parser = parse_kinematic_features, default_value = "state_action_prediction_length")]
    pub kinematic_features: KinematicFeatures,
    /// The experiments' preset: `default` (precond's) or `paper` (the paper's exact
    /// configuration).
    #[arg(long, value_parser = parse_preset, default_value = "default")]
    pub preset: Preset,
    /// Clip labels at this many `d_max` before fitting (0: raw labels), or `auto` (chosen at
    /// every fit from held-out judgements). Default: the preset's.
    #[arg(long, value_parser = parse_label_cap)]
    pub label_cap: Option<LabelCap>,
    /// Whether training proposals with no plan at `β_j` relax β (`true` or `false`). Default:
    /// the preset's.
    #[arg(long)]
    pub relax_beta: Option<bool>,
    /// The acquisition's exploration weight `c` in `α_step = μ − cσ`. Default: the service's (1).
    #[arg(long)]
    pub c: Option<f64>,
    /// How step utilities combine into a trajectory's (`max` or `sum`). Default: the service's
    /// (`max`).
    #[arg(long, value_parser = parse_aggregation)]
    pub aggregation: Option<Aggregation>,
    /// The acquisition `active` minimises: `lcb` (the paper's `h(μ − cσ)`), `level_set`,
    /// `bottleneck` or `spread`.
    /// Default: the preset's.
    #[arg(long, value_parser = parse_acquisition)]
    pub acquisition: Option<AcquisitionKind>,
    /// Whether `active` scores candidates with the σ of state-actions in flight fantasised as
    /// labelled (`true` or `false`). Default: the preset's.
    #[arg(long)]
    pub batch_diversity: Option<bool>,
    /// The β of test plans and of the held-out judgements (`learning.test_beta`). Default: the
    /// service's (2).
    #[arg(long)]
    pub test_beta: Option<f64>,
    /// Whether test plans and held-out judgements use the β each fitted version certifies
    /// (`learning.calibrate_test_beta`: `true` or `false`). Default: the preset's.
    #[arg(long)]
    pub calibrate_test_beta: Option<bool>,
    /// Whether test plans and held-out judgements judge each state-action at its locally
    /// calibrated β (`learning.local_test_margin`: `true` or `false`). Default: the preset's.
    #[arg(long)]
    pub local_test_margin: Option<bool>,
    /// The β schedule's amplitude `k1` (`learning.k1`): training β runs from about `−k1` to
    /// about `k1`. Default: the service's (2).
    #[arg(long)]
    pub k1: Option<f64>,
    /// The β schedule's steepness `k2` per iteration (`learning.k2`). Default: the service's
    /// (0.5).
    #[arg(long)]
    pub k2: Option<f64>,
    /// The iterations `J` the β schedule is planned over (`learning.iterations`; β crosses 0 at
    /// `J / 2`). Default: the run's `--iterations`.
    #[arg(long)]
    pub schedule_iterations: Option<u32>,
    /// The first iterations whose `active` proposals are random rollouts
    /// (`learning.warmup_iterations`). Default: the preset's.
    #[arg(long)]
    pub warmup_iterations: Option<u32>,
}

impl ExperimentArgs {
    /// The gridworld layouts to run: the files given with `--map` (or the default map when there
    /// are none), then the random ones. Empty for the water plant.
    pub fn layouts(&self) -> anyhow::Result<Vec<Layout>> {
        if self.domain != DomainKind::IcyGridworld {
            anyhow::ensure!(
                self.maps.is_empty() && self.random_maps == 0,
                "--map and --random-maps are for --domain icy_gridworld"
            );
            return Ok(Vec::new());
        }
        let mut out = Vec::new();
        for path in &self.maps {
            out.push(Layout::from_file(path)?);
        }
        if out.is_empty() {
            out.push(Layout::default_map());
        }
        out.extend((0..self.random_maps as u64).map(Layout::random));
        let mut names = std::collections::HashSet::new();
        for l in &out {
            anyhow::ensure!(names.insert(&l.name), "two layouts are named {:?}", l.name);
        }
        Ok(out)
    }
}

/// The resolved settings of a harness run (recorded in the summary).
#[derive(Debug, Clone, Serialize)]
pub struct Config {
    /// The world.
    pub domain: DomainKind,
    /// The gridworld layout (`None`: the default map, or the water plant).
    pub layout: Option<Layout>,
    /// The MDE's noise model (`None`: the service's default).
    pub noise: Option<NoiseMode>,
    /// The MDE's kernel (`None`: the preset's).
    pub kernel: Option<KernelChoice>,
    /// The MDE's regressor (`None`: the service's).
    pub estimator: Option<EstimatorChoice>,
    /// The gridworld's MDE features.
    pub grid_features: GridFeatures,
    /// The continuous worlds' MDE features.
    pub kinematic_features: KinematicFeatures,
    /// The experiments' preset.
    pub preset: Preset,
    /// The MDE's label cap (`None`: the preset's).
    pub label_cap: Option<LabelCap>,
    /// Whether training proposals relax β (`None`: the preset's).
    pub relax_beta: Option<bool>,
    /// The acquisition's `c` (`None`: the service's).
    pub c: Option<f64>,
    /// The acquisition's aggregation (`None`: the service's).
    pub aggregation: Option<Aggregation>,
    /// The acquisition function (`None`: the preset's).
    pub acquisition: Option<AcquisitionKind>,
    /// Whether `active` fantasises the state-actions in flight (`None`: the preset's).
    pub batch_diversity: Option<bool>,
    /// The test β (`None`: the service's).
    pub test_beta: Option<f64>,
    /// Whether test plans use the certified β (`None`: the preset's).
    pub calibrate_test_beta: Option<bool>,
    /// Whether test plans use the local margin (`None`: the preset's).
    pub local_test_margin: Option<bool>,
    /// The β schedule's `k1` (`None`: the service's).
    pub k1: Option<f64>,
    /// The β schedule's `k2` (`None`: the service's).
    pub k2: Option<f64>,
    /// The β schedule's planned iterations (`None`: `iterations`).
    pub schedule_iterations: Option<u32>,
    /// `active`'s random first iterations (`None`: the preset's).
    pub warmup_iterations: Option<u32>,
    /// Seeds `0..seeds`.
    pub seeds: usize,
    /// Iterations per run.
    pub iterations: usize,
    /// Strategies, in report order.
    pub strategies: Vec<Strategy>,
    /// Training trajectories per iteration.
    pub batch_size: usize,
    /// Test problems per iteration.
    pub test_problems: usize,
    /// Candidates per proposal.
    pub n_candidates: u32,
    /// RRT extension budget.
    pub max_extensions: u32,
    /// Held-out pool trajectories per seed.
    pub pool_trajectories: usize,
    /// Problems a training slot tries.
    pub problem_tries: usize,
    /// The long search's factor over `max_extensions` (0: none).
    pub long_search: u32,
    /// Runs in flight at once.
    pub jobs: usize,
    /// Iterations at which the water plant's precondition maps are taken (first seed, the
    /// `active` run or else the first strategy's).
    pub map_iterations: Vec<usize>,
    /// Map grid `(columns, rows)`.
    pub map_resolution: (usize, usize),
    /// Tilt of the rotation-only map's actions (degrees).
    pub map_tilt_degrees: f64,
    /// Wait for a background refit at most this long.
    #[serde(skip)]
    pub fit_timeout: Duration,
}

impl Config {
    /// Resolves the command-line options against the defaults (paper or `--quick`).
    pub fn from_args(args: &ExperimentArgs) -> anyhow::Result<Self> {
        let q = args.quick;
        let pick =
            |v: Option<usize>, full: usize, quick: usize| v.unwrap_or(if q { quick } else { full });
        let iterations = pick(args.iterations, 20, 3);
        let strategies = if args.strategies.is_empty() {
            vec![
                Strategy::Active,
                Strategy::GoalConditioned,
                Strategy::Random,
            ]
        } else {
            let mut s = Vec::new();
            for x in &args.strategies {
                if !s.contains(x) {
                    s.push(*x);
                }
            }
            s
        };
        let cfg = Self {
            domain: args.domain,
            layout: None,
            noise: args.noise,
            kernel: args.kernel,
            estimator: args.estimator,
            grid_features: args.grid_features,
            kinematic_features: args.kinematic_features,
            preset: args.preset,
            label_cap: args.label_cap,
            relax_beta: args.relax_beta,
            c: args.c,
            aggregation: args.aggregation,
            acquisition: args.acquisition,
            batch_diversity: args.batch_diversity,
            test_beta: args.test_beta,
            calibrate_test_beta: args.calibrate_test_beta,
            local_test_margin: args.local_test_margin,
            k1: args.k1,
            k2: args.k2,
            schedule_iterations: args.schedule_iterations,
            warmup_iterations: args.warmup_iterations,
            seeds: pick(args.seeds, 10, 2),
            iterations,
            strategies,
            batch_size: pick(args.batch_size, 5, 5),
            test_problems: pick(args.test_problems, 20, 3),
            n_candidates: args.n_candidates.unwrap_or(if q { 5 } else { 20 }),
            max_extensions: args.max_extensions.unwrap_or(if q { 1000 } else { 5000 }),
            pool_trajectories: pick(args.pool_trajectories, 20, 6),
            problem_tries: args.problem_tries.max(1),
            long_search: args.long_search,
            jobs: args.jobs.max(1),
            map_iterations: {
                let mut m: Vec<usize> = [0, 5, 10, iterations.saturating_sub(1)]
                    .into_iter()
                    .filter(|&j| j < iterations)
                    .collect();
                m.dedup();
                m
            },
            map_resolution: if q { (36, 30) } else { (71, 61) },
            map_tilt_degrees: 140.0,
            fit_timeout: Duration::from_secs(args.fit_timeout.max(1)),
        };
        anyhow::ensure!(cfg.seeds >= 1, "--seeds must be at least 1");
        anyhow::ensure!(cfg.iterations >= 1, "--iterations must be at least 1");
        anyhow::ensure!(cfg.batch_size >= 1, "--batch-size must be at least 1");
        Ok(cfg)
    }
}

impl Config {
    /// The layout's name (`default` for the default map and for the water plant).
    pub fn layout_name(&self) -> &str {
        self.layout.as_ref().map_or("default", |l| &l.name)
    }
}

/// Every measurement of a harness run.
#[derive(Debug, Clone)]
pub struct Results {
    /// The settings.
    pub config: Config,
    /// Runs in strategy-then-seed order.
    pub runs: Vec<RunResult>,
    /// Held-out transitions per pool seed.
    pub pool_sizes: Vec<usize>,
    /// Wall-clock seconds of the whole run.
    pub seconds: f64,
    /// The service driven (URL).
    pub server: String,
}

/// Runs `precond experiment`: starts the service unless `--server` is given, runs the
/// protocol on every layout, writes the CSVs, the summary and the plots to `<out>/<domain>/`
/// (one subdirectory per layout when there are several, with `layouts.csv` beside them), and
/// returns the directory.
pub async fn run(args: ExperimentArgs) -> anyhow::Result<PathBuf> {
    let base = Config::from_args(&args)?;
    let layouts = args.layouts()?;
    let top = args.out.join(base.domain.as_str());
    let nested = layouts.len() > 1 || layouts.first().is_some_and(|l| l.name != "default");
    let mut all = Vec::new();
    for layout in layouts
        .iter()
        .map(Some)
        .chain(layouts.is_empty().then_some(None))
    {
        let cfg = Config {
            layout: layout.cloned(),
            ..base.clone()
        };
        let dir = match layout {
            Some(l) if nested => top.join(&l.name),
            _ => top.clone(),
        };
        if nested {
            eprintln!("layout {}", cfg.layout_name());
        }
        all.push(run_layout(&args, cfg, &dir).await?);
    }
    if nested {
        report::write_layouts(&top, &all)?;
    }
    Ok(top)
}

/// Runs the protocol for one layout and writes its files to `dir`.
async fn run_layout(args: &ExperimentArgs, cfg: Config, dir: &Path) -> anyhow::Result<Results> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let started = Instant::now();
    let results = match &args.server {
        Some(url) => {
            let client = ApiClient::new(url);
            client
                .health()
                .await
                .with_context(|| format!("the service at {url} does not answer"))?;
            run_protocol(&client, &cfg, !args.no_progress).await?
        }
        None => {
            let server = InProcess::start(&dir.join("precond.db")).await?;
            let out = run_protocol(&server.client, &cfg, !args.no_progress).await;
            server.stop().await?;
            out?
        }
    };
    let results = Results {
        seconds: started.elapsed().as_secs_f64(),
        ..results
    };
    report::write_all(dir, &results)?;
    plot::write_all(dir, &results)?;
    eprintln!(
        "{} runs in {:.0} s; results in {}",
        results.runs.len(),
        results.seconds,
        dir.display()
    );
    // The closing table, from the summary as written (what a reader of the files sees).
    println!("\n{}", report::summary_table_of(dir)?);
    Ok(results)
}

/// Logs to stderr at `warn` unless `RUST_LOG` says otherwise (the in-process service would
/// otherwise log every request among the progress lines).
pub fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// The service started in-process on `127.0.0.1:0`.
struct InProcess {
    client: ApiClient,
    shutdown: tokio::sync::oneshot::Sender<()>,
    handle: tokio::task::JoinHandle<anyhow::Result<()>>,
}

impl InProcess {
    /// Starts it over a fresh database at `db` (an existing one is removed).
    async fn start(db: &Path) -> anyhow::Result<Self> {
        for suffix in ["", "-wal", "-shm"] {
            let mut p = db.as_os_str().to_owned();
            p.push(suffix);
            let p = PathBuf::from(p);
            if p.exists() {
                std::fs::remove_file(&p).with_context(|| format!("removing {}", p.display()))?;
            }
        }
        let path = db.to_str().context("the database path is not UTF-8")?;
        let store = Store::open(path).await?;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        // The harness measures learning, not latency: searches may take up to
        // two minutes (a search past them counts as no plan found).
        let limits = precond::service::Limits {
            plan_timeout: std::time::Duration::from_secs(120),
            ..precond::service::Limits::default()
        };
        let state = AppState::with_service(
            precond::service::Service::new(store).with_limits(limits),
            HttpConfig {
                // Precondition maps and held-out sets are sent in one request each.
                max_body_bytes: 64 * 1024 * 1024,
                ..HttpConfig::default()
            },
        );
        let handle = tokio::spawn(serve(listener, state, async {
            let _ = rx.await;
        }));
        Ok(Self {
            client: ApiClient::new(&format!("http://{addr}")),
            shutdown: tx,
            handle,
        })
    }

    async fn stop(self) -> anyhow::Result<()> {
        let _ = self.shutdown.send(());
        self.handle.await.context("the in-process server task")?
    }
}

/// Builds the pools, then runs every strategy × seed, `cfg.jobs` at a time.
async fn run_protocol(
    client: &ApiClient,
    cfg: &Config,
    show_progress: bool,
) -> anyhow::Result<Results> {
    let bench = Arc::new(Bench::new(
        cfg.domain,
        cfg.layout.as_ref(),
        cfg.grid_features,
    )?);
    let n_runs = cfg.strategies.len() * cfg.seeds;
    let progress = if show_progress {
        ProgressBar::with_draw_target(
            Some((n_runs * cfg.iterations) as u64),
            ProgressDrawTarget::stderr(),
        )
    } else {
        ProgressBar::hidden()
    };
    progress.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} iterations (eta {eta}) {wide_msg}",
        )
        .map(|s| s.progress_chars("=> "))
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    // Held-out pools: at least two, so that every seed has another seed's pool.
    let n_pools = cfg.seeds.max(2);
    let mut pools: Vec<Vec<Labelled>> = Vec::with_capacity(n_pools);
    progress.set_message("executing the held-out pools");
    for k in 0..n_pools {
        pools.push(protocol::build_pool(client, &bench, cfg, k as u64).await?);
    }
    let pool_sizes = pools.iter().map(Vec::len).collect();
    let map_strategy = if cfg.strategies.contains(&Strategy::Active) {
        Strategy::Active
    } else {
        cfg.strategies[0]
    };
    let mut specs = Vec::with_capacity(n_runs);
    for seed in 0..cfg.seeds {
        let references = Arc::new(tokio::sync::Mutex::new(protocol::ReferenceCache::new()));
        let held_out: Vec<Labelled> = pools
            .iter()
            .enumerate()
            .filter(|(k, _)| *k != seed)
            .flat_map(|(_, p)| p.iter().cloned())
            .collect();
        let held_out = Arc::new(held_out);
        for &strategy in &cfg.strategies {
            specs.push(RunSpec {
                strategy,
                seed: seed as u64,
                held_out: held_out.clone(),
                maps: seed == 0 && strategy == map_strategy,
                references: references.clone(),
            });
        }
    }
    let semaphore = Arc::new(tokio::sync::Semaphore::new(cfg.jobs));
    let mut set = tokio::task::JoinSet::new();
    for (i, spec) in specs.into_iter().enumerate() {
        let (client, bench, cfg, progress, semaphore) = (
            client.clone(),
            bench.clone(),
            cfg.clone(),
            progress.clone(),
            semaphore.clone(),
        );
        set.spawn(async move {
            let _permit = semaphore.acquire_owned().await?;
            let r = protocol::run_one(&client, &bench, &cfg, &spec, &progress)
                .await
                .with_context(|| format!("run {} seed {}", spec.strategy.as_str(), spec.seed))?;
            anyhow::Ok((i, r))
        });
    }
    let mut runs: Vec<(usize, RunResult)> = Vec::with_capacity(n_runs);
    while let Some(joined) = set.join_next().await {
        runs.push(joined.context("a run task")??);
    }
    progress.finish_and_clear();
    // Strategy-then-seed order.
    runs.sort_by_key(|(i, _)| {
        let (seed, s) = (i / cfg.strategies.len(), i % cfg.strategies.len());
        (s, seed)
    });
    Ok(Results {
        config: cfg.clone(),
        runs: runs.into_iter().map(|(_, r)| r).collect(),
        pool_sizes,
        seconds: 0.0,
        server: client.base().to_string(),
    })
}
