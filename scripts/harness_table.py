#!/usr/bin/env python3
"""Prints a Markdown table of `precond experiment` results: for each results directory given
(one per world/configuration, each holding `summary.json`), the mean ± standard error over
seeds of the chosen metrics at the chosen iterations, per strategy.

    python3 scripts/harness_table.py results/arm results/base --iterations 4,9 \
        --metrics plans_of_oracle,closed_loop_of_oracle,success_rate,tnr
"""

import argparse
import json
from pathlib import Path

DEFAULT_METRICS = (
    "plan_found_rate,success_rate,closed_loop_rate,oracle_rate,oracle_open_loop_rate,"
    "oracle_closed_loop_rate,baseline_rate,tpr,tnr,held_out_median_sigma"
)


def cell(series: list[dict], j: int) -> str:
    if j >= len(series) or series[j]["mean"] is None:
        return "–"
    mean, se = series[j]["mean"], series[j]["se"] or 0.0
    return f"{mean:.2f} ± {se:.2f}" if abs(mean) >= 0.01 or mean == 0 else f"{mean:.3f} ± {se:.3f}"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("dirs", nargs="+", type=Path)
    p.add_argument("--iterations", default="4,9")
    p.add_argument("--metrics", default=DEFAULT_METRICS)
    p.add_argument("--label", action="append", default=[], help="a label per directory")
    a = p.parse_args()
    its = [int(x) for x in a.iterations.split(",")]
    metrics = a.metrics.split(",")
    print("| run | strategy | it | " + " | ".join(metrics) + " |")
    print("|---|---|---|" + "---|" * len(metrics))
    for k, d in enumerate(a.dirs):
        s = json.loads((d / "summary.json").read_text())
        label = a.label[k] if k < len(a.label) else f"{s['domain']} ({d.parent.name})"
        for strategy, per_metric in s["strategies"].items():
            for j in its:
                cells = [cell(per_metric[m], j) if m in per_metric else "?" for m in metrics]
                print(f"| {label} | {strategy} | {j} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
