"""Gymnasium: the precondition's verdict on every step an agent takes, and its episodes posted
as trajectories. Needs ``gymnasium`` (``pip install 'precond-client[gymnasium]'``).

- :class:`PreconditionWrapper` adds ``info["precondition"]`` to each step: ``mu``, ``sigma``,
  ``upper = μ + βσ`` and ``inside = upper < d_max`` for the (observation, action) just taken,
  and optionally Safety-Gymnasium's ``info["cost"]`` (1 outside the precondition, else 0).
  One precondition query per step (one point, on a kept-alive connection);
  :class:`PreconditionVectorWrapper` asks once per step for every sub-environment of a vector
  environment, and :func:`judge` judges whole recorded episodes in one query.
- :class:`CollectEpisodes` records each episode's ``(observation, action, next observation)``
  and posts it when it ends as one trajectory, labelled by the experiment's model, with
  ``source = {"dataset": "gymnasium:<env id>", "episode": k, "label": ...}`` and the
  ``Idempotency-Key`` ``gym-<run>-<episode>-<part>`` (give ``run`` to make a re-run after a
  crash post nothing twice); :class:`CollectVectorEpisodes` does the same for every
  sub-environment of a vector environment.

**Vector environments reset themselves.** With Gymnasium's default next-step autoreset
(``autoreset_mode`` ``NextStep``), the step after a sub-environment's episode ended
(``terminated`` or ``truncated``) only resets it: its action is ignored and its observation is
the new episode's first. Such a step is never judged (``info["precondition"]["autoreset"]`` is
true there, ``inside`` false, ``mu``/``sigma`` NaN, ``cost`` 0: nothing was done) nor recorded,
so no transition ever joins an episode's last observation to the next episode's first. With
``SameStep`` autoreset the observation returned with ``terminated``/``truncated`` is already the
next episode's first: the collector ends the episode at ``info["final_obs"]`` instead.

The experiment's state is the environment's observation and its action the environment's
action, flattened, unless ``state_fn``/``action_fn`` map them (e.g. to a subset of the
observation). A state-action outside the experiment's spaces (the observation left the box
the experiment declares) is never trusted: the wrapper answers ``inside=False`` with ``mu`` and
``sigma`` NaN and ``in_domain=False`` without asking the server, and the collector splits the
episode there (posting the parts inside, each with its ``first_step``) since the server would
refuse such a transition.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, SupportsFloat, cast

import gymnasium
import numpy as np
from numpy.typing import NDArray

from .models import Array, Experiment, Source

if TYPE_CHECKING:
    from .client import Client

log = logging.getLogger("precond_client")

StateFn = Callable[[Any], Any]
"""Maps an observation (or action) to the experiment's state (or action) vector."""


def _flat(x: Any) -> Array:
    return np.asarray(x, dtype=np.float64).reshape(-1)


@dataclass(frozen=True)
class Box:
    """The experiment's state and action boxes, to tell which points it can judge."""

    state_low: Array
    state_high: Array
    action_low: Array
    action_high: Array
    discrete_actions: Array | None

    @classmethod
    def of(cls, exp: Experiment) -> Box:
        return cls(
            exp.state_space.low,
            exp.state_space.high,
            exp.action_space.low,
            exp.action_space.high,
            exp.action_space.values,
        )

    def contains(self, s: Array, a: Array) -> bool:
        """Whether ``(s, a)`` lies in the experiment's spaces (finite, right sizes, in the
        bounds; a discrete action one of its values)."""
        if s.shape != self.state_low.shape or a.shape != self.action_low.shape:
            return False
        if not (np.all(np.isfinite(s)) and np.all(np.isfinite(a))):
            return False
        if np.any(s < self.state_low) or np.any(s > self.state_high):
            return False
        if self.discrete_actions is not None:
            return bool(np.any(np.all(np.isclose(self.discrete_actions, a), axis=1)))
        return not (np.any(a < self.action_low) or np.any(a > self.action_high))


