//! `precond import`: logged transitions (CSV or Parquet files) into an existing experiment.
//!
//! Each episode of a file becomes one posted trajectory, labelled by the experiment's own model
//! on ingest like any other, with its provenance (`source`: the file, the episode, the step of
//! the episode it starts at, a label). Columns are found by convention or named by the user
//! (`precond::import::mapping`); without a next-state column, a transition's next state is the next row's
//! state within the episode (LeRobot's frames).
//!
//! **Resumable and idempotent, per episode.** Each trajectory is posted under the
//! `Idempotency-Key` `import-<dataset>-<episode>-<part>`, where `<dataset>` is the first 16 hex
//! digits of the SHA-256 of the dataset's name (by default the file's absolute path, so the
//! working directory does not matter; or `--dataset-id`). The key does not depend on the
//! file's bytes: running an import again — after an interruption, after the log grew, after a
//! bad line was fixed — stores only the episodes not stored yet (the service replays the
//! others), and an episode whose content, mapping or label changed since it was stored is
//! refused by name (`409`, naming the first field that differs) rather than stored twice.
//!
//! **Streaming.** Files are read row by row (CSV) or row group by row group (Parquet, only the
//! columns the mapping reads) on a blocking thread that hands finished trajectories to the
//! poster through a bounded channel; memory holds about two trajectories. An episode longer
//! than `--max-transitions` (the server's limit, 10 000 by default), or whose body would pass
//! `--max-body-bytes`, is split into consecutive trajectories, each saying its first step, and
//! the import says so.

use anyhow::Context;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use precond::api::{ErrorBody, ExperimentResponse, TrajectoryCreated, TrajectoryRequest};
use precond::import::{
    Assembly, Part, Progress, Reading, Stopped, Stored, drive,
    mapping::{self, Given, Spaces},
    table::{self, Format},
};
pub use precond::import::{ImportReport, dataset_identity};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The formats `precond import` reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FormatArg {
    /// From the file's extension (`.parquet`/`.pq` is Parquet, anything else CSV).
    Auto,
    /// Comma-separated values with a header row.
    Csv,
    /// Apache Parquet.
    Parquet,
}

impl From<FormatArg> for Format {
    fn from(f: FormatArg) -> Self {
        match f {
            FormatArg::Auto => Self::Auto,
            FormatArg::Csv => Self::Csv,
            FormatArg::Parquet => Self::Parquet,
        }
    }
}

/// Options of `precond import`.
#[derive(Debug, Clone, clap::Args)]
pub struct ImportArgs {
    /// The files to import (CSV or Parquet), each one dataset.
    #[arg(required = true, value_name = "FILE")]
    pub files: Vec<PathBuf>,
    /// The experiment to import into (it must exist; its model labels every transition).
    #[arg(long)]
    pub experiment: i64,
    /// The server.
    #[arg(long, env = "PRECOND_URL", default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// An access token with the `write` role (sent as `Authorization: Bearer`).
    #[arg(long, env = "PRECOND_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// The files' format; `auto` decides by extension (`.parquet`, `.pq`: Parquet).
    #[arg(long, value_enum, default_value_t = FormatArg::Auto)]
    pub format: FormatArg,
    /// The state's columns, comma-separated in the state's order, or one list column.
    /// Default: found by convention (`s.<name>`, `s_<name>`, `observation.state`).
    #[arg(long, value_delimiter = ',')]
    pub state: Option<Vec<String>>,
    /// The action's columns, likewise (`a.<name>`, `a_<name>`, `action`).
    #[arg(long, value_delimiter = ',')]
    pub action: Option<Vec<String>>,
    /// The next state's columns (`s_next.<name>`, `s_next_<name>`). Without them a
    /// transition's next state is the next row's state within the episode.
    #[arg(long, value_delimiter = ',')]
    pub next_state: Option<Vec<String>>,
    /// The client's predicted next state (`s_pred.<name>`), for an experiment whose model is
    /// the client's.
    #[arg(long, value_delimiter = ',')]
    pub predicted_state: Option<Vec<String>>,
    /// The episode column (`none`: one episode per file). Default: the first of
    /// `episode_index`, `episode`, `episode_id`, `trajectory_id`. Rows of an episode must be
    /// consecutive and in time order.
    #[arg(long)]
    pub episode: Option<String>,
    /// A free-form label stored with every trajectory's source.
    #[arg(long)]
    pub label: Option<String>,
    /// The source's dataset name. Default: the file's absolute path (the same from any
    /// working directory). Name it to import a moved file as the same dataset.
    #[arg(long)]
    pub dataset_name: Option<String>,
    /// The dataset's identity in the idempotency keys (letters, digits, `.`, `_`, `-`; at
    /// most 64). Default: the first 16 hex digits of the SHA-256 of the dataset's name.
    #[arg(long)]
    pub dataset_id: Option<String>,
    /// Transitions per posted trajectory: longer episodes are split. Set it to the server's
    /// `--max-transitions` when that is lower than the default.
    #[arg(long, default_value_t = precond_core::limits::MAX_TRANSITIONS)]
    pub max_transitions: usize,
    /// Largest request body: an episode whose JSON would be larger is split. Set it to the
    /// server's `--max-body-bytes` when that is lower than the default.
    #[arg(long, default_value_t = precond::limits::DEFAULT_MAX_BODY_BYTES)]
    pub max_body_bytes: usize,
    /// No progress bar.
    #[arg(long)]
    pub no_progress: bool,
}

