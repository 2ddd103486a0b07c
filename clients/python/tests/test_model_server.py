"""Unit tests of serve_model over a real loopback socket (no precond server)."""

from __future__ import annotations

import json
import socket
import struct
import threading
import time
from typing import Any

import httpx
import numpy as np
import pytest
from numpy.typing import NDArray

from precond_client import serve_model
from precond_client.model_server import F64LE, ModelError, ModelFn, evaluate
from precond_client.models import Array


def shift(states: Array, actions: Array) -> Array:
    return states + actions


def test_evaluate_answers_the_protocol() -> None:
    out = evaluate(shift, {"states": [[0, 0], [1, 1]], "actions": [[0.5, 0], [0, -1]]})
    assert out == {"next_states": [[0.5, 0.0], [1.0, 0.0]]}


def test_evaluate_passes_valid_flags_through() -> None:
    def with_valid(s: Array, a: Array) -> tuple[Array, NDArray[np.bool_]]:
        nxt = s + a
        return nxt, nxt[:, 0] <= 1.0

    out = evaluate(with_valid, {"states": [[0.5], [0.9]], "actions": [[0.1], [0.2]]})
    assert out["valid"] == [True, False]


@pytest.mark.parametrize(
    ("fn", "body", "match"),
    [
        (shift, {"states": [[0, 0]]}, "must be"),
        (shift, {"states": [[0, 0]], "actions": [[0, 0], [1, 1]]}, "equal rows"),
        (lambda s, a: s[:, :1], {"states": [[0, 0]], "actions": [[0, 0]]}, r"\(1, 1\)"),
        (lambda s, a: s * np.nan, {"states": [[0, 0]], "actions": [[0, 0]]}, "non-finite"),
        (lambda s, a: (s, [True, True]), {"states": [[0]], "actions": [[0]]}, "2 valid flags"),
    ],
)
def test_evaluate_refuses_wrong_shapes(fn: ModelFn, body: dict[str, Any], match: str) -> None:
    with pytest.raises(ModelError, match=match):
        evaluate(fn, body)


def test_an_empty_batch_does_not_call_the_model() -> None:
    def boom(s: Array, a: Array) -> Array:
        raise AssertionError("called")

    assert evaluate(boom, {"states": [], "actions": []}) == {"next_states": [], "valid": []}


def test_serve_model_answers_over_http_and_reports_failures() -> None:
    def model(s: Array, a: Array) -> Array:
        if np.any(a > 10):
            raise RuntimeError("joint limit")
        return s + 2 * a

    with serve_model(model, "127.0.0.1", 0) as server, httpx.Client() as http:
        assert server.url.startswith("http://127.0.0.1:") and server.url.endswith("/predict")
        ok = http.post(server.url, json={"states": [[1.0, 2.0]], "actions": [[0.5, -0.5]]})
        assert ok.status_code == 200
        assert ok.json() == {"next_states": [[2.0, 1.0]]}
        again = http.post(server.url, json={"states": [[0.0, 0.0]], "actions": [[1.0, 1.0]]})
        assert again.json() == {"next_states": [[2.0, 2.0]]}
        failed = http.post(server.url, json={"states": [[0.0, 0.0]], "actions": [[11.0, 0.0]]})
        assert failed.status_code == 500 and "joint limit" in failed.json()["error"]
        assert http.post(server.url, content=b"not json").status_code == 500
        wrong = http.post(server.url.replace("/predict", "/other"), json={})
        assert wrong.status_code == 404
        assert server.calls == 2 and server.points == 2
        kept = httpx.Client()
        assert kept.post(server.url, json={"states": [], "actions": []}).status_code == 200
    # Closed: new connections are refused and kept-alive ones are closed.
    with pytest.raises(httpx.ConnectError):
        httpx.post(server.url, json={"states": [], "actions": []})
    with pytest.raises(httpx.TransportError):
        kept.post(server.url, json={"states": [], "actions": []})
    kept.close()


def test_the_handshake_offers_binary_arrays_and_they_round_trip() -> None:
    def model(s: Array, a: Array) -> tuple[Array, NDArray[np.bool_]]:
        return s + a, a[:, 0] >= 0

    with (
        serve_model(model, "127.0.0.1", 0, state_dim=2, action_dim=1) as server,
        httpx.Client() as http,
    ):
        hello = http.get(server.url)
        assert hello.status_code == 200
        assert hello.json() == {
            "precond_model": 1,
            "encodings": ["f64le", "json"],
            "state_dim": 2,
            "action_dim": 1,
        }
        assert http.get(server.url.replace("/predict", "/other")).status_code == 404
        states = np.array([[1.0, 2.0], [0.1, 1e-300]])
        actions = np.array([[0.5], [-0.25]])
        body = states.astype("<f8").tobytes() + actions.astype("<f8").tobytes()
        headers = {"Content-Type": F64LE, "x-precond-shape": "2,2,1"}
        # A model of (N, 2) states and (N, 1) actions: numpy broadcasts s + a.
        ok = http.post(server.url, content=body, headers=headers)
        assert ok.status_code == 200 and ok.headers["content-type"] == F64LE
        nxt = np.frombuffer(ok.content[: 8 * 4], dtype="<f8").reshape(2, 2)
        np.testing.assert_array_equal(nxt, states + actions)  # bit for bit
        assert list(ok.content[8 * 4 :]) == [1, 0]
        short = http.post(server.url, content=body[:-8], headers=headers)
        assert short.status_code == 500 and "must hold 48 bytes" in short.json()["error"]
        bad = http.post(server.url, content=body, headers={"Content-Type": F64LE})
        assert bad.status_code == 500 and "x-precond-shape" in bad.json()["error"]
        assert server.calls == 1 and server.binary_calls == 1 and server.points == 2
    with serve_model(shift, "127.0.0.1", 0, binary=False) as server:
        assert httpx.get(server.url).json() == {"precond_model": 1, "encodings": ["json"]}


def test_a_caller_that_hangs_up_is_not_a_traceback(capfd: pytest.CaptureFixture[str]) -> None:
    """The service abandons calls past its timeout; the model server carries on quietly."""
    started = threading.Event()

    def slow(s: Array, a: Array) -> Array:
        started.set()
        time.sleep(0.3)
        return s + a

    with serve_model(slow, "127.0.0.1", 0) as server:
        body = json.dumps({"states": [[0.0]], "actions": [[1.0]]}).encode()
        head = f"POST /predict HTTP/1.1\r\nHost: x\r\nContent-Length: {len(body)}\r\n\r\n"
        sock = socket.create_connection(("127.0.0.1", server.port))
        sock.sendall(head.encode() + body)
        assert started.wait(5)
        # Close with a reset, as a client that timed out does: the answer cannot be written.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.close()
        time.sleep(0.6)
        # Still serving.
        ok = httpx.post(server.url, json={"states": [[1.0]], "actions": [[1.0]]})
        assert ok.json() == {"next_states": [[2.0]]}
    err = capfd.readouterr().err
    assert "Traceback" not in err and "BrokenPipe" not in err and "ConnectionReset" not in err, err
