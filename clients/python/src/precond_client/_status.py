"""What the client is doing, for the lines it logs while it waits, and how those lines reach a
user who configured no logging at all.

- :func:`activity` names what the calls inside it are for (``"problem 12: planning"``); a wait
  before a retry is then logged under that name instead of the request's method and path.
- :func:`visible` shows this package's ``INFO`` lines on standard error while a loop runs,
  when logging is not configured (no handler between the ``precond_client`` logger and the
  root): a robot's loop that waits minutes must not be silent.
- :func:`progress_bar` is a tqdm bar (the ``[progress]`` extra) where a terminal is attached.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator
from contextvars import ContextVar
from typing import Any

LOGGER = "precond_client"

_ACTIVITY: ContextVar[str | None] = ContextVar("precond_client_activity", default=None)


@contextlib.contextmanager
def activity(what: str) -> Iterator[None]:
    """Names what the requests made inside the block are for, in the lines logged when they
    wait (see :func:`current`)."""
    token = _ACTIVITY.set(what)
    try:
        yield
    finally:
        _ACTIVITY.reset(token)


def current() -> str | None:
    """The innermost :func:`activity`'s name, if any."""
    return _ACTIVITY.get()


def seconds(s: float) -> str:
    """A wait for a log line: ``30 s``, ``1.5 s``, ``0.12 s``."""
    if s >= 10:
        return f"{s:.0f} s"
    if s >= 1:
        return f"{s:.1f} s"
    return f"{s:.2g} s"


@contextlib.contextmanager
def visible(enabled: bool = True) -> Iterator[None]:
    """While the block runs, shows the ``precond_client`` logger's ``INFO`` lines on standard
    error if logging is not configured (no handler on the logger or its ancestors, so that
    Python would print only warnings, through ``logging.lastResort``). Configured logging is
    left alone: ``logging.basicConfig(level=logging.INFO)`` shows the lines its own way, a
    level of ``WARNING`` hides them."""
    logger = logging.getLogger(LOGGER)
    if not enabled or logger.hasHandlers():
        yield
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("precond_client: %(message)s"))
    handler.setLevel(logging.INFO)
    level = logger.level
    logger.addHandler(handler)
    if level == logging.NOTSET or level > logging.INFO:
        logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def progress_bar(show: bool | None, total: int | None, desc: str, unit: str) -> Any:
    """A tqdm bar, or ``None``: ``show=None`` makes one when tqdm is installed and standard
    error is a terminal, ``True`` whenever tqdm is installed, ``False`` never."""
    if show is False:
        return None
    if show is None and not _is_terminal():
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=True)


def _is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


@contextlib.contextmanager
def around_bar(bar: Any) -> Iterator[None]:
    """While ``bar`` is shown, console log lines (of the root and ``precond_client`` loggers)
    are written above it instead of through it (tqdm's ``logging_redirect_tqdm``)."""
    loggers = [
        logger
        for logger in (logging.root, logging.getLogger(LOGGER))
        if any(_on_console(h) for h in logger.handlers)
    ]
    if bar is None or not loggers:
        yield
        return
    from tqdm.contrib.logging import logging_redirect_tqdm

    # Only loggers that print to the console: tqdm gives every logger it is handed a handler,
    # and one on a logger without any would print each line twice.
    with logging_redirect_tqdm(loggers=loggers):
        yield


def _on_console(handler: logging.Handler) -> bool:
    return isinstance(handler, logging.StreamHandler) and handler.stream in (
        sys.stdout,
        sys.stderr,
    )
