"""Typed bodies of the precond API, mirroring the schemas of ``api/openapi.yaml``.

Responses are read into frozen dataclasses whose vectors are numpy arrays (``float64``; a
trajectory's ``states`` is ``(T + 1, n)``, its ``actions`` ``(T, m)``). Unknown fields are
ignored, so the client keeps working when the server adds one; the larger answers keep the JSON
they were read from in ``raw``.

Every dataclass names the schema it mirrors in ``SCHEMA`` (a tuple when one class reads several
schemas); its fields are that schema's properties, except those marked :data:`CLIENT_ONLY`.
``tests/test_wire.py`` checks both against ``api/openapi.yaml``.
"""

from __future__ import annotations

import types
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import (
    Annotated,
    Any,
    ClassVar,
    TypeVar,
    Union,
    cast,
    get_args,
    get_origin,
    get_type_hints,
)

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
"""A float64 numpy array."""

CLIENT_ONLY: Mapping[str, Any] = {"client_only": True}
"""``field(metadata=CLIENT_ONLY)``: a field the client adds that is no property of the schema
(e.g. ``raw``, or what a header said)."""


def vec(x: ArrayLike) -> Array:
    """``x`` as a 1-D float64 array."""
    return np.asarray(x, dtype=np.float64).reshape(-1)


def mat(x: ArrayLike, cols: int | None = None) -> Array:
    """``x`` as a 2-D float64 array (an empty list becomes ``(0, cols or 0)``)."""
    a = np.asarray(x, dtype=np.float64)
    if a.size == 0:
        return np.zeros((0, cols or 0))
    return a.reshape(len(a), -1) if a.ndim != 2 else a


Matrix = Annotated[Array, mat]
"""A 2-D float64 array; a :class:`Wire` field of this type is read with :func:`mat`."""


def as_list(x: ArrayLike) -> list[float]:
    """A vector as a JSON list of finite floats; raises ``ValueError`` on NaN or infinity."""
    v = vec(x)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"vector {v.tolist()} has a non-finite entry")
    return [float(e) for e in v]


