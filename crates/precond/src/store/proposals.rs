//! Proposals and their leases.

use super::transaction::WriteTx;
use super::{Store, decode_vec, encode_vec, flag, lock_experiment};
use crate::planning::Strategy;
use crate::records::{ProposalStatus, ProposalTerms};
use sqlx::any::AnyRow;
use sqlx::{AnyConnection, Row};

fn parse_strategy(s: &str) -> Result<Strategy, sqlx::Error> {
    s.parse()
        .map_err(|e: crate::planning::PlanningError| sqlx::Error::Decode(Box::new(e)))
}

/// A proposal to store.
#[derive(Debug, Clone)]
pub struct NewProposal {
    /// Its terms.
    pub terms: ProposalTerms,
    /// The chosen trajectory and the candidates, as JSON exactly as the API shows them.
    pub body: String,
    /// Actions of the chosen trajectory.
    pub n_actions: i64,
    /// RRT extensions its search spent.
    pub extensions: i64,
    /// Lease length in seconds.
    pub ttl_seconds: u32,
    /// The `Idempotency-Key` of the `continue` that plans it: the proposal is recorded with the
    /// key, and a replay under the key answers it instead of storing another.
    pub continues: Option<String>,
}

/// What [`Store::insert_proposal`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Inserted {
    /// Stored the new proposal.
    Created,
    /// The client's open lease appeared meanwhile: that one is answered.
    OpenLease,
    /// The continuation's key already names a proposal (a replay): that one is answered, in
    /// whatever state it now is.
    Continued,
}

/// A stored proposal.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredProposal {
    /// Identifier.
    pub id: i64,
    /// Where its lease stands.
    pub status: ProposalStatus,
    /// Its terms.
    pub terms: ProposalTerms,
    /// Creation time (RFC 3339).
    pub created_at: String,
    /// End of the lease (RFC 3339).
    pub expires_at: String,
    /// Trajectory and candidates (JSON, as stored).
    pub body: String,
    /// Whether the trajectory that executed it departs from it (false until executed).
    pub deviating: bool,
}

/// What a proposal asked the robot to do: the start and the actions, to compare an execution
/// with.
#[derive(Debug, Clone, PartialEq)]
pub struct ProposalPlan {
    /// Start state.
    pub start: Vec<f64>,
    /// The planned actions, in order.
    pub actions: Vec<Vec<f64>>,
}

/// The planned states and actions of an open proposal: state-actions a robot is about to
/// execute.
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
pub struct OpenPlan {
    /// Planned states, the start first (one more than actions).
    pub states: Vec<Vec<f64>>,
    /// Planned actions, in order.
    pub actions: Vec<Vec<f64>>,
}

/// The planned states and actions of a stored proposal body (its `trajectory`).
fn open_plan(body: &str) -> Result<OpenPlan, sqlx::Error> {
    /// The part of a stored body that holds the plan.
    #[derive(serde::Deserialize)]
    struct Body {
        trajectory: OpenPlan,
    }
    let body: Body = serde_json::from_str(body).map_err(|e| sqlx::Error::Decode(Box::new(e)))?;
    Ok(body.trajectory)
}

/// What linking a trajectory to a proposal found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkOutcome {
    /// The proposal was open (or had expired) and is now `executed`.
    Linked,
    /// No such proposal in this experiment.
    NotFound,
    /// Its trajectory was already posted.
    AlreadyExecuted,
}

const COLUMNS: &str =
    "id, client_id, status, iteration, beta, strategy, model_version, start, goal,
                       body, created_at, expires_at,
                       COALESCE((SELECT t.deviating FROM trajectories t
                                 WHERE t.proposal_id = proposals.id), FALSE) AS deviating";

fn unix_now() -> f64 {
    time::OffsetDateTime::now_utc().unix_timestamp_nanos() as f64 / 1e9
}

fn from_row(row: &AnyRow) -> Result<StoredProposal, sqlx::Error> {
    Ok(StoredProposal {
        id: row.try_get("id")?,
        status: parse_status(row.try_get("status")?)?,
        terms: ProposalTerms {
            client_id: row.try_get("client_id")?,
            iteration: row.try_get("iteration")?,
            beta: row.try_get("beta")?,
            strategy: parse_strategy(row.try_get("strategy")?)?,
            model_version: row.try_get("model_version")?,
            start: decode_vec(row.try_get("start")?)?,
            goal: decode_vec(row.try_get("goal")?)?,
        },
        body: row.try_get("body")?,
        created_at: row.try_get("created_at")?,
        expires_at: row.try_get("expires_at")?,
        deviating: flag(row, "deviating")?,
    })
}

/// Marks the experiment's open proposals whose lease has passed as `expired`.
async fn expire_leases(conn: &mut AnyConnection, experiment_id: i64) -> Result<(), sqlx::Error> {
    sqlx::query(
        "UPDATE proposals SET status = 'expired'
         WHERE experiment_id = $1 AND status = 'open' AND expires_unix <= $2",
    )
    .bind(experiment_id)
    .bind(unix_now())
    .execute(conn)
    .await?;
    Ok(())
}

