"""The robot bench: precond on MuJoCo robots nobody designed features for, declared as a lab would.

For each robot and seed: fixed test problems and held-out state-actions (true deviations from
MuJoCo); the references (oracle: the service's planner over the true precondition; baseline:
the model's own plan), and for each preset a learning run of the paper's protocol (``active``,
batches of 5, ``learning.iterations`` trajectories batches, everything else at the server's
defaults), evaluated at every iteration (precondition against the truth) and at the last (test
plans open and closed loop, unsafe planned steps). Every run spawns its own server over its own
database. One JSON per (robot, preset, seed) and per (robot, seed) for the references, then
``summary.md`` / ``summary.json``.

    python bench/robots/run.py --binary /work/bin/precond-base --robots arm,base,pusher,arm7 \\
        --seeds 5 --iterations 10 --presets default,paper --out DIR
    python bench/robots/run.py --binary /work/bin/precond-base --quick --out DIR   # smoke test
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import platform
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from precond_client import Client, errors, serve_model, spawn_server

sys.path.insert(0, str(Path(__file__).parent))

import evaluate as ev  # noqa: E402
import summary  # noqa: E402
from references import REFERENCE_BETA, ModelFns  # noqa: E402
from robot import Array, Robot  # noqa: E402

log = logging.getLogger("bench")


def robot_class(name: str) -> type[Robot]:
    if name == "arm":
        from arm import Arm
        return Arm
    if name == "base":
        from base import Base
        return Base
    if name == "base_theta":
        from base import BaseTheta
        return BaseTheta
    if name == "pusher":
        from pusher import Pusher
        return Pusher
    if name == "arm7":
        from arm7 import Arm7
        return Arm7
    raise SystemExit(f"unknown robot {name!r} (arm, base, base_theta, pusher, arm7)")


# --------------------------------------------------------------------------- the fixed test set


def test_set(robot: Robot, seed: int, n_problems: int, n_held: int) -> dict[str, Any]:
    """The seed's test problems and held-out state-actions with their true deviations: the same
    for every column of the seed."""
    rng = np.random.default_rng([seed, 7])
    problems = [robot.sample_problem(rng) for _ in range(n_problems)]
    held_s = np.array([robot.sample_state(rng) for _ in range(n_held)])
    held_a = np.array([robot.sample_action(rng) for _ in range(n_held)])
    held_dev = robot.true_deviation(held_s, held_a)
    return {"problems": problems, "held_s": held_s, "held_a": held_a, "held_dev": held_dev}


def jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return x


class Server:
    """A precond server over its own database, allowing one model server's URL prefix."""

    def __init__(self, binary: str, db: Path, ports: list[int], extra: list[str]) -> None:
        args: list[str] = []
        for p in ports:
            args += ["--allow-model-url", f"http://127.0.0.1:{p}/"]
        # The server's own log beside its database: a refused fit or a slow model call.
        self.proc, self.url = spawn_server(
            binary, db, *args, *extra, log=db.with_suffix(".log")
        )

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except Exception:
            self.proc.kill()
            self.proc.wait()


def count_statuses(client: Client) -> None:
    """Counts every HTTP answer by route and status (``POST proposals 503``), retried ones
    included: the client retries 5xx answers, so its exceptions alone would hide them."""
    import re
    from collections import Counter

    statuses: Counter[str] = Counter()
    client.statuses = statuses  # type: ignore[attr-defined]

    def hook(response: Any) -> None:
        path = re.sub(r"/\d+", "", response.request.url.path).replace("/v1/experiments", "")
        if response.status_code >= 400 or path.endswith(("/plans", "/proposals")):
            statuses[f"{response.request.method} {path or '/'} {response.status_code}"] += 1

    client._http.event_hooks["response"].append(hook)


def learning_settings(args: argparse.Namespace, preset: str) -> dict[str, Any]:
    return {"preset": preset, "batch_size": args.batch, "iterations": args.iterations}


