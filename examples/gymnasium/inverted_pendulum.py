"""Where a cart-pole's first model can be trusted: Gymnasium's MuJoCo ``InvertedPendulum-v5``
with precond's Gymnasium wrapper and collector.

The robot's model is the one a lab writes before identifying anything: the cart is a double
integrator pushed by the action (``ẍ = k·a``, ``k`` from the actuator's gear and the cart's
mass), and the pole is assumed held still by the controller — its angle integrates its angular
velocity, which stays as it is (no gravity, no coupling to the cart). In symbols, with
``dt = 0.04`` s, ``s = (x, θ, ẋ, θ̇)``::

    x' = x + dt·ẋ,   θ' = θ + dt·θ̇,   ẋ' = ẋ + dt·k·a,   θ̇' = θ̇

It is a ``linear`` custom domain: precond labels every transition with it. The script

1. collects ``--train-episodes`` episodes of a noisy balancing controller (and some random
   pushes) through ``CollectEpisodes``, each posted as a trajectory with its source;
2. refits the MDE once on all of them;
3. runs ``--test-episodes`` fresh episodes of the same behaviour through
   ``PreconditionWrapper(cost=True)`` and compares each step's verdict with the model's real
   error (``d(f̂(s, a), s')`` computed here with the experiment's own distance);
4. judges ``--samples`` uniform state-actions of the experiment's box: how much of it is
   trusted;

and writes ``inverted_pendulum_summary.json`` (and, with matplotlib,
``inverted_pendulum_precondition.png``) to
``--out``, a fresh temporary directory by default.

    pip install './clients/python[gymnasium,mujoco,progress]' matplotlib
    cargo build --release
    python examples/gymnasium/inverted_pendulum.py --spawn-server target/release/precond
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from numpy.typing import NDArray
from precond_client import Client, spawn_server
from precond_client.gymnasium import CollectEpisodes, PreconditionWrapper, judge

Array = NDArray[np.float64]
ENV = "InvertedPendulum-v5"
DT = 0.04
K_ACTION = 8.3
"""ẍ per unit of action: the actuator's gear over the cart's mass, as read off the model file
(and close to what a least-squares fit of logged data gives: 8.29)."""
D_MAX = 0.3
GAINS = np.array([1.0, 20.0, 2.0, 3.0])
"""A balancing controller ``a = K·s`` (keeps the pole up for hundreds of steps)."""
NAMES = ["x", "theta", "x_dot", "theta_dot"]
LOW = [-1.0, -0.25, -3.0, -6.0]
HIGH = [1.0, 0.25, 3.0, 6.0]


def model_matrices() -> tuple[list[list[float]], list[list[float]]]:
    a = np.eye(4)
    a[0, 2] = a[1, 3] = DT
    b = np.zeros((4, 1))
    b[2, 0] = DT * K_ACTION
    return a.tolist(), b.tolist()


def f_hat(s: Array, a: Array) -> Array:
    """The robot's model, here for measuring its real error (the server has its own copy)."""
    am, bm = (np.array(m) for m in model_matrices())
    return np.clip(am @ s + bm @ a, LOW, HIGH)


def experiment_settings() -> dict[str, Any]:
    am, bm = model_matrices()
    return {
        "d_max": D_MAX,
        "domain": {
            "kind": "custom",
            "state": {"names": NAMES, "low": LOW, "high": HIGH},
            "action": {"names": ["force"], "low": [-3.0], "high": [3.0]},
            "model": {"kind": "linear", "A": am, "B": bm},
        },
        # One refit, after collecting: batches never complete on their own.
        "learning": {"batch_size": 10_000},
    }


def behaviour(episode: int) -> tuple[str, float]:
    """The behaviour of an episode: the controller with little, some or much noise, or random
    pushes (every fifth episode)."""
    if episode % 5 == 4:
        return "random", 0.0
    return "controller", [0.5, 1.5, 3.0, 5.0][episode % 4]


def act(kind: str, noise: float, obs: Array, rng: np.random.Generator) -> NDArray[np.float32]:
    if kind == "random":
        a = rng.uniform(-3.0, 3.0)
    else:
        a = float(np.clip(GAINS @ obs + noise * rng.standard_normal(), -3.0, 3.0))
    return np.array([a], dtype=np.float32)


