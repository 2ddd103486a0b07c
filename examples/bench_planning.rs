//! Prints the planning benchmark: `cargo run --release --example bench_planning`.

fn main() {
    precond::bench::planning::run_default();
}
