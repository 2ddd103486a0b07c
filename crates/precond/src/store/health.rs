//! What a database error means for the client, and whether the store can write now.
//!
//! A full disk and an unreachable database are not bugs: the client should wait and retry
//! (`507` / `503` with `Retry-After`), and readiness says so. [`classify`] reads the engine's
//! error code; [`WriteHealth`] remembers that the last write failed for lack of space until a
//! write (or a probe that allocates pages) succeeds again.

use std::sync::Mutex;
use std::time::{Duration, Instant};

/// What a database error says about the database, as opposed to the request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    /// The disk (or the database's size limit) is full: nothing can be written until space is
    /// freed. SQLite's `SQLITE_FULL`, PostgreSQL's `disk_full` (53100).
    Full,
    /// The database cannot be reached or is not accepting work now: a connection refused or
    /// lost, the pool's wait for a connection timed out, a server shutting down or starting,
    /// SQLite's file locked by another process.
    Unreachable,
    /// Anything else: a bug, or a broken database.
    Other,
}

/// SQLite's primary result codes that mean "try again later" (`SQLITE_BUSY`, `SQLITE_LOCKED`).
const SQLITE_BUSY: i32 = 5;
const SQLITE_LOCKED: i32 = 6;
/// `SQLITE_FULL`.
const SQLITE_FULL: i32 = 13;

/// What `e` says about the database.
pub fn classify(e: &sqlx::Error) -> Failure {
    match e {
        sqlx::Error::Database(db) => {
            let Some(code) = db.code() else {
                return Failure::Other;
            };
            // PostgreSQL's codes are five-character SQLSTATEs (some all digits, as 53100);
            // SQLite's are numbers, extended ones with the primary code in the low byte.
            if db
                .try_downcast_ref::<sqlx::postgres::PgDatabaseError>()
                .is_some()
            {
                return match code.as_ref() {
                    "53100" => Failure::Full,
                    // insufficient resources, out of memory, too many connections; the
                    // connection exceptions (class 08); an administrator's shutdown, a crash,
                    // a server starting; a read-only standby.
                    "53000" | "53200" | "53300" | "57P01" | "57P02" | "57P03" | "25006" => {
                        Failure::Unreachable
                    }
                    c if c.starts_with("08") => Failure::Unreachable,
                    _ => Failure::Other,
                };
            }
            match code.parse::<i32>().map(|n| n & 0xff) {
                Ok(SQLITE_FULL) => Failure::Full,
                Ok(SQLITE_BUSY | SQLITE_LOCKED) => Failure::Unreachable,
                _ => Failure::Other,
            }
        }
        sqlx::Error::PoolTimedOut
        | sqlx::Error::PoolClosed
        | sqlx::Error::Io(_)
        | sqlx::Error::Tls(_)
        | sqlx::Error::WorkerCrashed => Failure::Unreachable,
        _ => Failure::Other,
    }
}

/// Whether the store's writes are failing for lack of space, shared by the store's clones.
#[derive(Debug, Default)]
pub(crate) struct WriteHealth {
    state: Mutex<State>,
}

#[derive(Debug, Default)]
struct State {
    /// Since when writes have failed with [`Failure::Full`], and the last such error.
    full: Option<(Instant, String)>,
    /// When readiness last probed a write.
    probed: Option<Instant>,
}

/// How often readiness may probe a write while the disk is full.
pub(crate) const PROBE_INTERVAL: Duration = Duration::from_secs(1);

impl WriteHealth {
    /// Notes a write's failure (only a lack of space matters here).
    pub(crate) fn failed(&self, e: &sqlx::Error) {
        if classify(e) != Failure::Full {
            return;
        }
        let mut state = self.state.lock().unwrap_or_else(|p| p.into_inner());
        let since = state.full.as_ref().map_or_else(Instant::now, |(t, _)| *t);
        state.full = Some((since, e.to_string()));
    }

    /// Notes a committed write: there is space again.
    pub(crate) fn committed(&self) {
        self.state.lock().unwrap_or_else(|p| p.into_inner()).full = None;
    }

    /// How long writes have failed for lack of space, and the last error; `None` when the last
    /// write (or probe) succeeded.
    pub(crate) fn full(&self) -> Option<(Duration, String)> {
        let state = self.state.lock().unwrap_or_else(|p| p.into_inner());
        state
            .full
            .as_ref()
            .map(|(since, message)| (since.elapsed(), message.clone()))
    }

    /// Whether a probe may run now (at most one per [`PROBE_INTERVAL`]); records that it does.
    pub(crate) fn may_probe(&self) -> bool {
        let mut state = self.state.lock().unwrap_or_else(|p| p.into_inner());
        if state.probed.is_some_and(|t| t.elapsed() < PROBE_INTERVAL) {
            return false;
        }
        state.probed = Some(Instant::now());
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pool_timeout_and_a_lost_connection_are_unreachable_not_bugs() {
        assert_eq!(classify(&sqlx::Error::PoolTimedOut), Failure::Unreachable);
        let io = std::io::Error::from(std::io::ErrorKind::ConnectionRefused);
        assert_eq!(classify(&sqlx::Error::Io(io)), Failure::Unreachable);
        assert_eq!(classify(&sqlx::Error::RowNotFound), Failure::Other);
    }

    #[test]
    fn a_full_disk_is_remembered_until_a_write_succeeds() {
        let health = WriteHealth::default();
        assert!(health.full().is_none());
        health.failed(&sqlx::Error::RowNotFound);
        assert!(health.full().is_none(), "another error is not a full disk");
        health.failed(&sqlx::Error::Protocol("x".into()));
        assert!(health.full().is_none());
        // A full disk as SQLite reports it, through a real connection with a page limit.
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let e = rt.block_on(async {
            use sqlx::Connection;
            let mut conn = sqlx::SqliteConnection::connect("sqlite::memory:")
                .await
                .unwrap();
            sqlx::query("CREATE TABLE t (x BLOB)")
                .execute(&mut conn)
                .await
                .unwrap();
            sqlx::query("PRAGMA max_page_count = 4")
                .execute(&mut conn)
                .await
                .unwrap();
            sqlx::query("INSERT INTO t VALUES (zeroblob(100000))")
                .execute(&mut conn)
                .await
                .unwrap_err()
        });
        assert_eq!(classify(&e), Failure::Full, "{e}");
        health.failed(&e);
        assert!(health.full().is_some());
        health.committed();
        assert!(health.full().is_none(), "a write was committed");
    }
}
