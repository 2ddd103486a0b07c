#!/usr/bin/env python3
"""A robot's learning loop against a deliberately overloaded server, for as long as it takes a
lab to notice: does the loop survive, and does it say what happened?

Starts BINARY with one planner slot, a short queue and a short planning deadline
(`--max-concurrent-plans 1 --max-queued-plans 2 --plan-timeout-ms PLAN_MS`), serves the robot's
model from Python (`serve_model`, as a lab would: "the puck moves by the action"), and runs
`Client.learn` on a custom 2-D pushing domain whose true world the model gets wrong (pushes
right of x = 0.5 go 70 % of the way; a box stops them) for MINUTES. Beside it a FLEET of
threads keep the server busy on experiments of their own: each asks for proposals (holding
the planner slot), posts random trajectories (triggering refits), asks the precondition of
20,000 points and forces refits, counting every answer's status. The loop's own log lines (what
it waits for, each retry, each skipped problem) go to standard error.

At the end it prints, and writes to OUT/overloaded_loop.json: the loop's counters (episodes,
posted, skipped for no plan / a deadline / other transient failures, abandoned), what the
server recorded (runs, refused proposals, model versions), the fleet's answers by status, and
whether the loop ever raised into the robot's script (it must not).

usage: scripts/overloaded_loop.py BINARY [--minutes 40] [--fleet 3] [--plan-ms 1500]
                                  [--out DIR] [--seed 0]
"""

import argparse
import collections
import json
import logging
import random
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from jsonhttp import call
from precond_client import Client, serve_model, spawn_server

D_MAX = 0.02
BOX = (np.array([0.25, 0.15]), np.array([0.4, 0.35]))


