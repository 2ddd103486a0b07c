//! Bounded work: the operator's limits and the gate every planning search and every fit
//! passes through.
//!
//! - At most [`Limits::max_concurrent_plans`] searches and fits run at once (one per core by
//!   default; with one slot, a search beside a fit — see below), so the async workers that answer health checks and cheap reads always find a
//!   core.
//! - A request waits for a slot at most until its deadline ([`Limits::plan_timeout`], counted
//!   from its arrival); the search itself stops at the same deadline. Either way the client
//!   gets `503 deadline_exceeded` with `Retry-After` (or `no_plan` if the search concluded).
//! - About [`Limits::max_queued_plans`] requests wait at once; beyond that a request is
//!   refused at once with `429 overloaded` and `Retry-After`.
//! - Experiments take turns: free slots go round robin to the experiments with requests
//!   waiting, one experiment runs at most [`Limits::max_plans_per_experiment`] searches at once
//!   (half the slots by default), and holds at most half the queue; an experiment with nothing
//!   waiting always gets a place in line. So one client flooding one experiment cannot take
//!   every slot, nor leave others only `429`s.
//! - Rebuilding an older model version (maps, diagnostics) takes a slot like a search.
//! - A search whose client went away stops at its next round: the request's future holds a
//!   guard that raises the search's cancel flag when it is dropped.
//! - Fits (background or forced) take a slot too, taking turns with the experiments (all fits
//!   as one), but have no deadline: a fit is one optimisation that cannot stop halfway, and its
//!   worst case is bounded by the training-set size and `restarts`. So that long fits cannot
//!   starve searches, fits hold at most all slots but one ([`fit_cap`]), and running fits
//!   never keep a search from its last slot: on a server with one slot a search runs beside
//!   a fit (both on threads at nice +10), so fits queued without pause cannot leave every
//!   search to its deadline. A fit itself starts only within the slots.
//! - Evaluations of a model on many points — a precondition map, diagnostics, a precondition
//!   query of more than a few hundred points — take an evaluation slot
//!   ([`WorkGate::evaluation_slot`]): as many as planning slots, but slots of their own, so
//!   that a map on the dashboard does not wait for the searches. Each evaluation's memory is
//!   bounded by its points and its model (predictions go in chunks), plus the matrix product's
//!   workspace of the thread it runs on
//!   ([`PRODUCT_WORKSPACE_BYTES`](crate::gp::cost::PRODUCT_WORKSPACE_BYTES)); the slots bound
//!   how many run at once, however many clients ask. Waiting is bounded as for searches (the
//!   same deadline, `503`; the same queue length, `429`).

use super::{Error, Result};
use crate::budget::Budget;
use crate::limits::MAX_TRANSITIONS;
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Shortest planning deadline an operator may set.
pub const MIN_PLAN_TIMEOUT: Duration = Duration::from_millis(100);
/// Longest planning deadline an operator may set (10 minutes).
pub const MAX_PLAN_TIMEOUT: Duration = Duration::from_secs(600);

/// The operator's limits (command-line options of `precond serve`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Limits {
    /// Searches and fits running at once: `1 ..= 256`; default the number of cores. With one
    /// slot, a search may run beside a fit (fits never take a search's last slot).
    pub max_concurrent_plans: usize,
    /// Searches (and model rebuilds) of one experiment running at once: `1 ..= 256` (at most
    /// `max_concurrent_plans` take effect); default half the slots, at least 1.
    pub max_plans_per_experiment: usize,
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
    /// Seconds one MDE fit (model selection included) may take by its estimate
    /// ([`crate::gp::FitCost::seconds`], at the cost model's assumed rate): a fit beyond it is
    /// not attempted but recorded as refused, and with `mde.estimator: auto` the sparse GP
    /// takes over first. So one experiment's fit cannot hold a fit slot for hours while every
    /// other experiment's refits wait. `10 ..= 86 400`; default 900.
    pub max_fit_seconds: u64,
    /// Large transfers at once — answers (a model export, a CSV of every transition) being
    /// written, imports being received: `1 ..= 256`; default 4. An answer holds at most a few
    /// chunks beyond its source (see `http::stream`); one beyond waits [`EXPORT_WAIT`] for a
    /// slot, then gets `429`.
    pub max_concurrent_exports: usize,
}

