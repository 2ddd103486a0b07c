//! The store: every SQL query and the mapping between rows and the service's values, in one
//! place, over SQLite (the embedded default, one process) or PostgreSQL (several replicas over
//! one database).
//!
//! Queries go through sqlx's `Any` driver and are written once, in SQL both engines accept:
//! `$1` parameters, `CAST(… AS DOUBLE PRECISION)` where PostgreSQL would answer `NUMERIC`,
//! `FALSE`/`TRUE` for flags (SQLite stores them as 0/1, read back by `flag`). **No `Option<f64>`
//! is bound**: sqlx 0.8.6's `Any` driver sends a NULL `f64` to PostgreSQL as a `float4` (its
//! `f32` and `f64` NULLs are swapped, transact-rs/sqlx#4284), which fixes that parameter's type
//! in the cached statement, and an `f64` bound there later is refused ("incorrect binary data
//! format"); a missing number is written as a `NULL` literal in a statement of its own. Other
//! `Option`s (`i64`, strings, flags) are sent with their own types and bind safely. Where the
//! engines differ (the file's size, ordering old timestamps, claiming a fit), [`Backend`] says
//! which text runs. Each engine has its own migrations (`migrations/sqlite`,
//! `migrations/postgres`), both applied at start-up.
//!
//! **What replicas agree on lives here.** A write transaction that reads before it writes
//! (an idempotency key, an open lease, the next model version, the experiment count) first
//! takes the experiment's lock (`lock_experiment`): on PostgreSQL a transaction-scoped
//! advisory lock, so such transactions of one experiment run one at a time across every
//! replica; on SQLite a no-op, because every write already goes through the one writer
//! connection. The right to fit is a row ([`fits`](mod@fits)).
//!
//! SQLite serialises writers, so the store keeps two pools over the same file: a pool of readers
//! and a single-connection writer. Every write transaction goes through the writer, which makes
//! read-then-write transactions (idempotency checks, counters) free of `SQLITE_BUSY` upgrades.
//! The file is in WAL mode, so readers never wait for the writer. A SQLite file is served by
//! one process; several replicas need PostgreSQL.

mod activity;
mod exclusions;
mod experiments;
pub mod fits;
mod health;
mod models;
mod proposals;
mod refusals;
mod serving;
mod trajectories;
mod transaction;

pub use exclusions::{Exclusion, ExclusionOutcome, ExclusionScope, ExclusionSet, RestoreOutcome};
pub use experiments::Experiment;
pub use fits::{FitClaim, FitJob};
pub use health::{Failure, classify};
pub use models::{StoredFurther, StoredModel};
pub use proposals::{Inserted, NewProposal, OpenPlan, ProposalPlan, StoredProposal};
pub use refusals::NewRefusal;
pub use serving::{ServingLock, lock_for_serving};
pub use trajectories::{
    IdempotencyKey, IngestOutcome, IngestRecord, LabelStats, StoredTrajectory, TrajectoryMeta,
};

pub use crate::records::{now, timestamp};

use anyhow::Context;
use health::WriteHealth;
use sqlx::any::{AnyConnectOptions, AnyPoolOptions, AnyRow};
use sqlx::sqlite::SqliteConnectOptions;
use sqlx::{AnyConnection, AnyPool, ConnectOptions, Row};
use std::str::FromStr;
use std::sync::Arc;
use std::time::Duration;
use transaction::WriteTx;

/// The database engine behind a [`Store`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    /// An embedded SQLite file, served by one process.
    Sqlite,
    /// A PostgreSQL database, shared by any number of replicas.
    Postgres,
}

impl Backend {
    /// The engine a `--database-url` names: `postgres://` or `postgresql://` is PostgreSQL,
    /// anything else a SQLite file (a path or a `sqlite:` URL).
    pub fn of_url(url: &str) -> Self {
        if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            Self::Postgres
        } else {
            Self::Sqlite
        }
    }

    /// `sqlite` or `postgres`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Sqlite => "sqlite",
            Self::Postgres => "postgres",
        }
    }
}

/// Connections a PostgreSQL replica keeps open at most.
const POSTGRES_CONNECTIONS: u32 = 16;

/// How long `precond serve` waits at start-up for a PostgreSQL database to answer.
const STARTUP_WAIT: Duration = Duration::from_secs(30);

/// How long a request waits for a PostgreSQL connection by default before it is answered
/// `503 unavailable` (the database down or every connection busy).
pub const DEFAULT_DATABASE_TIMEOUT: Duration = Duration::from_secs(2);

