//! Exclusions: trajectories an operator left out of an experiment's model (a bad run, a bad
//! calibration day), and the record of who did it, why, and who brought them back.
//!
//! An exclusion names one trajectory or a time range of ingest times; it is resolved when it is
//! made into the trajectories it covers (`excluded_trajectories`), so a range never grows. Rows
//! are never deleted: a restore marks the exclusion restored, and the table is the audit
//! trail. Each model version records the exclusions in effect when its fit read its training
//! set ([`ExclusionSet`]): that set and `n_train` say exactly which transitions it was fitted on,
//! so a version fitted before an exclusion (or a restore) is rebuilt on its own data.

use super::fits::raise_fit;
use super::{Backend, Store, lock_experiment, now};
use sqlx::Row;
use sqlx::any::AnyRow;

/// The exclusions a model version was fitted under: its training set is the experiment's
/// transitions in id order outside the trajectories these exclusions cover.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ExclusionSet(Vec<i64>);

impl ExclusionSet {
    /// The set of these exclusion ids (sorted, without repeats).
    pub fn new(mut ids: Vec<i64>) -> Self {
        ids.sort_unstable();
        ids.dedup();
        Self(ids)
    }

    /// The exclusion ids, ascending.
    pub fn ids(&self) -> &[i64] {
        &self.0
    }

    /// Whether no exclusion is in the set.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// As stored in `models.exclusions`: ids comma-separated, `None` for none.
    pub(super) fn encode(&self) -> Option<String> {
        (!self.0.is_empty()).then(|| {
            self.0
                .iter()
                .map(i64::to_string)
                .collect::<Vec<_>>()
                .join(",")
        })
    }

    /// Reads `models.exclusions`.
    pub(super) fn decode(text: Option<&str>) -> Result<Self, sqlx::Error> {
        let Some(text) = text.filter(|t| !t.is_empty()) else {
            return Ok(Self::default());
        };
        text.split(',')
            .map(|id| {
                id.trim().parse::<i64>().map_err(|e| {
                    sqlx::Error::Decode(format!("models.exclusions {text:?}: {e}").into())
                })
            })
            .collect::<Result<Vec<_>, _>>()
            .map(Self::new)
    }

    /// The SQL condition keeping a `transitions` row (its trajectory id in `column`) out of the
    /// training set: empty for no exclusion. The ids are integers read from the store, written
    /// into the statement as numbers (nothing a client sent is interpolated).
    pub(super) fn sql(&self, column: &str) -> String {
        if self.0.is_empty() {
            return String::new();
        }
        let ids: Vec<String> = self.0.iter().map(i64::to_string).collect();
        format!(
            " AND {column} NOT IN (SELECT trajectory_id FROM excluded_trajectories
                                   WHERE exclusion_id IN ({}))",
            ids.join(",")
        )
    }
}

/// What an exclusion covers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ExclusionScope {
    /// One trajectory.
    Trajectory(i64),
    /// The trajectories stored from `from` (inclusive) to `to` (exclusive), RFC 3339 as the
    /// store writes times ([`super::timestamp`]).
    TimeRange {
        /// The first instant covered.
        from: String,
        /// The first instant after the range.
        to: String,
    },
}

/// An exclusion as stored.
#[derive(Debug, Clone, PartialEq)]
pub struct Exclusion {
    /// Identifier, ascending in the order exclusions were made.
    pub id: i64,
    /// What it names.
    pub scope: ExclusionScope,
    /// Why (the operator's words).
    pub reason: String,
    /// The trajectories it covers.
    pub trajectory_ids: Vec<i64>,
    /// Their transitions.
    pub n_transitions: i64,
    /// When it was made (RFC 3339).
    pub created_at: String,
    /// Who made it: the caller's token fingerprint, `None` on a server without tokens.
    pub created_by: Option<String>,
    /// When it was restored, if it was.
    pub restored_at: Option<String>,
    /// Who restored it.
    pub restored_by: Option<String>,
}

