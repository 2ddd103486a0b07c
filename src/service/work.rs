//! Bounded work: the operator's limits and the gate every planning search and every fit
//! passes through.
//!
//! - At most [`Limits::max_concurrent_plans`] searches and fits run at once (a semaphore sized
//!   from the cores by default), so the async workers that answer health checks and cheap
//!   reads always find a core.
//! - A request waits for a slot at most until its deadline ([`Limits::plan_timeout`], counted
//!   from its arrival); the search itself stops at the same deadline. Either way the client
//!   gets `503 deadline_exceeded` with `Retry-After` (or `no_plan` if the search concluded).
//! - At most [`Limits::max_queued_plans`] requests wait at once; beyond that a request is
//!   refused at once with `429 overloaded` and `Retry-After`.
//! - A search whose client went away stops at its next round: the request's future holds a
//!   guard that raises the search's cancel flag when it is dropped.
//! - Fits (background or forced) take a slot too but have no deadline: a fit is one
//!   optimisation that cannot stop halfway, and its worst case is bounded by the training-set
//!   size and `restarts`.

use super::{Error, Result};
use crate::limits::MAX_TRANSITIONS;
use crate::planning::Budget;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// Shortest planning deadline an operator may set.
pub const MIN_PLAN_TIMEOUT: Duration = Duration::from_millis(100);
/// Longest planning deadline an operator may set (10 minutes).
pub const MAX_PLAN_TIMEOUT: Duration = Duration::from_secs(600);

/// The operator's limits (command-line options of `precond serve`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Limits {
    /// Searches and fits running at once: `1 ..= 256`; default the number of cores.
    pub max_concurrent_plans: usize,
    /// Requests waiting for a slot at once before new ones are refused with `429`:
    /// `0 ..= 10 000`; default `8 × max_concurrent_plans`.
    pub max_queued_plans: usize,
    /// Wall-clock budget of one planning request, queueing included:
    /// [`MIN_PLAN_TIMEOUT`] ..= [`MAX_PLAN_TIMEOUT`]; default 30 s.
    pub plan_timeout: Duration,
    /// Experiments this server holds: `1 ..= 1 000 000`; default 1000.
    pub max_experiments: usize,
    /// Transitions in one posted trajectory: `1 ..=` [`MAX_TRANSITIONS`]; default the same.
    pub max_transitions: usize,
    /// Bytes one MDE fit may use at its peak (estimated before it allocates, see
    /// [`crate::gp::FitCost`]): a fit beyond it is not attempted but recorded as refused, and
    /// with `mde.estimator: auto` the sparse GP takes over before the exact GP would need it.
    /// `64 MiB ..= 1 TiB`; default a quarter of the machine's memory (4 GiB where unknown).
    pub max_fit_memory: u64,
}

/// A quarter of the machine's physical memory (`/proc/meminfo`), or 4 GiB where unknown.
pub fn default_fit_memory() -> u64 {
    let total = std::fs::read_to_string("/proc/meminfo").ok().and_then(|m| {
        m.lines()
            .find(|l| l.starts_with("MemTotal:"))
            .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
            .map(|kib| kib * 1024)
    });
    total.map_or(4 << 30, |t| (t / 4).max(64 << 20))
}

impl Default for Limits {
    fn default() -> Self {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        Self {
            max_concurrent_plans: cores,
            max_queued_plans: 8 * cores,
            plan_timeout: Duration::from_secs(30),
            max_experiments: 1000,
            max_transitions: MAX_TRANSITIONS,
            max_fit_memory: default_fit_memory(),
        }
    }
}