/// Handle to the database; cheap to clone.
#[derive(Debug, Clone)]
pub struct Store {
    read: AnyPool,
    write: AnyPool,
    backend: Backend,
    /// Whether writes are failing for lack of space (shared by the clones).
    health: Arc<WriteHealth>,
}

/// `url` as a SQLite URL with an absolute path (a relative `sqlite://Name.db` would otherwise
/// be read as a host name, lower-cased).
fn sqlite_options(url: &str) -> anyhow::Result<SqliteConnectOptions> {
    let options = if url.starts_with("sqlite:") {
        SqliteConnectOptions::from_str(url)
    } else {
        Ok(SqliteConnectOptions::new().filename(url))
    }
    .with_context(|| format!("invalid database URL {url:?}"))?;
    let file = options.get_filename();
    let absolute = std::path::absolute(file)
        .with_context(|| format!("the database path {}", file.display()))?;
    Ok(options.filename(absolute))
}

/// A pool of `max` connections to the SQLite file of `options`, each set up as the store
/// needs (WAL, foreign keys, a busy timeout).
async fn sqlite_pool(options: &SqliteConnectOptions, max: u32) -> Result<AnyPool, sqlx::Error> {
    let url = options.to_url_lossy();
    AnyPoolOptions::new()
        .max_connections(max)
        .after_connect(|conn, _| {
            Box::pin(async move {
                for pragma in [
                    "PRAGMA journal_mode = WAL",
                    "PRAGMA synchronous = NORMAL",
                    "PRAGMA foreign_keys = ON",
                    "PRAGMA busy_timeout = 10000",
                ] {
                    sqlx::query(pragma).execute(&mut *conn).await?;
                }
                Ok(())
            })
        })
        .connect_with(AnyConnectOptions::from_url(&url)?)
        .await
}

impl Store {
    /// Opens the database at `url` and applies the embedded migrations: a PostgreSQL
    /// database for `postgres://…` (it must exist; replicas may open it at the same time), else
    /// a SQLite file (`sqlite://path` or a plain path; created if missing, WAL mode).
    pub async fn open(url: &str) -> anyhow::Result<Self> {
        Self::open_with_timeout(url, DEFAULT_DATABASE_TIMEOUT).await
    }

    /// [`Store::open`], a request waiting at most `timeout` for a PostgreSQL connection (a
    /// database that is down is then a `503` within that time, not a hang).
    pub async fn open_with_timeout(url: &str, timeout: Duration) -> anyhow::Result<Self> {
        sqlx::any::install_default_drivers();
        match Backend::of_url(url) {
            Backend::Sqlite => Self::open_sqlite(url).await,
            Backend::Postgres => Self::open_postgres(url, timeout).await,
        }
    }

    async fn open_sqlite(url: &str) -> anyhow::Result<Self> {
        let options = sqlite_options(url)?.create_if_missing(true);
        let shown = options.get_filename().display().to_string();
        let write = sqlite_pool(&options, 1)
            .await
            .with_context(|| format!("opening {shown}"))?;
        sqlx::migrate!("../../migrations/sqlite")
            .run(&write)
            .await
            .context("applying migrations")?;
        let read = sqlite_pool(&options.read_only(true), 8)
            .await
            .with_context(|| format!("opening {shown} for reading"))?;
        Ok(Self {
            read,
            write,
            backend: Backend::Sqlite,
            health: Arc::default(),
        })
    }

    async fn open_postgres(url: &str, timeout: Duration) -> anyhow::Result<Self> {
        let shown = redact(url);
        let pool = AnyPoolOptions::new()
            .max_connections(POSTGRES_CONNECTIONS)
            .acquire_timeout(timeout)
            .connect_lazy(url)
            .with_context(|| format!("connecting to {shown}"))?;
        // A database starting beside the server (a compose file, a reboot) may take a while:
        // wait for it, then every request waits at most `timeout`.
        let started = std::time::Instant::now();
        loop {
            match pool.acquire().await {
                Ok(_) => break,
                Err(e)
                    if started.elapsed() < STARTUP_WAIT && classify(&e) == Failure::Unreachable =>
                {
                    tracing::warn!(error = %e, database = %shown, "waiting for the database");
                    tokio::time::sleep(Duration::from_millis(500)).await;
                }
                Err(e) => {
                    return Err(anyhow::Error::new(e).context(format!("connecting to {shown}")));
                }
            }
        }
        // sqlx holds an advisory lock while it migrates: replicas starting together take turns.
        sqlx::migrate!("../../migrations/postgres")
            .run(&pool)
            .await
            .context("applying migrations")?;
        Ok(Self {
            read: pool.clone(),
            write: pool,
            backend: Backend::Postgres,
            health: Arc::default(),
        })
    }

