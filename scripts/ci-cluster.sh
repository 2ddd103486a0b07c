#!/usr/bin/env bash
# The cluster deployment, end to end: scripts/cluster.sh (PostgreSQL, two replicas of the debug
# binary, nginx with deploy/nginx-cluster.conf's proxy settings), then the API through the
# balancer — an experiment, a batch that gets fitted, one replica killed with -9, and every
# following request still answered, an idempotent retry replayed.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/common.sh
started=$SECONDS

target="${CARGO_TARGET_DIR:-target}"
export PRECOND_BIN="${PRECOND_BIN:-$target/debug/precond}"
[ -x "$PRECOND_BIN" ] || cargo build --locked
dir="$(mktemp -d /tmp/precond-cluster.XXXXXX)"
cleanup() {
    scripts/cluster.sh stop "$dir" || true
    rm -rf "$dir"
}
trap cleanup EXIT
port="$(free_port)"
scripts/cluster.sh start "$dir" 2 "$port"
b="http://127.0.0.1:$port"

fail() {
    echo "cluster: $*" >&2
    exit 1
}
json() { python3 -c "import json,sys; print(json.load(sys.stdin)$1)"; }

id="$(curl -fsS --json '{"domain": {"kind": "kinematic"}, "learning": {"batch_size": 2}}' \
    "$b/v1/experiments" | json '["id"]')"
for k in 1 2; do
    curl -fsS --json '{"transitions": [{"s": [0.2, 0.2], "a": [0.05, 0], "s_next": [0.24, 0.2]}]}' \
        "$b/v1/experiments/$id/trajectories" >/dev/null
done
version=0
for _ in $(seq 1 300); do
    version="$(curl -fsS "$b/v1/experiments/$id/model" | json '["version"]')"
    [ "$version" -ge 1 ] && break
    sleep 0.1
done
[ "$version" -ge 1 ] || fail "the batch was not fitted within 30 s"
echo "cluster: batch fitted (version $version), seen through the balancer"

kill -9 "$(cat "$dir/replica-1.pid")"
for _ in $(seq 1 6); do
    code="$(curl -s -o /dev/null -w '%{http_code}' "$b/v1/experiments/$id/model")"
    [ "$code" = 200 ] || fail "after a replica died the balancer answered $code"
done
body='{"transitions": [{"s": [0.3, 0.3], "a": [0, 0.05], "s_next": [0.3, 0.34]}]}'
first="$(curl -fsS -H 'Idempotency-Key: smoke-1' --json "$body" "$b/v1/experiments/$id/trajectories" | json '["id"]')"
replay="$(curl -fsS -D - -o /dev/null -H 'Idempotency-Key: smoke-1' --json "$body" \
    "$b/v1/experiments/$id/trajectories" | tr -d '\r' | grep -i '^idempotent-replayed:' || true)"
[ -n "$replay" ] || fail "a retry under the same key was not replayed"
n="$(curl -fsS "$b/v1/experiments/$id" | json '["n_trajectories"]')"
[ "$n" = 3 ] || fail "$n trajectories stored, 3 expected (trajectory $first once)"
echo "cluster: a replica killed, every request answered, the retry replayed, 3 trajectories"
echo "== cluster: done in $((SECONDS - started)) s"
