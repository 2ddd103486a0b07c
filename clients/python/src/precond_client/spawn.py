"""Start a local precond server binary, for scripts and examples that bring their own.

::

    proc, url = spawn_server("target/release/precond", "/tmp/precond.db")
    try:
        with Client(url) as client:
            ...
    finally:
        proc.terminate()
        proc.wait()
"""

from __future__ import annotations

import contextlib
import os
import re
import subprocess
import threading
from typing import IO

_SERVING = re.compile(r"serving.*?addr\W+(127\.0\.0\.1:\d+)")
"""The line ``precond serve`` logs once it listens, with the address it bound."""


def spawn_server(
    binary: str | os.PathLike[str],
    database_url: str | os.PathLike[str],
    *args: str,
    log: str | os.PathLike[str] | None = None,
) -> tuple[subprocess.Popen[str], str]:
    """Starts ``binary serve`` on a free loopback port over ``database_url`` (a SQLite file or a
    PostgreSQL URL), with the further ``precond serve`` arguments ``args`` (e.g.
    ``"--allow-model-url", prefix``); returns the process and its URL once it listens.

    Its log (warnings, and the HTTP layer's info) is read in the background and appended to the
    file ``log`` when one is given (the server's own account of a refused fit or a slow model),
    else dropped. The caller stops the process (``proc.terminate()``). Raises ``RuntimeError``
    when the binary ends without listening (with the log's last lines).
    """
    proc = subprocess.Popen(
        [
            os.fspath(binary),
            "serve",
            "--addr",
            "127.0.0.1:0",
            "--database-url",
            os.fspath(database_url),
            *args,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "NO_COLOR": "1", "RUST_LOG": "warn,precond::http=info"},
    )
    assert proc.stdout is not None
    out = open(log, "a", encoding="utf-8", buffering=1) if log is not None else None  # noqa: SIM115
    seen: list[str] = []
    for line in proc.stdout:
        if out is not None:
            out.write(line)
        seen = [*seen[-19:], line]
        m = _SERVING.search(line)
        if m:
            threading.Thread(target=_drain, args=(proc.stdout, out), daemon=True).start()
            return proc, f"http://{m.group(1)}"
    if out is not None:
        out.close()
    proc.kill()  # it closed its output: it has ended, or is about to
    proc.wait()
    tail = "".join(seen).strip()
    raise RuntimeError(f"{os.fspath(binary)} serve did not start" + (f": {tail}" if tail else ""))


def _drain(stream: IO[str], out: IO[str] | None) -> None:
    """Reads the server's log until it ends, keeping it in ``out`` when there is one."""
    with contextlib.ExitStack() as stack:
        if out is not None:
            stack.enter_context(out)
        for line in stream:
            if out is not None:
                out.write(line)
