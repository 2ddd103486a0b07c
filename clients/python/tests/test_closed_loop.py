"""Integration tests against the real server: a learning loop that outlives searches past the
planning deadline, training episodes executed closed loop and under a monitor, and test-time
plans executed closed loop. The world is ``test_integration``'s: a point on a table whose model
``clip(s + a)`` ignores an icy band ``0.45 ≤ x ≤ 0.75`` where it slides 1.8 times as far."""

from __future__ import annotations

import json
import logging
import time

import httpx
import numpy as np
import pytest
from conftest import MakeServer
from test_integration import model, settings, true_step

from precond_client import Client, DeadlineExceeded, DeviationExceeded, Metric, serve_model
from precond_client.models import Array

pytestmark = pytest.mark.integration

D_MAX = 0.05


class CountingTransport(httpx.HTTPTransport):
    """Counts the proposals asked for, by goal."""

    def __init__(self) -> None:
        super().__init__()
        self.searches: dict[tuple[float, ...], int] = {}

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.method == "POST" and request.url.path.endswith("/proposals"):
            goal = tuple(json.loads(request.content)["goal"])
            self.searches[goal] = self.searches.get(goal, 0) + 1
        return super().handle_request(request)


def test_a_learning_loop_skips_problems_it_cannot_plan_in_time_and_goes_on(
    make_server: MakeServer, caplog: pytest.LogCaptureFixture
) -> None:
    # The shortest deadline the server allows; a goal walled in by obstacles cannot be
    # reached, so its search runs until the deadline at every β the loop tries.
    server = make_server(extra_args=["--plan-timeout-ms", "100"])
    transport = CountingTransport()
    client = Client(server.url, timeout=60, client_id="arm", transport=transport)
    client.create_experiment(
        name="walled",
        domain={
            "kind": "kinematic",
            "obstacles": [
                {"low": [0.6, 0.6], "high": [1.0, 0.7]},
                {"low": [0.6, 0.6], "high": [0.7, 1.0]},
            ],
        },
        learning={"n_candidates": 1, "max_extensions": 200_000},
    )
    walled = [(0.9, 0.9), (0.85, 0.8)]
    problems = [
        ([0.1, 0.1], [0.3, 0.1]),
        ([0.1, 0.1], list(walled[0])),
        ([0.1, 0.5], [0.4, 0.5]),
        ([0.2, 0.2], list(walled[1])),
    ]
    t0 = time.monotonic()
    with caplog.at_level(logging.INFO, logger="precond_client"):
        learner = client.learn(problems)
        for episode in learner:  # a kinematic robot does what its model says
            episode.post(episode.predicted_states)
    elapsed = time.monotonic() - t0

    # It finished, said what it skipped, and searched each walled goal twice, not nine times.
    skipped = {(s.problem, s.reason) for s in learner.skipped}
    assert {(1, "deadline"), (3, "deadline")} <= skipped
    for goal in walled:
        assert transport.searches[goal] == 2
    assert learner.posted + learner.deadline == 4 and learner.failed == 0
    for s in learner.skipped:
        assert isinstance(s.error, DeadlineExceeded) and s.error.details["timeout_ms"] == 100
    assert client.get_experiment().n_trajectories == learner.posted
    # Each walled goal: two searches of 0.1 s and the server's Retry-After (1 s) between.
    assert elapsed < 30
    messages = [r.getMessage() for r in caplog.records]
    assert any(
        m.startswith("problem 1: planning: the search passed the server's deadline of 100 ms")
        and m.endswith("search 2/2 in 1.0 s")
        for m in messages
    ), messages
    assert any(m.startswith("problem 3: skipped, 2 searches passed") for m in messages)


def execute_open_loop(start: Array, actions: Array) -> Array:
    states = [np.asarray(start, dtype=np.float64)]
    for a in actions:
        states.append(true_step(states[-1], a))
    return np.array(states)


def test_an_episode_runs_closed_loop_to_its_goal_through_continuations(
    make_server: MakeServer,
) -> None:
    with serve_model(model, "127.0.0.1", 0) as served:
        server = make_server([f"http://127.0.0.1:{served.port}/"])
        client = Client(server.url, timeout=60, client_id="arm-1")
        exp = client.create_experiment(settings(served.url, "closed loop"))
        metric = Metric.of(exp)
        start, goal = np.array([0.1, 0.5]), np.array([0.9, 0.5])
        learner = client.learn([(start, goal)])
        episodes = []
        for episode in learner:
            first = episode.proposal
            execution = episode.run_closed_loop(true_step, max_steps=80)
            episodes.append(episode)
        (ep,) = episodes
        assert learner.posted == 1 and learner.abandoned == 0

        # The robot slid on the ice, left the plan, and the episode planned again from where
        # it was, until it reached the goal.
        assert execution.success and metric.at_goal(execution.states[-1], goal)
        assert execution.replans >= 1
        assert execution.proposal_ids[0] == first.id
        assert len(execution.proposal_ids) == execution.replans + 1
        assert ep.proposal.id == execution.proposal_ids[-1]
        on_ice = (execution.states[:-1, 0] >= 0.45) & (execution.states[:-1, 0] <= 0.75)
        assert (execution.deviations[on_ice] > 0).any()
        # Every step stored once: one trajectory per proposal, chained from the start.
        assert ep.stored_trajectory_ids == [t.id for t in execution.trajectories]
        assert len(ep.stored_trajectory_ids) == len(execution.proposal_ids)
        stored = list(client.transitions())
        assert len(stored) == execution.steps == client.get_experiment().n_transitions
        np.testing.assert_allclose([t.s for t in stored], execution.states[:-1])
        np.testing.assert_allclose([t.a for t in stored], execution.actions)
        np.testing.assert_allclose([t.s_next for t in stored], execution.states[1:])
        for pid, tid in zip(execution.proposal_ids, ep.stored_trajectory_ids, strict=True):
            t = client.get_trajectory(tid)
            assert t.proposal_id == pid and not t.deviating
            assert client.get_proposal(pid).status == "executed"
        # Each continuation left its plan beyond d_max, or came to its plan's end.
        for tid, pid in zip(ep.stored_trajectory_ids[:-1], execution.proposal_ids, strict=False):
            t = client.get_trajectory(tid)
            planned = client.get_proposal(pid)
            off = metric.distance(planned.states[t.n_transitions], t.transitions[-1].s_next)
            assert t.partial
            assert off > D_MAX or t.n_transitions == len(planned.actions)

        # Replaying the first continuation (a lost answer) stores nothing and answers the
        # proposal it made.
        prefix = client.get_trajectory(ep.stored_trajectory_ids[0]).transitions
        again = client.continue_proposal(
            execution.proposal_ids[0],
            [{"s": t.s.tolist(), "a": t.a.tolist(), "s_next": t.s_next.tolist()} for t in prefix],
        )
        assert again.trajectory.replayed and again.trajectory.id == ep.stored_trajectory_ids[0]
        assert again.proposal.id == execution.proposal_ids[1]
        assert client.get_experiment().n_transitions == execution.steps