/// What making an exclusion did.
#[derive(Debug)]
pub enum ExclusionOutcome {
    /// Stored, with a forced fit requested in the same transaction.
    Created(Exclusion),
    /// The trajectory is not one of the experiment's; nothing stored.
    NoSuchTrajectory,
    /// The time range holds no trajectory of the experiment; nothing stored.
    CoversNothing,
    /// With it, no transition would be left to fit; nothing stored.
    LeavesNothing {
        /// Transitions the experiment has in all.
        n_transitions: i64,
    },
}

/// What restoring an exclusion did.
#[derive(Debug)]
pub enum RestoreOutcome {
    /// Marked restored, with a forced fit requested in the same transaction.
    Restored(Exclusion),
    /// It had been restored before (as it stands); nothing changed.
    AlreadyRestored(Exclusion),
    /// No such exclusion in the experiment.
    NotFound,
}

const COLUMNS: &str = "id, trajectory_id, from_time, to_time, reason, n_transitions, created_at,
                       created_by, restored_at, restored_by";

fn exclusion_from_row(row: &AnyRow, trajectory_ids: Vec<i64>) -> Result<Exclusion, sqlx::Error> {
    let trajectory: Option<i64> = row.try_get("trajectory_id")?;
    let from: Option<String> = row.try_get("from_time")?;
    let to: Option<String> = row.try_get("to_time")?;
    let scope = match (trajectory, from, to) {
        (Some(t), _, _) => ExclusionScope::Trajectory(t),
        (None, Some(from), Some(to)) => ExclusionScope::TimeRange { from, to },
        _ => {
            return Err(sqlx::Error::Decode(
                "an exclusion names neither a trajectory nor a time range".into(),
            ));
        }
    };
    Ok(Exclusion {
        id: row.try_get("id")?,
        scope,
        reason: row.try_get("reason")?,
        trajectory_ids,
        n_transitions: row.try_get("n_transitions")?,
        created_at: row.try_get("created_at")?,
        created_by: row.try_get("created_by")?,
        restored_at: row.try_get("restored_at")?,
        restored_by: row.try_get("restored_by")?,
    })
}

/// Trajectories written per INSERT (2 parameters each).
const INSERT_ROWS: usize = 500;

impl Store {
    /// The exclusions in effect now (made and not restored): what the next fit leaves out.
    #[tracing::instrument(skip(self))]
    pub async fn active_exclusions(&self, experiment_id: i64) -> Result<ExclusionSet, sqlx::Error> {
        let ids: Vec<i64> = sqlx::query_scalar(
            "SELECT id FROM exclusions WHERE experiment_id = $1 AND restored_at IS NULL",
        )
        .bind(experiment_id)
        .fetch_all(&self.read)
        .await?;
        Ok(ExclusionSet::new(ids))
    }