    /// The engine.
    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// Whether the database answers a trivial query.
    pub async fn ping(&self) -> Result<(), sqlx::Error> {
        sqlx::query("SELECT 1")
            .execute(&self.read)
            .await
            .map(|_| ())
    }

    /// Whether the store can serve reads and writes now, answered within `timeout`: the
    /// database answers a trivial query, and writes are not failing for lack of space. While
    /// they are, a write that allocates pages as an ingest does is probed at most once a
    /// second, so readiness comes back once space is freed even if no client writes.
    pub async fn readiness(&self, timeout: Duration) -> Result<(), NotReady> {
        match tokio::time::timeout(timeout, self.ping()).await {
            Err(_) => {
                return Err(NotReady::Unreachable(format!(
                    "no answer within {} ms",
                    timeout.as_millis()
                )));
            }
            Ok(Err(e)) => return Err(NotReady::Unreachable(e.to_string())),
            Ok(Ok(())) => {}
        }
        if self.health.full().is_some() && self.health.may_probe() {
            // Its outcome is noted like any write's; a probe that outlasts the timeout (the
            // writer busy with a long ingest) leaves the state as it was.
            let _ = tokio::time::timeout(timeout, self.probe_write()).await;
        }
        match self.health.full() {
            Some((since, error)) => Err(NotReady::Full { since, error }),
            None => Ok(()),
        }
    }

    /// Replaces the write probe's row with 64 KiB of fresh random text in one transaction.
    async fn probe_write(&self) -> Result<(), sqlx::Error> {
        use rand::Rng;
        let padding: String = {
            let mut rng = rand::rng();
            (0..65_536)
                .map(|_| char::from(b'a' + rng.random_range(0..26u8)))
                .collect()
        };
        self.noted(async {
            let mut tx = self.begin_write().await?;
            sqlx::query("DELETE FROM write_probe")
                .execute(&mut *tx)
                .await?;
            sqlx::query("INSERT INTO write_probe (written_at, padding) VALUES ($1, $2)")
                .bind(now())
                .bind(padding)
                .execute(&mut *tx)
                .await?;
            tx.commit().await
        })
        .await
    }

    /// A write transaction on the writer (see [`transaction`](mod@transaction)); its commit
    /// ends a lack of space noted before.
    async fn begin_write(&self) -> Result<WriteTx, sqlx::Error> {
        WriteTx::begin(&self.write, self.backend, self.health.clone()).await
    }

    /// Runs a write and notes when it failed for lack of space: every method that writes goes
    /// through here.
    async fn noted<T>(
        &self,
        write: impl std::future::Future<Output = Result<T, sqlx::Error>>,
    ) -> Result<T, sqlx::Error> {
        let outcome = write.await;
        if let Err(e) = &outcome {
            self.health.failed(e);
        }
        outcome
    }

    /// Size of the database in bytes (SQLite: the file's pages, the WAL not included;
    /// PostgreSQL: the whole database) and the numbers of experiments, trajectories and
    /// transitions stored.
    #[tracing::instrument(skip(self))]
    pub async fn size(&self) -> Result<StoreSize, sqlx::Error> {
        let bytes = match self.backend {
            Backend::Sqlite => {
                "(SELECT page_count FROM pragma_page_count())
                 * (SELECT page_size FROM pragma_page_size())"
            }
            Backend::Postgres => "pg_database_size(current_database())",
        };
        let (bytes, experiments, trajectories, transitions): (i64, i64, i64, i64) =
            sqlx::query_as(&format!(
                "SELECT CAST({bytes} AS BIGINT),
                        (SELECT COUNT(*) FROM experiments),
                        (SELECT COUNT(*) FROM trajectories),
                        (SELECT COUNT(*) FROM transitions)"
            ))
            .fetch_one(&self.read)
            .await?;
        Ok(StoreSize {
            bytes,
            experiments,
            trajectories,
            transitions,
        })
    }

