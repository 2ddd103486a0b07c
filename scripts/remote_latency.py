#!/usr/bin/env python3
"""A proposal's latency when the robot's model is a Python `serve_model`, as a lab runs it.

Starts BINARY on a fresh SQLite file (default limits: one planner slot per core, 30 s
deadline), serves the robot's model from this process ("the puck moves by the action", the
2-D pushing domain of `scripts/overloaded_loop.py`, whose true world stops pushes at a box and
shortens them right of x = 0.5), and for each SIZE in `--sizes`: posts random 10-step
trajectories of the true world until the experiment holds SIZE transitions, forces a refit and
waits for it, then asks PROPOSALS proposals for seeded random problems (each abandoned at
once) and times each over HTTP, idle. Beside the latencies it reports where the time went on
the model's side: the calls the service made, their points, the seconds inside the model
function and the seconds this process spent decoding and encoding their JSON (measured by
re-encoding bodies of the same sizes).

Prints one JSON line per size: median, p90, p99 and max latency (s), extensions, model calls
and points per proposal, and the shares of the model's side.

`--encoding json` makes the model server offer JSON only (the protocol of a model without the
handshake); the default, `f64le`, is what `serve_model` offers: raw little-endian arrays.

usage: scripts/remote_latency.py BINARY [--sizes 500,2000] [--proposals 40] [--seed 0]
                                 [--encoding f64le|json]
"""

import argparse
import json
import random
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from jsonhttp import call
from overloaded_loop import D_MAX, domain, f_hat, true_step
from precond_client import serve_model, spawn_server

class Timed:
    """The model function, counting its calls, their sizes and the seconds inside it."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.sizes: list[int] = []
        self.seconds = 0.0

    def __call__(self, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        out = f_hat(states, actions)
        with self.lock:
            self.seconds += time.perf_counter() - t0
            self.sizes.append(len(states))
        return out

    def take(self) -> tuple[list[int], float]:
        with self.lock:
            sizes, seconds = self.sizes, self.seconds
            self.sizes, self.seconds = [], 0.0
        return sizes, seconds


def json_seconds(sizes: list[int], dim: int) -> float:
    """Seconds this process spends parsing the requests and writing the answers of calls of
    these sizes (measured on synthetic bodies, each size once, then summed per call)."""
    rng = np.random.default_rng(0)
    cost: dict[int, float] = {}
    for n in set(sizes):
        body = json.dumps({"states": rng.random((n, dim)).tolist(),
                           "actions": rng.random((n, dim)).tolist()}).encode()
        t0 = time.perf_counter()
        reps = max(1, 2000 // max(n, 1))
        for _ in range(reps):
            parsed = json.loads(body)
            s = np.asarray(parsed["states"], dtype=np.float64)
            json.dumps({"next_states": s.tolist()}).encode()
        cost[n] = (time.perf_counter() - t0) / reps
    return sum(cost[n] for n in sizes)


def quantile(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("binary")
    ap.add_argument("--sizes", default="500,2000")
    ap.add_argument("--proposals", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--encoding", choices=["f64le", "json"], default="f64le")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    model = Timed()
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory(prefix="precond-remote-latency-") as tmp, \
            serve_model(model, "127.0.0.1", 0, binary=args.encoding == "f64le") as served:
        proc, url = spawn_server(args.binary, Path(tmp) / "latency.db",
                                 "--allow-model-url", f"http://127.0.0.1:{served.port}/")
        try:
            return measure(args, url, served.url, model, sizes, rng)
        finally:
            proc.terminate()
            proc.wait()


def measure(args: argparse.Namespace, url: str, model_url: str, model: Timed,
            sizes: list[int], rng: np.random.Generator) -> int:
    status, exp = call(url, "POST", "/v1/experiments",
                       {"name": "remote latency", "d_max": D_MAX, "seed": args.seed,
                        "domain": domain(model_url), "learning": {"batch_size": 5}})
    assert status == 201, exp
    eid = exp["id"]
    stored = 0
    for size in sizes:
        while stored < size:
            s = rng.uniform(0.05, 0.95, 2)
            ts = []
            for _ in range(min(10, size - stored)):
                a = rng.uniform(-0.1, 0.1, 2)
                nxt = true_step(s, a)
                ts.append({"s": s.tolist(), "a": a.tolist(), "s_next": nxt.tolist()})
                s = nxt
            status, body = call(url, "POST", f"/v1/experiments/{eid}/trajectories",
                                {"transitions": ts})
            assert status == 201, body
            stored += len(ts)
        t0 = time.monotonic()
        status, body = call(url, "POST", f"/v1/experiments/{eid}/model/refit", {}, timeout=900)
        assert status in (200, 202), body
        while call(url, "GET", f"/v1/experiments/{eid}/model")[1]["n_train"] < size:
            time.sleep(0.5)
        fit_s = time.monotonic() - t0
        model.take()
        pr = random.Random(args.seed * 1000 + size)
        latencies, extensions, calls, points, refused = [], [], [], [], 0
        model_s = json_s = 0.0
        for _ in range(args.proposals):
            start = [pr.uniform(0.05, 0.95), pr.uniform(0.05, 0.95)]
            goal = [pr.uniform(0.05, 0.95), pr.uniform(0.05, 0.95)]
            t0 = time.perf_counter()
            status, p = call(url, "POST", f"/v1/experiments/{eid}/proposals",
                             {"start": start, "goal": goal, "client_id": "latency"},
                             timeout=120)
            latencies.append(time.perf_counter() - t0)
            sizes_k, seconds_k = model.take()
            calls.append(len(sizes_k))
            points.append(sum(sizes_k))
            model_s += seconds_k
            if args.encoding == "json":
                json_s += json_seconds(sizes_k, 2)
            if status == 201:
                extensions.append(p["extensions"])
                call(url, "POST", f"/v1/experiments/{eid}/proposals/{p['id']}/abandon")
            else:
                refused += 1
        total = sum(latencies)
        print(json.dumps({
            "encoding": args.encoding, "transitions": size, "fit_s": round(fit_s, 1),
            "proposals": args.proposals, "refused": refused,
            "median_s": round(statistics.median(latencies), 3),
            "p90_s": round(quantile(latencies, 0.9), 3),
            "p99_s": round(quantile(latencies, 0.99), 3),
            "max_s": round(max(latencies), 3),
            "extensions_median": statistics.median(extensions) if extensions else None,
            "model_calls_median": statistics.median(calls),
            "model_points_median": statistics.median(points),
            "share_in_model_fn": round(model_s / total, 3),
            "share_in_python_json": round(json_s / total, 3),
        }), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
