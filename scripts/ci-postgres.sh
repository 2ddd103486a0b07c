#!/usr/bin/env bash
# The PostgreSQL gate: a throwaway PostgreSQL server (scripts/postgres.sh: Debian's package,
# installed if missing, a cluster in a temporary directory on a free port), then the API tests
# against it (each test on a database of its own) and the replica tests (several `precond
# serve` processes over one database, kill -9 included). The server is stopped on exit.
set -euo pipefail
cd "$(dirname "$0")/.."
started=$SECONDS

dir="$(mktemp -d /tmp/precond-postgres.XXXXXX)"
cleanup() {
    scripts/postgres.sh stop "$dir" || true
    rm -rf "$dir"
}
trap cleanup EXIT
echo "== PostgreSQL in $dir"
url="$(scripts/postgres.sh start "$dir")"
echo "== server at $url"

export PRECOND_TEST_POSTGRES="$url"
echo "== cargo test --test api --test replicas (PostgreSQL)"
cargo test --locked --test api --test replicas

echo "== postgres: done in $((SECONDS - started)) s"
