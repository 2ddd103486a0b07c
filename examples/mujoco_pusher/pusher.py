"""Active learning of a pusher's model precondition, with MuJoCo as the true world.

The robot kicks a puck across a 1 m table (``scene.xml``). Its model is the analytical one a lab
would write first: "the puck moves by the commanded displacement" (``s' = clip(s + a)``), served
to precond over HTTP with ``serve_model``. The real table has two things the model does not know:
a waxed strip where the puck slides about four times further, and a toolbox that stops it. The
script runs precond's active-learning loop (propose → execute in MuJoCo → post), evaluates after
every batch (precondition TPR/TNR on held-out transitions, plan-found and success rates on test
problems) and saves the learning curve and a precondition map as PNG.

    pip install ./clients/python -r examples/mujoco_pusher/requirements.txt
    precond serve --allow-model-url http://127.0.0.1:9000/ &
    python examples/mujoco_pusher/pusher.py

or let the script start a server binary itself: ``--spawn-server target/release/precond``. The
figures and the summary go to ``--out``, a new temporary directory by default (the committed
ones in ``docs/mujoco_pusher`` are refreshed only by naming it).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import matplotlib.ticker
import mujoco
import numpy as np
from numpy.typing import NDArray
from precond_client import Client, serve_model, spawn_server
from tqdm import tqdm

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import Rectangle

Array = NDArray[np.float64]
SCENE = Path(__file__).with_name("scene.xml")
TABLE_FRICTION = 0.5
PUCK_Z = 0.0105
D_MAX = 0.03
GOAL_RADIUS = 0.05
BOUNDS = (0.03, 0.97)  # where the puck's centre can be (the rim)


class Table:
    """The true world: MuJoCo's puck on the table."""

    def __init__(self) -> None:
        self.model = mujoco.MjModel.from_xml_path(str(SCENE))
        self.data = mujoco.MjData(self.model)
        ice = self.model.geom("ice")
        block = self.model.geom("block")
        self.ice = (ice.pos[:2] - ice.size[:2], ice.pos[:2] + ice.size[:2])
        self.block = (block.pos[:2] - block.size[:2], block.pos[:2] + block.size[:2])

    def step(self, s: Array, a: Array) -> Array:
        """Puts the puck at ``s`` and kicks it so that, on the plain table, it slides by ``a``:
        the launch speed ``sqrt(2 μ g |a|)`` for the table's friction ``μ``. Returns where it
        stops."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:3] = [s[0], s[1], PUCK_Z]
        d.qpos[3:7] = [1, 0, 0, 0]
        dist = float(np.linalg.norm(a))
        if dist > 1e-9:
            d.qvel[:2] = np.sqrt(2 * TABLE_FRICTION * 9.81 * dist) * np.asarray(a) / dist
        mujoco.mj_forward(m, d)
        for i in range(3000):
            mujoco.mj_step(m, d)
            if i > 5 and np.linalg.norm(d.qvel[:2]) < 1e-3:
                break
        return np.clip(d.qpos[:2].copy(), 0.0, 1.0)

    def execute(self, start: Array, actions: Array) -> Array:
        """Executes ``actions`` open loop from ``start``: the observed states, the start first."""
        states = [np.asarray(start, dtype=np.float64)]
        for a in actions:
            states.append(self.step(states[-1], a))
        return np.array(states)


def f_hat(states: Array, actions: Array) -> Array:
    """The robot's analytical model: the puck moves by the action, and stays on the table."""
    return np.clip(states + actions, *BOUNDS)


def random_state(rng: np.random.Generator, table: Table) -> Array:
    """A start position on the table, off the toolbox."""
    while True:
        s = rng.uniform(0.05, 0.95, size=2)
        lo, hi = table.block
        if not np.all((s > lo - 0.03) & (s < hi + 0.03)):
            return s


def problem(rng: np.random.Generator, table: Table) -> tuple[Array, Array]:
    """A start and a goal 0.25 to 0.6 m apart."""
    while True:
        s, g = random_state(rng, table), random_state(rng, table)
        if 0.25 <= np.linalg.norm(g - s) <= 0.6:
            return s, g