@dataclass(frozen=True)
class Verdicts:
    """Precondition verdicts for several state-actions, one entry per point."""

    mu: Array
    sigma: Array
    upper: Array
    inside: NDArray[np.bool_]
    in_domain: NDArray[np.bool_]
    """Whether the point lies in the experiment's spaces (the others are never inside)."""
    model_version: int | None
    """The MDE version that answered (``None`` when no point was asked)."""

    def info(self, k: int | None, with_cost: bool) -> dict[str, Any]:
        """Point ``k``'s entry of ``info`` (Python numbers), or with ``k=None`` every point's
        (arrays, one entry per point, as a vector environment's): ``{"precondition": {...}}``
        and, with ``with_cost``, ``"cost"`` (0.0 inside the precondition, else 1.0)."""

        def at(column: NDArray[Any]) -> Any:
            return column if k is None else column[k].item()

        out: dict[str, Any] = {
            "precondition": {
                "mu": at(self.mu),
                "sigma": at(self.sigma),
                "upper": at(self.upper),
                "inside": at(self.inside),
                "in_domain": at(self.in_domain),
                "model_version": self.model_version,
            }
        }
        if with_cost:
            cost = np.where(at(self.inside), 0.0, 1.0)
            out["cost"] = cost if k is None else cost.item()
        return out


def judge(
    client: Client,
    states: Any,
    actions: Any,
    *,
    beta: float | None = None,
    box: Box | None = None,
) -> Verdicts:
    """Judges state-actions ``(N, n)``, ``(N, m)`` in one query (points outside the
    experiment's spaces are not asked: ``inside=False``, ``mu``/``sigma`` NaN)."""
    s = np.asarray(states, dtype=np.float64)
    a = np.asarray(actions, dtype=np.float64)
    box = box or Box.of(client.get_experiment())
    s = s.reshape(len(s), -1) if len(s) else np.zeros((0, len(box.state_low)))
    a = a.reshape(len(a), -1) if len(a) else np.zeros((0, len(box.action_low)))
    ok = np.array([box.contains(si, ai) for si, ai in zip(s, a, strict=True)], dtype=np.bool_)
    n = len(s)
    mu = np.full(n, np.nan)
    sigma = np.full(n, np.nan)
    upper = np.full(n, np.nan)
    inside = np.zeros(n, dtype=np.bool_)
    version = None
    if ok.any():
        p = client.precondition((s[ok], a[ok]), beta=beta)
        mu[ok], sigma[ok], upper[ok], inside[ok] = p.mu, p.sigma, p.upper, p.inside
        version = p.model_version
    return Verdicts(mu, sigma, upper, inside, ok, version)


class _Judging:
    """What :class:`PreconditionWrapper` and :class:`PreconditionVectorWrapper` judge each
    step with: their arguments, the experiment's boxes and the observation last seen."""

    def _judge_with(
        self, client: Client, beta: float | None, cost: bool, state_fn: StateFn, action_fn: StateFn
    ) -> None:
        self.client = client
        self.beta = beta
        self.cost = cost
        self.state_fn = state_fn
        self.action_fn = action_fn
        self.box = Box.of(client.get_experiment())
        self._obs: Any = None


class PreconditionWrapper(gymnasium.Wrapper[Any, Any, Any, Any], _Judging):
    """Adds the precondition's verdict on each step's (observation, action) to ``info``.

    Args:
        env: The environment.
        client: A client whose current experiment models this environment.
        beta: β of the verdicts (default the experiment's test β).
        cost: Also set ``info["cost"]`` = 1.0 when the step was outside the precondition,
            else 0.0 (Safety-Gymnasium's convention; a constrained-RL algorithm then treats
            leaving what is trusted as a cost).
        state_fn: Observation → the experiment's state (default: flattened).
        action_fn: Action → the experiment's action (default: flattened).
    """

    def __init__(
        self,
        env: gymnasium.Env[Any, Any],
        client: Client,
        *,
        beta: float | None = None,
        cost: bool = False,
        state_fn: StateFn = _flat,
        action_fn: StateFn = _flat,
    ) -> None:
        super().__init__(env)
        self._judge_with(client, beta, cost, state_fn, action_fn)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        self._obs = obs
        return obs, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        verdict = judge(
            self.client,
            [_flat(self.state_fn(self._obs))],
            [_flat(self.action_fn(action))],
            beta=self.beta,
            box=self.box,
        )
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._obs = obs
        return obs, reward, terminated, truncated, {**info, **verdict.info(0, self.cost)}


