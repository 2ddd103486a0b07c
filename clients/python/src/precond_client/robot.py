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
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from numpy.typing import ArrayLike

from . import errors
from .models import Array, Candidate, Proposal, TrajectoryCreated, Transition, mat, vec
from .models import transitions_from_states as _from_states

if TYPE_CHECKING:
    from .client import Client

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
    _client: Client = field(repr=False)
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


class Learner:
    """The loop over planning problems; iterate it for :class:`Episode` s.

    For each problem it asks for a proposal; on ``no_plan`` it skips the problem (counted in
    :attr:`no_plan`; ``skip_no_plan=False`` raises instead). An episode the caller did not report
    before asking for the next one is abandoned; one left unreported by leaving the loop stays
    leased, and the next loop of the same ``client_id`` resumes it. Counters: :attr:`episodes`,
    :attr:`posted`, :attr:`abandoned`, :attr:`no_plan`, :attr:`resumed`.
    """

    def __init__(
        self,
        client: Client,
        problems: Iterable[Problem],
        *,
        client_id: str,
        candidates: CandidateFn | None = None,
        resume: bool = True,
        skip_no_plan: bool = True,
    ) -> None:
        self.client = client
        self.problems = problems
        self.client_id = client_id
        self.candidates = candidates
        self.resume = resume
        self.skip_no_plan = skip_no_plan
        self.episodes = 0
        self.posted = 0
        self.abandoned = 0
        self.no_plan = 0
        self.resumed = 0

    def _finish(self, ep: Episode) -> None:
        if ep.result is not None:
            self.posted += 1
            return
        if not ep.abandoned:
            log.warning(
                "proposal %d was neither posted nor abandoned: abandoning it", ep.proposal.id
            )
            ep.abandon()
        self.abandoned += 1

    def _propose(self, start: ArrayLike, goal: ArrayLike) -> Proposal:
        cands = None
        if self.candidates is not None:
            s, g = vec(start), vec(goal)
            cands = self.candidates(s, g)
        return self.client.propose(start, goal, client_id=self.client_id, candidates=cands)

    def __iter__(self) -> Iterator[Episode]:
        for start, goal in self.problems:
            while True:
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
                except errors.NoPlan:
                    if not self.skip_no_plan:
                        raise
                    self.no_plan += 1
                    break
                yield from self._run(Episode(proposal, False, self.client))
                break

    def _run(self, ep: Episode) -> Iterator[Episode]:
        self.episodes += 1
        # Leaving the loop (break, an exception) leaves an unreported proposal leased: the
        # next loop of this client resumes it, as after a crash.
        yield ep
        self._finish(ep)
