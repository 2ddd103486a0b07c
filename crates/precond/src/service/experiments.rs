//! Experiments: create, list, show.

use super::live::{LiveExperiment, build_stored_domain};
use super::{Error, Result, Service};
use crate::domain::Domain;
use crate::limits::MAX_PAGE;
use crate::records::ListOrder;
use crate::settings::ExperimentRequest;
use crate::store::Experiment;
use std::sync::Arc;

/// A stored experiment with its built domain.
#[derive(Debug, Clone)]
pub struct ExperimentState {
    /// The stored experiment: settings, counters and latest model version.
    pub experiment: Experiment,
    /// Its domain (spaces, feature names).
    pub domain: Arc<dyn Domain>,
}

impl ExperimentState {
    /// The current learning iteration: completed batches.
    pub fn iteration(&self) -> i64 {
        self.experiment
            .settings
            .learning
            .iteration(self.experiment.n_trajectories)
    }
}

impl Service {
    /// Validates the settings, stores a new experiment and loads it (answering from the prior).
    pub async fn create_experiment(&self, request: ExperimentRequest) -> Result<ExperimentState> {
        let (settings, domain) = request.resolve(&self.model_calls)?;
        let max = self.work.limits().max_experiments;
        let Some(experiment) = self.store.insert_experiment(&settings, max as i64).await? else {
            return Err(Error::LimitReached(format!(
                "this server holds its limit of {max} experiments (--max-experiments)"
            )));
        };
        // Resolved settings make valid planning settings and models (`resolve` checked them).
        let models = settings.build_models(&*domain, &self.model_calls)?;
        self.live.insert(LiveExperiment::new(
            experiment.id,
            settings,
            domain.clone(),
            models,
        )?);
        tracing::info!(
            experiment = experiment.id,
            kind = domain.kind(),
            "experiment created"
        );
        Ok(ExperimentState { experiment, domain })
    }

    /// A page of experiments in `order`, skipping `offset`, at most `limit` (every one when
    /// `None`), with the total count. Experiments this process has not loaded are shown from
    /// the store alone: listing never rebuilds a model.
    pub async fn experiments(
        &self,
        order: ListOrder,
        offset: i64,
        limit: Option<i64>,
    ) -> Result<(Vec<ExperimentState>, i64)> {
        check_page(offset, limit)?;
        let total = self.store.count_experiments().await?;
        let items = self
            .store
            .experiments(order, offset, limit)
            .await?
            .into_iter()
            .map(|experiment| self.state_of(experiment))
            .collect::<Result<_>>()?;
        Ok((items, total))
    }

    /// One experiment; `NotFound` if there is none.
    pub async fn experiment(&self, id: i64) -> Result<ExperimentState> {
        let experiment = self
            .store
            .experiment(id)
            .await?
            .ok_or_else(|| Error::no_experiment(id))?;
        self.state_of(experiment)
    }

    fn state_of(&self, experiment: Experiment) -> Result<ExperimentState> {
        let domain = match self.live.cached(experiment.id) {
            Some(live) => live.domain.clone(),
            None => build_stored_domain(experiment.id, &experiment.settings, &self.model_calls)?,
        };
        Ok(ExperimentState { experiment, domain })
    }
}

/// Checks the `offset` and `limit` of an offset-paginated list.
pub(crate) fn check_page(offset: i64, limit: Option<i64>) -> Result<()> {
    if offset < 0 {
        return Err(Error::validation("offset", "must be at least 0"));
    }
    if limit.is_some_and(|l| !(1..=MAX_PAGE).contains(&l)) {
        return Err(Error::validation(
            "limit",
            format!("must be between 1 and {MAX_PAGE}"),
        ));
    }
    Ok(())
}

/// The `offset` of the page after one that skipped `offset` and held `len` of `total` rows.
pub(crate) fn next_offset(offset: i64, len: usize, total: i64) -> Option<i64> {
    let end = offset + len as i64;
    (len > 0 && end < total).then_some(end)
}
