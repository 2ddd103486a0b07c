"""Executing plans on the robot: step by step, watched, closed loop.

Three helpers share one robot interface, ``step_fn(state, action) -> observed state`` (the
robot executes ``action`` from ``state``, where it is, and reports where it ended; ``None``
means it stopped and will not go on), and report an :class:`Execution`:

- :class:`Monitor` watches a plan being executed: each observed state is compared with the
  state predicted for it, in the experiment's distance (:class:`Metric`); beyond the tolerance
  (default ``d_max``) the model was wrong there, so the run so far is posted as a ``partial``
  trajectory and :class:`~precond_client.errors.DeviationExceeded` is raised for the robot's
  script to stop on. :meth:`~precond_client.robot.Episode.execute` runs a training episode
  under a monitor; :meth:`~precond_client.Client.monitor` watches any plan.
- :meth:`~precond_client.robot.Episode.run_closed_loop` executes a training proposal closed
  loop: when the robot leaves the tolerance around the plan (or the plan runs out short of the
  goal) it posts the executed prefix through ``continue_proposal`` and goes on with the new
  proposal from where the robot is.
- :func:`execute_plan` (:meth:`~precond_client.Client.execute_plan`) does the same at test
  time with ``client.plan``: nothing is stored.

The experiment's own distance and goal test decide: a custom domain's ``distance.weights``
(``sqrt(Σ w_i (ŝ_i − s_i)²)``, a ``state.periodic`` component's difference the shorter way
round) and ``goal`` (``components`` within ``radius``); Euclidean for
the built-in kinds, with ``goal_radius`` on every component for ``kinematic``, the exact cell
for ``icy_gridworld``, the poured volume for ``water_plant``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from . import errors
from .models import Array, Experiment, Plan, TrajectoryCreated, Transition, mat, vec

log = logging.getLogger("precond_client")

StepFn = Callable[[Array, Array], "ArrayLike | None"]
"""The robot: ``step_fn(state, action)`` executes ``action`` from ``state`` (where the robot
is) and returns the state it observed afterwards, or ``None`` when it stopped (it will execute
nothing more)."""

PostFn = Callable[[Sequence[Transition], bool], TrajectoryCreated]
"""Posts executed transitions (``partial`` or not); returns the server's answer."""

PredictFn = Callable[[Array, Array], ArrayLike]
"""The robot's model ``f̂(state, action) -> predicted next state`` for one step."""

STATUSES = ("goal", "done", "deviated", "stopped", "budget", "replans", "no_plan", "failed")
"""How an :class:`Execution` ended: ``goal`` reached; ``done`` (every action of the plan
executed, the goal not reached); ``deviated`` (a monitor stopped it); ``stopped`` (the robot's
``step_fn`` returned ``None``); ``budget`` (``max_steps`` spent); ``replans`` (``max_replans``
spent); ``no_plan`` (no plan from where the robot is); ``failed`` (the server kept failing:
:attr:`Execution.error`)."""


def radius(value: float | Sequence[float]) -> float | Array:
    """A goal's ``radius`` as the server resolves it: a number, or one per goal component."""
    if isinstance(value, (int, float)):
        return float(value)
    radii = vec(value)
    return float(radii[0]) if len(radii) == 1 else radii


