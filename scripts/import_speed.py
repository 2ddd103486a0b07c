"""How long `Client.import_file` takes on a generated CSV log, against a fresh server.

    python scripts/import_speed.py [--rows 100000] [--episodes 100] [--client-src DIR]

The log: `--episodes` episodes of `--rows / --episodes` pushes each (precond's own `s_*`,
`a_*`, `s_next_*` columns), imported into a kinematic experiment of a server started on a
temporary SQLite database (`PRECOND_BIN`, default target/release/precond). `--client-src`
imports the client from another source tree, e.g. an older commit's
(`git archive 72d6cb6 clients/python/src | tar -x -C /tmp/old`, then
`--client-src /tmp/old/clients/python/src`), to compare two clients on the same log and server.
Prints the wall time, the trajectories stored and the client's peak memory.
"""

from __future__ import annotations

import argparse
import os
import random
import resource
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def write_log(path: Path, rows: int, episodes: int, seed: int = 0) -> None:
    rng = random.Random(seed)
    per = max(1, rows // episodes)
    with path.open("w") as f:
        f.write("episode,s_x,s_y,a_dx,a_dy,s_next_x,s_next_y\n")
        for e in range(episodes):
            s = [rng.uniform(0.2, 0.8), rng.uniform(0.2, 0.8)]
            for _ in range(per):
                a = [rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01)]
                n = [s[0] + 0.8 * a[0], s[1] + 0.8 * a[1]]
                f.write(",".join([str(e)] + [repr(v) for v in (*s, *a, *n)]) + "\n")
                s = n


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=100_000)
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--client-src", type=Path, default=REPO / "clients" / "python" / "src")
    args = p.parse_args()
    sys.path.insert(0, str(args.client_src))
    from precond_client import Client, spawn_server  # from --client-src

    binary = os.environ.get("PRECOND_BIN", str(REPO / "target" / "release" / "precond"))
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "log.csv"
        write_log(log, args.rows, args.episodes)
        size = log.stat().st_size
        proc, url = spawn_server(binary, Path(tmp) / "db.sqlite")
        try:
            with Client(url) as client:
                client.create_experiment(
                    name="import speed",
                    domain={"kind": "kinematic", "state_low": [-1, -1], "state_high": [2, 2]},
                    learning={"batch_size": 10_000},
                )
                t = time.perf_counter()
                report = client.import_file(log, progress=False)
                took = time.perf_counter() - t
        finally:
            proc.terminate()
            proc.wait(30)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"{args.client_src}: {args.rows} rows, {args.episodes} episodes, {size} bytes: "
        f"{took:.1f} s, {report.created} trajectories stored, client peak RSS {peak:.0f} MB"
    )


if __name__ == "__main__":
    main()
