//! Fits as jobs: which replica fits which experiment, and how every replica learns of the
//! versions the others fitted.
//!
//! A completed batch *requests* a fit in the store (`fit_jobs`, see
//! [`store::fits`](crate::store::fits)). Each replica runs one [`FitQueue::run_worker`] loop:
//! when a request is waiting it takes a fit slot of its own [`WorkGate`](super::WorkGate),
//! *claims* the request (on PostgreSQL claimers skip each other's rows, so two replicas take
//! two different experiments), fits on that slot while heartbeating, and stores the version and
//! ends the request in one transaction. A replica that dies mid-fit stops heartbeating; after
//! [`FitQueue::lease`] another takes its request over. So fits spread over the replicas'
//! cores, each replica bounded by its own fit budget.
//!
//! On PostgreSQL [`FitQueue::run_watcher`] polls the newest stored version of every
//! experiment this replica has loaded and swaps it in, so every replica answers from the
//! newest version within a poll interval of its fit. (One process owns a SQLite file, and swaps
//! in what it fits itself.)

use super::live::{LiveExperiment, Registry};
use super::work::{Slot, WorkGate};
use super::{Error, Service};
use crate::mde::ServedModel;
use crate::store::{Backend, FitClaim, Store};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::Notify;

/// This replica's side of the fit jobs: its name, the lease, and the bell that wakes its
/// worker when it requested a fit itself.
#[derive(Debug)]
pub struct FitQueue {
    /// This replica's name in `fit_jobs.claimed_by`: host, process and a random suffix.
    replica: String,
    /// A claim whose holder has not heartbeated for this long is taken over.
    lease: Duration,
    /// How often the worker looks for requests other replicas made, and the watcher for
    /// versions other replicas fitted.
    poll: Duration,
    wake: Notify,
    /// Experiments with a forced fit waiting for a fit slot or fitting
    /// ([`start_forcing`](Self::start_forcing)).
    forcing: std::sync::Mutex<std::collections::HashSet<i64>>,
}

/// Experiment `id`'s forced fit, from [`FitQueue::start_forcing`] until dropped.
#[derive(Debug)]
pub(crate) struct Forcing {
    queue: Arc<FitQueue>,
    id: i64,
}

impl Drop for Forcing {
    fn drop(&mut self) {
        self.queue.forcing_set().remove(&self.id);
    }
}

/// The default lease of a fit claim.
pub const DEFAULT_FIT_LEASE: Duration = Duration::from_secs(15);

/// The default interval between looks at the store for others' requests and versions.
pub const DEFAULT_POLL: Duration = Duration::from_millis(500);

impl Default for FitQueue {
    fn default() -> Self {
        Self::new(DEFAULT_FIT_LEASE, DEFAULT_POLL)
    }
}

