//! The service layer: what precond does, independent of how it is asked. Each operation takes a
//! request's plain values, validates them against the experiment's domain, does the work
//! (labelling, storing, fitting, planning, judging) and returns domain values; the HTTP layer
//! only parses requests and renders these values.
//!
//! - [`live`](mod@live): experiments in memory (built domain, current model), their fits.
//! - `further`: the estimators of an experiment's further models of its robot — their
//!   training sets, their fits beside the domain model's, their rebuild.
//! - [`fitting`](mod@fitting): fits as jobs claimed through the store, so that replicas over
//!   one database take turns and share the work; the watcher that loads others' versions.
//! - [`experiments`](mod@experiments): create, list and show experiments.
//! - [`ingest`](mod@ingest): label executed transitions with the experiment's own model (and
//!   each further model) and store a trajectory atomically and idempotently.
//! - [`imports`](mod@imports): a file of logged transitions into an experiment through
//!   [`crate::import`], each trajectory stored as a posted one.
//! - [`learning`](mod@learning): the model, refits, precondition judgements (any of the
//!   robot's models') and test-time plans.
//! - [`proposals`](mod@proposals): proposals (ask) and their leases.
//! - [`work`](mod@work): bounded work — the operator's [`Limits`] and the gate every search,
//!   fit and large evaluation (maps, diagnostics, large precondition queries) passes through
//!   (concurrency, queue, deadlines, cancellation).
//! - [`activity`](mod@activity): an experiment's runs, learning timeline and each model's
//!   labels summed up, for the dashboard.
//! - [`inspection`](mod@inspection): a model version on a grid (the precondition map) and its
//!   leave-one-out calibration.
//! - [`exports`](mod@exports): large answers (a model's export, every transition as CSV)
//!   prepared in export slots, to be written a chunk at a time.
//! - [`exclusions`](mod@exclusions): trajectories left out of an experiment's model, and
//!   restored.
//! - [`error`](mod@error): the service's [`Error`].
//!
//! CPU-heavy work (large judgements, in-process dynamics models) runs on the blocking pool,
//! searches and fits on threads of their own under the work gate, calls to remote dynamics
//! models on threads of their own under [`ModelCalls`]' limits — never on the async workers.

pub mod activity;
pub mod error;
pub mod exclusions;
pub mod experiments;
pub mod exports;
pub mod fitting;
mod further;
pub mod imports;
pub mod ingest;
pub mod inspection;
pub mod learning;
pub mod live;
pub mod proposals;
pub mod work;

pub use activity::{LearningTimeline, Runs};
pub use error::{Error, Result};
pub use experiments::ExperimentState;
pub use exports::{ModelExport, TransitionsExport};
pub use fitting::FitQueue;
pub use ingest::Ingested;
pub use inspection::{LooDiagnostics, MapRequest, PreconditionGrid};
pub use learning::{Judged, ModelView, Planned};
pub use live::{LiveExperiment, Registry};
pub use proposals::ProposalRecord;
pub use work::{ExportSlot, Limits, WorkGate};

use crate::planning::{Budget, PlanningError, Stop};
use crate::remote_model::{ModelCallLimits, ModelCalls, ModelUrlPolicy};
use crate::store::Store;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How long readiness waits for the database: within a probe's usual budget (Kubernetes'
/// default is 1 s), so a database that does not answer is a `503`, not a timed-out probe.
pub const READINESS_TIMEOUT: Duration = Duration::from_millis(800);

/// What a search is for, for the metrics it counts itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SearchKind {
    /// A training proposal (`precond_proposals_total`).
    Proposal,
    /// A test-time plan.
    Plan,
}

impl SearchKind {
    /// Counts a search its client abandoned (the request is gone, so the search counts it).
    fn count_cancelled(self) {
        match self {
            Self::Proposal => {
                metrics::counter!("precond_proposals_total", "outcome" => "cancelled").increment(1)
            }
            Self::Plan => {}
        }
    }
}

/// Counts its search as cancelled when dropped while it still holds the kind (the request went
/// away while its search waited for a slot).
struct CountIfDropped(Option<SearchKind>);

impl Drop for CountIfDropped {
    fn drop(&mut self) {
        if let Some(kind) = self.0 {
            kind.count_cancelled();
        }
    }
}

/// The service: the store, the operator's policies and the experiments this process has
/// loaded. Cheap to clone.
#[derive(Debug, Clone)]
pub struct Service {
    store: Store,
    live: Arc<Registry>,
    /// Where remote models may live and how their calls are bounded.
    model_calls: Arc<ModelCalls>,
    work: Arc<WorkGate>,
    /// This replica's side of the fit jobs.
    fits: Arc<FitQueue>,
}

