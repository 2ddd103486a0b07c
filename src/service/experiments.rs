//! Experiments: create, list, show.

use super::live::{LiveExperiment, build_stored_domain};
use super::{Error, Result, Service};
use crate::domain::Domain;
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
        let batch = i64::from(self.experiment.settings.learning.batch_size.max(1));
        self.experiment.n_trajectories / batch
    }
}

impl Service {
    /// Validates the settings, stores a new experiment and loads it (answering from the prior).
    pub async fn create_experiment(&self, request: ExperimentRequest) -> Result<ExperimentState> {
        let (settings, domain) = request.resolve(&self.model_urls)?;
        let _counted_and_created_together = self.creating.lock().await;
        let max = self.work.limits().max_experiments;
        if self.store.count_experiments().await? >= max as i64 {
            return Err(Error::LimitReached(format!(
                "this server holds its limit of {max} experiments (--max-experiments)"
            )));
        }
        let experiment = self.store.insert_experiment(&settings).await?;
        self.live
            .insert(LiveExperiment::new(experiment.id, settings, domain.clone()));
        tracing::info!(
            experiment = experiment.id,
            kind = domain.kind(),
            "experiment created"
        );
        Ok(ExperimentState { experiment, domain })
    }

    /// Every experiment, oldest first. Experiments this process has not loaded are shown from
    /// the store alone: listing never rebuilds a model.
    pub async fn experiments(&self) -> Result<Vec<ExperimentState>> {
        self.store
            .experiments()
            .await?
            .into_iter()
            .map(|experiment| self.state_of(experiment))
            .collect()
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
            None => build_stored_domain(experiment.id, &experiment.settings)?,
        };
        Ok(ExperimentState { experiment, domain })
    }
}
