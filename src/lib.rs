//! precond: learns where an inaccurate dynamics model can be trusted.
pub mod domain;
