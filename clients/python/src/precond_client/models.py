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

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

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


@dataclass(frozen=True)
class Space:
    """A state or action space (schema ``Space``)."""

    SCHEMA: ClassVar[str] = "Space"

    names: list[str]
    low: Array
    high: Array
    values: Array | None = None
    """The allowed actions of a discrete space, one per row."""

    @property
    def dim(self) -> int:
        """Number of components."""
        return len(self.names)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Space:
        """Reads the JSON form."""
        values = d.get("values")
        return cls(
            names=list(d["names"]),
            low=vec(d["low"]),
            high=vec(d["high"]),
            values=mat(values) if values is not None else None,
        )


@dataclass(frozen=True)
class Experiment:
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

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Experiment:
        """Reads the JSON form."""
        return cls(
            id=int(d["id"]),
            name=str(d["name"]),
            domain=dict(d["domain"]),
            d_max=float(d["d_max"]),
            seed=int(d["seed"]),
            mde=dict(d["mde"]),
            learning=dict(d["learning"]),
            state_space=Space.from_json(d["state_space"]),
            action_space=Space.from_json(d["action_space"]),
            feature_names=list(d["feature_names"]),
            created_at=str(d["created_at"]),
            n_trajectories=int(d["n_trajectories"]),
            n_transitions=int(d["n_transitions"]),
            iteration=int(d["iteration"]),
            model_version=int(d["model_version"]),
            n_refused=int(d["n_refused"]),
            last_activity=str(d["last_activity"]),
            raw=d,
        )


@dataclass(frozen=True)
class Transition:
    """One executed transition to post (schema ``TransitionRequest``).

    ``s_pred`` is the client's own prediction ``f̂(s, a)``: required when the experiment's model
    is the client's (``model.kind`` ``client``), refused otherwise.
    """

    SCHEMA: ClassVar[str] = "TransitionRequest"

    s: ArrayLike
    a: ArrayLike
    s_next: ArrayLike
    s_pred: ArrayLike | None = None

    def to_json(self) -> dict[str, Any]:
        """The JSON form."""
        d: dict[str, Any] = {
            "s": as_list(self.s),
            "a": as_list(self.a),
            "s_next": as_list(self.s_next),
        }
        if self.s_pred is not None:
            d["s_pred"] = as_list(self.s_pred)
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
class StoredTransition:
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

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> StoredTransition:
        """Reads the JSON form."""
        return cls(
            id=int(d["id"]),
            trajectory_id=int(d["trajectory_id"]),
            step=int(d["step"]),
            s=vec(d["s"]),
            a=vec(d["a"]),
            s_next=vec(d["s_next"]),
            s_pred=vec(d["s_pred"]),
            deviation=float(d["deviation"]),
        )


@dataclass(frozen=True)
class Source:
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

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Source:
        """Reads the JSON form."""
        ep, fs, label = d.get("episode"), d.get("first_step"), d.get("label")
        return cls(
            dataset=str(d["dataset"]),
            episode=int(ep) if ep is not None else None,
            first_step=int(fs) if fs is not None else None,
            label=str(label) if label is not None else None,
        )


def _source(d: Mapping[str, Any]) -> Source | None:
    s = d.get("source")
    return Source.from_json(s) if s is not None else None


@dataclass(frozen=True)
class TrajectoryCreated:
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

    @classmethod
    def from_json(cls, d: Mapping[str, Any], replayed: bool = False) -> TrajectoryCreated:
        """Reads the JSON form."""
        pid = d.get("proposal_id")
        return cls(
            id=int(d["id"]),
            experiment_id=int(d["experiment_id"]),
            proposal_id=int(pid) if pid is not None else None,
            partial=bool(d["partial"]),
            deviating=bool(d["deviating"]),
            source=_source(d),
            n_transitions=int(d["n_transitions"]),
            deviations=vec(d["deviations"]),
            iteration=int(d["iteration"]),
            model_version=int(d["model_version"]),
            n_trajectories=int(d["n_trajectories"]),
            created_at=str(d["created_at"]),
            replayed=replayed,
        )


@dataclass(frozen=True)
class Trajectory:
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

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Trajectory:
        """Reads the JSON form."""
        pid = d.get("proposal_id")
        return cls(
            id=int(d["id"]),
            experiment_id=int(d["experiment_id"]),
            proposal_id=int(pid) if pid is not None else None,
            partial=bool(d["partial"]),
            deviating=bool(d["deviating"]),
            source=_source(d),
            created_at=str(d["created_at"]),
            n_transitions=int(d["n_transitions"]),
            transitions=[StoredTransition.from_json(t) for t in d["transitions"]],
        )


