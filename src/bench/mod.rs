//! Benchmarks that print timings (run through `examples/` or the service's `bench` subcommand).

pub mod planning;
