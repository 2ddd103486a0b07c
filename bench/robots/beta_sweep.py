"""How a finished learning run's last model judges and plans at other test β.

The bench measures a run at its experiment's test β. This script reopens the runs' databases
(copies; the originals stay as they were) with the same robot model served where the experiment
calls it, and measures the last model on the seed's held-out state-actions at a grid of β (TPR,
TNR, and how well ``μ`` alone ranks safe before unsafe, as an AUC), then plans the seed's test
problems at a few β (plans found, open- and closed-loop success, unsafe planned steps). Nothing
is refitted: every β sees the same model, so the columns differ only by the margin.

    target/venv-bench/bin/python bench/robots/beta_sweep.py --binary target/release/precond \
        --plan-betas 2.0,certified,0.5 DB [DB ...] > sweep.jsonl

Each ``DB`` is a bench database named ``<robot>-<preset>-<seed>.db`` (the bench keeps them in
the temporary directory it logs). One JSON line per run.

``--mde KEY=VALUE`` (repeatable) changes the copy's MDE settings and ``--refit`` fits the last
model again on the same transitions before measuring: two estimators compared on the very data
one learning run gathered (e.g. ``--mde estimator=local_experts --refit`` against ``--refit``
alone, which refits with the run's own settings).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sqlite3
import sys
import tempfile
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import evaluate as ev  # noqa: E402
from references import ModelFns  # noqa: E402
from run import robot_class, test_set  # noqa: E402

from precond_client import Client, serve_model, spawn_server  # noqa: E402

GRID = [-1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0]


def auc(score: np.ndarray, safe: np.ndarray) -> float | None:
    """The chance that a safe state-action scores below an unsafe one (ties count half)."""
    pos, neg = score[safe], score[~safe]
    if len(pos) == 0 or len(neg) == 0:
        return None
    below = (pos[:, None] < neg[None, :]).mean()
    ties = (pos[:, None] == neg[None, :]).mean()
    return float(below + 0.5 * ties)


def sweep(binary: str, db: Path, plan_betas: list[str], args: argparse.Namespace) -> dict[str, Any]:
    name, preset, seed_text = db.stem.rsplit("-", 2)
    seed = int(seed_text)
    robot = robot_class(name)()
    ts = test_set(robot, seed, args.test_problems, args.held_out)
    work = Path(tempfile.mkdtemp(prefix="precond-sweep-")) / db.name
    shutil.copy(db, work)
    with sqlite3.connect(work) as conn:
        settings = json.loads(conn.execute("select settings from experiments").fetchone()[0])
        for key, value in args.mde:
            settings["mde"][key] = value
        for key, value in args.learning:
            settings["learning"][key] = value
        conn.execute("update experiments set settings = ?", (json.dumps(settings),))
    port = urlparse(settings["domain"]["model"]["url"]).port
    assert port is not None
    out: dict[str, Any] = {"run": db.stem, "robot": name, "preset": preset, "seed": seed}
    with serve_model(ModelFns(robot).lab, "127.0.0.1", port):
        proc, url = spawn_server(binary, work, "--allow-model-url", f"http://127.0.0.1:{port}/",
                                 log=work.with_suffix(".log"))
        try:
            client = Client(url, timeout=600, experiment_id=1, retries=1)
            model = client.model()
            if args.refit:
                before = model.version
                model = client.refit()
                while model.version == before:  # answered 202: the fit goes on
                    time.sleep(2)
                    model = client.model()
            out.update(mde={k: settings["mde"].get(k) for k in ("estimator", "expert_size")},
                       refit_seconds=model.fit_seconds if args.refit else None)
            safe = ts["held_dev"] < robot.d_max
            choice = model.raw.get("beta_choice") or {}
            out.update(n_train=model.n_train, model_version=model.version,
                       truly_safe_share=float(safe.mean()), certified_beta=choice.get("beta"),
                       test_beta=settings["learning"].get("test_beta"))
            judged = {}
            for beta in GRID:
                pre = client.precondition((ts["held_s"], ts["held_a"]), beta=beta)
                judged[f"{beta:g}"] = {"tpr": float(np.mean(pre.inside[safe])),
                                       "tnr": float(np.mean(~pre.inside[~safe]))}
            pre = client.precondition((ts["held_s"], ts["held_a"]))  # the experiment's own way
            judged["default"] = {"tpr": float(np.mean(pre.inside[safe])),
                                 "tnr": float(np.mean(~pre.inside[~safe]))}
            out["judged"] = judged
            pre = client.precondition((ts["held_s"], ts["held_a"]), beta=0.0)
            out["auc_mu"] = auc(pre.mu, safe)
            out["auc_mu_plus_2sigma"] = auc(pre.mu + 2.0 * pre.sigma, safe)
            planned = {}
            for label in plan_betas:
                if label == "default":  # no β: the experiment's test-time judgement
                    beta = None
                else:
                    beta = choice.get("beta") if label == "certified" else float(label)
                    if beta is None:
                        continue
                failures = ev.Failures()
                planner = ev.service_planner(client, failures, beta=beta)
                res = ev.test_plans(robot, planner, ts["problems"], closed=True,
                                    closed_seconds=args.closed_loop_seconds)
                res.pop("problems")
                res["beta"] = beta
                res["failures"] = failures.as_dict()
                planned[label] = res
            out["planned"] = planned
        finally:
            proc.terminate()
            proc.wait(20)
    return out


def mde_setting(text: str) -> tuple[str, Any]:
    key, _, value = text.partition("=")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--binary", required=True)
    ap.add_argument("--plan-betas", default="2.0,certified,0.5",
                    help="β to plan the test problems at (numbers, `certified`, or `default`: "
                         "no β, as the experiment's settings judge)")
    ap.add_argument("--test-problems", type=int, default=10)
    ap.add_argument("--held-out", type=int, default=400)
    ap.add_argument("--closed-loop-seconds", type=float, default=90.0)
    ap.add_argument("--mde", action="append", default=[], type=mde_setting, metavar="KEY=VALUE",
                    help="an MDE setting of the copy (a JSON value, or a bare string)")
    ap.add_argument("--learning", action="append", default=[], type=mde_setting,
                    metavar="KEY=VALUE",
                    help="a learning setting of the copy (e.g. local_test_margin=true)")
    ap.add_argument("--refit", action="store_true",
                    help="fit the last model again before measuring (POST …/model/refit)")
    ap.add_argument("dbs", nargs="+", type=Path)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    plan_betas = [b for b in args.plan_betas.split(",") if b]  # "": judge only, plan nothing
    for db in args.dbs:
        print(json.dumps(sweep(args.binary, db, plan_betas, args)), flush=True)


if __name__ == "__main__":
    main()
