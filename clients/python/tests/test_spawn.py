"""spawn_server: the real binary started on a free port, and a binary that never listens."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

from precond_client import Client, spawn_server


@pytest.mark.integration
def test_spawn_server_answers_on_the_url_it_returns(precond_binary: Path, tmp_path: Path) -> None:
    prefix = "http://127.0.0.1:9/"
    log = tmp_path / "server.log"
    proc, url = spawn_server(
        precond_binary, tmp_path / "precond.db", "--allow-model-url", prefix, log=log
    )
    try:
        assert url.startswith("http://127.0.0.1:")
        with Client(url) as client:
            assert client.ready()
            # The extra argument reached `precond serve`: a remote model under the prefix is
            # accepted (without --allow-model-url, remote models are refused).
            exp = client.create_experiment(
                domain={
                    "kind": "custom",
                    "state": {"names": ["x"], "low": [0.0], "high": [1.0]},
                    "action": {"names": ["dx"], "low": [-0.1], "high": [0.1]},
                    "model": {"kind": "remote", "url": prefix + "predict"},
                }
            )
            assert exp.domain["model"]["url"] == prefix + "predict"
    finally:
        proc.terminate()
        proc.wait(20)
    # The server's log was kept: the line that said where it listens, and (read on after it)
    # the line it logs as it stops.
    deadline = time.monotonic() + 10  # the reader thread may still be at the pipe's end
    while "stopped" not in (text := log.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert url.removeprefix("http://") in text, text
    assert "stopped" in text, text


def test_spawn_server_raises_when_the_binary_never_listens(tmp_path: Path) -> None:
    script = tmp_path / "not-precond"
    script.write_text(f"#!{sys.executable}\nprint('no server here')\n")
    script.chmod(0o755)
    with pytest.raises(RuntimeError, match="serve did not start: no server here"):
        spawn_server(script, tmp_path / "precond.db")