def collect(client: Client, episodes: int, steps: int, seed: int) -> dict[str, int]:
    env = CollectEpisodes(
        gymnasium.make(ENV, max_episode_steps=steps), client, label="behaviour", run=f"s{seed}"
    )
    rng = np.random.default_rng(seed)
    lengths = []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed * 1000 + k)
        kind, noise = behaviour(k)
        n, done = 0, False
        while not done:
            obs, _, terminated, truncated, _ = env.step(act(kind, noise, obs, rng))
            n += 1
            done = terminated or truncated
        lengths.append(n)
    env.close()
    c = env.collected
    return {
        "episodes": c.episodes,
        "trajectories": c.trajectories,
        "transitions": c.transitions,
        "dropped_outside_box": c.dropped,
        "mean_episode_length": round(float(np.mean(lengths)), 1),
    }


def evaluate(client: Client, episodes: int, steps: int, seed: int) -> dict[str, Any]:
    """Runs fresh episodes through the wrapper; each step's verdict against the real error."""
    env = PreconditionWrapper(gymnasium.make(ENV, max_episode_steps=steps), client, cost=True)
    rng = np.random.default_rng(seed)
    inside, error, in_domain, kinds = [], [], [], []
    costs = []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed * 1000 + k)
        kind, noise = behaviour(k)
        done, cost = False, 0.0
        while not done:
            a = act(kind, noise, obs, rng)
            nxt, _, terminated, truncated, info = env.step(a)
            p = info["precondition"]
            inside.append(p["inside"])
            in_domain.append(p["in_domain"])
            error.append(float(np.linalg.norm(f_hat(obs, a.astype(np.float64)) - nxt)))
            kinds.append(kind)
            cost += info["cost"]
            obs, done = nxt, terminated or truncated
        costs.append(cost)
    ins = np.array(inside)
    err = np.array(error)
    good = err < D_MAX

    def share(mask: NDArray[np.bool_]) -> float | None:
        return round(float(mask.mean()), 3) if mask.size else None

    def q(x: Array, p: float) -> float | None:
        return round(float(np.percentile(x, p)), 4) if x.size else None

    return {
        "steps": int(ins.size),
        "in_domain": share(np.array(in_domain)),
        "model_right": share(good),
        "trusted": share(ins),
        "trusted_and_right": share(good[ins]) if ins.any() else None,
        "tpr": share(ins[good]),
        "tnr": share(~ins[~good]),
        "error_trusted_median": q(err[ins], 50),
        "error_trusted_p95": q(err[ins], 95),
        "error_trusted_max": q(err[ins], 100),
        "error_untrusted_median": q(err[~ins], 50),
        "mean_episode_cost": round(float(np.mean(costs)), 2),
        "trusted_by_behaviour": {
            kind: share(ins[np.array(kinds) == kind]) for kind in sorted(set(kinds))
        },
    }


