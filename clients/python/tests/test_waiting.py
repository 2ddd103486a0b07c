"""Unit tests (scripted transport, no server) of how the client and its loop wait: the
server's ``Retry-After`` honoured and logged, a search past the deadline repeated a bounded
number of times, a problem that keeps failing skipped and counted instead of raised, and the
loop's progress visible when logging is not configured."""

from __future__ import annotations

import json
import logging
from typing import Any

import httpx
import numpy as np
import pytest
from test_client import FakeLoopServer, error, make_client, proposal_json, run_loop, scripted

from precond_client import DeadlineExceeded, ModelUnavailable, Skipped, ValidationFailed
from precond_client.errors import is_transient, retry_after


def deadline(extensions: int = 5123, retry: int = 30) -> httpx.Response:
    return httpx.Response(
        503,
        headers={"Retry-After": str(retry)},
        json={
            "error": {
                "code": "deadline_exceeded",
                "message": f"the deadline of 30000 ms passed ({extensions} extensions "
                f"searched); retry in {retry} s",
                "details": {
                    "extensions": extensions,
                    "timeout_ms": 30000,
                    "retry_after_seconds": retry,
                },
            }
        },
    )


def recording_sleeps(c: Any) -> list[float]:
    slept: list[float] = []
    c._sleep = slept.append
    return slept


def test_retry_after_is_honoured_beyond_the_backoff_and_every_wait_is_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    unavailable = error(503, "unavailable", "the database does not answer")
    unavailable.headers["Retry-After"] = "30"
    handler, sent = scripted(
        lambda _r: unavailable,
        lambda _r: httpx.Response(200, json={"items": []}),
    )
    c = make_client(handler, max_backoff=5.0)
    slept = recording_sleeps(c)
    with caplog.at_level(logging.INFO, logger="precond_client"):
        assert c.list_experiments() == []
    # The server said 30 s: the back-off's 5 s cap does not shorten it.
    assert slept == [30.0] and len(sent) == 2
    (line,) = [r.getMessage() for r in caplog.records]
    assert line == (
        "GET /v1/experiments: 503 unavailable (the database does not answer); retry 1/8 in 30 s"
    )


def test_an_absurd_retry_after_is_capped() -> None:
    full = error(507, "insufficient_storage", "disk full")
    full.headers["Retry-After"] = "86400"
    handler, _ = scripted(lambda _r: full, lambda _r: httpx.Response(200, json={"items": []}))
    c = make_client(handler, max_retry_after=60.0)
    slept = recording_sleeps(c)
    c.list_experiments()
    assert slept == [60.0]


def test_a_search_past_the_deadline_is_repeated_once_not_eight_times(
    caplog: pytest.LogCaptureFixture,
) -> None:
    handler, sent = scripted(lambda _r: deadline())
    c = make_client(handler, experiment_id=1, client_id="r1")
    slept = recording_sleeps(c)
    with caplog.at_level(logging.INFO, logger="precond_client"), pytest.raises(DeadlineExceeded):
        c.propose([0.0, 0.0], [1.0, 1.0])
    assert len(sent) == 2 and slept == [30.0]
    assert [r.getMessage() for r in caplog.records] == [
        "POST /v1/experiments/1/proposals: 503 deadline_exceeded (the deadline of 30000 ms "
        "passed (5123 extensions searched)); retry 1/1 in 30 s"
    ]
    # Per call, and per client.
    sent.clear()
    with pytest.raises(DeadlineExceeded):
        c.plan([0.0, 0.0], [1.0, 1.0], deadline_retries=0)
    assert len(sent) == 1
    c.deadline_retries = 3
    sent.clear()
    with pytest.raises(DeadlineExceeded):
        c.continue_proposal(1, [{"s": [0, 0], "a": [1, 0], "s_next": [1, 0]}])
    assert len(sent) == 4


def test_a_deadline_that_passed_waiting_for_a_slot_is_retried_like_any_503() -> None:
    # No extension searched: the server was busy, and another try may find a slot.
    answers = [lambda _r: deadline(extensions=0, retry=2)] * 3
    answers.append(lambda r: httpx.Response(201, json=proposal_json(1, [0, 0], [1, 1])))
    handler, sent = scripted(*answers)
    c = make_client(handler, experiment_id=1, client_id="r1")
    slept = recording_sleeps(c)
    assert c.propose([0.0, 0.0], [1.0, 1.0]).id == 1
    assert len(sent) == 4 and slept == [2.0, 2.0, 2.0]