# --------------------------------------------------------------------------- references


def reference_run(robot: Robot, seed: int, ts: dict[str, Any], args: argparse.Namespace,
                  dbdir: Path) -> dict[str, Any]:
    """Oracle and baseline columns for one (robot, seed)."""
    fns = ModelFns(robot)
    out: dict[str, Any] = {"robot": robot.name, "seed": seed, "kind": "references"}
    with serve_model(fns.oracle, "127.0.0.1", 0, path="/oracle") as om, \
            serve_model(fns.lab, "127.0.0.1", 0, path="/lab") as lm:
        # The oracle simulates every point the planner asks about: give its searches time.
        # The oracle simulates every point the planner asks about, so its searches take longer
        # than the learned column's; they get --reference-plan-seconds each (no retry), and a
        # search cut by it counts as "no plan" (reported as plan:deadline_exceeded).
        limit_ms = int(args.reference_plan_seconds * 1000)
        server = Server(args.binary, dbdir / f"{robot.name}-references-{seed}.db",
                        [om.port, lm.port],
                        ["--plan-timeout-ms", str(limit_ms), "--max-model-timeout-ms", str(limit_ms)])
        try:
            client = Client(server.url, timeout=args.reference_plan_seconds + 60,
                            client_id=f"bench-{robot.name}", retries=0)
            count_statuses(client)
            client.wait_ready(30)
            for col, model_url, timeout_ms in [("oracle", om.url, limit_ms), ("baseline", lm.url, None)]:
                domain = robot.domain(model_url)
                if timeout_ms is not None:
                    domain["model"]["timeout_ms"] = timeout_ms
                client.create_experiment(
                    name=f"{robot.name} {col} seed {seed}", d_max=robot.d_max, seed=seed,
                    domain=domain, learning=learning_settings(args, "default"))
                failures = ev.Failures()
                timings: list[float] = []
                sim0 = fns.simulated
                t0 = time.monotonic()
                inner = ev.service_planner(client, failures, beta=REFERENCE_BETA, timings=timings,
                                           max_extensions=args.reference_max_extensions)

                def planner(start: Array, goal: Array) -> ev.Planned | None:
                    fns.deadline = time.monotonic() + args.reference_plan_seconds
                    try:
                        return inner(start, goal)
                    finally:
                        fns.deadline = time.monotonic()  # what still arrives is stale

                res = ev.test_plans(robot, planner, ts["problems"], closed=True,
                                    closed_seconds=args.reference_closed_loop_seconds)
                res["closed_loop_out_of_time"] = sum(
                    1 for p in res["problems"] if p.get("closed_loop", {}).get("outcome") == "time")
                res["failures"] = failures.as_dict()
                res["plan_seconds"] = timings
                res["seconds"] = time.monotonic() - t0
                res["simulated_points"] = fns.simulated - sim0
                res["http_statuses"] = dict(client.statuses)  # type: ignore[attr-defined]
                client.statuses.clear()  # type: ignore[attr-defined]
                out[col] = res
                log.info("%s seed %d %s: plans %.2f open %.2f closed %.2f (%.0f s)", robot.name,
                         seed, col, res["plans_found"], res["open_loop_success"],
                         res["closed_loop_success"], res["seconds"])
        finally:
            server.close()
    out["model_calls"] = fns.stats()
    return out


# --------------------------------------------------------------------------- learning runs


