"""Fixtures: the real precond server binary on a free loopback port with a temporary database.

The binary is ``$PRECOND_BIN``, else ``<repo>/target/debug/precond`` (built by ``cargo test``).
The integration tests are skipped when it is missing, unless ``PRECOND_REQUIRE_SERVER=1``
(as in CI), which makes that a failure.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
ADDR_RE = re.compile(r"serving.*?addr\W+(127\.0\.0\.1:\d+)")


def server_binary() -> Path:
    return Path(os.environ.get("PRECOND_BIN") or REPO / "target" / "debug" / "precond")


class PrecondServer:
    """A ``precond serve`` process that can be stopped and started again on the same port and
    database (a server restart)."""

    def __init__(
        self,
        binary: Path,
        db: Path,
        allow_model_urls: list[str],
        extra_args: list[str] | None = None,
    ) -> None:
        self.binary = binary
        self.db = db
        self.allow = allow_model_urls
        self.extra_args = extra_args or []
        self.addr = "127.0.0.1:0"
        self.proc: subprocess.Popen[str] | None = None
        self.log: list[str] = []
        self.starts = 0

    @property
    def url(self) -> str:
        return f"http://{self.addr}"

    def start(self) -> None:
        """Starts the server and waits until it listens (it logs the bound address)."""
        args = [str(self.binary), "serve", "--addr", self.addr, "--database-url", str(self.db)]
        for prefix in self.allow:
            args += ["--allow-model-url", prefix]
        args += self.extra_args
        env = {**os.environ, "NO_COLOR": "1", "RUST_LOG": "info"}
        proc = subprocess.Popen(
            args,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        self.proc = proc
        bound = threading.Event()

        def drain() -> None:
            assert proc.stdout is not None
            for line in proc.stdout:
                self.log.append(line)
                m = ADDR_RE.search(line)
                if m and not bound.is_set():
                    self.addr = m.group(1)
                    bound.set()
            bound.set()

        threading.Thread(target=drain, daemon=True).start()
        if not bound.wait(60) or proc.poll() is not None:
            self.stop()
            raise RuntimeError("precond serve did not start:\n" + "".join(self.log[-30:]))
        self.starts += 1

    def stop(self) -> None:
        """Stops the server gracefully (SIGTERM), killing it if it does not exit."""
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

    def restart(self) -> None:
        """Stops the server and starts it again on the same port and database."""
        self.stop()
        self.start()


@pytest.fixture
def precond_binary() -> Path:
    binary = server_binary()
    if not binary.exists():
        if os.environ.get("PRECOND_REQUIRE_SERVER") == "1":
            pytest.fail(f"no precond binary at {binary}")
        pytest.skip(f"no precond binary at {binary} (set PRECOND_BIN or run cargo build)")
    return binary


MakeServer = Callable[..., PrecondServer]
"""The type of the ``make_server`` fixture."""


@pytest.fixture
def make_server(precond_binary: Path, tmp_path: Path) -> Iterator[MakeServer]:
    """A factory ``make_server(allow_model_urls, extra_args)`` of started servers, stopped at
    the end."""
    servers: list[PrecondServer] = []

    def factory(
        allow_model_urls: list[str] | None = None, extra_args: list[str] | None = None
    ) -> PrecondServer:
        db = tmp_path / f"precond-{len(servers)}.db"
        s = PrecondServer(precond_binary, db, allow_model_urls or [], extra_args)
        servers.append(s)
        s.start()
        return s

    yield factory
    for s in servers:
        s.stop()
