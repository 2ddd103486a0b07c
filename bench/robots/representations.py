"""What a custom domain's deviation model could learn from, measured apart from the service.

Two directions issue 47 names, on each bench robot with the same data: trajectory-like training
transitions (``--trajectories`` random rollouts of ``--length`` steps from valid states, executed
in MuJoCo) and uniform held-out state-actions with their true deviations. Every regressor is a
scikit-learn GP (Matérn 5/2 with one length scale per input, a constant amplitude and white
noise, normalised targets), so the comparison is of *what* is learned, not of precond's fit:

- **scalar**: one GP on the deviation ``d`` (raw, and capped at ``2·d_max`` as precond's automatic
  label cap often chooses), features as the service's defaults for a custom domain — the state,
  the action and the model's prediction ``ŝ'`` in the unit box of their bounds;
- **residual**: one GP per state component on the signed residual ``s'_i − ŝ'_i`` (periodic
  components the short way round; raw, and clipped at ``±2·d_max/√w_i``), combined as
  ``μ_d = ‖μ_r‖_w`` and ``σ_d = sqrt(Σ w_i σ_i²)`` (so ``μ_d + β σ_d`` bounds ``‖r‖_w`` when each
  component is within ``β σ_i``);
- **features** (``--features``): the scalar capped GP with other feature sets.

Printed: one JSON line per robot and seed: TPR and TNR of ``μ + β σ < d_max`` at β = 1 and 2 on
the held-out set, and the median σ over ``d_max``.

    python bench/robots/representations.py --robots arm,base,pusher,arm7 --seeds 3 > reps.jsonl
    python bench/robots/representations.py --summary reps.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

sys.path.insert(0, str(Path(__file__).resolve().parent))
from robot import Array, Robot  # noqa: E402
from run import robot_class  # noqa: E402

BETAS = (1.0, 2.0)


def rollouts(robot: Robot, rng: np.random.Generator, n: int, length: int) -> tuple[Array, Array]:
    states, actions = [], []
    for _ in range(n):
        s = robot.sample_state(rng)
        for _ in range(length):
            a = robot.sample_action(rng)
            states.append(s)
            actions.append(a)
            s = robot.true_step(s, a)
    return np.array(states), np.array(actions)


def fit(x: Array, y: Array) -> GaussianProcessRegressor:
    kernel = ConstantKernel(1.0, (1e-4, 1e4)) * Matern(
        length_scale=np.full(x.shape[1], 0.5), length_scale_bounds=(1e-2, 1e2), nu=2.5
    ) + WhiteKernel(1e-2, (1e-10, 1e1))
    gp = GaussianProcessRegressor(kernel, normalize_y=True, n_restarts_optimizer=1, random_state=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        gp.fit(x, y)
    return gp


def judged(mu: Array, sigma: Array, safe: Array, d_max: float) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for beta in BETAS:
        trusted = mu + beta * sigma < d_max
        out[f"tpr@{beta:g}"] = float((trusted & safe).sum() / max(safe.sum(), 1))
        out[f"tnr@{beta:g}"] = float((~trusted & ~safe).sum() / max((~safe).sum(), 1))
    out["sigma_over_dmax"] = float(np.median(sigma) / d_max)
    return out


def measure(name: str, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    robot = robot_class(name)()
    rng = np.random.default_rng([seed, 47])
    s, a = rollouts(robot, rng, args.trajectories, args.length)
    p = robot.f_hat(s, a)
    r = robot.difference(robot.true_steps(s, a), p)
    w = np.ones(s.shape[1]) if robot.distance_weights is None else np.asarray(robot.distance_weights)
    d = np.sqrt((w * r**2).sum(1))
    hs = np.array([robot.sample_state(rng) for _ in range(args.held_out)])
    ha = np.array([robot.sample_action(rng) for _ in range(args.held_out)])
    hp = robot.f_hat(hs, ha)
    hd = robot.distance(hp, robot.true_steps(hs, ha))
    safe = hd < robot.d_max

    lo_s, hi_s, lo_a, hi_a = robot.state_low, robot.state_high, robot.action_low, robot.action_high

    def unit(x: Array, lo: Array, hi: Array) -> Array:
        return (x - lo) / (hi - lo)

    def move(st: Array, pr: Array) -> Array:
        diag = np.sqrt((w * (hi_s - lo_s) ** 2).sum())
        return np.sqrt((w * robot.difference(pr, st) ** 2).sum(1, keepdims=True)) / diag

    feature_sets: dict[str, Callable[[Array, Array, Array], Array]] = {
        "s,a,p": lambda st, ac, pr: np.hstack([unit(st, lo_s, hi_s), unit(ac, lo_a, hi_a), unit(pr, lo_s, hi_s)]),
        "s,a": lambda st, ac, pr: np.hstack([unit(st, lo_s, hi_s), unit(ac, lo_a, hi_a)]),
        "p,a": lambda st, ac, pr: np.hstack([unit(pr, lo_s, hi_s), unit(ac, lo_a, hi_a)]),
        "s,a,p,|move|": lambda st, ac, pr: np.hstack(
            [unit(st, lo_s, hi_s), unit(ac, lo_a, hi_a), unit(pr, lo_s, hi_s), move(st, pr)]),
    }
    out: dict[str, Any] = {"robot": name, "seed": seed, "n_train": len(d),
                           "train_safe": float((d < robot.d_max).mean()), "held_out_safe": float(safe.mean())}
    x, hx = feature_sets["s,a,p"](s, a, p), feature_sets["s,a,p"](hs, ha, hp)
    for cap in (None, 2.0):
        t = time.perf_counter()
        gp = fit(x, d if cap is None else np.minimum(d, cap * robot.d_max))
        mu, sd = gp.predict(hx, return_std=True)
        out[f"scalar{'' if cap is None else ' capped'}"] = {
            **judged(mu, sd, safe, robot.d_max), "seconds": time.perf_counter() - t}
    for clip in (None, 2.0):
        t = time.perf_counter()
        mus, sds = np.zeros((len(hs), s.shape[1])), np.zeros((len(hs), s.shape[1]))
        for i in range(s.shape[1]):
            if w[i] == 0:
                continue
            y = r[:, i] if clip is None else np.clip(r[:, i], *(np.array([-1, 1]) * clip * robot.d_max / np.sqrt(w[i])))
            mus[:, i], sds[:, i] = fit(x, y).predict(hx, return_std=True)
        mu_d, sd_d = np.sqrt((w * mus**2).sum(1)), np.sqrt((w * sds**2).sum(1))
        out[f"residual{'' if clip is None else ' clipped'}"] = {
            **judged(mu_d, sd_d, safe, robot.d_max), "seconds": time.perf_counter() - t}
    if args.features:
        capped = np.minimum(d, 2.0 * robot.d_max)
        for key, f in feature_sets.items():
            if key == "s,a,p":
                continue
            mu, sd = fit(f(s, a, p), capped).predict(f(hs, ha, hp), return_std=True)
            out[f"capped, features {key}"] = judged(mu, sd, safe, robot.d_max)
    return out


def summary(path: Path) -> None:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    by: dict[str, dict[str, list[dict[str, Any]]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        for key, v in row.items():
            if isinstance(v, dict):
                by[row["robot"]][key].append(v)
    print("| robot | regressor | seeds | TPR, TNR at β 1 | TPR, TNR at β 2 | median σ / d_max |")
    print("|---|---|---|---|---|---|")
    for robot, cols in by.items():
        for key, vs in cols.items():
            def m(k: str, vs: list[dict[str, Any]] = vs) -> str:
                x = np.array([v[k] for v in vs])
                se = x.std(ddof=1) / np.sqrt(len(x)) if len(x) > 1 else 0.0
                return f"{x.mean():.2f} ± {se:.2f}"
            label = key.replace("|", "\\|")
            print(f"| {robot} | {label} | {len(vs)} | {m('tpr@1')}, {m('tnr@1')} | {m('tpr@2')}, {m('tnr@2')} "
                  f"| {m('sigma_over_dmax')} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", default="arm,base,pusher,arm7")
    ap.add_argument("--seeds", type=int, default=3, help="seeds FIRST .. FIRST+N-1")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--trajectories", type=int, default=50)
    ap.add_argument("--length", type=int, default=10)
    ap.add_argument("--held-out", type=int, default=1500)
    ap.add_argument("--features", action="store_true", help="also other feature sets (scalar, capped)")
    ap.add_argument("--summary", type=Path, help="summarise a JSON-lines file instead")
    args = ap.parse_args()
    if args.summary:
        summary(args.summary)
        return
    for name in args.robots.split(","):
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            print(json.dumps(measure(name, seed, args)), flush=True)


if __name__ == "__main__":
    main()