/// The default dataset name of a file: its absolute path, links resolved when it exists.
pub fn default_dataset_name(path: &Path) -> String {
    std::fs::canonicalize(path)
        .or_else(|_| std::path::absolute(path))
        .unwrap_or_else(|_| path.to_path_buf())
        .display()
        .to_string()
}

/// Lines in a file (a CSV file's progress: rows are lines but one).
fn count_lines(path: &Path) -> anyhow::Result<u64> {
    let mut file =
        std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut buf = vec![0u8; 1 << 20];
    let mut lines = 0u64;
    loop {
        let n = file
            .read(&mut buf)
            .with_context(|| format!("reading {}", path.display()))?;
        if n == 0 {
            return Ok(lines);
        }
        lines += buf[..n].iter().filter(|&&b| b == b'\n').count() as u64;
    }
}

/// The HTTP side: posts with retries (transport errors, `429` and `5xx`, with back-off; the
/// idempotency key makes a repeat harmless).
struct Poster {
    http: reqwest::Client,
    base: String,
    token: Option<String>,
}

impl Poster {
    fn request(&self, method: reqwest::Method, path: &str) -> reqwest::RequestBuilder {
        let r = self.http.request(method, format!("{}{path}", self.base));
        match &self.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }

    /// The error of an answer, as the service said it.
    async fn error(what: &str, r: reqwest::Response) -> anyhow::Error {
        let status = r.status().as_u16();
        let text = r.text().await.unwrap_or_default();
        match serde_json::from_str::<ErrorBody>(&text) {
            Ok(e) => anyhow::anyhow!(
                "{what}: HTTP {status} {}: {}",
                e.error.code,
                e.error.message
            ),
            Err(_) => anyhow::anyhow!("{what}: HTTP {status}: {text}"),
        }
    }

    async fn experiment(&self, id: i64) -> anyhow::Result<ExperimentResponse> {
        let what = format!("GET /v1/experiments/{id}");
        let r = self
            .request(reqwest::Method::GET, &format!("/v1/experiments/{id}"))
            .send()
            .await
            .with_context(|| format!("{what}: is the server at {} running?", self.base))?;
        if !r.status().is_success() {
            return Err(Self::error(&what, r).await);
        }
        r.json()
            .await
            .with_context(|| format!("{what}: unexpected body"))
    }

