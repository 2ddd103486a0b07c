"""Errors: every error the server answers becomes an :class:`ApiError` carrying its ``code``,
``message`` and ``details``; a server that cannot be reached becomes a :class:`TransportError`.

The server's error body is always ``{"error": {"code", "message", "details"}}``; each ``code``
has its own subclass so a robot loop can catch exactly what it handles::

    try:
        proposal = client.propose(start, goal)
    except NoPlan as e:
        print("nothing trusted reaches the goal", e.details["extensions"])
"""

from __future__ import annotations

from typing import Any

AT_GOAL_REASON = "the start already satisfies the goal"
"""How the server's ``validation_failed`` on ``goal`` begins when a proposal's start already
satisfies its goal."""


class PrecondError(Exception):
    """Base class of every error this package raises."""


class TransportError(PrecondError):
    """The server could not be reached (or kept failing) after every retry."""


class DeviationExceeded(PrecondError):
    """An execution was stopped by a :class:`~precond_client.execution.Monitor`: the robot's
    observed state after step :attr:`step` lies further than :attr:`tolerance` (by default the
    experiment's ``d_max``, in its distance) from the state predicted for it, so the model was
    wrong there and the rest of the plan is not worth executing. The run up to and including
    that step was posted (``partial``) before this was raised.

    Attributes:
        step: The index of the deviating step (from 0).
        deviation: The distance between the predicted and the observed state.
        tolerance: The tolerance it exceeded.
        observed: The observed state after the step.
        predicted: The state predicted for it.
        execution: What was executed up to and including the step, with the posted
            trajectory (an :class:`~precond_client.execution.Execution`).
    """

    def __init__(
        self,
        step: int,
        deviation: float,
        tolerance: float,
        observed: Any,
        predicted: Any,
        execution: Any,
    ) -> None:
        super().__init__(
            f"step {step} deviated from its prediction by {deviation:.4g} > {tolerance:.4g}: "
            f"execution stopped"
        )
        self.step = step
        self.deviation = deviation
        self.tolerance = tolerance
        self.observed = observed
        self.predicted = predicted
        self.execution = execution


class ExperimentMismatch(PrecondError):
    """:meth:`~precond_client.Client.ensure_experiment` found an experiment by its name whose
    stored settings differ from the ones asked for (creating another with the same name would
    hide it; learning on in it would mix two setups).

    Attributes:
        experiment: The experiment found (an :class:`~precond_client.models.Experiment`).
        differences: ``(path, asked, stored)`` per differing setting, e.g.
            ``("domain.model.url", "http://…:9001/predict", "http://…:9000/predict")``;
            ``stored`` is :data:`ABSENT` when the experiment has no such setting.
    """

    def __init__(self, experiment: Any, differences: list[tuple[str, Any, Any]]) -> None:
        listed = "; ".join(
            f"{path}: asked {asked!r}, stored {stored!r}" for path, asked, stored in differences
        )
        super().__init__(
            f"experiment {experiment.id} {experiment.name!r} exists with other settings "
            f"({listed}); choose another name, or ensure_experiment(name) without settings to "
            f"use it as it is"
        )
        self.experiment = experiment
        self.differences = differences


ABSENT = "<absent>"
"""The stored value in :attr:`ExperimentMismatch.differences` of a setting the experiment
does not have."""


class ApiError(PrecondError):
    """An error answered by the server.

    Attributes:
        status: The HTTP status code.
        code: The stable machine-readable code, e.g. ``validation_failed``.
        message: The server's human-readable message.
        details: Code-specific details (``{"field", "reason"}`` for ``validation_failed``, the
            lease for a ``conflict`` over a held proposal, ...), or ``None``.
    """

    def __init__(self, status: int, code: str, message: str, details: Any = None) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status = status
        self.code = code
        self.message = message
        self.details = details


class BadRequest(ApiError):
    """``400 bad_request``: the body was not well-formed JSON."""


