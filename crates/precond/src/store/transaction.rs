//! Write transactions whose commit is the database's outermost `COMMIT`, and whose connection
//! never goes back to the pool in a transaction.
//!
//! sqlx's own transactions count their nesting depth per connection and turn a `begin` on a
//! connection it believes is inside a transaction into a `SAVEPOINT`. When SQLite rolls a
//! transaction back by itself (it may on `SQLITE_FULL` or an I/O error), sqlx's `ROLLBACK`
//! then fails and the count stays one too high: every later `begin` is a savepoint inside a
//! transaction that is never committed, every `commit` only releases that savepoint, and a
//! server answers `201` for writes that vanish at its next restart (transact-rs/sqlx#3742; it
//! happened here on a full disk). A [`WriteTx`] therefore issues `BEGIN` and `COMMIT` itself:
//!
//! - `BEGIN` on a connection that is somehow still in a transaction fails, so nothing is ever
//!   written inside a transaction left open by an earlier request;
//! - a successful [`WriteTx::commit`] is the outermost `COMMIT`, so what it wrote is stored;
//! - after any error, and whenever a transaction is dropped without `commit` or `rollback`
//!   (a `?` on the way out), the connection is closed rather than returned to the pool, and the
//!   database rolls back whatever it held. [`WriteTx::rollback`] keeps the connection only when
//!   its `ROLLBACK` succeeded.

use super::Backend;
use super::health::WriteHealth;
use sqlx::pool::PoolConnection;
use sqlx::{Any, AnyConnection, AnyPool};
use std::ops::{Deref, DerefMut};
use std::sync::Arc;

/// A write transaction on a connection of the store's writer pool. Dereferences to the
/// connection, so queries run on `&mut *tx` as on a sqlx transaction.
pub(crate) struct WriteTx {
    conn: PoolConnection<Any>,
    /// `BEGIN` succeeded and neither `COMMIT` nor `ROLLBACK` has since.
    open: bool,
    /// Told of a successful commit (there is space to write).
    health: Arc<WriteHealth>,
}

impl WriteTx {
    /// Begins a transaction on a connection of `pool`: `BEGIN IMMEDIATE` on SQLite (the write
    /// lock is taken now, not at the first write), `BEGIN` on PostgreSQL.
    pub(crate) async fn begin(
        pool: &AnyPool,
        backend: Backend,
        health: Arc<WriteHealth>,
    ) -> Result<Self, sqlx::Error> {
        let mut conn = pool.acquire().await?;
        let begin = match backend {
            Backend::Sqlite => "BEGIN IMMEDIATE",
            Backend::Postgres => "BEGIN",
        };
        if let Err(e) = sqlx::query(begin).execute(&mut *conn).await {
            // Perhaps still in a transaction, perhaps broken: never reuse it.
            conn.close_on_drop();
            return Err(e);
        }
        Ok(Self {
            conn,
            open: true,
            health,
        })
    }

    /// Commits: `Ok` only when the database's outermost `COMMIT` succeeded. On failure the
    /// connection is closed (the database rolls back what the transaction held).
    pub(crate) async fn commit(mut self) -> Result<(), sqlx::Error> {
        let done = sqlx::query("COMMIT").execute(&mut *self.conn).await;
        self.open = false;
        match done {
            Ok(_) => {
                self.health.committed();
                Ok(())
            }
            Err(e) => {
                self.conn.close_on_drop();
                Err(e)
            }
        }
    }

    /// Rolls back what the transaction wrote (a read-only check that found nothing to do).
    /// The connection goes back to the pool only if the `ROLLBACK` succeeded.
    pub(crate) async fn rollback(mut self) -> Result<(), sqlx::Error> {
        let done = sqlx::query("ROLLBACK").execute(&mut *self.conn).await;
        self.open = false;
        match done {
            Ok(_) => Ok(()),
            Err(e) => {
                self.conn.close_on_drop();
                Err(e)
            }
        }
    }
}

impl Drop for WriteTx {
    fn drop(&mut self) {
        if self.open {
            // Dropped on an error path (or a panic): the transaction is in an unknown state,
            // perhaps rolled back by the database itself. Closing the connection ends whatever
            // is left of it; the pool opens a fresh one for the next writer.
            self.conn.close_on_drop();
        }
    }
}

impl Deref for WriteTx {
    type Target = AnyConnection;

    fn deref(&self) -> &AnyConnection {
        &self.conn
    }
}

impl DerefMut for WriteTx {
    fn deref_mut(&mut self) -> &mut AnyConnection {
        &mut self.conn
    }
}
