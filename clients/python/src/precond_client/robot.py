"""The robot's active-learning loop: propose, let the robot execute, post what happened.

::

    for episode in client.learn(problems):
        observed = robot.run(episode.start, episode.actions)   # (k + 1, n) states, start first
        episode.post(observed)                                 # partial if k < len(actions)

or, with the robot stepping itself (``step(state, action) -> observed state``)::

    for episode in client.learn(problems):
        episode.run_closed_loop(robot.step)    # replans from where the robot is when it drifts
        # episode.execute(robot.step)          # open loop, stopped where a step deviates

The loop survives a restart of either side:

- **The server restarts.** Every request is retried with back-off; a trajectory carries the
  ``Idempotency-Key`` ``proposal-<id>``, so a post whose answer was lost is replayed by the
  server, never stored twice, and one that never arrived is stored on the retry.
- **The robot's process restarts.** Leases live on the server under ``client_id`` (default the
  host name). Asked for a new problem while the previous process's proposal is still open, the
  server answers ``409`` naming the held proposal; the loop then hands that proposal out first
  (``episode.resumed`` is true: bring the robot to ``episode.start``) — or abandons it, with
  ``resume=False`` — and goes on with the problem it was asked.

It survives a busy or failing server too (see :class:`Learner`): a problem whose search keeps
passing the server's deadline, or whose proposal keeps failing with a transient answer, is
skipped and counted, never raised into the robot's script.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Iterator, Sequence, Sized
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from . import _status, errors
from .execution import (
    Execution,
    Metric,
    Monitor,
    PredictFn,
    StepFn,
    _Record,
    client_side,
    observe,
)
from .models import (
    Array,
    Candidate,
    Experiment,
    Proposal,
    TrajectoryCreated,
    Transition,
    mat,
    vec,
)
from .models import transitions_from_states as _from_states
from .protocols import LearningClient

log = logging.getLogger("precond_client")

Problem = tuple[ArrayLike, ArrayLike]
"""A planning problem: ``(start, goal)``."""

CandidateFn = Callable[[Array, Array], Sequence[Candidate]]
"""The client's own planner for a problem ``(start, goal)`` (client-side models)."""

ModelsFn = Callable[[int], Sequence[str] | None]
"""The models a proposal may step with, given the number of episodes so far (``None``: the
domain's model alone)."""

SleepFn = Callable[[float], None]

_T = TypeVar("_T")


@dataclass
class _Context:
    """What an :class:`Episode` needs beyond its client: the experiment (fetched once), how
    to wait, and how many times a post that fails transiently is tried."""

    experiment: Callable[[], Experiment]
    sleep: SleepFn = time.sleep
    post_attempts: int = 3


