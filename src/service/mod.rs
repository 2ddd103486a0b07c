//! The service layer: what precond does, independent of how it is asked. Each operation takes a
//! request's plain values, validates them against the experiment's domain, does the work
//! (labelling, storing, fitting, planning, judging) and returns domain values; the HTTP layer
//! only parses requests and renders these values.
//!
//! - [`live`](mod@live): experiments in memory (built domain, current model), background refits.
//! - [`experiments`](mod@experiments): create, list and show experiments.
//! - [`ingest`](mod@ingest): label executed transitions with the experiment's own model and
//!   store a trajectory atomically and idempotently.
//! - [`learning`](mod@learning): the model, refits, precondition judgements and test-time plans.
//! - [`proposals`](mod@proposals): proposals (ask) and their leases.
//! - [`activity`](mod@activity): an experiment's runs and learning timeline, for the dashboard.
//! - [`inspection`](mod@inspection): a model version on a grid (the precondition map) and its
//!   leave-one-out calibration.
//! - [`error`](mod@error): the service's [`Error`].
//!
//! CPU-heavy work (fits, planning, large judgements, calls to the dynamics model) runs on the
//! blocking pool, never on the async workers.

pub mod activity;
pub mod error;
pub mod experiments;
pub mod ingest;
pub mod inspection;
pub mod learning;
pub mod live;
pub mod proposals;

pub use activity::{LearningTimeline, Runs};
pub use error::{Error, Result};
pub use experiments::ExperimentState;
pub use ingest::Ingested;
pub use inspection::{LooDiagnostics, MapRequest, PreconditionGrid};
pub use learning::{Judged, ModelView, Planned};
pub use live::{FitTrigger, LiveExperiment, Registry};
pub use proposals::ProposalRecord;

use crate::remote_model::ModelUrlPolicy;
use crate::store::Store;
use std::sync::Arc;

/// The service: the store, the operator's policies and the experiments this process has
/// loaded. Cheap to clone.
#[derive(Debug, Clone)]
pub struct Service {
    store: Store,
    live: Arc<Registry>,
    model_urls: Arc<ModelUrlPolicy>,
}

impl Service {
    /// The service over an opened store, with no remote model allowed.
    pub fn new(store: Store) -> Self {
        Self::with_model_urls(store, ModelUrlPolicy::default())
    }

    /// The service over an opened store, allowing remote models under `model_urls`.
    pub fn with_model_urls(store: Store, model_urls: ModelUrlPolicy) -> Self {
        Self {
            store,
            live: Arc::new(Registry::default()),
            model_urls: Arc::new(model_urls),
        }
    }

    /// The store.
    pub fn store(&self) -> &Store {
        &self.store
    }

    /// Whether the database answers.
    pub async fn ready(&self) -> Result<(), sqlx::Error> {
        self.store.ping().await
    }

    /// The live experiment `id` (domain and current model), loading it if needed; `NotFound`
    /// if there is no such experiment.
    pub async fn live(&self, id: i64) -> Result<Arc<LiveExperiment>> {
        self.live.get(&self.store, id).await
    }

    /// Runs CPU-heavy or blocking work (planning, fitting, the dynamics model) on the blocking
    /// pool.
    pub(crate) async fn blocking<T: Send + 'static>(
        work: impl FnOnce() -> T + Send + 'static,
    ) -> Result<T> {
        tokio::task::spawn_blocking(work)
            .await
            .map_err(|e| Error::Internal(anyhow::Error::new(e).context("blocking task")))
    }
}