def as_lists(x: ArrayLike) -> list[list[float]]:
    """Rows of a 2-D array as JSON lists of finite floats."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"expected a 2-D array, got shape {a.shape}")
    return [as_list(row) for row in a]


_W = TypeVar("_W", bound="Wire")


class Wire:
    """A body the client reads: a frozen dataclass whose ``from_json`` reads each field from the
    property of its name, by the field's type.

    ``int``, ``float``, ``str`` and ``bool`` are read by that constructor, :data:`Array` by
    :func:`vec`, ``Annotated[T, read]`` (e.g. :data:`Matrix`) by ``read``, ``list[T]`` item by
    item, ``dict[str, Any]`` as a copy and another :class:`Wire` by its ``from_json``. A field
    ``T | None`` reads an absent or ``null`` property as ``None``; any other property must be
    there. Fields marked :data:`CLIENT_ONLY` are not read: a field ``raw`` keeps the JSON it was
    read from, others are given to ``from_json`` by keyword (e.g. ``replayed``).
    """

    @classmethod
    def from_json(cls: type[_W], d: Mapping[str, Any], **given: Any) -> _W:
        """Reads the JSON form; ``given`` sets fields by keyword instead."""
        readers, keeps_raw = _readers(cls)
        read = {name: reader(d) for name, reader in readers.items() if name not in given}
        if keeps_raw and "raw" not in given:
            read["raw"] = d
        return cls(**read, **given)


_Readers = dict[str, Callable[[Mapping[str, Any]], Any]]
_READERS: dict[type, tuple[_Readers, bool]] = {}


def _readers(cls: type) -> tuple[_Readers, bool]:
    """How each property of ``cls`` (see :class:`Wire`) is read from a JSON object, and whether
    it keeps that object in ``raw``."""
    if cls not in _READERS:
        hints = get_type_hints(cls, include_extras=True)
        wire = [f for f in fields(cls) if not f.metadata.get("client_only")]
        keeps_raw = any(f.name == "raw" for f in fields(cls) if f.metadata.get("client_only"))
        _READERS[cls] = ({f.name: _property(f.name, hints[f.name]) for f in wire}, keeps_raw)
    return _READERS[cls]


def _property(name: str, tp: Any) -> Callable[[Mapping[str, Any]], Any]:
    if get_origin(tp) in (Union, types.UnionType) and type(None) in get_args(tp):
        (inner,) = [a for a in get_args(tp) if a is not type(None)]
        read = _value(inner)
        return lambda d: None if d.get(name) is None else read(d[name])
    read = _value(tp)
    return lambda d: read(d[name])


def _value(tp: Any) -> Callable[[Any], Any]:
    """How a JSON value becomes a value of type ``tp``."""
    if get_origin(tp) is Annotated:
        reader: Callable[[Any], Any] = get_args(tp)[1]
        return reader
    if tp in (int, float, str, bool):
        return cast(Callable[[Any], Any], tp)
    if tp == Array:
        return vec
    if get_origin(tp) is list:
        item = _value(get_args(tp)[0])
        return lambda v: [item(x) for x in v]
    if get_origin(tp) is dict:
        return dict
    if isinstance(tp, type) and issubclass(tp, Wire):
        return tp.from_json
    raise TypeError(f"no reader for a field of type {tp}")


@dataclass(frozen=True)
class Space(Wire):
    """A state or action space (schema ``Space``)."""

    SCHEMA: ClassVar[str] = "Space"

    names: list[str]
    low: Array
    high: Array
    values: Matrix | None = None
    """The allowed actions of a discrete space, one per row."""

    @property
    def dim(self) -> int:
        """Number of components."""
        return len(self.names)


@dataclass(frozen=True)
class Experiment(Wire):
    """An experiment with its resolved settings, spaces and progress (schema ``Experiment``)."""

    SCHEMA: ClassVar[str] = "Experiment"

    id: int
    name: str
    domain: dict[str, Any]
    d_max: float
    seed: int
    mde: dict[str, Any]
    learning: dict[str, Any]
    state_space: Space
    action_space: Space
    feature_names: list[str]
    created_at: str
    n_trajectories: int
    n_transitions: int
    iteration: int
    model_version: int
    n_refused: int
    """Proposal requests answered ``no_plan`` (each a ``refused`` run)."""
    last_activity: str
    """The latest of its creation, its last posted trajectory, its last proposal and its last
    refused proposal request."""
    raw: dict[str, Any] = field(repr=False, compare=False, metadata=CLIENT_ONLY)
    models: list[dict[str, Any]] | None = None
    """Its further models of the robot (``name``, ``cost``, ``model``), each labelling every
    posted transition; ``None`` when it has none."""


@dataclass(frozen=True)
class Transition:
    """One executed transition to post (schema ``TransitionRequest``).

    ``s_pred`` is the client's own prediction ``f̂(s, a)``: required when the experiment's model
    is the client's (``model.kind`` ``client``), refused otherwise. ``predictions`` are the
    predictions of the experiment's further models that are the client's own, by name (one
    left out leaves that model's label missing).
    """

    SCHEMA: ClassVar[str] = "TransitionRequest"

    s: ArrayLike
    a: ArrayLike
    s_next: ArrayLike
    s_pred: ArrayLike | None = None
    predictions: Mapping[str, ArrayLike] | None = None

    def to_json(self) -> dict[str, Any]:
        """The JSON form."""
        d: dict[str, Any] = {
            "s": as_list(self.s),
            "a": as_list(self.a),
            "s_next": as_list(self.s_next),
        }
        if self.s_pred is not None:
            d["s_pred"] = as_list(self.s_pred)
        if self.predictions is not None:
            d["predictions"] = {name: as_list(p) for name, p in self.predictions.items()}
        return d


def transitions_from_states(
    states: ArrayLike, actions: ArrayLike, predicted: ArrayLike | None = None
) -> list[Transition]:
    """The transitions of a trajectory given the ``k + 1`` observed states (the start first)
    and the ``k`` actions executed (and, for a client-side model, the ``k`` predictions)."""
    s = mat(states)
    a = mat(actions)
    if len(s) != len(a) + 1:
        raise ValueError(f"{len(s)} observed states for {len(a)} actions: need one more state")
    p = mat(predicted) if predicted is not None else None
    if p is not None and len(p) != len(a):
        raise ValueError(f"{len(p)} predictions for {len(a)} actions")
    return [
        Transition(s[i], a[i], s[i + 1], p[i] if p is not None else None) for i in range(len(a))
    ]


@dataclass(frozen=True)
class ModelLabel(Wire):
    """A further model's label of a transition (schema ``ModelLabel``): its prediction and
    deviation, or — when the model could not answer — ``None`` for both and ``missing``, why."""

    SCHEMA: ClassVar[str] = "ModelLabel"

    model: str
    s_pred: Array | None
    deviation: float | None
    missing: str | None


@dataclass(frozen=True)
class ModelLabelStats(Wire):
    """One model's labels of an experiment's executed transitions, summed up (schema
    ``ModelLabelStats``)."""

    SCHEMA: ClassVar[str] = "ModelLabelStats"

    model: str
    """The model's name; ``"domain"`` for the domain's own."""
    cost: float
    kind: str
    n_labelled: int
    n_missing: int
    mean_deviation: float | None
    max_deviation: float | None
    share_within_d_max: float | None
    """How often the model was right where the robot went (``None`` without labels)."""


@dataclass(frozen=True)
class ModelLabels(Wire):
    """Each of an experiment's models of its robot with what its labels say (schema
    ``ModelLabels``): the domain's own first, then the further models in their order."""

    SCHEMA: ClassVar[str] = "ModelLabels"

    experiment_id: int
    d_max: float
    items: list[ModelLabelStats]

    def of(self, model: str) -> ModelLabelStats:
        """The summary of ``model`` (``KeyError`` when the experiment has none by that name)."""
        for m in self.items:
            if m.model == model:
                return m
        raise KeyError(f"the experiment has no model named {model!r}")


