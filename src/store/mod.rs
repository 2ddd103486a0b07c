//! The SQLite store: every sqlx query and the mapping between rows and the service's values, in
//! one place.
//!
//! SQLite serialises writers, so the store keeps two pools over the same file: a pool of readers
//! and a single-connection writer. Every write transaction goes through the writer, which makes
//! read-then-write transactions (idempotency checks, counters) free of `SQLITE_BUSY` upgrades.
//! The file is in WAL mode, so readers never wait for the writer.

mod activity;
mod experiments;
mod models;
mod proposals;
mod refusals;
mod trajectories;

pub use activity::{IterationStats, ModelSummary, Run, RunStatus};
pub use experiments::{Experiment, ListOrder};
pub use models::{FitRefusal, StoredModel};
pub use proposals::{NewProposal, ProposalPlan, ProposalStatus, ProposalTerms, StoredProposal};
pub use refusals::NewRefusal;
pub use trajectories::{
    IdempotencyKey, IngestOutcome, IngestRecord, Provenance, StoredTrajectory, StoredTransition,
    TrajectoryMeta,
};

use anyhow::Context;
use sqlx::SqlitePool;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use std::str::FromStr;
use std::time::Duration;

/// Handle to the database; cheap to clone.
#[derive(Debug, Clone)]
pub struct Store {
    read: SqlitePool,
    write: SqlitePool,
}

impl Store {
    /// Opens (creating if missing) the database at `url` (`sqlite://path` or a plain path), in WAL
    /// mode, and applies the embedded migrations.
    pub async fn open(url: &str) -> anyhow::Result<Self> {
        let url = if url.starts_with("sqlite:") {
            url.to_string()
        } else {
            format!("sqlite://{url}")
        };
        let options = SqliteConnectOptions::from_str(&url)
            .with_context(|| format!("invalid database URL {url:?}"))?
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Normal)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(10));
        let write = SqlitePoolOptions::new()
            .max_connections(1)
            .connect_with(options.clone())
            .await
            .with_context(|| format!("opening {url}"))?;
        sqlx::migrate!("./migrations")
            .run(&write)
            .await
            .context("applying migrations")?;
        let read = SqlitePoolOptions::new()
            .max_connections(8)
            .connect_with(options.read_only(true))
            .await
            .with_context(|| format!("opening {url} for reading"))?;
        Ok(Self { read, write })
    }

    /// Whether the database answers a trivial query.
    pub async fn ping(&self) -> Result<(), sqlx::Error> {
        sqlx::query("SELECT 1")
            .execute(&self.read)
            .await
            .map(|_| ())
    }

    /// Size of the database file in bytes (pages × page size; the WAL not included) and the
    /// numbers of experiments, trajectories and transitions stored.
    #[tracing::instrument(skip(self))]
    pub async fn size(&self) -> Result<StoreSize, sqlx::Error> {
        let (bytes, experiments, trajectories, transitions): (i64, i64, i64, i64) = sqlx::query_as(
            "SELECT (SELECT page_count FROM pragma_page_count())
                          * (SELECT page_size FROM pragma_page_size()),
                        (SELECT COUNT(*) FROM experiments),
                        (SELECT COUNT(*) FROM trajectories),
                        (SELECT COUNT(*) FROM transitions)",
        )
        .fetch_one(&self.read)
        .await?;
        Ok(StoreSize {
            bytes,
            experiments,
            trajectories,
            transitions,
        })
    }

    /// Writes a consistent copy of the database to the new file `path` while it is being
    /// served (`VACUUM INTO` on a reader: one read transaction, so writers are not blocked in WAL
    /// mode).
    #[tracing::instrument(skip(self))]
    pub async fn backup_to(&self, path: &str) -> Result<(), sqlx::Error> {
        sqlx::query("VACUUM INTO ?")
            .bind(path)
            .execute(&self.read)
            .await
            .map(|_| ())
    }

    /// Closes both pools, waiting for in-flight queries; the WAL is checkpointed on close.
    pub async fn close(&self) {
        self.read.close().await;
        self.write.close().await;
    }
}

/// Removes the temporary files that backups to `name` in `dir` left when they were killed
/// (`.<name>.backup-<pid>.tmp` and its `-journal`, hidden and never named): those whose process
/// no longer runs, or that carry this process's id (this backup has not written its own yet).
/// A backup that still runs keeps its file. Returns how many were removed.
fn remove_stale_temporaries(dir: &std::path::Path, name: &str) -> usize {
    let prefix = format!(".{name}.backup-");
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let mut removed = 0;
    for entry in entries.flatten() {
        let file = entry.file_name();
        let Some(pid) = file.to_str().and_then(|f| {
            let rest = f.strip_prefix(&prefix)?;
            let pid = rest
                .strip_suffix(".tmp")
                .or_else(|| rest.strip_suffix(".tmp-journal"))?;
            pid.parse::<u32>().ok()
        }) else {
            continue;
        };
        if (pid == std::process::id() || !process_runs(pid))
            && std::fs::remove_file(entry.path()).is_ok()
        {
            removed += 1;
        }
    }
    removed
}

/// Whether a process with id `pid` runs (on platforms where that cannot be asked: yes).
fn process_runs(pid: u32) -> bool {
    #[cfg(unix)]
    {
        let Ok(pid) = libc::pid_t::try_from(pid) else {
            return false;
        };
        // SAFETY: signal 0 sends nothing; `kill` only checks that the process exists and may
        // be signalled (EPERM: it exists, owned by someone else).
        let rc = unsafe { libc::kill(pid, 0) };
        rc == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
    }
    #[cfg(not(unix))]
    {
        let _ = pid;
        true
    }
}

