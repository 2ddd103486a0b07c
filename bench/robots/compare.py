"""Two bench directories side by side, seed for seed: the learned columns of one preset at the
last iteration, ``before → after`` (means over the seeds both have) and the paired difference
(mean ± standard error).

    target/venv-bench/bin/python bench/robots/compare.py BEFORE_DIR AFTER_DIR [--preset default] \
        [--also-before DIR ...]

``--also-before`` adds directories where runs of the "before" binary are looked for too (seeds
measured later, by another start of the bench).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

COLUMNS = [
    ("plans_found", "plans"),
    ("open_loop_success", "open loop"),
    ("closed_loop_success", "closed loop"),
    ("tpr", "TPR"),
    ("tnr", "TNR"),
    ("unsafe_step_share", "unsafe steps"),
]


def final(path: Path) -> dict[str, Any] | None:
    if not path.exists():
        return None
    d = json.loads(path.read_text())
    return d.get("final")


def cell(before: list[float | None], after: list[float | None], percent: bool) -> str:
    pairs = [(b, a) for b, a in zip(before, after, strict=True) if b is not None and a is not None]
    if not pairs:
        return "–"
    b, a = np.array(pairs).T
    diff = a - b
    se = float(np.std(diff, ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else float("nan")
    scale, unit = (100.0, " %") if percent else (1.0, "")
    return (f"{scale * b.mean():.2f}{unit} → {scale * a.mean():.2f}{unit} "
            f"({scale * diff.mean():+.2f} ± {scale * se:.2f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--also-before", type=Path, action="append", default=[])
    ap.add_argument("--robots", default="arm,base,pusher,arm7",
                    help="robots; `base:base_theta` pairs base before with base_theta after")
    args = ap.parse_args()
    print("| robot | seeds | " + " | ".join(label for _, label in COLUMNS) + " |")
    print("|---|---|" + "---|" * len(COLUMNS))
    for robot in args.robots.split(","):
        name, _, after_name = robot.partition(":")
        after_name = after_name or name
        seeds = []
        for path in sorted(args.after.glob(f"{after_name}-{args.preset}-*.json")):
            seed = path.stem.rsplit("-", 1)[1]
            b = next((r for d in [args.before, *args.also_before]
                      if (r := final(d / f"{name}-{args.preset}-{seed}.json")) is not None), None)
            a = final(path)
            if b is not None and a is not None:
                seeds.append((seed, b, a))
        if not seeds:
            continue
        cells = [cell([b.get(k) for _, b, _ in seeds], [a.get(k) for _, _, a in seeds],
                      k == "unsafe_step_share") for k, _ in COLUMNS]
        names = ",".join(s for s, _, _ in seeds)
        print(f"| {robot} | {names} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