@dataclass
class Episode:
    """One proposal to execute; report it once with :meth:`post` (or :meth:`abandon`), or
    let :meth:`execute` or :meth:`run_closed_loop` drive the robot and report it."""

    proposal: Proposal
    """The proposal, with the trajectory to execute and the MDE's view of it. Closed loop
    (:meth:`run_closed_loop`) this is the proposal being executed, the last continuation."""
    resumed: bool
    """The lease was held from before (an earlier process of this client asked for it)."""
    _client: LearningClient = field(repr=False)
    result: TrajectoryCreated | None = None
    """The server's answer once posted (closed loop: to the last proposal's post)."""
    abandoned: bool = False
    trajectories: list[TrajectoryCreated] = field(default_factory=list)
    """Every trajectory posted for this episode, in order (closed loop: one per proposal)."""
    stored_trajectory_ids: list[int] = field(default_factory=list)
    """The ids of every trajectory stored for this episode (also a prefix stored by a
    continuation whose new plan then failed)."""
    execution: Execution | None = None
    """What :meth:`execute` or :meth:`run_closed_loop` did."""
    _context: _Context | None = field(default=None, repr=False)
    _stored_elsewhere: bool = field(default=False, repr=False)

    @property
    def start(self) -> Array:
        """Where the robot must be before executing."""
        return self.proposal.start

    @property
    def goal(self) -> Array:
        """The problem's goal."""
        return self.proposal.goal

    @property
    def actions(self) -> Array:
        """The actions to execute, ``(T, m)``."""
        return self.proposal.actions

    @property
    def predicted_states(self) -> Array:
        """The model's predicted states, ``(T + 1, n)``."""
        return self.proposal.states

    @property
    def done(self) -> bool:
        """Posted or abandoned."""
        return self.result is not None or self.abandoned

    @property
    def reported(self) -> bool:
        """Something was stored for it (posted, or a prefix stored by a continuation)."""
        return bool(self.stored_trajectory_ids) or self._stored_elsewhere

    def _ctx(self) -> _Context:
        if self._context is None:
            self._context = _Context(self._client.get_experiment)
        return self._context

    def metric(self) -> Metric:
        """The experiment's distance and goal test (:class:`~precond_client.execution.Metric`)."""
        return Metric.of(self._ctx().experiment())

    def post(
        self,
        observed_states: ArrayLike,
        actions: ArrayLike | None = None,
        *,
        predicted: ArrayLike | None = None,
        partial: bool | None = None,
    ) -> TrajectoryCreated:
        """Reports the execution: the ``k + 1`` states the robot observed (the start first)
        after executing the first ``k`` actions (default the proposal's, in order).

        ``partial`` defaults to whether the robot stopped before the last action.
        ``predicted`` is the ``k`` predictions of a client-side model. A post that fails
        transiently (the server unreachable or answering ``429``/``5xx`` through all the
        client's retries) is tried again, a few times, after the server's ``Retry-After``: it
        carries the robot's data, under the same ``Idempotency-Key``.
        """
        states = mat(observed_states)
        k = len(states) - 1
        acts = mat(actions) if actions is not None else self.actions[:k]
        return self.post_transitions(
            _from_states(states, acts, predicted),
            partial=k < len(self.actions) if partial is None else partial,
        )

    def post_transitions(
        self, transitions: Sequence[Transition], partial: bool = False
    ) -> TrajectoryCreated:
        """Reports the execution as explicit transitions (see :meth:`post`)."""
        if self.result is not None:
            return self.result
        pid = self.proposal.id
        self.result = self._persist(
            f"posting proposal {pid}",
            lambda: self._client.post_trajectory(transitions, proposal_id=pid, partial=partial),
        )
        self.trajectories.append(self.result)
        self.stored_trajectory_ids.append(self.result.id)
        return self.result

    def _persist(self, what: str, call: Callable[[], _T]) -> _T:
        """``call()``, tried again after a transient failure (``post_attempts`` in all)."""
        ctx = self._ctx()
        attempt = 1
        while True:
            try:
                with _status.activity(what):
                    return call()
            except errors.PrecondError as e:
                if not errors.is_transient(e) or attempt >= ctx.post_attempts:
                    raise
                delay = errors.retry_after(e, 30.0)
                log.warning(
                    "%s failed (%s): trying again, %d/%d, in %s",
                    what,
                    e,
                    attempt + 1,
                    ctx.post_attempts,
                    _status.seconds(delay),
                )
                ctx.sleep(delay)
                attempt += 1

    def abandon(self) -> None:
        """Gives the proposal up (the robot could not execute it at all)."""
        if not self.done:
            self._client.abandon(self.proposal.id)
            self.abandoned = True

    # ------------------------------------------------------------------ executing

    def monitor(
        self, *, tolerance: float | None = None, predict: PredictFn | None = None
    ) -> Monitor:
        """A :class:`~precond_client.execution.Monitor` of this episode's execution: report
        each observed state with ``monitor.observe(state)``; a step further than ``tolerance``
        (default the experiment's ``d_max``, in its distance) from its prediction posts the run
        so far as this episode's ``partial`` trajectory and raises
        :class:`~precond_client.errors.DeviationExceeded`; ``monitor.finish()`` posts a run
        that ended otherwise. With ``predict``, the robot's model, each step is judged from
        where the robot really was (a ``client``-kind model's predictions are posted too)."""
        experiment = self._ctx().experiment()
        metric = Metric.of(experiment)
        return Monitor(
            self.start,
            self.actions,
            self.predicted_states,
            tolerance=metric.d_max if tolerance is None else tolerance,
            metric=metric,
            post=lambda transitions, partial: self.post_transitions(transitions, partial),
            goal=self.goal,
            predict=predict,
            send_predictions=predict is not None and client_side(experiment),
            proposal_id=self.proposal.id,
        )

    def execute(
        self,
        step_fn: StepFn,
        *,
        tolerance: float | None = None,
        monitor: bool = True,
        predict: PredictFn | None = None,
    ) -> Execution:
        """Executes the proposal open loop, one action at a time with ``step_fn(state,
        action) -> observed state`` (``None``: the robot stopped), and posts it. With
        ``monitor`` (default) the execution stops at the first step further than
        ``tolerance`` (default ``d_max``) from its prediction — the model was wrong there —
        and the run so far is posted ``partial`` (``status == "deviated"``; see
        :meth:`monitor`). Returns the :class:`~precond_client.execution.Execution`."""
        watch = self.monitor(
            tolerance=tolerance if monitor else float("inf"),
            predict=predict,
        )
        try:
            for action in watch.actions:
                observed = observe(step_fn, watch.state, action)
                if observed is None:
                    break
                watch.observe(observed, action)
            self.execution = watch.finish()
        except errors.DeviationExceeded as e:
            self.execution = e.execution
        if not self.reported and not self.abandoned:
            self.abandon()  # the robot executed nothing: give the lease up
        assert self.execution is not None
        return self.execution

    def run_closed_loop(
        self,
        step_fn: StepFn,
        *,
        tolerance: float | None = None,
        max_steps: int | None = None,
        max_replans: int = 20,
    ) -> Execution:
        """Executes the proposal closed loop, one action at a time with ``step_fn(state,
        action) -> observed state`` (``None``: the robot stopped).

        After each step: the goal reached (the experiment's goal test) posts the executed
        prefix and ends. An observed state further than ``tolerance`` (default the
        experiment's ``d_max``, in its distance) from the plan's prediction, or a plan spent
        short of the goal, posts the prefix executed since the last plan through
        :meth:`~precond_client.Client.continue_proposal` (under ``continue-<id>``: a replay
        stores nothing twice) and goes on with the new proposal, planned from where the robot
        is to the same goal; :attr:`proposal` follows it. It also ends when the robot stops,
        after ``max_steps`` steps (default three times the first plan's length, at least 10)
        or ``max_replans`` continuations (the prefix posted ``partial``), when there is no plan
        from where the robot is (``no_plan``), or when the server keeps failing (``failed``;
        transient errors are not raised). Returns the
        :class:`~precond_client.execution.Execution`; :attr:`stored_trajectory_ids` lists
        everything stored.

        Not for a ``client``-kind model (its continuations need the client's own candidates
        and predictions: use :meth:`~precond_client.Client.continue_proposal`)."""
        if self.done or self.reported:
            raise RuntimeError(f"episode of proposal {self.proposal.id} was already reported")
        experiment = self._ctx().experiment()
        if client_side(experiment):
            raise ValueError(
                "run_closed_loop cannot continue a client-kind model's proposal: post "
                "continue_proposal(..., candidates=...) with your own predictions"
            )
        metric = Metric.of(experiment)
        tol = metric.d_max if tolerance is None else float(tolerance)
        budget = max(10, 3 * len(self.actions)) if max_steps is None else int(max_steps)
        rec = _Record(self.start)
        rec.proposal_ids.append(self.proposal.id)
        goal = self.goal
        segment: list[Transition] = []
        k = 0

        def end(status: str, partial: bool, error: errors.PrecondError | None = None) -> Execution:
            if segment:
                created = self.post_transitions(segment, partial)
                rec.posted(created)
            elif k == 0 and not self.done:
                # Nothing executed of the current proposal (the robot stopped at once, or
                # the budget ended with a continuation): give its lease up.
                self._abandon_quietly()
            self.execution = rec.result(status, error)
            return self.execution

        while True:
            actions, states = self.proposal.actions, self.proposal.states
            if k < len(actions):
                if len(rec.actions) >= budget:
                    return end("budget", True)
                action = actions[k]
                observed = observe(step_fn, rec.state, action)
                if observed is None:
                    return end("stopped", True)
                deviation = metric.distance(states[k + 1], observed)
                segment.append(Transition(rec.state, action, observed))
                rec.add(action.copy(), observed, states[k + 1].copy(), deviation)
                k += 1
                if metric.at_goal(observed, goal):
                    return end("goal", k < len(actions))
                if deviation <= tol and k < len(actions):
                    continue
                why = (
                    f"{deviation:.4g} from the plan's prediction (tolerance {tol:.4g})"
                    if deviation > tol
                    else "the plan is spent short of the goal"
                )
            elif not segment:
                # An empty plan (the server thinks the start is at the goal): nothing to do.
                return end("done", False)
            else:
                why = "the plan is spent short of the goal"
            if len(rec.actions) >= budget:
                return end("budget", True)
            if rec.replans >= max_replans:
                return end("replans", True)
            pid = self.proposal.id
            log.info(
                "proposal %d: step %d %s: continuing from %s",
                pid,
                len(rec.actions) - 1,
                why,
                np.round(rec.state, 4).tolist(),
            )
            try:
                with _status.activity(f"continuing proposal {pid}"):
                    continued = self._client.continue_proposal(pid, segment)
            except errors.PrecondError as e:
                stored = _stored_id(e)
                if stored is not None:  # the prefix is stored: nothing more to post
                    self.stored_trajectory_ids.append(stored)
                    rec.stored.append(stored)
                    segment = []
                if isinstance(e, errors.ValidationFailed) and e.start_satisfies_goal:
                    return end("goal", True)  # the server's goal test says it arrived
                if isinstance(e, errors.NoPlan):
                    log.info(
                        "proposal %d: no plan from %s: stopping",
                        pid,
                        np.round(rec.state, 4).tolist(),
                    )
                    return end("no_plan", True, e)
                if not errors.is_transient(e):
                    raise
                log.warning("proposal %d: continuing failed (%s): stopping", pid, e)
                try:
                    return end("failed", True, e)
                except errors.Conflict:
                    # The continuation stored the prefix but its answer was lost: the
                    # proposal is executed already.
                    self._stored_elsewhere = True
                    return self._ended(rec, "failed", e)
            self.trajectories.append(continued.trajectory)
            self.stored_trajectory_ids.append(continued.trajectory.id)
            rec.posted(continued.trajectory)
            self.proposal = continued.proposal
            rec.proposal_ids.append(continued.proposal.id)
            rec.replans += 1
            segment = []
            k = 0

    def _ended(
        self, rec: _Record, status: str, error: errors.PrecondError | None = None
    ) -> Execution:
        self.execution = rec.result(status, error)
        return self.execution

    def _abandon_quietly(self) -> None:
        """Abandons the proposal; a transient failure is logged (the lease expires by
        itself), as is a proposal executed already."""
        try:
            self.abandon()
        except errors.Conflict as e:
            log.info("proposal %d: not abandoned (%s)", self.proposal.id, e)
        except errors.PrecondError as e:
            if not errors.is_transient(e):
                raise
            log.warning(
                "abandoning proposal %d failed (%s): its lease expires", self.proposal.id, e
            )