@dataclass(frozen=True)
class Run:
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
    extensions: int | None
    model_version: int | None
    created_at: str
    length: int
    partial: bool
    deviating: bool
    source: Source | None
    max_deviation: float | None

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Run:
        """Reads the JSON form."""

        def opt_int(key: str) -> int | None:
            v = d.get(key)
            return int(v) if v is not None else None

        def opt_float(key: str) -> float | None:
            v = d.get(key)
            return float(v) if v is not None else None

        betas = d.get("betas_tried")
        return cls(
            proposal_id=opt_int("proposal_id"),
            trajectory_id=opt_int("trajectory_id"),
            refusal_id=opt_int("refusal_id"),
            status=str(d["status"]),
            client_id=d.get("client_id"),
            iteration=opt_int("iteration"),
            beta=opt_float("beta"),
            betas_tried=vec(betas) if betas is not None else None,
            extensions=opt_int("extensions"),
            model_version=opt_int("model_version"),
            created_at=str(d["created_at"]),
            length=int(d["length"]),
            partial=bool(d["partial"]),
            deviating=bool(d["deviating"]),
            source=_source(d),
            max_deviation=opt_float("max_deviation"),
        )


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
class PlannedTrajectory:
    """A planned trajectory with the MDE's answer per step (schemas ``PlannedTrajectory`` and
    ``ProposedTrajectory``: a proposal's trajectory also has ``alpha_step`` and ``alpha``)."""

    SCHEMA: ClassVar[tuple[str, ...]] = ("PlannedTrajectory", "ProposedTrajectory")

    states: Array
    """Predicted states ``(T + 1, n)``, the start first."""
    actions: Array
    """Actions ``(T, m)``."""
    mu: Array
    sigma: Array
    alpha_step: Array | None = None
    alpha: float | None = None

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> PlannedTrajectory:
        """Reads the JSON form."""
        states = mat(d["states"])
        alpha_step = d.get("alpha_step")
        alpha = d.get("alpha")
        return cls(
            states=states,
            actions=mat(d["actions"]),
            mu=vec(d["mu"]),
            sigma=vec(d["sigma"]),
            alpha_step=vec(alpha_step) if alpha_step is not None else None,
            alpha=float(alpha) if alpha is not None else None,
        )


@dataclass(frozen=True)
class CandidateScore:
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

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> CandidateScore:
        """Reads the JSON form."""
        fo = d.get("first_outside")
        return cls(
            alpha=float(d["alpha"]),
            length=int(d["length"]),
            inside=d.get("inside"),
            first_outside=int(fo) if fo is not None else None,
            reaches_goal=d.get("reaches_goal"),
            mu=vec(d["mu"]) if d.get("mu") is not None else None,
            sigma=vec(d["sigma"]) if d.get("sigma") is not None else None,
        )


@dataclass(frozen=True)
class Proposal:
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

    @property
    def actions(self) -> Array:
        """The actions to execute from :attr:`start`, ``(T, m)``."""
        return self.trajectory.actions

    @property
    def states(self) -> Array:
        """The model's predicted states, ``(T + 1, n)``."""
        return self.trajectory.states

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Proposal:
        """Reads the JSON form."""
        return cls(
            id=int(d["id"]),
            status=str(d["status"]),
            deviating=bool(d["deviating"]),
            client_id=d.get("client_id"),
            iteration=int(d["iteration"]),
            beta=float(d["beta"]),
            strategy=str(d["strategy"]),
            model_version=int(d["model_version"]),
            start=vec(d["start"]),
            goal=vec(d["goal"]),
            created_at=str(d["created_at"]),
            expires_at=str(d["expires_at"]),
            trajectory=PlannedTrajectory.from_json(d["trajectory"]),
            candidates=[CandidateScore.from_json(c) for c in d["candidates"]],
            chosen_index=int(d["chosen_index"]),
            extensions=int(d["extensions"]),
            raw=d,
            relaxed_from_beta=(
                float(d["relaxed_from_beta"]) if d.get("relaxed_from_beta") is not None else None
            ),
        )


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
class RejectionCounts:
    """Why a search's extensions added nothing to its tree (schema ``RejectionCounts``)."""

    SCHEMA: ClassVar[str] = "RejectionCounts"

    constraints: int
    """No steered action was allowed by the domain and new: the search could not reach on."""
    precondition: int
    """Some were, but none was trusted."""

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RejectionCounts:
        """Reads the JSON form."""
        return cls(constraints=int(d["constraints"]), precondition=int(d["precondition"]))


@dataclass(frozen=True)
class Plan:
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

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Plan:
        """Reads the JSON form."""
        t = d.get("trajectory")
        c = d.get("candidates")
        return cls(
            found=bool(d["found"]),
            extensions=int(d["extensions"]),
            rejections=RejectionCounts.from_json(d["rejections"]),
            beta=float(d["beta"]),
            d_max=float(d["d_max"]),
            model_version=int(d["model_version"]),
            trajectory=PlannedTrajectory.from_json(t) if t is not None else None,
            candidates=[CandidateScore.from_json(x) for x in c] if c is not None else None,
        )


@dataclass(frozen=True)
class Hyperparameters:
    """A GP's hyperparameters in natural units (schema ``Hyperparameters``)."""

    SCHEMA: ClassVar[str] = "Hyperparameters"

    length_scales: Array
    signal_variance: float
    noise_variance: float
    prior_mean: float
    kernel: str
    """The Matérn kernel: ``matern12``, ``matern32`` or ``matern52``."""

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Hyperparameters:
        """Reads the JSON form (``matern52`` when a server too old to say omits the kernel)."""
        return cls(
            length_scales=vec(d["length_scales"]),
            signal_variance=float(d["signal_variance"]),
            noise_variance=float(d["noise_variance"]),
            prior_mean=float(d["prior_mean"]),
            kernel=str(d.get("kernel", "matern52")),
        )