def test_what_is_transient() -> None:
    from precond_client import ApiError, Conflict, NoPlan, TransportError
    from precond_client.errors import InternalError

    assert is_transient(TransportError("down"))
    for status in (429, 502, 503, 504, 507):
        assert is_transient(ApiError(status, "x", "m"))
    assert not is_transient(InternalError(500, "internal", "bug"))
    assert not is_transient(NoPlan(422, "no_plan", "none"))
    assert not is_transient(Conflict(409, "conflict", "held"))
    assert not is_transient(ValueError("x"))
    assert retry_after(ApiError(503, "x", "m", {"retry_after_seconds": 7}), 1.0) == 7.0
    assert retry_after(ApiError(503, "x", "m", None), 1.5) == 1.5


class DoomedServer(FakeLoopServer):
    """The loop's fake server, on which the problems whose goal is in ``doomed`` answer every
    search with ``answer`` (a deadline, or a model that keeps failing)."""

    def __init__(self, doomed: set[tuple[float, ...]], answer: Any) -> None:
        super().__init__()
        self.doomed = doomed
        self.answer = answer
        self.searched: dict[tuple[float, ...], int] = {}

    def __call__(self, req: httpx.Request) -> httpx.Response:
        if req.url.path.endswith("/proposals"):
            goal = tuple(json.loads(req.content)["goal"])
            self.searched[goal] = self.searched.get(goal, 0) + 1
            if goal in self.doomed:
                response: httpx.Response = self.answer()
                return response
        return super().__call__(req)


def test_learn_skips_a_problem_whose_searches_keep_passing_the_deadline(
    caplog: pytest.LogCaptureFixture,
) -> None:
    server = DoomedServer({(9.0, 9.0)}, deadline)
    c = make_client(server, experiment_id=1, client_id="r1")
    slept = recording_sleeps(c)
    problems = [([0.0, 0.0], [1.0, 0.0]), ([0.0, 0.0], [9.0, 9.0]), ([0.0, 0.0], [2.0, 0.0])]
    seen: list[Any] = []
    with caplog.at_level(logging.INFO, logger="precond_client"):
        learner = c.learn(problems, progress=seen.append)
        assert run_loop(learner) == [1, 2]
    # Two searches (the default deadline_attempts), one wait of the server's 30 s between.
    assert server.searched[(9.0, 9.0)] == 2
    assert slept == [30.0]
    assert (learner.posted, learner.deadline, learner.failed, learner.no_plan) == (2, 1, 0, 0)
    (skipped,) = learner.skipped
    assert (skipped.problem, skipped.reason) == (1, "deadline")
    assert isinstance(skipped.error, DeadlineExceeded)
    np.testing.assert_array_equal(skipped.goal, [9.0, 9.0])
    assert [p.event for p in seen] == ["posted", "deadline", "posted"]
    assert seen[1].deadline == 1
    messages = [r.getMessage() for r in caplog.records]
    assert "problem 1: planning from [0.0, 0.0] to [9.0, 9.0]" in messages
    assert (
        "problem 1: planning: the search passed the server's deadline of 30000 ms "
        "(5123 extensions); search 2/2 in 30 s" in messages
    )
    assert (
        "problem 1: skipped, 2 searches passed the server's deadline of 30000 ms "
        "(the last after 5123 extensions)" in messages
    )


def test_learn_skips_a_problem_the_server_keeps_failing_and_says_each_wait() -> None:
    def model_down() -> httpx.Response:
        return error(502, "model_unavailable", "the model at http://m/ refused")

    server = DoomedServer({(9.0, 9.0)}, model_down)
    c = make_client(server, experiment_id=1, client_id="r1", retries=2)
    slept = recording_sleeps(c)
    problems = [([0.0, 0.0], [9.0, 9.0]), ([0.0, 0.0], [2.0, 0.0])]
    learner = c.learn(problems, transient_attempts=2)
    assert run_loop(learner) == [1]
    # Twice the client's 3 requests; between the two loop attempts the loop's own wait.
    assert server.searched[(9.0, 9.0)] == 6
    assert len(slept) == 2 * 2 + 1 and slept[2] == 5.0
    assert (learner.failed, learner.deadline) == (1, 0)
    (skipped,) = learner.skipped
    assert isinstance(skipped, Skipped) and (skipped.problem, skipped.reason) == (0, "failed")
    assert isinstance(skipped.error, ModelUnavailable)