@dataclass(frozen=True)
class StoredTransition(Wire):
    """A stored, labelled transition (schema ``Transition``)."""

    SCHEMA: ClassVar[str] = "Transition"

    id: int
    trajectory_id: int
    step: int
    s: Array
    a: Array
    s_next: Array
    s_pred: Array
    deviation: float
    labels: list[ModelLabel] | None = None
    """The experiment's further models' labels, in the order of its ``models``; ``None`` when
    it has none."""

    def deviation_of(self, model: str) -> float | None:
        """The deviation ``model`` labelled this transition with (``"domain"``: the domain's own
        model's); ``None`` when its label is missing. ``KeyError`` for a model the experiment
        does not have."""
        if model == "domain":
            return self.deviation
        for label in self.labels or []:
            if label.model == model:
                return label.deviation
        raise KeyError(f"the experiment has no model named {model!r}")


@dataclass(frozen=True)
class Source(Wire):
    """Where a posted trajectory comes from (schema ``TrajectorySource``): a logged dataset or
    file, a simulated environment. Stored with the trajectory and shown with it."""

    SCHEMA: ClassVar[tuple[str, ...]] = ("TrajectorySource", "ResolvedTrajectorySource")

    dataset: str
    """The dataset, file or environment (1 to 1000 characters)."""
    episode: int | None = None
    """The episode of the dataset."""
    first_step: int | None = None
    """The step of the episode that was the trajectory's first transition (an episode longer
    than one post allows is posted as several trajectories)."""
    label: str | None = None
    """A free-form label (at most 1000 characters)."""

    def to_json(self) -> dict[str, Any]:
        """The JSON form (absent fields left out)."""
        d: dict[str, Any] = {"dataset": self.dataset}
        if self.episode is not None:
            d["episode"] = int(self.episode)
        if self.first_step is not None:
            d["first_step"] = int(self.first_step)
        if self.label is not None:
            d["label"] = self.label
        return d