def _autoreset_mode(env: Any) -> str:
    """The vector environment's autoreset mode: ``NextStep`` (Gymnasium's default),
    ``SameStep`` or ``Disabled``."""
    mode = (getattr(env, "metadata", None) or {}).get("autoreset_mode", "NextStep")
    return str(getattr(mode, "value", mode))


def _ended(terminated: Any, truncated: Any, n: int) -> NDArray[np.bool_]:
    return np.logical_or(
        np.asarray(terminated, dtype=np.bool_).reshape(n),
        np.asarray(truncated, dtype=np.bool_).reshape(n),
    )


class PreconditionVectorWrapper(gymnasium.vector.VectorWrapper, _Judging):
    """:class:`PreconditionWrapper` for a vector environment: one query per step for every
    sub-environment. ``info["precondition"]`` holds arrays (one entry per sub-environment:
    ``mu``, ``sigma``, ``upper``, ``inside``, ``in_domain``, ``autoreset``) and
    ``info["cost"]`` an array.

    With the default next-step autoreset, the step after an episode ended only resets its
    sub-environment (its action is not taken): that entry is not judged and not sent
    (``autoreset`` true, ``inside`` false, ``mu``/``sigma``/``upper`` NaN, ``cost`` 0).
    """

    def __init__(
        self,
        env: gymnasium.vector.VectorEnv[Any, Any, Any],
        client: Client,
        *,
        beta: float | None = None,
        cost: bool = False,
        state_fn: StateFn = _flat,
        action_fn: StateFn = _flat,
    ) -> None:
        super().__init__(env)
        self._judge_with(client, beta, cost, state_fn, action_fn)
        self._next_step_reset = _autoreset_mode(env) == "NextStep"
        self._autoreset: NDArray[np.bool_] = np.zeros(self.num_envs, dtype=np.bool_)

    def reset(
        self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        # Vector environments take a seed per sub-environment too.
        obs, info = self.env.reset(seed=cast(Any, seed), options=options)
        self._obs = obs
        mask = (options or {}).get("reset_mask")
        if mask is None:
            self._autoreset[:] = False
        else:
            self._autoreset[np.asarray(mask, dtype=np.bool_)] = False
        return obs, info

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        n = self.num_envs
        resetting = self._autoreset.copy()
        taken = np.flatnonzero(~resetting)
        # Judged before the step, as PreconditionWrapper does; an autoreset entry is not sent.
        judged = judge(
            self.client,
            [_flat(self.state_fn(self._obs[k])) for k in taken],
            [_flat(self.action_fn(actions[k])) for k in taken],
            beta=self.beta,
            box=self.box,
        )
        obs, reward, terminated, truncated, info = self.env.step(actions)
        self._obs = obs
        if self._next_step_reset:
            self._autoreset = _ended(terminated, truncated, n)
        mu, sigma, upper = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        inside, in_domain = np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_)
        mu[taken], sigma[taken], upper[taken] = judged.mu, judged.sigma, judged.upper
        inside[taken], in_domain[taken] = judged.inside, judged.in_domain
        v = Verdicts(mu, sigma, upper, inside, in_domain, judged.model_version)
        out = v.info(None, self.cost)
        out["precondition"]["autoreset"] = resetting
        if self.cost:
            out["cost"] = np.where(inside | resetting, 0.0, 1.0)
        return obs, reward, terminated, truncated, {**info, **out}


@dataclass
class Collected:
    """What :class:`CollectEpisodes` posted."""

    episodes: int = 0
    """Episodes that ended."""
    trajectories: int = 0
    """Trajectories posted (an episode leaving the experiment's spaces, or longer than
    ``max_transitions``, is posted in parts)."""
    transitions: int = 0
    """Transitions posted."""
    dropped: int = 0
    """Steps not posted: outside the experiment's spaces."""
    trajectory_ids: list[int] = field(default_factory=list)


Step = tuple[Array, Array, Array]
"""A recorded ``(state, action, next state)``."""


