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
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field

from numpy.typing import ArrayLike

from . import errors
from .models import Array, Candidate, Proposal, TrajectoryCreated, Transition, mat, vec
from .models import transitions_from_states as _from_states
from .protocols import LearningClient

log = logging.getLogger("precond_client")

Problem = tuple[ArrayLike, ArrayLike]
"""A planning problem: ``(start, goal)``."""

CandidateFn = Callable[[Array, Array], Sequence[Candidate]]
"""The client's own planner for a problem ``(start, goal)`` (client-side models)."""


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
        ``predicted`` is the ``k`` predictions of a client-side model.
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
        """Reports the execution as explicit transitions."""
        if self.result is not None:
            return self.result
        self.result = self._client.post_trajectory(
            transitions, proposal_id=self.proposal.id, partial=partial
        )
        return self.result

    def abandon(self) -> None:
        """Gives the proposal up (the robot could not execute it at all)."""
        if not self.done:
            self._client.abandon(self.proposal.id)
            self.abandoned = True


@dataclass(frozen=True)
class Progress:
    """Where a :class:`Learner` stands, handed to its ``progress`` callback after each event."""

    event: str
    """What just happened: ``posted`` (an episode's trajectory was stored), ``abandoned``,
    ``no_plan`` or ``at_goal`` (a problem skipped), ``model`` (the model covering the latest
    batch answers now)."""
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


ProgressFn = Callable[[Progress], None]
"""A callback receiving a :class:`Progress` after each event of the loop."""


class Learner:
    """The loop over planning problems; iterate it for :class:`Episode` s.

    For each problem it asks for a proposal. A problem whose start already satisfies its goal
    is skipped with a warning (counted in :attr:`at_goal`); on ``no_plan`` the problem is
    skipped (counted in :attr:`no_plan`; ``skip_no_plan=False`` raises instead). An episode the
    caller did not report before asking for the next one is abandoned; one left unreported by
    leaving the loop stays leased, and the next loop of the same ``client_id`` resumes it.

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

    **Progress** goes to the ``precond_client`` logger (``INFO``: each episode, skipped
    problem and model wait; ``WARNING``: a start at its goal, a model wait that timed out) and,
    with ``progress=``, to a callback receiving a :class:`Progress` after each event.
    Counters: :attr:`episodes`, :attr:`posted`, :attr:`abandoned`, :attr:`no_plan`,
    :attr:`at_goal`, :attr:`resumed`, and :attr:`model_version`.
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
    ) -> None:
        self.client = client
        self.problems = problems
        self.client_id = client_id
        self.candidates = candidates
        self.resume = resume
        self.skip_no_plan = skip_no_plan
        self.wait_for_model = wait_for_model
        self.model_timeout = model_timeout
        self.progress = progress
        self.episodes = 0
        self.posted = 0
        self.abandoned = 0
        self.no_plan = 0
        self.at_goal = 0
        self.resumed = 0
        self.model_version: int | None = None
        """The latest MDE version seen (see :attr:`Progress.model_version`)."""
        self._problem = 0
        self._batch_size: int | None = None
        self._covered_iteration = 0
        """Completed batches the answering model is known to cover."""
        self._posted_iteration = 0
        """Completed batches after the latest post."""

    def _report(
        self,
        event: str,
        proposal_id: int | None = None,
        result: TrajectoryCreated | None = None,
    ) -> None:
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
                )
            )

    def _finish(self, ep: Episode) -> None:
        if ep.result is not None:
            self.posted += 1
            r = ep.result
            self.model_version = r.model_version
            self._posted_iteration = max(self._posted_iteration, r.iteration)
            log.info(
                "episode %d: proposal %d posted, %d transitions (max deviation %.3g%s), "
                "%d trajectories, iteration %d, model version %d",
                self.episodes,
                ep.proposal.id,
                r.n_transitions,
                float(r.deviations.max()) if len(r.deviations) else 0.0,
                ", partial" if r.partial else "",
                r.n_trajectories,
                r.iteration,
                r.model_version,
            )
            self._report("posted", ep.proposal.id, r)
            return
        if not ep.abandoned:
            log.warning(
                "proposal %d was neither posted nor abandoned: abandoning it", ep.proposal.id
            )
            ep.abandon()
        self.abandoned += 1
        log.info("episode %d: proposal %d abandoned", self.episodes, ep.proposal.id)
        self._report("abandoned", ep.proposal.id)

    def _await_model(self) -> None:
        """Waits until the answering model covers every batch posted (see the class)."""
        if not self.wait_for_model or self._posted_iteration <= self._covered_iteration:
            return
        if self._batch_size is None:
            self._batch_size = int(self.client.get_experiment().learning["batch_size"])
        iteration = self._posted_iteration
        needed = iteration * self._batch_size
        log.info(
            "waiting for the model fitted after iteration %d (%d trajectories)", iteration, needed
        )
        t0 = time.monotonic()
        try:
            model = self.client.wait_for_model(needed, timeout=self.model_timeout)
        except TimeoutError as e:
            log.warning("%s: going on with the model that answers", e)
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
        return self.client.propose(start, goal, client_id=self.client_id, candidates=cands)

    def __iter__(self) -> Iterator[Episode]:
        for index, (start, goal) in enumerate(self.problems):
            self._problem = index
            while True:
                self._await_model()
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
                        continue
                    log.info("resuming proposal %d held from before", held.id)
                    self.resumed += 1
                    yield from self._run(Episode(held, True, self.client))
                    continue
                except errors.NoPlan as e:
                    if not self.skip_no_plan:
                        raise
                    self.no_plan += 1
                    extensions = (
                        e.details.get("extensions") if isinstance(e.details, dict) else None
                    )
                    log.info(
                        "problem %d: no trajectory inside the precondition reaches the goal "
                        "(%s extensions): skipped",
                        index,
                        extensions,
                    )
                    self._report("no_plan")
                    break
                except errors.ValidationFailed as e:
                    if not e.start_satisfies_goal:
                        raise
                    self.at_goal += 1
                    log.warning(
                        "problem %d: the start %s already satisfies the goal %s: skipped",
                        index,
                        vec(start).tolist(),
                        vec(goal).tolist(),
                    )
                    self._report("at_goal")
                    break
                self.model_version = proposal.model_version
                yield from self._run(Episode(proposal, False, self.client))
                break
        self._await_model()

    def _run(self, ep: Episode) -> Iterator[Episode]:
        self.episodes += 1
        # Leaving the loop (break, an exception) leaves an unreported proposal leased: the
        # next loop of this client resumes it, as after a crash.
        yield ep
        self._finish(ep)
