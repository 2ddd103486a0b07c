"""Several models of one robot on the MuJoCo bench: the lab's kinematic model and a coarse
simulator, each with its own learned precondition, and test plans that step with either.

For the pusher and the base, each (robot, seed) run:

1. serves two models with ``serve_model``: the lab's ``f_hat`` as the domain's model (cost 1)
   and a **coarse simulator** of the true world as the further model ``sim`` (cost 20): the
   same MuJoCo scene and the same step code, stepped with a larger timestep
   (``COARSE_TIMESTEP_FACTOR``: pusher 4 ms -> 16 ms, base 10 ms -> 20 ms), every phase of the
   step keeping its duration in seconds (so fewer, coarser steps). The base's factor is 2, not
   4: at 40 ms its wheel contacts (``solref`` 0.02 s) are no longer resolved and the
   simulator is within ``d_max`` of the truth on about a quarter of state-actions only (measured
   once, on 300 uniform state-actions, before any learning run; see the results' README);
2. measures on the seed's held-out state-actions (``run.test_set``: uniform valid states ×
   the action box) the share where each model is within ``d_max`` of the true next state;
3. creates the experiment as ``run.py``'s learning run does (custom domain, remote lab model,
   ``learning: {preset: default, batch_size: 5, iterations: 10}``), with
   ``models=[{"name": "sim", "cost": 20, "model": {"kind": "remote", "url": ...}}]``;
4. learns with ``client.learn`` for 10 × 5 trajectories, each proposal executed open loop in
   MuJoCo, then waits for the model fitted on all 50;
5. plans ``run.test_set``'s fixed test problems (the same as ``run.py``'s) with
   ``models=["domain"]``, ``models=["sim"]`` and all models (``None``), executes each found plan
   open loop in MuJoCo; success is the robot's goal test on the last true state. Records found,
   success, search cost (``plan.cost()``), step cost (Σ of each step's model cost) and wall time.

A plan's search has ``--plan-seconds`` of wall clock (the server's ``--plan-timeout-ms``, no
client retry); a search cut by it counts as not found (``error: deadline_exceeded``).

    /work/main/target/venv-bench/bin/python bench/robots/several.py --binary /work/bin/precond-several \\
        --robots pusher,base --seeds 3 --out bench/robots/results/2026-11-29-several
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import platform
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from precond_client import Client, errors, serve_model

sys.path.insert(0, str(Path(__file__).parent))

import run as bench  # noqa: E402
from robot import Array, Robot  # noqa: E402

log = logging.getLogger("several")

COSTS = {"domain": 1.0, "sim": 20.0}
ARMS: dict[str, list[str] | None] = {"domain": ["domain"], "sim": ["sim"], "all": None}
COARSE_TIMESTEP_FACTOR = {"pusher": 4, "base": 2}
REFERENCE_DIRS = ["2026-11-28-6c39bc9", "2026-11-29-f305d47", "2026-11-28-dcf605d-seeds34",
                  "2026-11-28-6c39bc9-seed2", "2026-11-28-a49abbd"]


# --------------------------------------------------------------------------- the coarse simulator


def coarse_robot(name: str) -> Robot:
    """The robot's own class, its MuJoCo timestep multiplied by the factor, and every step count
    derived from the timestep recomputed (each phase keeps its duration in seconds)."""
    factor = COARSE_TIMESTEP_FACTOR[name]
    robot = bench.robot_class(name)()
    m = robot.model  # type: ignore[attr-defined]
    m.opt.timestep *= factor
    dt = float(m.opt.timestep)
    if name == "pusher":
        import pusher
        robot.dt = dt  # type: ignore[attr-defined]
        robot.nstep = int(round(pusher.STEP_SECONDS / dt))  # type: ignore[attr-defined]
    elif name == "base":
        import base
        robot.n_settle = int(round(base.SETTLE_SECONDS / dt))  # type: ignore[attr-defined]
        robot.n_drive = int(round(base.DRIVE_SECONDS / dt))  # type: ignore[attr-defined]
        robot.n_stop = int(round(base.STOP_SECONDS / dt))  # type: ignore[attr-defined]
    else:
        raise SystemExit(f"no coarse simulator for {name!r}")
    return robot


class Served:
    """The two model functions served for one run, counting points and time."""

    def __init__(self, robot: Robot, sim: Robot) -> None:
        self.robot, self.sim = robot, sim
        self.points = {"domain": 0, "sim": 0}
        self.seconds = {"domain": 0.0, "sim": 0.0}
        self.lock = threading.Lock()

    def lab(self, states: Array, actions: Array) -> tuple[Array, Any]:
        t0 = time.perf_counter()
        out = self.robot.f_hat(states, actions), self.robot.lab_valid(states, actions)
        self.points["domain"] += len(states)
        self.seconds["domain"] += time.perf_counter() - t0
        return out

    def coarse(self, states: Array, actions: Array) -> tuple[Array, Any]:
        t0 = time.perf_counter()
        with self.lock:  # one MjData
            nxt = self.sim.true_steps(states, actions)
        self.points["sim"] += len(states)
        self.seconds["sim"] += time.perf_counter() - t0
        return nxt, np.ones(len(states), dtype=bool)


def shares(robot: Robot, sim: Robot, ts: dict[str, Any]) -> dict[str, Any]:
    """Where each model is within d_max of MuJoCo on the seed's held-out state-actions."""
    s, a = ts["held_s"], ts["held_a"]
    t0 = time.perf_counter()
    true = robot.true_steps(s, a)
    t_true = (time.perf_counter() - t0) / len(s)
    t0 = time.perf_counter()
    coarse = sim.true_steps(s, a)
    t_sim = (time.perf_counter() - t0) / len(s)
    d_lab = robot.distance(robot.f_hat(s, a), true)
    d_sim = robot.distance(coarse, true)
    ok_lab, ok_sim = d_lab < robot.d_max, d_sim < robot.d_max
    return {
        "n": len(s),
        "domain_within_d_max": float(np.mean(ok_lab)),
        "sim_within_d_max": float(np.mean(ok_sim)),
        "both": float(np.mean(ok_lab & ok_sim)),
        "domain_only": float(np.mean(ok_lab & ~ok_sim)),
        "sim_only": float(np.mean(ok_sim & ~ok_lab)),
        "either": float(np.mean(ok_lab | ok_sim)),
        "sim_deviation_quantiles_50_90_99": np.quantile(d_sim, [0.5, 0.9, 0.99]),
        "domain_deviation_quantiles_50_90_99": np.quantile(d_lab, [0.5, 0.9, 0.99]),
        "ms_per_point_true": 1000 * t_true,
        "ms_per_point_sim": 1000 * t_sim,
    }