@dataclass(frozen=True)
class ImportReport(Wire):
    """What an import did (schema ``ImportReport``): the answer of ``POST …/imports``, read by
    :meth:`~precond_client.Client.import_file` and the other ``import_*`` calls."""

    SCHEMA: ClassVar[str] = "ImportReport"

    episodes: int
    """Episodes read with at least one transition."""
    trajectories: int
    """Trajectories stored or found stored (an episode split in parts counts each)."""
    created: int
    """Of those, stored by this import."""
    replayed: int
    """Of those, already stored by an earlier one (nothing stored)."""
    transitions: int
    """Transitions in those trajectories."""
    split_episodes: int
    """Episodes stored as several trajectories."""
    skipped_episodes: int
    """Episodes without a transition (a single frame)."""
    trajectory_ids: list[int]
    """The trajectories stored or found stored, in the data's order: the first 100 000 of
    them (``trajectories`` counts all)."""


@dataclass(frozen=True)
class ImportStop(Wire):
    """Where an import stopped part-way and what it stored before (schema ``ImportStop``, an
    import error's ``details["import"]``)."""

    SCHEMA: ClassVar[str] = "ImportStop"

    episode: int | None
    """The episode of the refused trajectory; ``None`` when the data could not be read
    further."""
    first_step: int | None
    """The step of that episode the refused trajectory started at."""
    stored_before: ImportReport
    """What the import stored before it stopped (importing again skips it)."""


@dataclass(frozen=True)
class TrajectoryCreated(Wire):
    """The answer to a posted trajectory (schema ``TrajectoryCreated``)."""

    SCHEMA: ClassVar[str] = "TrajectoryCreated"

    id: int
    experiment_id: int
    proposal_id: int | None
    partial: bool
    deviating: bool
    """Whether it departs from its proposal: other actions, longer, or another start (a prefix
    does not); ``False`` without a proposal."""
    source: Source | None
    """Where it comes from, as posted."""
    n_transitions: int
    deviations: Array
    iteration: int
    model_version: int
    n_trajectories: int
    created_at: str
    replayed: bool = field(default=False, metadata=CLIENT_ONLY)
    """Whether the server replayed the answer to an earlier request with the same
    ``Idempotency-Key`` (nothing new was stored)."""


@dataclass(frozen=True)
class Trajectory(Wire):
    """A stored trajectory with its labelled transitions in step order (schema
    ``Trajectory``)."""

    SCHEMA: ClassVar[str] = "Trajectory"

    id: int
    experiment_id: int
    proposal_id: int | None
    partial: bool
    deviating: bool
    """Whether it departs from its proposal (other actions, longer, or another start)."""
    source: Source | None
    """Where it comes from, as posted."""
    created_at: str
    n_transitions: int
    transitions: list[StoredTransition]

    @property
    def states(self) -> Array:
        """The states ``(T + 1, n)``: each transition's ``s``, then the last ``s_next``."""
        return np.vstack([[t.s for t in self.transitions], self.transitions[-1].s_next])

    @property
    def actions(self) -> Array:
        """The actions ``(T, m)``."""
        return np.vstack([t.a for t in self.transitions])

    @property
    def deviations(self) -> Array:
        """The deviation labels ``(T,)``."""
        return np.array([t.deviation for t in self.transitions], dtype=np.float64)


@dataclass(frozen=True)
class Run(Wire):
    """A proposal with the trajectory that executed it, a trajectory posted without a
    proposal, or a refused proposal request (schema ``Run``)."""

    SCHEMA: ClassVar[str] = "Run"

    proposal_id: int | None
    trajectory_id: int | None
    refusal_id: int | None
    status: str
    """``open``, ``executed``, ``abandoned``, ``expired``, ``partial``, ``unsolicited`` or
    ``refused``."""
    client_id: str | None
    iteration: int | None
    beta: float | None
    betas_tried: Array | None
    """Every β a refused request tried, in order."""
    refusal_reason: str | None
    """Why a refused request was refused: ``no_plan`` or ``deadline_exceeded``."""
    extensions: int | None
    model_version: int | None
    created_at: str
    length: int
    partial: bool
    deviating: bool
    source: Source | None
    max_deviation: float | None
    excluded_by: int | None
    """The exclusion (the oldest in effect) keeping the posted trajectory out of the model."""