class Unauthorized(ApiError):
    """``401 unauthorized``: the server checks access tokens and the request had none, or one
    it does not know (pass ``token=`` to :class:`~precond_client.Client`)."""


class Forbidden(ApiError):
    """``403 forbidden``: the token lacks the route's role (``read`` < ``write`` < ``admin``)
    or does not reach the experiment."""


class NotFound(ApiError):
    """``404 not_found``: no such experiment, trajectory, proposal or route."""


class MethodNotAllowed(ApiError):
    """``405 method_not_allowed``: the path exists but not with this method."""


class Conflict(ApiError):
    """``409 conflict``: an ``Idempotency-Key`` reused with another body, a proposal already
    executed, a refit with no data, or a client holding a lease on another problem.

    For a held lease, :attr:`lease` gives its ``proposal_id``, ``client_id``, ``start`` and
    ``goal``.
    """

    @property
    def lease(self) -> dict[str, Any] | None:
        """The held lease (``proposal_id``, ``client_id``, ``start``, ``goal``), if this is one."""
        d = self.details
        if isinstance(d, dict) and "proposal_id" in d and "client_id" in d:
            return d
        return None


class LimitReached(ApiError):
    """``409 limit_reached``: creating an experiment on a server that holds its limit of
    experiments (``--max-experiments``)."""


class PayloadTooLarge(ApiError):
    """``413 payload_too_large``: the body exceeds the server's ``--max-body-bytes``."""


class ValidationFailed(ApiError):
    """``422 validation_failed``: a field is wrong; ``details["field"]`` names it."""

    @property
    def field(self) -> str | None:
        """The offending field, e.g. ``transitions[3].s``."""
        d = self.details
        return str(d["field"]) if isinstance(d, dict) and "field" in d else None

    @property
    def reason(self) -> str | None:
        """Why the field is wrong."""
        d = self.details
        return str(d["reason"]) if isinstance(d, dict) and "reason" in d else None

    @property
    def start_satisfies_goal(self) -> bool:
        """Whether the answer is to a proposal whose start already satisfies its goal (there is
        nothing to plan; the spec's ``at_goal`` example of ``create_proposal``)."""
        return self.field == "goal" and AT_GOAL_REASON in (self.reason or "")


class NoPlan(ApiError):
    """``422 no_plan``: no goal-reaching trajectory inside the precondition was found."""


class Overloaded(ApiError):
    """``429 overloaded``: too many planning requests wait for a slot; nothing was planned.
    Retried by the client (after the server's ``Retry-After``) before it is raised;
    ``details["retry_after_seconds"]`` says when to try again."""


class ModelUnavailable(ApiError):
    """``502 model_unavailable``: the experiment's remote model refused, failed or answered
    the wrong shape; nothing was stored."""


class ModelTimeout(ApiError):
    """``504 model_timeout``: the experiment's remote model did not answer in time."""


class Unavailable(ApiError):
    """``503 unavailable``: the server's database does not answer."""


class DeadlineExceeded(ApiError):
    """``503 deadline_exceeded``: a proposal or plan did not finish within the server's
    deadline (nothing was stored), or a forced refit did not (it goes on in the background).
    ``details`` has ``extensions``, ``timeout_ms`` and ``retry_after_seconds``. A search that
    ran until the deadline (``extensions`` > 0) is repeated only the client's
    ``deadline_retries`` times before this is raised (it would most likely run as long
    again); one that passed its deadline waiting for a planning slot is retried like any
    ``503``. :meth:`~precond_client.Client.learn` skips a problem after ``deadline_attempts``
    such searches."""


class Cancelled(ApiError):
    """``503 cancelled``: the server cancelled the request's search because the client went
    away; a client only sees it when a proxy kept the connection open."""


class ModelNotAllowed(ApiError):
    """``409 model_not_allowed``: the experiment's remote model URL is no longer under a prefix
    the operator allows (``--allow-model-url`` changed since the experiment was created);
    nothing was sent or stored. ``details`` has ``model`` and ``reason``."""


