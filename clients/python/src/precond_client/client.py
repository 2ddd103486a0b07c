"""The HTTP client of a precond server.

One :class:`Client` talks to one server and, for the experiment-scoped calls, to one current
experiment (``experiment_id``; set by :meth:`Client.create_experiment`,
:meth:`Client.ensure_experiment` or :meth:`Client.use`).

**Retries.** A request that could not be sent (connection refused, the server restarting) is
retried with exponential back-off and jitter, and so is an answer ``429`` or ``5xx`` for requests
that are safe to repeat: reads, precondition queries and plans, proposals (a repeated proposal
for the same ``client_id`` and problem returns the open one), abandons, and trajectories, which
always carry an ``Idempotency-Key`` (a repeat is replayed by the server, never stored twice).
Creating an experiment is not idempotent on the server, so it is retried only when the request
surely did not arrive; :meth:`Client.ensure_experiment` makes creation safe to repeat by name.
An answer with ``Retry-After`` (``429``, ``503``, ``507``) is retried after the seconds it says
(at most ``max_retry_after``), others after the back-off. A search that ran until the server's
planning deadline (``503 deadline_exceeded`` with extensions searched) would run as long again,
so it is repeated only ``deadline_retries`` times (default once), not ``retries`` times. Every
wait is logged at ``INFO`` on the ``precond_client`` logger, with what it is for.
"""

from __future__ import annotations

import datetime
import logging
import math
import random
import re
import socket
import tempfile
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from numpy.typing import ArrayLike

from . import _status, errors
from .execution import Execution, Metric, Monitor, StepFn, client_side, execute_plan
from .export import ExportedModel
from .imports import (
    DatasetError,
    check_dataset_id,
    dataset_identity,
    default_dataset_name,
    import_episodes,
    import_error,
    lerobot_table,
    read_minari,
)
from .models import (
    Candidate,
    Continued,
    Exclusion,
    Experiment,
    ImportReport,
    Model,
    ModelLabels,
    Plan,
    PlannedTrajectory,
    Precondition,
    Proposal,
    Run,
    Source,
    StoredTransition,
    Trajectory,
    TrajectoryCreated,
    Transition,
    as_list,
    mat,
)
from .robot import CandidateFn, Learner, ModelsFn, Problem, ProgressFn

log = logging.getLogger("precond_client")

_RETRY_IN = re.compile(r"[;,]?\s*retry in \d+ s\s*$")
"""The end of a server message that says when to retry (the client's log line says it)."""

PRECONDITION_CHUNK = 10_000
"""Points per precondition request (the server accepts up to 100 000, but the request body
is limited to 4 MiB by default)."""


def settings_differences(asked: Any, stored: Any, path: str = "") -> list[tuple[str, Any, Any]]:
    """``(path, asked, stored)`` wherever ``stored`` (an experiment's resolved settings, as
    JSON) differs from ``asked``: only what ``asked`` gives is compared (its keys, recursively;
    ``None`` means "the default" and is not compared); lists item by item; numbers as
    numbers, so ``0`` equals ``0.0``."""
    if asked is None:
        return []
    if isinstance(asked, Mapping):
        if not isinstance(stored, Mapping):
            return [(path, asked, stored)]
        out = []
        for key, value in asked.items():
            at = f"{path}.{key}" if path else str(key)
            if key not in stored:
                if value is not None:
                    out.append((at, value, errors.ABSENT))
                continue
            out += settings_differences(value, stored[key], at)
        return out
    if isinstance(asked, np.ndarray):
        asked = asked.tolist()
    if isinstance(asked, (list, tuple)):
        if not isinstance(stored, list) or len(stored) != len(asked):
            return [(path, asked, stored)]
        out = []
        for i, (a, s) in enumerate(zip(asked, stored, strict=True)):
            out += settings_differences(a, s, f"{path}[{i}]")
        return out
    numbers = (int, float, np.integer, np.floating)
    if (
        isinstance(asked, numbers)
        and not isinstance(asked, bool)
        and isinstance(stored, numbers)
        and not isinstance(stored, bool)
    ):
        same = math.isclose(float(asked), float(stored), rel_tol=1e-12, abs_tol=0.0)
    else:
        same = asked == stored
    return [] if same else [(path, asked, stored)]


def _upload_progress(size: int, desc: str, show: bool | None) -> Any:
    """A tqdm bar of an upload's bytes, when tqdm is installed and ``show`` is not ``False``."""
    if show is False:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm(total=size, desc=desc, unit="B", unit_scale=True, unit_divisor=1024)


def _body(r: httpx.Response) -> Any:
    """An answer's JSON, or its text when it is not JSON (a proxy's page)."""
    try:
        return r.json()
    except ValueError:
        return r.text


def _error(body: Any) -> dict[str, Any]:
    err = body.get("error") if isinstance(body, dict) else None
    return err if isinstance(err, dict) else {}


def _searched_until_deadline(status: int, body: Any) -> bool:
    """Whether an answer is a search stopped by the server's deadline after searching (not one
    that passed its deadline waiting for a planning slot)."""
    err = _error(body)
    if status != 503 or err.get("code") != "deadline_exceeded":
        return False
    details = err.get("details")
    extensions = details.get("extensions") if isinstance(details, dict) else None
    return not (isinstance(extensions, int) and extensions == 0)


def _why(status: int, body: Any) -> str:
    """An error answer in a log line: ``503 deadline_exceeded (the deadline of 30000 ms passed
    (5123 extensions searched))``."""
    err = _error(body)
    if not err:
        return f"{status}"
    message = _RETRY_IN.sub("", str(err.get("message", "")))
    return f"{status} {err.get('code')} ({message})" if message else f"{status} {err.get('code')}"


def _transitions_json(
    transitions: Iterable[Transition | Mapping[str, Any]], empty: str
) -> list[dict[str, Any]]:
    """The JSON form of ``transitions`` (a trajectory posted or a proposal's executed prefix);
    ``ValueError(empty)`` when there are none."""
    items = [t.to_json() if isinstance(t, Transition) else dict(t) for t in transitions]
    if not items:
        raise ValueError(empty)
    return items


