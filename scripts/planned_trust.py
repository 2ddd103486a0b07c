#!/usr/bin/env python3
"""How often the steps a planner chose were trusted and then beyond d_max.

A certified test β (`learning.calibrate_test_beta`) is judged on training transitions held
out; a plan's steps are not held-out points but the ones a search picked because the model
trusted them. This reads a harness database (`<out>/<world>/precond.db`; read only) and, for
every executed training step that started from its planned state with its planned action
(open loop, the planned μ and σ are the proposing model version's prediction for exactly that
state-action; steps after a drift are skipped), counts for each β: the steps that version
trusted (μ + βσ < d_max), how many of them were beyond d_max (what a plan meets), and the
share of all unsafe steps it trusted (1 − TNR on the planner's own choices).

    python3 scripts/planned_trust.py runs/base/precond.db --min-iteration 4
"""

from __future__ import annotations

import argparse
import json
import sqlite3

BETAS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0)


def close(u: list[float], v: list[float]) -> bool:
    """Equal up to the rounding of a JSON round trip."""
    return len(u) == len(v) and all(abs(x - y) <= 1e-9 for x, y in zip(u, v))


def planned_steps(
    con: sqlite3.Connection, experiment: int, min_iteration: int
) -> tuple[float, list[tuple[float, float, float]]]:
    """d_max and (μ, σ, deviation) of each step executed exactly as planned."""
    (settings,) = con.execute(
        "SELECT settings FROM experiments WHERE id = ?", (experiment,)
    ).fetchone()
    d_max = float(json.loads(settings)["d_max"])
    steps = []
    rows = con.execute(
        "SELECT p.body, t.id FROM proposals p JOIN trajectories t ON t.proposal_id = p.id "
        "WHERE p.experiment_id = ? AND t.partial = 0 AND p.iteration >= ?",
        (experiment, min_iteration),
    ).fetchall()
    for body, trajectory in rows:
        plan = json.loads(body)["trajectory"]
        for step, deviation, s, a in con.execute(
            "SELECT step, deviation, s, a FROM transitions WHERE trajectory_id = ? "
            "ORDER BY step",
            (trajectory,),
        ):
            if step >= len(plan["mu"]):
                continue
            if close(json.loads(s), plan["states"][step]) and close(
                json.loads(a), plan["actions"][step]
            ):
                steps.append((plan["mu"][step], plan["sigma"][step], deviation))
    return d_max, steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("db", help="a harness database (opened read only)")
    parser.add_argument(
        "--min-iteration", type=int, default=0, help="proposals from this iteration on"
    )
    args = parser.parse_args()
    con = sqlite3.connect(f"file:{args.db}?mode=ro", uri=True)
    experiments = [
        row[0]
        for row in con.execute(
            "SELECT id FROM experiments WHERE name LIKE 'experiment %' ORDER BY id"
        )
    ]
    pooled: list[tuple[float, float, float, float]] = []
    for e in experiments:
        d_max, steps = planned_steps(con, e, args.min_iteration)
        pooled += [(mu, sd, dev, d_max) for mu, sd, dev in steps]
        n_unsafe = sum(dev >= d_max for _, _, dev in steps)
        print(
            f"experiment {e}: {len(steps)} steps executed as planned, {n_unsafe} unsafe"
        )
    n_unsafe = sum(dev >= d for _, _, dev, d in pooled)
    print(f"all {len(experiments)}: {len(pooled)} steps, {n_unsafe} beyond d_max")
    print("    β  trusted  of them unsafe  unsafe trusted")
    for beta in BETAS:
        trusted = [(dev, d) for mu, sd, dev, d in pooled if mu + beta * sd < d]
        bad = sum(dev >= d for dev, d in trusted)
        print(
            f"  {beta:3.1f}  {len(trusted):7d}  {bad:5d} ({bad / max(len(trusted), 1):.3f})"
            f"  {bad:3d}/{n_unsafe} ({bad / max(n_unsafe, 1):.3f})"
        )


if __name__ == "__main__":
    main()
