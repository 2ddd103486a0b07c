#!/usr/bin/env python3
"""Strategies side by side, at equal iterations and at equal executed transitions.

Reads every `iterations.csv` under each directory given (a world's directory, or a gridworld
run's with one subdirectory per layout). An *arm* is a strategy of a directory, named
`LABEL/strategy` (the label defaults to the directory's name; directories with the same label
pool their runs). For each arm it prints the mean
± standard error over runs (layout × seed) of a metric at the chosen iterations and at the
chosen numbers of executed transitions (a run's value at `T` transitions is the one of its last
iteration with `n_train ≤ T`; runs that never reached `T` are left out, and the count says
how many are in), then the paired difference of every arm against the baseline arm over the
runs both have (pairs by layout and seed, so common random numbers cancel).

    python3 scripts/harness_strategies.py runs/grid-paper:paper runs/grid-new:new \
        --baseline paper/goal_conditioned --iterations 4,9 --transitions 200,400 \
        --metric success_rate
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
from pathlib import Path

Run = tuple[str, str]  # (layout, seed)


def load(root: Path, label: str) -> dict[str, dict[Run, list[dict[str, str]]]]:
    """Per arm, per run, its iteration rows in iteration order."""
    arms: dict[str, dict[Run, list[dict[str, str]]]] = {}
    for path in sorted(root.rglob("iterations.csv")):
        with path.open(newline="") as f:
            for r in csv.DictReader(f):
                layout = r.get("layout") or path.parent.name
                arm = f"{label}/{r['strategy']}"
                arms.setdefault(arm, {}).setdefault((layout, r["seed"]), []).append(r)
    for runs in arms.values():
        for rows in runs.values():
            rows.sort(key=lambda r: int(r["iteration"]))
    return arms


def value(row: dict[str, str], metric: str) -> float | None:
    try:
        v = float(row[metric])
    except (KeyError, ValueError):
        return None
    return v if math.isfinite(v) else None


def at_iteration(rows: list[dict[str, str]], j: int, metric: str) -> float | None:
    return value(rows[j], metric) if j < len(rows) else None


def at_transitions(rows: list[dict[str, str]], t: int, metric: str) -> float | None:
    reached = [r for r in rows if float(r["n_train"]) <= t]
    if not reached or float(rows[-1]["n_train"]) < t:
        return None
    return value(reached[-1], metric)


def mean_se(xs: list[float]) -> str:
    if not xs:
        return "–"
    se = statistics.stdev(xs) / math.sqrt(len(xs)) if len(xs) > 1 else 0.0
    return f"{statistics.mean(xs):.2f} ± {se:.2f} ({len(xs)})"


def paired(a: dict[Run, float | None], b: dict[Run, float | None]) -> str:
    d = [a[k] - b[k] for k in a if k in b and a[k] is not None and b[k] is not None]
    if len(d) < 2:
        return "–"
    se = statistics.stdev(d) / math.sqrt(len(d))
    ahead = sum(x > 0 for x in d)
    return f"{statistics.mean(d):+.3f} ± {se:.3f} ({ahead}/{len(d)} ahead)"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dirs", nargs="+", help="DIR or DIR:LABEL")
    p.add_argument("--baseline", help="the arm to pair against, LABEL/strategy")
    p.add_argument("--iterations", default="4,9")
    p.add_argument("--transitions", default="")
    p.add_argument("--metric", default="success_rate")
    a = p.parse_args()
    arms: dict[str, dict[Run, list[dict[str, str]]]] = {}
    for d in a.dirs:
        path, _, label = d.partition(":")
        for arm, runs in load(Path(path), label or Path(path).name).items():
            arms.setdefault(arm, {}).update(runs)
    points = [("it", int(j)) for j in a.iterations.split(",") if j] + [
        ("T", int(t)) for t in a.transitions.split(",") if t
    ]
    heads = [f"it {j}" if kind == "it" else f"{j} transitions" for kind, j in points]
    print(f"{a.metric}: mean ± se (runs)")
    print("| arm | " + " | ".join(heads) + " |")
    print("|---|" + "---|" * len(points))
    table: dict[str, list[dict[Run, float | None]]] = {}
    for arm, runs in sorted(arms.items()):
        cols = []
        for kind, j in points:
            f = at_iteration if kind == "it" else at_transitions
            cols.append({run: f(rows, j, a.metric) for run, rows in runs.items()})
        table[arm] = cols
        cells = [mean_se([v for v in c.values() if v is not None]) for c in cols]
        print(f"| {arm} | " + " | ".join(cells) + " |")
    if a.baseline:
        if a.baseline not in table:
            raise SystemExit(f"no arm {a.baseline!r}; arms: {', '.join(sorted(table))}")
        print(f"\npaired against {a.baseline}:")
        print("| arm | " + " | ".join(heads) + " |")
        print("|---|" + "---|" * len(points))
        base = table[a.baseline]
        for arm, cols in table.items():
            if arm != a.baseline:
                cells = [paired(c, b) for c, b in zip(cols, base)]
                print(f"| {arm} − baseline | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