    /// Writes a consistent copy of a SQLite database to the new file `path` while it is being
    /// served (`VACUUM INTO` on a reader: one read transaction, so writers are not blocked in WAL
    /// mode). A PostgreSQL database is copied with its own tools (`pg_dump`).
    #[tracing::instrument(skip(self))]
    pub async fn backup_to(&self, path: &str) -> Result<(), sqlx::Error> {
        if self.backend != Backend::Sqlite {
            return Err(sqlx::Error::Configuration(
                "a PostgreSQL database is copied with pg_dump, not by precond".into(),
            ));
        }
        sqlx::query("VACUUM INTO $1")
            .bind(path)
            .execute(&self.read)
            .await
            .map(|_| ())
    }

    /// Closes both pools, waiting for in-flight queries; SQLite's WAL is checkpointed on close.
    pub async fn close(&self) {
        self.read.close().await;
        self.write.close().await;
    }
}

/// Inside a write transaction that reads before it writes: waits until no other such
/// transaction of `experiment_id` runs, on any replica, and holds that until this one ends.
/// PostgreSQL: a transaction-scoped advisory lock; SQLite: nothing to do (one writer).
pub(crate) async fn lock_experiment(
    conn: &mut AnyConnection,
    backend: Backend,
    experiment_id: i64,
) -> Result<(), sqlx::Error> {
    lock(conn, backend, EXPERIMENT_LOCKS, experiment_id).await
}

/// The same for the experiment list: creating an experiment under the server's limit.
pub(crate) async fn lock_experiment_list(
    conn: &mut AnyConnection,
    backend: Backend,
) -> Result<(), sqlx::Error> {
    lock(conn, backend, LIST_LOCK, 0).await
}

/// The advisory locks' first keys ("prec" and "prel" in ASCII): keep precond's locks apart
/// from other users of the database.
const EXPERIMENT_LOCKS: i32 = 0x7072_6563;
const LIST_LOCK: i32 = 0x7072_656c;

/// A transaction-scoped advisory lock on `(space, key)` (PostgreSQL), nothing on SQLite.
async fn lock(
    conn: &mut AnyConnection,
    backend: Backend,
    space: i32,
    key: i64,
) -> Result<(), sqlx::Error> {
    if backend == Backend::Postgres {
        // Cast to text: the lock function returns `void`, which `Any` cannot decode.
        sqlx::query("SELECT CAST(pg_advisory_xact_lock($1, CAST($2 AS INTEGER)) AS TEXT)")
            .bind(space)
            .bind(key.rem_euclid(i64::from(i32::MAX)))
            .execute(conn)
            .await?;
    }
    Ok(())
}

/// A boolean column: PostgreSQL's `BOOLEAN` or SQLite's 0/1 integer.
pub(crate) fn flag(row: &AnyRow, column: &str) -> Result<bool, sqlx::Error> {
    match row.try_get::<bool, _>(column) {
        Ok(b) => Ok(b),
        Err(_) => Ok(row.try_get::<i64, _>(column)? != 0),
    }
}

/// `url` with its password replaced by `***`, for messages and logs.
pub fn redact(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else {
        return url.to_string();
    };
    let authority_end = rest.find('/').unwrap_or(rest.len());
    let Some(at) = rest[..authority_end].rfind('@') else {
        return url.to_string();
    };
    match rest[..at].split_once(':') {
        Some((user, _password)) => format!("{scheme}://{user}:***{}", &rest[at..]),
        None => url.to_string(),
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
    use sqlx::Connection;
    anyhow::ensure!(
        Backend::of_url(source) == Backend::Sqlite,
        "precond backup copies a SQLite file; copy a PostgreSQL database with pg_dump"
    );
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

/// Why the store cannot serve now ([`Store::readiness`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum NotReady {
    /// The database does not answer (or not in time).
    Unreachable(String),
    /// Writes fail for lack of space, for `since`, the last error being `error`.
    Full {
        /// How long writes have been failing.
        since: Duration,
        /// The last write's error.
        error: String,
    },
}

impl std::fmt::Display for NotReady {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Unreachable(e) => write!(f, "the database is not answering: {e}"),
            Self::Full { since, error } => write!(
                f,
                "the database's disk is full: writes have failed for {} s ({error}); free \
                 space, then writes and readiness resume without a restart",
                since.as_secs()
            ),
        }
    }
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

/// Encodes a vector as a JSON array for a TEXT column.
fn encode_vec(v: &[f64]) -> String {
    serde_json::to_string(v).unwrap_or_else(|_| "[]".into())
}

/// Decodes a TEXT column written by [`encode_vec`].
fn decode_vec(s: &str) -> Result<Vec<f64>, sqlx::Error> {
    serde_json::from_str(s).map_err(|e| sqlx::Error::Decode(Box::new(e)))
}