@dataclass(frozen=True, eq=False)
class Metric:
    """An experiment's distance between states and its goal test, as the server computes them
    (see the module docs). ``Metric.of(experiment)`` reads them from its resolved domain."""

    d_max: float
    """The experiment's tolerance, in the distance's units."""
    kind: str
    """The domain's kind."""
    weights: Array | None = None
    """A custom domain's ``distance.weights``; ``None``: Euclidean (or the water plant's)."""
    goal_components: tuple[int, ...] | None = None
    """The state components compared with the goal vector (``None``: every one)."""
    goal_radius: float | Array = 0.0
    """The goal's radius (``kinematic``, ``custom``), or one per goal component (a custom
    domain's ``goal.radius`` as a list: ``Σ ((s_i − g_i) / r_i)² ≤ 1``)."""
    periods: dict[int, float] = field(default_factory=dict)
    """A custom domain's periodic state components (``state.periodic``) and their periods
    ``high − low``: differences in them are taken the shorter way round."""

    @classmethod
    def of(cls, experiment: Experiment) -> Metric:
        """The metric of ``experiment`` (its resolved ``domain`` and ``d_max``)."""
        domain = experiment.domain
        kind = str(domain.get("kind"))
        d_max = float(experiment.d_max)
        if kind == "custom":
            distance = domain.get("distance") or {}
            goal = domain.get("goal") or {}
            weights = distance.get("weights")
            components = goal.get("components")
            state = domain.get("state") or {}
            periods = {
                int(i): float(state["high"][int(i)]) - float(state["low"][int(i)])
                for i in state.get("periodic") or []
            }
            return cls(
                d_max,
                kind,
                weights=None if weights is None else vec(weights),
                goal_components=None if components is None else tuple(int(c) for c in components),
                goal_radius=radius(goal.get("radius", 0.05)),
                periods=periods,
            )
        if kind == "kinematic":
            return cls(d_max, kind, goal_radius=float(domain.get("goal_radius", 0.05)))
        if kind in ("icy_gridworld", "water_plant"):
            return cls(d_max, kind)
        raise ValueError(
            f"domain kind {kind!r}: the client knows no distance or goal test for it; "
            f"build a Metric(d_max, kind, weights=..., goal_components=..., goal_radius=...)"
        )

    def distance(self, predicted: ArrayLike, observed: ArrayLike) -> float:
        """The experiment's distance ``d(ŝ, s)`` between a predicted and an observed state
        (what the server labels a transition with)."""
        p, o = vec(predicted), vec(observed)
        if p.shape != o.shape:
            raise ValueError(f"states of {len(p)} and {len(o)} components")
        if self.kind == "water_plant":
            # Both containers' position distances plus the mean volume deviation.
            src = float(np.hypot(p[0] - o[0], p[1] - o[1]))
            tgt = float(np.hypot(p[4] - o[4], p[5] - o[5]))
            return src + tgt + 0.5 * float(abs(p[3] - o[3]) + abs(p[7] - o[7]))
        diff = self._wrapped(p - o, range(len(p)))
        if self.weights is None:
            return float(np.sqrt(np.dot(diff, diff)))
        return float(np.sqrt(np.dot(self.weights, diff * diff)))

    def _wrapped(self, diff: Array, components: Sequence[int] | range) -> Array:
        """``diff`` (over the state ``components``) with every periodic one the short way."""
        if not self.periods:
            return diff
        out = np.array(diff, dtype=np.float64)
        for k, i in enumerate(components):
            period = self.periods.get(i, 0.0)
            if period > 0.0:
                out[k] -= period * np.round(out[k] / period)
        return out

    def at_goal(self, state: ArrayLike, goal: ArrayLike) -> bool:
        """Whether ``state`` satisfies ``goal`` (the server's goal test)."""
        s, g = vec(state), vec(goal)
        if self.kind == "water_plant":
            v = float(g[0])
            return bool(s[7] >= 0.98 * v - 1e-9 and s[8] <= 0.02 * v + 1e-9)
        components = list(self.goal_components or range(len(s)))
        if self.goal_components is not None:
            s = s[components]
        if s.shape != g.shape:
            raise ValueError(f"a goal of {len(g)} components for {len(s)} state components")
        diff = self._wrapped(s - g, components)
        if self.kind == "icy_gridworld":
            return float(np.linalg.norm(diff)) < 0.5
        return float(np.linalg.norm(diff / self.goal_radius)) <= 1.0


