#!/usr/bin/env python3
"""Paired differences between two `precond experiment` result directories.

Runs are paired by (layout, seed, strategy) from every `iterations.csv` under each directory
(a world's directory, or a gridworld run's with one subdirectory per layout). For each metric
the difference A − B is averaged over the chosen iterations within each pair, and the mean and
standard error of those per-pair means are printed.

    python3 scripts/harness_paired.py runs/new/arm runs/old/arm --iterations 5,6,7,8,9 \
        --metrics success_rate,closed_loop_rate,tpr,tnr,n_train
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
from pathlib import Path

Key = tuple[str, str, str, int]


def load(root: Path) -> dict[Key, dict[str, str]]:
    """Every row of every `iterations.csv` under `root`, keyed by layout, strategy, seed and
    iteration."""
    rows: dict[Key, dict[str, str]] = {}
    for path in sorted(root.rglob("iterations.csv")):
        with path.open(newline="") as f:
            for r in csv.DictReader(f):
                layout = r.get("layout") or path.parent.name
                key = (layout, r.get("strategy", ""), r["seed"], int(r["iteration"]))
                rows[key] = r
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("--iterations", default="5,6,7,8,9")
    p.add_argument("--metrics", default="success_rate,tpr,tnr,n_train")
    args = p.parse_args()
    its = {int(i) for i in args.iterations.split(",")}
    a, b = load(args.a), load(args.b)
    print(f"{args.a} − {args.b}, iterations {args.iterations}:")
    for metric in args.metrics.split(","):
        per_pair: dict[tuple[str, str, str], list[float]] = {}
        for key, row in a.items():
            other = b.get(key)
            if other is None or key[3] not in its:
                continue
            try:
                d = float(row[metric]) - float(other[metric])
            except (KeyError, ValueError):
                continue
            if math.isfinite(d):
                per_pair.setdefault(key[:3], []).append(d)
        means = [statistics.mean(v) for v in per_pair.values()]
        if len(means) < 2:
            print(f"  {metric}: fewer than two pairs")
            continue
        se = statistics.stdev(means) / math.sqrt(len(means))
        print(f"  {metric}: {statistics.mean(means):+.3f} ± {se:.3f} over {len(means)} pairs")


if __name__ == "__main__":
    main()
