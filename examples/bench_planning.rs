//! Prints the planning benchmark: `cargo run --release --example bench_planning`
//! (the same as `precond bench planning`).

fn main() -> Result<(), Box<dyn std::error::Error>> {
    precond::bench::planning::run_default()?;
    Ok(())
}