impl Limits {
    /// Checks the ranges; the error names the option.
    pub fn check(&self) -> std::result::Result<(), String> {
        let range = |name: &str, v: usize, lo: usize, hi: usize| {
            if (lo..=hi).contains(&v) {
                Ok(())
            } else {
                Err(format!("--{name} must lie in {lo} ..= {hi}, got {v}"))
            }
        };
        range("max-concurrent-plans", self.max_concurrent_plans, 1, 256)?;
        range("max-queued-plans", self.max_queued_plans, 0, 10_000)?;
        range("max-experiments", self.max_experiments, 1, 1_000_000)?;
        range("max-transitions", self.max_transitions, 1, MAX_TRANSITIONS)?;
        let mib = self.max_fit_memory >> 20;
        if !(64..=(1 << 20)).contains(&mib) {
            return Err(format!(
                "--max-fit-memory-mib must lie in 64 ..= 1048576, got {mib}"
            ));
        }
        if !(MIN_PLAN_TIMEOUT..=MAX_PLAN_TIMEOUT).contains(&self.plan_timeout) {
            return Err(format!(
                "--plan-timeout-ms must lie in {} ..= {}, got {}",
                MIN_PLAN_TIMEOUT.as_millis(),
                MAX_PLAN_TIMEOUT.as_millis(),
                self.plan_timeout.as_millis()
            ));
        }
        Ok(())
    }

    /// Seconds a refused client should wait before retrying: the planning deadline, rounded
    /// up, at least 1.
    pub fn retry_after_secs(&self) -> u64 {
        self.plan_timeout.as_millis().div_ceil(1000).max(1) as u64
    }
}

/// The gate: the slots, the queue and the limits.
#[derive(Debug)]
pub struct WorkGate {
    limits: Limits,
    slots: Arc<Semaphore>,
    waiting: AtomicUsize,
    running: Arc<AtomicUsize>,
}

/// A slot: held while a search or fit runs; releasing it updates the gauges.
#[derive(Debug)]
pub struct Slot {
    _permit: OwnedSemaphorePermit,
    running: Arc<AtomicUsize>,
}

impl Drop for Slot {
    fn drop(&mut self) {
        let now = self.running.fetch_sub(1, Ordering::Relaxed) - 1;
        metrics::gauge!("precond_planning_running").set(now as f64);
    }
}

/// Raises a search's cancel flag when the request that started it is dropped (the client went
/// away) or finishes.
#[derive(Debug)]
pub struct CancelOnDrop(pub Arc<AtomicBool>);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

impl WorkGate {
    /// A gate with these limits (assumed checked).
    pub fn new(limits: Limits) -> Self {
        Self {
            slots: Arc::new(Semaphore::new(limits.max_concurrent_plans)),
            limits,
            waiting: AtomicUsize::new(0),
            running: Arc::new(AtomicUsize::new(0)),
        }
    }

    /// The limits.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Requests waiting for a slot now.
    pub fn queue_depth(&self) -> usize {
        self.waiting.load(Ordering::Relaxed)
    }

    fn set_waiting(&self, delta: isize) {
        let now = if delta > 0 {
            self.waiting.fetch_add(1, Ordering::Relaxed) + 1
        } else {
            self.waiting.fetch_sub(1, Ordering::Relaxed) - 1
        };
        metrics::gauge!("precond_planning_queue_depth").set(now as f64);
    }

    fn granted(&self, permit: OwnedSemaphorePermit) -> Slot {
        let now = self.running.fetch_add(1, Ordering::Relaxed) + 1;
        metrics::gauge!("precond_planning_running").set(now as f64);
        Slot {
            _permit: permit,
            running: self.running.clone(),
        }
    }

    /// A slot for a planning request that arrived at `arrived`: `429` at once when the queue
    /// is full, `503` when the deadline passes while waiting.
    pub async fn plan_slot(&self, arrived: Instant) -> Result<(Slot, Instant)> {
        let deadline = arrived + self.limits.plan_timeout;
        if let Ok(permit) = self.slots.clone().try_acquire_owned() {
            return Ok((self.granted(permit), deadline));
        }
        if self.queue_depth() >= self.limits.max_queued_plans {
            return Err(Error::Overloaded {
                retry_after_secs: self.limits.retry_after_secs(),
            });
        }
        self.set_waiting(1);
        let waited = tokio::time::timeout_at(
            tokio::time::Instant::from_std(deadline),
            self.slots.clone().acquire_owned(),
        )
        .await;
        self.set_waiting(-1);
        match waited {
            Ok(Ok(permit)) => Ok((self.granted(permit), deadline)),
            Ok(Err(_closed)) => Err(Error::Internal(anyhow::anyhow!("the work gate closed"))),
            Err(_elapsed) => Err(self.deadline_exceeded(0)),
        }
    }