@dataclass(frozen=True)
class NoiseSummary:
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

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> NoiseSummary:
        """Reads the JSON form."""
        return cls(
            min_noise_variance=float(d["min_noise_variance"]),
            mean_noise_variance=float(d["mean_noise_variance"]),
            max_noise_variance=float(d["max_noise_variance"]),
            noise_model=Hyperparameters.from_json(d["noise_model"]),
            rounds=int(d["rounds"]),
            homoscedastic_lml=float(d["homoscedastic_lml"]),
        )


@dataclass(frozen=True)
class HeldOutTrust:
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

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> HeldOutTrust:
        """Reads the JSON form."""
        return cls(
            label_cap=float(d["label_cap"]),
            safe=int(d["safe"]),
            unsafe_transitions=int(d["unsafe_transitions"]),
            trusted_safe=int(d["trusted_safe"]),
            trusted_unsafe=int(d["trusted_unsafe"]),
            log_score=float(d["log_score"]),
            held_out_groups=int(d["held_out_groups"]),
        )


@dataclass(frozen=True)
class KernelTrial:
    """One candidate kernel's fit when the kernel is chosen from the data (schema
    ``KernelTrial``)."""

    SCHEMA: ClassVar[str] = "KernelTrial"

    kernel: str
    """``matern12``, ``matern32`` or ``matern52``."""
    log_marginal_likelihood: float
    held_out_log_score: float | None = None
    """The mean held-out log probability of the training state-actions' side of ``d_max``
    (``None`` when not computed and for fits made before it existed)."""

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> KernelTrial:
        """Reads the JSON form."""
        score = d.get("held_out_log_score")
        return cls(
            kernel=str(d["kernel"]),
            log_marginal_likelihood=float(d["log_marginal_likelihood"]),
            held_out_log_score=float(score) if score is not None else None,
        )


@dataclass(frozen=True)
class FitRefusal:
    """A fit the server did not attempt because its estimated peak memory exceeded the server's
    budget; the version before it kept answering (schema ``FitRefusal``)."""

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

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> FitRefusal:
        """Reads the JSON form."""
        return cls(
            n_train=int(d["n_train"]),
            n_trajectories=int(d["n_trajectories"]),
            estimator=str(d["estimator"]),
            needed_bytes=float(d["needed_bytes"]),
            budget_bytes=float(d["budget_bytes"]),
            reason=str(d["reason"]),
            refused_at=str(d["refused_at"]),
        )


@dataclass(frozen=True)
class Model:
    """The MDE version answering queries (schema ``Model``)."""

    SCHEMA: ClassVar[str] = "Model"

    experiment_id: int
    version: int
    source: str
    """``prior`` (version 0) or ``fit``."""
    n_train: int
    noise: str | None
    feature_names: list[str]
    hyperparameters: Hyperparameters
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
    """``exact`` or ``sparse`` (``None`` for the prior)."""
    online_trajectories: int
    """Trajectories taken in by online updates since the fit (sparse GP)."""
    last_fit_refusal: FitRefusal | None
    """The latest fit refused since this version for the memory budget."""
    kernel_trials: list[KernelTrial]
    """With ``mde.kernel`` ``auto``, each kernel's fit; the highest log marginal likelihood won
    unless another's held-out score was clearly better."""
    raw: dict[str, Any] = field(repr=False, compare=False, metadata=CLIENT_ONLY)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Model:
        """Reads the JSON form."""
        lml = d.get("log_marginal_likelihood")
        fs = d.get("fit_seconds")
        cap = d.get("label_cap")
        noise_model = d.get("noise_model")
        return cls(
            experiment_id=int(d["experiment_id"]),
            version=int(d["version"]),
            source=str(d["source"]),
            n_train=int(d["n_train"]),
            noise=d.get("noise"),
            feature_names=list(d["feature_names"]),
            hyperparameters=Hyperparameters.from_json(d["hyperparameters"]),
            noise_model=NoiseSummary.from_json(noise_model) if noise_model is not None else None,
            log_marginal_likelihood=float(lml) if lml is not None else None,
            fit_seconds=float(fs) if fs is not None else None,
            fitted_at=d.get("fitted_at"),
            n_trajectories=int(d["n_trajectories"]),
            label_cap=float(cap) if cap is not None else None,
            label_cap_trials=[HeldOutTrust.from_json(t) for t in d["label_cap_trials"]],
            estimator=d.get("estimator"),
            online_trajectories=int(d["online_trajectories"]),
            last_fit_refusal=(
                FitRefusal.from_json(d["last_fit_refusal"])
                if d.get("last_fit_refusal") is not None
                else None
            ),
            kernel_trials=[KernelTrial.from_json(t) for t in d["kernel_trials"]],
            raw=d,
        )


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
        )