@dataclass(frozen=True)
class Exclusion(Wire):
    """Trajectories left out of the experiment's model (schema ``Exclusion``): one trajectory
    or those stored in a time range, why, who made it (their token's fingerprint) and when,
    whether it was restored, and whether the model answering agrees with it yet."""

    SCHEMA: ClassVar[str] = "Exclusion"

    id: int
    experiment_id: int
    status: str
    """``in_effect`` or ``restored``."""
    trajectory_id: int | None
    since: str | None
    """The first ingest time of a time range (``None`` for one trajectory)."""
    until: str | None
    """The end of a time range, exclusive."""
    reason: str
    trajectory_ids: list[int]
    n_transitions: int
    created_at: str
    created_by: str | None
    """The first 12 hex digits of the SHA-256 of the caller's token (``None`` without tokens)."""
    restored_at: str | None
    restored_by: str | None
    applied: bool
    """Whether the answering version was fitted under the exclusion as it stands: ``False``
    until the refit its making (or restoring) requested is swapped in."""


@dataclass(frozen=True)
class Candidate:
    """A trajectory the client planned itself (schema ``CandidateTrajectory``): its predicted
    states, starting with the start state, and the actions between them."""

    SCHEMA: ClassVar[str] = "CandidateTrajectory"

    states: ArrayLike
    actions: ArrayLike

    def to_json(self) -> dict[str, Any]:
        """The JSON form."""
        return {"states": as_lists(mat(self.states)), "actions": as_lists(mat(self.actions))}


@dataclass(frozen=True)
class PlannedTrajectory(Wire):
    """A planned trajectory with the MDE's answer per step (schemas ``PlannedTrajectory`` and
    ``ProposedTrajectory``: a proposal's trajectory also has ``alpha_step`` and ``alpha``)."""

    SCHEMA: ClassVar[tuple[str, ...]] = ("PlannedTrajectory", "ProposedTrajectory")

    states: Matrix
    """Predicted states ``(T + 1, n)``, the start first."""
    actions: Matrix
    """Actions ``(T, m)``."""
    mu: Array
    sigma: Array
    alpha_step: Array | None = None
    alpha: float | None = None


@dataclass(frozen=True)
class CandidateScore(Wire):
    """A scored candidate of a proposal or plan (schema ``CandidateScore``); the verdict
    fields are set only for the client's own candidates."""

    SCHEMA: ClassVar[str] = "CandidateScore"

    alpha: float
    length: int
    inside: bool | None = None
    first_outside: int | None = None
    reaches_goal: bool | None = None
    mu: Array | None = None
    sigma: Array | None = None


@dataclass(frozen=True)
class Proposal(Wire):
    """A proposal: the trajectory to execute next, leased to a client (schema ``Proposal``)."""

    SCHEMA: ClassVar[str] = "Proposal"

    id: int
    status: str
    """``open``, ``executed``, ``abandoned`` or ``expired``."""
    deviating: bool
    """Whether the trajectory posted for it departs from it (other actions, longer, or another
    start; a prefix does not); ``False`` until executed."""
    client_id: str | None
    iteration: int
    beta: float
    strategy: str
    model_version: int
    start: Array
    goal: Array
    created_at: str
    expires_at: str
    trajectory: PlannedTrajectory
    candidates: list[CandidateScore]
    chosen_index: int
    extensions: int
    raw: dict[str, Any] = field(repr=False, compare=False, metadata=CLIENT_ONLY)
    relaxed_from_beta: float | None = None
    """The iteration's ``β_j`` when no trajectory reached the goal inside the precondition at
    it and the proposal was planned at the lower :attr:`beta` (``learning.relax_beta``)."""
    valued_by: str | None = None
    """The acquisition the candidates were compared by (the service's and a client's alike):
    the experiment's ``learning.acquisition``, or ``lcb`` where a value-based one valued no
    candidate above 0 (``None`` for proposals stored before it was recorded)."""
    models: list[str] | None = None
    """The models the candidates stepped with, cheapest first, when the request named more than
    the domain's model; a continuation steps with the same."""
    step_models: list[str] | None = None
    """The model each step of the trajectory relied on, with :attr:`models`."""

    @property
    def actions(self) -> Array:
        """The actions to execute from :attr:`start`, ``(T, m)``."""
        return self.trajectory.actions

    @property
    def states(self) -> Array:
        """The model's predicted states, ``(T + 1, n)``."""
        return self.trajectory.states


