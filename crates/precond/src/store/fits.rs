//! The right to fit: one row per experiment whose model needs a fit (`fit_jobs`), held by one
//! replica at a time.
//!
//! - A batch that completes, or a client asking for a refit, **requests** a fit
//!   ([`Store::request_fit`]): the row is created, or its generation raised.
//! - A replica's fit worker **claims** a row nobody holds, or one whose holder stopped
//!   heartbeating (it died) ([`Store::claim_fit`]; PostgreSQL: `FOR UPDATE SKIP LOCKED`, so
//!   replicas claiming at once take different rows), and heartbeats while it fits
//!   ([`Store::heartbeat_fit`]).
//! - It **finishes** ([`Store::finish_fit`]) in one transaction: stores the new model version
//!   (if it fitted one) and deletes the row — or, when another request came in during the fit
//!   (the generation moved on), hands the row back for another fit. A replica that lost its
//!   claim while fitting (it stalled past its lease and another took over) stores nothing.

use super::models::insert_model_on;
use super::{Backend, Store, StoredModel, flag, lock_experiment, now};
use sqlx::{AnyConnection, Row};

/// A requested fit, as claimed.
#[derive(Debug, Clone, PartialEq)]
pub struct FitClaim {
    /// The experiment to fit.
    pub experiment_id: i64,
    /// The request generation this claim answers.
    pub generation: i64,
    /// Whether a client asked for the fit (fit even when a model covers the latest batch).
    pub forced: bool,
    /// The replica holding the claim.
    pub replica: String,
    /// The version the fit will store: the experiment's latest plus one.
    pub version: i64,
    /// Trajectories the latest stored version was fitted with (0 without one).
    pub covered_trajectories: i64,
}

/// A fit waiting or running, as listed for operators and tests.
#[derive(Debug, Clone, PartialEq)]
pub struct FitJob {
    /// The experiment.
    pub experiment_id: i64,
    /// Requests so far.
    pub generation: i64,
    /// The replica fitting it, if one holds it.
    pub claimed_by: Option<String>,
}

/// How a finished fit ended for its row.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FitFinish {
    /// Done: the row is gone (or handed back, when a request came in meanwhile).
    Done,
    /// The claim was no longer this replica's: nothing was stored.
    Lost,
}

fn unix_now() -> f64 {
    time::OffsetDateTime::now_utc().unix_timestamp_nanos() as f64 / 1e9
}

/// Requests a fit of `experiment_id` inside the caller's transaction (which holds the
/// experiment's lock): what [`Store::request_fit`] does, for a change that must not be stored
/// without its fit being requested (an exclusion, a restore).
pub(super) async fn raise_fit(
    conn: &mut AnyConnection,
    experiment_id: i64,
    forced: bool,
) -> Result<(), sqlx::Error> {
    let raised = sqlx::query(
        "UPDATE fit_jobs SET generation = generation + 1, forced = (forced OR $2)
         WHERE experiment_id = $1",
    )
    .bind(experiment_id)
    .bind(forced)
    .execute(&mut *conn)
    .await?
    .rows_affected();
    if raised == 0 {
        sqlx::query(
            "INSERT INTO fit_jobs (experiment_id, generation, forced, requested_at)
             VALUES ($1, 1, $2, $3)",
        )
        .bind(experiment_id)
        .bind(forced)
        .bind(now())
        .execute(&mut *conn)
        .await?;
    }
    Ok(())
}

/// The seconds a requested fit of `fit_jobs j` is expected to take: the longest of its
/// experiment's last five fits (a warm refit's cost, or the model selection one in five
/// re-runs), scaled by the cube of how much its data grew since (an exact GP's cost; a fleet's
/// experiment that tripled since its last fit takes 27 times as long); 0 before its first fit.
/// Fits are claimed in the order they would finish if each started when it was requested: a
/// robot's fit of a few hundred transitions (seconds) goes before a fleet's refit of thousands
/// (minutes) requested a little earlier, and a large fit waits at most about its own length for
/// the small ones requested after it.
fn expected_seconds() -> String {
    let growth = "((SELECT CAST(COUNT(*) AS DOUBLE PRECISION) FROM transitions t
                    WHERE t.experiment_id = j.experiment_id)
                   / (SELECT CAST(MAX(v.n_train) AS DOUBLE PRECISION) FROM models v
                      WHERE v.experiment_id = j.experiment_id))";
    format!(
        "COALESCE((SELECT MAX(m.fit_seconds) FROM models m
                   WHERE m.experiment_id = j.experiment_id
                     AND m.version > (SELECT MAX(v.version) FROM models v
                                      WHERE v.experiment_id = j.experiment_id) - 5)
                  * {growth} * {growth} * {growth}, 0)"
    )
}

