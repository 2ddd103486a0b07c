//! The `precond` binary: parse the command line and run it.

use clap::Parser;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    precond::cli::run(precond::cli::Cli::parse()).await
}