@dataclass(frozen=True)
class Continued:
    """The answer to continuing a proposal (schema ``ContinueResponse``): the executed prefix,
    stored as a partial trajectory, and the proposal planned from where the robot now is."""

    SCHEMA: ClassVar[str] = "ContinueResponse"

    trajectory: TrajectoryCreated
    proposal: Proposal

    @classmethod
    def from_json(cls, d: Mapping[str, Any], replayed: bool = False) -> Continued:
        """Reads the JSON form."""
        return cls(
            trajectory=TrajectoryCreated.from_json(d["trajectory"], replayed=replayed),
            proposal=Proposal.from_json(dict(d["proposal"])),
        )


@dataclass(frozen=True)
class RejectionCounts(Wire):
    """Why a search's extensions added nothing to its tree (schema ``RejectionCounts``)."""

    SCHEMA: ClassVar[str] = "RejectionCounts"

    constraints: int
    """No steered action was allowed by the domain and new: the search could not reach on."""
    precondition: int
    """Some were, but none was trusted."""


@dataclass(frozen=True)
class ModelCalls(Wire):
    """What a plan's search spent on one model (schema ``ModelCalls``)."""

    SCHEMA: ClassVar[str] = "ModelCalls"

    model: str
    """The model's name; ``"domain"`` for the domain's own."""
    calls: int
    cost: float
    """What one call costs, in calls of the domain's own model."""


@dataclass(frozen=True)
class Plan(Wire):
    """A test-time plan (schema ``Plan``)."""

    SCHEMA: ClassVar[str] = "Plan"

    found: bool
    extensions: int
    rejections: RejectionCounts
    """Why extensions added nothing: many ``precondition`` rejections and no plan means the model
    is not trusted between the start and the goal yet."""
    beta: float
    d_max: float
    model_version: int
    trajectory: PlannedTrajectory | None
    candidates: list[CandidateScore] | None = None
    step_models: list[str] | None = None
    """Which model each step relied on (predicted by it, trusted by its precondition), when the
    experiment has several models."""
    model_calls: list[ModelCalls] | None = None
    """What the search spent on each model it could step with, when the experiment has several
    models."""

    def cost(self) -> float | None:
        """The search's model calls weighted by their cost, in calls of the domain's own model
        (``None`` for a single-model experiment, whose plans do not count them)."""
        if self.model_calls is None:
            return None
        return sum(m.calls * m.cost for m in self.model_calls)


@dataclass(frozen=True)
class Hyperparameters(Wire):
    """A GP's hyperparameters in natural units (schema ``Hyperparameters``)."""

    SCHEMA: ClassVar[str] = "Hyperparameters"

    length_scales: Array
    signal_variance: float
    noise_variance: float
    prior_mean: float
    kernel: str
    """The Matérn kernel: ``matern12``, ``matern32`` or ``matern52``."""

    @classmethod
    def from_json(cls, d: Mapping[str, Any], **given: Any) -> Hyperparameters:
        """Reads the JSON form (``matern52`` when a server too old to say omits the kernel)."""
        given.setdefault("kernel", str(d.get("kernel", "matern52")))
        return super().from_json(d, **given)