    /// Makes an exclusion of `scope` and requests a forced fit, in one transaction: the
    /// exclusion is acknowledged only once both are stored, and a server that stops before the
    /// fit finds it requested when it starts.
    #[tracing::instrument(skip(self, reason))]
    pub async fn create_exclusion(
        &self,
        experiment_id: i64,
        scope: &ExclusionScope,
        reason: &str,
        created_by: Option<&str>,
    ) -> Result<ExclusionOutcome, sqlx::Error> {
        self.noted(async {
            let mut tx = self.begin_write().await?;
            lock_experiment(&mut tx, self.backend, experiment_id).await?;
            let covered: Vec<(i64, i64)> = match scope {
                ExclusionScope::Trajectory(t) => {
                    sqlx::query_as(
                        "SELECT id, n_transitions FROM trajectories
                         WHERE experiment_id = $1 AND id = $2",
                    )
                    .bind(experiment_id)
                    .bind(*t)
                    .fetch_all(&mut *tx)
                    .await?
                }
                ExclusionScope::TimeRange { from, to } => {
                    // Times written by older SQLite versions may have fewer fractional digits:
                    // SQLite compares instants. PostgreSQL only holds today's format.
                    let within = match self.backend {
                        Backend::Sqlite => {
                            "julianday(created_at) >= julianday($2)
                             AND julianday(created_at) < julianday($3)"
                        }
                        Backend::Postgres => "created_at >= $2 AND created_at < $3",
                    };
                    sqlx::query_as(&format!(
                        "SELECT id, n_transitions FROM trajectories
                         WHERE experiment_id = $1 AND {within}
                         ORDER BY id"
                    ))
                    .bind(experiment_id)
                    .bind(from)
                    .bind(to)
                    .fetch_all(&mut *tx)
                    .await?
                }
            };
            if covered.is_empty() {
                return Ok(match scope {
                    ExclusionScope::Trajectory(_) => ExclusionOutcome::NoSuchTrajectory,
                    ExclusionScope::TimeRange { .. } => ExclusionOutcome::CoversNothing,
                });
            }
            let n_covered: i64 = covered.iter().map(|(_, n)| n).sum();
            let covered: Vec<i64> = covered.into_iter().map(|(t, _)| t).collect();
            let id: i64 = sqlx::query_scalar(
                "INSERT INTO exclusions (experiment_id, trajectory_id, from_time, to_time, reason,
                                         n_trajectories, n_transitions, created_at, created_by)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9) RETURNING id",
            )
            .bind(experiment_id)
            .bind(match scope {
                ExclusionScope::Trajectory(t) => Some(*t),
                ExclusionScope::TimeRange { .. } => None,
            })
            .bind(match scope {
                ExclusionScope::TimeRange { from, .. } => Some(from.as_str()),
                ExclusionScope::Trajectory(_) => None,
            })
            .bind(match scope {
                ExclusionScope::TimeRange { to, .. } => Some(to.as_str()),
                ExclusionScope::Trajectory(_) => None,
            })
            .bind(reason)
            .bind(covered.len() as i64)
            .bind(n_covered)
            .bind(now())
            .bind(created_by)
            .fetch_one(&mut *tx)
            .await?;
            for chunk in covered.chunks(INSERT_ROWS) {
                let values: Vec<String> = (0..chunk.len())
                    .map(|i| format!("(${}, ${})", 2 * i + 1, 2 * i + 2))
                    .collect();
                let sql = format!(
                    "INSERT INTO excluded_trajectories (exclusion_id, trajectory_id) VALUES {}",
                    values.join(", ")
                );
                let mut insert = sqlx::query(&sql);
                for t in chunk {
                    insert = insert.bind(id).bind(*t);
                }
                insert.execute(&mut *tx).await?;
            }
            // The transitions the exclusions in effect, this one included, leave to fit.
            let n_left: i64 = sqlx::query_scalar(
                "SELECT COUNT(*) FROM transitions WHERE experiment_id = $1 AND trajectory_id NOT IN
                   (SELECT e.trajectory_id FROM excluded_trajectories e
                    JOIN exclusions x ON x.id = e.exclusion_id
                    WHERE x.experiment_id = $1 AND x.restored_at IS NULL)",
            )
            .bind(experiment_id)
            .fetch_one(&mut *tx)
            .await?;
            if n_left == 0 {
                let n_transitions: i64 =
                    sqlx::query_scalar("SELECT COUNT(*) FROM transitions WHERE experiment_id = $1")
                        .bind(experiment_id)
                        .fetch_one(&mut *tx)
                        .await?;
                tx.rollback().await?;
                return Ok(ExclusionOutcome::LeavesNothing { n_transitions });
            }
            raise_fit(&mut tx, experiment_id, true).await?;
            let exclusion = self.exclusion_on(&mut tx, id).await?;
            tx.commit().await?;
            Ok(ExclusionOutcome::Created(exclusion))
        })
        .await
    }

    /// Marks exclusion `exclusion_id` restored and requests a forced fit, in one transaction:
    /// the next fit takes its trajectories in again.
    #[tracing::instrument(skip(self))]
    pub async fn restore_exclusion(
        &self,
        experiment_id: i64,
        exclusion_id: i64,
        restored_by: Option<&str>,
    ) -> Result<RestoreOutcome, sqlx::Error> {
        self.noted(async {
            let mut tx = self.begin_write().await?;
            lock_experiment(&mut tx, self.backend, experiment_id).await?;
            let restored: Option<Option<String>> = sqlx::query_scalar(
                "SELECT restored_at FROM exclusions WHERE experiment_id = $1 AND id = $2",
            )
            .bind(experiment_id)
            .bind(exclusion_id)
            .fetch_optional(&mut *tx)
            .await?;
            let fresh = match restored {
                None => return Ok(RestoreOutcome::NotFound),
                Some(at) => at.is_none(),
            };
            if fresh {
                sqlx::query(
                    "UPDATE exclusions SET restored_at = $2, restored_by = $3 WHERE id = $1",
                )
                .bind(exclusion_id)
                .bind(now())
                .bind(restored_by)
                .execute(&mut *tx)
                .await?;
                raise_fit(&mut tx, experiment_id, true).await?;
            }
            let exclusion = self.exclusion_on(&mut tx, exclusion_id).await?;
            tx.commit().await?;
            Ok(if fresh {
                RestoreOutcome::Restored(exclusion)
            } else {
                RestoreOutcome::AlreadyRestored(exclusion)
            })
        })
        .await
    }

    async fn exclusion_on(
        &self,
        conn: &mut sqlx::AnyConnection,
        exclusion_id: i64,
    ) -> Result<Exclusion, sqlx::Error> {
        let row = sqlx::query(&format!("SELECT {COLUMNS} FROM exclusions WHERE id = $1"))
            .bind(exclusion_id)
            .fetch_one(&mut *conn)
            .await?;
        let trajectories: Vec<i64> = sqlx::query_scalar(
            "SELECT trajectory_id FROM excluded_trajectories WHERE exclusion_id = $1
             ORDER BY trajectory_id",
        )
        .bind(exclusion_id)
        .fetch_all(&mut *conn)
        .await?;
        exclusion_from_row(&row, trajectories)
    }

    /// An experiment's exclusions, newest first, `limit` from `offset`, and how many it has.
    #[tracing::instrument(skip(self))]
    pub async fn exclusions(
        &self,
        experiment_id: i64,
        offset: i64,
        limit: i64,
    ) -> Result<(Vec<Exclusion>, i64), sqlx::Error> {
        let mut conn = self.read.acquire().await?;
        let total: i64 =
            sqlx::query_scalar("SELECT COUNT(*) FROM exclusions WHERE experiment_id = $1")
                .bind(experiment_id)
                .fetch_one(&mut *conn)
                .await?;
        // The page's rows, then their trajectories in one query.
        let rows = sqlx::query(&format!(
            "SELECT {COLUMNS} FROM exclusions WHERE experiment_id = $1 ORDER BY id DESC
             LIMIT $2 OFFSET $3"
        ))
        .bind(experiment_id)
        .bind(limit)
        .bind(offset)
        .fetch_all(&mut *conn)
        .await?;
        let mut items = Vec::with_capacity(rows.len());
        if let (Some(newest), Some(oldest)) = (rows.first(), rows.last()) {
            let (newest, oldest): (i64, i64) = (newest.try_get("id")?, oldest.try_get("id")?);
            let covered: Vec<(i64, i64)> = sqlx::query_as(
                "SELECT e.exclusion_id, e.trajectory_id FROM excluded_trajectories e
                 JOIN exclusions x ON x.id = e.exclusion_id
                 WHERE x.experiment_id = $1 AND e.exclusion_id BETWEEN $2 AND $3
                 ORDER BY e.exclusion_id, e.trajectory_id",
            )
            .bind(experiment_id)
            .bind(oldest)
            .bind(newest)
            .fetch_all(&mut *conn)
            .await?;
            let mut by_exclusion: std::collections::HashMap<i64, Vec<i64>> = Default::default();
            for (exclusion, trajectory) in covered {
                by_exclusion.entry(exclusion).or_default().push(trajectory);
            }
            for row in &rows {
                let id: i64 = row.try_get("id")?;
                items.push(exclusion_from_row(
                    row,
                    by_exclusion.remove(&id).unwrap_or_default(),
                )?);
            }
        }
        Ok((items, total))
    }
}