@dataclass(frozen=True, eq=False)
class Execution:
    """What an execution did: the observed states, the actions taken, what was predicted for
    each step and how far the robot was from it, and how it ended (:attr:`status`)."""

    status: str
    """How it ended; one of :data:`STATUSES`."""
    states: Array
    """The observed states, ``(k + 1, n)``, the start first."""
    actions: Array
    """The actions executed, ``(k, m)``."""
    predicted: Array
    """The state predicted for each step, ``(k, n)``: by the plan being followed, or by the
    robot's model from the observed state where a monitor was given one (``predict=``)."""
    deviations: Array
    """The distance between each step's prediction and its observed state, ``(k,)``."""
    replans: int = 0
    """How many times it planned again from where the robot was."""
    proposal_ids: tuple[int, ...] = ()
    """The proposals executed, in order (a training episode)."""
    trajectories: tuple[TrajectoryCreated, ...] = ()
    """The trajectories it posted, in order (the server's answers)."""
    stored_trajectory_ids: tuple[int, ...] = ()
    """The ids of every trajectory stored for it (also those stored by a continuation whose
    new plan failed)."""
    error: errors.PrecondError | None = field(default=None, compare=False)
    """Why it ended, for ``no_plan`` and ``failed``."""

    @property
    def success(self) -> bool:
        """The goal was reached."""
        return self.status == "goal"

    @property
    def steps(self) -> int:
        """Steps executed."""
        return len(self.actions)

    @property
    def max_deviation(self) -> float:
        """The largest deviation of a step (0 without steps)."""
        return float(self.deviations.max()) if len(self.deviations) else 0.0


class _Record:
    """An execution being recorded step by step; :meth:`result` freezes it."""

    def __init__(self, start: ArrayLike) -> None:
        self.states: list[Array] = [vec(start)]
        self.actions: list[Array] = []
        self.predicted: list[Array] = []
        self.deviations: list[float] = []
        self.replans = 0
        self.proposal_ids: list[int] = []
        self.trajectories: list[TrajectoryCreated] = []
        self.stored: list[int] = []

    @property
    def state(self) -> Array:
        return self.states[-1]

    def add(self, action: Array, observed: Array, predicted: Array, deviation: float) -> None:
        self.actions.append(action)
        self.states.append(observed)
        self.predicted.append(predicted)
        self.deviations.append(deviation)

    def posted(self, created: TrajectoryCreated) -> None:
        self.trajectories.append(created)
        self.stored.append(created.id)

    def result(self, status: str, error: errors.PrecondError | None = None) -> Execution:
        n = len(self.states[0])
        m = len(self.actions[0]) if self.actions else 0
        return Execution(
            status=status,
            states=np.array(self.states),
            actions=np.array(self.actions) if self.actions else np.zeros((0, m)),
            predicted=np.array(self.predicted) if self.predicted else np.zeros((0, n)),
            deviations=np.array(self.deviations, dtype=np.float64),
            replans=self.replans,
            proposal_ids=tuple(self.proposal_ids),
            trajectories=tuple(self.trajectories),
            stored_trajectory_ids=tuple(self.stored),
            error=error,
        )


def client_side(experiment: Experiment) -> bool:
    """Whether the experiment's model is the client's (``model.kind == "client"``): its
    transitions carry the client's predictions, its plans the client's candidates."""
    model = experiment.domain.get("model") or {}
    return experiment.domain.get("kind") == "custom" and model.get("kind") == "client"


def observe(step_fn: StepFn, state: Array, action: Array) -> Array | None:
    """The robot's observed state after ``action`` from ``state`` (``None``: it stopped);
    checked to be a finite state of the right size."""
    out = step_fn(state.copy(), action.copy())
    if out is None:
        return None
    observed = vec(out)
    if observed.shape != state.shape or not np.all(np.isfinite(observed)):
        raise ValueError(
            f"step_fn returned {observed.tolist()} for a state of {len(state)} components"
        )
    return observed