class _Poster:
    """Posts recorded episodes as trajectories, in parts inside the experiment's spaces (the
    collectors' common part)."""

    def __init__(
        self,
        client: Client,
        *,
        label: str | None,
        run: str | None,
        dataset: str,
        max_transitions: int,
        min_transitions: int,
    ) -> None:
        self.client = client
        self.label = label
        self.run = run or uuid.uuid4().hex[:12]
        self.dataset = dataset
        self.max_transitions = max(1, max_transitions)
        self.min_transitions = max(1, min_transitions)
        self.box = Box.of(client.get_experiment())
        self.collected = Collected()
        self.episode = 0
        """The index the next episode posted gets (episodes posted so far)."""

    def post(self, steps: list[Step]) -> list[int]:
        """Posts one episode (in parts inside the experiment's spaces); returns the
        trajectory ids."""
        self.collected.episodes += 1
        ids: list[int] = []
        part: list[dict[str, Any]] = []
        first = 0

        def flush() -> None:
            nonlocal part
            if len(part) >= self.min_transitions:
                key = f"gym-{self.run}-{self.episode}-{first}"
                created = self.client.post_trajectory(
                    part,
                    idempotency_key=key,
                    source=Source(self.dataset, self.episode, first, self.label),
                )
                ids.append(created.id)
                self.collected.trajectories += 1
                self.collected.transitions += len(part)
            else:
                self.collected.dropped += len(part)
            part = []

        for k, (s, a, s_next) in enumerate(steps):
            usable = self.box.contains(s, a) and bool(np.all(np.isfinite(s_next)))
            usable = usable and s_next.shape == s.shape
            if not usable or len(part) >= self.max_transitions:
                flush()
            if not usable:
                self.collected.dropped += 1
                first = k + 1
                continue
            if not part:
                first = k
            part.append({"s": s.tolist(), "a": a.tolist(), "s_next": s_next.tolist()})
        flush()
        self.collected.trajectory_ids += ids
        self.episode += 1
        return ids


def _dataset_name(env: Any, dataset: str | None) -> str:
    if dataset is not None:
        return dataset
    spec = getattr(env, "spec", None)
    if spec is None:
        # A vector environment made by gymnasium.make_vec has the sub-environments' spec.
        spec = getattr(getattr(env, "unwrapped", env), "spec", None)
    return f"gymnasium:{spec.id if spec is not None else type(env).__name__}"


class CollectEpisodes(gymnasium.Wrapper[Any, Any, Any, Any]):
    """Posts each episode the environment runs as one trajectory when it ends (terminated or
    truncated), labelled on ingest by the experiment's model, with its source; see the module
    docs.

    Args:
        env: The environment.
        client: A client whose current experiment models this environment.
        label: ``source.label`` of every trajectory.
        run: This collection's name in the idempotency keys; default a random one. Give the
            same ``run`` (and the same episodes, e.g. by seeding ``reset``) to make a
            repeated collection post nothing twice.
        dataset: ``source.dataset``; default ``gymnasium:<env id>``.
        state_fn: Observation → the experiment's state (default: flattened).
        action_fn: Action → the experiment's action (default: flattened).
        max_transitions: Transitions per posted trajectory (the server's
            ``--max-transitions``).
        min_transitions: Parts shorter than this are not posted (counted as dropped).
    """

    def __init__(
        self,
        env: gymnasium.Env[Any, Any],
        client: Client,
        *,
        label: str | None = None,
        run: str | None = None,
        dataset: str | None = None,
        state_fn: StateFn = _flat,
        action_fn: StateFn = _flat,
        max_transitions: int = 10_000,
        min_transitions: int = 1,
    ) -> None:
        super().__init__(env)
        self.client = client
        self.state_fn = state_fn
        self.action_fn = action_fn
        self._poster = _Poster(
            client,
            label=label,
            run=run,
            dataset=_dataset_name(env, dataset),
            max_transitions=max_transitions,
            min_transitions=min_transitions,
        )
        self._obs: Any = None
        self._steps: list[Step] = []

    @property
    def collected(self) -> Collected:
        """What was posted so far."""
        return self._poster.collected

    @property
    def run(self) -> str:
        """This collection's name in the idempotency keys."""
        return self._poster.run

    @property
    def dataset(self) -> str:
        """``source.dataset`` of every trajectory."""
        return self._poster.dataset

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        if self._steps:
            # An episode reset before it ended: posted as it is.
            self._post()
        obs, info = self.env.reset(seed=seed, options=options)
        self._obs = obs
        return obs, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._steps.append(
            (
                _flat(self.state_fn(self._obs)),
                _flat(self.action_fn(action)),
                _flat(self.state_fn(obs)),
            )
        )
        self._obs = obs
        if terminated or truncated:
            info = {**info, "precond_trajectories": self._post()}
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        if self._steps:
            self._post()
        super().close()

    def _post(self) -> list[int]:
        """Posts the recorded episode (in parts inside the experiment's spaces); returns the
        trajectory ids."""
        steps, self._steps = self._steps, []
        return self._poster.post(steps)