async fn select_by_id(
    conn: &mut AnyConnection,
    experiment_id: i64,
    proposal_id: i64,
) -> Result<Option<StoredProposal>, sqlx::Error> {
    sqlx::query(&format!(
        "SELECT {COLUMNS} FROM proposals WHERE experiment_id = $1 AND id = $2"
    ))
    .bind(experiment_id)
    .bind(proposal_id)
    .fetch_optional(conn)
    .await?
    .as_ref()
    .map(from_row)
    .transpose()
}

async fn continuation_on(
    conn: &mut AnyConnection,
    experiment_id: i64,
    key: &str,
) -> Result<Option<i64>, sqlx::Error> {
    Ok(sqlx::query_scalar(
        "SELECT continued_proposal_id FROM idempotency_keys WHERE experiment_id = $1 AND key = $2",
    )
    .bind(experiment_id)
    .bind(key)
    .fetch_optional(conn)
    .await?
    .flatten())
}

async fn open_for_client(
    conn: &mut AnyConnection,
    experiment_id: i64,
    client_id: &str,
) -> Result<Option<StoredProposal>, sqlx::Error> {
    sqlx::query(&format!(
        "SELECT {COLUMNS} FROM proposals
         WHERE experiment_id = $1 AND client_id = $2 AND status = 'open' AND expires_unix > $3
         ORDER BY id DESC LIMIT 1"
    ))
    .bind(experiment_id)
    .bind(client_id)
    .bind(unix_now())
    .fetch_optional(conn)
    .await?
    .as_ref()
    .map(from_row)
    .transpose()
}

impl Store {
    /// A write transaction holding experiment `experiment_id`'s lock, its leases brought up to
    /// date (those past their end marked `expired`).
    async fn leases_current(&self, experiment_id: i64) -> Result<WriteTx, sqlx::Error> {
        let mut tx = self.begin_write().await?;
        lock_experiment(&mut tx, self.backend, experiment_id).await?;
        expire_leases(&mut tx, experiment_id).await?;
        Ok(tx)
    }

    /// The start and planned actions of a proposal of this experiment, or `None`.
    #[tracing::instrument(skip(self))]
    pub async fn proposal_plan(
        &self,
        experiment_id: i64,
        proposal_id: i64,
    ) -> Result<Option<ProposalPlan>, sqlx::Error> {
        let Some(row) =
            sqlx::query("SELECT start, body FROM proposals WHERE experiment_id = $1 AND id = $2")
                .bind(experiment_id)
                .bind(proposal_id)
                .fetch_optional(&self.read)
                .await?
        else {
            return Ok(None);
        };
        let plan = open_plan(&row.try_get::<String, _>("body")?)?;
        Ok(Some(ProposalPlan {
            start: decode_vec(row.try_get("start")?)?,
            actions: plan.actions,
        }))
    }

    /// The plans of the open, unexpired proposals of an experiment not leased to `client_id`,
    /// newest first, at most `limit`.
    #[tracing::instrument(skip(self))]
    pub async fn open_plans(
        &self,
        experiment_id: i64,
        client_id: Option<&str>,
        limit: i64,
    ) -> Result<Vec<OpenPlan>, sqlx::Error> {
        sqlx::query(
            "SELECT body FROM proposals
             WHERE experiment_id = $1 AND status = 'open' AND expires_unix > $2
               AND COALESCE(client_id, '') <> $3
             ORDER BY id DESC LIMIT $4",
        )
        .bind(experiment_id)
        .bind(unix_now())
        .bind(client_id.unwrap_or(""))
        .bind(limit)
        .fetch_all(&self.read)
        .await?
        .iter()
        .map(|row| open_plan(&row.try_get::<String, _>("body")?))
        .collect()
    }

    /// The open, unexpired proposal leased to `client_id`, if any.
    #[tracing::instrument(skip(self))]
    pub async fn open_proposal(
        &self,
        experiment_id: i64,
        client_id: &str,
    ) -> Result<Option<StoredProposal>, sqlx::Error> {
        let mut conn = self.read.acquire().await?;
        open_for_client(&mut conn, experiment_id, client_id).await
    }

