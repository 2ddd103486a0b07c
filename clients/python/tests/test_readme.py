"""The READMEs' robot loop runs as written, against the real server binary.

The block after the marker ``<!-- robot-loop`` in the root ``README.md`` and in
``clients/python/README.md`` is executed as it stands, with three substitutions that any reader
makes too, each checked to occur exactly once:

- the server's address ``"http://127.0.0.1:8080"`` becomes the test server's (a free port);
- the model's port ``9001`` (the curl section's model server has 9000) becomes a free port
  the test server allows;
- ``robot_execute``, whose body in the README is ``...`` ("your robot"), is a simulated robot:
  the README's model ``clip(s + a)`` except on an icy band, where the robot slides further.

Everything else (the experiment's settings, ``default_rng(0)``'s 50 problems, the loop, the
final query) is the README's, so the first hour a user spends with it cannot break again.
"""

from __future__ import annotations

import ast
import contextlib
import io
import logging
import re
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import REPO, PrecondServer

from precond_client import Client
from precond_client.models import Array

pytestmark = pytest.mark.integration

MARKER = "<!-- robot-loop"
READMES = [REPO / "README.md", REPO / "clients" / "python" / "README.md"]

ICE_LOW, ICE_HIGH, SLIP = 0.4, 0.6, 1.5


def robot_execute(start: Array, actions: Array) -> Array:
    """The simulated robot: the states it observed executing ``actions`` from ``start``."""
    states = [np.asarray(start, dtype=np.float64)]
    for a in np.asarray(actions, dtype=np.float64):
        s = states[-1]
        gain = SLIP if ICE_LOW <= s[0] <= ICE_HIGH else 1.0
        states.append(np.clip(s + gain * a, 0.0, 1.0))
    return np.array(states)


def robot_loop(readme: Path) -> str:
    """The code block right after the marker (a line of its own)."""
    text = readme.read_text(encoding="utf-8")
    starts = [m.end() for m in re.finditer(f"^{re.escape(MARKER)}.*\n", text, re.M)]
    assert len(starts) == 1, f"{readme}: one line starting {MARKER}, not {len(starts)}"
    m = re.match(r"```python\n(.*?)\n```\n", text[starts[0] :], re.S)
    assert m, f"{readme}: the marker is right before a ```python block"
    return m.group(1)


class Substitute(ast.NodeTransformer):
    """Points the README's code at the test server and the simulated robot."""

    def __init__(self, server_url: str, model_port: int) -> None:
        self.replace: dict[Any, Any] = {"http://127.0.0.1:8080": server_url, 9001: model_port}
        self.replaced: list[Any] = []
        self.placeholder_removed = False

    def visit_Constant(self, node: ast.Constant) -> ast.AST:
        value = node.value
        if not isinstance(value, bool) and value in self.replace:
            self.replaced.append(value)
            return ast.copy_location(ast.Constant(self.replace[value]), node)
        return node

    def visit_FunctionDef(self, node: ast.FunctionDef) -> ast.AST | None:
        if node.name != "robot_execute":
            return self.generic_visit(node)
        body = node.body
        assert (
            len(body) == 1
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and body[0].value.value is Ellipsis
        ), "the README's robot_execute is the placeholder `...` the test stands in for"
        self.placeholder_removed = True
        return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def rng_problems() -> list[tuple[Array, Array]]:
    """The README's problems."""
    rng = np.random.default_rng(0)
    return [(rng.uniform(0, 1, 2), rng.uniform(0, 1, 2)) for _ in range(50)]


def test_the_readme_problems_include_a_start_at_its_goal() -> None:
    # Why the loop must skip such problems: problem 10 lies 0.028 from its goal (radius 0.05).
    near = [i for i, (s, g) in enumerate(rng_problems()) if float(np.linalg.norm(s - g)) < 0.05]
    assert near == [10]


def distinct_loops() -> list[tuple[str, str]]:
    """``(names of the READMEs showing it, code)`` of each distinct robot loop: the loop takes
    a minute and a half on a debug server, so one the two READMEs show alike (the same syntax
    tree: layout and comments aside) runs once."""
    by_tree: dict[str, tuple[list[str], str]] = {}
    for readme in READMES:
        code = robot_loop(readme)
        names, _ = by_tree.setdefault(ast.dump(ast.parse(code)), ([], code))
        names.append(str(readme.relative_to(REPO)))
    return [(" and ".join(names), code) for names, code in by_tree.values()]


LOOPS = distinct_loops()


@pytest.mark.parametrize(("readmes", "code"), LOOPS, ids=[names for names, _ in LOOPS])
def test_the_readme_robot_loop_runs_as_written(
    readmes: str,
    code: str,
    make_server: Callable[..., PrecondServer],
    caplog: pytest.LogCaptureFixture,
) -> None:
    port = free_port()
    server = make_server([f"http://127.0.0.1:{port}/"])
    sub = Substitute(server.url, port)
    tree = ast.fix_missing_locations(sub.visit(ast.parse(code)))
    assert sorted(sub.replaced, key=str) == sorted(["http://127.0.0.1:8080", 9001], key=str)
    assert sub.placeholder_removed

    namespace: dict[str, Any] = {"__name__": "readme", "robot_execute": robot_execute}
    out = io.StringIO()
    with caplog.at_level(logging.INFO, logger="precond_client"), contextlib.redirect_stdout(out):
        exec(compile(tree, readmes, "exec"), namespace)

    # It printed the verdict of its one query.
    assert out.getvalue().strip() in ("[ True]", "[False]"), out.getvalue()
    # Every problem was proposed, skipped for no plan, or skipped at its goal (problem 10).
    messages = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("problem 10: the start") for m in messages), messages
    with Client(server.url) as client:
        (exp,) = client.list_experiments()
        client.use(exp.id)
        assert exp.name == "my robot" and exp.d_max == 0.03
        posted = sum(m.startswith("episode ") and " posted, " in m for m in messages)
        no_plan = sum("no trajectory inside the precondition" in m for m in messages)
        assert exp.n_trajectories == posted and posted + no_plan == 49
        assert posted >= 5, "at least one batch was learned from"
        model = client.model()
        # learn waited for the refit of every completed batch before it ended.
        assert model.n_trajectories == exp.iteration * exp.learning["batch_size"]
        assert model.version >= 1