@dataclass(frozen=True)
class NoiseSummary(Wire):
    """A heteroscedastic model's noise, summarised (schema ``NoiseSummary``)."""

    SCHEMA: ClassVar[str] = "NoiseSummary"

    min_noise_variance: float
    mean_noise_variance: float
    max_noise_variance: float
    noise_model: Hyperparameters
    """The GP on log noise variances."""
    rounds: int
    homoscedastic_lml: float
    """Log marginal likelihood of the initial homoscedastic fit."""


@dataclass(frozen=True)
class HeldOutTrust(Wire):
    """How a candidate label cap's model judged its own training transitions, each distinct
    state-action held out in turn (schema ``HeldOutTrust``)."""

    SCHEMA: ClassVar[str] = "HeldOutTrust"

    label_cap: float
    """The candidate cap (times ``d_max``; 0 = raw labels)."""
    safe: int
    unsafe_transitions: int
    trusted_safe: int
    trusted_unsafe: int
    """Unsafe transitions inside the held-out precondition (false trust)."""
    log_score: float
    """Mean log probability given to the side of ``d_max`` each deviation fell on (0 is
    perfect); ``"auto"`` keeps the highest."""
    held_out_groups: int


@dataclass(frozen=True)
class KernelTrial(Wire):
    """One candidate kernel's fit when the kernel is chosen from the data (schema
    ``KernelTrial``)."""

    SCHEMA: ClassVar[str] = "KernelTrial"

    kernel: str
    """``matern12``, ``matern32`` or ``matern52``."""
    log_marginal_likelihood: float
    held_out_log_score: float | None = None
    """The mean held-out log probability of the training state-actions' side of ``d_max``
    (``None`` when not computed and for fits made before it existed)."""


@dataclass(frozen=True)
class BetaChoice(Wire):
    """The test β a fitted version certifies on its own training transitions, each executed
    trajectory held out whole with every copy of its state-actions: the smallest β (grid of
    0.1, at most ``learning.test_beta``) at which at most 2 % of the unsafe ones are trusted
    (schema ``BetaChoice``)."""

    SCHEMA: ClassVar[str] = "BetaChoice"

    beta: float
    safe: int
    unsafe_transitions: int
    trusted_safe: int
    """Safe training transitions trusted at :attr:`beta`, held out."""
    trusted_unsafe: int
    """Unsafe training transitions trusted at :attr:`beta`, held out (false trust)."""


@dataclass(frozen=True)
class FitPhase(Wire):
    """One phase of a fit and its wall time (schema ``FitPhase``)."""

    SCHEMA: ClassVar[str] = "FitPhase"

    phase: str
    """What it did, e.g. ``kernels: 3 fits``, ``warm fit``, ``certified β``."""
    seconds: float


@dataclass(frozen=True)
class SelectionRecord(Wire):
    """How a version's kernel and label cap were chosen — anew, or kept from an earlier version
    by a warm refit — and what its fit spent its time on (schema ``SelectionRecord``)."""

    SCHEMA: ClassVar[str] = "SelectionRecord"

    selected_at_version: int
    """The version whose fit made the choice (this one's own when it chose)."""
    selected_n_train: int
    reason: str
    phases: list[FitPhase]


@dataclass(frozen=True)
class FitRefusal(Wire):
    """A fit the server did not attempt because its estimated peak memory or time exceeded the
    server's budget; the version before it kept answering (schema ``FitRefusal``)."""

    SCHEMA: ClassVar[str] = "FitRefusal"

    n_train: int
    """Transitions the fit would have been trained on."""
    n_trajectories: int
    estimator: str
    """``exact`` or ``sparse``."""
    needed_bytes: float
    budget_bytes: float
    reason: str
    refused_at: str
    needed_seconds: float | None
    """For a refusal over time: its estimated seconds; ``None`` for one over memory."""
    budget_seconds: float | None
    """For a refusal over time: the server's ``--max-fit-seconds``."""


