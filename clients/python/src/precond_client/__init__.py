"""precond-client: drive a precond server's active learning of model preconditions from Python.

- :class:`Client` — experiments, proposals, trajectories (idempotent, retried), the model,
  precondition queries and plans, with numpy arrays in and out.
- :meth:`Client.learn` — the robot's loop: propose, execute, post, surviving restarts and a
  busy server; each :class:`Episode` can drive the robot itself, open loop under a
  :class:`Monitor` (:meth:`Episode.execute`) or closed loop (:meth:`Episode.run_closed_loop`).
- :meth:`Client.execute_plan` — a test-time plan executed closed loop; :meth:`Client.monitor`
  — any plan's execution stopped where it deviates beyond ``d_max``
  (:mod:`precond_client.execution`).
- :func:`serve_model` — serve a numpy dynamics model as a custom domain's ``remote`` model.
- :func:`spawn_server` — start a local precond server binary on a free port (examples, scripts).
- :meth:`Client.import_file`, :meth:`Client.import_lerobot`, :meth:`Client.import_minari` —
  logged data (CSV, Parquet, LeRobot v3, Minari) into an experiment, idempotently
  (:mod:`precond_client.imports`).
- :meth:`Client.export_model` — a fitted model as an :class:`ExportedModel` that evaluates the
  precondition with numpy alone, inside a control loop (:mod:`precond_client.export`).
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
    DeviationExceeded,
    ExperimentMismatch,
    Forbidden,
    InternalError,
    LimitReached,
    MethodNotAllowed,
    ModelBusy,
    ModelNotAllowed,
    ModelTimeout,
    ModelUnavailable,
    NoPlan,
    NotFound,
    Overloaded,
    PayloadTooLarge,
    PrecondError,
    RequestTimeout,
    TransportError,
    Unauthorized,
    Unavailable,
    UnsupportedMediaType,
    ValidationFailed,
)
from .execution import Execution, Metric, Monitor
from .export import ExportedModel
from .imports import DatasetError, ImportFailed, LoggedEpisode
from .model_server import ModelServer, serve_model
from .models import (
    BetaChoice,
    Candidate,
    CandidateScore,
    Continued,
    Exclusion,
    Experiment,
    FitRefusal,
    HeldOutTrust,
    Hyperparameters,
    ImportReport,
    ImportStop,
    KernelTrial,
    Model,
    ModelCalls,
    ModelLabel,
    ModelLabels,
    ModelLabelStats,
    NoiseSummary,
    Plan,
    PlannedTrajectory,
    Precondition,
    Proposal,
    RejectionCounts,
    Run,
    Source,
    Space,
    StoredTransition,
    Trajectory,
    TrajectoryCreated,
    Transition,
    transitions_from_states,
)
from .robot import Episode, Learner, Progress, Skipped
from .spawn import spawn_server

__all__ = [
    "ApiError",
    "BadRequest",
    "BetaChoice",
    "Cancelled",
    "Candidate",
    "CandidateScore",
    "Client",
    "Conflict",
    "Continued",
    "DatasetError",
    "DeadlineExceeded",
    "DeviationExceeded",
    "Episode",
    "Exclusion",
    "Execution",
    "Experiment",
    "ExperimentMismatch",
    "ExportedModel",
    "FitRefusal",
    "Forbidden",
    "HeldOutTrust",
    "Hyperparameters",
    "ImportFailed",
    "ImportReport",
    "ImportStop",
    "InternalError",
    "KernelTrial",
    "Learner",
    "LimitReached",
    "LoggedEpisode",
    "MethodNotAllowed",
    "Metric",
    "Model",
    "ModelBusy",
    "ModelCalls",
    "ModelLabel",
    "ModelLabelStats",
    "ModelLabels",
    "ModelNotAllowed",
    "ModelServer",
    "ModelTimeout",
    "ModelUnavailable",
    "Monitor",
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
    "RejectionCounts",
    "RequestTimeout",
    "Run",
    "Skipped",
    "Source",
    "Space",
    "StoredTransition",
    "Trajectory",
    "TrajectoryCreated",
    "Transition",
    "TransportError",
    "Unauthorized",
    "Unavailable",
    "UnsupportedMediaType",
    "ValidationFailed",
    "serve_model",
    "spawn_server",
    "transitions_from_states",
]

__version__ = "0.1.0"
