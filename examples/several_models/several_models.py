"""Several models of one robot: plans that step with whichever model is trusted where it is.

A point robot on a 1 m x 1 m floor moves by one of eight moves of 10 cm. Its lab has more than
one model of it, each right in different places and at a different cost per call:

- ``sand``: right of x = 0.5 the floor is sand and the robot goes half as far. ``domain``
  (``s + a``, cost 1) is right on the left, ``slow`` (``s + a/2``, cost 4) on the right: no plan
  from the left to the right is trusted by either model alone.
- ``bands``: a mud band (0.35 ≤ x < 0.65: half as far) and a slope right of it (the robot slides
  3 cm down each move). ``domain`` (cost 1) and ``slow`` (cost 4) as above, and ``sim`` (cost
  20), a simulator served over HTTP that knows the floor, up to a coarse 5 mm grid.

For each seed the script creates the experiment with its further ``models``, runs precond's
learning loop (propose, execute in the true world, post; every posted transition labels every
model), then plans ``--test-problems`` fixed problems from the left edge to the right edge with
each model alone (``models=[name]``), with all of them (each step the cheapest model whose
precondition trusts it), and with an oracle: a breadth-first planner over the true union
precondition (a move is allowed where some model's prediction is within ``d_max`` of the true
next state; the cheapest such model is charged). Every plan is executed open loop in the true
world (success: ending within the goal radius, 5 cm) and closed loop (``execute_plan``: one
move at a time, re-planned with the same models whenever the robot strays from the plan). It prints a table per world and writes
``several_models_summary.json`` to ``--out``.

    pip install ./clients/python
    cargo build --release
    python examples/several_models/several_models.py --spawn-server target/release/precond
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from precond_client import Client, serve_model, spawn_server

Array = NDArray[np.float64]
D_MAX = 0.02
GOAL_RADIUS = 0.05
MOVES = [
    [0.1, 0.0],
    [-0.1, 0.0],
    [0.0, 0.1],
    [0.0, -0.1],
    [0.07, 0.07],
    [0.07, -0.07],
    [-0.07, 0.07],
    [-0.07, -0.07],
]


def linear(gain: float) -> dict[str, Any]:
    """The linear model ``s' = s + gain a`` (clipped to the floor by the service)."""
    return {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[gain, 0], [0, gain]]}


def sand_step(s: Array, a: Array) -> Array:
    return np.clip(s + (1.0 if s[0] < 0.5 else 0.5) * a, 0.0, 1.0)


def bands_step(s: Array, a: Array) -> Array:
    if s[0] < 0.35:
        nxt = s + a
    elif s[0] < 0.65:
        nxt = s + 0.5 * a
    else:
        nxt = s + a + np.array([0.0, -0.03])
    return np.clip(nxt, 0.0, 1.0)


def coarse(step: Callable[[Array, Array], Array]) -> Callable[[Array, Array], Array]:
    """A simulator of ``step`` that answers on a 5 mm grid: off by at most 3.5 mm."""

    def sim(states: Array, actions: Array) -> Array:
        nxt = np.array([step(s, a) for s, a in zip(states, actions, strict=True)])
        return np.round(nxt / 0.005) * 0.005

    return sim


@dataclass
class World:
    name: str
    step: Callable[[Array, Array], Array]
    remote_sim: bool
    #: name -> (cost, its prediction of one step), the domain's model first
    models: dict[str, tuple[float, Callable[[Array, Array], Array]]] = field(
        default_factory=dict
    )


def worlds() -> list[World]:
    def gain(k: float) -> Callable[[Array, Array], Array]:
        return lambda s, a: np.clip(s + k * a, 0.0, 1.0)

    sand = World(
        "sand", sand_step, False, {"domain": (1.0, gain(1.0)), "slow": (4.0, gain(0.5))}
    )
    sim = coarse(bands_step)
    bands = World(
        "bands",
        bands_step,
        True,
        {
            "domain": (1.0, gain(1.0)),
            "slow": (4.0, gain(0.5)),
            "sim": (20.0, lambda s, a: sim(s[None], a[None])[0]),
        },
    )
    return [sand, bands]


def execute(world: World, start: Array, actions: Array) -> Array:
    states = [np.asarray(start, dtype=np.float64)]
    for a in actions:
        states.append(world.step(states[-1], np.asarray(a, dtype=np.float64)))
    return np.array(states)