/// How long a large answer waits for an export slot before `429 overloaded`.
pub const EXPORT_WAIT: Duration = Duration::from_secs(2);

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
            max_plans_per_experiment: Self::default_per_experiment(cores),
            max_queued_plans: 8 * cores,
            plan_timeout: Duration::from_secs(30),
            max_experiments: 1000,
            max_transitions: MAX_TRANSITIONS,
            max_fit_memory: default_fit_memory(),
            max_concurrent_exports: 4,
            max_fit_seconds: 900,
        }
    }
}

impl Limits {
    /// The default of [`Limits::max_plans_per_experiment`] for `slots` slots: half, at least 1.
    pub fn default_per_experiment(slots: usize) -> usize {
        (slots / 2).max(1)
    }

    /// Searches one experiment may run at once, in effect.
    pub fn per_experiment(&self) -> usize {
        self.max_plans_per_experiment
            .clamp(1, self.max_concurrent_plans.max(1))
    }

    /// Places in the queue one experiment may hold: half the queue, at least 1.
    pub fn queue_share(&self) -> usize {
        (self.max_queued_plans / 2).max(1)
    }

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
        range(
            "max-plans-per-experiment",
            self.max_plans_per_experiment,
            1,
            256,
        )?;
        range("max-queued-plans", self.max_queued_plans, 0, 10_000)?;
        range("max-experiments", self.max_experiments, 1, 1_000_000)?;
        range("max-transitions", self.max_transitions, 1, MAX_TRANSITIONS)?;
        range(
            "max-concurrent-exports",
            self.max_concurrent_exports,
            1,
            256,
        )?;
        if !(10..=86_400).contains(&self.max_fit_seconds) {
            return Err(format!(
                "--max-fit-seconds must lie in 10 ..= 86400, got {}",
                self.max_fit_seconds
            ));
        }
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

/// Whose turn a slot is: an experiment's searches (and rebuilds), or the fits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Key {
    /// Searches and model rebuilds of one experiment: at most
    /// [`Limits::max_plans_per_experiment`] at once.
    Experiment(i64),
    /// Fits (background or forced), of any experiment: no cap of their own.
    Fits,
}

/// One request waiting for a slot.
#[derive(Debug)]
struct Waiter {
    id: u64,
    grant: tokio::sync::oneshot::Sender<Slot>,
}

/// What the gate knows, under one lock.
#[derive(Debug, Default)]
struct State {
    running: usize,
    running_by_key: HashMap<Key, usize>,
    waiting: usize,
    queues: HashMap<Key, VecDeque<Waiter>>,
    /// Keys with waiters, in the order their turn comes (round robin).
    turn: VecDeque<Key>,
    next_id: u64,
}

/// The gate: the slots, the queue and the limits.
#[derive(Debug)]
pub struct WorkGate {
    limits: Limits,
    state: Arc<Mutex<State>>,
    /// The evaluation slots ([`WorkGate::evaluation_slot`]): `max_concurrent_plans` permits.
    evaluations: Arc<tokio::sync::Semaphore>,
    /// Evaluations waiting for a slot now.
    evaluations_waiting: AtomicUsize,
    /// The export slots ([`WorkGate::export_slot`]): `max_concurrent_exports` permits.
    exports: Arc<tokio::sync::Semaphore>,
}

/// An export slot: held while a large answer is written (move it into the writer, so that it
/// is held until the answer ends or its client leaves).
#[derive(Debug)]
pub struct ExportSlot {
    _permit: tokio::sync::OwnedSemaphorePermit,
}

/// An evaluation slot: held while a map, diagnostics or a large precondition query is
/// evaluated; dropping it lets the next evaluation in.
#[derive(Debug)]
pub struct EvaluationSlot {
    _permit: tokio::sync::OwnedSemaphorePermit,
}

/// Counts a waiting evaluation out when it stops waiting (slot, deadline or dropped request).
struct StopWaiting<'a>(&'a AtomicUsize);

impl Drop for StopWaiting<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

/// A slot: held while a search, rebuild or fit runs; releasing it hands it to the next in
/// turn and updates the gauges.
#[derive(Debug)]
pub struct Slot {
    key: Key,
    state: Arc<Mutex<State>>,
    limits: Arc<(usize, usize)>,
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut state = lock(&self.state);
        state.running -= 1;
        if let Some(n) = state.running_by_key.get_mut(&self.key) {
            *n -= 1;
            if *n == 0 {
                state.running_by_key.remove(&self.key);
            }
        }
        let refused = dispatch(&mut state, &self.state, &self.limits);
        drop(state);
        // Slots whose waiter had gone: dropping them dispatches again, outside the lock.
        drop(refused);
    }
}