def test_learn_still_raises_what_is_not_transient() -> None:
    def bad() -> httpx.Response:
        return error(422, "validation_failed", "goal: outside", {"field": "goal", "reason": "x"})

    server = DoomedServer({(9.0, 9.0)}, bad)
    c = make_client(server, experiment_id=1, client_id="r1")
    with pytest.raises(ValidationFailed):
        run_loop(c.learn([([0.0, 0.0], [9.0, 9.0])]))


def test_a_post_that_fails_transiently_is_tried_again_with_the_same_key() -> None:
    server = FakeLoopServer()
    keys: list[str] = []
    down = {"left": 4}

    def flaky(req: httpx.Request) -> httpx.Response:
        if req.url.path.endswith("/trajectories"):
            keys.append(req.headers["Idempotency-Key"])
            if down["left"] > 0:
                down["left"] -= 1
                return error(503, "unavailable", "database")
        return server(req)

    c = make_client(flaky, experiment_id=1, client_id="r1", retries=1)
    slept = recording_sleeps(c)
    learner = c.learn([([0.0, 0.0], [1.0, 0.0])])
    assert run_loop(learner) == [1]
    assert keys == ["proposal-1"] * 5 and server.posted == [1]
    # The client's own retry, then the episode's wait (no Retry-After: 30 s), twice.
    assert len(slept) == 4 and slept[1] == slept[3] == 30.0


def test_the_wait_for_a_fit_is_logged_with_what_answers(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    server = FakeLoopServer(batch_size=1, fit_polls=4)
    c = make_client(server, experiment_id=1, client_id="r1")
    clock = {"t": 0.0}
    monkeypatch.setattr("precond_client.client.time.monotonic", lambda: clock["t"])

    def sleep(s: float) -> None:
        clock["t"] += 20.0  # each poll: 20 s pass

    c._sleep = sleep
    with caplog.at_level(logging.INFO, logger="precond_client"):
        run_loop(c.learn([([0.0, 0.0], [1.0, 0.0])]))
    messages = [r.getMessage() for r in caplog.records]
    assert "waiting for the model fitted after iteration 1 (1 trajectories; version 0 answers)" in (
        messages
    )
    still = [m for m in messages if "still waiting" in m]
    assert still and still[0].startswith(
        "waiting for the fit after iteration 1: still waiting for a model fitted on 1 "
        "trajectories (40 s so far): version 0 answers, fitted on 0 trajectories"
    )


def test_with_logging_unconfigured_the_loop_shows_its_progress_on_stderr(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    logger = logging.getLogger("precond_client")
    server = FakeLoopServer()
    server.no_plan_goals.add((9.0, 9.0))
    c = make_client(server, experiment_id=1, client_id="r1")
    with monkeypatch.context() as m:
        # As in a script that configured nothing: no handler anywhere.
        m.setattr(logging.root, "handlers", [])
        assert not logger.hasHandlers()
        run_loop(c.learn([([0.0, 0.0], [1.0, 0.0]), ([0.0, 0.0], [9.0, 9.0])]))
        err = capsys.readouterr().err
        # Only while the loop runs, and not with verbose=False.
        assert not logger.handlers and logger.level == logging.NOTSET
        run_loop(c.learn([([0.0, 0.0], [3.0, 0.0])], verbose=False))
        assert capsys.readouterr().err == ""
        # Above a progress bar, once each.
        pytest.importorskip("tqdm")
        run_loop(c.learn([([0.0, 0.0], [4.0, 0.0])], progress_bar=True))
        bar = capsys.readouterr().err
        assert bar.count("episode 1: proposal 3 posted") == 1 and "1/1" in bar
    assert "precond_client: problem 0: planning from [0.0, 0.0] to [1.0, 0.0]" in err
    assert "precond_client: episode 1: proposal 1 posted" in err
    assert "precond_client: problem 1: no trajectory inside the precondition" in err


def test_a_progress_bar_shows_the_problems(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("tqdm")
    server = FakeLoopServer()
    c = make_client(server, experiment_id=1, client_id="r1")
    problems = [([0.0, 0.0], [float(i), 0.0]) for i in range(1, 4)]
    run_loop(c.learn(problems, progress_bar=True))
    err = capsys.readouterr().err
    assert "3/3" in err and "posted=3" in err
