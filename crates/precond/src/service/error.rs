//! What the service layer can answer instead of a result, by what the caller should do about
//! it. Knows nothing of HTTP: the HTTP layer maps each variant to a status and a code.

use crate::api::CandidateView;
use crate::domain::{DomainError, DynamicsError};
use crate::planning::PlanningError;
use crate::settings::InvalidSetting;

/// Why a service operation did not succeed.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A field of the request has the wrong dimension, range or value.
    #[error("{field}: {reason}")]
    Validation {
        /// Path of the offending field, e.g. `transitions[3].s`.
        field: String,
        /// Why it is wrong.
        reason: String,
    },
    /// The experiment, trajectory or proposal does not exist.
    #[error("{0}")]
    NotFound(String),
    /// The request conflicts with what is stored (an idempotency key reused with another body,
    /// a proposal executed twice, a lease held for another problem, nothing to fit).
    #[error("{0}")]
    Conflict(String),
    /// The idempotency key was used before with another request (`field` the first that
    /// differs, empty when the bodies cannot be compared); nothing was stored.
    #[error(
        "this Idempotency-Key was already used with a different request ({difference}); nothing was stored"
    )]
    KeyReused {
        /// The first differing field, e.g. `transitions[3].a[1]` or `source.dataset`.
        field: String,
        /// Both values, as a sentence.
        difference: String,
    },
    /// The client holds an open proposal for another problem: it must execute or abandon that
    /// one first.
    #[error(
        "client {client_id:?} holds open proposal {proposal_id} for start {start:?} and goal \
         {goal:?}; execute or abandon it before asking for another problem"
    )]
    LeaseHeld {
        /// The open proposal.
        proposal_id: i64,
        /// The client holding it.
        client_id: String,
        /// Its start state.
        start: Vec<f64>,
        /// Its goal.
        goal: Vec<f64>,
    },
    /// The planner found no goal-reaching trajectory inside the precondition (or none of the
    /// client's candidates is inside and reaches the goal).
    #[error("no goal-reaching trajectory inside the precondition ({extensions} extensions, {} candidates judged)", candidates.len())]
    NoPlan {
        /// Extensions spent by the search.
        extensions: usize,
        /// The client's candidates with their verdicts, when it posted some.
        candidates: Vec<CandidateView>,
    },
    /// Too many planning requests are already waiting: retry after `retry_after_secs`.
    #[error(
        "the planner is saturated: too many requests are waiting; retry in {retry_after_secs} s"
    )]
    Overloaded {
        /// Seconds to wait before retrying.
        retry_after_secs: u64,
    },
    /// Every export slot has been busy for a while: retry after `retry_after_secs`.
    #[error(
        "{limit} large transfers (model exports, CSV exports, imports) are under way, the server's limit; retry in {retry_after_secs} s"
    )]
    ExportsBusy {
        /// `max_concurrent_exports`.
        limit: usize,
        /// Seconds to wait before retrying.
        retry_after_secs: u64,
    },
    /// The deadline passed: a search (waiting for a slot or searching; nothing was stored) or
    /// a forced refit (which goes on in the background and is swapped in when done).
    #[error(
        "the deadline of {timeout_ms} ms passed ({extensions} extensions searched); retry in {retry_after_secs} s"
    )]
    DeadlineExceeded {
        /// Extensions spent before the search stopped (0 if it never started).
        extensions: usize,
        /// The deadline, in milliseconds from the request's arrival.
        timeout_ms: u64,
        /// Seconds to wait before retrying.
        retry_after_secs: u64,
    },
    /// The client went away and its search was cancelled; nobody reads this answer.
    #[error("the request was cancelled")]
    Cancelled,
    /// An operator's limit (experiments per server) is reached.
    #[error("{0}")]
    LimitReached(String),
    /// The experiment's dynamics model could not answer; nothing was stored.
    #[error(transparent)]
    Dynamics(#[from] DynamicsError),
    /// The database's disk is full: the write was not stored (a `201` is only ever answered
    /// after the outermost commit). Retry once space is freed.
    #[error(
        "the database's disk is full ({0}); nothing of this request was stored: retry once space is freed"
    )]
    StorageFull(String),
    /// The database cannot be reached now (a connection refused or lost, no connection free in
    /// time, a server restarting): retry shortly.
    #[error("the database is not answering ({0}); retry shortly")]
    DatabaseUnavailable(String),
    /// A `continue` stored its executed prefix as trajectory `trajectory_id`, then could not
    /// answer a new proposal (`error`): answered as `error`, saying what was stored.
    #[error("{error} (the executed prefix is stored as trajectory {trajectory_id})")]
    PrefixStored {
        /// The stored prefix.
        trajectory_id: i64,
        /// Why no proposal followed.
        error: Box<Error>,
    },
    /// An import stopped at an episode, or reading the file, on `error`: answered as `error`,
    /// saying where and what of the import was stored before it (importing again skips that).
    #[error(
        "{error} (the import stopped at {stop}; {} of its trajectories were stored before: importing again skips them)",
        stop.stored_before.trajectories
    )]
    ImportStopped {
        /// Where, and what the import did before it stopped.
        stop: Box<crate::import::ImportStop>,
        /// Why it stopped.
        error: Box<Error>,
    },
    /// A bug or a broken dependency: logged with its cause, never shown.
    #[error(transparent)]
    Internal(#[from] anyhow::Error),
}

