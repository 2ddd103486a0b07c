"""Summary of a bench directory: mean ± standard error over seeds per robot and column.

    python bench/robots/summary.py DIR     # (re)writes DIR/summary.md and DIR/summary.json
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np


def mean_se(values: list[float | None]) -> dict[str, Any]:
    v = np.array([x for x in values if x is not None], dtype=float)
    if len(v) == 0:
        return {"mean": None, "se": None, "n": 0}
    se = float(np.std(v, ddof=1) / np.sqrt(len(v))) if len(v) > 1 else None
    return {"mean": float(np.mean(v)), "se": se, "n": int(len(v))}


def fmt(ms: dict[str, Any], digits: int = 2, scale: float = 1.0) -> str:
    if ms["mean"] is None:
        return "–"
    m = ms["mean"] * scale
    if ms["se"] is None:
        return f"{m:.{digits}f}"
    return f"{m:.{digits}f} ± {ms['se'] * scale:.{digits}f}"


def collect(out: Path) -> dict[str, Any]:
    runs = [json.loads(p.read_text()) for p in sorted(out.glob("*.json"))
            if p.name not in ("summary.json", "meta.json") and not p.name.endswith("-robot.json")]
    by_robot: dict[str, dict[str, list[dict[str, Any]]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        col = "references" if r.get("kind") == "references" else r.get("preset")
        by_robot[r["robot"]][col].append(r)
    table: dict[str, Any] = {}
    for robot, cols in by_robot.items():
        row: dict[str, Any] = {}
        seeds = {r["seed"]: r["truly_safe_share"] for c in cols.values() for r in c
                 if "truly_safe_share" in r}
        row["truly_safe_share"] = mean_se(list(seeds.values()))
        row["seeds"] = sorted(seeds)
        refs = [r for r in cols.get("references", []) if "error" not in r]
        row["reference_seeds"] = sorted(r["seed"] for r in refs)
        for ref in ("oracle", "baseline"):
            row[ref] = {k: mean_se([r[ref][k] for r in refs]) for k in
                        ("plans_found", "open_loop_success", "closed_loop_success",
                         "unsafe_step_share", "mean_plan_length")}
            row[ref]["plan_seconds"] = mean_se(
                [float(np.mean(r[ref]["plan_seconds"])) for r in refs if r[ref]["plan_seconds"]])
        row["errors"] = {c: [r["seed"] for r in rs if "error" in r] for c, rs in cols.items()}
        for preset, rs in cols.items():
            if preset == "references":
                continue
            ok = [r for r in rs if "error" not in r and r.get("final")]
            f = [r["final"] for r in ok]
            col: dict[str, Any] = {k: mean_se([x.get(k) for x in f]) for k in
                                   ("plans_found", "open_loop_success", "closed_loop_success",
                                    "tpr", "tnr", "median_sigma", "unsafe_step_share",
                                    "trusted_share", "mean_plan_length", "test_beta")}
            col["proposal_seconds"] = mean_se(
                [float(np.mean(r["proposal_seconds"])) for r in ok if r["proposal_seconds"]])
            col["fit_seconds"] = mean_se(
                [float(np.mean(r["fit_seconds"])) for r in ok if r["fit_seconds"]])
            col["fit_seconds_last"] = mean_se([r["fit_seconds"][-1] for r in ok if r["fit_seconds"]])
            col["posted"] = mean_se([r["posted"] for r in ok])
            col["no_plan_proposals"] = mean_se([r["counters"]["no_plan"] for r in ok])
            col["relaxed_proposals"] = mean_se([r["counters"]["relaxed"] for r in ok])
            col["training_transitions"] = mean_se([r["counters"]["transitions"] for r in ok])
            col["training_unsafe_share"] = mean_se(
                [r["counters"]["deviations_over_dmax"] / r["counters"]["transitions"]
                 for r in ok if r["counters"]["transitions"]])
            fails: dict[str, int] = defaultdict(int)
            for r in ok:
                for k, v in r.get("failures", {}).items():
                    fails[k] += v
                for k, v in r.get("http_statuses", {}).items():  # retried ones included
                    if int(k.rsplit(" ", 1)[1]) >= 500:
                        fails[f"answered {k}"] += v
            col["failures_total"] = dict(fails)
            col["stalled_seeds"] = [r["seed"] for r in ok if r["final"].get("stalled")]
            # The learning curve: per iteration, over seeds.
            iters = sorted({c["iteration"] for r in ok for c in r["curve"]})
            col["curve"] = {
                str(i): {k: mean_se([c.get(k) for r in ok for c in r["curve"] if c["iteration"] == i])
                         for k in ("tpr", "tnr", "median_sigma", "trusted_share", "plans_found",
                                   "open_loop_success", "fit_seconds")}
                for i in iters}
            row[preset] = col
        table[robot] = row
    return table


def markdown(table: dict[str, Any], meta: dict[str, Any]) -> str:
    lines = [
        "# Robot bench summary",
        "",
        f"`{meta.get('command', '')}`  ",
        f"started {meta.get('started', '?')}; binary `{meta.get('binary', '?')}` "
        f"(commit {meta.get('binary_commit') or '?'}); MuJoCo {meta.get('mujoco', '?')}; "
        f"{meta.get('iterations')} iterations of {meta.get('batch')} trajectories; "
        f"{meta.get('test_problems')} test problems and {meta.get('held_out')} held-out "
        "state-actions per seed. Mean ± standard error over seeds.",
        "",
        "## References (no learning)",
        "",
        "| robot | seeds (truly safe; references) | truly safe | oracle plans | oracle open | oracle closed | baseline plans | baseline open | baseline closed | baseline unsafe steps | s per oracle plan |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for robot, row in table.items():
        o, b = row["oracle"], row["baseline"]
        lines.append(
            f"| {robot} | {len(row['seeds'])}; {len(row['reference_seeds'])} | {fmt(row['truly_safe_share'])} | "
            f"{fmt(o['plans_found'])} | {fmt(o['open_loop_success'])} | "
            f"{fmt(o['closed_loop_success'])} | {fmt(b['plans_found'])} | "
            f"{fmt(b['open_loop_success'])} | {fmt(b['closed_loop_success'])} | "
            f"{fmt(b['unsafe_step_share'], 0, 100)} % | {fmt(o['plan_seconds'], 1)} |")
    presets = sorted({p for row in table.values() for p in row
                      if isinstance(row[p], dict) and "tpr" in row[p]})
    lines += [
        "",
        "## Learned precondition at the last iteration",
        "",
        "| robot | preset | seeds | plans | open loop | closed loop | TPR | TNR | median σ | trusted | unsafe steps | s / proposal | s / refit (mean, last) | no_plan proposals | relaxed | failures |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for robot, row in table.items():
        for p in presets:
            if p not in row:
                continue
            c = row[p]
            fails = ", ".join(f"{k} {v}" for k, v in sorted(c["failures_total"].items())) or "none"
            if c["stalled_seeds"]:
                fails += f"; stalled seeds {c['stalled_seeds']}"
            lines.append(
                f"| {robot} | {p} | {c['posted']['n']} | {fmt(c['plans_found'])} | {fmt(c['open_loop_success'])} | "
                f"{fmt(c['closed_loop_success'])} | {fmt(c['tpr'])} | {fmt(c['tnr'])} | "
                f"{fmt(c['median_sigma'], 3)} | {fmt(c['trusted_share'])} | "
                f"{fmt(c['unsafe_step_share'], 0, 100)} % | {fmt(c['proposal_seconds'], 1)} | "
                f"{fmt(c['fit_seconds'], 1)}, {fmt(c['fit_seconds_last'], 1)} | {fmt(c['no_plan_proposals'], 1)} | "
                f"{fmt(c['relaxed_proposals'], 1)} | {fails} |")
    lines += ["", "## Learning curves (precondition against the truth, per iteration)", ""]
    for robot, row in table.items():
        for p in presets:
            if p not in row:
                continue
            lines.append(f"**{robot}, {p}**: " + "; ".join(
                f"{i}: TPR {fmt(v['tpr'])} TNR {fmt(v['tnr'])}"
                for i, v in row[p]["curve"].items()))
            lines.append("")
    errs = {r: e for r, row in table.items() for e in [row["errors"]] if any(e.values())}
    if errs:
        lines += ["## Runs that failed", "", "```", json.dumps(errs, indent=1), "```", ""]
    return "\n".join(lines) + "\n"


def write(out: Path) -> dict[str, Any]:
    table = collect(out)
    meta_path = out / "meta.json"
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    (out / "summary.json").write_text(json.dumps({"meta": meta, "robots": table}, indent=1))
    (out / "summary.md").write_text(markdown(table, meta))
    return table


if __name__ == "__main__":
    write(Path(sys.argv[1]))
    print((Path(sys.argv[1]) / "summary.md").read_text())