def coverage(client: Client, samples: int, seed: int) -> dict[str, Any]:
    """The share of the experiment's state-action box that is trusted (uniform samples), in all
    and near the upright (|θ| < 0.05, |θ̇| < 0.5)."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(LOW, HIGH, (samples, 4))
    a = rng.uniform(-3.0, 3.0, (samples, 1))
    v = judge(client, s, a)
    near = (np.abs(s[:, 1]) < 0.05) & (np.abs(s[:, 3]) < 0.5)
    return {
        "samples": samples,
        "trusted": round(float(v.inside.mean()), 4),
        "trusted_near_upright": round(float(v.inside[near].mean()), 4) if near.any() else None,
        "near_upright_samples": int(near.sum()),
        "model_version": v.model_version,
    }


def plot(client: Client, out: Path) -> str | None:
    """μ + βσ over (θ, force) at x = ẋ = θ̇ = 0, with the model's real one-step error there."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    thetas = np.linspace(-0.2, 0.2, 41)
    forces = np.linspace(-3.0, 3.0, 41)
    tt, ff = np.meshgrid(thetas, forces)
    s = np.c_[np.zeros(tt.size), tt.ravel(), np.zeros(tt.size), np.zeros(tt.size)]
    v = judge(client, s, ff.reshape(-1, 1))
    env = gymnasium.make(ENV).unwrapped
    env.reset(seed=0)
    err = np.empty(tt.size)
    for k, (si, fi) in enumerate(zip(s, ff.ravel(), strict=True)):
        qpos = np.array([si[0], si[1]])
        qvel = np.array([si[2], si[3]])
        env.set_state(qpos, qvel)
        nxt, *_ = env.step(np.array([fi], dtype=np.float32))
        err[k] = np.linalg.norm(f_hat(si, np.array([fi])) - nxt)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    up = v.upper.reshape(tt.shape)
    im = axes[0].pcolormesh(thetas, forces, up, cmap="RdYlGn_r", vmin=0, vmax=2 * D_MAX)
    axes[0].contour(thetas, forces, up, levels=[D_MAX], colors="k")
    axes[0].set_title("learned μ + 2σ (black: d_max)")
    fig.colorbar(im, ax=axes[0])
    im = axes[1].pcolormesh(
        thetas, forces, err.reshape(tt.shape), cmap="RdYlGn_r", vmin=0, vmax=2 * D_MAX
    )
    axes[1].contour(thetas, forces, err.reshape(tt.shape), levels=[D_MAX], colors="k")
    axes[1].set_title("the model's real error (MuJoCo)")
    fig.colorbar(im, ax=axes[1])
    for ax in axes:
        ax.set_xlabel("pole angle θ (rad), x = ẋ = θ̇ = 0")
    axes[0].set_ylabel("force")
    fig.tight_layout()
    path = out / "inverted_pendulum_precondition.png"
    fig.savefig(path, dpi=110)
    return path.name


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--server", default="http://127.0.0.1:8080", help="a running precond server")
    ap.add_argument("--spawn-server", metavar="BINARY", help="start this precond binary instead")
    ap.add_argument("--train-episodes", type=int, default=20)
    ap.add_argument("--test-episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=80, help="steps per episode at most")
    ap.add_argument("--samples", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="output directory (default: a new temporary one)")
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="precond-inverted-pendulum-"))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    proc = None
    url = args.server
    if args.spawn_server:
        proc, url = spawn_server(args.spawn_server, Path(tempfile.mkdtemp()) / "precond.db")
    try:
        with Client(url, timeout=600) as client:
            client.wait_ready(30)
            exp = client.create_experiment(experiment_settings(), name=f"{ENV} kinematic")
            print(f"experiment {exp.id} on {url}")
            collected = collect(client, args.train_episodes, args.steps, args.seed)
            print("collected", collected)
            model = client.refit()
            model = client.wait_for_model(collected["trajectories"], timeout=1800)
            print(f"model v{model.version}: {model.n_train} transitions, {model.fit_seconds} s")
            evaluation = evaluate(client, args.test_episodes, args.steps, args.seed + 1)
            print("evaluation", evaluation)
            box = coverage(client, args.samples, args.seed + 2)
            print("coverage", box)
            figure = plot(client, out)
            summary = {
                "env": ENV,
                "gymnasium": gymnasium.__version__,
                "d_max": D_MAX,
                "model": "x'=x+dt·ẋ, θ'=θ+dt·θ̇, ẋ'=ẋ+dt·k·a, θ̇'=θ̇ (dt 0.04, k 8.3)",
                "seed": args.seed,
                "collected": collected,
                "fit": {
                    "version": model.version,
                    "n_train": model.n_train,
                    "seconds": model.fit_seconds,
                    "label_cap": model.label_cap,
                },
                "evaluation": evaluation,
                "coverage": box,
                "figure": figure,
                "seconds": round(time.monotonic() - t0, 1),
            }
            (out / "inverted_pendulum_summary.json").write_text(
                json.dumps(summary, indent=1, ensure_ascii=False) + "\n"
            )
            print(f"summary in {out / 'inverted_pendulum_summary.json'}")
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(20)


if __name__ == "__main__":
    main()