    /// Posts one part; `Ok((answer, replayed))`.
    async fn post(&self, id: i64, part: Part) -> anyhow::Result<(TrajectoryCreated, bool)> {
        let (episode, first_step) = (
            part.source.episode.unwrap_or_default(),
            part.source.first_step.unwrap_or_default(),
        );
        let dataset = part.source.dataset.clone();
        let key = part.key;
        let body = TrajectoryRequest {
            proposal_id: None,
            partial: false,
            source: Some(part.source),
            transitions: part.transitions,
        };
        let path = format!("/v1/experiments/{id}/trajectories");
        let mut delay = Duration::from_millis(200);
        for attempt in 0.. {
            let sent = self
                .request(reqwest::Method::POST, &path)
                .header("idempotency-key", &key)
                .json(&body)
                .send()
                .await;
            let retry = match &sent {
                Err(e) => Some(e.to_string()),
                Ok(r) if r.status().as_u16() == 429 || r.status().is_server_error() => {
                    Some(format!("HTTP {}", r.status()))
                }
                Ok(_) => None,
            };
            match (retry, sent) {
                (Some(why), _) if attempt < 8 => {
                    tracing::warn!(key = %key, %why, "retrying in {delay:?}");
                    tokio::time::sleep(delay).await;
                    delay = (delay * 2).min(Duration::from_secs(10));
                }
                (_, Err(e)) => return Err(anyhow::Error::new(e).context(format!("POST {path}"))),
                (_, Ok(r)) => {
                    let status = r.status().as_u16();
                    if status == 201 {
                        let replayed = r.headers().contains_key("idempotent-replayed");
                        let created = r.json().await.context("the 201 answer")?;
                        return Ok((created, replayed));
                    }
                    let err = Self::error(&format!("POST {path}"), r).await;
                    return Err(match status {
                        409 => err.context(format!(
                            "episode {} (from step {}) of dataset {:?} was imported before and \
                             differs now (its rows, the column mapping or the label changed); \
                             nothing was stored for it — import it under another --dataset-name \
                             to keep both",
                            episode, first_step, dataset
                        )),
                        413 => err.context(
                            "lower --max-body-bytes (or --max-transitions) to the server's limit",
                        ),
                        _ => err,
                    });
                }
            }
        }
        unreachable!("the loop returns")
    }
}

/// Prints a line above the progress bar (also when stderr is no terminal and the bar is hidden).
fn say(progress: &ProgressBar, line: String) {
    progress.suspend(|| eprintln!("{line}"));
}

/// Imports one file into the experiment.
async fn import_file(
    args: &ImportArgs,
    poster: &Poster,
    spaces: &Spaces,
    path: &Path,
    progress: &ProgressBar,
) -> anyhow::Result<ImportReport> {
    let format = Format::from(args.format);
    let (columns, n_rows) =
        table::columns(path, format).with_context(|| path.display().to_string())?;
    let given = Given {
        as_query: false,
        state: args.state.clone(),
        action: args.action.clone(),
        next_state: args.next_state.clone(),
        predicted: args.predicted_state.clone(),
        episode: args.episode.clone(),
    };
    let mapping =
        mapping::resolve(&columns, spaces, &given).with_context(|| path.display().to_string())?;
    let dataset = args
        .dataset_name
        .clone()
        .unwrap_or_else(|| default_dataset_name(path));
    let dataset_id = precond::import::dataset_id(args.dataset_id.as_deref(), &dataset)
        .map_err(|reason| anyhow::anyhow!("--dataset-id: {reason}"))?;
    let total = match n_rows {
        Some(n) => n,
        None => {
            let file = path.to_path_buf();
            tokio::task::spawn_blocking(move || count_lines(&file))
                .await
                .context("counting the file's lines")??
                .saturating_sub(1)
        }
    };
    progress.set_length(progress.length().unwrap_or(0) + total);
    say(
        progress,
        format!(
            "{}: {total} rows; {}; dataset id {dataset_id}",
            path.display(),
            mapping.describe(&columns)
        ),
    );

    let reading = Reading {
        path: path.to_path_buf(),
        format,
        columns,
        mapping,
        dims: (spaces.state.len(), spaces.action.len()),
        assembly: Assembly {
            dataset: dataset.clone(),
            dataset_id,
            label: args.label.clone(),
            max_transitions: args.max_transitions,
            max_body_bytes: args.max_body_bytes,
        },
    };
    let store = |part: Part| async move {
        let (episode, first_step) = (part.source.episode, part.source.first_step);
        let stored = poster.post(args.experiment, part).await;
        let (created, replayed) = stored.with_context(|| {
            format!(
                "{} episode {} (from step {})",
                path.display(),
                episode.unwrap_or_default(),
                first_step.unwrap_or_default()
            )
        })?;
        anyhow::Ok(Stored {
            id: created.trajectory.id,
            transitions: created.n_transitions,
            replayed,
        })
    };
    let shown = |event: Progress<'_>| match event {
        Progress::Stored { rows, report } => {
            progress.inc(rows);
            progress.set_message(format!(
                "{} trajectories stored, {} already there",
                report.created, report.replayed
            ));
        }
        Progress::Split(episode, length, parts) => say(
            progress,
            format!(
                "{}: episode {episode} has {length} transitions, posted as {parts} \
                 trajectories (at most {} transitions or {} bytes each)",
                path.display(),
                args.max_transitions,
                args.max_body_bytes
            ),
        ),
    };
    drive(reading, store, shown)
        .await
        .map_err(|stopped| match stopped {
            Stopped::Storing { error, .. } => error,
            Stopped::Reading { error, .. } => error.context(path.display().to_string()),
            Stopped::Reader(e) => anyhow::anyhow!(
                "reading {}: the reader failed ({e}); the file may be damaged",
                path.display()
            ),
        })
}

