"""What the robot's loop (:mod:`precond_client.robot`) and the importers
(:mod:`precond_client.imports`) need of a client, as protocols.

They take any object with these calls; a :class:`~precond_client.Client` is one (mypy checks it
where the client hands itself over). So those modules do not import the client module, which
imports them for :meth:`~precond_client.Client.learn` and the ``import_*`` methods: the imports
run one way.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

from numpy.typing import ArrayLike

from .models import (
    Candidate,
    Continued,
    Experiment,
    ImportReport,
    Model,
    Proposal,
    Source,
    TrajectoryCreated,
    Transition,
)


class TrajectoryPoster(Protocol):
    """Posts executed or logged trajectories (:meth:`~precond_client.Client.post_trajectory`)."""

    def post_trajectory(
        self,
        transitions: Iterable[Transition | Mapping[str, Any]],
        proposal_id: int | None = None,
        partial: bool = False,
        idempotency_key: str | None = None,
        source: Source | Mapping[str, Any] | None = None,
    ) -> TrajectoryCreated: ...


class FileImporter(Protocol):
    """Imports a file of logged transitions on the server
    (:meth:`~precond_client.Client.import_file`), into the experiment it describes."""

    def get_experiment(self, experiment_id: int | None = None) -> Experiment: ...

    def import_file(
        self,
        path: str | Path,
        *,
        format: str | None = None,
        label: str | None = None,
        dataset_name: str | None = None,
        dataset_id: str | None = None,
        max_transitions: int | None = None,
        progress: bool | None = None,
    ) -> ImportReport: ...


class LearningClient(TrajectoryPoster, Protocol):
    """The calls of the robot's loop: proposals, leases, continuations, the model it waits
    for."""

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
    ) -> Proposal: ...

    def continue_proposal(
        self,
        proposal_id: int,
        transitions: Iterable[Transition | Mapping[str, Any]],
        candidates: Sequence[Candidate] | None = None,
        idempotency_key: str | None = None,
        *,
        deadline_retries: int | None = None,
    ) -> Continued: ...

    def get_proposal(self, proposal_id: int) -> Proposal: ...

    def abandon(self, proposal_id: int) -> Proposal: ...

    def get_experiment(self, experiment_id: int | None = None) -> Experiment: ...

    def wait_for_model(self, n_trajectories: int, timeout: float = 120.0) -> Model: ...