/// Copies the database at `source` (a path or `sqlite://` URL, which must exist: it is opened
/// read-only, never created and never migrated) to the new file `to` while it may be served,
/// and returns what the copy holds, counted in the copy itself.
///
/// The copy is a consistent snapshot (`VACUUM INTO` in one read transaction; in WAL mode
/// writers are not blocked). It is written under a temporary name beside `to`, checked
/// (`PRAGMA quick_check`), counted, flushed to disk and only then linked to `to`, which must not
/// exist: a backup that is killed or fails leaves nothing under the final name (at most the
/// temporary file, named `.<file>.backup-<pid>.tmp`, removed on failure when possible, and by
/// the next backup to the same name when its process was killed).
pub async fn backup(source: &str, to: &std::path::Path) -> anyhow::Result<StoreSize> {
    use sqlx::{ConnectOptions, Connection};
    let url = if source.starts_with("sqlite:") {
        source.to_string()
    } else {
        format!("sqlite://{source}")
    };
    let options = SqliteConnectOptions::from_str(&url)
        .with_context(|| format!("invalid database URL {url:?}"))?
        .create_if_missing(false)
        .read_only(true)
        .busy_timeout(Duration::from_secs(10));
    let file = options.get_filename().to_path_buf();
    anyhow::ensure!(
        file.is_file(),
        "the database {} does not exist (a backup never creates one: check --database-url)",
        file.display()
    );
    anyhow::ensure!(
        !to.exists(),
        "{} exists; a backup goes to a new file",
        to.display()
    );
    let name = to
        .file_name()
        .and_then(|n| n.to_str())
        .context("the backup path names no file")?;
    let dir = match to.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    anyhow::ensure!(
        dir.is_dir(),
        "the directory {} of the backup does not exist",
        dir.display()
    );
    let stale = remove_stale_temporaries(&dir, name);
    if stale > 0 {
        tracing::warn!(
            removed = stale,
            "removed the temporary files of earlier backups to {} that did not finish",
            to.display()
        );
    }
    let tmp = dir.join(format!(".{name}.backup-{}.tmp", std::process::id()));
    let tmp_str = tmp.to_str().context("the backup path is not UTF-8")?;
    let remove_tmp = || {
        let _ = std::fs::remove_file(&tmp);
        let _ = std::fs::remove_file(format!("{tmp_str}-journal"));
    };
    let written = async {
        let mut source = options
            .connect()
            .await
            .with_context(|| format!("opening {} read-only", file.display()))?;
        sqlx::query("VACUUM INTO ?")
            .bind(tmp_str)
            .execute(&mut source)
            .await
            .with_context(|| format!("writing the copy {tmp_str}"))?;
        source.close().await?;
        let mut copy = SqliteConnectOptions::new()
            .filename(&tmp)
            .read_only(true)
            .connect()
            .await
            .context("opening the copy")?;
        let check: String = sqlx::query_scalar("PRAGMA quick_check")
            .fetch_one(&mut copy)
            .await?;
        anyhow::ensure!(check == "ok", "the copy fails its integrity check: {check}");
        let (experiments, trajectories, transitions): (i64, i64, i64) = sqlx::query_as(
            "SELECT (SELECT COUNT(*) FROM experiments), (SELECT COUNT(*) FROM trajectories),
                    (SELECT COUNT(*) FROM transitions)",
        )
        .fetch_one(&mut copy)
        .await
        .context("counting the copy's rows")?;
        copy.close().await?;
        std::fs::File::open(&tmp)?.sync_all()?;
        let bytes = std::fs::metadata(&tmp)?.len() as i64;
        anyhow::Ok(StoreSize {
            bytes,
            experiments,
            trajectories,
            transitions,
        })
    }
    .await;
    let size = match written {
        Ok(size) => size,
        Err(e) => {
            remove_tmp();
            return Err(e);
        }
    };
    // A hard link never replaces a file that appeared meanwhile; the directory entry is then
    // flushed so the name survives a crash.
    if let Err(e) = std::fs::hard_link(&tmp, to) {
        remove_tmp();
        return Err(anyhow::Error::new(e).context(format!("naming the copy {}", to.display())));
    }
    remove_tmp();
    if let Ok(d) = std::fs::File::open(&dir) {
        let _ = d.sync_all();
    }
    Ok(size)
}

/// How much a store holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StoreSize {
    /// Bytes of the database file (WAL excluded).
    pub bytes: i64,
    /// Experiments.
    pub experiments: i64,
    /// Trajectories, over all experiments.
    pub trajectories: i64,
    /// Transitions, over all experiments.
    pub transitions: i64,
}

/// The current time as an RFC 3339 UTC string, the store's time format.
pub fn now() -> String {
    timestamp(time::OffsetDateTime::now_utc())
}

/// `t` as the store writes times: RFC 3339 in UTC with exactly nine fractional digits, so that
/// comparing two as text compares them in time (SQLite's date functions keep milliseconds only,
/// and rows stored within one millisecond must still sort in the order they were made).
pub fn timestamp(t: time::OffsetDateTime) -> String {
    const FORMAT: &[time::format_description::BorrowedFormatItem<'_>] = time::macros::format_description!(
        "[year]-[month]-[day]T[hour]:[minute]:[second].[subsecond digits:9]Z"
    );
    t.to_offset(time::UtcOffset::UTC)
        .format(FORMAT)
        .unwrap_or_default()
}

/// Encodes a vector as a JSON array for a TEXT column.
fn encode_vec(v: &[f64]) -> String {
    serde_json::to_string(v).unwrap_or_else(|_| "[]".into())
}

/// Decodes a TEXT column written by [`encode_vec`].
fn decode_vec(s: &str) -> Result<Vec<f64>, sqlx::Error> {
    serde_json::from_str(s).map_err(|e| sqlx::Error::Decode(Box::new(e)))
}