/// Runs `precond import`: every file in turn into the experiment; returns what was done in
/// all (also printed).
pub async fn run(args: ImportArgs) -> anyhow::Result<ImportReport> {
    let poster = Poster {
        http: reqwest::Client::builder()
            .timeout(Duration::from_secs(300))
            .build()?,
        base: args.server.trim_end_matches('/').to_string(),
        token: args.token.clone(),
    };
    let experiment = poster.experiment(args.experiment).await?;
    let domain = serde_json::to_value(&experiment.settings.domain)?;
    let spaces = Spaces {
        state: experiment.state_space.names.clone(),
        action: experiment.action_space.names.clone(),
        client_side: domain["kind"] == "custom" && domain["model"]["kind"] == "client",
    };
    let progress = if args.no_progress {
        ProgressBar::hidden()
    } else {
        ProgressBar::with_draw_target(Some(0), ProgressDrawTarget::stderr())
    };
    progress.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} rows {wide_msg}")
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut total = ImportReport::default();
    for path in &args.files {
        let report = import_file(&args, &poster, &spaces, path, &progress).await?;
        say(
            &progress,
            format!(
                "{}: {} episodes as {} trajectories ({} transitions): {} stored, {} already there{}{}",
                path.display(),
                report.episodes,
                report.trajectories,
                report.transitions,
                report.created,
                report.replayed,
                if report.split_episodes > 0 {
                    format!("; {} episodes split", report.split_episodes)
                } else {
                    String::new()
                },
                if report.skipped_episodes > 0 {
                    format!(
                        "; {} single-frame episodes skipped",
                        report.skipped_episodes
                    )
                } else {
                    String::new()
                },
            ),
        );
        total.add(&report);
    }
    progress.finish_and_clear();
    println!(
        "imported into experiment {}: {} episodes, {} trajectories, {} transitions ({} stored now, \
         {} already stored)",
        args.experiment,
        total.episodes,
        total.trajectories,
        total.transitions,
        total.created,
        total.replayed
    );
    Ok(total)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_files_dataset_does_not_depend_on_the_working_directory() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("log.csv");
        std::fs::write(&file, "x\n").unwrap();
        let sub = dir.path().join("sub");
        std::fs::create_dir(&sub).unwrap();
        let roundabout = sub.join("..").join("log.csv");
        assert_eq!(
            default_dataset_name(&file),
            default_dataset_name(&roundabout)
        );
        assert_eq!(
            dataset_identity(&default_dataset_name(&file)),
            dataset_identity(&default_dataset_name(&roundabout))
        );
        // The key is the name's hash, not the content's: a grown file keeps its identity.
        let before = dataset_identity(&default_dataset_name(&file));
        std::fs::write(&file, "x\n1\n").unwrap();
        assert_eq!(before, dataset_identity(&default_dataset_name(&file)));
        assert_eq!(dataset_identity("logs/run3.csv").len(), 16);
    }
}
