#!/usr/bin/env bash
# End-to-end tests of the dashboard in headless Chromium. Starts the real server binary
# (${PRECOND_BIN:-target/debug/precond}, under $CARGO_TARGET_DIR when set) on a free port over a
# temp database, fills it through the API (tests/browser/seed.mjs), opens the pages with
# Playwright and checks them (tests/browser/dashboard.mjs). Screenshots go to target/browser-tests/screenshots/.
# Installs what it needs: Debian's chromium (apt) if /usr/bin/chromium is missing, and
# playwright-core, eslint and prettier (npm ci from tests/browser/package-lock.json) into
# target/browser-tests/. First, before any build, the lint and format gate: eslint
# (tests/browser/eslint.config.mjs) and prettier --check (.prettierrc.json) on ui/ and
# tests/browser/*.mjs; any finding fails the script.
set -euo pipefail
cd "$(dirname "$0")/.."
started=$(date +%s)

work=target/browser-tests
mkdir -p "$work"
cp tests/browser/package.json tests/browser/package-lock.json tests/browser/*.mjs "$work/"
if ! cmp -s tests/browser/package-lock.json "$work/node_modules/.package-lock.json.copy" 2>/dev/null; then
    (cd "$work" && npm ci --ignore-scripts --no-audit --no-fund --loglevel=error)
    cp tests/browser/package-lock.json "$work/node_modules/.package-lock.json.copy"
fi

# The eslint config imports @eslint/js and globals, so it runs from its copy beside node_modules;
# its file patterns are relative to the working directory (the repository root) all the same.
echo "== eslint and prettier --check: ui/ tests/browser/*.mjs"
"$work/node_modules/.bin/eslint" --config "$work/eslint.config.mjs" --max-warnings 0 ui tests/browser/*.mjs
"$work/node_modules/.bin/prettier" --check --log-level warn ui tests/browser/*.mjs || {
    echo "not formatted: $work/node_modules/.bin/prettier --write ui tests/browser/*.mjs"
    exit 1
}

bin=${PRECOND_BIN:-${CARGO_TARGET_DIR:-target}/debug/precond}
if [ ! -x "$bin" ]; then
    cargo build --locked
fi

if [ ! -x /usr/bin/chromium ]; then
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi

db_dir=$(mktemp -d)
log="$db_dir/server.log"
"$bin" serve --addr 127.0.0.1:0 --database-url "$db_dir/precond.db" --log-format json >"$log" 2>&1 &
server=$!
cleanup() {
    kill "$server" 2>/dev/null || true
    wait "$server" 2>/dev/null || true
    rm -rf "$db_dir"
}
trap cleanup EXIT

# The server logs the address it bound (port 0: the OS picks a free one).
addr=""
for _ in $(seq 1 100); do
    addr=$(grep -o '"addr":"[^"]*"' "$log" | head -n1 | cut -d'"' -f4 || true)
    [ -n "$addr" ] && break
    kill -0 "$server" 2>/dev/null || { cat "$log"; echo "the server exited"; exit 1; }
    sleep 0.1
done
[ -n "$addr" ] || { cat "$log"; echo "the server did not report its address"; exit 1; }
echo "server at http://$addr"

rm -rf "$work/screenshots"
status=0
node "$work/dashboard.mjs" "http://$addr" "$work/screenshots" || status=$?
if [ "$status" -ne 0 ]; then
    echo "== server log (last 40 lines)"
    tail -n 40 "$log"
fi
echo "browser tests took $(( $(date +%s) - started )) s"
exit "$status"