class Monitor:
    """Watches the execution of a plan step by step, and stops it where the model was wrong.

    Report each state the robot observes with :meth:`observe`; it returns the step's
    deviation, the experiment's distance between the observed state and the state predicted
    for it. Beyond ``tolerance`` the run so far (the deviating step included: it is what the
    model got wrong) is posted as a ``partial`` trajectory, and
    :class:`~precond_client.errors.DeviationExceeded` is raised: stop the robot. When the robot
    is done (every action executed, or it stopped early), :meth:`finish` posts what it did
    (``partial`` if it executed fewer actions than planned)::

        monitor = client.monitor(plan)                      # or episode.monitor()
        try:
            for action in monitor.actions:
                monitor.observe(robot.step(action))
            monitor.finish()
        except DeviationExceeded as e:
            robot.stop()                                    # e.step, e.deviation; posted

    Args:
        start: Where the robot is before the first action.
        actions: The planned actions ``(T, m)``.
        predicted_states: The plan's predicted states ``(T + 1, n)``, the start first.
        tolerance: The largest deviation let through (usually the experiment's ``d_max``).
        metric: The experiment's distance and goal test (:meth:`Metric.of`).
        post: How the run is posted (``None``: it is not; :meth:`finish` only reports it).
        goal: The goal, to tell whether :meth:`finish` ended there (``status == "goal"``).
        predict: The robot's own model for one step: each step is then judged by
            ``d(predict(s, a), s')`` from the state the robot really was in (the server's
            label of the transition). Without it a step is judged against the plan's
            prediction, which also counts how far the robot drifted from the plan.
        send_predictions: Post ``predict``'s predictions as ``s_pred`` (a ``client``-kind
            model's experiment needs them; the others refuse them).
        proposal_id: The proposal executed, if any (for :attr:`Execution.proposal_ids`).
    """

    def __init__(
        self,
        start: ArrayLike,
        actions: ArrayLike,
        predicted_states: ArrayLike,
        *,
        tolerance: float,
        metric: Metric,
        post: PostFn | None = None,
        goal: ArrayLike | None = None,
        predict: PredictFn | None = None,
        send_predictions: bool = False,
        proposal_id: int | None = None,
    ) -> None:
        self.actions = mat(actions)
        self.predicted_states = mat(predicted_states)
        if len(self.predicted_states) != len(self.actions) + 1:
            raise ValueError(
                f"{len(self.predicted_states)} predicted states for {len(self.actions)} actions "
                f"(the plan's states, the start first)"
            )
        self.tolerance = float(tolerance)
        self.metric = metric
        self.goal = None if goal is None else vec(goal)
        self._post = post
        self._predict = predict
        if send_predictions and predict is None:
            raise ValueError("send_predictions needs predict")
        self._send_predictions = send_predictions
        self._record = _Record(start)
        if proposal_id is not None:
            self._record.proposal_ids.append(proposal_id)
        self._transitions: list[Transition] = []
        self._status: str | None = None

    @property
    def step(self) -> int:
        """Steps observed so far."""
        return len(self._transitions)

    @property
    def state(self) -> Array:
        """Where the robot is: the last observed state (the start before any step)."""
        return self._record.state

    @property
    def next_action(self) -> Array | None:
        """The next planned action, ``None`` when the plan is spent or the run is over."""
        if self._status is not None or self.step >= len(self.actions):
            return None
        action: Array = self.actions[self.step]
        return action

    @property
    def done(self) -> bool:
        """Stopped by a deviation, or finished."""
        return self._status is not None

    def observe(self, observed: ArrayLike, action: ArrayLike | None = None) -> float:
        """Records one step: the robot executed ``action`` (default the next planned action)
        and observed ``observed``. Returns the step's deviation; beyond the tolerance, posts
        the run so far and raises :class:`~precond_client.errors.DeviationExceeded`."""
        if self._status is not None:
            raise RuntimeError(f"the execution is over ({self._status})")
        k = self.step
        if k >= len(self.actions):
            raise ValueError(f"the plan has {len(self.actions)} actions, all observed already")
        s = self.state
        a = self.actions[k] if action is None else vec(action)
        s_next = vec(observed)
        if s_next.shape != s.shape or not np.all(np.isfinite(s_next)):
            raise ValueError(f"observed state {s_next.tolist()}: not a state like {s.tolist()}")
        if self._predict is not None:
            predicted = vec(self._predict(s, a))
            transition = Transition(s, a, s_next, predicted if self._send_predictions else None)
        else:
            predicted = self.predicted_states[k + 1]
            transition = Transition(s, a, s_next)
        deviation = self.metric.distance(predicted, s_next)
        self._transitions.append(transition)
        self._record.add(a, s_next, predicted, deviation)
        if deviation > self.tolerance:
            log.info(
                "step %d deviated from its prediction by %.4g > %.4g: execution stopped",
                k,
                deviation,
                self.tolerance,
            )
            execution = self._end("deviated", partial=True)
            raise errors.DeviationExceeded(
                k, deviation, self.tolerance, s_next, predicted, execution
            )
        return deviation

    def finish(self) -> Execution:
        """Ends the execution (the robot executed every action, or stopped early): posts what
        was observed (``partial`` when fewer actions than planned) and returns it."""
        if self._status is not None:
            return self._record.result(self._status)
        reached = self.goal is not None and self.metric.at_goal(self.state, self.goal)
        if reached:
            status = "goal"
        elif self.step == len(self.actions):
            status = "done"
        else:
            status = "stopped"
        return self._end(status, partial=self.step < len(self.actions))

    def _end(self, status: str, partial: bool) -> Execution:
        self._status = status
        if self._post is not None and self._transitions:
            self._record.posted(self._post(self._transitions, partial))
        return self._record.result(status)