def _stored_id(e: errors.PrecondError) -> int | None:
    """The trajectory a continuation stored before it failed (``details``)."""
    details = getattr(e, "details", None)
    if isinstance(details, dict):
        stored = details.get("stored_trajectory_id")
        if isinstance(stored, int) and not isinstance(stored, bool):
            return stored
    return None


@dataclass(frozen=True)
class Skipped:
    """A problem :class:`Learner` skipped, and why."""

    problem: int
    """Its index in ``problems`` (from 0)."""
    start: Array
    goal: Array
    reason: str
    """``no_plan`` (no trajectory inside the precondition), ``at_goal`` (the start satisfies
    the goal), ``deadline`` (its searches kept passing the server's deadline) or ``failed``
    (the server kept answering transiently: :attr:`error`)."""
    error: errors.PrecondError | None = field(default=None, compare=False)
    """The last error answered for it."""


@dataclass(frozen=True)
class Progress:
    """Where a :class:`Learner` stands, handed to its ``progress`` callback after each event."""

    event: str
    """What just happened: ``posted`` (an episode's trajectory was stored), ``abandoned``,
    ``no_plan``, ``at_goal``, ``deadline`` or ``failed`` (a problem skipped; see
    :class:`Skipped`), ``model`` (the model covering the latest batch answers now)."""
    problem: int
    """Index of the current problem (from 0) in ``problems``."""
    episodes: int
    posted: int
    abandoned: int
    no_plan: int
    at_goal: int
    resumed: int
    model_version: int | None
    """The latest MDE version the loop saw (of a proposal, a posted trajectory's answer or the
    model it waited for); ``None`` before the first answer."""
    proposal_id: int | None = None
    """The episode's proposal (``posted``, ``abandoned``)."""
    result: TrajectoryCreated | None = None
    """The server's answer to the posted trajectory (``posted``)."""
    deadline: int = 0
    """Problems skipped because their searches kept passing the server's deadline."""
    failed: int = 0
    """Problems skipped because the server kept failing transiently."""