impl FitQueue {
    /// A queue with a new replica name, claims leased for `lease`, polling every `poll`.
    pub fn new(lease: Duration, poll: Duration) -> Self {
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "host".into());
        let suffix = uuid::Uuid::new_v4().simple().to_string();
        Self {
            replica: format!("{host}-{}-{}", std::process::id(), &suffix[..8]),
            lease,
            poll,
            wake: Notify::new(),
            forcing: Default::default(),
        }
    }

    /// Marks a forced fit of experiment `id` as waiting (until the returned value is dropped),
    /// or `None` when one already waits or runs: a refit asked for again meanwhile waits for
    /// what that one (or the worker after it) stores, instead of queueing a fit of its own.
    pub(crate) fn start_forcing(queue: &Arc<Self>, id: i64) -> Option<Forcing> {
        queue.forcing_set().insert(id).then(|| Forcing {
            queue: queue.clone(),
            id,
        })
    }

    fn forcing_set(&self) -> std::sync::MutexGuard<'_, std::collections::HashSet<i64>> {
        // A panic while holding it cannot leave the set inconsistent (one insert or remove).
        self.forcing.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// This replica's name.
    pub fn replica(&self) -> &str {
        &self.replica
    }

    /// The lease of a claim.
    pub fn lease(&self) -> Duration {
        self.lease
    }

    /// Wakes this replica's worker: a request is waiting.
    pub fn wake(&self) {
        self.wake.notify_one();
    }

    /// Claims the requested fit that would finish first (see
    /// [`Store::claim_fit`](crate::store::Store::claim_fit)), of any experiment.
    pub(crate) async fn claim_next(&self, store: &Store) -> Result<Option<FitClaim>, Error> {
        Ok(store
            .claim_fit(&self.replica, self.lease.as_secs_f64(), None)
            .await?)
    }

    /// Fits the experiment `claim` names on `slot`, loading it if needed; a claim whose
    /// experiment no longer loads (its remote model is no longer allowed, say) is ended rather
    /// than retried forever.
    pub(crate) async fn fit_claim(
        &self,
        service: &Service,
        claim: FitClaim,
        slot: Slot,
    ) -> Result<Arc<ServedModel>, Error> {
        match service.live(claim.experiment_id).await {
            Ok(live) => {
                self.fit(&live, service.store(), service.work(), claim, slot)
                    .await
            }
            Err(e) => {
                let _ = service.store().finish_fit(&claim, None).await;
                Err(e)
            }
        }
    }

    /// Fits `live` under `claim` on `slot` (see [`LiveExperiment::fit_under`]), heartbeating
    /// the claim all the while so no other replica takes it over.
    pub(crate) async fn fit(
        &self,
        live: &Arc<LiveExperiment>,
        store: &Store,
        gate: &WorkGate,
        claim: FitClaim,
        slot: Slot,
    ) -> Result<Arc<ServedModel>, Error> {
        let heartbeat = self.keep_alive(store, &claim);
        let fitted = live.fit_under(store, gate, claim, slot, self.lease).await;
        heartbeat.abort();
        fitted
    }

    /// Heartbeats `claim` every quarter lease until aborted.
    fn keep_alive(&self, store: &Store, claim: &FitClaim) -> tokio::task::JoinHandle<()> {
        let (store, claim, every) = (store.clone(), claim.clone(), self.lease / 4);
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(every).await;
                match store.heartbeat_fit(&claim).await {
                    Ok(true) => {}
                    Ok(false) => {
                        tracing::warn!(
                            experiment = claim.experiment_id,
                            "another replica took over this fit; its result will be dropped"
                        );
                        return;
                    }
                    Err(e) => tracing::warn!(
                        experiment = claim.experiment_id,
                        error = %e,
                        "could not renew a fit claim"
                    ),
                }
            }
        })
    }

    /// The worker: waits for requested fits (woken by [`FitQueue::wake`], or every poll
    /// interval for those other replicas made, or whose holder died), and fits each in a
    /// fit slot of `service`'s work gate, several at once up to the gate's fit cap. Runs until
    /// its task is aborted.
    pub async fn run_worker(self: Arc<Self>, service: Service) {
        loop {
            if !self.waiting(service.store()).await {
                tokio::select! {
                    () = self.wake.notified() => {}
                    () = tokio::time::sleep(self.poll) => {}
                }
                continue;
            }
            let slot = match service.work().fit_slot().await {
                Ok(slot) => slot,
                Err(e) => {
                    tracing::error!(error = %e, "no fit slot");
                    tokio::time::sleep(self.poll).await;
                    continue;
                }
            };
            let claim = match self.claim_next(service.store()).await {
                Ok(Some(claim)) => claim,
                Ok(None) => continue,
                Err(e) => {
                    tracing::error!(error = %e, "could not claim a fit");
                    tokio::time::sleep(self.poll).await;
                    continue;
                }
            };
            let (service, queue) = (service.clone(), self.clone());
            tokio::spawn(async move {
                let id = claim.experiment_id;
                let fitted = queue.fit_claim(&service, claim, slot).await.map(|_| ());
                match fitted {
                    Ok(()) => {}
                    // Nothing to fit, or the claim went to another replica: not a failure.
                    Err(e @ Error::Conflict(_)) => {
                        tracing::warn!(experiment = id, error = %e, "background fit not made");
                    }
                    Err(e) => {
                        tracing::error!(experiment = id, error = %e, "background fit failed");
                    }
                }
            });
        }
    }

    /// Whether a request waits that this replica may claim (cheap: no claim is taken).
    async fn waiting(&self, store: &Store) -> bool {
        match store.claimable_fits(self.lease.as_secs_f64()).await {
            Ok(n) => n > 0,
            Err(e) => {
                tracing::warn!(error = %e, "could not look for requested fits");
                false
            }
        }
    }

    /// The watcher (PostgreSQL): every poll interval, swaps in the newest stored version of
    /// each experiment this replica has loaded, when another replica fitted it. Runs until its
    /// task is aborted.
    pub async fn run_watcher(self: Arc<Self>, store: Store, live: Arc<Registry>) {
        if store.backend() != Backend::Postgres {
            return;
        }
        loop {
            tokio::time::sleep(self.poll).await;
            let versions = match store.latest_versions().await {
                Ok(v) => v,
                Err(e) => {
                    tracing::warn!(error = %e, "could not look for new model versions");
                    continue;
                }
            };
            for (id, version) in versions {
                let Some(experiment) = live.cached(id) else {
                    continue;
                };
                if version <= experiment.model().version {
                    continue;
                }
                match experiment.load_latest(&store).await {
                    Ok(v) => tracing::info!(experiment = id, version = v, "loaded a newer version"),
                    Err(e) => tracing::warn!(
                        experiment = id,
                        error = %e,
                        "could not load a newer model version"
                    ),
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_forced_fit_per_experiment_waits_at_a_time() {
        let queue = Arc::new(FitQueue::default());
        let first = FitQueue::start_forcing(&queue, 1).expect("none waits yet");
        assert!(
            FitQueue::start_forcing(&queue, 1).is_none(),
            "one waits already"
        );
        let other = FitQueue::start_forcing(&queue, 2).expect("another experiment's own");
        drop(first);
        assert!(
            FitQueue::start_forcing(&queue, 1).is_some(),
            "free once it ended"
        );
        drop(other);
        assert!(queue.forcing_set().is_empty());
    }
}