def _rfc3339(t: datetime.datetime | str) -> str:
    """``t`` as RFC 3339; a naive datetime is refused (its time zone would be a guess)."""
    if isinstance(t, str):
        return t
    if t.tzinfo is None or t.utcoffset() is None:
        raise ValueError(f"{t!r} has no time zone: give e.g. datetime.now(timezone.utc)")
    return t.isoformat()


class Client:
    """A client of one precond server.

    Args:
        base_url: The server, e.g. ``http://127.0.0.1:8080``.
        token: The access token, sent as ``Authorization: Bearer <token>``. A server started
            with ``--token-file`` checks it on every route but ``/healthz`` and ``/readyz``:
            none or an unknown one raises :class:`~precond_client.errors.Unauthorized` (401);
            a token without the route's role or whose experiments do not include the one asked
            for raises :class:`~precond_client.errors.Forbidden` (403). Roles are cumulative:
            ``read`` for reads, precondition queries and test-time plans; ``write`` also for
            proposals and trajectories (what a robot needs); ``admin`` also for creating
            experiments and forced refits. A token scoped to some experiments lists only those
            and cannot create any (so :meth:`ensure_experiment` with a robot's ``write`` token
            finds an experiment but cannot create one). A server without a token file
            (loopback only, unless ``--insecure-no-auth``) ignores the header.
        timeout: Seconds to wait for each answer. The default, 60, outlasts the server's
            default planning deadline (``--plan-timeout-ms``, 30 s), so a slow search comes
            back as :class:`~precond_client.errors.DeadlineExceeded` (retried) rather than a
            read timeout; raise it with the server's deadline.
        experiment_id: The current experiment for the experiment-scoped calls.
        client_id: The lease holder's name used by :meth:`propose` and :meth:`learn` when they
            are not given one; default the host name, so a restarted robot process finds the
            lease it held.
        retries: How many times a failed request is repeated before giving up.
        backoff: The first back-off in seconds; it doubles per retry (with jitter) up to
            ``max_backoff``.
        max_backoff: The longest back-off in seconds (of a retry whose answer did not say
            when to retry).
        deadline_retries: How many times a search (a proposal, a continuation, a plan) that
            ran until the server's planning deadline (``503 deadline_exceeded`` with
            extensions searched) is repeated before
            :class:`~precond_client.errors.DeadlineExceeded` is raised: the same search would
            most likely run as long again. A deadline that passed while the request waited for
            a planning slot (no extensions searched) is retried like any ``503``.
        max_retry_after: The longest wait in seconds honoured from an answer's
            ``Retry-After`` (the server says 30 s after a 30 s deadline, 30 s on a full disk).
        transport: An ``httpx`` transport (tests use ``httpx.MockTransport``).
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8080",
        token: str | None = None,
        timeout: float = 60.0,
        *,
        experiment_id: int | None = None,
        client_id: str | None = None,
        retries: int = 8,
        backoff: float = 0.1,
        max_backoff: float = 5.0,
        deadline_retries: int = 1,
        max_retry_after: float = 120.0,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        headers = {"Accept": "application/json", "User-Agent": "precond-client/0.1"}
        if token is not None:
            headers["Authorization"] = f"Bearer {token}"
        self._http = httpx.Client(
            base_url=base_url.rstrip("/"), timeout=timeout, headers=headers, transport=transport
        )
        self.experiment_id = experiment_id
        self.client_id = client_id or socket.gethostname() or "precond-client"
        self.retries = retries
        self.backoff = backoff
        self.max_backoff = max_backoff
        self.deadline_retries = deadline_retries
        self.max_retry_after = max_retry_after
        self._sleep: Callable[[float], None] = time.sleep
        self._state_dim: dict[int, int] = {}

    # ------------------------------------------------------------------ plumbing

    def close(self) -> None:
        """Closes the connection pool."""
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _delay(self, attempt: int, response: httpx.Response | None) -> float:
        """Seconds to wait before retry ``attempt + 1``: what the answer's ``Retry-After``
        says (up to ``max_retry_after``), else the exponential back-off with jitter."""
        if response is not None:
            ra = response.headers.get("Retry-After")
            if ra is not None:
                try:
                    return max(0.0, min(float(ra), self.max_retry_after))
                except ValueError:
                    pass
        base: float = min(self.max_backoff, self.backoff * 2.0**attempt)
        return base * random.uniform(0.5, 1.0)

    def _wait(self, delay: float, why: str, retry: int, of: int, method: str, path: str) -> None:
        """Logs a wait before a retry (under the current activity's name) and sleeps."""
        what = _status.current() or f"{method} {path}"
        log.info("%s: %s; retry %d/%d in %s", what, why, retry, of, _status.seconds(delay))
        self._sleep(delay)

    def _request(
        self,
        method: str,
        path: str,
        *,
        json: Any = None,
        params: Mapping[str, Any] | None = None,
        headers: Mapping[str, str] | None = None,
        idempotent: bool = True,
        deadline_retries: int | None = None,
        content: Callable[[], Iterator[bytes]] | None = None,
        timeout: httpx.Timeout | None = None,
    ) -> httpx.Response:
        """Sends a request with retries; returns a 2xx answer or raises.

        ``deadline_retries`` (default :attr:`deadline_retries`) bounds the repeats of a search
        that ran until the server's deadline (see the class). ``content`` gives the body's
        bytes afresh for each attempt (a file read again); ``timeout`` replaces the client's."""
        searches = self.deadline_retries if deadline_retries is None else deadline_retries
        attempt = 0
        deadlines = 0
        while True:
            try:
                r = self._http.request(
                    method,
                    path,
                    json=json,
                    params=params,
                    headers=headers,
                    content=None if content is None else content(),
                    timeout=self._http.timeout if timeout is None else timeout,
                )
            except httpx.TransportError as e:
                # A request that never reached the server is always safe to send again.
                unsent = isinstance(e, (httpx.ConnectError, httpx.ConnectTimeout))
                if attempt >= self.retries or not (idempotent or unsent):
                    raise errors.TransportError(f"{method} {path}: {e!r}") from e
                why = f"the server did not answer ({type(e).__name__}: {e})"
                self._wait(self._delay(attempt, None), why, attempt + 1, self.retries, method, path)
                attempt += 1
                continue
            retryable = r.status_code == 429 or r.status_code >= 500
            if not idempotent:
                # Answers after which nothing was stored: safe to send again.
                retryable = r.status_code in (429, 503, 507)
            if retryable:
                body = _body(r)
                if _searched_until_deadline(r.status_code, body):
                    if deadlines < searches and attempt < self.retries:
                        why = _why(r.status_code, body)
                        self._wait(
                            self._delay(attempt, r), why, deadlines + 1, searches, method, path
                        )
                        deadlines += 1
                        attempt += 1
                        continue
                elif attempt < self.retries:
                    why = _why(r.status_code, body)
                    self._wait(
                        self._delay(attempt, r), why, attempt + 1, self.retries, method, path
                    )
                    attempt += 1
                    continue
            if r.is_error:
                raise errors.from_response(r.status_code, _body(r))
            return r

    def _exp(self, experiment_id: int | None) -> int:
        eid = experiment_id if experiment_id is not None else self.experiment_id
        if eid is None:
            raise ValueError(
                "no current experiment: call create_experiment, ensure_experiment or use(id) first"
            )
        return eid

    def _path(self, suffix: str, experiment_id: int | None = None) -> str:
        return f"/v1/experiments/{self._exp(experiment_id)}{suffix}"

    def _post_idempotent(
        self,
        suffix: str,
        body: dict[str, Any],
        idempotency_key: str,
        deadline_retries: int | None = None,
    ) -> tuple[Any, bool]:
        """POSTs ``body`` to the current experiment's ``suffix`` under ``idempotency_key``;
        returns the answer's JSON and whether the server replayed a stored answer."""
        r = self._request(
            "POST",
            self._path(suffix),
            json=body,
            headers={"Idempotency-Key": idempotency_key},
            deadline_retries=deadline_retries,
        )
        return r.json(), r.headers.get("idempotent-replayed", "").lower() == "true"

    # ------------------------------------------------------------------ health

    def ready(self) -> bool:
        """Whether the server answers and its database is ready (one try, no retries)."""
        try:
            return self._http.get("/readyz").status_code == 200
        except httpx.TransportError:
            return False

    def wait_ready(self, timeout: float = 30.0) -> None:
        """Waits until the server is ready; raises :class:`TransportError` after ``timeout``."""
        deadline = time.monotonic() + timeout
        while not self.ready():
            if time.monotonic() > deadline:
                raise errors.TransportError(f"{self._http.base_url} not ready after {timeout} s")
            self._sleep(0.05)

    # ------------------------------------------------------------------ experiments

    def use(self, experiment_id: int) -> Client:
        """Makes ``experiment_id`` the current experiment; returns the client."""
        self.experiment_id = experiment_id
        return self

    def create_experiment(
        self, settings: Mapping[str, Any] | None = None, **fields: Any
    ) -> Experiment:
        """Creates an experiment and makes it the current one.

        ``settings`` is the ``ExperimentRequest`` body (``name``, ``domain``, ``d_max``,
        ``seed``, ``mde``, ``learning``); keyword arguments are merged into it. The server does
        not deduplicate creations, so this is not retried once the request may have arrived;
        use :meth:`ensure_experiment` to create by name safely.
        """
        body = {**(settings or {}), **fields}
        r = self._request("POST", "/v1/experiments", json=body, idempotent=False)
        exp = Experiment.from_json(r.json())
        self.experiment_id = exp.id
        return exp

    def ensure_experiment(
        self, name: str, settings: Mapping[str, Any] | None = None, **fields: Any
    ) -> Experiment:
        """The newest experiment called ``name``, created with ``settings`` if there is none;
        it becomes the current one. Safe to call again after a crash or a lost answer (an
        experiment whose creation answer was lost is found by its name).

        An experiment found by its name must have the settings asked for: each setting given
        (``settings`` merged with the keyword arguments, nested objects and lists compared
        item by item, numbers as numbers) is compared with the resolved settings the server
        returns; settings not given, and those given as ``None`` (the default), are not
        compared. Any difference raises :class:`~precond_client.errors.ExperimentMismatch`
        listing them (nothing is created or used). Without settings the experiment is used as
        it is.
        """
        if not name:
            raise ValueError("ensure_experiment needs a non-empty name")
        asked = {k: v for k, v in {**(settings or {}), **fields}.items() if k != "name"}
        for attempt in range(self.retries + 1):
            found = [e for e in self.list_experiments() if e.name == name]
            if found:
                exp = found[-1]
                differences = settings_differences(asked, exp.raw)
                if differences:
                    raise errors.ExperimentMismatch(exp, differences)
                self.experiment_id = exp.id
                return exp
            try:
                return self.create_experiment(settings, **{**fields, "name": name})
            except errors.TransportError as e:
                if attempt >= self.retries:
                    raise
                why = f"creating experiment {name!r} failed ({e})"
                delay = self._delay(attempt, None)
                self._wait(delay, why, attempt + 1, self.retries, "POST", "/v1/experiments")
        raise AssertionError("unreachable")

    def list_experiments(self) -> list[Experiment]:
        """Every experiment, oldest first."""
        items = self._request("GET", "/v1/experiments").json()["items"]
        return [Experiment.from_json(e) for e in items]

    def get_experiment(self, experiment_id: int | None = None) -> Experiment:
        """An experiment (default the current one) with its progress."""
        exp = Experiment.from_json(self._request("GET", self._path("", experiment_id)).json())
        self._state_dim[exp.id] = exp.state_space.dim
        return exp

    # ------------------------------------------------------------------ proposals and plans

    def propose(
        self,
        start: ArrayLike,
        goal: ArrayLike,
        client_id: str | None = None,
        candidates: Sequence[Candidate] | None = None,
        strategy: str | None = None,
        *,
        models: Sequence[str] | None = None,
        deadline_retries: int | None = None,
    ) -> Proposal:
        """Asks for the trajectory to execute from ``start`` to ``goal``, leased to
        ``client_id`` (default :attr:`client_id`).

        In an experiment with several models, ``models`` names the models the service's
        candidates may step with (``"domain"`` for the domain's own): each step relies on the
        cheapest model whose precondition trusts it, and the candidates are valued by what
        their execution teaches each of them (``Proposal.step_models`` says which model each
        step relied on). Default: the domain's model alone.

        Asking again while the lease is open returns the same proposal; asking for another
        problem raises :class:`~precond_client.errors.Conflict` whose ``lease`` names the
        held proposal. With ``candidates`` (required for a client-side model) the server
        scores them instead of planning. No trajectory inside the precondition raises
        :class:`~precond_client.errors.NoPlan`; a search that keeps running past the server's
        deadline raises :class:`~precond_client.errors.DeadlineExceeded` after
        ``deadline_retries`` repeats (default :attr:`deadline_retries`).
        """
        body: dict[str, Any] = {
            "start": as_list(start),
            "goal": as_list(goal),
            "client_id": client_id or self.client_id,
        }
        if strategy is not None:
            body["strategy"] = strategy
        if candidates is not None:
            body["candidates"] = [c.to_json() for c in candidates]
        if models is not None:
            body["models"] = list(models)
        r = self._request(
            "POST", self._path("/proposals"), json=body, deadline_retries=deadline_retries
        )
        return Proposal.from_json(r.json())

    def get_proposal(self, proposal_id: int) -> Proposal:
        """A proposal with its current status."""
        return Proposal.from_json(
            self._request("GET", self._path(f"/proposals/{proposal_id}")).json()
        )

    def abandon(self, proposal_id: int) -> Proposal:
        """Gives a proposal up, releasing its lease (repeating it is harmless)."""
        r = self._request("POST", self._path(f"/proposals/{proposal_id}/abandon"))
        return Proposal.from_json(r.json())

    def continue_proposal(
        self,
        proposal_id: int,
        transitions: Iterable[Transition | Mapping[str, Any]],
        candidates: Sequence[Candidate] | None = None,
        idempotency_key: str | None = None,
        *,
        deadline_retries: int | None = None,
    ) -> Continued:
        """Closed-loop execution: posts the prefix of proposal ``proposal_id`` the robot has
        executed (stored as a partial trajectory, closing the lease) and returns it with a new
        proposal from the last ``s_next`` to the same goal, leased to the same client.

        The first transition must start at the proposal's start. The default
        ``Idempotency-Key`` is ``continue-<id>``: a proposal is continued once, so a retry after
        a lost answer stores nothing twice and returns the same new proposal. With
        ``candidates`` (a client-side model) the server scores them instead of planning.

        The prefix is stored before the new proposal is planned: an error answered after that
        (``no_plan`` from where the robot is, a search past the deadline — repeated
        ``deadline_retries`` times, default :attr:`deadline_retries`) carries
        ``details["stored_trajectory_id"]``. :meth:`~precond_client.robot.Episode.run_closed_loop`
        drives this step by step.
        """
        items = _transitions_json(transitions, "continuing a proposal needs the executed prefix")
        body: dict[str, Any] = {"transitions": items}
        if candidates is not None:
            body["candidates"] = [c.to_json() for c in candidates]
        answer, replayed = self._post_idempotent(
            f"/proposals/{int(proposal_id)}/continue",
            body,
            idempotency_key or f"continue-{int(proposal_id)}",
            deadline_retries=deadline_retries,
        )
        return Continued.from_json(answer, replayed=replayed)

    def plan(
        self,
        start: ArrayLike,
        goal: ArrayLike,
        beta: float | None = None,
        candidates: Sequence[Candidate] | None = None,
        max_extensions: int | None = None,
        *,
        models: Sequence[str] | None = None,
        deadline_retries: int | None = None,
    ) -> Plan:
        """A test-time plan inside the precondition at ``beta`` (default the experiment's test
        β); ``found`` is false when there is none. Nothing is stored. ``max_extensions``: this
        search's budget (default the experiment's ``learning.max_extensions``), e.g. ten times
        it to tell "no plan inside the precondition" from "none found in time". ``models``: the
        models the search may step with, by name (``"domain"`` for the domain's own; default
        every model with a precondition), each step relying on the cheapest whose precondition
        trusts it; the plan's ``step_models`` say which. A search past the server's deadline
        is repeated ``deadline_retries`` times (default :attr:`deadline_retries`), then raises
        :class:`~precond_client.errors.DeadlineExceeded`. :meth:`execute_plan` executes plans
        closed loop."""
        body: dict[str, Any] = {"start": as_list(start), "goal": as_list(goal)}
        if models is not None:
            body["models"] = [str(m) for m in models]
        if beta is not None:
            body["beta"] = float(beta)
        if candidates is not None:
            body["candidates"] = [c.to_json() for c in candidates]
        if max_extensions is not None:
            body["max_extensions"] = int(max_extensions)
        r = self._request(
            "POST", self._path("/plans"), json=body, deadline_retries=deadline_retries
        )
        return Plan.from_json(r.json())

    # ------------------------------------------------------------------ trajectories

    def post_trajectory(
        self,
        transitions: Iterable[Transition | Mapping[str, Any]],
        proposal_id: int | None = None,
        partial: bool = False,
        idempotency_key: str | None = None,
        source: Source | Mapping[str, Any] | None = None,
    ) -> TrajectoryCreated:
        """Posts an executed trajectory; the server labels and stores it atomically.

        Every post carries an ``Idempotency-Key``, so retries never store it twice. The default
        key is ``proposal-<id>`` for the execution of a proposal (a proposal is executed once,
        so even a restarted robot posting it again is recognised) and a random one otherwise.
        ``source`` says where the trajectory comes from (a logged dataset and episode, a
        simulated environment); the server stores it and shows it with the trajectory and in
        the runs list. A trajectory posted for a proposal that is not the proposal's actions
        from its start (or a prefix of them) is stored all the same and comes back
        ``deviating``.
        """
        items = _transitions_json(transitions, "a trajectory needs at least one transition")
        body: dict[str, Any] = {"transitions": items, "partial": bool(partial)}
        if proposal_id is not None:
            body["proposal_id"] = int(proposal_id)
        if source is not None:
            body["source"] = source.to_json() if isinstance(source, Source) else dict(source)
        if idempotency_key is None:
            idempotency_key = (
                f"proposal-{proposal_id}" if proposal_id is not None else f"py-{uuid.uuid4()}"
            )
        answer, replayed = self._post_idempotent("/trajectories", body, idempotency_key)
        return TrajectoryCreated.from_json(answer, replayed=replayed)

    def get_trajectory(self, trajectory_id: int) -> Trajectory:
        """A stored trajectory with its labelled transitions, whether it deviated from its
        proposal and where it comes from."""
        r = self._request("GET", self._path(f"/trajectories/{trajectory_id}"))
        return Trajectory.from_json(r.json())

    def labels(self) -> ModelLabels:
        """What each of the experiment's models of its robot labelled — the domain's own
        (``"domain"``) first, then the further models of its ``models``: how many transitions,
        how many missing, the mean and largest deviation and how often below ``d_max``."""
        r = self._request("GET", self._path("/labels"))
        return ModelLabels.from_json(r.json())

    def runs(self, page_size: int = 100) -> Iterator[Run]:
        """Every run of the experiment, newest first: proposals with the trajectories that
        executed them, trajectories posted without a proposal, and refused proposal requests
        (``status == "refused"``), fetched page by page as the iterator advances."""
        for item in self._pages("/runs", "offset", 0, page_size):
            yield Run.from_json(item)

    def transitions(self, after: int = 0, page_size: int = 1000) -> Iterator[StoredTransition]:
        """Every stored transition with an id greater than ``after``, in id order, fetched
        page by page as the iterator advances."""
        for item in self._pages("/transitions", "after", after, page_size):
            yield StoredTransition.from_json(item)

    def _pages(
        self, suffix: str, cursor_name: str, start: int, page_size: int
    ) -> Iterator[dict[str, Any]]:
        """The items of a paged list, page by page: each page is asked for with
        ``cursor_name`` set to the previous page's ``next`` (``start`` first) until it is null."""
        cursor: int | None = start
        while cursor is not None:
            page = self._request(
                "GET", self._path(suffix), params={cursor_name: cursor, "limit": page_size}
            ).json()
            yield from page["items"]
            cursor = page["next"]

    # ------------------------------------------------------------------ logged data

    def import_file(
        self,
        path: str | Path,
        *,
        format: str | None = None,
        state: Sequence[str] | str | None = None,
        action: Sequence[str] | str | None = None,
        next_state: Sequence[str] | str | None = None,
        predicted: Sequence[str] | str | None = None,
        episode: str | None = None,
        label: str | None = None,
        dataset_name: str | None = None,
        dataset_id: str | None = None,
        max_transitions: int | None = None,
        progress: bool | None = None,
        timeout: float | None = 3600.0,
    ) -> ImportReport:
        """Imports a CSV or Parquet file of logged transitions into the current experiment,
        one trajectory per episode: the file is sent as it is to the server, which runs
        ``precond import``'s code on it (``POST /v1/experiments/{id}/imports``: same columns
        by convention, same idempotency keys, so importing again stores nothing twice and
        either tool finds the other's imports).

        ``state``, ``action``, ``next_state`` (and ``predicted`` for a client-side model)
        name the columns — several scalar columns in order, or one list column — when the
        conventions (``s_*``/``a_*``/``s_next_*``, ``observation.state``/``action``) do not
        find them; without a next state a transition ends at the next row's state.
        ``episode`` names the episode column (``"none"``: the file is one episode).
        ``format`` is ``csv`` or ``parquet`` (default by extension). The dataset's name is
        ``dataset_name`` or the file's absolute path, its id in the keys the hash of that name
        (``dataset_id`` to pin it): importing the file again stores only the episodes not
        stored yet, from any working directory. An episode longer than ``max_transitions``
        (at most the server's ``--max-transitions``) is stored as several trajectories. The
        file may be up to the server's ``--max-import-bytes`` (256 MiB by default); the answer
        is awaited for up to ``timeout`` seconds (``None``: without limit). ``progress``: a
        tqdm bar of the upload when tqdm is installed (``False``: never).

        Returns an :class:`~precond_client.models.ImportReport`; data the server cannot read
        raises :class:`~precond_client.imports.DatasetError` naming the line and column, a
        refused trajectory (an episode that changed since it was stored, say)
        :class:`~precond_client.imports.ImportFailed` saying which episode and what was
        stored before it."""
        p = Path(path)
        fmt = format or ("parquet" if p.suffix.lower() in (".parquet", ".pq") else "csv")
        if fmt not in ("csv", "parquet"):
            raise ValueError(f"format {format!r}: use 'csv' or 'parquet'")
        dataset = dataset_name or default_dataset_name(p)
        if dataset_id is not None:
            check_dataset_id(dataset_id)
        if max_transitions is not None and max_transitions < 1:
            raise ValueError(f"max_transitions {max_transitions}: at least 1")
        try:
            size = p.stat().st_size
        except OSError as e:
            raise DatasetError(f"{p}: {e.strerror or e}") from e

        def listed(columns: Sequence[str] | str | None) -> str | None:
            return columns if columns is None or isinstance(columns, str) else ",".join(columns)

        query = {
            "dataset": dataset,
            "dataset_id": dataset_id,
            "format": fmt,
            "label": label,
            "state": listed(state),
            "action": listed(action),
            "next_state": listed(next_state),
            "predicted_state": listed(predicted),
            "episode": episode,
            "max_transitions": max_transitions,
        }
        content_type = "text/csv" if fmt == "csv" else "application/vnd.apache.parquet"
        bar = _upload_progress(size, p.name, progress)

        def chunks() -> Iterator[bytes]:
            if bar is not None:
                bar.reset(total=size)
            with p.open("rb") as f:
                while chunk := f.read(1 << 16):
                    if bar is not None:
                        bar.update(len(chunk))
                    yield chunk

        log.info("%s: %d bytes to the server's import (dataset %s)", p, size, dataset)
        try:
            r = self._request(
                "POST",
                self._path("/imports"),
                params={k: v for k, v in query.items() if v is not None},
                headers={"Content-Type": content_type, "Content-Length": str(size)},
                content=chunks,
                timeout=httpx.Timeout(self._http.timeout.connect, read=timeout, write=timeout),
            )
        except errors.ApiError as e:
            raise import_error(dataset, e) from e
        finally:
            if bar is not None:
                bar.close()
        report = ImportReport.from_json(r.json())
        if report.split_episodes:
            log.warning(
                "%s: %d episodes were stored as several trajectories (longer than %s "
                "transitions or the server's body limit)",
                dataset,
                report.split_episodes,
                max_transitions or "the server's",
            )
        log.info(
            "%s: %d episodes as %d trajectories (%d transitions): %d stored, %d already there",
            dataset,
            report.episodes,
            report.trajectories,
            report.transitions,
            report.created,
            report.replayed,
        )
        return report

    def import_lerobot(
        self,
        root: str | Path,
        *,
        state: str = "observation.state",
        action: str = "action",
        label: str | None = None,
        dataset_name: str | None = None,
        dataset_id: str | None = None,
        max_transitions: int | None = None,
        progress: bool | None = None,
        timeout: float | None = 3600.0,
    ) -> ImportReport:
        """Imports a LeRobot v3 dataset (a local directory with ``meta/info.json`` and
        ``data/**/*.parquet``) into the current experiment: one trajectory per
        ``episode_index``, each transition from a frame's ``observation.state`` with its
        ``action`` to the next frame's state. Its data files' three columns are written to
        one temporary Parquet file (an episode may span two files) and imported as
        :meth:`import_file` does. Source ``lerobot:<directory name>`` (or ``dataset_name``);
        the dataset id hashes the directory's absolute path (or ``dataset_name``), so a
        dataset that grows imports only its new episodes. Needs ``pyarrow``. The experiment's
        state and action must be the dataset's (their dimensions are checked)."""
        r = Path(root)
        with tempfile.TemporaryDirectory(prefix="precond-lerobot-") as tmp:
            table = Path(tmp) / "frames.parquet"
            lerobot_table(r, table, [state, action, "episode_index"])
            return self.import_file(
                table,
                format="parquet",
                state=state,
                action=action,
                episode="episode_index",
                label=label,
                dataset_name=dataset_name or f"lerobot:{r.resolve().name}",
                dataset_id=dataset_id or dataset_identity(dataset_name or str(r.resolve())),
                max_transitions=max_transitions,
                progress=progress,
                timeout=timeout,
            )

    def import_minari(
        self,
        dataset: str | Path,
        *,
        observation_key: str | None = None,
        label: str | None = None,
        dataset_id: str | None = None,
        max_transitions: int | None = None,
        progress: bool | None = None,
    ) -> ImportReport:
        """Imports a Minari dataset into the current experiment: by id with ``minari``
        installed, or from its HDF5 file with ``h5py``; one trajectory per episode, ``s``
        each observation but the last, ``s_next`` the one after it (a dict observation is read
        at ``observation_key``). Source ``minari:<dataset>``. The episodes are written to a
        temporary CSV file and imported by the server
        (:func:`~precond_client.imports.import_episodes`)."""
        name, ident, episodes = read_minari(dataset, observation_key=observation_key)
        return import_episodes(
            self,
            episodes,
            dataset=name,
            dataset_id=dataset_id or ident,
            label=label,
            max_transitions=max_transitions,
            progress=progress,
        )

    # ------------------------------------------------------------------ the model

    # ------------------------------------------------------------------ data hygiene

    def exclude_trajectory(self, trajectory_id: int, reason: str) -> Exclusion:
        """Leaves one stored trajectory (a bad run) out of the experiment's model, saying why.
        The exclusion and a refit are stored together; the refit runs in the background, and
        the next model version (its ``exclusions``) is fitted without it. Needs an ``admin``
        token. The trajectory stays stored; :meth:`restore_exclusion` brings it back."""
        body = {"trajectory_id": int(trajectory_id), "reason": reason}
        r = self._request("POST", self._path("/exclusions"), json=body, idempotent=False)
        return Exclusion.from_json(r.json())

    def exclude_time_range(
        self, since: datetime.datetime | str, until: datetime.datetime | str, reason: str
    ) -> Exclusion:
        """Leaves every trajectory stored from ``since`` (inclusive) to ``until`` (exclusive)
        out of the model — a day a sensor was miscalibrated. Times are RFC 3339 strings or
        timezone-aware datetimes; the range covers what is stored now, never a trajectory
        stored later. As :meth:`exclude_trajectory` otherwise."""
        body = {"since": _rfc3339(since), "until": _rfc3339(until), "reason": reason}
        r = self._request("POST", self._path("/exclusions"), json=body, idempotent=False)
        return Exclusion.from_json(r.json())

    def restore_exclusion(self, exclusion_id: int) -> Exclusion:
        """Takes an exclusion's trajectories back into the model (the next fit, requested
        now); restoring twice is harmless."""
        r = self._request("POST", self._path(f"/exclusions/{int(exclusion_id)}/restore"))
        return Exclusion.from_json(r.json())

    def exclusions(self, page_size: int = 100) -> Iterator[Exclusion]:
        """Every exclusion of the experiment, in effect or restored, newest first: what was
        left out of the model, why, by whom and when."""
        for item in self._pages("/exclusions", "offset", 0, page_size):
            yield Exclusion.from_json(item)

    # ------------------------------------------------------------------ the model

    def model(self) -> Model:
        """The MDE version answering queries."""
        return Model.from_json(self._request("GET", self._path("/model")).json())

    def export_model(self, version: int | None = None, model: str | None = None) -> ExportedModel:
        """The answering model version (or ``version``) exported as a self-contained document,
        read into an :class:`~precond_client.export.ExportedModel` that evaluates ``μ``, ``σ``
        and the precondition with numpy alone (and saves to a JSON file for the robot).
        ``model`` names one of the experiment's further models whose estimator to export
        (default the domain's own model's). Raises :class:`~precond_client.errors.Conflict`
        while the prior answers, or when the version holds no estimator of ``model``."""
        params: dict[str, Any] = {}
        if version is not None:
            params["version"] = int(version)
        if model is not None:
            params["model"] = model
        r = self._request("GET", self._path("/model/export"), params=params or None)
        return ExportedModel.from_json(r.json())

    def refit(self) -> Model:
        """Fits the MDE now on everything stored and returns the new version. A fit that
        outlasts the server's deadline is answered ``202`` with the version still answering
        and goes on in the background; then that version is returned (poll :meth:`model` for
        the new one)."""
        r = self._request("POST", self._path("/model/refit"), idempotent=False)
        return Model.from_json(r.json())

    def wait_for_model(
        self, n_trajectories: int, timeout: float = 120.0, *, log_every: float = 30.0
    ) -> Model:
        """Waits until the answering model was fitted on at least ``n_trajectories``
        trajectories (background refits run after every batch); returns it. Raises
        ``TimeoutError`` after ``timeout`` seconds. Every ``log_every`` seconds of waiting it
        logs (``INFO``) which version answers and what it covers."""
        t0 = time.monotonic()
        deadline = t0 + timeout
        next_log = t0 + log_every
        poll = 0.1
        while True:
            m = self.model()
            if m.n_trajectories >= n_trajectories:
                return m
            now = time.monotonic()
            if now > deadline:
                raise TimeoutError(
                    f"model covers {m.n_trajectories} trajectories, not {n_trajectories}, "
                    f"after {timeout} s"
                )
            if now >= next_log:
                log.info(
                    "%s: still waiting for a model fitted on %d trajectories (%s so far): "
                    "version %d answers, fitted on %d trajectories (n = %d transitions)",
                    _status.current() or "waiting for the model",
                    n_trajectories,
                    _status.seconds(now - t0),
                    m.version,
                    m.n_trajectories,
                    m.n_train,
                )
                next_log = now + log_every
            self._sleep(poll)
            poll = min(1.0, poll * 1.5)

    def precondition(
        self,
        points: ArrayLike | tuple[ArrayLike, ArrayLike],
        beta: float | None = None,
        predicted: ArrayLike | None = None,
        model: str | None = None,
    ) -> Precondition:
        """Judges state-actions: ``μ``, ``σ``, ``μ + βσ`` and whether each is inside the
        precondition, at ``beta`` (default the experiment's test β).

        ``model`` names one of the experiment's further models (its ``models``) whose own
        precondition to judge (the service asks that model for its predictions); default the
        domain's own model (``"domain"``).

        ``points`` is either a pair ``(states, actions)`` of arrays ``(N, n)`` and ``(N, m)``,
        or one array ``(N, n + m)`` whose first ``n`` columns are the state. ``predicted``
        ``(N, n)`` is the model's ``f̂(s, a)`` per point, needed only when the model is the
        client's and the features read its prediction (``features.prediction``): the service
        asks every other model itself. Large queries are sent in chunks.
        """
        if isinstance(points, tuple):
            states, actions = mat(points[0]), mat(points[1])
        else:
            rows = mat(points)
            eid = self._exp(None)
            if eid not in self._state_dim:
                self.get_experiment()
            n = self._state_dim[eid]
            states, actions = rows[:, :n], rows[:, n:]
        if len(states) != len(actions):
            raise ValueError(f"{len(states)} states for {len(actions)} actions")
        if len(states) == 0:
            raise ValueError("no points to judge")
        preds = None if predicted is None else mat(predicted)
        if preds is not None and len(preds) != len(states):
            raise ValueError(f"{len(preds)} predictions for {len(states)} states")
        parts = []
        for lo in range(0, len(states), PRECONDITION_CHUNK):
            hi = lo + PRECONDITION_CHUNK
            chunk: list[dict[str, Any]] = [
                {"s": as_list(s), "a": as_list(a)}
                for s, a in zip(states[lo:hi], actions[lo:hi], strict=True)
            ]
            if preds is not None:
                for point, p in zip(chunk, preds[lo:hi], strict=True):
                    point["s_pred"] = as_list(p)
            body: dict[str, Any] = {"points": chunk}
            if beta is not None:
                body["beta"] = float(beta)
            if model is not None:
                body["model"] = model
            r = self._request("POST", self._path("/precondition"), json=body)
            parts.append(Precondition.from_json(r.json()))
        return parts[0] if len(parts) == 1 else Precondition.concat(parts)

    # ------------------------------------------------------------------ the loop

    def learn(
        self,
        problems: Iterable[Problem],
        *,
        client_id: str | None = None,
        candidates: CandidateFn | None = None,
        models: Sequence[str] | ModelsFn | None = None,
        resume: bool = True,
        skip_no_plan: bool = True,
        wait_for_model: bool = True,
        model_timeout: float = 300.0,
        progress: ProgressFn | None = None,
        deadline_attempts: int = 2,
        transient_attempts: int = 3,
        progress_bar: bool | None = None,
        verbose: bool = True,
    ) -> Learner:
        """The active-learning loop over ``problems`` (pairs ``(start, goal)``): an iterator of
        :class:`~precond_client.robot.Episode`, each a proposal to execute and report with
        ``episode.post(observed_states)`` (or ``episode.abandon()``), or to let the robot
        execute with ``episode.execute(step_fn)`` (open loop, stopped at a step beyond
        ``d_max``) or ``episode.run_closed_loop(step_fn)``.

        A problem whose start already satisfies its goal is skipped (logged), as is one with
        no plan unless ``skip_no_plan=False``. With ``wait_for_model`` (default) the loop waits
        up to ``model_timeout`` seconds, after each completed batch, for the background refit
        before the next proposal. ``progress`` receives a
        :class:`~precond_client.robot.Progress` after each event. ``models`` names the models
        each proposal may step with (see :meth:`propose`), or is a function of the number of
        episodes so far giving them (``None``: the domain's model alone).

        A busy server does not stop the loop: a problem whose search passes the server's
        deadline ``deadline_attempts`` times (default 2), or whose proposal fails with another
        transient answer ``transient_attempts`` times (default 3, each after the client's own
        retries), is skipped and counted (``learner.deadline``, ``learner.failed``,
        ``learner.skipped``), waiting the server's ``Retry-After`` between attempts. Every wait
        is logged at ``INFO``; when logging is not configured, the loop shows its ``INFO``
        lines on standard error (``verbose=False``: it does not), and a tqdm bar where
        standard error is a terminal (``progress_bar``: ``True`` always, ``False`` never). See
        :class:`~precond_client.robot.Learner`."""
        return Learner(
            self,
            problems,
            client_id=client_id or self.client_id,
            candidates=candidates,
            models=models,
            resume=resume,
            skip_no_plan=skip_no_plan,
            wait_for_model=wait_for_model,
            model_timeout=model_timeout,
            progress=progress,
            deadline_attempts=deadline_attempts,
            transient_attempts=transient_attempts,
            progress_bar=progress_bar,
            verbose=verbose,
            sleep=self._sleep,
        )

    # ------------------------------------------------------------------ executing plans

    def metric(self, experiment_id: int | None = None) -> Metric:
        """The experiment's distance between states, goal test and ``d_max``, as the server
        computes them (:class:`~precond_client.execution.Metric`)."""
        return Metric.of(self.get_experiment(experiment_id))

    def monitor(
        self,
        planned: Plan | Proposal | PlannedTrajectory,
        *,
        tolerance: float | None = None,
        post: bool = True,
        goal: ArrayLike | None = None,
        predict: Callable[[Any, Any], ArrayLike] | None = None,
        idempotency_key: str | None = None,
    ) -> Monitor:
        """A :class:`~precond_client.execution.Monitor` of the execution of ``planned`` (a
        test-time :class:`Plan`, a :class:`Proposal`, or a trajectory): report each observed
        state with ``monitor.observe(state)``; a step further than ``tolerance`` (default the
        experiment's ``d_max``, in its distance) from its prediction stops it: the run so far
        is posted as a ``partial`` trajectory (with ``post``; a proposal's as its execution,
        under ``proposal-<id>``, else under ``idempotency_key`` or a random key) and
        :class:`~precond_client.errors.DeviationExceeded` is raised. ``monitor.finish()``
        posts a run that ended otherwise. ``goal`` (a proposal's own by default) tells whether
        it ended there; ``predict(s, a)``, the robot's model, judges each step from where the
        robot really was instead of against the plan."""
        if isinstance(planned, Plan):
            if planned.trajectory is None:
                raise ValueError("the plan was not found: nothing to execute")
            trajectory = planned.trajectory
        elif isinstance(planned, Proposal):
            trajectory = planned.trajectory
        else:
            trajectory = planned
        proposal_id = planned.id if isinstance(planned, Proposal) else None
        if goal is None and isinstance(planned, Proposal):
            goal = planned.goal
        experiment = self.get_experiment()
        metric = Metric.of(experiment)
        key = idempotency_key
        if key is None and proposal_id is None:
            key = f"py-monitor-{uuid.uuid4()}"

        def send(transitions: Sequence[Transition], partial: bool) -> TrajectoryCreated:
            return self.post_trajectory(
                transitions, proposal_id=proposal_id, partial=partial, idempotency_key=key
            )

        return Monitor(
            trajectory.states[0],
            trajectory.actions,
            trajectory.states,
            tolerance=metric.d_max if tolerance is None else tolerance,
            metric=metric,
            post=send if post else None,
            goal=goal,
            predict=predict,
            send_predictions=predict is not None and client_side(experiment),
            proposal_id=proposal_id,
        )

    def execute_plan(
        self,
        start: ArrayLike,
        goal: ArrayLike,
        step_fn: StepFn,
        *,
        tolerance: float | None = None,
        max_steps: int = 1000,
        max_replans: int = 50,
        beta: float | None = None,
        max_extensions: int | None = None,
        models: Sequence[str] | None = None,
    ) -> Execution:
        """Test time, closed loop: plans from ``start`` to ``goal`` inside the precondition
        (:meth:`plan`, at ``beta``, default the test β, with ``models``, default every model of
        the experiment with a precondition), executes it one action at a time with
        ``step_fn(state, action) -> observed state`` (``None``: the robot stopped), and plans
        again from the observed state whenever it is further than ``tolerance`` (default the
        experiment's ``d_max``, in its distance) from the plan's prediction or the plan is
        spent short of the goal. Ends at the goal (the experiment's goal test), after
        ``max_steps`` steps or ``max_replans`` new plans, when no plan is found from where the
        robot is (``status == "no_plan"``), or when the server keeps failing transiently
        (``"failed"``, with the error). Nothing is stored. Returns the
        :class:`~precond_client.execution.Execution` (``success``, ``steps``, ``replans``,
        ``states``, ``deviations``)."""
        metric = self.metric()

        def plan(s: Any, g: Any) -> Plan:
            with _status.activity(f"planning from {np.round(s, 4).tolist()}"):
                return self.plan(s, g, beta=beta, max_extensions=max_extensions, models=models)

        return execute_plan(
            plan,
            start,
            goal,
            step_fn,
            metric=metric,
            tolerance=metric.d_max if tolerance is None else tolerance,
            max_steps=max_steps,
            max_replans=max_replans,
        )
