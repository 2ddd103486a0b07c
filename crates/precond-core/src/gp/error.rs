//! The one error type of the GP core.

use thiserror::Error;

/// Everything that can go wrong when configuring, fitting, rebuilding or querying a GP.
///
/// Numerical failure is a value of this type, never a panic.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum GpError {
    /// A parameter of [`GpParams`](super::GpParams) is out of its documented range.
    #[error("invalid GP parameter `{name}`: {reason}")]
    InvalidParameter {
        /// The parameter's field name (dotted for nested fields, e.g. `bounds.length_scale`).
        name: &'static str,
        /// Why the value was rejected.
        reason: String,
    },
    /// Two inputs that must agree in size do not.
    #[error("dimension mismatch in {what}: expected {expected}, found {found}")]
    DimensionMismatch {
        /// What was being compared (e.g. `rows of x vs length of y`).
        what: &'static str,
        /// The size that was required.
        expected: usize,
        /// The size that was given.
        found: usize,
    },
    /// An input contains NaN or an infinity.
    #[error("non-finite value in {what} at index {index}")]
    NonFinite {
        /// Which input (`x`, `y`, or a stored state field).
        what: &'static str,
        /// Position of the first offending value (row-major `row * dim + col` for matrices).
        index: usize,
    },
    /// There are no training points, or the inputs have no columns.
    #[error("empty data: {0}")]
    EmptyData(&'static str),
    /// The covariance matrix could not be factorised even with the largest allowed jitter.
    #[error("Cholesky factorisation failed even with jitter {jitter:e} added to the diagonal")]
    NotPositiveDefinite {
        /// The largest (absolute) jitter that was tried.
        jitter: f64,
    },
    /// A stored [`ModelState`](super::ModelState) is inconsistent with itself or with the data.
    #[error("invalid model state: {0}")]
    InvalidState(String),
    /// No optimiser start produced a finite log marginal likelihood.
    #[error("hyperparameter optimisation failed: {0}")]
    OptimisationFailed(String),
}
