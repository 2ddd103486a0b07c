"""Evaluation shared by every column: test plans open and closed loop, the precondition against
the truth on held-out state-actions, unsafe steps in test plans.

A *planner* is ``plan(start, goal) -> (actions, predicted states) | None``: the learned
experiment's ``client.plan`` at the test β, or a reference experiment's (oracle, baseline) at a
very negative β. The same functions judge all three, so the columns differ only in what the
service's planner trusts.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from precond_client import Client, errors

from robot import Array, Robot

Planned = tuple[Array, Array]
"""``(actions (T, m), predicted states (T + 1, n))``."""
Planner = Callable[[Array, Array], "Planned | None"]

CLOSED_LOOP_BUDGET = 3
"""Closed loop may take this many times the first plan's length in steps."""


@dataclass
class Failures:
    """Requests the loop or the evaluation could not complete, by kind (``deadline_exceeded``,
    ``no_plan``, ``model_unavailable``, …)."""

    counts: Counter[str] = field(default_factory=Counter)

    def add(self, where: str, e: Exception) -> None:
        code = getattr(e, "code", None) or type(e).__name__
        self.counts[f"{where}:{code}"] += 1

    def as_dict(self) -> dict[str, int]:
        return dict(sorted(self.counts.items()))


def service_planner(client: Client, failures: Failures, beta: float | None = None,
                    timings: list[float] | None = None,
                    max_extensions: int | None = None) -> Planner:
    """``client.plan`` at ``beta`` (None: the experiment's test β); a refused or failed plan is
    "no plan", counted in ``failures``."""

    def plan(start: Array, goal: Array) -> Planned | None:
        t0 = time.monotonic()
        try:
            p = client.plan(start, goal, beta=beta, max_extensions=max_extensions)
        except errors.ApiError as e:
            failures.add("plan", e)
            return None
        finally:
            if timings is not None:
                timings.append(time.monotonic() - t0)
        if not p.found or p.trajectory is None:
            return None
        return np.asarray(p.trajectory.actions), np.asarray(p.trajectory.states)

    return plan


def open_loop(robot: Robot, start: Array, goal: Array, planned: Planned) -> tuple[bool, Array]:
    """Executes the plan's actions; success if the end state is within the goal."""
    states = robot.execute(start, planned[0])
    return robot.at_goal(states[-1], goal), states


def closed_loop(robot: Robot, planner: Planner, start: Array, goal: Array,
                first: Planned, seconds: float | None = None) -> dict[str, Any]:
    """Step by step: after each step, re-plan from where the robot is when the observed state is
    farther than ``d_max`` from the plan's prediction, or when the plan ran out short of the goal;
    at most ``CLOSED_LOOP_BUDGET`` × the first plan's length steps. Success: within the goal
    (checked after every step). A re-plan that finds nothing ends the attempt, and so does a
    re-plan due after ``seconds`` of wall time (outcome ``time``: the references' slow
    planner)."""
    t0 = time.monotonic()
    budget = CLOSED_LOOP_BUDGET * len(first[0])
    s = np.asarray(start, dtype=np.float64)
    actions, states = first
    i = 0
    steps = replans = 0
    outcome = "budget"
    while steps < budget:
        if i >= len(actions):
            if seconds is not None and time.monotonic() - t0 > seconds:
                outcome = "time"
                break
            replans += 1
            p = planner(s, goal)
            if p is None:
                outcome = "no_plan"
                break
            actions, states = p
            i = 0
        s_next = robot.true_step(s, actions[i])
        steps += 1
        if robot.at_goal(s_next, goal):
            s = s_next
            outcome = "success"
            break
        off = float(robot.distance(s_next, states[i + 1])) > robot.d_max
        s = s_next
        i += 1
        if off:
            i = len(actions)  # re-plan from here
    return {"success": outcome == "success", "outcome": outcome, "steps": steps, "replans": replans}


def test_plans(robot: Robot, planner: Planner, problems: list[tuple[Array, Array]],
               closed: bool, closed_seconds: float | None = None) -> dict[str, Any]:
    """Plans found, open-loop (and closed-loop) success, and the true deviation of every planned
    step (executed from its planned state) over the test problems."""
    found = opened = closed_ok = 0
    lengths: list[int] = []
    unsafe_steps = planned_steps = 0
    per_problem = []
    for start, goal in problems:
        p = planner(start, goal)
        row: dict[str, Any] = {"found": p is not None}
        if p is not None:
            found += 1
            actions, states = p
            lengths.append(len(actions))
            ok, _ = open_loop(robot, start, goal, p)
            opened += ok
            dev = robot.true_deviation(states[:-1], actions)
            unsafe_steps += int(np.sum(dev >= robot.d_max))
            planned_steps += len(dev)
            row.update(length=len(actions), open_loop=ok, max_step_deviation=float(dev.max()))
            if closed:
                c = closed_loop(robot, planner, start, goal, p, closed_seconds)
                closed_ok += c["success"]
                row["closed_loop"] = c
        per_problem.append(row)
    k = len(problems)
    out: dict[str, Any] = {
        "plans_found": found / k,
        "open_loop_success": opened / k,
        "mean_plan_length": float(np.mean(lengths)) if lengths else None,
        "unsafe_step_share": unsafe_steps / planned_steps if planned_steps else None,
        "planned_steps": planned_steps,
        "problems": per_problem,
    }
    if closed:
        out["closed_loop_success"] = closed_ok / k
    return out


def precondition_quality(client: Client, held_s: Array, held_a: Array, held_dev: Array,
                         d_max: float) -> dict[str, Any]:
    """TPR and TNR of the precondition at the test β (the server's default judgement) against
    the true deviation ``< d_max``; the median σ."""
    pre = client.precondition((held_s, held_a))
    truth = held_dev < d_max
    return {
        "tpr": float(np.mean(pre.inside[truth])) if truth.any() else None,
        "tnr": float(np.mean(~pre.inside[~truth])) if (~truth).any() else None,
        "trusted_share": float(np.mean(pre.inside)),
        "median_sigma": float(np.median(pre.sigma)),
        "median_mu": float(np.median(pre.mu)),
    }