    /// A slot for a fit: waits as long as it takes.
    pub async fn fit_slot(&self) -> Result<Slot> {
        self.set_waiting(1);
        let permit = self.slots.clone().acquire_owned().await;
        self.set_waiting(-1);
        permit
            .map(|p| self.granted(p))
            .map_err(|_| Error::Internal(anyhow::anyhow!("the work gate closed")))
    }

    /// The answer for a search stopped by its deadline after `extensions` extensions.
    pub fn deadline_exceeded(&self, extensions: usize) -> Error {
        Error::DeadlineExceeded {
            extensions,
            timeout_ms: self.limits.plan_timeout.as_millis() as u64,
            retry_after_secs: self.limits.retry_after_secs(),
        }
    }

    /// The budget of a search that must end by `deadline`, with the flag that cancels it.
    pub fn budget(deadline: Instant) -> (Budget, CancelOnDrop) {
        let flag = Arc::new(AtomicBool::new(false));
        (
            Budget::until(deadline).cancelled_by(flag.clone()),
            CancelOnDrop(flag),
        )
    }
}

/// Runs CPU-heavy `work` (a search or a fit) on a thread of its own at a lower scheduling
/// priority (nice +10 on Linux), so that the async workers answering health checks and reads
/// preempt it whenever they have something to do; the result comes back over a channel. A
/// panic in `work` is an internal error.
pub async fn run_niced<T: Send + 'static>(work: impl FnOnce() -> T + Send + 'static) -> Result<T> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    std::thread::Builder::new()
        .name("precond-work".into())
        .spawn(move || {
            lower_priority();
            let _ = tx.send(work());
        })
        .map_err(|e| Error::Internal(anyhow::Error::new(e).context("starting a work thread")))?;
    rx.await
        .map_err(|_| Error::Internal(anyhow::anyhow!("a work thread panicked")))
}

/// Raises this thread's nice value by 10 (Linux: per thread). Raising it needs no privilege;
/// if it fails anyway the work runs at normal priority.
fn lower_priority() {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: gettid and setpriority take and return plain integers; PRIO_PROCESS with a
        // thread id changes that thread only, this one.
        let rc = unsafe {
            let tid = libc::gettid();
            libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, 10)
        };
        if rc != 0 {
            tracing::debug!("could not lower a work thread's priority");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(slots: usize, queue: usize, timeout_ms: u64) -> Limits {
        Limits {
            max_concurrent_plans: slots,
            max_queued_plans: queue,
            plan_timeout: Duration::from_millis(timeout_ms),
            ..Limits::default()
        }
    }

    #[test]
    fn limits_are_checked_and_name_the_option() {
        assert!(Limits::default().check().is_ok());
        let e = limits(0, 1, 1000).check().unwrap_err();
        assert!(e.contains("--max-concurrent-plans"), "{e}");
        let e = limits(1, 1, 10).check().unwrap_err();
        assert!(e.contains("--plan-timeout-ms"), "{e}");
        assert_eq!(limits(1, 1, 1500).retry_after_secs(), 2);
        assert_eq!(limits(1, 1, 100).retry_after_secs(), 1);
    }

    #[tokio::test]
    async fn a_full_gate_queues_then_refuses() {
        let gate = Arc::new(WorkGate::new(limits(1, 1, 200)));
        let (held, _) = gate.plan_slot(Instant::now()).await.unwrap();
        // One waits (and times out at its deadline), the next is refused at once.
        let waiter = {
            let gate = gate.clone();
            tokio::spawn(async move { gate.plan_slot(Instant::now()).await.map(|_| ()) })
        };
        while gate.queue_depth() == 0 {
            tokio::task::yield_now().await;
        }
        assert!(matches!(
            gate.plan_slot(Instant::now()).await,
            Err(Error::Overloaded { .. })
        ));
        assert!(matches!(
            waiter.await.unwrap(),
            Err(Error::DeadlineExceeded { extensions: 0, .. })
        ));
        drop(held);
        assert!(gate.plan_slot(Instant::now()).await.is_ok());
        assert_eq!(gate.queue_depth(), 0);
    }
}
