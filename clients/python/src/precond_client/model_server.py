"""Serve a Python dynamics model as a custom domain's ``remote`` model.

The server calls ``POST <url>`` with ``{"states": [[...]], "actions": [[...]]}`` (up to 4096
points per call) and expects ``{"next_states": [[...]], "valid": [...]?}``. :func:`serve_model`
answers those calls with a numpy function::

    def f_hat(states, actions):            # (N, n), (N, m) -> (N, n)
        return states + actions

    with serve_model(f_hat, "127.0.0.1", 9000) as model:
        client.create_experiment(domain={..., "model": {"kind": "remote", "url": model.url}})
        ...

``fn`` may also return ``(next_states, valid)``, ``valid`` a boolean per point: the robot's own
constraint check (collisions, joint limits); a step it calls invalid is never planned. Wrong
shapes, non-finite numbers and exceptions in ``fn`` are answered with ``500`` and a message
(the precond server reports them as ``502 model_unavailable`` naming the URL) and logged here.
The server runs on the standard library's threading HTTP server, keep-alive, in a background
thread; calls to ``fn`` are serialised unless ``threadsafe=True``.

It answers the service's handshake (``GET <url>``: ``{"precond_model": 1, "encodings":
["f64le", "json"], "state_dim"?, "action_dim"?}``), so the service sends its points as raw
little-endian arrays (``application/x-precond-f64le``, shape in ``x-precond-shape:
points,n,m``) rather than JSON lists of floats; ``binary=False`` keeps JSON. Declare
``state_dim`` and ``action_dim`` and the service checks them against the experiment's domain.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import sys
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .models import Array

log = logging.getLogger("precond_client.model_server")

ModelFn = Callable[[Array, Array], "ArrayLike | tuple[ArrayLike, ArrayLike]"]
"""A batched dynamics model: ``fn(states (N, n), actions (N, m)) -> next_states (N, n)`` or
``(next_states, valid)``."""

MAX_BODY_BYTES = 64 * 1024 * 1024
F64LE = "application/x-precond-f64le"
"""Content type of the binary encoding: raw little-endian float64 arrays."""


class ModelError(ValueError):
    """A request or an answer of the model that does not fit the protocol."""


def evaluate(fn: ModelFn, body: Any) -> dict[str, Any]:
    """Answers one protocol request ``body`` with ``fn``; raises :class:`ModelError` for a
    request or answer of the wrong shape."""
    if not isinstance(body, dict) or "states" not in body or "actions" not in body:
        raise ModelError('the request must be {"states": [[...]], "actions": [[...]]}')
    try:
        states = np.asarray(body["states"], dtype=np.float64)
        actions = np.asarray(body["actions"], dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ModelError(f"states and actions must be arrays of numbers: {e}") from e
    if len(states) == 0:
        return {"next_states": [], "valid": []}
    nxt, valid = evaluate_arrays(fn, states, actions)
    answer: dict[str, Any] = {"next_states": nxt.tolist()}
    if valid is not None:
        answer["valid"] = valid.tolist()
    return answer


def evaluate_arrays(
    fn: ModelFn, states: NDArray[np.float64], actions: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_] | None]:
    """``fn`` on ``states`` (N, n) and ``actions`` (N, m), checked: the next states (N, n),
    finite, and the validity flags when ``fn`` returned some; raises :class:`ModelError`."""
    n = len(states)
    if states.ndim != 2 or actions.ndim != 2 or len(actions) != n:
        raise ModelError(
            f"states {states.shape} and actions {actions.shape} must be 2-D with equal rows"
        )
    out = fn(states, actions)
    valid: NDArray[np.bool_] | None = None
    if isinstance(out, tuple):
        nxt_raw, valid_raw = out
        valid = np.asarray(valid_raw, dtype=np.bool_).reshape(-1)
        if len(valid) != n:
            raise ModelError(f"the model returned {len(valid)} valid flags for {n} points")
    else:
        nxt_raw = out
    nxt = np.asarray(nxt_raw, dtype=np.float64)
    if nxt.shape != states.shape:
        raise ModelError(f"the model returned next states {nxt.shape} for states {states.shape}")
    if not np.all(np.isfinite(nxt)):
        raise ModelError("the model returned a non-finite next state")
    return nxt, valid


def decode_f64le(body: bytes, shape: str | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The states and actions of a binary request: ``body`` holds ``points × n`` then
    ``points × m`` little-endian float64s, ``shape`` is ``"points,n,m"``."""
    try:
        points, n, m = (int(v) for v in (shape or "").split(","))
    except ValueError as e:
        raise ModelError(f'x-precond-shape must be "points,n,m", got {shape!r}') from e
    if min(points, n, m) < 0 or len(body) != 8 * points * (n + m):
        raise ModelError(
            f"a binary request of shape {shape} must hold {8 * points * (n + m)} bytes, "
            f"got {len(body)}"
        )
    values = np.frombuffer(body, dtype="<f8")
    states = values[: points * n].reshape(points, n)
    actions = values[points * n :].reshape(points, m)
    return states.astype(np.float64), actions.astype(np.float64)