def learning_run(robot: Robot, preset: str, seed: int, ts: dict[str, Any],
                 args: argparse.Namespace, dbdir: Path) -> dict[str, Any]:
    fns = ModelFns(robot)
    out: dict[str, Any] = {"robot": robot.name, "preset": preset, "seed": seed, "kind": "learning"}
    failures = ev.Failures()
    t_start = time.monotonic()
    with serve_model(fns.lab, "127.0.0.1", 0) as model:
        server = Server(args.binary, dbdir / f"{robot.name}-{preset}-{seed}.db", [model.port], [])
        try:
            client = Client(server.url, timeout=120, client_id=f"bench-{robot.name}", retries=1)
            count_statuses(client)
            client.wait_ready(30)
            exp = client.create_experiment(
                name=f"{robot.name} {preset} seed {seed}", d_max=robot.d_max, seed=seed,
                domain=robot.domain(model.url), learning=learning_settings(args, preset))
            out["settings"] = {"domain": exp.domain, "d_max": exp.d_max, "mde": exp.mde,
                               "learning": exp.learning, "features": exp.feature_names}

            proposal_seconds: list[float] = []
            propose = client.propose

            def timed_propose(*a: Any, **k: Any) -> Any:
                t0 = time.monotonic()
                try:
                    return propose(*a, **k)
                finally:
                    proposal_seconds.append(time.monotonic() - t0)

            client.propose = timed_propose  # type: ignore[method-assign]

            rng = np.random.default_rng([seed, 1])

            def problems():  # endless; a problem with no proposal is skipped
                while True:
                    yield robot.sample_problem(rng)

            total = args.iterations * args.batch
            posted = 0
            counters = {"no_plan": 0, "at_goal": 0, "abandoned": 0, "deviations_over_dmax": 0,
                        "transitions": 0, "relaxed": 0}
            curve: list[dict[str, Any]] = []
            max_requests = total * args.max_requests_per_trajectory
            final: dict[str, Any] | None = None

            def evaluate(iteration: int, last: bool = False) -> dict[str, Any]:
                m = client.wait_for_model(iteration * args.batch, timeout=600)
                row: dict[str, Any] = {"iteration": iteration, "n_trajectories": m.n_trajectories,
                                       "model_version": m.version, "fit_seconds": m.fit_seconds,
                                       "n_train": m.n_train, "test_beta": m.test_beta,
                                       "label_cap": m.label_cap, "estimator": m.estimator}
                row.update(ev.precondition_quality(client, ts["held_s"], ts["held_a"],
                                                   ts["held_dev"], robot.d_max))
                last = last or iteration == args.iterations
                if last or args.curve_plans:
                    t0 = time.monotonic()
                    res = ev.test_plans(robot, ev.service_planner(client, failures),
                                        ts["problems"], closed=last)
                    res["seconds"] = time.monotonic() - t0
                    row.update(res)
                log.info("%s %s seed %d iteration %d: TPR %.2f TNR %.2f sigma %.3f%s", robot.name,
                         preset, seed, iteration, row["tpr"] or 0, row["tnr"] or 0,
                         row["median_sigma"],
                         f" plans {row['plans_found']:.2f} open {row['open_loop_success']:.2f}"
                         if "plans_found" in row else "")
                return row

            while posted < total and len(proposal_seconds) < max_requests:
                learner = client.learn(problems(), client_id=f"bench-{robot.name}",
                                       model_timeout=600)
                try:
                    for ep in learner:
                        if ep.proposal.relaxed_from_beta is not None:
                            counters["relaxed"] += 1
                        observed = robot.execute(ep.start, ep.actions)
                        created = ep.post(observed)
                        posted += 1
                        counters["transitions"] += int(created.n_transitions)
                        counters["deviations_over_dmax"] += int(np.sum(created.deviations >= robot.d_max))
                        if created.n_trajectories % args.batch == 0:
                            curve.append(evaluate(created.n_trajectories // args.batch))
                        if posted >= total or len(proposal_seconds) >= max_requests:
                            break
                except errors.ApiError as e:
                    failures.add("proposal", e)
                    log.warning("%s %s seed %d: learning loop: %s", robot.name, preset, seed, e)
                finally:
                    counters["no_plan"] += learner.no_plan
                    counters["at_goal"] += learner.at_goal
                    counters["abandoned"] += learner.abandoned
            if posted < total:
                log.warning("%s %s seed %d: stopped after %d proposal requests with %d of %d "
                            "trajectories", robot.name, preset, seed, len(proposal_seconds),
                            posted, total)
            if curve and curve[-1]["iteration"] == args.iterations:
                final = curve[-1]
            elif posted:
                # The loop stalled: judge what was learnt as the last iteration would be.
                final = evaluate(args.iterations if posted >= total else max(1, posted // args.batch),
                                 last=True)
                final["stalled"] = True
                curve.append(final)
            exp_now = client.get_experiment()
            out.update({
                "posted": posted,
                "proposal_requests": len(proposal_seconds),
                "proposal_seconds": proposal_seconds,
                "fit_seconds": [r["fit_seconds"] for r in curve if r.get("fit_seconds") is not None],
                "counters": counters,
                "refused_on_server": exp_now.n_refused,
                "http_statuses": dict(client.statuses),  # type: ignore[attr-defined]
                "curve": curve,
                "final": final,
            })
        finally:
            server.close()
    out["failures"] = failures.as_dict()
    out["model_calls"] = fns.stats()
    out["seconds"] = time.monotonic() - t_start
    return out


# --------------------------------------------------------------------------- main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--binary", required=True, help="the precond server binary to measure")
    ap.add_argument("--binary-commit", default=None, help="its commit, for the record")
    ap.add_argument("--robots", default="arm,base,pusher,arm7")
    ap.add_argument("--seeds", type=int, default=5, help="seeds 0 .. N-1")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--batch", type=int, default=5)
    ap.add_argument("--presets", default="default,paper")
    ap.add_argument("--test-problems", type=int, default=10)
    ap.add_argument("--held-out", type=int, default=400)
    ap.add_argument("--curve-plans", action="store_true",
                    help="also plan the test problems (open loop) at every iteration")
    ap.add_argument("--no-references", action="store_true")
    ap.add_argument("--reference-plan-seconds", type=float, default=90.0,
                    help="wall-clock limit of one reference plan (the oracle simulates each point)")
    ap.add_argument("--reference-closed-loop-seconds", type=float, default=150.0,
                    help="wall-clock budget of one reference closed-loop attempt: no re-plan "
                         "starts after it (outcome 'time', counted as a failure)")
    ap.add_argument("--max-requests-per-trajectory", type=int, default=4,
                    help="a learning run stops after this many proposal requests per planned "
                         "trajectory (no_plan answers repeat on a stuck run)")
    ap.add_argument("--order", choices=["seeds", "first-preset"], default="seeds",
                    help="seeds: seed by seed, every preset, the references of the first "
                         "--reference-seeds-early seeds after them and the others at the end; "
                         "first-preset: the first preset and the references seed by seed, then "
                         "the other presets (an interrupted bench has whole seeds of them)")
    ap.add_argument("--reference-seeds-early", type=int, default=2,
                    help="with --order seeds: run the references of the first N seeds right "
                         "after their learning runs, the others after every learning run")
    ap.add_argument("--reference-max-extensions", type=int, default=None,
                    help="extension budget of the references' plans (default: the server's, as "
                         "the learned column's)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: 1 seed, 3 iterations, 4 test problems, 100 held out")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.quick:
        args.seeds, args.iterations, args.test_problems, args.held_out = 1, 3, 4, 100
    if args.out is None:
        args.out = Path(tempfile.mkdtemp(prefix="precond-robot-bench-"))
    args.out.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s",
                        handlers=[logging.StreamHandler(),
                                  logging.FileHandler(args.out / "bench.log")])
    logging.getLogger("httpx").setLevel(logging.WARNING)
    logging.getLogger("precond_client").setLevel(logging.WARNING)
    dbdir = Path(tempfile.mkdtemp(prefix="precond-robot-bench-db-"))
    meta = {
        "command": " ".join(sys.argv),
        "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "binary": args.binary, "binary_commit": args.binary_commit,
        "mujoco": mujoco.__version__, "numpy": np.__version__, "python": platform.python_version(),
        "iterations": args.iterations, "batch": args.batch, "test_problems": args.test_problems,
        "held_out": args.held_out, "closed_loop_budget": ev.CLOSED_LOOP_BUDGET,
        "reference_beta": REFERENCE_BETA,
        "reference_max_extensions": args.reference_max_extensions,
        "reference_plan_seconds": args.reference_plan_seconds,
        "reference_closed_loop_seconds": args.reference_closed_loop_seconds,
        "max_requests_per_trajectory": args.max_requests_per_trajectory,
    }
    (args.out / "meta.json").write_text(json.dumps(meta, indent=1))
    presets = [p for p in args.presets.split(",") if p]
    robots: dict[str, Robot] = {}
    for name in args.robots.split(","):
        robot = robots[name] = robot_class(name)()
        (args.out / f"{name}-robot.json").write_text(json.dumps(jsonable({
            "name": robot.name, "description": robot.description, "state": robot.state_names,
            "state_low": robot.state_low, "state_high": robot.state_high,
            "action": robot.action_names, "action_low": robot.action_low,
            "action_high": robot.action_high, "d_max": robot.d_max,
            "distance_weights": robot.distance_weights, "goal_components": robot.goal_components,
            "goal_radius": robot.goal_radius, "problem_distance": robot.problem_distance,
            "parameters": robot.parameters()}), indent=1))
    # Seed-major, all learning runs before the references: an interrupted bench has whole
    # seeds of the learned columns (what the bench is for), and references for the first seeds.
    t0 = time.monotonic()
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    order: list[tuple[str, list[Any], int]] = []
    if args.order == "seeds":
        # Seed by seed, every preset; the references of the first seeds right after them.
        early = seeds[: args.reference_seeds_early]
        for seed in seeds:
            order.append(("learning", presets, seed))
            if seed in early and not args.no_references:
                order.append(("references", [None], seed))
        if not args.no_references:
            order += [("references", [None], seed) for seed in seeds if seed not in early]
    else:
        # The first preset and the references seed by seed, then the other presets.
        for seed in seeds:
            order.append(("learning", presets[:1], seed))
            if not args.no_references:
                order.append(("references", [None], seed))
        order += [("learning", presets[1:], seed) for seed in seeds]
    for kind, variants, seed in order:
        if True:
            for name, robot in robots.items():
                ts = test_set(robot, seed, args.test_problems, args.held_out)
                truth = {"truly_safe_share": float(np.mean(ts["held_dev"] < robot.d_max)),
                         "held_out_deviation_quantiles":
                             np.quantile(ts["held_dev"], [0.1, 0.25, 0.5, 0.75, 0.9])}
                for preset in variants:
                    tag = f"{name}-{preset or 'references'}-{seed}"
                    path = args.out / f"{tag}.json"
                    if path.exists():
                        log.info("%s: already measured", tag)
                        continue
                    t1 = time.monotonic()
                    try:
                        if kind == "references":
                            res = reference_run(robot, seed, ts, args, dbdir)
                        else:
                            res = learning_run(robot, preset, seed, ts, args, dbdir)
                    except Exception as e:  # record and go on with the next run
                        log.error("%s failed: %s", tag, e)
                        res = {"robot": name, "preset": preset, "seed": seed, "kind": kind,
                               "error": repr(e), "traceback": traceback.format_exc()}
                    res.update(truth)
                    res["wall_seconds"] = time.monotonic() - t1
                    path.write_text(json.dumps(jsonable(res), indent=1))
                    log.info("%s: %.0f s (total %.0f s)", tag, res["wall_seconds"],
                             time.monotonic() - t0)
            summary.write(args.out)
    log.info("done in %.0f s; %s", time.monotonic() - t0, args.out / "summary.md")


if __name__ == "__main__":
    main()
