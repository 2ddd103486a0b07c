//! The `precond` binary: parse the command line and run it.

use clap::Parser;
use std::time::Duration;

fn main() -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let result = runtime.block_on(precond_tools::cli::run(precond_tools::cli::Cli::parse()));
    // A fit still running on the blocking pool (it cannot stop halfway) must not hold the
    // process past its grace period; the next start refits what it did not store.
    runtime.shutdown_timeout(Duration::from_secs(1));
    result
}
