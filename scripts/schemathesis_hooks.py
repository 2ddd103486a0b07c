"""Loaded by schemathesis (SCHEMATHESIS_HOOKS) in scripts/ci-schemathesis.sh.

CPython 3.11 keeps the ast module's recursion counter in interpreter-wide state
(python/cpython#106905), so two threads compiling at once can fail with "AST constructor
recursion depth mismatch". Hypothesis compiles source (ast.parse) while it describes a
strategy, in each schemathesis worker thread; the CI run of 2026-11-25 failed on it twice in a
row with two workers. One lock around the builtin compile (which ast.parse calls) lets the
workers run side by side while their compilations take turns. Nothing about the server or the
checks changes.
"""

import builtins
import threading
from typing import Any

_compile = builtins.compile
_lock = threading.RLock()


def _serialised_compile(*args: Any, **kwargs: Any) -> Any:
    with _lock:
        return _compile(*args, **kwargs)


builtins.compile = _serialised_compile
