//! How long a search may run: a wall-clock deadline and a cancel flag another thread may raise
//! (the service raises it when the client that asked has gone away).
//!
//! The planner checks its budget between RRT rounds, between runs and between the steps of a
//! random rollout, so a search stops within one round of the deadline. The check costs one
//! clock read and one atomic load; the numeric core stays free of any runtime.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// Why a search stopped before it concluded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stop {
    /// The deadline passed.
    Deadline,
    /// The cancel flag was raised.
    Cancelled,
}

/// A search's budget: unlimited by default.
#[derive(Debug, Clone, Default)]
pub struct Budget {
    deadline: Option<Instant>,
    cancel: Option<Arc<AtomicBool>>,
}

impl Budget {
    /// No deadline, no cancel flag.
    pub fn unlimited() -> Self {
        Self::default()
    }

    /// Stops at `deadline`.
    pub fn until(deadline: Instant) -> Self {
        Self {
            deadline: Some(deadline),
            cancel: None,
        }
    }

    /// Also stops once `flag` is set.
    pub fn cancelled_by(mut self, flag: Arc<AtomicBool>) -> Self {
        self.cancel = Some(flag);
        self
    }

    /// The deadline, if there is one (a model call made during the search ends by it too).
    pub fn deadline(&self) -> Option<Instant> {
        self.deadline
    }

    /// Why the search must stop now, if it must.
    pub fn stop(&self) -> Option<Stop> {
        if self
            .cancel
            .as_ref()
            .is_some_and(|c| c.load(Ordering::Relaxed))
        {
            return Some(Stop::Cancelled);
        }
        if self.deadline.is_some_and(|d| Instant::now() >= d) {
            return Some(Stop::Deadline);
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_budget_stops_at_its_deadline_or_when_cancelled() {
        assert_eq!(Budget::unlimited().stop(), None);
        let later = Budget::until(Instant::now() + Duration::from_secs(3600));
        assert_eq!(later.stop(), None);
        assert_eq!(Budget::until(Instant::now()).stop(), Some(Stop::Deadline));
        let flag = Arc::new(AtomicBool::new(false));
        let b = later.cancelled_by(flag.clone());
        assert_eq!(b.stop(), None);
        flag.store(true, Ordering::Relaxed);
        assert_eq!(b.stop(), Some(Stop::Cancelled));
    }
}