# --------------------------------------------------------------------------- one run


def several_run(name: str, seed: int, args: argparse.Namespace, dbdir: Path) -> dict[str, Any]:
    robot = bench.robot_class(name)()
    sim = coarse_robot(name)
    ts = bench.test_set(robot, seed, args.test_problems, args.held_out)
    out: dict[str, Any] = {"robot": name, "seed": seed,
                           "coarse_sim": {"timestep_factor": COARSE_TIMESTEP_FACTOR[name],
                                          "timestep": float(sim.model.opt.timestep)},  # type: ignore[attr-defined]
                           "costs": COSTS, "learn": args.learn}
    t_start = time.monotonic()
    out["shares"] = shares(robot, sim, ts)
    log.info("%s seed %d: within d_max: domain %.3f sim %.3f either %.3f", name, seed,
             out["shares"]["domain_within_d_max"], out["shares"]["sim_within_d_max"],
             out["shares"]["either"])
    fns = Served(robot, sim)
    limit_ms = int(args.plan_seconds * 1000)
    with serve_model(fns.lab, "127.0.0.1", 0, path="/lab") as lab, \
            serve_model(fns.coarse, "127.0.0.1", 0, path="/sim") as simserver:
        server = bench.Server(args.binary, dbdir / f"{name}-several-{seed}.db",
                              [lab.port, simserver.port],
                              ["--plan-timeout-ms", str(limit_ms),
                               "--max-model-timeout-ms", "60000"])
        try:
            client = Client(server.url, timeout=args.plan_seconds + 120,
                            client_id=f"several-{name}", retries=1)
            bench.count_statuses(client)
            client.wait_ready(30)
            exp = client.create_experiment(
                name=f"{name} several models seed {seed}", d_max=robot.d_max, seed=seed,
                domain=robot.domain(lab.url),
                learning={"preset": "default", "batch_size": args.batch,
                          "iterations": args.iterations},
                models=[{"name": "sim", "cost": COSTS["sim"],
                         "model": {"kind": "remote", "url": simserver.url,
                                   "timeout_ms": 60000}}])
            out["settings"] = {"domain": exp.domain, "learning": exp.learning,
                               "models": getattr(exp, "models", None)}

            # ---- learning (run.py's loop, simplified)
            t0 = time.monotonic()
            rng = np.random.default_rng([seed, 1])

            def problems():
                while True:
                    yield robot.sample_problem(rng)

            total = args.iterations * args.batch
            posted, requests_guard = 0, 0

            # What the proposals step with after the first batch (when `sim` has an
            # estimator): `domain`, the service's default, the lab model alone; `all`, both,
            # each proposal valued by what it teaches each; `separate`, one at a time in turn.
            def separately(_episodes: int) -> list[str] | None:
                if args.learn == "domain" or posted < args.batch:
                    return None
                if args.learn == "all":
                    return ["domain", "sim"]
                return [["domain", "sim"][posted % 2]]

            failures: dict[str, int] = {}
            no_plan = 0
            while posted < total and requests_guard < 4 * total:
                learner = client.learn(problems(), client_id=f"several-{name}",
                                       model_timeout=600, models=separately)
                try:
                    for ep in learner:
                        ep.post(robot.execute(ep.start, ep.actions))
                        posted += 1
                        if posted % args.batch == 0:
                            log.info("%s seed %d: %d trajectories posted (%.0f s)", name, seed,
                                     posted, time.monotonic() - t0)
                        if posted >= total:
                            break
                except errors.ApiError as e:
                    key = f"learn:{getattr(e, 'code', type(e).__name__)}"
                    failures[key] = failures.get(key, 0) + 1
                    log.warning("%s seed %d: learning loop: %s", name, seed, e)
                finally:
                    no_plan += learner.no_plan
                    requests_guard += learner.no_plan + 1
            m = client.wait_for_model(posted, timeout=900)
            out["learning"] = {"posted": posted, "no_plan": no_plan, "failures": failures,
                               "seconds": time.monotonic() - t0,
                               "model_version": m.version, "n_trajectories": m.n_trajectories,
                               "fit_seconds": m.fit_seconds, "test_beta": m.test_beta,
                               "model_points_after_learning": dict(fns.points)}
            try:
                out["labels"] = client._request("GET", client._path("/labels")).json()
            except Exception as e:  # the labels are a record, not the measurement
                out["labels"] = repr(e)
            # The learned preconditions on the held-out points: how much each trusts.
            pts = (ts["held_s"], ts["held_a"])
            for model in COSTS:
                try:
                    pre = client.precondition(pts, model=model)
                    inside = np.asarray(pre.inside, dtype=bool)
                    out.setdefault("trusted_share", {})[model] = float(np.mean(inside))
                except Exception as e:
                    out.setdefault("trusted_share", {})[model] = repr(e)

            # ---- test plans
            out["plans"] = {}
            for arm, models in ARMS.items():
                rows = []
                p0 = dict(fns.points)
                for i, (s, g) in enumerate(ts["problems"]):
                    row: dict[str, Any] = {"problem": i}
                    t1 = time.monotonic()
                    try:
                        plan = client.plan(s, g, models=models, deadline_retries=0)
                    except errors.ApiError as e:
                        row.update(found=False, success=False,
                                   error=getattr(e, "code", type(e).__name__),
                                   seconds=time.monotonic() - t1)
                        rows.append(row)
                        continue
                    row["seconds"] = time.monotonic() - t1
                    row["search_cost"] = plan.cost()
                    row["model_calls"] = [{"model": c.model, "calls": c.calls, "cost": c.cost}
                                          for c in (plan.model_calls or [])]
                    row["found"] = bool(plan.found and plan.trajectory is not None)
                    row["success"] = False
                    if row["found"]:
                        actions = np.asarray(plan.trajectory.actions)
                        states = robot.execute(s, actions)
                        row["success"] = robot.at_goal(states[-1], g)
                        row["steps"] = len(actions)
                        row["step_models"] = list(plan.step_models or [])
                        row["step_cost"] = float(sum(COSTS[x] for x in row["step_models"]))
                    rows.append(row)
                found = [r for r in rows if r["found"]]
                costs = [r["search_cost"] for r in rows if r.get("search_cost") is not None]
                summ = {
                    "found": float(np.mean([r["found"] for r in rows])),
                    "success": float(np.mean([r["success"] for r in rows])),
                    "search_cost": float(np.mean(costs)) if costs else None,
                    "step_cost": float(np.mean([r["step_cost"] for r in found])) if found else None,
                    "steps": float(np.mean([r["steps"] for r in found])) if found else None,
                    "seconds_per_plan": float(np.mean([r["seconds"] for r in rows])),
                    "errors": sum(1 for r in rows if "error" in r),
                    "served_points": {k: fns.points[k] - p0[k] for k in fns.points},
                }
                # What the search asked the models point by point (a "call" of plan.cost() is
                # one batched request): points per plan, and weighted by the models' costs.
                summ["points_per_plan"] = {k: v / len(rows) for k, v in summ["served_points"].items()}
                summ["point_cost_per_plan"] = sum(COSTS[k] * v for k, v in summ["points_per_plan"].items())
                out["plans"][arm] = {"summary": summ, "problems": rows}
                log.info("%s seed %d arm %s: found %.2f success %.2f search cost %s step cost %s "
                         "(%.1f s/plan, %d errors)", name, seed, arm, summ["found"],
                         summ["success"], summ["search_cost"], summ["step_cost"],
                         summ["seconds_per_plan"], summ["errors"])
            out["http_statuses"] = dict(client.statuses)  # type: ignore[attr-defined]
        finally:
            server.close()
    out["served"] = {"points": fns.points, "seconds": fns.seconds}
    out["seconds"] = time.monotonic() - t_start
    return out