ProgressFn = Callable[[Progress], None]
"""A callback receiving a :class:`Progress` after each event of the loop."""


class Learner:
    """The loop over planning problems; iterate it for :class:`Episode` s.

    For each problem it asks for a proposal. A problem whose start already satisfies its goal
    is skipped with a warning (counted in :attr:`at_goal`); on ``no_plan`` the problem is
    skipped (counted in :attr:`no_plan`; ``skip_no_plan=False`` raises instead). An episode the
    caller did not report before asking for the next one is abandoned; one left unreported by
    leaving the loop stays leased, and the next loop of the same ``client_id`` resumes it.

    **A busy or failing server** never stops the loop. Every request is retried by the client
    (back-off, the server's ``Retry-After``); beyond that:

    - A proposal whose search passes the server's planning deadline (``503
      deadline_exceeded``) is asked again after the ``Retry-After``, ``deadline_attempts``
      searches in all (default 2), then the problem is skipped (counted in :attr:`deadline`):
      the same search would run as long again, and a doomed problem must not cost minutes.
    - A proposal failing with another transient answer (``429``, ``502``, ``503``, ``504``,
      ``507``, or the server unreachable) through all the client's retries is asked again
      after the ``Retry-After``, ``transient_attempts`` times in all (default 3), then the
      problem is skipped (counted in :attr:`failed`).
    - Waiting for the model, abandoning an unreported proposal: a transient failure is
      logged and the loop goes on.
    - A post (:meth:`Episode.post`) is tried ``transient_attempts`` times too (it carries the
      robot's data), then raises.

    Every skipped problem is in :attr:`skipped` with its reason. Errors that are not transient
    (a validation error, a conflict, the server's own bug) are raised.

    **Waiting for the model** (``wait_for_model=True``, the default). The server refits the MDE
    in the background after every batch of ``learning.batch_size`` trajectories. Active
    learning expects the next proposal to be scored by the model that has seen the batch just
    posted (the paper's loop fits between batches), so after a post that completes a batch the
    loop polls ``GET …/model`` until the answering model's ``n_trajectories`` covers that batch
    before it asks for the next proposal, and once more when the problems run out, so that
    after the loop the model covers every completed batch. It waits at most ``model_timeout``
    seconds each time; then it logs a warning and goes on with the model that answers.
    ``wait_for_model=False`` proposes at once (a proposal may then be scored by a model one
    batch behind, as when several robots share an experiment).

    **Progress** goes to the ``precond_client`` logger (``INFO``: each problem planned, each
    episode, skipped problem and model wait, and every wait before a retry with what it waits
    for; ``WARNING``: a start at its goal, a skipped problem, a model wait that timed out)
    and, with ``progress=``, to a callback receiving a :class:`Progress` after each event.
    When logging is not configured at all (no handler anywhere), the loop shows its ``INFO``
    lines on standard error itself while it runs (``verbose=False``: it does not); configured
    logging decides for itself. Where standard error is a terminal and ``tqdm`` is installed,
    a progress bar shows the problems done and what the loop waits for (``progress_bar=``:
    ``True`` always, ``False`` never). Counters: :attr:`episodes`, :attr:`posted`,
    :attr:`abandoned`, :attr:`no_plan`, :attr:`at_goal`, :attr:`deadline`, :attr:`failed`,
    :attr:`resumed`, and :attr:`model_version`.
    """

    def __init__(
        self,
        client: LearningClient,
        problems: Iterable[Problem],
        *,
        client_id: str,
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
        sleep: SleepFn = time.sleep,
    ) -> None:
        if deadline_attempts < 1 or transient_attempts < 1:
            raise ValueError("deadline_attempts and transient_attempts must be at least 1")
        self.client = client
        self.problems = problems
        self.client_id = client_id
        self.candidates = candidates
        self.models = models
        self.resume = resume
        self.skip_no_plan = skip_no_plan
        self.wait_for_model = wait_for_model
        self.model_timeout = model_timeout
        self.progress = progress
        self.deadline_attempts = deadline_attempts
        self.transient_attempts = transient_attempts
        self.progress_bar = progress_bar
        self.verbose = verbose
        self._sleep = sleep
        self.episodes = 0
        self.posted = 0
        self.abandoned = 0
        self.no_plan = 0
        self.at_goal = 0
        self.deadline = 0
        self.failed = 0
        self.resumed = 0
        self.skipped: list[Skipped] = []
        """Every problem skipped, in order, with its reason."""
        self.model_version: int | None = None
        """The latest MDE version seen (see :attr:`Progress.model_version`)."""
        self._problem = 0
        self._experiment: Experiment | None = None
        self._covered_iteration = 0
        """Completed batches the answering model is known to cover."""
        self._posted_iteration = 0
        """Completed batches after the latest post."""
        self._bar: Any = None

    def _report(
        self,
        event: str,
        proposal_id: int | None = None,
        result: TrajectoryCreated | None = None,
    ) -> None:
        if self._bar is not None:
            self._bar.set_postfix(
                posted=self.posted,
                skipped=len(self.skipped),
                model=self.model_version,
                refresh=False,
            )
        if self.progress is not None:
            self.progress(
                Progress(
                    event=event,
                    problem=self._problem,
                    episodes=self.episodes,
                    posted=self.posted,
                    abandoned=self.abandoned,
                    no_plan=self.no_plan,
                    at_goal=self.at_goal,
                    resumed=self.resumed,
                    model_version=self.model_version,
                    proposal_id=proposal_id,
                    result=result,
                    deadline=self.deadline,
                    failed=self.failed,
                )
            )

    def _show(self, what: str) -> None:
        """Says on the progress bar what the loop does now."""
        if self._bar is not None:
            self._bar.set_description_str(what)

    def _experiment_settings(self) -> Experiment:
        if self._experiment is None:
            self._experiment = self.client.get_experiment()
        return self._experiment

    def _context(self) -> _Context:
        return _Context(self._experiment_settings, self._sleep, self.transient_attempts)

    def _finish(self, ep: Episode) -> None:
        if ep.reported:
            self.posted += 1
            for r in ep.trajectories:
                self.model_version = r.model_version
                self._posted_iteration = max(self._posted_iteration, r.iteration)
            last = ep.trajectories[-1] if ep.trajectories else None
            ex = ep.execution
            if ex is not None and (ex.replans or len(ep.trajectories) != 1):
                log.info(
                    "episode %d: %s after %d steps, %d replans (proposals %s), max deviation "
                    "%.3g; %d trajectories stored",
                    self.episodes,
                    "goal reached" if ex.success else ex.status,
                    ex.steps,
                    ex.replans,
                    ", ".join(str(p) for p in ex.proposal_ids),
                    ex.max_deviation,
                    len(ep.stored_trajectory_ids),
                )
            elif last is not None:
                log.info(
                    "episode %d: proposal %d posted, %d transitions (max deviation %.3g%s), "
                    "%d trajectories, iteration %d, model version %d",
                    self.episodes,
                    ep.proposal.id,
                    last.n_transitions,
                    float(last.deviations.max()) if len(last.deviations) else 0.0,
                    ", partial" if last.partial else "",
                    last.n_trajectories,
                    last.iteration,
                    last.model_version,
                )
            self._report("posted", ep.proposal.id, last)
            return
        if not ep.abandoned:
            log.warning(
                "proposal %d was neither posted nor abandoned: abandoning it", ep.proposal.id
            )
            ep._abandon_quietly()
        self.abandoned += 1
        log.info("episode %d: proposal %d abandoned", self.episodes, ep.proposal.id)
        self._report("abandoned", ep.proposal.id)

    def _await_model(self) -> None:
        """Waits until the answering model covers every batch posted (see the class)."""
        if not self.wait_for_model or self._posted_iteration <= self._covered_iteration:
            return
        iteration = self._posted_iteration
        what = f"waiting for the fit after iteration {iteration}"
        self._show(what)
        t0 = time.monotonic()
        try:
            with _status.activity(what):
                needed = iteration * int(self._experiment_settings().learning["batch_size"])
                log.info(
                    "waiting for the model fitted after iteration %d (%d trajectories; "
                    "version %s answers)",
                    iteration,
                    needed,
                    self.model_version,
                )
                model = self.client.wait_for_model(needed, timeout=self.model_timeout)
        except TimeoutError as e:
            log.warning("%s: going on with the model that answers", e)
        except errors.PrecondError as e:
            if not errors.is_transient(e):
                raise
            log.warning("%s failed (%s): going on with the model that answers", what, e)
        else:
            self.model_version = model.version
            log.info(
                "model version %d covers %d trajectories (waited %.1f s)",
                model.version,
                model.n_trajectories,
                time.monotonic() - t0,
            )
            self._report("model")
        # Either way, wait for this iteration once only.
        self._covered_iteration = iteration

    def _propose(self, start: ArrayLike, goal: ArrayLike) -> Proposal:
        cands = None
        if self.candidates is not None:
            s, g = vec(start), vec(goal)
            cands = self.candidates(s, g)
        # A search past the deadline is counted here (deadline_attempts), not repeated by the
        # client as well.
        models = self.models(self.episodes) if callable(self.models) else self.models
        return self.client.propose(
            start,
            goal,
            client_id=self.client_id,
            candidates=cands,
            models=models,
            deadline_retries=0,
        )

    def _skip(
        self,
        index: int,
        start: ArrayLike,
        goal: ArrayLike,
        reason: str,
        error: errors.PrecondError | None,
    ) -> None:
        if reason == "no_plan":
            self.no_plan += 1
        elif reason == "at_goal":
            self.at_goal += 1
        elif reason == "deadline":
            self.deadline += 1
        else:
            self.failed += 1
        self.skipped.append(Skipped(index, vec(start), vec(goal), reason, error))
        self._report(reason)

    def _ask(self, index: int, start: ArrayLike, goal: ArrayLike) -> tuple[Episode | None, bool]:
        """One request for problem ``index``: ``(episode to execute or None, whether the
        problem is done with)``. Transient errors propagate (the caller counts them)."""
        try:
            proposal = self._propose(start, goal)
        except errors.Conflict as e:
            lease = e.lease
            if lease is None:
                raise
            held = self.client.get_proposal(int(lease["proposal_id"]))
            if not self.resume:
                log.info("abandoning proposal %d held from before", held.id)
                self.client.abandon(held.id)
                return None, False
            log.info("resuming proposal %d held from before", held.id)
            self.resumed += 1
            return Episode(held, True, self.client, _context=self._context()), False
        except errors.NoPlan as e:
            if not self.skip_no_plan:
                raise
            extensions = e.details.get("extensions") if isinstance(e.details, dict) else None
            log.info(
                "problem %d: no trajectory inside the precondition reaches the goal "
                "(%s extensions): skipped",
                index,
                extensions,
            )
            self._skip(index, start, goal, "no_plan", e)
            return None, True
        except errors.ValidationFailed as e:
            if not e.start_satisfies_goal:
                raise
            log.warning(
                "problem %d: the start %s already satisfies the goal %s: skipped",
                index,
                vec(start).tolist(),
                vec(goal).tolist(),
            )
            self._skip(index, start, goal, "at_goal", e)
            return None, True
        self.model_version = proposal.model_version
        return Episode(proposal, False, self.client, _context=self._context()), True

    def _problem_episodes(self, index: int, start: ArrayLike, goal: ArrayLike) -> Iterator[Episode]:
        """The episodes of one problem (a resumed lease first), skipping it when the server
        keeps failing (see the class)."""
        deadlines = 0
        failures = 0
        while True:
            self._await_model()
            what = f"problem {index}: planning"
            self._show(what)
            log.info("%s from %s to %s", what, vec(start).tolist(), vec(goal).tolist())
            try:
                with _status.activity(what):
                    episode, finished = self._ask(index, start, goal)
            except errors.DeadlineExceeded as e:
                deadlines += 1
                d = e.details if isinstance(e.details, dict) else {}
                if deadlines >= self.deadline_attempts:
                    log.warning(
                        "problem %d: skipped, %d searches passed the server's deadline of %s ms "
                        "(the last after %s extensions)",
                        index,
                        deadlines,
                        d.get("timeout_ms"),
                        d.get("extensions"),
                    )
                    self._skip(index, start, goal, "deadline", e)
                    return
                delay = errors.retry_after(e, 30.0)
                log.info(
                    "%s: the search passed the server's deadline of %s ms (%s extensions); "
                    "search %d/%d in %s",
                    what,
                    d.get("timeout_ms"),
                    d.get("extensions"),
                    deadlines + 1,
                    self.deadline_attempts,
                    _status.seconds(delay),
                )
                self._show(f"{what}, again in {_status.seconds(delay)}")
                self._sleep(delay)
                continue
            except errors.PrecondError as e:
                if not errors.is_transient(e):
                    raise
                failures += 1
                if failures >= self.transient_attempts:
                    log.warning("problem %d: skipped, the server kept failing: %s", index, e)
                    self._skip(index, start, goal, "failed", e)
                    return
                delay = errors.retry_after(e, 5.0)
                log.warning(
                    "%s failed (%s); attempt %d/%d in %s",
                    what,
                    e,
                    failures + 1,
                    self.transient_attempts,
                    _status.seconds(delay),
                )
                self._sleep(delay)
                continue
            if episode is not None:
                yield from self._run(episode)
            if finished:
                return

    def __iter__(self) -> Iterator[Episode]:
        total = len(self.problems) if isinstance(self.problems, Sized) else None
        bar = _status.progress_bar(self.progress_bar, total, "precond learn", "problem")
        self._bar = bar
        try:
            with _status.visible(self.verbose), _status.around_bar(bar):
                for index, (start, goal) in enumerate(self.problems):
                    self._problem = index
                    yield from self._problem_episodes(index, start, goal)
                    if bar is not None:
                        bar.update(1)
                self._await_model()
        finally:
            if bar is not None:
                bar.close()
            self._bar = None

    def _run(self, ep: Episode) -> Iterator[Episode]:
        self.episodes += 1
        self._show(f"problem {self._problem}: executing proposal {ep.proposal.id}")
        # Leaving the loop (break, an exception) leaves an unreported proposal leased: the
        # next loop of this client resumes it, as after a crash.
        yield ep
        self._finish(ep)
