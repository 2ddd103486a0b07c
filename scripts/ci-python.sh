#!/usr/bin/env bash
# The Python client's gate: install it into a venv under target/, lint (ruff), type-check
# (mypy --strict), and run its unit tests and its integration tests against the real server
# binary, ${PRECOND_BIN:-target/debug/precond} (built here if missing).
set -euo pipefail
cd "$(dirname "$0")/.."
started=$SECONDS

# shellcheck source=scripts/common.sh
source scripts/common.sh
server_binary

venv=target/venv-python-client
ensure_venv "$venv"
echo "== pip install -e clients/python[dev]"
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check -e "clients/python[dev]"

cd clients/python
echo "== ruff check, ruff format --check"
"../../$venv/bin/ruff" check .
"../../$venv/bin/ruff" format --check .
echo "== mypy --strict"
"../../$venv/bin/mypy"
echo "== pytest (unit and integration, server $PRECOND_BIN)"
PRECOND_REQUIRE_SERVER=1 "../../$venv/bin/pytest" -q -p no:cacheprovider tests

echo "== python client: done in $((SECONDS - started)) s"
