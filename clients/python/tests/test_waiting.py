"""Unit tests (scripted transport, no server) of how the client waits: the server's
``Retry-After`` honoured and logged, a search past the deadline repeated a bounded number of
times."""

from __future__ import annotations

import logging
from typing import Any

import httpx
import pytest
from test_client import error, make_client, proposal_json, scripted

from precond_client import DeadlineExceeded
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