fn lock(state: &Mutex<State>) -> std::sync::MutexGuard<'_, State> {
    state.lock().unwrap_or_else(|p| p.into_inner())
}

/// Whether `key` may start one more. Fits: while fewer than `slots` run in all and the fits
/// hold fewer than [`fit_cap`]. An experiment: below its cap, and while the searches hold
/// fewer than the slots the fits leave — at least one, so that a fit never takes the last
/// slot a search could use (with one slot, a search runs beside a fit).
fn may_start(state: &State, key: Key, slots: usize, per_experiment: usize) -> bool {
    let running = state.running_by_key.get(&key).copied().unwrap_or(0);
    let fits = state.running_by_key.get(&Key::Fits).copied().unwrap_or(0);
    match key {
        Key::Fits => state.running < slots && running < fit_cap(slots),
        Key::Experiment(_) => {
            running < per_experiment && state.running - fits < slots.saturating_sub(fits).max(1)
        }
    }
}

/// Fits running at once: all slots but one (at least one), so that however many large fits
/// queue — they have no deadline — a search always finds a slot within its own. With the
/// default two slots on two cores, fits run one at a time.
pub fn fit_cap(slots: usize) -> usize {
    slots.saturating_sub(1).max(1)
}

/// Hands free slots to waiters, keys in round-robin turn, skipping keys at their cap. Returns
/// the slots whose waiter had gone, to be dropped once the lock is released.
fn dispatch(
    state: &mut State,
    shared: &Arc<Mutex<State>>,
    limits: &Arc<(usize, usize)>,
) -> Vec<Slot> {
    let (slots, per_experiment) = **limits;
    let mut refused = Vec::new();
    let mut skipped = 0;
    while skipped < state.turn.len() {
        let Some(key) = state.turn.pop_front() else {
            break;
        };
        if !may_start(state, key, slots, per_experiment) {
            state.turn.push_back(key);
            skipped += 1;
            continue;
        }
        skipped = 0;
        let waiter = state.queues.get_mut(&key).and_then(VecDeque::pop_front);
        if state.queues.get(&key).is_some_and(|q| !q.is_empty()) {
            state.turn.push_back(key);
        } else {
            state.queues.remove(&key);
        }
        let Some(waiter) = waiter else { continue };
        state.waiting -= 1;
        state.running += 1;
        *state.running_by_key.entry(key).or_insert(0) += 1;
        let slot = Slot {
            key,
            state: shared.clone(),
            limits: limits.clone(),
        };
        if let Err(slot) = waiter.grant.send(slot) {
            refused.push(slot);
        }
    }
    gauges(state);
    refused
}

fn gauges(state: &State) {
    metrics::gauge!("precond_planning_running").set(state.running as f64);
    metrics::gauge!("precond_planning_queue_depth").set(state.waiting as f64);
}

/// Takes a waiter out of the queue when its request stops waiting (deadline or dropped).
struct LeaveQueue<'a> {
    state: &'a Arc<Mutex<State>>,
    key: Key,
    id: u64,
}

