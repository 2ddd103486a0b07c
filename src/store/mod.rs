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
pub use models::StoredModel;
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
