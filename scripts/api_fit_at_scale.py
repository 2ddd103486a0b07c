#!/usr/bin/env python3
"""A fit on many transitions and a batched precondition query, through the API with default
settings: what a lab that imports a large log sees.

Starts BINARY on a fresh database, creates a kinematic experiment (default settings), posts N
transitions of a robot whose pushes go 80 % of the way in parts of 10,000, forces a refit and
waits for the version (the refit answers 202 after the planning deadline and goes on), then asks
the precondition of Q points in one POST, REPEAT times. Prints the fit's wall time, its phases
(the model's `selection`) and the query's points per second, with Python's JSON encoding and
decoding (`points_per_s`) and for the HTTP exchange alone (`points_per_s_exchange`).

usage: scripts/api_fit_at_scale.py BINARY [N] [Q] [REPEAT] [--mde KEY=VALUE ...]

The robot's tolerance is d_max = 0.01, so its precondition is a real region: every push is
trusted left of x = 0.5, only the short ones (|a| < 0.05) right of it. The query's points are
fresh ones, so the answer is also a held-out judgement: the script prints the true-positive
rate (trusted among the truly safe) and the false trust (trusted among the unsafe).

After the first fit it posts one more trajectory of 1,000 transitions and refits again (a warm
refit: the kernel and label cap kept). Q points go in one POST (the default 4 MiB body limit
holds about 60,000 of them).
"""

import argparse
import json
import math
import random
import socket
import subprocess
import tempfile
import time
import urllib.request

from jsonhttp import call


GAIN = 0.8
D_MAX = 0.01


def true_deviation(s: list, a: list) -> float:
    """How far the kinematic prediction s + a misses the robot's move."""
    gain = GAIN if s[0] > 0.5 else 1.0
    return (1.0 - gain) * math.hypot(a[0], a[1])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def post_transitions(base: str, eid: int, rng: random.Random, k: int) -> None:
    """Posts one trajectory of `k` transitions of the robot whose pushes go 80 % of the way
    right of x = 0.5."""
    ts = []
    for _ in range(k):
        s = [rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.9)]
        a = [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)]
        gain = GAIN if s[0] > 0.5 else 1.0
        ts.append({"s": s, "a": a, "s_next": [s[0] + gain * a[0], s[1] + gain * a[1]]})
    st, body = call(base, "POST", f"/v1/experiments/{eid}/trajectories", {"transitions": ts})
    assert st == 201, body


def refit_until(base: str, eid: int, version: int) -> dict:
    """Forces a refit (answered 202 past the planning deadline; it goes on) and waits until
    the answering model is `version`; returns it."""
    st, body = call(base, "POST", f"/v1/experiments/{eid}/model/refit", {})
    assert st in (200, 202), body
    while True:
        st, model = call(base, "GET", f"/v1/experiments/{eid}/model")
        if model["version"] >= version:
            return model
        time.sleep(0.5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("binary")
    ap.add_argument("n", type=int, nargs="?", default=100_000)
    ap.add_argument("q", type=int, nargs="?", default=40_000)
    ap.add_argument("repeat", type=int, nargs="?", default=3)
    ap.add_argument("--mde", action="append", default=[], metavar="KEY=VALUE",
                    help="an mde setting (a JSON value), e.g. --mde selection_subset=2000")
    args = ap.parse_args()
    binary, n, q, repeat = args.binary, args.n, args.q, args.repeat
    mde = {}
    for kv in args.mde:
        key, value = kv.split("=", 1)
        try:
            mde[key] = json.loads(value)
        except json.JSONDecodeError:
            mde[key] = value
    port = free_port()
    db = tempfile.mkdtemp() + "/scale.db"
    server = subprocess.Popen(
        [binary, "serve", "--addr", f"127.0.0.1:{port}", "--database-url", db],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}"
    try:
        for _ in range(100):
            try:
                if call(base, "GET", "/readyz")[0] == 200:
                    break
            except OSError:
                time.sleep(0.1)
        status, exp = call(
            base, "POST", "/v1/experiments",
            {"domain": {"kind": "kinematic"}, "d_max": D_MAX, "mde": mde,
             "learning": {"batch_size": 10000}},
        )
        assert status == 201, exp
        eid = exp["id"]
        rng = random.Random(0)
        t0 = time.monotonic()
        for part in range(0, n, 10_000):
            post_transitions(base, eid, rng, min(10_000, n - part))
        posted = time.monotonic() - t0
        t0 = time.monotonic()
        model = refit_until(base, eid, 1)
        fit_wall = time.monotonic() - t0
        print(json.dumps({"fit_wall_s": round(fit_wall, 1), "posting_s": round(posted, 1),
                          "estimator": model["estimator"], "fit_seconds": model["fit_seconds"],
                          "selection": model.get("selection")}, indent=1), flush=True)
        # One more batch and a refit: a warm one (the kept kernel and cap, no selection).
        post_transitions(base, eid, rng, 1000)
        t0 = time.monotonic()
        again = refit_until(base, eid, 2)
        print(json.dumps({"warm_refit_wall_s": round(time.monotonic() - t0, 1),
                          "fit_seconds": again["fit_seconds"],
                          "reason": again["selection"]["reason"],
                          "phases": again["selection"]["phases"]}, indent=1), flush=True)
        points = []
        for _ in range(q):
            s = [rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.9)]
            points.append({"s": s, "a": [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)]})
        rates, exchange_rates = [], []
        for _ in range(repeat):
            t0 = time.monotonic()
            body = json.dumps({"points": points}).encode()
            req = urllib.request.Request(
                base + f"/v1/experiments/{eid}/precondition", data=body, method="POST"
            )
            req.add_header("Content-Type", "application/json")
            t1 = time.monotonic()
            with urllib.request.urlopen(req, timeout=600) as r:
                st, raw = r.status, r.read()
            t2 = time.monotonic()
            ans = json.loads(raw)
            t3 = time.monotonic()
            assert st == 200 and len(ans["results"]) == q, st
            # With Python's json.dumps and json.loads (what a script sees), and the HTTP
            # exchange alone (what the server answers).
            rates.append(q / (t3 - t0))
            exchange_rates.append(q / (t2 - t1))
        safe = [true_deviation(p["s"], p["a"]) < D_MAX for p in points]
        inside = [r["inside"] for r in ans["results"]]
        n_safe = sum(safe)
        tpr = sum(i and t for i, t in zip(inside, safe)) / max(n_safe, 1)
        false_trust = sum(i and not t for i, t in zip(inside, safe)) / max(q - n_safe, 1)
        print(
            json.dumps(
                {
                    "transitions": n,
                    "posting_s": round(posted, 1),
                    "fit_wall_s": round(fit_wall, 1),
                    "estimator": model["estimator"],
                    "fit_seconds": model["fit_seconds"],
                    "selection": model.get("selection"),
                    "kernel": (model.get("hyperparameters") or {}).get("kernel"),
                    "label_cap": model.get("label_cap"),
                    "test_beta": model.get("test_beta"),
                    "query_points": q,
                    "points_per_s": [round(r) for r in rates],
                    "points_per_s_exchange": [round(r) for r in exchange_rates],
                    "held_out": {"tpr": round(tpr, 4), "false_trust": round(false_trust, 4),
                                 "safe": n_safe, "unsafe": q - n_safe},
                    "mde": mde,
                },
                indent=1,
            )
        )
    finally:
        server.terminate()
        server.wait()


if __name__ == "__main__":
    main()