def oracle(world: World, start: Array, goal: Array) -> tuple[bool, float]:
    """Breadth-first search over the true union precondition: found, and the plan's step cost
    (each step charged the cheapest model within ``d_max`` of the true next state). States
    closer than 1 cm are merged, which keeps the search finite (the moves' lengths 10, 7, 5
    and 3.5 cm fill the floor densely) and can only miss a plan, never invent one."""

    def key(s: Array) -> tuple[int, ...]:
        return tuple(int(v) for v in np.round(s / 0.01))

    seen = {key(start): 0.0}
    queue = deque([(np.asarray(start, dtype=np.float64), 0.0, 0)])
    order = sorted(world.models.values(), key=lambda m: m[0])
    while queue:
        s, cost, depth = queue.popleft()
        if np.linalg.norm(s - goal) <= GOAL_RADIUS:
            return True, cost
        if depth >= 60:
            continue
        for move in MOVES:
            a = np.array(move)
            nxt = world.step(s, a)
            if np.array_equal(nxt, s) or np.any(
                np.abs(s + a - np.clip(s + a, 0, 1)) > 0
            ):
                continue
            charge = next(
                (c for c, f in order if np.linalg.norm(f(s, a) - nxt) < D_MAX), None
            )
            if charge is None or key(nxt) in seen:
                continue
            seen[key(nxt)] = cost + charge
            queue.append((nxt, cost + charge, depth + 1))
    return False, float("nan")


def test_problems(rng: np.random.Generator, n: int) -> list[tuple[Array, Array]]:
    """Start near the left edge, goal near the right edge."""
    return [
        (
            np.array([rng.uniform(0.05, 0.2), rng.uniform(0.3, 0.8)]),
            np.array([rng.uniform(0.8, 0.95), rng.uniform(0.3, 0.8)]),
        )
        for _ in range(n)
    ]


