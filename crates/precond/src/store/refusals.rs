//! Refused proposals: a proposal request answered `no_plan`, or stopped by its planning
//! deadline, is recorded with its problem, why, and everything the search tried.

use super::{Store, encode_vec, now};
use crate::planning::Strategy;
use crate::records::RefusalReason;

/// A proposal request that no trajectory answered, to store.
#[derive(Debug, Clone, PartialEq)]
pub struct NewRefusal {
    /// The client that asked.
    pub client_id: Option<String>,
    /// The learning iteration it was asked in.
    pub iteration: i64,
    /// The strategy that would have chosen.
    pub strategy: Strategy,
    /// The MDE version that scored the search.
    pub model_version: i64,
    /// Start state.
    pub start: Vec<f64>,
    /// Goal.
    pub goal: Vec<f64>,
    /// Every β tried, in order (the iteration's `β_j` first; more with `learning.relax_beta`).
    pub betas: Vec<f64>,
    /// RRT extensions spent over every β (for `random`, actions tried; 0 for the client's
    /// candidates).
    pub extensions: i64,
    /// How many of the client's candidates were judged (`None`: the service planned).
    pub candidates: Option<i64>,
    /// Why it was refused.
    pub reason: RefusalReason,
}

impl Store {
    /// Records a refused proposal; returns its identifier.
    #[tracing::instrument(skip(self, r))]
    pub async fn insert_refusal(
        &self,
        experiment_id: i64,
        r: &NewRefusal,
    ) -> Result<i64, sqlx::Error> {
        self.noted(async {
            sqlx::query_scalar(
                "INSERT INTO refusals (experiment_id, client_id, iteration, strategy, model_version,
                                       start, goal, betas, extensions, candidates, created_at,
                                       first_beta, reason)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13) RETURNING id",
            )
            .bind(experiment_id)
            .bind(&r.client_id)
            .bind(r.iteration)
            .bind(r.strategy.as_str())
            .bind(r.model_version)
            .bind(encode_vec(&r.start))
            .bind(encode_vec(&r.goal))
            .bind(encode_vec(&r.betas))
            .bind(r.extensions)
            .bind(r.candidates)
            .bind(now())
            .bind(r.betas.first().copied())
            .bind(r.reason.as_str())
            .fetch_one(&self.write)
            .await
        })
        .await
    }
}
