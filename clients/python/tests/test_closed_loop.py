"""Integration tests against the real server: a learning loop that outlives searches past the
planning deadline."""

from __future__ import annotations

import json
import logging
import time

import httpx
import pytest
from conftest import MakeServer

from precond_client import Client, DeadlineExceeded

pytestmark = pytest.mark.integration


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
