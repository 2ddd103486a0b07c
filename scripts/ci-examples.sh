#!/usr/bin/env bash
# The examples' figures: install their dependencies into a venv under target/, run the MuJoCo
# pusher, the Gymnasium cart-pole and the several-models example on seed 0 against ${PRECOND_BIN:-target/debug/precond}
# (built here if missing), and fail when a figure their READMEs quote has drifted from the
# committed summary (scripts/check_example_figures.py).
set -euo pipefail
cd "$(dirname "$0")/.."
started=$SECONDS

# shellcheck source=scripts/common.sh
source scripts/common.sh
server_binary

venv=target/venv-examples
ensure_venv "$venv"
echo "== pip install clients/python[gymnasium,mujoco] -r examples/mujoco_pusher/requirements.txt"
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
    "./clients/python[gymnasium,mujoco]" -r examples/mujoco_pusher/requirements.txt

echo "== scripts/check_example_figures.py $PRECOND_BIN"
MPLBACKEND=Agg "$venv/bin/python" scripts/check_example_figures.py "$PRECOND_BIN" \
    --python "$venv/bin/python"

echo "== examples: done in $((SECONDS - started)) s"