    /// Stores a proposal, unless an open one for the same client appeared meanwhile, or the
    /// continuation's key already names one (a concurrent replay), which is returned instead.
    #[tracing::instrument(skip(self, p))]
    pub async fn insert_proposal(
        &self,
        experiment_id: i64,
        p: &NewProposal,
    ) -> Result<(StoredProposal, Inserted), sqlx::Error> {
        self.noted(async {
            let mut tx = self.leases_current(experiment_id).await?;
            if let Some(key) = &p.continues
                && let Some(made) = continuation_on(&mut tx, experiment_id, key).await?
                && let Some(made) = select_by_id(&mut tx, experiment_id, made).await?
            {
                tx.commit().await?;
                return Ok((made, Inserted::Continued));
            }
            if let Some(client) = &p.terms.client_id
                && let Some(open) = open_for_client(&mut tx, experiment_id, client).await?
            {
                tx.commit().await?;
                return Ok((open, Inserted::OpenLease));
            }
            let created = time::OffsetDateTime::now_utc();
            let expires = created + time::Duration::seconds(i64::from(p.ttl_seconds));
            let fmt = super::timestamp;
            let id: i64 = sqlx::query_scalar(
                "INSERT INTO proposals (experiment_id, client_id, status, iteration, beta, strategy,
                                        model_version, start, goal, body, created_at, expires_at,
                                        expires_unix, n_actions, extensions)
                 VALUES ($1, $2, 'open', $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14)
                 RETURNING id",
            )
            .bind(experiment_id)
            .bind(&p.terms.client_id)
            .bind(p.terms.iteration)
            .bind(p.terms.beta)
            .bind(p.terms.strategy.as_str())
            .bind(p.terms.model_version)
            .bind(encode_vec(&p.terms.start))
            .bind(encode_vec(&p.terms.goal))
            .bind(&p.body)
            .bind(fmt(created))
            .bind(fmt(expires))
            .bind(expires.unix_timestamp_nanos() as f64 / 1e9)
            .bind(p.n_actions)
            .bind(p.extensions)
            .fetch_one(&mut *tx)
            .await?;
            let stored = sqlx::query(&format!("SELECT {COLUMNS} FROM proposals WHERE id = $1"))
                .bind(id)
                .fetch_one(&mut *tx)
                .await?;
            let stored = from_row(&stored)?;
            if let Some(key) = &p.continues {
                sqlx::query(
                    "UPDATE idempotency_keys SET continued_proposal_id = $3
                     WHERE experiment_id = $1 AND key = $2",
                )
                .bind(experiment_id)
                .bind(key)
                .bind(id)
                .execute(&mut *tx)
                .await?;
            }
            tx.commit().await?;
            Ok((stored, Inserted::Created))
        })
        .await
    }

    /// The proposal a `continue` under `key` planned, if its first call got that far.
    #[tracing::instrument(skip(self))]
    pub async fn continuation(
        &self,
        experiment_id: i64,
        key: &str,
    ) -> Result<Option<i64>, sqlx::Error> {
        let mut conn = self.read.acquire().await?;
        continuation_on(&mut conn, experiment_id, key).await
    }

    /// One proposal, with its lease brought up to date.
    #[tracing::instrument(skip(self))]
    pub async fn proposal(
        &self,
        experiment_id: i64,
        proposal_id: i64,
    ) -> Result<Option<StoredProposal>, sqlx::Error> {
        self.noted(async {
            let mut tx = self.leases_current(experiment_id).await?;
            let p = select_by_id(&mut tx, experiment_id, proposal_id).await?;
            tx.commit().await?;
            Ok(p)
        })
        .await
    }

    /// Abandons an open proposal. Returns the proposal as it now is (unchanged if it was not
    /// open), or `None` if there is no such proposal.
    #[tracing::instrument(skip(self))]
    pub async fn abandon_proposal(
        &self,
        experiment_id: i64,
        proposal_id: i64,
    ) -> Result<Option<StoredProposal>, sqlx::Error> {
        self.noted(async {
            let mut tx = self.leases_current(experiment_id).await?;
            sqlx::query(
                "UPDATE proposals SET status = 'abandoned'
                 WHERE experiment_id = $1 AND id = $2 AND status = 'open'",
            )
            .bind(experiment_id)
            .bind(proposal_id)
            .execute(&mut *tx)
            .await?;
            let p = select_by_id(&mut tx, experiment_id, proposal_id).await?;
            tx.commit().await?;
            Ok(p)
        })
        .await
    }
}

/// Inside an ingest transaction: closes the lease of the proposal a trajectory executed. An
/// expired or abandoned proposal still accepts its trajectory (the robot did execute it; the
/// data is real); one already executed does not.
pub(super) async fn link_trajectory(
    conn: &mut AnyConnection,
    experiment_id: i64,
    proposal_id: i64,
) -> Result<LinkOutcome, sqlx::Error> {
    let status: Option<String> =
        sqlx::query_scalar("SELECT status FROM proposals WHERE experiment_id = $1 AND id = $2")
            .bind(experiment_id)
            .bind(proposal_id)
            .fetch_optional(&mut *conn)
            .await?;
    match status.as_deref() {
        None => Ok(LinkOutcome::NotFound),
        Some("executed") => Ok(LinkOutcome::AlreadyExecuted),
        Some(_) => {
            sqlx::query("UPDATE proposals SET status = 'executed' WHERE id = $1")
                .bind(proposal_id)
                .execute(conn)
                .await?;
            Ok(LinkOutcome::Linked)
        }
    }
}

/// A stored proposal status.
fn parse_status(s: &str) -> Result<ProposalStatus, sqlx::Error> {
    ProposalStatus::from_name(s)
        .ok_or_else(|| sqlx::Error::Decode(format!("unknown proposal status {s:?}").into()))
}
