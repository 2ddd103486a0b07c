//! Calls to remote models, bounded: how many run at once (per model URL and in all), how long
//! one may take, and where it runs.
//!
//! - A call needs a permit for its URL (at most [`ModelCallLimits::max_calls_per_url`]) and one
//!   of all (at most [`ModelCallLimits::max_calls`]); it waits for them at most until its
//!   deadline, then fails with [`DynamicsError::Busy`]. Permits that come with less than a
//!   tenth of the call's time left ([`starts_too_late`]) are given back and the call fails
//!   `Busy` too: a call that short would time out before a model could answer, a `Timeout` would
//!   blame a model that was never called, and the model would receive a request nobody waits
//!   for. Waiting holds no thread: an ingest waits as an async task, a search on its own thread.
//! - A call's deadline is its experiment's `timeout_ms`, capped by the operator's
//!   [`ModelCallLimits::max_timeout`], and during a search the search's own deadline, whichever
//!   comes first; waiting for permits counts.
//! - The HTTP exchange runs on a thread of its own (`precond-model`), which holds the permits
//!   until it ends: by the deadline at the latest. So remote calls never use the blocking pool
//!   that local labelling and precondition queries share, and a hung model holds at most its
//!   own permits.
//! - The caller waits for the answer and gives up as soon as its search is cancelled or out of
//!   time (the thread then ends by its own deadline), so a planning slot never waits on a
//!   model beyond the search's budget.

use super::ModelUrlPolicy;
use crate::domain::DynamicsError;
use std::collections::HashMap;
use std::future::Future;
use std::pin::pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, Wake, Waker};
use std::time::{Duration, Instant};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// The longest `timeout_ms` an experiment may declare.
pub const MAX_TIMEOUT_MS: u64 = 600_000;

/// The operator's limits on remote model calls (options of `precond serve`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelCallLimits {
    /// Calls to remote models running at once, over all URLs: `1 ..= 1024`; default 32.
    pub max_calls: usize,
    /// Calls to one model URL running at once: `1 ..= 1024`; default 8.
    pub max_calls_per_url: usize,
    /// The longest a call may take whatever its experiment declares (waiting for a permit
    /// included): `1 ms ..=` [`MAX_TIMEOUT_MS`]; default 30 s.
    pub max_timeout: Duration,
}

impl Default for ModelCallLimits {
    fn default() -> Self {
        Self {
            max_calls: 32,
            max_calls_per_url: 8,
            max_timeout: Duration::from_secs(30),
        }
    }
}

impl ModelCallLimits {
    /// Checks the ranges; the error names the option.
    pub fn check(&self) -> Result<(), String> {
        for (name, v) in [
            ("max-model-calls", self.max_calls),
            ("max-model-calls-per-url", self.max_calls_per_url),
        ] {
            if !(1..=1024).contains(&v) {
                return Err(format!("--{name} must lie in 1 ..= 1024, got {v}"));
            }
        }
        let ms = self.max_timeout.as_millis();
        if !(1..=u128::from(MAX_TIMEOUT_MS)).contains(&ms) {
            return Err(format!(
                "--max-model-timeout-ms must lie in 1 ..= {MAX_TIMEOUT_MS}, got {ms}"
            ));
        }
        Ok(())
    }
}

/// Where remote models may live and how their calls are bounded: one per service, shared by
/// every remote model it builds.
#[derive(Debug)]
pub struct ModelCalls {
    policy: ModelUrlPolicy,
    limits: ModelCallLimits,
    all: Arc<Semaphore>,
    per_url: Mutex<HashMap<String, Arc<Semaphore>>>,
}

impl Default for ModelCalls {
    /// No URL allowed, the default limits.
    fn default() -> Self {
        Self::new(ModelUrlPolicy::default(), ModelCallLimits::default())
    }
}

/// The permits a running call holds.
#[derive(Debug)]
pub(crate) struct Permits {
    _url: OwnedSemaphorePermit,
    _all: OwnedSemaphorePermit,
}

impl ModelCalls {
    /// Calls allowed under `policy`, bounded by `limits` (assumed checked).
    pub fn new(policy: ModelUrlPolicy, limits: ModelCallLimits) -> Self {
        Self {
            all: Arc::new(Semaphore::new(limits.max_calls)),
            policy,
            limits,
            per_url: Mutex::new(HashMap::new()),
        }
    }

    /// The URL policy.
    pub fn policy(&self) -> &ModelUrlPolicy {
        &self.policy
    }

    /// The limits.
    pub fn limits(&self) -> &ModelCallLimits {
        &self.limits
    }

    /// Calls running now.
    pub fn running(&self) -> usize {
        self.limits.max_calls - self.all.available_permits()
    }

    /// Waits for a permit of `url` and one of all (in that order, so that a URL with a full
    /// queue does not hold permits of all while it waits).
    pub(crate) async fn permits(&self, url: &str) -> Option<Permits> {
        let for_url = {
            let mut per_url = self.per_url.lock().unwrap_or_else(|p| p.into_inner());
            per_url
                .entry(url.to_string())
                .or_insert_with(|| Arc::new(Semaphore::new(self.limits.max_calls_per_url)))
                .clone()
        };
        let url_permit = for_url.acquire_owned().await.ok()?;
        let all = self.all.clone().acquire_owned().await.ok()?;
        Some(Permits {
            _url: url_permit,
            _all: all,
        })
    }
}

