//! Trajectories and their transitions; atomic, idempotent ingest.

use super::proposals::{LinkOutcome, link_trajectory};
use super::{ExclusionSet, Store, decode_vec, encode_vec, flag, lock_experiment, now};
use crate::domain::LabelledTransition;
use crate::records::{ModelLabel, Provenance, StoredTransition};
use sqlx::Row;
use sqlx::any::AnyRow;

/// What one model's labels of an experiment's executed transitions say.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct LabelStats {
    /// The model's name (`domain` for the domain's own).
    pub model: String,
    /// Transitions it labelled.
    pub n_labelled: i64,
    /// Transitions whose label it left missing.
    pub n_missing: i64,
    /// Mean deviation label (`None` without labels).
    pub mean_deviation: Option<f64>,
    /// Largest deviation label (`None` without labels).
    pub max_deviation: Option<f64>,
    /// Share of its labels below `d_max` (`None` without labels).
    pub share_within_d_max: Option<f64>,
}

/// What a trajectory is besides its transitions, as stored with them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrajectoryMeta<'a> {
    /// The proposal it executed, if any.
    pub proposal_id: Option<i64>,
    /// Whether the robot stopped before the end.
    pub partial: bool,
    /// Whether it departs from its proposal (see `service::ingest::deviates`).
    pub deviating: bool,
    /// Where it comes from.
    pub source: Option<&'a Provenance>,
}

/// A stored trajectory with its transitions.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredTrajectory {
    /// Identifier.
    pub id: i64,
    /// Owning experiment.
    pub experiment_id: i64,
    /// The proposal it executed, if any.
    pub proposal_id: Option<i64>,
    /// Whether the robot stopped before the end.
    pub partial: bool,
    /// Whether it departs from its proposal.
    pub deviating: bool,
    /// Where it comes from, when its client said.
    pub source: Option<Provenance>,
    /// Ingest time (RFC 3339).
    pub created_at: String,
    /// Its transitions in order.
    pub transitions: Vec<StoredTransition>,
}

/// What one ingest did: the trajectory it stored and the state it found, recorded under the
/// idempotency key (when there is one) so that a retry learns the same.
#[derive(Debug, Clone, PartialEq)]
pub struct IngestRecord {
    /// The stored trajectory's identifier.
    pub trajectory_id: i64,
    /// The proposal it executed, if any.
    pub proposal_id: Option<i64>,
    /// Whether the robot stopped before the end.
    pub partial: bool,
    /// Whether it departs from its proposal.
    pub deviating: bool,
    /// Where it comes from, when its client said.
    pub source: Option<Provenance>,
    /// Each transition's deviation label, in order.
    pub deviations: Vec<f64>,
    /// The model version answering when it was stored.
    pub model_version: i64,
    /// Trajectories of the experiment, this one included.
    pub n_trajectories: i64,
    /// Ingest time (RFC 3339).
    pub created_at: String,
}

/// What an ingest did.
#[derive(Debug)]
pub enum IngestOutcome {
    /// Stored, and recorded under the idempotency key if there was one.
    Created(IngestRecord),
    /// The idempotency key was seen with the same request: what the first ingest did;
    /// nothing stored.
    Replayed(IngestRecord),
    /// The idempotency key was seen with a different request; nothing stored.
    KeyReused {
        /// The request stored under the key (canonical JSON), to say what differs.
        stored_request: String,
    },
    /// `proposal_id` names no proposal of this experiment; nothing stored.
    ProposalNotFound,
    /// The proposal's trajectory was already posted; nothing stored.
    ProposalAlreadyExecuted,
}

/// An idempotency key and the canonical request it guards.
#[derive(Debug, Clone, Copy)]
pub struct IdempotencyKey<'a> {
    /// The client's key.
    pub key: &'a str,
    /// Canonical JSON of the request.
    pub request: &'a str,
}

fn transition_from_row(row: &AnyRow) -> Result<StoredTransition, sqlx::Error> {
    Ok(StoredTransition {
        id: row.try_get("id")?,
        trajectory_id: row.try_get("trajectory_id")?,
        step: row.try_get("step")?,
        s: decode_vec(row.try_get("s")?)?,
        a: decode_vec(row.try_get("a")?)?,
        s_next: decode_vec(row.try_get("s_next")?)?,
        s_pred: decode_vec(row.try_get("s_pred")?)?,
        deviation: row.try_get("deviation")?,
        labels: None,
    })
}