def run_world(
    client: Client,
    world: World,
    sim_url: str | None,
    seed: int,
    args: argparse.Namespace,
) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    further = [
        {"name": name, "cost": cost, "model": linear(0.5)}
        for name, (cost, _) in world.models.items()
        if name == "slow"
    ]
    if world.remote_sim:
        assert sim_url is not None
        further.append(
            {"name": "sim", "cost": 20.0, "model": {"kind": "remote", "url": sim_url}}
        )
    client.create_experiment(
        name=f"several models: {world.name}, seed {seed}",
        d_max=D_MAX,
        seed=seed,
        domain={
            "kind": "custom",
            "state": {"names": ["x", "y"], "low": [0, 0], "high": [1, 1]},
            "action": {"names": ["dx", "dy"], "values": MOVES},
            "goal": {"radius": GOAL_RADIUS},
            "model": linear(1.0),
        },
        learning={"batch_size": args.batch, "n_candidates": 5, "max_extensions": 2000},
        models=further,
    )

    def problems() -> Iterator[tuple[Array, Array]]:
        while True:
            yield rng.uniform(0.05, 0.95, size=2), rng.uniform(0.05, 0.95, size=2)

    # What the proposals step with (the further models have estimators after the first
    # batch): `domain`, the service's default, the domain's model alone; `all`, every model,
    # each proposal valued by what it teaches each; `separate`, one model at a time in turn.
    names = list(world.models)

    def across(episodes: int) -> list[str] | None:
        return None if episodes < args.batch else names

    def separately(episodes: int) -> list[str] | None:
        return None if episodes < args.batch else [names[episodes % len(names)]]

    chosen = {"domain": None, "all": across, "separate": separately}[args.learn]
    learner = client.learn(problems(), models=chosen, verbose=False)
    transitions = 0
    for ep in learner:
        created = ep.post(execute(world, ep.start, ep.actions))
        transitions += len(ep.actions)
        if created.n_trajectories >= args.trajectories:
            break
    client.wait_for_model(args.trajectories, timeout=600)

    tests = test_problems(rng, args.test_problems)
    arms: dict[str, list[str] | None] = {f"{m} alone": [m] for m in world.models}
    arms["all models"] = None
    rows: dict[str, dict[str, float]] = {}
    for arm, models in arms.items():
        found = success = closed = 0
        search_cost: list[float] = []
        step_cost: list[float] = []
        for s, g in tests:
            plan = client.plan(s, g, models=models)
            cost = plan.cost()
            search_cost.append(float("nan") if cost is None else cost)
            if (
                plan.found
                and plan.trajectory is not None
                and plan.step_models is not None
            ):
                found += 1
                end = execute(world, s, plan.trajectory.actions)[-1]
                success += int(np.linalg.norm(end - g) <= GOAL_RADIUS)
                step_cost.append(sum(world.models[m][0] for m in plan.step_models))
            # Closed loop: executed one move at a time, re-planned (with the same models)
            # from where the robot is whenever it strays more than d_max from the plan.
            run = client.execute_plan(s, g, world.step, models=models, max_steps=200)
            closed += int(run.success)
        rows[arm] = {
            "found": found / len(tests),
            "success": success / len(tests),
            "closed_loop": closed / len(tests),
            "search_cost": float(np.mean(search_cost)) if search_cost else float("nan"),
            "step_cost": float(np.mean(step_cost)) if step_cost else float("nan"),
        }
    found_cost = [oracle(world, s, g) for s, g in tests]
    costs = [c for f, c in found_cost if f]
    rows["oracle (true union)"] = {
        "found": sum(f for f, _ in found_cost) / len(tests),
        "success": sum(f for f, _ in found_cost) / len(tests),
        "closed_loop": sum(f for f, _ in found_cost) / len(tests),
        "search_cost": float("nan"),
        "step_cost": float(np.mean(costs)) if costs else float("nan"),
    }
    rows["learning"] = {
        "transitions": float(transitions),
        "no_plan": float(learner.no_plan),
    }
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--server", default="http://127.0.0.1:8080", help="a running precond server"
    )
    ap.add_argument(
        "--spawn-server", metavar="BINARY", help="start this precond binary instead"
    )
    ap.add_argument("--seeds", type=int, default=5, help="seeds 0 … SEEDS-1")
    ap.add_argument("--seed", type=int, help="this seed alone (instead of --seeds)")
    ap.add_argument(
        "--trajectories", type=int, default=40, help="learning trajectories per run"
    )
    ap.add_argument("--batch", type=int, default=10, help="trajectories per refit")
    ap.add_argument("--test-problems", type=int, default=20)
    ap.add_argument("--world", choices=["sand", "bands"], action="append")
    ap.add_argument(
        "--learn",
        choices=["domain", "all", "separate"],
        default="domain",
        help="proposals with the domain's model alone (the service's default), across every "
        "model, or one model at a time in turn",
    )
    ap.add_argument(
        "--out", type=Path, help="directory for the summary (default: a new temp dir)"
    )
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="precond-several-models-"))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    chosen = [w for w in worlds() if args.world is None or w.name in args.world]
    seeds = [args.seed] if args.seed is not None else list(range(args.seeds))
    bands = next(w for w in worlds() if w.name == "bands")
    sim = coarse(bands.step)
    summary: dict[str, Any] = {
        "args": {k: str(v) for k, v in vars(args).items()},
        "worlds": {},
    }
    with serve_model(sim, "127.0.0.1", 0) as served:
        proc = None
        url = args.server
        if args.spawn_server:
            db = Path(tempfile.mkdtemp()) / "several.db"
            proc, url = spawn_server(
                args.spawn_server,
                db,
                "--allow-model-url",
                f"http://127.0.0.1:{served.port}/",
            )
        try:
            client = Client(url, timeout=300, client_id="several-models")
            client.wait_ready(30)
            for world in chosen:
                per_seed = [
                    run_world(client, world, served.url, seed, args) for seed in seeds
                ]
                arms = list(per_seed[0])
                table = {
                    arm: {
                        k: float(np.nanmean([r[arm][k] for r in per_seed]))
                        if any(np.isfinite(r[arm][k]) for r in per_seed)
                        else float("nan")
                        for k in per_seed[0][arm]
                    }
                    for arm in arms
                }
                summary["worlds"][world.name] = {"mean": table, "per_seed": per_seed}
                print(
                    f"\n{world.name}: seeds {seeds} × {args.test_problems} problems, "
                    f"{args.trajectories} learning trajectories each ({args.learn}: "
                    f"{table['learning']['transitions']:.0f} transitions, "
                    f"{table['learning']['no_plan']:.1f} problems without a proposal)"
                )
                print(
                    f"{'':22s} {'found':>6s} {'success':>8s} {'closed loop':>12s} "
                    f"{'search cost':>12s} {'step cost':>10s}"
                )
                for arm, r in table.items():
                    if arm == "learning":
                        continue
                    print(
                        f"{arm:22s} {r['found']:6.2f} {r['success']:8.2f} {r['closed_loop']:12.2f} "
                        f"{r['search_cost']:12.0f} {r['step_cost']:10.1f}"
                    )
        finally:
            if proc is not None:
                proc.terminate()
                proc.wait()
    summary["seconds"] = round(time.monotonic() - t0, 1)
    (out / "several_models_summary.json").write_text(json.dumps(summary, indent=1))
    print(f"\n{summary['seconds']} s; summary in {out / 'several_models_summary.json'}")


if __name__ == "__main__":
    main()
