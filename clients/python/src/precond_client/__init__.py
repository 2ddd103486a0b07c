"""precond-client: drive a precond server's active learning of model preconditions from Python.

- :class:`Client` — experiments, proposals, trajectories (idempotent, retried), the model,
  precondition queries and plans, with numpy arrays in and out.
- :meth:`Client.learn` — the robot's loop: propose, execute, post, surviving restarts.
- :func:`serve_model` — serve a numpy dynamics model as a custom domain's ``remote`` model.
- :meth:`Client.import_file`, :meth:`Client.import_lerobot`, :meth:`Client.import_minari` —
  logged data (CSV, Parquet, LeRobot v3, Minari) into an experiment, idempotently
  (:mod:`precond_client.imports`).
- :mod:`precond_client.errors` — the server's errors as exceptions with ``code``, ``message``
  and ``details``.
"""

from .client import Client
from .errors import (
    ApiError,
    BadRequest,
    Cancelled,
    Conflict,
    DeadlineExceeded,
    ExperimentMismatch,
    Forbidden,
    InternalError,
    LimitReached,
    MethodNotAllowed,
    ModelTimeout,
    ModelUnavailable,
    NoPlan,
    NotFound,
    Overloaded,
    PayloadTooLarge,
    PrecondError,
    TransportError,
    Unauthorized,
    Unavailable,
    ValidationFailed,
)
from .imports import DatasetError, ImportFailed, ImportReport, LoggedEpisode
from .model_server import ModelServer, serve_model
from .models import (
    Candidate,
    CandidateScore,
    Experiment,
    HeldOutTrust,
    Hyperparameters,
    Model,
    NoiseSummary,
    Plan,
    PlannedTrajectory,
    Precondition,
    Proposal,
    Run,
    Source,
    Space,
    StoredTransition,
    Trajectory,
    TrajectoryCreated,
    Transition,
    transitions_from_states,
)
from .robot import Episode, Learner, Progress

__all__ = [
    "ApiError",
    "BadRequest",
    "Cancelled",
    "Candidate",
    "CandidateScore",
    "Client",
    "Conflict",
    "DatasetError",
    "DeadlineExceeded",
    "Episode",
    "Experiment",
    "ExperimentMismatch",
    "Forbidden",
    "HeldOutTrust",
    "Hyperparameters",
    "ImportFailed",
    "ImportReport",
    "InternalError",
    "Learner",
    "LimitReached",
    "LoggedEpisode",
    "MethodNotAllowed",
    "Model",
    "ModelServer",
    "ModelTimeout",
    "ModelUnavailable",
    "NoPlan",
    "NoiseSummary",
    "NotFound",
    "Overloaded",
    "PayloadTooLarge",
    "Plan",
    "PlannedTrajectory",
    "PrecondError",
    "Precondition",
    "Progress",
    "Proposal",
    "Run",
    "Source",
    "Space",
    "StoredTransition",
    "Trajectory",
    "TrajectoryCreated",
    "Transition",
    "TransportError",
    "Unauthorized",
    "Unavailable",
    "ValidationFailed",
    "serve_model",
    "transitions_from_states",
]

__version__ = "0.1.0"
