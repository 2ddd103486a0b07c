"""What a bench robot is: a lab's declaration (spaces, d_max, goal, inaccurate model) plus the
true world (MuJoCo) that the bench alone can see.

A robot is declared to precond exactly as a lab would: a ``custom`` domain whose model is
``remote``, served from this process with ``precond_client.serve_model``. Nothing about the true
world (obstacles, friction, gravity, torque limits) is told to the service.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

SETTLED_SPEED = 1e-3
"""A simulation may stop early once every joint moves slower than this (rad/s or m/s) after the
command's last change: what is left of the step changes the state by at most about
``SETTLED_SPEED × remaining time`` (≤ 1 mm or 1 mrad), far below every robot's ``d_max``."""


def run_until_settled(m: mujoco.MjModel, d: mujoco.MjData, nstep: int, min_steps: int,
                      chunk: int = 10) -> None:
    """Steps ``nstep`` times, or fewer once at least ``min_steps`` are done and the system is at
    rest (``max |qvel| < SETTLED_SPEED``)."""
    done = 0
    while done < nstep:
        k = min(chunk, nstep - done)
        mujoco.mj_step(m, d, nstep=k)
        done += k
        if done >= min_steps and np.max(np.abs(d.qvel)) < SETTLED_SPEED:
            return


class Robot(ABC):
    """One bench robot. Subclasses set the class attributes and implement the methods."""

    name: str
    description: str
    state_names: list[str]
    state_low: Array
    state_high: Array
    action_names: list[str]
    action_low: Array
    action_high: Array
    d_max: float
    """Tolerance in the units of :meth:`distance`."""
    goal_components: list[int]
    goal_radius: float
    distance_weights: list[float] | None = None
    """``d = sqrt(Σ w_i (ŝ_i − s_i)²)``; ``None``: all ones."""
    problem_distance: tuple[float, float]
    """Start and goal this far apart (in the goal components, Euclidean)."""
    periodic: list[int] = []
    """State components that are angles of period ``high − low``, declared ``state.periodic``:
    the distance takes them the shorter way round, as the service does."""

    # ---------------------------------------------------------------- the lab's side

    @abstractmethod
    def f_hat(self, states: Array, actions: Array) -> Array:
        """The lab's inaccurate model, batched: ``(N, n), (N, m) -> (N, n)``."""

    def lab_valid(self, states: Array, actions: Array) -> NDArray[np.bool_]:
        """The lab's own constraint check (what it knows: joint limits it clips to, the
        state box). Default: every step is allowed."""
        return np.ones(len(states), dtype=bool)

    def domain(self, model_url: str) -> dict[str, Any]:
        """The ``custom`` domain a lab would post (features at the server's defaults)."""
        d: dict[str, Any] = {
            "kind": "custom",
            "state": {
                "names": self.state_names,
                "low": self.state_low.tolist(),
                "high": self.state_high.tolist(),
            },
            "action": {
                "names": self.action_names,
                "low": self.action_low.tolist(),
                "high": self.action_high.tolist(),
            },
            "goal": {"components": self.goal_components, "radius": self.goal_radius},
            "model": {"kind": "remote", "url": model_url},
        }
        if self.distance_weights is not None:
            d["distance"] = {"weights": list(self.distance_weights)}
        if self.periodic:
            d["state"]["periodic"] = list(self.periodic)
        return d

    # ---------------------------------------------------------------- the true world

    @abstractmethod
    def true_step(self, s: Array, a: Array) -> Array:
        """Resets MuJoCo to ``s``, executes ``a``, returns the observed next state.
        Deterministic."""

    def true_steps(self, states: Array, actions: Array) -> Array:
        return np.array([self.true_step(s, a) for s, a in zip(states, actions, strict=True)])

    def execute(self, start: Array, actions: Array) -> Array:
        """Open loop: the observed states, the start first."""
        states = [np.asarray(start, dtype=np.float64)]
        for a in actions:
            states.append(self.true_step(states[-1], np.asarray(a, dtype=np.float64)))
        return np.array(states)

    # ---------------------------------------------------------------- shared helpers

    def difference(self, a: Array, b: Array) -> Array:
        """``a − b`` row-wise, periodic components the shorter way round."""
        diff = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
        for i in self.periodic:
            period = self.state_high[i] - self.state_low[i]
            diff[..., i] -= period * np.round(diff[..., i] / period)
        return diff

    def distance(self, a: Array, b: Array) -> Array:
        """The experiment's distance, row-wise."""
        w = np.ones(a.shape[-1]) if self.distance_weights is None else np.asarray(self.distance_weights)
        return np.sqrt(np.sum(w * self.difference(a, b) ** 2, axis=-1))

    def true_deviation(self, states: Array, actions: Array) -> Array:
        """``d(f̂(s, a), s')`` with ``s'`` from MuJoCo."""
        return self.distance(self.f_hat(states, actions), self.true_steps(states, actions))

    def at_goal(self, s: Array, goal: Array) -> bool:
        return bool(np.linalg.norm(np.asarray(s)[self.goal_components] - goal) <= self.goal_radius)

    @abstractmethod
    def sample_state(self, rng: np.random.Generator) -> Array:
        """A valid state (at rest, not in collision), uniformly over what the robot can be in."""

    def sample_action(self, rng: np.random.Generator) -> Array:
        return rng.uniform(self.action_low, self.action_high)

    def sample_problem(self, rng: np.random.Generator) -> tuple[Array, Array]:
        """A start and a goal (a vector over ``goal_components``) ``problem_distance`` apart,
        both taken from valid states."""
        lo, hi = self.problem_distance
        while True:
            s, g = self.sample_state(rng), self.sample_state(rng)
            gv = g[self.goal_components]
            if lo <= np.linalg.norm(gv - s[self.goal_components]) <= hi:
                return s, gv

    def parameters(self) -> dict[str, Any]:
        """The physical parameters, for the report."""
        return {}


class ServoArm(Robot):
    """An arm whose joints are position servos: the state is the joint angles, an action a
    displacement of the servos' targets held for ``nstep`` simulation steps from rest, and the
    lab's model ``clip(s + a)`` (the arm goes where it is told). Subclasses set ``model``,
    ``data`` and ``nstep`` in ``__init__``."""

    model: mujoco.MjModel
    data: mujoco.MjData
    nstep: int

    def f_hat(self, states: Array, actions: Array) -> Array:
        return np.clip(states + actions, self.state_low, self.state_high)

    def true_step(self, s: Array, a: Array) -> Array:
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:] = s
        d.ctrl[:] = np.clip(s + a, self.state_low, self.state_high)
        run_until_settled(m, d, self.nstep, self.nstep // 5)
        return np.clip(d.qpos.copy(), self.state_low, self.state_high)

    def in_collision(self, s: Array) -> bool:
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:] = s
        mujoco.mj_forward(m, d)
        return any(d.contact[i].dist < 0 for i in range(d.ncon))

    def sample_state(self, rng: np.random.Generator) -> Array:
        while True:
            s = rng.uniform(self.state_low, self.state_high)
            if not self.in_collision(s):
                return s