def f_hat(states: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """The robot's model: the puck moves by the action and stays on the table."""
    return np.clip(states + actions, 0.0, 1.0)


def true_step(s: np.ndarray, a: np.ndarray) -> np.ndarray:
    """The world: pushes right of x = 0.5 go 70 % of the way; the box stops the puck."""
    gain = 0.7 if s[0] > 0.5 else 1.0
    nxt = np.clip(s + gain * a, 0.0, 1.0)
    lo, hi = BOX
    if np.all((nxt > lo) & (nxt < hi)):
        return s.copy()
    return nxt


def problem(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A start and a goal 0.2 to 0.5 apart, off the box."""
    lo, hi = BOX
    while True:
        s, g = rng.uniform(0.05, 0.95, 2), rng.uniform(0.05, 0.95, 2)
        off = not np.all((s > lo) & (s < hi)) and not np.all((g > lo) & (g < hi))
        if off and 0.2 <= np.linalg.norm(g - s) <= 0.5:
            return s, g


def domain(model_url: str) -> dict:
    return {
        "kind": "custom",
        "state": {"names": ["x", "y"], "low": [0, 0], "high": [1, 1]},
        "action": {"names": ["dx", "dy"], "low": [-0.1, -0.1], "high": [0.1, 0.1]},
        "goal": {"radius": 0.05},
        "model": {"kind": "remote", "url": model_url, "timeout_ms": 10000},
    }


def raw(base: str, method: str, path: str, body: object = None,
        timeout: float = 120) -> tuple[int, dict]:
    """One request, no retries: the status (0 when the server could not be reached) and the
    JSON answer ({} when there is none)."""
    try:
        status, answer = call(base, method, path, body, timeout)
    except OSError:
        return 0, {}
    return status, answer if isinstance(answer, dict) else {}


def fleet_member(base: str, model_url: str, k: int, stop: threading.Event,
                 tally: collections.Counter, lock: threading.Lock) -> None:
    """Keeps the server busy on an experiment of its own until `stop`."""
    rnd = random.Random(1000 + k)
    status, created = call(
        base, "POST", "/v1/experiments",
        {"name": f"fleet {k}", "d_max": D_MAX, "domain": domain(model_url),
         "learning": {"batch_size": 3, "max_extensions": 20000, "n_candidates": 20}},
        timeout=60,
    )
    assert status == 201, (status, created)
    eid = created["id"]
    points = [{"s": [rnd.random(), rnd.random()], "a": [rnd.uniform(-0.1, 0.1), 0.0]}
              for _ in range(20000)]

    def count(what: str, status: int) -> None:
        with lock:
            tally[f"{what} {status}"] += 1

    while not stop.is_set():
        action = rnd.choice(["propose", "propose", "post", "query", "refit"])
        if action == "propose":
            s = [rnd.uniform(0.05, 0.95), rnd.uniform(0.05, 0.95)]
            g = [rnd.uniform(0.05, 0.95), rnd.uniform(0.05, 0.95)]
            status, proposal = raw(base, "POST", f"/v1/experiments/{eid}/proposals",
                                   {"start": s, "goal": g, "client_id": f"fleet-{k}"})
            count("proposal", status)
            if status == 201:
                # A fleet robot that gives its proposal up: the planner slot is what it costs.
                count("abandon", raw(
                    base, "POST",
                    f"/v1/experiments/{eid}/proposals/{proposal['id']}/abandon")[0])
        elif action == "post":
            s = np.array([rnd.uniform(0.05, 0.95), rnd.uniform(0.05, 0.95)])
            ts = []
            for _ in range(20):
                a = np.array([rnd.uniform(-0.1, 0.1), rnd.uniform(-0.1, 0.1)])
                n = true_step(s, a)
                ts.append({"s": s.tolist(), "a": a.tolist(), "s_next": n.tolist()})
                s = n
            count("trajectory", raw(base, "POST", f"/v1/experiments/{eid}/trajectories",
                                    {"transitions": ts})[0])
        elif action == "query":
            count("precondition", raw(base, "POST", f"/v1/experiments/{eid}/precondition",
                                      {"points": points})[0])
        else:
            count("refit", raw(base, "POST", f"/v1/experiments/{eid}/model/refit")[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("binary")
    ap.add_argument("--minutes", type=float, default=40.0)
    ap.add_argument("--fleet", type=int, default=3)
    ap.add_argument("--plan-ms", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="precond-overloaded-"))
    out.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s",
                        stream=sys.stderr)
    logging.getLogger("httpx").setLevel(logging.WARNING)
    rng = np.random.default_rng(args.seed)
    started = time.monotonic()
    raised = None
    with serve_model(f_hat, "127.0.0.1", 0, threadsafe=True) as model:
        db = out / "overloaded.db"
        proc, url = spawn_server(
            args.binary, db, "--allow-model-url", f"http://127.0.0.1:{model.port}/",
            "--max-concurrent-plans", "1", "--max-queued-plans", "2",
            "--plan-timeout-ms", str(args.plan_ms), log=str(out / "server.log"),
        )
        stop = threading.Event()
        tally: collections.Counter = collections.Counter()
        lock = threading.Lock()
        fleet = [threading.Thread(target=fleet_member,
                                  args=(url, model.url, k, stop, tally, lock), daemon=True)
                 for k in range(args.fleet)]
        try:
            client = Client(url, timeout=120, client_id="robot-1")
            client.wait_ready(30)
            client.create_experiment(
                name="overloaded loop", d_max=D_MAX, seed=args.seed,
                domain=domain(model.url),
                learning={"batch_size": 5, "iterations": 100_000, "n_candidates": 5,
                          "max_extensions": 1500},
            )
            for t in fleet:
                t.start()

            def problems():
                while time.monotonic() - started < args.minutes * 60:
                    yield problem(rng)

            learner = client.learn(problems(), progress_bar=False)
            try:
                for ep in learner:
                    states = [np.asarray(ep.start, dtype=float)]
                    for a in ep.actions:
                        states.append(true_step(states[-1], np.asarray(a, dtype=float)))
                    ep.post(np.array(states))
            except Exception as e:  # the loop must not raise into the robot's script
                raised = f"{type(e).__name__}: {e}"
            stop.set()
            for t in fleet:
                t.join(timeout=180)
            final = client.get_experiment()
            model_now = client.model()
            summary = {
                "minutes": round((time.monotonic() - started) / 60, 1),
                "plan_timeout_ms": args.plan_ms,
                "fleet": args.fleet,
                "raised_into_the_script": raised,
                "loop": {k: getattr(learner, k) for k in
                         ["episodes", "posted", "abandoned", "no_plan", "at_goal", "deadline",
                          "failed", "resumed"]},
                "skipped": collections.Counter(
                    str(getattr(s, "reason", s)) for s in getattr(learner, "skipped", [])
                ),
                "server": {"trajectories": final.n_trajectories, "iteration": final.iteration,
                           "refused_proposals": final.n_refused,
                           "model_version": model_now.version, "n_train": model_now.n_train},
                "model_calls": model.calls,
                "fleet_answers": dict(sorted(tally.items())),
            }
        finally:
            stop.set()
            proc.terminate()
            proc.wait(timeout=60)
    (out / "overloaded_loop.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    print(f"written to {out / 'overloaded_loop.json'}; server log {out / 'server.log'}")
    return 0 if raised is None else 1


if __name__ == "__main__":
    sys.exit(main())