impl Drop for LeaveQueue<'_> {
    fn drop(&mut self) {
        let mut state = lock(self.state);
        let Some(queue) = state.queues.get_mut(&self.key) else {
            return;
        };
        let before = queue.len();
        queue.retain(|w| w.id != self.id);
        let left = before - queue.len();
        if queue.is_empty() {
            state.queues.remove(&self.key);
            state.turn.retain(|k| *k != self.key);
        }
        state.waiting -= left;
        gauges(&state);
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

/// How a request for a slot ended before it got one.
enum Refusal {
    /// The queue (or the key's share of it) is full.
    Full,
}

impl WorkGate {
    /// A gate with these limits (assumed checked).
    pub fn new(limits: Limits) -> Self {
        Self {
            evaluations: Arc::new(tokio::sync::Semaphore::new(limits.max_concurrent_plans)),
            evaluations_waiting: AtomicUsize::new(0),
            exports: Arc::new(tokio::sync::Semaphore::new(limits.max_concurrent_exports)),
            limits,
            state: Arc::new(Mutex::new(State::default())),
        }
    }

    /// The limits.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Requests waiting for a slot now.
    pub fn queue_depth(&self) -> usize {
        lock(&self.state).waiting
    }

    /// Searches, rebuilds and fits running now.
    pub fn running(&self) -> usize {
        lock(&self.state).running
    }

    fn shared_limits(&self) -> Arc<(usize, usize)> {
        Arc::new((
            self.limits.max_concurrent_plans,
            self.limits.per_experiment(),
        ))
    }

    /// A slot at once, or a place in `key`'s queue (with the receiver of its slot and its
    /// waiter id), or a refusal when `bounded` and the queue has no room for `key`.
    #[allow(clippy::type_complexity)]
    fn enter(
        &self,
        key: Key,
        bounded: bool,
    ) -> Result<Result<Slot, (tokio::sync::oneshot::Receiver<Slot>, u64)>, Refusal> {
        let limits = self.shared_limits();
        let mut state = lock(&self.state);
        let queued_for_key = state.queues.get(&key).map_or(0, VecDeque::len);
        if queued_for_key == 0
            && may_start(
                &state,
                key,
                self.limits.max_concurrent_plans,
                self.limits.per_experiment(),
            )
        {
            state.running += 1;
            *state.running_by_key.entry(key).or_insert(0) += 1;
            gauges(&state);
            return Ok(Ok(Slot {
                key,
                state: self.state.clone(),
                limits,
            }));
        }
        if bounded {
            // Every experiment keeps a place in line: one with nobody waiting may queue even
            // when the others filled the queue; none may hold more than its share of it.
            let share = self.limits.queue_share();
            let full = self.limits.max_queued_plans == 0
                || queued_for_key >= share
                || (state.waiting >= self.limits.max_queued_plans && queued_for_key > 0);
            if full {
                return Err(Refusal::Full);
            }
        }
        let (tx, rx) = tokio::sync::oneshot::channel();
        state.next_id += 1;
        let id = state.next_id;
        state
            .queues
            .entry(key)
            .or_default()
            .push_back(Waiter { id, grant: tx });
        if queued_for_key == 0 {
            state.turn.push_back(key);
        }
        state.waiting += 1;
        gauges(&state);
        Ok(Err((rx, id)))
    }

    /// A slot for a planning request on experiment `experiment` that arrived at `arrived`:
    /// `429` at once when the queue has no room for it, `503` when the deadline passes while
    /// waiting. Experiments take turns for free slots, and each runs at most
    /// [`Limits::max_plans_per_experiment`] at once.
    pub async fn plan_slot(&self, experiment: i64, arrived: Instant) -> Result<(Slot, Instant)> {
        let deadline = arrived + self.limits.plan_timeout;
        let key = Key::Experiment(experiment);
        let (rx, id) = match self.enter(key, true) {
            Ok(Ok(slot)) => return Ok((slot, deadline)),
            Ok(Err(waiting)) => waiting,
            Err(Refusal::Full) => {
                return Err(Error::Overloaded {
                    retry_after_secs: self.limits.retry_after_secs(),
                });
            }
        };
        let _leave = LeaveQueue {
            state: &self.state,
            key,
            id,
        };
        match tokio::time::timeout_at(tokio::time::Instant::from_std(deadline), rx).await {
            Ok(Ok(slot)) => Ok((slot, deadline)),
            Ok(Err(_closed)) => Err(Error::Internal(anyhow::anyhow!("the work gate closed"))),
            Err(_elapsed) => Err(self.deadline_exceeded(0)),
        }
    }

    /// A slot for a fit: waits as long as it takes, taking turns with the experiments' searches.
    pub async fn fit_slot(&self) -> Result<Slot> {
        let (rx, id) = match self.enter(Key::Fits, false) {
            Ok(Ok(slot)) => return Ok(slot),
            Ok(Err(waiting)) => waiting,
            Err(Refusal::Full) => unreachable!("an unbounded wait is never refused"),
        };
        let _leave = LeaveQueue {
            state: &self.state,
            key: Key::Fits,
            id,
        };
        rx.await
            .map_err(|_| Error::Internal(anyhow::anyhow!("the work gate closed")))
    }

    /// A slot to evaluate a model on many points (a precondition map, diagnostics, a large
    /// precondition query) for a request that arrived at `arrived`: at once when one of the
    /// `max_concurrent_plans` evaluation slots is free; else it waits in line (first come, first
    /// served) until the deadline `plan_timeout` after `arrived` (`503 deadline_exceeded`), or
    /// is refused at once with `429 overloaded` when `max_queued_plans` evaluations already
    /// wait. Move the slot into the task that evaluates, so that it is held until the
    /// evaluation ends even when the client goes away.
    pub async fn evaluation_slot(&self, arrived: Instant) -> Result<EvaluationSlot> {
        if let Ok(permit) = self.evaluations.clone().try_acquire_owned() {
            return Ok(EvaluationSlot { _permit: permit });
        }
        if self.evaluations_waiting.fetch_add(1, Ordering::Relaxed) >= self.limits.max_queued_plans
        {
            self.evaluations_waiting.fetch_sub(1, Ordering::Relaxed);
            return Err(Error::Overloaded {
                retry_after_secs: self.limits.retry_after_secs(),
            });
        }
        let _stop_waiting = StopWaiting(&self.evaluations_waiting);
        let deadline = tokio::time::Instant::from_std(arrived + self.limits.plan_timeout);
        match tokio::time::timeout_at(deadline, self.evaluations.clone().acquire_owned()).await {
            Ok(Ok(permit)) => Ok(EvaluationSlot { _permit: permit }),
            Ok(Err(_closed)) => Err(Error::Internal(anyhow::anyhow!(
                "the evaluation slots closed"
            ))),
            Err(_elapsed) => Err(self.deadline_exceeded(0)),
        }
    }

    /// A slot to write a large answer in, waiting at most [`EXPORT_WAIT`] for one; `429
    /// overloaded` when `max_concurrent_exports` answers are being written all that time.
    pub async fn export_slot(&self) -> Result<ExportSlot> {
        match tokio::time::timeout(EXPORT_WAIT, self.exports.clone().acquire_owned()).await {
            Ok(Ok(permit)) => Ok(ExportSlot { _permit: permit }),
            Ok(Err(_closed)) => Err(Error::Internal(anyhow::anyhow!("the export slots closed"))),
            Err(_elapsed) => Err(Error::ExportsBusy {
                limit: self.limits.max_concurrent_exports,
                retry_after_secs: 5,
            }),
        }
    }

    /// Large answers being written now.
    pub fn exports_running(&self) -> usize {
        self.limits.max_concurrent_exports - self.exports.available_permits()
    }

    /// Evaluations running now.
    pub fn evaluations_running(&self) -> usize {
        self.limits.max_concurrent_plans - self.evaluations.available_permits()
    }

    /// Evaluations waiting for a slot now.
    pub fn evaluations_waiting(&self) -> usize {
        self.evaluations_waiting.load(Ordering::Relaxed)
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
            max_plans_per_experiment: slots,
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
        let (held, _) = gate.plan_slot(1, Instant::now()).await.unwrap();
        // One waits (and times out at its deadline), the next is refused at once.
        let waiter = {
            let gate = gate.clone();
            tokio::spawn(async move { gate.plan_slot(1, Instant::now()).await.map(|_| ()) })
        };
        while gate.queue_depth() == 0 {
            tokio::task::yield_now().await;
        }
        assert!(matches!(
            gate.plan_slot(1, Instant::now()).await,
            Err(Error::Overloaded { .. })
        ));
        assert!(matches!(
            waiter.await.unwrap(),
            Err(Error::DeadlineExceeded { extensions: 0, .. })
        ));
        drop(held);
        assert!(gate.plan_slot(1, Instant::now()).await.is_ok());
        assert_eq!(gate.queue_depth(), 0);
    }

    #[tokio::test]
    async fn evaluations_have_slots_of_their_own_a_queue_and_a_deadline() {
        let gate = Arc::new(WorkGate::new(limits(2, 1, 200)));
        // Searches holding every planning slot do not hold up evaluations ...
        let searches = [
            gate.plan_slot(1, Instant::now()).await.unwrap(),
            gate.plan_slot(2, Instant::now()).await.unwrap(),
        ];
        let a = gate.evaluation_slot(Instant::now()).await.unwrap();
        let b = gate.evaluation_slot(Instant::now()).await.unwrap();
        assert_eq!(gate.evaluations_running(), 2);
        // ... but evaluations are bounded by their own slots: the next waits, the one after is
        // refused at once, and the waiting one gets `503` at its deadline.
        let waiter = {
            let gate = gate.clone();
            tokio::spawn(async move { gate.evaluation_slot(Instant::now()).await.map(drop) })
        };
        while gate.evaluations_waiting() == 0 {
            tokio::task::yield_now().await;
        }
        assert!(matches!(
            gate.evaluation_slot(Instant::now()).await,
            Err(Error::Overloaded { .. })
        ));
        assert!(matches!(
            waiter.await.unwrap(),
            Err(Error::DeadlineExceeded { extensions: 0, .. })
        ));
        assert_eq!(gate.evaluations_waiting(), 0);
        // A freed slot goes to the next in line.
        let waiter = {
            let gate = gate.clone();
            tokio::spawn(async move { gate.evaluation_slot(Instant::now()).await.is_ok() })
        };
        while gate.evaluations_waiting() == 0 {
            tokio::task::yield_now().await;
        }
        drop(a);
        assert!(waiter.await.unwrap());
        drop((b, searches));
        assert_eq!(
            (gate.evaluations_running(), gate.evaluations_waiting()),
            (0, 0)
        );
        assert_eq!(gate.running(), 0);
    }

    /// A request for experiment `e` as a task, answering whether it got a slot (held for
    /// `hold_ms`).
    fn ask(
        gate: &Arc<WorkGate>,
        e: i64,
        hold_ms: u64,
        order: &Arc<Mutex<Vec<i64>>>,
    ) -> tokio::task::JoinHandle<bool> {
        let (gate, order) = (gate.clone(), order.clone());
        tokio::spawn(async move {
            match gate.plan_slot(e, Instant::now()).await {
                Ok((slot, _)) => {
                    order.lock().unwrap().push(e);
                    tokio::time::sleep(Duration::from_millis(hold_ms)).await;
                    drop(slot);
                    true
                }
                Err(_) => false,
            }
        })
    }

    async fn until_waiting(gate: &WorkGate, n: usize) {
        while gate.queue_depth() < n {
            tokio::task::yield_now().await;
        }
    }

    #[tokio::test]
    async fn one_experiment_cannot_take_every_slot() {
        let gate = Arc::new(WorkGate::new(Limits {
            max_plans_per_experiment: 1,
            ..limits(2, 8, 5000)
        }));
        let (_held, _) = gate.plan_slot(1, Instant::now()).await.unwrap();
        // Experiment 1's next request waits although a slot is free ...
        let order = Arc::new(Mutex::new(Vec::new()));
        let second = ask(&gate, 1, 0, &order);
        until_waiting(&gate, 1).await;
        assert_eq!(gate.running(), 1);
        // ... which experiment 2 gets at once.
        let (other, _) = gate.plan_slot(2, Instant::now()).await.unwrap();
        assert_eq!((gate.running(), gate.queue_depth()), (2, 1));
        drop(other);
        drop(_held);
        assert!(second.await.unwrap());
        assert_eq!((gate.running(), gate.queue_depth()), (0, 0));
    }

    #[tokio::test]
    async fn experiments_take_turns_for_free_slots() {
        let gate = Arc::new(WorkGate::new(limits(1, 16, 5000)));
        let (held, _) = gate.plan_slot(1, Instant::now()).await.unwrap();
        let order = Arc::new(Mutex::new(Vec::new()));
        let mut tasks = Vec::new();
        for (k, e) in [1, 1, 1, 2, 3].into_iter().enumerate() {
            tasks.push(ask(&gate, e, 5, &order));
            until_waiting(&gate, k + 1).await;
        }
        drop(held);
        for t in tasks {
            assert!(t.await.unwrap());
        }
        // Round robin: 1, 2, 3, then experiment 1's remaining requests in their order.
        assert_eq!(*order.lock().unwrap(), vec![1, 2, 3, 1, 1]);
    }

    #[tokio::test]
    async fn one_experiment_holds_at_most_half_the_queue_and_others_always_get_a_place() {
        let gate = Arc::new(WorkGate::new(limits(1, 4, 5000)));
        let (held, _) = gate.plan_slot(9, Instant::now()).await.unwrap();
        let order = Arc::new(Mutex::new(Vec::new()));
        let a = [ask(&gate, 1, 0, &order), ask(&gate, 1, 0, &order)];
        until_waiting(&gate, 2).await;
        assert!(
            matches!(
                gate.plan_slot(1, Instant::now()).await,
                Err(Error::Overloaded { .. })
            ),
            "experiment 1 holds its share (2 of 4)"
        );
        let b = [ask(&gate, 2, 0, &order), ask(&gate, 3, 0, &order)];
        until_waiting(&gate, 4).await;
        // The queue is full, but experiment 4 has nobody waiting: it gets a place.
        let c = ask(&gate, 4, 0, &order);
        until_waiting(&gate, 5).await;
        assert!(matches!(
            gate.plan_slot(2, Instant::now()).await,
            Err(Error::Overloaded { .. })
        ));
        drop(held);
        for t in a.into_iter().chain(b).chain([c]) {
            assert!(t.await.unwrap());
        }
        assert_eq!(*order.lock().unwrap(), vec![1, 2, 3, 4, 1]);
    }

    #[tokio::test]
    async fn fits_leave_a_slot_to_the_searches() {
        assert_eq!((fit_cap(1), fit_cap(2), fit_cap(8)), (1, 1, 7));
        let gate = Arc::new(WorkGate::new(limits(2, 8, 5000)));
        let fit = gate.fit_slot().await.unwrap();
        // A second fit waits although a slot is free ...
        let second_fit = {
            let gate = gate.clone();
            tokio::spawn(async move { gate.fit_slot().await.map(drop).is_ok() })
        };
        until_waiting(&gate, 1).await;
        assert_eq!(gate.running(), 1);
        // ... which a search gets at once.
        let (search, _) = gate.plan_slot(1, Instant::now()).await.unwrap();
        assert_eq!((gate.running(), gate.queue_depth()), (2, 1));
        drop(search);
        assert_eq!(
            gate.running(),
            1,
            "the waiting fit does not take the searches' slot"
        );
        drop(fit);
        assert!(second_fit.await.unwrap());
        assert_eq!((gate.running(), gate.queue_depth()), (0, 0));
    }

    #[tokio::test]
    async fn with_one_slot_a_search_runs_beside_a_fit_and_fits_wait_for_the_searches() {
        let gate = Arc::new(WorkGate::new(limits(1, 8, 5000)));
        let fit = gate.fit_slot().await.unwrap();
        // The fit holds the one slot; a search still starts at once ...
        let (search, _) = gate.plan_slot(1, Instant::now()).await.unwrap();
        assert_eq!((gate.running(), gate.queue_depth()), (2, 0));
        // ... but only one: a second search (another experiment) waits for it.
        let order = Arc::new(Mutex::new(Vec::new()));
        let second = ask(&gate, 2, 0, &order);
        until_waiting(&gate, 1).await;
        assert_eq!(gate.running(), 2);
        // A fit waits while a search holds the slot, even when no fit runs.
        drop(fit);
        let next_fit = {
            let gate = gate.clone();
            tokio::spawn(async move { gate.fit_slot().await.map(drop).is_ok() })
        };
        until_waiting(&gate, 2).await;
        assert_eq!(
            gate.running(),
            1,
            "the search runs; the second search and the fit wait"
        );
        drop(search);
        assert!(second.await.unwrap());
        assert!(next_fit.await.unwrap());
        assert_eq!((gate.running(), gate.queue_depth()), (0, 0));
    }

    #[tokio::test]
    async fn a_request_that_stops_waiting_leaves_the_queue() {
        let gate = Arc::new(WorkGate::new(limits(1, 4, 5000)));
        let (held, _) = gate.plan_slot(1, Instant::now()).await.unwrap();
        let order = Arc::new(Mutex::new(Vec::new()));
        let gone = ask(&gate, 2, 0, &order);
        let stays = ask(&gate, 3, 0, &order);
        until_waiting(&gate, 2).await;
        gone.abort();
        assert!(gone.await.is_err());
        assert_eq!(gate.queue_depth(), 1);
        drop(held);
        assert!(stays.await.unwrap());
        assert_eq!(*order.lock().unwrap(), vec![3]);
        // Fits take turns too and are never refused.
        let (held, _) = gate.plan_slot(1, Instant::now()).await.unwrap();
        let fit = {
            let gate = gate.clone();
            tokio::spawn(async move { gate.fit_slot().await.map(drop).is_ok() })
        };
        until_waiting(&gate, 1).await;
        drop(held);
        assert!(fit.await.unwrap());
        assert_eq!((gate.running(), gate.queue_depth()), (0, 0));
    }
}