fn label_from_row(row: &AnyRow) -> Result<(i64, ModelLabel), sqlx::Error> {
    let s_pred: Option<String> = row.try_get("s_pred")?;
    Ok((
        row.try_get("transition_id")?,
        ModelLabel {
            model: row.try_get("model")?,
            s_pred: s_pred.as_deref().map(decode_vec).transpose()?,
            deviation: row.try_get("deviation")?,
            missing: row.try_get("missing")?,
        },
    ))
}

/// The provenance of a row with the `source_*` columns (`None` without a dataset).
pub(super) fn provenance_from_row(row: &AnyRow) -> Result<Option<Provenance>, sqlx::Error> {
    let dataset: Option<String> = row.try_get("source_dataset")?;
    dataset
        .map(|dataset| {
            Ok(Provenance {
                dataset,
                episode: row.try_get("source_episode")?,
                first_step: row.try_get("source_first_step")?,
                label: row.try_get("source_label")?,
            })
        })
        .transpose()
}

/// Transitions one INSERT statement writes (8 parameters each: far below SQLite's and
/// PostgreSQL's limits on parameters per statement).
const INSERT_ROWS: usize = 256;

/// `INSERT INTO model_labels` of `rows` rows, each `($e, $t, $m, <tail>)` with `tail` (whose
/// `${}` are numbered on) completing `s_pred, deviation, missing`; `per_row` parameters a row.
fn label_insert(rows: usize, tail: &str, per_row: usize) -> String {
    let values: Vec<String> = (0..rows)
        .map(|r| {
            let mut n = per_row * r;
            let mut next = || {
                n += 1;
                format!("${n}")
            };
            let head = format!("({}, {}, {}, ", next(), next(), next());
            let mut row = head;
            for (k, part) in tail.split("${}").enumerate() {
                if k > 0 {
                    row.push_str(&next());
                }
                row.push_str(part);
            }
            row.push(')');
            row
        })
        .collect();
    format!(
        "INSERT INTO model_labels
           (experiment_id, transition_id, model, s_pred, deviation, missing)
         VALUES {}",
        values.join(", ")
    )
}

const TRANSITION_COLUMNS: &str = "id, trajectory_id, step, s, a, s_next, s_pred, deviation";

