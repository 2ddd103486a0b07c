#!/usr/bin/env python3
"""Why test problems fail on a gridworld harness run: the planner or the precondition?

For one layout directory written by `precond experiment --domain icy_gridworld` (its
`summary.json`, `tests.csv` and `precond.db`), this serves a copy of the database, asks each
run's final model which of the map's state-actions it trusts at the test β, and for every test
problem of the chosen iteration whose plan was not found:

- searches the learned precondition exhaustively (breadth-first over trusted moves): if a path
  exists, the RRT's budget is to blame, not what was learned;
- otherwise finds the fewest truly safe moves that are not trusted yet would solve it
  (0-1 breadth-first search over the true world) and reports them: executed or never
  executed, and their μ and σ.

Usage: scripts/gridworld_gaps.py RESULTS/icy_gridworld/LAYOUT [--iteration N]
       [--binary target/release/precond] [--beta 2]
Standard library only.
"""

from __future__ import annotations

import argparse
import collections
import csv
import json
import shutil
import socket
import statistics
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

MOVES = [(1, 0), (-1, 0), (0, 1), (0, -1)]
Cell = tuple[int, int]
Move = tuple[int, int]


class Server:
    """`precond serve` on a copy of a results database, on a free loopback port."""

    def __init__(self, binary: str, db: Path) -> None:
        self.tmp = tempfile.TemporaryDirectory()
        copy = Path(self.tmp.name) / "precond.db"
        shutil.copy(db, copy)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.proc = subprocess.Popen(
            [binary, "serve", "--addr", f"127.0.0.1:{self.port}", "--database-url", str(copy)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for _ in range(200):
            try:
                self.get("/readyz")
                return
            except OSError:
                time.sleep(0.05)
        raise RuntimeError("the server did not start")

    def get(self, path: str) -> Any:
        with urllib.request.urlopen(f"http://127.0.0.1:{self.port}{path}") as r:
            return json.load(r)

    def post(self, path: str, body: Any) -> Any:
        req = urllib.request.Request(
            f"http://127.0.0.1:{self.port}{path}",
            data=json.dumps(body).encode(),
            headers={"content-type": "application/json"},
        )
        with urllib.request.urlopen(req) as r:
            return json.load(r)

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait()
        self.tmp.cleanup()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("layout_dir", type=Path)
    ap.add_argument("--iteration", type=int, help="default: the last")
    ap.add_argument("--binary", default="target/release/precond")
    ap.add_argument("--beta", type=float, default=2.0)
    args = ap.parse_args()

    summary = json.loads((args.layout_dir / "summary.json").read_text())
    layout = summary["config"].get("layout")
    rows: list[str] = layout["map"] if layout else default_map(args.binary)
    h, w = len(rows), len(rows[0])
    tests = list(csv.DictReader((args.layout_dir / "tests.csv").open()))
    last = max(int(t["iteration"]) for t in tests)
    iteration = last if args.iteration is None else args.iteration
    tests = [t for t in tests if int(t["iteration"]) == iteration]

    def clamp(c: Cell) -> Cell:
        return (min(max(c[0], 0), w - 1), min(max(c[1], 0), h - 1))

    def true_next(c: Cell, m: Move) -> Cell:
        if rows[c[1]][c[0]] == "~" and m[0] != 0:
            m = (-m[0], m[1])
        n = clamp((c[0] + m[0], c[1] + m[1]))
        return c if rows[n[1]][n[0]] == "#" else n

    def predicted(c: Cell, m: Move) -> Cell:
        return clamp((c[0] + m[0], c[1] + m[1]))

    server = Server(args.binary, args.layout_dir / "precond.db")
    try:
        runs = [
            e
            for e in server.get("/v1/experiments?limit=100")["items"]
            if e["name"].startswith("experiment")
        ]
        counts: collections.Counter[str] = collections.Counter()
        missing_sigma: list[float] = []
        missing_mu: list[float] = []
        for run in runs:
            points = [
                {"s": [x, y], "a": list(m)} for y in range(h) for x in range(w) for m in MOVES
            ]
            judged = server.post(
                f"/v1/experiments/{run['id']}/precondition", {"points": points, "beta": args.beta}
            )["results"]
            trust = {
                ((p["s"][0], p["s"][1]), (p["a"][0], p["a"][1])): j
                for p, j in zip(points, judged, strict=True)
            }
            executed: set[tuple[Cell, Move]] = set()
            after = 0
            while True:
                page = server.get(
                    f"/v1/experiments/{run['id']}/transitions?limit=1000&after={after}"
                )
                for t in page["items"]:
                    executed.add(
                        ((int(t["s"][0]), int(t["s"][1])), (int(t["a"][0]), int(t["a"][1])))
                    )
                if not page.get("next") or not page["items"]:
                    break
                after = page["next"]
            for t in tests:
                if int(t["seed"]) != run["seed"] or t["strategy"] != run_strategy(run):
                    continue
                counts["test problems"] += 1
                if t["found"] == "true":
                    counts["plan found"] += 1
                    continue
                start = cell(t["start"])
                goal = cell(t["goal"])
                # Cost 0 for a trusted move, 1 for a truly safe move that is not trusted.
                dist = {start: 0}
                prev: dict[Cell, tuple[Cell, Move]] = {}
                queue = collections.deque([start])
                while queue:
                    c = queue.popleft()
                    for m in MOVES:
                        n = predicted(c, m)
                        if n == c:
                            continue
                        inside = trust[(c, m)]["inside"]
                        if not inside and true_next(c, m) != n:
                            continue
                        cost = dist[c] + (0 if inside else 1)
                        if cost < dist.get(n, 1 << 30):
                            dist[n] = cost
                            prev[n] = (c, m)
                            (queue.appendleft if cost == dist[c] else queue.append)(n)
                if goal not in dist:
                    counts["unsolvable in the true world"] += 1
                    continue
                if dist[goal] == 0:
                    counts["not found, but a path lies inside the learned precondition"] += 1
                    continue
                counts["not found: the learned precondition has no path"] += 1
                n = goal
                while n != start:
                    c, m = prev[n]
                    j = trust[(c, m)]
                    if not j["inside"]:
                        seen = "executed" if (c, m) in executed else "never executed"
                        counts[f"missing safe moves, {seen}"] += 1
                        missing_mu.append(j["mu"])
                        missing_sigma.append(j["sigma"])
                    n = c
    finally:
        server.close()

    print(f"{args.layout_dir}, iteration {iteration}, {len(runs)} runs, test β = {args.beta}")
    for k, v in counts.items():
        print(f"  {k}: {v}")
    if missing_sigma:
        q = statistics.quantiles(missing_sigma, n=4)
        print(
            f"  missing moves: median μ {statistics.median(missing_mu):.3f}, σ quartiles "
            f"{q[0]:.3f} / {q[1]:.3f} / {q[2]:.3f} (trusted needs μ + {args.beta}σ < d_max)"
        )


def cell(text: str) -> Cell:
    x, y = (int(float(v)) for v in text.split(";"))
    return (x, y)


def run_strategy(run: dict[str, Any]) -> str:
    """The strategy in a harness run's name, `experiment <domain>, <strategy>, seed <n>`."""
    return str(run["name"].split(", ")[1])


def default_map(binary: str) -> list[str]:
    """The default map, as the service reports it for a new gridworld experiment."""
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "empty.db"
        db.touch()
        server = Server(binary, db)
        try:
            created = server.post("/v1/experiments", {})
            return list(created["domain"]["map"])
        finally:
            server.close()


if __name__ == "__main__":
    main()