# --------------------------------------------------------------------------- summary


def mean_se(xs: list[float]) -> str:
    xs = [x for x in xs if x is not None and np.isfinite(x)]
    if not xs:
        return "–"
    m = float(np.mean(xs))
    if len(xs) < 2:
        return f"{m:.2f}" if abs(m) < 10 else f"{m:.0f}"
    se = float(np.std(xs, ddof=1) / np.sqrt(len(xs)))
    return f"{m:.2f} ± {se:.2f}" if abs(m) < 10 else f"{m:.0f} ± {se:.0f}"


def oracle_reference(robot: str, seed: int) -> dict[str, Any] | None:
    """run.py's reference run of the same (robot, seed), same test problems, if committed."""
    root = Path(__file__).parent / "results"
    for d in REFERENCE_DIRS:
        p = root / d / f"{robot}-references-{seed}.json"
        if p.exists():
            r = json.loads(p.read_text())
            o = r.get("oracle") or {}
            if "open_loop_success" in o:
                return {"dir": d, "plans_found": o.get("plans_found"),
                        "open_loop_success": o.get("open_loop_success")}
    return None


def write_summary(out: Path) -> None:
    runs = [json.loads(p.read_text()) for p in sorted(out.glob("*-several-*.json"))]
    runs = [r for r in runs if "plans" in r]
    lines = ["# Several models on the MuJoCo robots (pusher, base)", "",
             "Mean ± standard error over seeds (each seed: the mean over its test problems; "
             "step cost over found plans only). Success: open loop in MuJoCo.", ""]
    summary: dict[str, Any] = {}
    for robot in sorted({r["robot"] for r in runs}):
        rr = [r for r in runs if r["robot"] == robot]
        seeds = [r["seed"] for r in rr]
        sh = {k: [r["shares"][k] for r in rr] for k in
              ["domain_within_d_max", "sim_within_d_max", "both", "domain_only", "sim_only",
               "either", "ms_per_point_true", "ms_per_point_sim"]}
        lines += [f"## {robot} (seeds {seeds}, n = {len(rr)}; coarse sim: timestep × "
                  f"{rr[0]['coarse_sim']['timestep_factor']} = {rr[0]['coarse_sim']['timestep']*1000:.0f} ms)", "",
                  "Within `d_max` of MuJoCo on 400 uniform held-out state-actions per seed: "
                  f"domain {mean_se(sh['domain_within_d_max'])}, sim {mean_se(sh['sim_within_d_max'])}, "
                  f"both {mean_se(sh['both'])}, domain only {mean_se(sh['domain_only'])}, "
                  f"sim only {mean_se(sh['sim_only'])}, either {mean_se(sh['either'])}. "
                  f"ms per point: true {mean_se(sh['ms_per_point_true'])}, sim {mean_se(sh['ms_per_point_sim'])}.",
                  "", "| arm | found | success (open loop) | search cost | step cost | steps | point cost / plan | s / plan | errors | seeds |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        summary[robot] = {"seeds": seeds, "shares": sh, "arms": {}}
        for arm in ARMS:
            s = [r["plans"][arm]["summary"] for r in rr]
            col = {k: [x[k] for x in s] for k in
                   ["found", "success", "search_cost", "step_cost", "steps", "seconds_per_plan",
                    "point_cost_per_plan"]}
            summary[robot]["arms"][arm] = col
            lines.append(f"| {arm} | {mean_se(col['found'])} | {mean_se(col['success'])} | "
                         f"{mean_se(col['search_cost'])} | {mean_se(col['step_cost'])} | "
                         f"{mean_se(col['steps'])} | {mean_se(col['point_cost_per_plan'])} | {mean_se(col['seconds_per_plan'])} | "
                         f"{sum(x['errors'] for x in s)} | {len(rr)} |")
        refs = [oracle_reference(robot, sd) for sd in seeds]
        if any(refs):
            got = [(sd, x) for sd, x in zip(seeds, refs) if x]
            lines.append(f"| oracle (run.py's references, seeds {[sd for sd, _ in got]}, "
                         f"another binary) | {mean_se([x['plans_found'] for _, x in got])} | "
                         f"{mean_se([x['open_loop_success'] for _, x in got])} | – | – | – | – | – | – | {len(got)} |")
            summary[robot]["oracle"] = dict(got)
        walls = [r["seconds"] for r in rr]
        learn = [r["learning"]["seconds"] for r in rr]
        lines += ["", f"Wall time per seed {mean_se(walls)} s (learning {mean_se(learn)} s).", ""]
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    (out / "summary.json").write_text(json.dumps(bench.jsonable(summary), indent=1))


# --------------------------------------------------------------------------- main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--binary", required=True)
    ap.add_argument("--robots", default="pusher,base")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--batch", type=int, default=5)
    ap.add_argument("--test-problems", type=int, default=10)
    ap.add_argument("--held-out", type=int, default=400)
    ap.add_argument("--plan-seconds", type=float, default=45.0,
                    help="wall-clock limit of one plan's search (the server's --plan-timeout-ms)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--learn", choices=["domain", "all", "separate"], default="domain",
                    help="proposals with the lab model alone (the service's default), across "
                    "both models, or one model at a time in turn")
    ap.add_argument("--summary-only", action="store_true")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.summary_only:
        write_summary(args.out)
        return
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s",
                        handlers=[logging.StreamHandler(),
                                  logging.FileHandler(args.out / f"several-{args.robots.replace(',', '-')}.log")])
    logging.getLogger("httpx").setLevel(logging.WARNING)
    logging.getLogger("precond_client").setLevel(logging.WARNING)
    dbdir = Path(tempfile.mkdtemp(prefix="precond-several-db-"))
    log.info("databases in %s", dbdir)
    meta = {"command": " ".join(sys.argv), "binary": args.binary,
            "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "mujoco": mujoco.__version__, "numpy": np.__version__,
            "python": platform.python_version(), "costs": COSTS,
            "coarse_timestep_factor": COARSE_TIMESTEP_FACTOR, "plan_seconds": args.plan_seconds}
    (args.out / f"meta-{args.robots.replace(',', '-')}-{meta['started']}.json").write_text(json.dumps(meta, indent=1))
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for name in args.robots.split(","):
            path = args.out / f"{name}-several-{seed}.json"
            if path.exists():
                log.info("%s: already measured", path.name)
                continue
            t0 = time.monotonic()
            try:
                res = several_run(name, seed, args, dbdir)
            except Exception as e:
                log.error("%s seed %d failed: %s", name, seed, e)
                res = {"robot": name, "seed": seed, "error": repr(e),
                       "traceback": traceback.format_exc()}
            res["wall_seconds"] = time.monotonic() - t0
            path.write_text(json.dumps(bench.jsonable(res), indent=1))
            log.info("%s: %.0f s", path.name, res["wall_seconds"])
            write_summary(args.out)


if __name__ == "__main__":
    main()
