#!/usr/bin/env python3
"""One proposal's latency over HTTP on a continuous experiment whose MDE holds 1000
transitions (by default), for an acquisition: starts `BINARY serve` on 127.0.0.1:PORT over a fresh SQLite
file, creates a `kinematic` experiment, posts 200 (TRAJECTORIES) five-step trajectories of random moves (the
model is wrong right of x = 0.5, where x-moves fall 30 % short), refits, then times nine
proposals from [0.1, 0.1] to [0.9, 0.9] (each abandoned) and prints the median.

usage: scripts/proposal_latency.py BINARY PORT ACQUISITION [ESTIMATOR] [TRAJECTORIES]
(e.g. lcb, spread; exact, sparse or auto, default auto; 200 five-step trajectories by default)
"""

import os
import random
import statistics
import subprocess
import sys
import tempfile
import time

import jsonhttp

binary, port, acquisition = sys.argv[1], int(sys.argv[2]), sys.argv[3]
estimator = sys.argv[4] if len(sys.argv) > 4 else "auto"
n_traj = int(sys.argv[5]) if len(sys.argv) > 5 else 200
db = os.path.join(tempfile.mkdtemp(prefix="precond-latency-"), "precond.db")
proc = subprocess.Popen(
    [binary, "serve", "--addr", f"127.0.0.1:{port}", "--database-url", db],
    stdout=subprocess.DEVNULL,
    stderr=subprocess.DEVNULL,
)
base = f"http://127.0.0.1:{port}"


def call(method, path, body=None):
    status, answer = jsonhttp.call(base, method, path, body)
    if status >= 400:
        raise RuntimeError(f"{method} {path}: {status} {answer}")
    return answer


try:
    for _ in range(100):
        try:
            call("GET", "/healthz")
            break
        except OSError:
            time.sleep(0.1)
    learning = {"batch_size": 10_000, "acquisition": acquisition}
    settings = {"domain": {"kind": "kinematic"}, "learning": learning}
    settings["mde"] = {"estimator": estimator}
    eid = call("POST", "/v1/experiments", settings)["id"]
    rng = random.Random(7)
    for _ in range(n_traj):
        s = [rng.uniform(0.05, 0.95), rng.uniform(0.05, 0.95)]
        transitions = []
        for _ in range(5):
            a = [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)]
            short = 0.3 if s[0] > 0.5 else 0.0
            nxt = [min(max(s[0] + a[0] * (1 - short), 0), 1), min(max(s[1] + a[1], 0), 1)]
            transitions.append({"s": s, "a": a, "s_next": nxt})
            s = nxt
        call("POST", f"/v1/experiments/{eid}/trajectories", {"transitions": transitions})
    call("POST", f"/v1/experiments/{eid}/model/refit")
    for _ in range(600):
        model = call("GET", f"/v1/experiments/{eid}/model")
        if model["version"] >= 1 and model["n_train"] == 5 * n_traj:
            break
        time.sleep(0.5)
    times = []
    for i in range(9):
        body = {"start": [0.1, 0.1], "goal": [0.9, 0.9], "client_id": f"c{i}"}
        t0 = time.time()
        p = call("POST", f"/v1/experiments/{eid}/proposals", body)
        times.append(time.time() - t0)
        call("POST", f"/v1/experiments/{eid}/proposals/{p['id']}/abandon")
    print(
        f"{acquisition} ({estimator}): n_train {model['n_train']}, median {statistics.median(times):.3f} s "
        f"(min {min(times):.3f}, max {max(times):.3f}) over 9 proposals"
    )
finally:
    proc.terminate()
    proc.wait()