def encode_f64le(nxt: NDArray[np.float64], valid: NDArray[np.bool_] | None) -> bytes:
    """A binary answer: the next states as little-endian float64s, row-major, then one byte
    (0 or 1) of validity per point when there are flags."""
    data = np.ascontiguousarray(nxt, dtype="<f8").tobytes()
    if valid is not None:
        data += valid.astype(np.uint8).tobytes()
    return data


class _QuietServer(ThreadingHTTPServer):
    """A threading server that does not print a traceback when a caller hangs up mid-request
    (the service abandons calls past its timeout); other errors are logged."""

    def handle_error(self, request: Any, client_address: Any) -> None:
        err = sys.exc_info()[1]
        if isinstance(err, (BrokenPipeError, ConnectionResetError, ConnectionAbortedError)):
            log.debug("%s hung up: %s", client_address, err)
        else:
            log.exception("serving %s failed", client_address)


class ModelServer:
    """A running model server; stop it with :meth:`close` (or use it as a context manager).

    Attributes:
        url: What to put in the experiment's ``domain.model.url``.
        calls: Requests answered so far.
        points: Points predicted so far.
        binary_calls: Requests answered in raw little-endian arrays (the handshake's encoding).
    """

    def __init__(
        self,
        fn: ModelFn,
        host: str,
        port: int,
        path: str,
        threadsafe: bool,
        *,
        binary: bool = True,
        state_dim: int | None = None,
        action_dim: int | None = None,
    ) -> None:
        self.fn = fn
        self.path = path if path.startswith("/") else "/" + path
        self.calls = 0
        self.points = 0
        self.binary_calls = 0
        handshake: dict[str, Any] = {
            "precond_model": 1,
            "encodings": ["f64le", "json"] if binary else ["json"],
        }
        if state_dim is not None:
            handshake["state_dim"] = state_dim
        if action_dim is not None:
            handshake["action_dim"] = action_dim
        lock = threading.Lock()
        server = self
        self._connections: set[socket.socket] = set()

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"
            # The headers and the body go out in two writes; with Nagle's algorithm the second
            # waits for the peer's delayed ACK, 40 ms per call on Linux.
            disable_nagle_algorithm = True

            def setup(self) -> None:
                super().setup()
                with lock:
                    server._connections.add(self.connection)

            def finish(self) -> None:
                with lock:
                    server._connections.discard(self.connection)
                super().finish()

            def log_message(self, format: str, *args: Any) -> None:
                log.debug("%s " + format, self.address_string(), *args)

            def _send(self, status: int, body: dict[str, Any] | bytes) -> None:
                binary_answer = isinstance(body, bytes)
                data = body if isinstance(body, bytes) else json.dumps(body).encode()
                try:
                    self.send_response(status)
                    self.send_header("Content-Type", F64LE if binary_answer else "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError) as e:
                    # The service gave up on this call (its timeout, or a search that ended):
                    # routine, not an error of the model's.
                    self.close_connection = True
                    log.debug("the caller left before the answer: %s", e)

            def do_POST(self) -> None:
                length = int(self.headers.get("Content-Length") or 0)
                if length > MAX_BODY_BYTES:
                    self.close_connection = True
                    self._send(413, {"error": f"body over {MAX_BODY_BYTES} bytes"})
                    return
                raw = self.rfile.read(length)
                if self.path.split("?")[0] != server.path:
                    self._send(404, {"error": f"the model is served at {server.path}"})
                    return
                binary_request = (self.headers.get("Content-Type") or "").startswith(F64LE)
                answer: dict[str, Any] | bytes
                try:
                    if binary_request and binary:
                        states, actions = decode_f64le(raw, self.headers.get("x-precond-shape"))
                        with contextlib.nullcontext() if threadsafe else lock:
                            nxt, valid = evaluate_arrays(server.fn, states, actions)
                        answer, points = encode_f64le(nxt, valid), len(nxt)
                    else:
                        body = json.loads(raw)
                        with contextlib.nullcontext() if threadsafe else lock:
                            answer = evaluate(server.fn, body)
                        points = len(answer["next_states"])
                except (ModelError, json.JSONDecodeError) as e:
                    log.error("model request refused: %s", e)
                    self._send(500, {"error": str(e)})
                    return
                except Exception as e:
                    log.exception("the model raised")
                    self._send(500, {"error": f"the model raised {e!r}"})
                    return
                with lock:
                    server.calls += 1
                    server.points += points
                    server.binary_calls += isinstance(answer, bytes)
                self._send(200, answer)

            def do_GET(self) -> None:
                # The service's handshake: what this model reads and answers in.
                if self.path.split("?")[0] != server.path:
                    self._send(404, {"error": f"the model is served at {server.path}"})
                    return
                self._send(200, handshake)

        self._httpd = _QuietServer((host, port), Handler)
        self._httpd.daemon_threads = True
        self.host = host
        self.port = int(self._httpd.server_address[1])
        self.url = f"http://{host}:{self.port}{self.path}"
        self._thread: threading.Thread | None = None

    def start(self) -> ModelServer:
        """Serves in a background thread; returns the server."""
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._httpd.serve_forever, name="precond-model", daemon=True
            )
            self._thread.start()
        return self

    def serve_forever(self) -> None:
        """Serves in this thread until interrupted."""
        try:
            self._httpd.serve_forever()
        except KeyboardInterrupt:
            pass
        finally:
            self._httpd.server_close()

    def close(self) -> None:
        """Stops serving, closes open keep-alive connections and frees the port."""
        if self._thread is not None:
            self._httpd.shutdown()
            self._thread.join()
            self._thread = None
        self._httpd.server_close()
        for conn in list(self._connections):
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)

    def __enter__(self) -> ModelServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def serve_model(
    fn: ModelFn,
    host: str = "127.0.0.1",
    port: int = 9000,
    *,
    path: str = "/predict",
    threadsafe: bool = False,
    block: bool = False,
    binary: bool = True,
    state_dim: int | None = None,
    action_dim: int | None = None,
) -> ModelServer:
    """Serves ``fn`` as a remote model at ``http://host:port/path`` (port 0 picks a free one;
    the server's ``url`` says which). Runs in a background thread and returns the server, or
    with ``block=True`` serves in this thread until interrupted. Start precond with
    ``--allow-model-url http://host:port/`` so that experiments may use it.

    The service then exchanges raw little-endian arrays with it (negotiated by a handshake;
    ``binary=False`` keeps JSON). ``state_dim`` and ``action_dim``, when given, are declared
    in the handshake and checked by the service against the experiment's domain."""
    server = ModelServer(
        fn,
        host,
        port,
        path,
        threadsafe,
        binary=binary,
        state_dim=state_dim,
        action_dim=action_dim,
    )
    if block:
        log.info("serving the model at %s", server.url)
        server.serve_forever()
        return server
    return server.start()