impl Error {
    /// A validation failure of `field`.
    pub fn validation(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Validation {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// The answer for an experiment id that names nothing.
    pub fn no_experiment(id: i64) -> Self {
        Self::NotFound(format!("no experiment {id}"))
    }

    /// The answer itself, looking through [`Error::PrefixStored`] and [`Error::ImportStopped`]
    /// (which say what was stored beside it).
    pub fn answered(&self) -> &Error {
        match self {
            Self::PrefixStored { error, .. } | Self::ImportStopped { error, .. } => {
                error.answered()
            }
            other => other,
        }
    }

    /// A file-system failure while `what`: a full disk is [`Error::StorageFull`] (retry once
    /// space is freed), anything else internal.
    pub fn from_io(e: std::io::Error, what: &str) -> Self {
        if e.kind() == std::io::ErrorKind::StorageFull || e.raw_os_error() == Some(libc::ENOSPC) {
            Self::StorageFull(format!("{what}: {e}"))
        } else {
            Self::Internal(anyhow::Error::new(e).context(what.to_string()))
        }
    }

    /// A domain check that failed on the value at `field` of the request.
    pub fn invalid_at(field: &str, e: DomainError) -> Self {
        Self::validation(e.path_under(field), e.reason)
    }
}

impl From<InvalidSetting> for Error {
    fn from(e: InvalidSetting) -> Self {
        Self::Validation {
            field: e.field,
            reason: e.reason,
        }
    }
}

impl From<sqlx::Error> for Error {
    fn from(e: sqlx::Error) -> Self {
        match crate::store::classify(&e) {
            crate::store::Failure::Full => Self::StorageFull(e.to_string()),
            crate::store::Failure::Unreachable => Self::DatabaseUnavailable(e.to_string()),
            crate::store::Failure::Other => {
                Self::Internal(anyhow::Error::new(e).context("database"))
            }
        }
    }
}

impl From<PlanningError> for Error {
    fn from(e: PlanningError) -> Self {
        match e {
            PlanningError::NoPlan { extensions } => Self::NoPlan {
                extensions,
                candidates: Vec::new(),
            },
            PlanningError::InvalidInput { field, reason } => Self::validation(field, reason),
            PlanningError::InvalidSettings { field, reason } => {
                Self::validation(format!("learning.{field}"), reason)
            }
            PlanningError::Dynamics(e) => Self::Dynamics(e),
            // The service maps a stopped search itself, knowing its deadline; one that reaches
            // here ran outside the work gate.
            e @ PlanningError::Stopped { .. } => Self::Internal(e.into()),
            e @ PlanningError::ModelOutput { .. } => Self::Internal(e.into()),
        }
    }
}

/// Result of a service operation.
pub type Result<T, E = Error> = std::result::Result<T, E>;