def execute_plan(
    plan: Callable[[Array, Array], Plan],
    start: ArrayLike,
    goal: ArrayLike,
    step_fn: StepFn,
    *,
    metric: Metric,
    tolerance: float,
    max_steps: int,
    max_replans: int,
) -> Execution:
    """Executes ``plan(start, goal)``'s trajectory closed loop with ``step_fn``: after each
    step, the goal reached ends it; an observed state further than ``tolerance`` from the
    plan's prediction, or a plan spent short of the goal, plans again from the observed state
    (up to ``max_replans`` times); ``max_steps`` bounds the steps. A plan not found ends it
    (``no_plan``), as does a transient error of the server (``failed``, the error attached);
    other errors are raised. See :meth:`~precond_client.Client.execute_plan`."""
    g = vec(goal)
    rec = _Record(start)
    if metric.at_goal(rec.state, g):
        return rec.result("goal")

    def new_plan() -> tuple[Array, Array] | errors.PrecondError:
        try:
            answer = plan(rec.state, g)
        except errors.PrecondError as e:
            if not errors.is_transient(e):
                raise
            log.warning("planning from %s failed: %s", np.round(rec.state, 4).tolist(), e)
            return e
        if not answer.found or answer.trajectory is None:
            return errors.NoPlan(
                422,
                "no_plan",
                f"no plan inside the precondition from {rec.state.tolist()} to {g.tolist()} "
                f"({answer.extensions} extensions)",
                {"extensions": answer.extensions},
            )
        return answer.trajectory.states, answer.trajectory.actions

    current = new_plan()
    while True:
        if isinstance(current, errors.PrecondError):
            status = "no_plan" if isinstance(current, errors.NoPlan) else "failed"
            return rec.result(status, current)
        states, actions = current
        replan = False
        for k in range(len(actions)):
            if len(rec.actions) >= max_steps:
                return rec.result("budget")
            observed = observe(step_fn, rec.state, actions[k])
            if observed is None:
                return rec.result("stopped")
            deviation = metric.distance(states[k + 1], observed)
            rec.add(actions[k].copy(), observed, states[k + 1].copy(), deviation)
            if metric.at_goal(observed, g):
                return rec.result("goal")
            if deviation > tolerance:
                log.info(
                    "step %d: %.4g from the plan's prediction (tolerance %.4g): planning again",
                    len(rec.actions) - 1,
                    deviation,
                    tolerance,
                )
                replan = True
                break
        if not replan:
            log.info(
                "the plan is spent short of the goal: planning again from %s",
                np.round(rec.state, 4).tolist(),
            )
        if len(rec.actions) >= max_steps:
            return rec.result("budget")
        if rec.replans >= max_replans:
            return rec.result("replans")
        rec.replans += 1
        current = new_plan()