class ModelBusy(ApiError):
    """``503 model_busy``: no call to the experiment's remote model could start before its
    deadline (the server's per-URL limit of calls in flight was reached); nothing was sent or
    stored. Retried by the client before it is raised."""


class RequestTimeout(ApiError):
    """``408 request_timeout``: the request's body did not arrive within the server's
    ``--body-read-timeout-secs``; nothing was stored."""


class UnsupportedMediaType(ApiError):
    """``415 unsupported_media_type``: a body sent without ``Content-Type: application/json``
    (the client always sends it)."""


class InsufficientStorage(ApiError):
    """``507 insufficient_storage``: the server's disk is full; nothing of the request was
    stored. Retried by the client (it honours ``Retry-After``) before it is raised."""


class InternalError(ApiError):
    """``500 internal``: a bug in the server (logged there)."""


_BY_CODE: dict[str, type[ApiError]] = {
    "bad_request": BadRequest,
    "unauthorized": Unauthorized,
    "forbidden": Forbidden,
    "not_found": NotFound,
    "method_not_allowed": MethodNotAllowed,
    "conflict": Conflict,
    "limit_reached": LimitReached,
    "payload_too_large": PayloadTooLarge,
    "validation_failed": ValidationFailed,
    "no_plan": NoPlan,
    "overloaded": Overloaded,
    "internal": InternalError,
    "insufficient_storage": InsufficientStorage,
    "model_unavailable": ModelUnavailable,
    "unavailable": Unavailable,
    "deadline_exceeded": DeadlineExceeded,
    "cancelled": Cancelled,
    "model_timeout": ModelTimeout,
    "model_not_allowed": ModelNotAllowed,
    "model_busy": ModelBusy,
    "request_timeout": RequestTimeout,
    "unsupported_media_type": UnsupportedMediaType,
}
"""The exception class of each error code the server answers (the spec's
``ErrorBody.code`` enum; ``tests/test_wire.py`` checks they are the same list)."""


TRANSIENT_STATUSES = frozenset({429, 502, 503, 504, 507})
"""The statuses of answers that say "not now" rather than "never": overloaded (429), a remote
model that failed or timed out (502, 504), a deadline passed, a database or model that did not
answer (503), a full disk (507). Nothing of such a request was stored."""


def is_transient(error: BaseException) -> bool:
    """Whether ``error`` may go away if the same request is made later: a
    :class:`TransportError` (the server stayed unreachable through every retry) or an
    :class:`ApiError` whose status is in :data:`TRANSIENT_STATUSES`. Validation errors,
    conflicts, a missing experiment, ``no_plan`` and the server's own bugs (500) are not."""
    if isinstance(error, TransportError):
        return True
    return isinstance(error, ApiError) and error.status in TRANSIENT_STATUSES


def retry_after(error: BaseException, default: float) -> float:
    """The seconds ``error`` (an :class:`ApiError`) says to wait before trying again
    (``details.retry_after_seconds``, as the ``Retry-After`` header said), else ``default``."""
    details = getattr(error, "details", None)
    if isinstance(details, dict):
        value = details.get("retry_after_seconds")
        if isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 0:
            return float(value)
    return default


def from_response(status: int, body: Any) -> ApiError:
    """The error for a non-2xx answer with JSON ``body`` (or anything else, e.g. a proxy's
    HTML page, which becomes an :class:`ApiError` with code ``http_<status>``)."""
    err = body.get("error") if isinstance(body, dict) else None
    if isinstance(err, dict) and isinstance(err.get("code"), str):
        code = err["code"]
        cls = _BY_CODE.get(code, ApiError)
        return cls(status, code, str(err.get("message", "")), err.get("details"))
    text = body if isinstance(body, str) else repr(body)
    return ApiError(status, f"http_{status}", text[:500], None)
