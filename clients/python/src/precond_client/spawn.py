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

import os
import re
import subprocess
import threading

_SERVING = re.compile(r"serving.*?addr\W+(127\.0\.0\.1:\d+)")
"""The line ``precond serve`` logs once it listens, with the address it bound."""


def spawn_server(
    binary: str | os.PathLike[str], database_url: str | os.PathLike[str], *args: str
) -> tuple[subprocess.Popen[str], str]:
    """Starts ``binary serve`` on a free loopback port over ``database_url`` (a SQLite file or a
    PostgreSQL URL), with the further ``precond serve`` arguments ``args`` (e.g.
    ``"--allow-model-url", prefix``); returns the process and its URL once it listens.

    Its log (warnings, and the HTTP layer's info) is read and dropped in the background. The
    caller stops the process (``proc.terminate()``). Raises ``RuntimeError`` when the binary
    ends without listening.
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
    for line in proc.stdout:
        m = _SERVING.search(line)
        if m:
            threading.Thread(target=proc.stdout.read, daemon=True).start()  # drain the log
            return proc, f"http://{m.group(1)}"
    proc.kill()  # it closed its output: it has ended, or is about to
    proc.wait()
    raise RuntimeError(f"{os.fspath(binary)} serve did not start")