/// Wakes a thread parked in [`block_until`].
struct ThreadWaker(std::thread::Thread);

impl Wake for ThreadWaker {
    fn wake(self: Arc<Self>) {
        self.0.unpark();
    }

    fn wake_by_ref(self: &Arc<Self>) {
        self.0.unpark();
    }
}

/// Runs `future` on this thread (one that is not an async worker: a search's) until it is
/// ready or `give_up` says so (checked at least every 10 ms and at `deadline`); `None` when
/// given up. Needs no runtime: the futures it runs (semaphore permits, a oneshot) are woken by
/// whoever completes them.
pub(crate) fn block_until<F: Future>(
    future: F,
    deadline: Instant,
    mut give_up: impl FnMut() -> bool,
) -> Option<F::Output> {
    let waker = Waker::from(Arc::new(ThreadWaker(std::thread::current())));
    let mut cx = Context::from_waker(&waker);
    let mut future = pin!(future);
    loop {
        if let Poll::Ready(v) = future.as_mut().poll(&mut cx) {
            return Some(v);
        }
        let now = Instant::now();
        if now >= deadline || give_up() {
            return None;
        }
        std::thread::park_timeout((deadline - now).min(Duration::from_millis(10)));
    }
}

/// Whether a call that began waiting for its permits at `begun` and got them at `now` is too
/// late to start: less than a tenth of its whole window (`begun` to `deadline`), and less than
/// 1 ms, is left.
pub(crate) fn starts_too_late(begun: Instant, now: Instant, deadline: Instant) -> bool {
    let window = deadline.saturating_duration_since(begun);
    deadline.saturating_duration_since(now) < (window / 10).max(Duration::from_millis(1))
}

/// The answer of a call that could not start within its deadline.
pub(crate) fn busy(model: &str, limits: &ModelCallLimits) -> DynamicsError {
    DynamicsError::Busy {
        model: model.to_string(),
        reason: format!(
            "no call could start in time (with a tenth of its time left): {} calls to this \
             model (or {} to all models) are already running (--max-model-calls-per-url, \
             --max-model-calls)",
            limits.max_calls_per_url, limits.max_calls
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_call_needs_a_tenth_of_its_window_left_to_start() {
        let begun = Instant::now();
        let deadline = begun + Duration::from_millis(800);
        let at = |ms| begun + Duration::from_millis(ms);
        assert!(!starts_too_late(begun, at(0), deadline));
        assert!(
            !starts_too_late(begun, at(720), deadline),
            "80 ms of 800 left"
        );
        assert!(
            starts_too_late(begun, at(721), deadline),
            "79 ms of 800 left"
        );
        assert!(
            starts_too_late(begun, at(900), deadline),
            "past the deadline"
        );
        // A window under 10 ms still starts with at least 1 ms left.
        let short = begun + Duration::from_millis(5);
        assert!(!starts_too_late(begun, at(3), short));
        assert!(starts_too_late(begun, at(5), short));
    }

    #[test]
    fn limits_are_checked_and_name_the_option() {
        assert!(ModelCallLimits::default().check().is_ok());
        let e = ModelCallLimits {
            max_calls: 0,
            ..ModelCallLimits::default()
        }
        .check()
        .unwrap_err();
        assert!(e.contains("--max-model-calls"), "{e}");
        let e = ModelCallLimits {
            max_timeout: Duration::from_secs(601),
            ..ModelCallLimits::default()
        }
        .check()
        .unwrap_err();
        assert!(e.contains("--max-model-timeout-ms"), "{e}");
    }

    #[test]
    fn permits_bound_calls_per_url_and_in_all_without_a_runtime() {
        let calls = ModelCalls::new(
            ModelUrlPolicy::default(),
            ModelCallLimits {
                max_calls: 3,
                max_calls_per_url: 2,
                ..ModelCallLimits::default()
            },
        );
        let soon = || Instant::now() + Duration::from_millis(50);
        let a1 = block_until(calls.permits("a"), soon(), || false).flatten();
        let a2 = block_until(calls.permits("a"), soon(), || false).flatten();
        assert!(a1.is_some() && a2.is_some());
        let started = Instant::now();
        assert!(
            block_until(calls.permits("a"), soon(), || false).is_none(),
            "a third call to one URL waits, until its deadline"
        );
        assert!(started.elapsed() >= Duration::from_millis(45));
        let b1 = block_until(calls.permits("b"), soon(), || false).flatten();
        assert!(b1.is_some(), "another URL still has room");
        assert_eq!(calls.running(), 3);
        assert!(
            block_until(calls.permits("c"), soon(), || false).is_none(),
            "all calls are taken"
        );
        // Giving up is prompt.
        let started = Instant::now();
        let far = Instant::now() + Duration::from_secs(10);
        assert!(block_until(calls.permits("c"), far, || true).is_none());
        assert!(started.elapsed() < Duration::from_secs(1));
        drop(a1);
        assert!(block_until(calls.permits("c"), soon(), || false).is_some());
    }
}