impl Store {
    /// Requests a fit of `experiment_id` (`forced`: even if a model covers its latest batch).
    #[tracing::instrument(skip(self))]
    pub async fn request_fit(&self, experiment_id: i64, forced: bool) -> Result<(), sqlx::Error> {
        self.noted(async {
            let mut tx = self.begin_write().await?;
            lock_experiment(&mut tx, self.backend, experiment_id).await?;
            raise_fit(&mut tx, experiment_id, forced).await?;
            tx.commit().await
        })
        .await
    }

    /// Claims a requested fit for `replica`: one nobody holds, or whose holder's last
    /// heartbeat is older than `lease_seconds`; the one expected to finish first if each
    /// started when it was requested ([`expected_seconds`]); only `experiment_id`'s when given.
    /// `None` when there is none to claim.
    #[tracing::instrument(skip(self))]
    pub async fn claim_fit(
        &self,
        replica: &str,
        lease_seconds: f64,
        experiment_id: Option<i64>,
    ) -> Result<Option<FitClaim>, sqlx::Error> {
        self.noted(async {
            let now = unix_now();
            // SQLite's one writer makes the claim atomic; PostgreSQL's claimers skip each other's
            // locked rows. SQLite's `julianday` rounds to whole milliseconds: on a tie, the
            // stored time's nanoseconds (text that sorts in time) keep requests made within one
            // millisecond in the order they were made.
            let (skip_locked, requested_unix) = match self.backend {
                Backend::Sqlite => ("", "(julianday(j.requested_at) - 2440587.5) * 86400.0"),
                Backend::Postgres => (
                    "FOR UPDATE SKIP LOCKED",
                    "CAST(EXTRACT(EPOCH FROM CAST(j.requested_at AS TIMESTAMPTZ))
                          AS DOUBLE PRECISION)",
                ),
            };
            let expected = expected_seconds();
            let mut tx = self.begin_write().await?;
            let row = sqlx::query(&format!(
                "UPDATE fit_jobs
                 SET claimed_by = $1, claimed_generation = generation, heartbeat_unix = $2
                 WHERE experiment_id = (
                     SELECT j.experiment_id FROM fit_jobs j
                     WHERE (j.claimed_by IS NULL OR j.heartbeat_unix < $3)
                       AND ($4 IS NULL OR j.experiment_id = $4)
                     ORDER BY {requested_unix} + {expected}, j.requested_at, j.experiment_id
                     LIMIT 1 {skip_locked})
                 RETURNING experiment_id, generation, forced"
            ))
            .bind(replica)
            .bind(now)
            .bind(now - lease_seconds)
            .bind(experiment_id)
            .fetch_optional(&mut *tx)
            .await?;
            let Some(row) = row else {
                tx.commit().await?;
                return Ok(None);
            };
            let experiment_id: i64 = row.try_get("experiment_id")?;
            let generation: i64 = row.try_get("generation")?;
            let forced = flag(&row, "forced")?;
            if forced {
                // Taken: a client asking again during the fit raises it anew.
                sqlx::query("UPDATE fit_jobs SET forced = FALSE WHERE experiment_id = $1")
                    .bind(experiment_id)
                    .execute(&mut *tx)
                    .await?;
            }
            tx.commit().await?;
            let (version, covered): (i64, i64) = sqlx::query_as(
                "SELECT CAST(COALESCE(MAX(version), 0) + 1 AS BIGINT),
                        CAST(COALESCE(MAX(n_trajectories), 0) AS BIGINT)
                 FROM models WHERE experiment_id = $1",
            )
            .bind(experiment_id)
            .fetch_one(&self.write)
            .await?;
            Ok(Some(FitClaim {
                experiment_id,
                generation,
                forced,
                replica: replica.to_string(),
                version,
                covered_trajectories: covered,
            }))
        })
        .await
    }

    /// How many requested fits a replica may claim now (nobody holds them, or their holder's
    /// last heartbeat is older than `lease_seconds`).
    pub async fn claimable_fits(&self, lease_seconds: f64) -> Result<i64, sqlx::Error> {
        sqlx::query_scalar(
            "SELECT COUNT(*) FROM fit_jobs WHERE claimed_by IS NULL OR heartbeat_unix < $1",
        )
        .bind(unix_now() - lease_seconds)
        .fetch_one(&self.read)
        .await
    }

    /// Renews `claim`'s lease; `false` when it is no longer this replica's.
    pub async fn heartbeat_fit(&self, claim: &FitClaim) -> Result<bool, sqlx::Error> {
        self.noted(async {
            let renewed = sqlx::query(
                "UPDATE fit_jobs SET heartbeat_unix = $3 WHERE experiment_id = $1 AND claimed_by = $2",
            )
            .bind(claim.experiment_id)
            .bind(&claim.replica)
            .bind(unix_now())
            .execute(&self.write)
            .await?
            .rows_affected();
            Ok(renewed == 1)
        })
        .await
    }

    /// Ends `claim`: stores `model` (when the fit made one) and deletes the request, or hands
    /// it back when another request came in during the fit — all in one transaction, and only
    /// while the claim is still this replica's ([`FitFinish::Lost`] otherwise: nothing
    /// stored).
    #[tracing::instrument(skip(self, model))]
    pub async fn finish_fit(
        &self,
        claim: &FitClaim,
        model: Option<&StoredModel>,
    ) -> Result<FitFinish, sqlx::Error> {
        self.noted(async {
            let mut tx = self.begin_write().await?;
            lock_experiment(&mut tx, self.backend, claim.experiment_id).await?;
            let held: Option<(i64, Option<String>)> = sqlx::query_as(
                "SELECT generation, claimed_by FROM fit_jobs WHERE experiment_id = $1",
            )
            .bind(claim.experiment_id)
            .fetch_optional(&mut *tx)
            .await?;
            let Some((generation, Some(holder))) = held else {
                tx.rollback().await?;
                return Ok(FitFinish::Lost);
            };
            if holder != claim.replica {
                tx.rollback().await?;
                return Ok(FitFinish::Lost);
            }
            if let Some(model) = model {
                insert_model_on(&mut tx, claim.experiment_id, model).await?;
            }
            if generation == claim.generation {
                sqlx::query("DELETE FROM fit_jobs WHERE experiment_id = $1")
                    .bind(claim.experiment_id)
                    .execute(&mut *tx)
                    .await?;
            } else {
                // Requested again while it ran: the new request waits behind those made
                // meanwhile (keeping the first request's time, an experiment whose fits are
                // asked for without pause would claim every fit slot before the others).
                sqlx::query(
                    "UPDATE fit_jobs
                     SET claimed_by = NULL, claimed_generation = NULL, heartbeat_unix = NULL,
                         requested_at = $2
                     WHERE experiment_id = $1",
                )
                .bind(claim.experiment_id)
                .bind(now())
                .execute(&mut *tx)
                .await?;
            }
            tx.commit().await?;
            Ok(FitFinish::Done)
        })
        .await
    }

    /// Hands back every claim `replica` holds (it is shutting down), or every claim at all
    /// (`None`: a SQLite file opened by a new process, where no other process can be
    /// fitting). Returns how many.
    pub async fn release_fit_claims(&self, replica: Option<&str>) -> Result<u64, sqlx::Error> {
        self.noted(async {
            Ok(sqlx::query(
                "UPDATE fit_jobs
                 SET claimed_by = NULL, claimed_generation = NULL, heartbeat_unix = NULL
                 WHERE claimed_by IS NOT NULL AND ($1 IS NULL OR claimed_by = $1)",
            )
            .bind(replica)
            .execute(&self.write)
            .await?
            .rows_affected())
        })
        .await
    }

    /// The requested fits, oldest request first.
    pub async fn fit_jobs(&self) -> Result<Vec<FitJob>, sqlx::Error> {
        let rows: Vec<(i64, i64, Option<String>)> = sqlx::query_as(
            "SELECT experiment_id, generation, claimed_by FROM fit_jobs
             ORDER BY requested_at, experiment_id",
        )
        .fetch_all(&self.read)
        .await?;
        Ok(rows
            .into_iter()
            .map(|(experiment_id, generation, claimed_by)| FitJob {
                experiment_id,
                generation,
                claimed_by,
            })
            .collect())
    }

    /// Every experiment's latest model version (experiments with one).
    pub async fn latest_versions(&self) -> Result<Vec<(i64, i64)>, sqlx::Error> {
        sqlx::query_as(
            "SELECT experiment_id, CAST(MAX(version) AS BIGINT) FROM models
             GROUP BY experiment_id",
        )
        .fetch_all(&self.read)
        .await
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::{LabelledTransition, Transition};
    use crate::remote_model::ModelCalls;
    use crate::settings::ExperimentRequest;
    use crate::store::TrajectoryMeta;
    use std::sync::Arc;

    /// A new store with two default experiments.
    async fn two_experiments() -> (tempfile::TempDir, Store, i64, i64) {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path().join("fits.db").to_str().unwrap())
            .await
            .unwrap();
        let (settings, _) = ExperimentRequest::default()
            .resolve(&Arc::new(ModelCalls::default()))
            .unwrap();
        let mut ids = Vec::new();
        for _ in 0..2 {
            let e = store.insert_experiment(&settings, 10).await.unwrap();
            ids.push(e.unwrap().id);
        }
        (dir, store, ids[0], ids[1])
    }

    #[tokio::test]
    async fn an_experiment_asked_to_fit_again_while_it_fits_waits_behind_the_others() {
        let (_dir, store, busy, waiting) = two_experiments().await;
        store.request_fit(busy, false).await.unwrap();
        tokio::time::sleep(std::time::Duration::from_millis(5)).await;
        store.request_fit(waiting, false).await.unwrap();
        let first = store.claim_fit("r", 60.0, None).await.unwrap().unwrap();
        assert_eq!(first.experiment_id, busy, "the oldest request first");
        // Asked again while it fits; when it finishes, the other's request is older.
        store.request_fit(busy, true).await.unwrap();
        store.finish_fit(&first, None).await.unwrap();
        let next = store.claim_fit("r", 60.0, None).await.unwrap().unwrap();
        assert_eq!(next.experiment_id, waiting);
        let after = store.claim_fit("r", 60.0, None).await.unwrap().unwrap();
        assert_eq!(after.experiment_id, busy, "its request is kept, behind");
    }

    /// A model version of `experiment` whose fit took `seconds` (only the columns a claim
    /// reads mean anything).
    async fn fitted(store: &Store, experiment: i64, version: i64, seconds: f64) {
        sqlx::query(
            "INSERT INTO models (experiment_id, version, n_train, n_trajectories, noise, state,
                                 hyperparameters, log_marginal_likelihood, fit_seconds,
                                 fitted_at, label_cap, label_cap_trials)
             VALUES ($1, $2, 1, 1, 'homoscedastic', '{}', 'null', 0, $3, $4, 0, '[]')",
        )
        .bind(experiment)
        .bind(version)
        .bind(seconds)
        .bind(now())
        .execute(&store.write)
        .await
        .unwrap();
    }

    /// Stores a trajectory of `n` transitions in `experiment`.
    async fn stored(store: &Store, experiment: i64, n: usize) {
        let row: Vec<LabelledTransition> = (0..n)
            .map(|_| LabelledTransition {
                observed: Transition::new(vec![0.0, 0.0], vec![1.0, 0.0], vec![1.0, 0.0]),
                s_pred: vec![1.0, 0.0],
                deviation: 0.0,
            })
            .collect();
        let meta = TrajectoryMeta {
            proposal_id: None,
            partial: false,
            deviating: false,
            source: None,
        };
        store
            .ingest_trajectory(experiment, meta, &row, &[], None, 1)
            .await
            .unwrap();
    }

    #[tokio::test]
    async fn a_quick_fit_goes_before_a_long_one_requested_a_little_earlier_but_not_forever() {
        let (_dir, store, fleet, robot) = two_experiments().await;
        // The fleet's refits take minutes (the longest of the last five counts), the robot's
        // a second.
        fitted(&store, fleet, 1, 300.0).await;
        fitted(&store, fleet, 2, 2.0).await;
        fitted(&store, robot, 1, 0.5).await;
        // Neither grew since (one transition each, as fitted).
        stored(&store, fleet, 1).await;
        stored(&store, robot, 1).await;
        store.request_fit(fleet, true).await.unwrap();
        tokio::time::sleep(std::time::Duration::from_millis(5)).await;
        store.request_fit(robot, false).await.unwrap();
        let first = store.claim_fit("r", 60.0, None).await.unwrap().unwrap();
        assert_eq!(first.experiment_id, robot, "the quick fit first");
        store.finish_fit(&first, None).await.unwrap();
        // Requested long enough ago, the long fit goes before a quick one asked for now.
        sqlx::query("UPDATE fit_jobs SET requested_at = $2 WHERE experiment_id = $1")
            .bind(fleet)
            .bind(super::super::timestamp(
                time::OffsetDateTime::now_utc() - time::Duration::seconds(600),
            ))
            .execute(&store.write)
            .await
            .unwrap();
        store.request_fit(robot, false).await.unwrap();
        let next = store.claim_fit("r", 60.0, None).await.unwrap().unwrap();
        assert_eq!(next.experiment_id, fleet, "it waited longer than it takes");
        store.finish_fit(&next, None).await.unwrap();
        store.finish_fit(&first, None).await.unwrap();
    }

    /// Two requests within one millisecond (SQLite's date functions round to milliseconds):
    /// the earlier is claimed first, whichever experiment id is lower. The same order was left
    /// to the ids before, so a re-request finishing within a millisecond of another's request
    /// could jump ahead of it (a CI run of the test above failed so).
    #[tokio::test]
    async fn requests_within_one_millisecond_are_claimed_in_the_order_they_were_made() {
        let (_dir, store, low_id, high_id) = two_experiments().await;
        store.request_fit(low_id, false).await.unwrap();
        store.request_fit(high_id, false).await.unwrap();
        let second = time::OffsetDateTime::now_utc()
            .replace_nanosecond(0)
            .unwrap();
        let at = |nanos: i64| super::super::timestamp(second + time::Duration::nanoseconds(nanos));
        let (earlier, later) = (at(100_000), at(400_000));
        for (id, when) in [(high_id, &earlier), (low_id, &later)] {
            sqlx::query("UPDATE fit_jobs SET requested_at = $2 WHERE experiment_id = $1")
                .bind(id)
                .bind(when)
                .execute(&store.write)
                .await
                .unwrap();
        }
        let first = store.claim_fit("r", 60.0, None).await.unwrap().unwrap();
        assert_eq!(first.experiment_id, high_id, "{earlier} before {later}");
    }

    #[tokio::test]
    async fn an_experiment_whose_data_grew_since_its_last_fit_is_expected_to_take_longer() {
        let (_dir, store, grown, steady) = two_experiments().await;
        // Both last fitted in 10 s on one transition (`fitted`); the first has 8 since, so its
        // next fit is expected to take 512 × as long.
        fitted(&store, grown, 1, 10.0).await;
        fitted(&store, steady, 1, 10.0).await;
        stored(&store, grown, 8).await;
        stored(&store, steady, 1).await;
        store.request_fit(grown, false).await.unwrap();
        tokio::time::sleep(std::time::Duration::from_millis(5)).await;
        store.request_fit(steady, false).await.unwrap();
        let first = store.claim_fit("r", 60.0, None).await.unwrap().unwrap();
        assert_eq!(
            first.experiment_id, steady,
            "the grown one is expected to take 85 min"
        );
    }
}