class CollectVectorEpisodes(gymnasium.vector.VectorWrapper):
    """:class:`CollectEpisodes` for a vector environment: every sub-environment's episodes
    are recorded and each is posted when it ends, numbered in the order they end (so
    collecting again with the same ``run`` and seeds posts nothing twice). An autoreset step
    (see the module docs) is never recorded; with ``SameStep`` autoreset an episode ends at
    ``info["final_obs"]``. Arguments as :class:`CollectEpisodes`'; ``info["precond_trajectories"]``
    holds, per sub-environment, the ids posted at this step."""

    def __init__(
        self,
        env: gymnasium.vector.VectorEnv[Any, Any, Any],
        client: Client,
        *,
        label: str | None = None,
        run: str | None = None,
        dataset: str | None = None,
        state_fn: StateFn = _flat,
        action_fn: StateFn = _flat,
        max_transitions: int = 10_000,
        min_transitions: int = 1,
    ) -> None:
        super().__init__(env)
        self.client = client
        self.state_fn = state_fn
        self.action_fn = action_fn
        self._poster = _Poster(
            client,
            label=label,
            run=run,
            dataset=_dataset_name(env, dataset),
            max_transitions=max_transitions,
            min_transitions=min_transitions,
        )
        self._mode = _autoreset_mode(env)
        self._obs: Any = None
        self._steps: list[list[Step]] = [[] for _ in range(self.num_envs)]
        self._autoreset: NDArray[np.bool_] = np.zeros(self.num_envs, dtype=np.bool_)

    @property
    def collected(self) -> Collected:
        """What was posted so far."""
        return self._poster.collected

    @property
    def run(self) -> str:
        """This collection's name in the idempotency keys."""
        return self._poster.run

    def reset(
        self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        mask = (options or {}).get("reset_mask")
        which = (
            np.ones(self.num_envs, dtype=np.bool_)
            if mask is None
            else np.asarray(mask, dtype=np.bool_)
        )
        for k in np.flatnonzero(which):
            if self._steps[k]:
                # An episode reset before it ended: posted as it is.
                self._post(int(k))
        obs, info = self.env.reset(seed=cast(Any, seed), options=options)
        self._obs = obs
        self._autoreset[which] = False
        return obs, info

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        n = self.num_envs
        obs, reward, terminated, truncated, info = self.env.step(actions)
        ended = _ended(terminated, truncated, n)
        final_obs = info.get("final_obs") if self._mode == "SameStep" else None
        posted: list[list[int]] = [[] for _ in range(n)]
        for k in range(n):
            if self._autoreset[k]:
                continue  # a reset, not a step: the action was ignored
            s_next = obs[k]
            if ended[k] and final_obs is not None:
                s_next = final_obs[k]
            self._steps[k].append(
                (
                    _flat(self.state_fn(self._obs[k])),
                    _flat(self.action_fn(actions[k])),
                    _flat(self.state_fn(s_next)),
                )
            )
            if ended[k]:
                posted[k] = self._post(k)
        self._obs = obs
        self._autoreset = ended if self._mode == "NextStep" else np.zeros(n, dtype=np.bool_)
        if any(posted):
            info = {**info, "precond_trajectories": posted}
        return obs, reward, terminated, truncated, info

    def close(self, **kwargs: Any) -> None:
        for k in range(self.num_envs):
            if self._steps[k]:
                self._post(k)
        super().close(**kwargs)

    def _post(self, k: int) -> list[int]:
        steps, self._steps[k] = self._steps[k], []
        return self._poster.post(steps)