/// The background tasks of a serving [`Service`] (the fit worker and the version watcher):
/// stopped when dropped.
#[derive(Debug)]
pub struct Background {
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Drop for Background {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
    }
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
            model_calls: Arc::new(ModelCalls::new(model_urls, ModelCallLimits::default())),
            work: Arc::new(WorkGate::new(Limits::default())),
            fits: Arc::new(FitQueue::default()),
        }
    }

    /// The same service with fit claims leased for `lease` and the store polled every `poll`
    /// for other replicas' fit requests and versions (see [`fitting`](mod@fitting)).
    pub fn with_fit_lease(mut self, lease: std::time::Duration, poll: std::time::Duration) -> Self {
        self.fits = Arc::new(FitQueue::new(lease, poll));
        self
    }

    /// Starts the fit worker and (on PostgreSQL) the version watcher; they run until the
    /// returned value is dropped. On SQLite, claims a previous process left are handed back
    /// first: one process owns the file, so nobody else is fitting.
    pub async fn start_background(&self) -> Background {
        if self.store.backend() == crate::store::Backend::Sqlite {
            match self.store.release_fit_claims(None).await {
                Ok(0) => {}
                Ok(n) => tracing::info!(fits = n, "fits a stopped server left are requested again"),
                Err(e) => tracing::error!(error = %e, "could not hand back old fit claims"),
            }
        }
        Background {
            tasks: vec![
                tokio::spawn(self.fits.clone().run_worker(self.clone())),
                tokio::spawn(
                    self.fits
                        .clone()
                        .run_watcher(self.store.clone(), self.live.clone()),
                ),
            ],
        }
    }

    /// Hands back the fit claims this replica holds (it is stopping): another replica takes
    /// them over at once instead of after the lease.
    pub async fn release_fits(&self) {
        if let Err(e) = self
            .store
            .release_fit_claims(Some(self.fits.replica()))
            .await
        {
            tracing::warn!(error = %e, "could not hand back this replica's fit claims");
        }
    }

    /// This replica's side of the fit jobs.
    pub fn fits(&self) -> &Arc<FitQueue> {
        &self.fits
    }

    /// The same service under the operator's `limits` (assumed checked, see
    /// [`Limits::check`]).
    pub fn with_limits(mut self, limits: Limits) -> Self {
        self.work = Arc::new(WorkGate::new(limits));
        self
    }

    /// The same service with the operator's limits on remote model calls (assumed checked, see
    /// [`ModelCallLimits::check`]); the URL policy stays.
    pub fn with_model_limits(mut self, limits: ModelCallLimits) -> Self {
        self.model_calls = Arc::new(ModelCalls::new(self.model_calls.policy().clone(), limits));
        self
    }

    /// Remote model calls: the URL policy, the limits, the calls running.
    pub fn model_calls(&self) -> &Arc<ModelCalls> {
        &self.model_calls
    }

    /// The gate searches and fits pass through, with the limits.
    pub fn work(&self) -> &WorkGate {
        &self.work
    }

    /// The store.
    pub fn store(&self) -> &Store {
        &self.store
    }

    /// Whether the store can serve now (the database answers within [`READINESS_TIMEOUT`],
    /// and writes are not failing for lack of space).
    pub async fn ready(&self) -> Result<(), crate::store::NotReady> {
        self.store.readiness(READINESS_TIMEOUT).await
    }

    /// The live experiment `id` (domain and current model), loading it if needed; `NotFound`
    /// if there is no such experiment.
    pub async fn live(&self, id: i64) -> Result<Arc<LiveExperiment>> {
        self.live
            .get(&self.store, || self.fits.wake(), &self.model_calls, id)
            .await
    }

    /// Runs a planning search of `experiment` through the work gate (see [`work`](mod@work)):
    /// waits for a slot (experiments take turns) until the deadline counted from `arrived`, then searches on a thread of its own
    /// with that deadline and a flag raised if this future is dropped (the client went away).
    ///
    /// A search stopped by that flag is counted by the search itself
    /// (`precond_proposals_total{outcome="cancelled"}` for a proposal), and one whose request
    /// went away while it waited for a slot when it leaves the queue: nobody is left to count
    /// the answer.
    pub(crate) async fn search<T: Send + 'static>(
        &self,
        experiment: i64,
        arrived: Instant,
        kind: SearchKind,
        search: impl FnOnce(&Budget) -> Result<T, PlanningError> + Send + 'static,
    ) -> Result<T> {
        // A request dropped while it waits for a slot is cancelled too, with no search to count
        // it: the guard counts it unless the wait ends.
        let mut waiting = CountIfDropped(Some(kind));
        let slot = self.work.plan_slot(experiment, arrived).await;
        waiting.0 = None;
        let (slot, deadline) = slot?;
        let (budget, _cancel_on_drop) = WorkGate::budget(deadline);
        let outcome = work::run_niced(move || {
            // The slot is held by the running search, not by the request: a cancelled
            // request's slot frees when its search has actually stopped.
            let _slot = slot;
            let outcome = search(&budget);
            if let Err(PlanningError::Stopped {
                reason: Stop::Cancelled,
                ..
            }) = &outcome
            {
                kind.count_cancelled();
            }
            outcome
        })
        .await?;
        outcome.map_err(|e| match e {
            PlanningError::Stopped {
                reason: Stop::Deadline,
                extensions,
            } => self.work.deadline_exceeded(extensions),
            PlanningError::Stopped {
                reason: Stop::Cancelled,
                ..
            } => Error::Cancelled,
            e => e.into(),
        })
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