@dataclass(frozen=True)
class Model(Wire):
    """The MDE version answering queries (schema ``Model``)."""

    SCHEMA: ClassVar[str] = "Model"

    experiment_id: int
    version: int
    source: str
    """``prior`` (version 0) or ``fit``."""
    n_train: int
    noise: str | None
    feature_names: list[str]
    hyperparameters: Hyperparameters | None
    """``None`` for local experts, each of which has its own (see the export)."""
    noise_model: NoiseSummary | None
    """The heteroscedastic noise model; ``None`` for the prior and homoscedastic fits."""
    log_marginal_likelihood: float | None
    fit_seconds: float | None
    fitted_at: str | None
    n_trajectories: int
    label_cap: float | None
    """The label cap the fit clipped deviations at (times ``d_max``; 0 = raw labels); ``None``
    for the prior."""
    label_cap_trials: list[HeldOutTrust]
    """Each candidate cap's held-out judgement (empty for the prior)."""
    estimator: str | None
    """``exact``, ``sparse`` or ``local_experts`` (``None`` for the prior)."""
    online_trajectories: int
    """Trajectories taken in by online updates since the fit (sparse GP)."""
    last_fit_refusal: FitRefusal | None
    """The latest fit refused since this version for the memory budget."""
    kernel_trials: list[KernelTrial]
    """With ``mde.kernel`` ``auto``, each kernel's fit; the highest log marginal likelihood won
    unless another's held-out score was clearly better."""
    beta_choice: BetaChoice | None
    """The test β this version certifies (``None`` for the prior and where not computed)."""
    test_beta: float
    """The β test plans use with this version (``beta_choice.beta`` with
    ``learning.calibrate_test_beta``, else ``learning.test_beta``)."""
    selection: SelectionRecord | None
    """How this version's kernel and label cap were chosen, anew or kept by a warm refit, and
    what the fit spent its time on (``None`` for the prior and older versions)."""
    exclusions: list[int]
    """The exclusions in effect when this version was fitted (see :meth:`Client.exclusions`)."""
    raw: dict[str, Any] = field(repr=False, compare=False, metadata=CLIENT_ONLY)


@dataclass(frozen=True)
class Precondition:
    """The answer to a precondition query, one entry per point in every array
    (schema ``PreconditionAnswer``, its ``results`` (schema ``PreconditionResult``) read
    column by column into ``mu``, ``sigma``, ``upper`` and ``inside``)."""

    SCHEMA: ClassVar[str] = "PreconditionAnswer"
    COLUMNS: ClassVar[Mapping[str, str]] = {"results": "PreconditionResult"}
    """Array properties whose items' properties become one array field each."""

    model_version: int
    source: str
    beta: float
    d_max: float
    mu: Array
    """Predicted mean deviation ``μ`` per point."""
    sigma: Array
    """Predicted standard deviation ``σ`` per point."""
    upper: Array
    """``μ + βσ`` per point."""
    inside: NDArray[np.bool_]
    """``upper < d_max`` per point."""
    model: str | None = None
    """The further model whose precondition this is; ``None`` for the domain's own model's."""

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Precondition:
        """Reads the JSON form."""
        rs: Sequence[Mapping[str, Any]] = d["results"]
        return cls(
            model_version=int(d["model_version"]),
            source=str(d["source"]),
            beta=float(d["beta"]),
            d_max=float(d["d_max"]),
            mu=np.array([r["mu"] for r in rs], dtype=np.float64),
            sigma=np.array([r["sigma"] for r in rs], dtype=np.float64),
            upper=np.array([r["upper"] for r in rs], dtype=np.float64),
            inside=np.array([bool(r["inside"]) for r in rs], dtype=np.bool_),
            model=None if d.get("model") is None else str(d["model"]),
        )

    @staticmethod
    def concat(parts: Sequence[Precondition]) -> Precondition:
        """The answers of consecutive chunks of one query, joined."""
        first = parts[0]
        return Precondition(
            model_version=first.model_version,
            source=first.source,
            beta=first.beta,
            d_max=first.d_max,
            mu=np.concatenate([p.mu for p in parts]),
            sigma=np.concatenate([p.sigma for p in parts]),
            upper=np.concatenate([p.upper for p in parts]),
            inside=np.concatenate([p.inside for p in parts]),
            model=first.model,
        )
