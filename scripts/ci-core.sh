#!/usr/bin/env bash
# The numeric core stands alone: precond-core's dependency list (normal dependencies, the whole
# tree) holds none of the server's crates, it builds by itself, and its in-process example (fit
# on transitions, query, plan) runs.
set -euo pipefail
cd "$(dirname "$0")/.."

server_crates='^(tokio|axum|hyper|hyper-util|tower|tower-http|sqlx|sqlx-core|serde_json|reqwest|ureq|metrics) '
tree=$(cargo tree --locked -p precond-core -e normal --prefix none)
if grep -E "$server_crates" <<<"$tree"; then
    echo "precond-core depends on a server crate (above)"
    exit 1
fi
echo "precond-core: $(sort -u <<<"$tree" | wc -l) crates in its dependency tree, none of the server's"

cargo build --locked -p precond-core
cargo run --locked -q -p precond-core --example in_process