@dataclass
class Evaluation:
    iteration: int
    n_trajectories: int
    tpr: float
    tnr: float
    plan_found: float
    success: float
    model_version: int
    label_cap: float | None
    """The label cap the answering version was fitted with (``mde.label_cap`` "auto" chooses
    it at every fit)."""


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--server", default="http://127.0.0.1:8080", help="a running precond server")
    ap.add_argument("--spawn-server", metavar="BINARY", help="start this precond binary instead")
    ap.add_argument("--model-port", type=int, default=9000, help="port of the served model")
    ap.add_argument("--iterations", type=int, default=10, help="learning iterations (batches)")
    ap.add_argument("--batch", type=int, default=5, help="trajectories per iteration")
    ap.add_argument("--test-problems", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--preset", choices=["default", "paper"], default="default", help="learning.preset"
    )
    ap.add_argument(
        "--out", type=Path, help="output directory (default: a new temporary directory)"
    )
    args = ap.parse_args()
    if args.out is None:
        args.out = Path(tempfile.mkdtemp(prefix="precond-mujoco-pusher-"))
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    table = Table()
    t0 = time.monotonic()

    with serve_model(f_hat, "127.0.0.1", args.model_port) as model:
        proc = None
        url = args.server
        if args.spawn_server:
            db = Path(tempfile.mkdtemp()) / "pusher.db"
            proc, url = spawn_server(
                args.spawn_server, db, "--allow-model-url", f"http://127.0.0.1:{model.port}/"
            )
        try:
            client = Client(url, timeout=120, client_id="pusher-1")
            client.wait_ready(30)
            exp = client.create_experiment(
                name=f"mujoco pusher seed {args.seed}",
                d_max=D_MAX,
                seed=args.seed,
                domain={
                    "kind": "custom",
                    "state": {"names": ["x", "y"], "low": [0, 0], "high": [1, 1]},
                    "action": {"names": ["dx", "dy"], "low": [-0.1, -0.1], "high": [0.1, 0.1]},
                    "goal": {"radius": GOAL_RADIUS},
                    "model": {"kind": "remote", "url": model.url, "timeout_ms": 10000},
                },
                learning={
                    "batch_size": args.batch,
                    "iterations": args.iterations,
                    "n_candidates": 5,
                    "max_extensions": 1500,
                    "preset": args.preset,
                },
            )
            print(f"experiment {exp.id} on {url}; model served at {model.url}")

            # Held-out transitions of the true world and fixed test problems.
            held_s = np.array([random_state(rng, table) for _ in range(400)])
            held_a = rng.uniform(-0.1, 0.1, size=(400, 2))
            held_dev = np.array(
                [
                    np.linalg.norm(table.step(s, a) - f_hat(s[None], a[None])[0])
                    for s, a in zip(held_s, held_a, strict=True)
                ]
            )
            tests = [problem(rng, table) for _ in range(args.test_problems)]

            def evaluate(iteration: int) -> Evaluation:
                n = client.get_experiment().n_trajectories
                m = client.wait_for_model(n, timeout=300)
                pre = client.precondition((held_s, held_a), beta=2.0)
                truth = held_dev < D_MAX
                tpr = float(np.mean(pre.inside[truth])) if truth.any() else float("nan")
                tnr = float(np.mean(~pre.inside[~truth])) if (~truth).any() else float("nan")
                found = success = 0
                for s, g in tests:
                    plan = client.plan(s, g)
                    if plan.found and plan.trajectory is not None:
                        found += 1
                        end = table.execute(s, plan.trajectory.actions)[-1]
                        success += int(np.linalg.norm(end - g) <= GOAL_RADIUS)
                k = len(tests)
                return Evaluation(
                    iteration, n, tpr, tnr, found / k, success / k, m.version, m.label_cap
                )

            curve = [evaluate(0)]
            total = args.iterations * args.batch

            def problems():  # endless: a problem with no plan is skipped
                while True:
                    yield problem(rng, table)

            bar = tqdm(total=total, desc="trajectories", unit="traj")
            learner = client.learn(problems())
            for ep in learner:
                observed = table.execute(ep.start, ep.actions)
                created = ep.post(observed)
                bar.update(1)
                bar.set_postfix(
                    iteration=created.iteration,
                    no_plan=learner.no_plan,
                    max_dev=f"{created.deviations.max():.3f}",
                )
                if created.n_trajectories % args.batch == 0:
                    curve.append(evaluate(created.n_trajectories // args.batch))
                    e = curve[-1]
                    tqdm.write(
                        f"iteration {e.iteration:2d}: TPR {e.tpr:.2f} TNR {e.tnr:.2f} "
                        f"plan found {e.plan_found:.2f} success {e.success:.2f}"
                    )
                if created.n_trajectories >= total:
                    break
            bar.close()
            no_plan = learner.no_plan

            plot_curve(curve, args.out / "mujoco_pusher_learning_curve.png")
            plot_map(client, table, args.out / "mujoco_pusher_precondition_map.png")
            final = curve[-1]
            summary = {
                "mujoco": mujoco.__version__,
                "seed": args.seed,
                "preset": args.preset,
                "iterations": args.iterations,
                "batch": args.batch,
                "no_plan_proposals": no_plan,
                # The server's count of refused proposal requests (the same, seen from there).
                "refused_on_server": client.get_experiment().n_refused,
                "relaxed_proposals": sum(
                    1
                    for r in client.runs()
                    if r.proposal_id is not None
                    and client.get_proposal(r.proposal_id).relaxed_from_beta is not None
                ),
                "model_calls": model.calls,
                "model_points": model.points,
                "seconds": round(time.monotonic() - t0, 1),
                "curve": [e.__dict__ for e in curve],
            }
            (args.out / "mujoco_pusher_summary.json").write_text(json.dumps(summary, indent=1))
            print(
                f"final: TPR {final.tpr:.2f} TNR {final.tnr:.2f} plan found {final.plan_found:.2f} "
                f"success {final.success:.2f} after {final.n_trajectories} trajectories, "
                f"{summary['seconds']} s; MuJoCo {mujoco.__version__}; figures in {args.out}"
            )
        finally:
            if proc is not None:
                proc.terminate()
                proc.wait()


def plot_curve(curve: list[Evaluation], path: Path) -> None:
    it = [e.iteration for e in curve]
    fig, ax = plt.subplots(figsize=(7.6, 4))
    for key, label in [
        ("tpr", "TPR (held-out)"),
        ("tnr", "TNR (held-out)"),
        ("plan_found", "plan found"),
        ("success", "success"),
    ]:
        ax.plot(it, [getattr(e, key) for e in curve], marker="o", label=label)
    ax.set_xlabel("iteration (5 executed trajectories each)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title("MuJoCo pusher: learning the model precondition (β = 2)")
    ax.grid(alpha=0.3)
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_map(client: Client, table: Table, path: Path) -> None:
    """μ + 2σ for a push of 8 cm to the right over the table, the truth, and the states of
    every stored transition."""
    visited = np.array([t.s for t in client.transitions()])
    a = np.array([0.08, 0.0])
    xs = np.linspace(0.03, 0.97, 48)
    xx, yy = np.meshgrid(xs, xs)
    states = np.column_stack([xx.ravel(), yy.ravel()])
    actions = np.tile(a, (len(states), 1))
    pre = client.precondition((states, actions), beta=2.0)
    truth = np.array(
        [np.linalg.norm(table.step(s, a) - f_hat(s[None], a[None])[0]) for s in states]
    )
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
    panels = [(pre.upper, "learned: μ + 2σ of the deviation"), (truth, "true deviation (MuJoCo)")]
    for ax, (val, title) in zip(axes, panels, strict=True):
        im = ax.pcolormesh(
            xx, yy, val.reshape(xx.shape), cmap="viridis", vmin=0, vmax=0.15, shading="auto"
        )
        ax.contour(xx, yy, val.reshape(xx.shape), levels=[D_MAX], colors="white", linewidths=1.5)
        for (lo, hi), name in [(table.ice, "low friction"), (table.block, "toolbox")]:
            ax.add_patch(Rectangle(lo, *(hi - lo), fill=False, ec="red", lw=1.5, ls="--"))
            ax.text(lo[0] + 0.01, hi[1] - 0.04, name, color="red", fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
    axes[0].scatter(
        visited[:, 0], visited[:, 1], s=3, c="white", alpha=0.6, label="training states"
    )
    axes[0].legend(loc="lower right", fontsize=8)
    fig.colorbar(im, ax=axes, label="deviation (m); white line: d_max = 0.03")
    fig.suptitle("'push 8 cm to the right': trusted on the dark side of the white line (d_max)")
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