impl Store {
    /// Stores one trajectory and all its transitions in one transaction, or nothing — with
    /// `labels[i]`, the further models' labels of transition `i` (empty: none);
    /// `model_version` is the version answering now, recorded with it.
    ///
    /// With an idempotency key, a retry of the same request learns what the first one did and
    /// stores nothing, and a different request under the same key is refused; the record is
    /// written in the same transaction as the trajectory.
    #[tracing::instrument(skip(self, meta, transitions, idempotency), fields(n = transitions.len()))]
    pub async fn ingest_trajectory(
        &self,
        experiment_id: i64,
        meta: TrajectoryMeta<'_>,
        transitions: &[LabelledTransition],
        labels: &[Vec<ModelLabel>],
        idempotency: Option<IdempotencyKey<'_>>,
        model_version: i64,
    ) -> Result<IngestOutcome, sqlx::Error> {
        self.noted(async {
            let mut tx = self.begin_write().await?;
            lock_experiment(&mut tx, self.backend, experiment_id).await?;
            if let Some(k) = idempotency {
                let seen = sqlx::query(
                    "SELECT k.request, k.trajectory_id, k.model_version, k.n_trajectories,
                            k.created_at, t.proposal_id, t.partial, t.deviating, t.source_dataset,
                            t.source_episode, t.source_first_step, t.source_label
                     FROM idempotency_keys k JOIN trajectories t ON t.id = k.trajectory_id
                     WHERE k.experiment_id = $1 AND k.key = $2",
                )
                .bind(experiment_id)
                .bind(k.key)
                .fetch_optional(&mut *tx)
                .await?;
                if let Some(row) = seen {
                    let request: String = row.try_get("request")?;
                    if request != k.request {
                        tx.rollback().await?;
                        return Ok(IngestOutcome::KeyReused {
                            stored_request: request,
                        });
                    }
                    let trajectory_id: i64 = row.try_get("trajectory_id")?;
                    let deviations: Vec<f64> = sqlx::query_scalar(
                        "SELECT deviation FROM transitions WHERE trajectory_id = $1 ORDER BY step",
                    )
                    .bind(trajectory_id)
                    .fetch_all(&mut *tx)
                    .await?;
                    let record = IngestRecord {
                        trajectory_id,
                        proposal_id: row.try_get("proposal_id")?,
                        partial: flag(&row, "partial")?,
                        deviating: flag(&row, "deviating")?,
                        source: provenance_from_row(&row)?,
                        deviations,
                        model_version: row.try_get("model_version")?,
                        n_trajectories: row.try_get("n_trajectories")?,
                        created_at: row.try_get("created_at")?,
                    };
                    tx.rollback().await?;
                    return Ok(IngestOutcome::Replayed(record));
                }
            }
            if let Some(pid) = meta.proposal_id {
                let refused = match link_trajectory(&mut tx, experiment_id, pid).await? {
                    LinkOutcome::Linked => None,
                    LinkOutcome::NotFound => Some(IngestOutcome::ProposalNotFound),
                    LinkOutcome::AlreadyExecuted => Some(IngestOutcome::ProposalAlreadyExecuted),
                };
                if let Some(refused) = refused {
                    tx.rollback().await?;
                    return Ok(refused);
                }
            }
            let created_at = now();
            let trajectory_id: i64 = sqlx::query_scalar(
                "INSERT INTO trajectories (experiment_id, proposal_id, partial, n_transitions, created_at,
                                           deviating, source_dataset, source_episode,
                                           source_first_step, source_label)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10) RETURNING id",
            )
            .bind(experiment_id)
            .bind(meta.proposal_id)
            .bind(meta.partial)
            .bind(transitions.len() as i64)
            .bind(&created_at)
            .bind(meta.deviating)
            .bind(meta.source.map(|p| p.dataset.as_str()))
            .bind(meta.source.and_then(|p| p.episode))
            .bind(meta.source.and_then(|p| p.first_step))
            .bind(meta.source.and_then(|p| p.label.as_deref()))
            .fetch_one(&mut *tx)
            .await?;
            // Many rows a statement: one round trip per chunk, not per transition (PostgreSQL is
            // across a network); rows are numbered in the order listed, so ids follow the steps.
            for (chunk_index, chunk) in transitions.chunks(INSERT_ROWS).enumerate() {
                let rows: Vec<String> = (0..chunk.len())
                    .map(|r| {
                        let p = 8 * r;
                        format!(
                            "(${}, ${}, ${}, ${}, ${}, ${}, ${}, ${})",
                            p + 1,
                            p + 2,
                            p + 3,
                            p + 4,
                            p + 5,
                            p + 6,
                            p + 7,
                            p + 8
                        )
                    })
                    .collect();
                let sql = format!(
                    "INSERT INTO transitions
                       (experiment_id, trajectory_id, step, s, a, s_next, s_pred, deviation)
                     VALUES {}",
                    rows.join(", ")
                );
                let mut insert = sqlx::query(&sql);
                for (k, t) in chunk.iter().enumerate() {
                    let o = &t.observed;
                    insert = insert
                        .bind(experiment_id)
                        .bind(trajectory_id)
                        .bind((chunk_index * INSERT_ROWS + k) as i64)
                        .bind(encode_vec(&o.s))
                        .bind(encode_vec(&o.a))
                        .bind(encode_vec(&o.s_next))
                        .bind(encode_vec(&t.s_pred))
                        .bind(t.deviation);
                }
                insert.execute(&mut *tx).await?;
            }
            if labels.iter().any(|l| !l.is_empty()) {
                let ids: Vec<i64> = sqlx::query_scalar(
                    "SELECT id FROM transitions WHERE trajectory_id = $1 ORDER BY step",
                )
                .bind(trajectory_id)
                .fetch_all(&mut *tx)
                .await?;
                let rows: Vec<(i64, &ModelLabel)> = ids
                    .iter()
                    .zip(labels)
                    .flat_map(|(&id, of)| of.iter().map(move |l| (id, l)))
                    .collect();
                // A missing label writes NULL literals rather than binding `None::<f64>`: the
                // store's rule against NULL floats (see the module map of `store`).
                let (labelled, missing): (Vec<_>, Vec<_>) =
                    rows.into_iter().partition(|(_, l)| l.deviation.is_some());
                for chunk in labelled.chunks(INSERT_ROWS) {
                    let sql = label_insert(chunk.len(), "${}, ${}, NULL", 5);
                    let mut insert = sqlx::query(&sql);
                    for (id, l) in chunk {
                        insert = insert
                            .bind(experiment_id)
                            .bind(*id)
                            .bind(l.model.as_str())
                            .bind(encode_vec(l.s_pred.as_deref().unwrap_or_default()))
                            .bind(l.deviation.unwrap_or_default());
                    }
                    insert.execute(&mut *tx).await?;
                }
                for chunk in missing.chunks(INSERT_ROWS) {
                    let sql = label_insert(chunk.len(), "NULL, NULL, ${}", 4);
                    let mut insert = sqlx::query(&sql);
                    for (id, l) in chunk {
                        insert = insert
                            .bind(experiment_id)
                            .bind(*id)
                            .bind(l.model.as_str())
                            .bind(l.missing.as_deref().unwrap_or("missing"));
                    }
                    insert.execute(&mut *tx).await?;
                }
            }
            let n_trajectories: i64 =
                sqlx::query_scalar("SELECT COUNT(*) FROM trajectories WHERE experiment_id = $1")
                    .bind(experiment_id)
                    .fetch_one(&mut *tx)
                    .await?;
            if let Some(k) = idempotency {
                sqlx::query(
                    "INSERT INTO idempotency_keys
                       (experiment_id, key, request, trajectory_id, model_version, n_trajectories,
                        created_at)
                     VALUES ($1, $2, $3, $4, $5, $6, $7)",
                )
                .bind(experiment_id)
                .bind(k.key)
                .bind(k.request)
                .bind(trajectory_id)
                .bind(model_version)
                .bind(n_trajectories)
                .bind(&created_at)
                .execute(&mut *tx)
                .await?;
            }
            tx.commit().await?;
            Ok(IngestOutcome::Created(IngestRecord {
                trajectory_id,
                proposal_id: meta.proposal_id,
                partial: meta.partial,
                deviating: meta.deviating,
                source: meta.source.cloned(),
                deviations: transitions.iter().map(|t| t.deviation).collect(),
                model_version,
                n_trajectories,
                created_at,
            }))
        })
        .await
    }

    /// One trajectory of an experiment with its transitions, or `None`.
    #[tracing::instrument(skip(self))]
    pub async fn trajectory(
        &self,
        experiment_id: i64,
        trajectory_id: i64,
    ) -> Result<Option<StoredTrajectory>, sqlx::Error> {
        let Some(row) = sqlx::query(
            "SELECT id, experiment_id, proposal_id, partial, deviating, source_dataset,
                    source_episode, source_first_step, source_label, created_at
             FROM trajectories WHERE experiment_id = $1 AND id = $2",
        )
        .bind(experiment_id)
        .bind(trajectory_id)
        .fetch_optional(&self.read)
        .await?
        else {
            return Ok(None);
        };
        let transitions = sqlx::query(&format!(
            "SELECT {TRANSITION_COLUMNS} FROM transitions WHERE trajectory_id = $1 ORDER BY step"
        ))
        .bind(trajectory_id)
        .fetch_all(&self.read)
        .await?
        .iter()
        .map(transition_from_row)
        .collect::<Result<_, _>>()?;
        Ok(Some(StoredTrajectory {
            id: row.try_get("id")?,
            experiment_id: row.try_get("experiment_id")?,
            proposal_id: row.try_get("proposal_id")?,
            partial: flag(&row, "partial")?,
            deviating: flag(&row, "deviating")?,
            source: provenance_from_row(&row)?,
            created_at: row.try_get("created_at")?,
            transitions,
        }))
    }

    /// Transitions of an experiment with `id > after`, in id order, at most `limit` (all when
    /// `None`).
    #[tracing::instrument(skip(self))]
    pub async fn transitions(
        &self,
        experiment_id: i64,
        after: i64,
        limit: Option<i64>,
    ) -> Result<Vec<StoredTransition>, sqlx::Error> {
        self.transitions_outside(experiment_id, &ExclusionSet::default(), after, limit)
            .await
    }

    /// The further models' labels of the experiment's transitions with `first <= id <= last`,
    /// in transition id order (each transition's in model-name order): what
    /// [`StoredTransition::labels`] shows.
    #[tracing::instrument(skip(self))]
    pub async fn model_labels(
        &self,
        experiment_id: i64,
        first: i64,
        last: i64,
    ) -> Result<Vec<(i64, ModelLabel)>, sqlx::Error> {
        sqlx::query(
            "SELECT transition_id, model, s_pred, deviation, missing FROM model_labels
             WHERE experiment_id = $1 AND transition_id >= $2 AND transition_id <= $3
             ORDER BY transition_id, model",
        )
        .bind(experiment_id)
        .bind(first)
        .bind(last)
        .fetch_all(&self.read)
        .await?
        .iter()
        .map(label_from_row)
        .collect()
    }

    /// What the domain's model's labels (as `domain`) and each further model's say of the
    /// experiment's transitions: the domain's first, then the further models' by name; a
    /// further model without a stored label is not listed.
    #[tracing::instrument(skip(self))]
    pub async fn label_stats(
        &self,
        experiment_id: i64,
        d_max: f64,
    ) -> Result<Vec<LabelStats>, sqlx::Error> {
        let domain: LabelStats = sqlx::query_as(
            "SELECT 'domain' AS model, COUNT(*) AS n_labelled, CAST(0 AS BIGINT) AS n_missing,
                    AVG(deviation) AS mean_deviation, MAX(deviation) AS max_deviation,
                    CAST(AVG(CASE WHEN deviation < $2 THEN 1.0 ELSE 0.0 END)
                         AS DOUBLE PRECISION) AS share_within_d_max
             FROM transitions WHERE experiment_id = $1",
        )
        .bind(experiment_id)
        .bind(d_max)
        .fetch_one(&self.read)
        .await?;
        let further: Vec<LabelStats> = sqlx::query_as(
            "SELECT model, COUNT(deviation) AS n_labelled, COUNT(missing) AS n_missing,
                    AVG(deviation) AS mean_deviation, MAX(deviation) AS max_deviation,
                    CAST(AVG(CASE WHEN deviation IS NULL THEN NULL
                                  WHEN deviation < $2 THEN 1.0 ELSE 0.0 END)
                         AS DOUBLE PRECISION) AS share_within_d_max
             FROM model_labels WHERE experiment_id = $1 GROUP BY model ORDER BY model",
        )
        .bind(experiment_id)
        .bind(d_max)
        .fetch_all(&self.read)
        .await?;
        Ok(std::iter::once(domain).chain(further).collect())
    }

    /// [`Store::transitions`] outside the trajectories `outside` covers: a model version's
    /// training transitions, or those it has not seen, under the exclusions it was fitted with.
    #[tracing::instrument(skip(self))]
    pub async fn transitions_outside(
        &self,
        experiment_id: i64,
        outside: &ExclusionSet,
        after: i64,
        limit: Option<i64>,
    ) -> Result<Vec<StoredTransition>, sqlx::Error> {
        sqlx::query(&format!(
            "SELECT {TRANSITION_COLUMNS} FROM transitions
             WHERE experiment_id = $1 AND id > $2{} ORDER BY id LIMIT $3",
            outside.sql("trajectory_id")
        ))
        .bind(experiment_id)
        .bind(after)
        .bind(limit.unwrap_or(i64::MAX))
        .fetch_all(&self.read)
        .await?
        .iter()
        .map(transition_from_row)
        .collect()
    }

    /// Transitions of an experiment with `after < id <= upto`, in id order, at most `limit`.
    #[tracing::instrument(skip(self))]
    pub async fn transitions_between(
        &self,
        experiment_id: i64,
        after: i64,
        upto: i64,
        limit: i64,
    ) -> Result<Vec<StoredTransition>, sqlx::Error> {
        sqlx::query(&format!(
            "SELECT {TRANSITION_COLUMNS} FROM transitions
             WHERE experiment_id = $1 AND id > $2 AND id <= $3 ORDER BY id LIMIT $4"
        ))
        .bind(experiment_id)
        .bind(after)
        .bind(upto)
        .bind(limit)
        .fetch_all(&self.read)
        .await?
        .iter()
        .map(transition_from_row)
        .collect()
    }

    /// Where an export of the transitions after `after` ends: the last id it writes (the
    /// `limit`-th after `after`, or the last stored now), and the cursor of the following page
    /// when `limit` leaves some out.
    #[tracing::instrument(skip(self))]
    pub async fn export_bounds(
        &self,
        experiment_id: i64,
        after: i64,
        limit: Option<i64>,
    ) -> Result<(i64, Option<i64>), sqlx::Error> {
        if let Some(limit) = limit.filter(|l| *l >= 1) {
            let ids: Vec<i64> = sqlx::query_scalar(
                "SELECT id FROM transitions WHERE experiment_id = $1 AND id > $2
                 ORDER BY id LIMIT 2 OFFSET $3",
            )
            .bind(experiment_id)
            .bind(after)
            .bind(limit - 1)
            .fetch_all(&self.read)
            .await?;
            match ids.as_slice() {
                [last, _more] => return Ok((*last, Some(*last))),
                [last] => return Ok((*last, None)),
                _ => {}
            }
        }
        let last: Option<i64> = sqlx::query_scalar(
            "SELECT CAST(MAX(id) AS BIGINT) FROM transitions WHERE experiment_id = $1",
        )
        .bind(experiment_id)
        .fetch_one(&self.read)
        .await?;
        Ok((last.unwrap_or(after).max(after), None))
    }
}
