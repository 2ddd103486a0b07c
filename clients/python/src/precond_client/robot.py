"""The robot's active-learning loop: propose, let the robot execute, post what happened.

::

    for episode in client.learn(problems):
        observed = robot.run(episode.start, episode.actions)   # (k + 1, n) states, start first
        episode.post(observed)                                 # partial if k < len(actions)

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

from numpy.typing import ArrayLike

from . import _status, errors
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
    """One proposal to execute; report it once with :meth:`post` (or :meth:`abandon`)."""

    proposal: Proposal
    """The proposal, with the trajectory to execute and the MDE's view of it."""
    resumed: bool
    """The lease was held from before (an earlier process of this client asked for it)."""
    _client: LearningClient = field(repr=False)
    result: TrajectoryCreated | None = None
    """The server's answer once posted."""
    abandoned: bool = False
    trajectories: list[TrajectoryCreated] = field(default_factory=list)
    """Every trajectory posted for this episode, in order."""
    stored_trajectory_ids: list[int] = field(default_factory=list)
    """The ids of every trajectory stored for this episode."""
    _context: _Context | None = field(default=None, repr=False)

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
        """Something was stored for it."""
        return bool(self.stored_trajectory_ids)

    def _ctx(self) -> _Context:
        if self._context is None:
            self._context = _Context(self._client.get_experiment)
        return self._context

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
            if last is not None:
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
        return self.client.propose(
            start, goal, client_id=self.client_id, candidates=cands, deadline_retries=0
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
