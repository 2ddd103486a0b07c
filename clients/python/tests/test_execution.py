"""Unit tests of executing plans (no server): the experiment's distance and goal test, the
monitor that stops an execution where it deviates, test-time closed loop with a scripted
planner, and a training episode's closed loop against a scripted server."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import httpx
import numpy as np
import pytest
from test_client import (
    FakeLoopServer,
    created_json,
    error,
    experiment_json,
    make_client,
    proposal_json,
)

from precond_client import (
    DeadlineExceeded,
    DeviationExceeded,
    Experiment,
    Metric,
    Monitor,
    NoPlan,
    Transition,
)
from precond_client.execution import execute_plan
from precond_client.models import Array, Plan, TrajectoryCreated


def experiment(domain: dict[str, Any], d_max: float = 0.1) -> Experiment:
    d = experiment_json(1)
    d["domain"] = domain
    d["d_max"] = d_max
    return Experiment.from_json(d)


def test_the_metric_is_the_experiments_distance_and_goal_test() -> None:
    custom = Metric.of(
        experiment(
            {
                "kind": "custom",
                "distance": {"weights": [4.0, 1.0, 0.0]},
                "goal": {"components": [0, 1], "radius": 0.05},
            },
            d_max=0.03,
        )
    )
    assert custom.d_max == 0.03
    # sqrt(4 · 0.1² + 1 · 0.2² + 0 · 5²)
    assert custom.distance([0.0, 0.0, 0.0], [0.1, 0.2, 5.0]) == pytest.approx(np.sqrt(0.08))
    assert custom.at_goal([0.5, 0.5, 9.0], [0.53, 0.53])  # 0.042 on components 0, 1
    assert not custom.at_goal([0.5, 0.5, 9.0], [0.54, 0.54])

    # A heading in [−π, π] declared periodic: 3.1 and −3.1 are 0.083 apart, not 6.2.
    heading = Metric.of(
        experiment(
            {
                "kind": "custom",
                "state": {"low": [0, -np.pi], "high": [1, np.pi], "periodic": [1]},
                "distance": {"weights": [1.0, 1.0]},
                "goal": {"components": [1], "radius": 0.1},
            }
        )
    )
    short = 2 * np.pi - 6.2
    assert heading.distance([0.5, 3.1], [0.5, -3.1]) == pytest.approx(short)
    assert heading.at_goal([0.5, 3.1], [-3.1]) and not heading.at_goal([0.5, 2.9], [-3.1])

    # A radius per goal component: 5 cm in x, 0.3 rad in heading (an ellipse).
    ellipse = Metric.of(
        experiment(
            {
                "kind": "custom",
                "state": {"low": [0, -np.pi], "high": [1, np.pi], "periodic": [1]},
                "goal": {"components": [0, 1], "radius": [0.05, 0.3]},
            }
        )
    )
    assert ellipse.at_goal([0.5, 3.1], [0.53, -3.1])  # (0.6² + 0.28²) < 1
    assert not ellipse.at_goal([0.5, 3.1], [0.54, 2.9])  # (0.8² + 0.67²) > 1

    kinematic = Metric.of(experiment({"kind": "kinematic", "goal_radius": 0.05}))
    assert kinematic.distance([0, 0], [0.3, 0.4]) == pytest.approx(0.5)
    assert kinematic.at_goal([0.5, 0.5], [0.5, 0.54]) and not kinematic.at_goal(
        [0.5, 0.5], [0.5, 0.56]
    )

    grid = Metric.of(experiment({"kind": "icy_gridworld"}))
    assert grid.at_goal([3, 2], [3, 2]) and not grid.at_goal([3, 2], [3, 3])

    water = Metric.of(experiment({"kind": "water_plant"}))
    p = np.zeros(9)
    o = p.copy()
    o[[0, 1, 3, 4, 5, 7]] = [0.3, 0.4, 0.2, 0.0, 0.1, 0.4]
    assert water.distance(p, o) == pytest.approx(0.5 + 0.1 + 0.5 * (0.2 + 0.4))
    poured = np.zeros(9)
    poured[7], poured[8] = 0.99, 0.01
    assert water.at_goal(poured, [1.0])
    poured[8] = 0.03  # more than 2 % spilled
    assert not water.at_goal(poured, [1.0])

    with pytest.raises(ValueError, match="no distance or goal test"):
        Metric.of(experiment({"kind": "teleporter"}))


class Posts:
    """Records what a monitor posts."""

    def __init__(self) -> None:
        self.calls: list[tuple[list[dict[str, Any]], bool]] = []

    def __call__(self, transitions: Sequence[Transition], partial: bool) -> TrajectoryCreated:
        self.calls.append(([t.to_json() for t in transitions], partial))
        n = len(transitions)
        return TrajectoryCreated.from_json(
            {
                "id": len(self.calls),
                "experiment_id": 1,
                "proposal_id": 7,
                "partial": partial,
                "deviating": False,
                "source": None,
                "n_transitions": n,
                "deviations": [0.0] * n,
                "iteration": 0,
                "model_version": 0,
                "n_trajectories": 1,
                "created_at": "t",
            }
        )


EUCLID = Metric(0.05, "kinematic", goal_radius=0.05)
PLAN_STATES = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0], [0.3, 0.0]])
PLAN_ACTIONS = np.diff(PLAN_STATES, axis=0)


def test_the_monitor_stops_at_the_first_step_beyond_the_tolerance_and_posts_it_partial() -> None:
    posts = Posts()
    m = Monitor(
        PLAN_STATES[0], PLAN_ACTIONS, PLAN_STATES, tolerance=0.05, metric=EUCLID, post=posts
    )
    assert m.observe([0.11, 0.0]) == pytest.approx(0.01)
    with pytest.raises(DeviationExceeded) as stop:
        m.observe([0.2, 0.07])  # 0.07 from the predicted [0.2, 0]
    e = stop.value
    assert (e.step, e.tolerance) == (1, 0.05) and e.deviation == pytest.approx(0.07)
    np.testing.assert_allclose(e.predicted, [0.2, 0.0])
    ex = e.execution
    assert ex.status == "deviated" and ex.steps == 2 and not ex.success
    np.testing.assert_allclose(ex.deviations, [0.01, 0.07])
    # The deviating step is posted with the others: it is what the model got wrong.
    ((posted, partial),) = posts.calls
    assert partial is True
    assert posted == [
        {"s": [0.0, 0.0], "a": [0.1, 0.0], "s_next": [0.11, 0.0]},
        {"s": [0.11, 0.0], "a": [0.1, 0.0], "s_next": [0.2, 0.07]},
    ]
    assert ex.trajectories[0].id == 1 and m.done and m.next_action is None
    with pytest.raises(RuntimeError, match="over"):
        m.observe([0.3, 0.0])


def test_the_monitor_posts_a_whole_run_and_says_whether_it_reached_the_goal() -> None:
    posts = Posts()
    m = Monitor(
        PLAN_STATES[0],
        PLAN_ACTIONS,
        PLAN_STATES,
        tolerance=0.05,
        metric=EUCLID,
        post=posts,
        goal=[0.3, 0.0],
    )
    for s in ([0.1, 0.01], [0.2, 0.02], [0.3, 0.03]):
        assert m.next_action is not None
        m.observe(s)
    ex = m.finish()
    assert ex.status == "goal" and ex.success and posts.calls[0][1] is False
    assert m.finish().status == "goal" and len(posts.calls) == 1  # posted once

    stopped = Monitor(
        PLAN_STATES[0], PLAN_ACTIONS, PLAN_STATES, tolerance=0.05, metric=EUCLID, post=posts
    )
    stopped.observe([0.1, 0.0])
    assert stopped.finish().status == "stopped" and posts.calls[-1][1] is True


def test_with_the_robots_model_a_step_is_judged_from_where_the_robot_was() -> None:
    posts = Posts()

    def f_hat(s: Array, a: Array) -> Array:
        return s + a

    m = Monitor(
        PLAN_STATES[0],
        PLAN_ACTIONS,
        PLAN_STATES,
        tolerance=0.05,
        metric=EUCLID,
        post=posts,
        predict=f_hat,
        send_predictions=True,
    )
    # 0.04 off the plan after each step, 0.12 after three: each step alone is right.
    for k, s in enumerate(([0.1, 0.04], [0.2, 0.08], [0.3, 0.12])):
        assert m.observe(s) == pytest.approx(0.04)
        assert m.step == k + 1
    assert m.finish().status == "done"
    first = posts.calls[0][0][0]
    assert first["s_pred"] == [0.1, 0.0]


def test_a_plan_and_predictions_must_agree() -> None:
    with pytest.raises(ValueError, match="predicted states"):
        Monitor([0, 0], PLAN_ACTIONS, PLAN_STATES[:3], tolerance=0.1, metric=EUCLID)


def planned(states: Array) -> Plan:
    states = np.asarray(states, dtype=np.float64)
    return Plan.from_json(
        {
            "found": True,
            "extensions": 10,
            "rejections": {"constraints": 0, "precondition": 0},
            "beta": 2.0,
            "d_max": 0.05,
            "model_version": 1,
            "trajectory": {
                "states": states.tolist(),
                "actions": np.diff(states, axis=0).tolist(),
                "mu": [0.0] * (len(states) - 1),
                "sigma": [0.0] * (len(states) - 1),
            },
        }
    )


def straight(start: Array, goal: Array) -> Plan:
    """A planner: steps of at most 0.1 straight to the goal."""
    n = max(1, int(np.ceil(np.linalg.norm(goal - start) / 0.1)))
    return planned(np.linspace(start, goal, n + 1))


def test_test_time_closed_loop_replans_where_the_robot_drifts() -> None:
    calls: list[Array] = []

    def plan(s: Array, g: Array) -> Plan:
        calls.append(s.copy())
        return straight(s, g)

    def drifting(s: Array, a: Array) -> Array:
        moved: Array = s + a + np.array([0.0, 0.03])  # the robot drifts up 0.03 per step
        return moved

    ex = execute_plan(
        plan,
        [0.0, 0.0],
        [0.6, 0.0],
        drifting,
        metric=EUCLID,
        tolerance=0.05,
        max_steps=50,
        max_replans=20,
    )
    assert ex.success and ex.replans >= 2 and len(calls) == ex.replans + 1
    assert EUCLID.at_goal(ex.states[-1], [0.6, 0.0])
    assert ex.states.shape == (ex.steps + 1, 2) and ex.predicted.shape == (ex.steps, 2)
    # It replanned whenever the drift passed the tolerance: never further off than that.
    assert ex.deviations.max() <= 0.05 + 0.03 + 1e-12
    # Open loop the same robot misses the goal.
    s = np.zeros(2)
    for a in straight(np.zeros(2), np.array([0.6, 0.0])).trajectory.actions:  # type: ignore[union-attr]
        s = drifting(s, a)
    assert not EUCLID.at_goal(s, [0.6, 0.0])


def test_test_time_closed_loop_reports_why_it_ended() -> None:
    def nowhere(s: Array, g: Array) -> Plan:
        return Plan.from_json(
            {
                "found": False,
                "extensions": 5000,
                "rejections": {"constraints": 0, "precondition": 5000},
                "beta": 2.0,
                "d_max": 0.05,
                "model_version": 1,
                "trajectory": None,
            }
        )

    def stuck(s: Array, a: Array) -> Array:
        return s  # the robot does not move

    common: dict[str, Any] = {"metric": EUCLID, "tolerance": 0.05, "max_replans": 3}
    assert execute_plan(nowhere, [0, 0], [0.5, 0], stuck, max_steps=9, **common).status == "no_plan"
    replans = execute_plan(straight, [0, 0], [0.5, 0], stuck, max_steps=99, **common)
    assert (replans.status, replans.replans, replans.steps) == ("replans", 3, 4)
    budget = execute_plan(
        straight, [0, 0], [0.5, 0], lambda s, a: s + 0.5 * a, max_steps=3, **common
    )
    assert budget.status == "budget" and budget.steps == 3
    stops = execute_plan(straight, [0, 0], [0.5, 0], lambda s, a: None, max_steps=9, **common)
    assert stops.status == "stopped" and stops.steps == 0
    there = execute_plan(straight, [0.5, 0], [0.5, 0], stuck, max_steps=9, **common)
    assert there.success and there.steps == 0


class ContinuingServer(FakeLoopServer):
    """The loop's fake server with ``…/continue``: each continuation answers the next of
    ``answers`` — ``"ok"`` (the prefix stored, a new proposal from where the robot is),
    ``"no_plan"`` or ``"deadline"`` (the prefix stored, then the error)."""

    def __init__(self, answers: list[str]) -> None:
        super().__init__()
        self.answers = answers
        self.continued: list[tuple[int, str, int]] = []  # (proposal, key, transitions)
        self.stored = 100
        self.keys: dict[str, int] = {}

    def __call__(self, req: httpx.Request) -> httpx.Response:
        path = req.url.path
        if not path.endswith("/continue"):
            return super().__call__(req)
        pid = int(path.split("/")[-2])
        body = json.loads(req.content)
        self.continued.append((pid, req.headers["Idempotency-Key"], len(body["transitions"])))
        self.proposals[pid]["status"] = "executed"
        key = req.headers["Idempotency-Key"]
        if key not in self.keys:  # a replay stores nothing again
            self.stored += 1
            self.keys[key] = self.stored
        stored = self.keys[key]
        answer = self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]
        if answer == "no_plan":
            return error(
                422, "no_plan", "none", {"extensions": 5000, "stored_trajectory_id": stored}
            )
        if answer == "deadline":
            return error(
                503,
                "deadline_exceeded",
                "deadline",
                {
                    "extensions": 10,
                    "timeout_ms": 100,
                    "retry_after_seconds": 0,
                    "stored_trajectory_id": stored,
                },
            )
        held = self.proposals[pid]
        new_id = len(self.proposals) + 1
        p = proposal_json(new_id, body["transitions"][-1]["s_next"], held["goal"])
        p["client_id"] = held["client_id"]
        self.proposals[new_id] = p
        created = created_json(stored, pid)
        created["partial"] = True
        return httpx.Response(201, json={"trajectory": created, "proposal": p})


def drift_up(s: Array, a: Array) -> Array:
    """The robot: 0.2 off in y at every step (d_max is 0.1)."""
    moved: Array = s + a + np.array([0.0, 0.2])
    return moved


@pytest.mark.parametrize(
    ("answers", "status", "error"),
    [(["ok", "no_plan"], "no_plan", NoPlan), (["ok", "deadline"], "failed", DeadlineExceeded)],
)
def test_a_closed_loop_episode_ends_when_a_continuation_fails_with_its_prefix_stored(
    answers: list[str], status: str, error: type
) -> None:
    server = ContinuingServer(answers)
    c = make_client(server, experiment_id=1, client_id="r1")
    c._sleep = lambda _s: None
    learner = c.learn([([0.0, 0.0], [1.0, 0.0])])
    for episode in learner:
        execution = episode.run_closed_loop(drift_up)
    assert execution.status == status and isinstance(execution.error, error)
    # Two continuations, each of the one step of its proposal, under continue-<id>; the
    # client repeats a search past the deadline once (the same key: nothing stored twice).
    repeats = 2 if status == "failed" else 1
    assert server.continued == [(1, "continue-1", 1)] + [(2, "continue-2", 1)] * repeats
    assert execution.proposal_ids == (1, 2) and execution.replans == 1
    assert episode.stored_trajectory_ids == [101, 102]
    assert execution.stored_trajectory_ids == (101, 102)
    # Nothing posted after the stored prefix, nothing abandoned: the episode counts as posted.
    assert server.posted == [] and server.abandoned == []
    assert (learner.posted, learner.abandoned) == (1, 0)


def test_a_robot_that_stops_at_once_gives_its_lease_up() -> None:
    server = ContinuingServer([])
    c = make_client(server, experiment_id=1, client_id="r1")
    learner = c.learn([([0.0, 0.0], [1.0, 0.0])])
    for episode in learner:
        execution = episode.run_closed_loop(lambda s, a: None)
    assert execution.status == "stopped" and execution.steps == 0
    assert server.abandoned == [1] and (learner.posted, learner.abandoned) == (0, 1)


def test_an_episode_executed_under_a_monitor_posts_its_prefix_once() -> None:
    server = ContinuingServer([])
    c = make_client(server, experiment_id=1, client_id="r1")
    for episode in c.learn([([0.0, 0.0], [1.0, 0.0])]):
        execution = episode.execute(drift_up)
    assert execution.status == "deviated" and execution.steps == 1
    assert server.posted == [1] and episode.result is not None