def first_beyond(start: Array, actions: Array, predicted: Array, one_step: bool) -> int:
    """The first step a monitor stops at: the robot's state further than ``D_MAX`` from the
    plan's prediction, or (``one_step``) from the model's prediction from where it was."""
    s = np.asarray(start, dtype=np.float64)
    for k, a in enumerate(actions):
        expected = model(s[None], a[None])[0] if one_step else predicted[k + 1]
        s = true_step(s, a)
        if np.linalg.norm(s - expected) > D_MAX:
            return k
    raise AssertionError("the plan never leaves the tolerance")


def test_a_monitor_stops_an_episode_where_the_model_was_wrong_and_posts_it_partial(
    make_server: MakeServer,
) -> None:
    with serve_model(model, "127.0.0.1", 0) as served:
        server = make_server([f"http://127.0.0.1:{served.port}/"])
        client = Client(server.url, timeout=60, client_id="arm-1")
        client.create_experiment(settings(served.url, "monitored"))
        problems = [([0.1, 0.3], [0.9, 0.3]), ([0.1, 0.7], [0.9, 0.7])]
        results = []
        for i, episode in enumerate(client.learn(problems)):
            one_step = i == 1
            expected = first_beyond(
                episode.start, episode.actions, episode.predicted_states, one_step
            )
            execution = episode.execute(true_step, predict=model if one_step else None)
            results.append((episode, execution, expected))
        assert len(results) == 2
        for episode, execution, expected in results:
            assert execution.status == "deviated" and execution.steps == expected + 1
            assert execution.deviations[-1] > D_MAX >= execution.deviations[:-1].max(initial=0)
            (posted,) = execution.trajectories
            t = client.get_trajectory(posted.id)
            assert t.partial and not t.deviating and t.proposal_id == episode.proposal.id
            assert t.n_transitions == expected + 1
            assert client.get_proposal(episode.proposal.id).status == "executed"
        # Judged by the robot's own model, the monitor stops where the server's label (the
        # model's one-step error) first passes d_max.
        _, one_step_run, _ = results[1]
        labels = client.get_trajectory(one_step_run.trajectories[0].id).deviations
        np.testing.assert_allclose(labels, one_step_run.deviations, rtol=1e-9)
        assert labels[-1] > D_MAX and (labels[:-1] <= D_MAX).all()


def test_a_test_time_plan_runs_closed_loop_and_a_monitor_stops_one_open_loop(
    make_server: MakeServer,
) -> None:
    with serve_model(model, "127.0.0.1", 0) as served:
        server = make_server([f"http://127.0.0.1:{served.port}/"])
        client = Client(server.url, timeout=60)
        exp = client.create_experiment(settings(served.url, "test time"))
        metric = Metric.of(exp)
        start, goal = np.array([0.1, 0.5]), np.array([0.9, 0.5])
        # With the prior, β = −3 trusts everything: the plans cross the ice.
        run = client.execute_plan(start, goal, true_step, beta=-3.0, max_steps=80)
        assert run.success and metric.at_goal(run.states[-1], goal)
        assert run.replans >= 1 and run.steps == len(run.actions) == len(run.deviations)
        # Every replanned step started where the robot was.
        np.testing.assert_allclose(
            run.states[1:],
            [true_step(s, a) for s, a in zip(run.states[:-1], run.actions, strict=True)],
        )
        assert client.get_experiment().n_trajectories == 0  # nothing is stored

        plan = client.plan(start, goal, beta=-3.0)
        assert plan.trajectory is not None
        stop = first_beyond(start, plan.trajectory.actions, plan.trajectory.states, False)
        monitor = client.monitor(plan)
        with pytest.raises(DeviationExceeded) as e:
            for action in monitor.actions:
                monitor.observe(true_step(monitor.state, action))
        assert e.value.step == stop and e.value.deviation > D_MAX == e.value.tolerance
        (posted,) = e.value.execution.trajectories
        t = client.get_trajectory(posted.id)
        assert t.partial and t.proposal_id is None and t.n_transitions == stop + 1
        np.testing.assert_allclose(t.states[-1], e.value.observed)
