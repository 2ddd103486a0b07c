#!/usr/bin/env python3
"""Runs the examples on one seed and fails when their figures drift from the committed ones.

The examples' READMEs quote the summaries committed under `docs/` (`docs/mujoco_pusher/`,
`docs/gymnasium/`, `docs/several_models/`): seed 0, the date and commit they were measured on. This script runs each
example again, seed 0, against BINARY, into a temporary directory, and compares the figures the
READMEs quote with the committed summary, each within the tolerance below (the spread a README
states: a run on the same seed is deterministic on one machine; the tolerances absorb one test
problem of ten, or a few hundredths of a rate, between machines). Exit status 1 when a figure
is outside its tolerance, with a table of every figure either way.

usage: scripts/check_example_figures.py BINARY [--python PYTHON] [--only pusher|gymnasium|several]

The examples' own dependencies must be installed in PYTHON (scripts/ci-examples.sh does it).
When a default changes a figure on purpose, refresh the committed outputs (`--out docs/...`,
the commands in each example's README) and the README's figures in the same commit.
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# (name, script, committed summary, extra args, [(figure path, tolerance)]).
EXAMPLES = [
    (
        "pusher",
        "examples/mujoco_pusher/pusher.py",
        "docs/mujoco_pusher/mujoco_pusher_summary.json",
        ["--model-port", "0"],
        [
            # Measured between machines, same commit (60438e0), seed 0: 0.7897 where the
            # figures were committed, 0.7276 on an AVX-512 VM (2026-11-29) — faer's kernels
            # round differently per SIMD width, and ten iterations of learning carry it on.
            ("curve[-1].tpr", 0.07),
            ("curve[-1].tnr", 0.05),
            ("curve[-1].plan_found", 0.1),
            ("curve[-1].success", 0.1),
            ("curve[5].plan_found", 0.1),
            ("curve[5].success", 0.1),
        ],
    ),
    (
        "gymnasium",
        "examples/gymnasium/inverted_pendulum.py",
        "docs/gymnasium/inverted_pendulum_summary.json",
        [],
        [
            ("collected.transitions", 0),
            ("evaluation.model_right", 0.02),
            ("evaluation.trusted", 0.02),
            ("evaluation.trusted_and_right", 0.02),
            ("evaluation.tpr", 0.03),
            ("evaluation.tnr", 0.02),
            ("coverage.trusted", 0.02),
        ],
    ),
    (
        "several",
        "examples/several_models/several_models.py",
        "docs/several_models/several_models_summary.json",
        [],
        [
            # Each model alone finds no plan across the sand; together they find every one.
            ("worlds.sand.mean.domain alone.found", 0),
            ("worlds.sand.mean.slow alone.found", 0),
            ("worlds.sand.mean.all models.found", 0.1),
            ("worlds.sand.mean.all models.success", 0.1),
            ("worlds.bands.mean.sim alone.success", 0.1),
            ("worlds.bands.mean.all models.success", 0.1),
            ("worlds.bands.mean.all models.closed_loop", 0.1),
            # The plans' step cost across models, against the simulator's alone (228).
            ("worlds.bands.mean.all models.step_cost", 15),
        ],
    ),
]


def figure(summary: dict, path: str) -> float:
    """The number at `path` ("a.b", "curve[-1].tpr") of a summary."""
    value: object = summary
    for part in path.split("."):
        key, _, index = part.partition("[")
        value = value[key]  # type: ignore[index]
        if index:
            value = value[int(index.rstrip("]"))]  # type: ignore[index]
    return float(value)  # type: ignore[arg-type]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("binary", help="the precond server binary the examples spawn")
    ap.add_argument("--python", default=sys.executable, help="the Python with the examples' deps")
    ap.add_argument("--only", choices=[e[0] for e in EXAMPLES])
    args = ap.parse_args()
    failed = []
    rows = []
    for name, script, committed_path, extra, figures in EXAMPLES:
        if args.only and name != args.only:
            continue
        committed = json.loads((ROOT / committed_path).read_text())
        with tempfile.TemporaryDirectory() as out:
            started = time.monotonic()
            run = subprocess.run(
                [args.python, str(ROOT / script), "--spawn-server", args.binary,
                 "--seed", "0", "--out", out, *extra],
                cwd=ROOT, capture_output=True, text=True,
            )
            took = time.monotonic() - started
            if run.returncode != 0:
                print(f"{name}: {script} failed ({run.returncode}) after {took:.0f} s")
                print(run.stdout[-2000:], run.stderr[-4000:], sep="\n")
                failed.append(f"{name}: the run")
                continue
            fresh = json.loads(next(Path(out).glob("*_summary.json")).read_text())
        print(f"{name}: {script}, seed 0, {took:.0f} s")
        for path, tolerance in figures:
            want, got = figure(committed, path), figure(fresh, path)
            ok = abs(got - want) <= tolerance + 1e-12
            rows.append((name, path, want, got, tolerance, ok))
            if not ok:
                failed.append(f"{name}: {path} {got:.4g}, committed {want:.4g} ± {tolerance}")
    print(f"\n{'example':<10} {'figure':<30} {'committed':>10} {'now':>10} {'±':>6}")
    for name, path, want, got, tolerance, ok in rows:
        mark = "" if ok else "  <- outside"
        print(f"{name:<10} {path:<30} {want:>10.4g} {got:>10.4g} {tolerance:>6}{mark}")
    if failed:
        print("\nfigures that no longer match their README:", *failed, sep="\n  ")
        print("refresh the committed outputs and the README figures if the change is meant")
        return 1
    print("\nevery example's figures match the committed ones")
    return 0


if __name__ == "__main__":
    sys.exit(main())
