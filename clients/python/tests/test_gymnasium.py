"""The Gymnasium wrapper and collector on a small pure-Python environment against the real
server: episodes posted with their source (once, even when collected again), the precondition's
verdict and Safety-Gymnasium cost on every step, agreeing with the model's real error, and the
vector wrapper asking once per step."""

from __future__ import annotations

import json
from typing import Any

import httpx
import numpy as np
import pytest
from conftest import MakeServer

pytest.importorskip("gymnasium")

import gymnasium

from precond_client import Client
from precond_client.gymnasium import (
    CollectEpisodes,
    CollectVectorEpisodes,
    PreconditionVectorWrapper,
    PreconditionWrapper,
    judge,
)

pytestmark = pytest.mark.integration

ICE = (0.5, 0.7)
"""On this stretch a push goes 2.5 times as far as commanded."""
D_MAX = 0.03


class IcyLine(gymnasium.Env[np.ndarray, np.ndarray]):
    """A point on [0, 1] pushed by a ∈ [−0.1, 0.1]; on the ice it slides 2.5 times as far. The
    robot's model (the experiment's) is ``x' = x + a``."""

    def __init__(self, **_: Any) -> None:
        self.observation_space = gymnasium.spaces.Box(0.0, 1.0, (1,), np.float64)
        self.action_space = gymnasium.spaces.Box(-0.1, 0.1, (1,), np.float64)
        self.x = np.zeros(1)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.x = self.np_random.uniform(0.0, 1.0, 1)
        return self.x.copy(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        a = np.clip(np.asarray(action, dtype=np.float64), -0.1, 0.1)
        gain = 2.5 if ICE[0] <= self.x[0] < ICE[1] else 1.0
        self.x = np.clip(self.x + gain * a, 0.0, 1.0)
        return self.x.copy(), 0.0, False, False, {}


STEPS = 15
gymnasium.register(id="precond/IcyLine-v0", entry_point=IcyLine, max_episode_steps=STEPS)


def experiment(client: Client) -> None:
    client.create_experiment(
        name="icy line",
        d_max=D_MAX,
        # A quick fit: the debug server binary fits this in about a second.
        mde={"restarts": 0, "noise": "homoscedastic", "label_cap": 0},
        learning={"batch_size": 1000},
        domain={
            "kind": "custom",
            "state": {"names": ["x"], "low": [0.0], "high": [1.0]},
            "action": {"names": ["a"], "low": [-0.1], "high": [0.1]},
            "model": {"kind": "linear", "A": [[1.0]], "B": [[1.0]]},
        },
    )


def collect(client: Client, episodes: int, run: str, seed: int = 0) -> CollectEpisodes:
    env = CollectEpisodes(gymnasium.make("precond/IcyLine-v0"), client, label="random", run=run)
    for k in range(episodes):
        env.reset(seed=seed + k)
        env.action_space.seed(seed + k)
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            done = terminated or truncated
    env.close()
    return env


def test_episodes_are_posted_once_and_steps_judged_by_what_was_learned(
    make_server: MakeServer,
) -> None:
    server = make_server()
    with Client(server.url) as client:
        experiment(client)
        env = collect(client, 16, run="t1")
        assert (env.collected.episodes, env.collected.trajectories) == (16, 16)
        assert (env.collected.transitions, env.collected.dropped) == (16 * STEPS, 0)
        runs = list(client.runs())
        assert {(r.source.dataset, r.source.label) for r in runs if r.source} == {
            ("gymnasium:precond/IcyLine-v0", "random")
        }
        assert sorted(r.source.episode or 0 for r in runs if r.source) == list(range(16))
        # Collected again under the same run name and seeds: nothing new is stored.
        again = collect(client, 16, run="t1")
        assert again.collected.trajectory_ids == env.collected.trajectory_ids
        assert client.get_experiment().n_trajectories == 16
        client.refit()
        model = client.wait_for_model(16)

        wrapped = PreconditionWrapper(gymnasium.make("precond/IcyLine-v0"), client, cost=True)
        rng = np.random.default_rng(7)
        inside_errors: list[float] = []
        outside_errors: list[float] = []
        on_ice: list[bool] = []
        for k in range(8):
            obs, _ = wrapped.reset(seed=100 + k)
            done = False
            while not done:
                a = rng.uniform(-0.1, 0.1, 1)
                nxt, _, terminated, truncated, info = wrapped.step(a)
                p = info["precondition"]
                assert set(p) == {"mu", "sigma", "upper", "inside", "in_domain", "model_version"}
                assert p["model_version"] == model.version and p["in_domain"]
                assert p["upper"] == pytest.approx(p["mu"] + 2.0 * p["sigma"])
                assert info["cost"] == (0.0 if p["inside"] else 1.0)
                error = abs(float(nxt[0]) - float(np.clip(obs[0] + a[0], 0, 1)))
                (inside_errors if p["inside"] else outside_errors).append(error)
                if ICE[0] <= obs[0] < ICE[1] and abs(a[0]) > 0.05:
                    on_ice.append(p["inside"])
                obs, done = nxt, terminated or truncated
        # What is trusted is where the model is right; big pushes on the ice are not trusted.
        assert len(inside_errors) >= 100 and len(outside_errors) >= 5
        assert np.mean(np.array(inside_errors) < D_MAX) >= 0.95
        assert max(outside_errors) > D_MAX
        assert on_ice and not any(on_ice)


def test_out_of_domain_steps_are_not_trusted_and_not_asked(make_server: MakeServer) -> None:
    server = make_server()
    with Client(server.url) as client:
        experiment(client)
        shifted = PreconditionWrapper(
            gymnasium.make("precond/IcyLine-v0"), client, cost=True, state_fn=lambda o: o + 2.0
        )
        shifted.reset(seed=0)
        _, _, _, _, info = shifted.step(np.array([0.05]))
        p = info["precondition"]
        assert (p["inside"], p["in_domain"], p["model_version"], info["cost"]) == (
            False,
            False,
            None,
            1.0,
        )
        assert np.isnan(p["mu"]) and np.isnan(p["sigma"])
        # The collector posts only the parts inside the experiment's spaces.
        env = CollectEpisodes(
            gymnasium.make("precond/IcyLine-v0"),
            client,
            run="split",
            state_fn=lambda o: o * 1.6,  # leaves [0, 1] beyond x = 0.625
        )
        env.reset(seed=3)
        for a in [0.1] * 8 + [-0.1] * (STEPS - 8):
            _, _, _, truncated, _ = env.step(np.array([a]))
        assert truncated
        c = env.collected
        assert c.episodes == 1 and c.dropped > 0 and c.trajectories >= 1
        assert c.transitions + c.dropped == STEPS
        for r in client.runs():
            assert r.source is not None and r.source.first_step is not None
            t = client.get_trajectory(r.trajectory_id or 0)
            assert all(0.0 <= x.s[0] <= 1.0 for x in t.transitions)


def test_a_vector_environment_is_judged_once_per_step(make_server: MakeServer) -> None:
    server = make_server()
    with Client(server.url) as client:
        experiment(client)
        collect(client, 10, run="v")
        client.refit()
        client.wait_for_model(10)
        envs = gymnasium.vector.SyncVectorEnv(
            [lambda: gymnasium.make("precond/IcyLine-v0") for _ in range(3)]
        )
        wrapped = PreconditionVectorWrapper(envs, client, cost=True)
        obs, _ = wrapped.reset(seed=[1, 2, 3])
        actions = np.array([[0.09], [-0.02], [0.0]])
        _, _, _, _, info = wrapped.step(actions)
        p = info["precondition"]
        assert p["inside"].shape == (3,) and info["cost"].shape == (3,)
        direct = judge(client, obs, actions)
        np.testing.assert_array_equal(p["inside"], direct.inside)
        np.testing.assert_allclose(p["mu"], direct.mu)
        np.testing.assert_array_equal(info["cost"], np.where(direct.inside, 0.0, 1.0))


class CountingPoints(httpx.HTTPTransport):
    """Counts the points of every precondition query."""

    def __init__(self) -> None:
        super().__init__()
        self.queries: list[list[list[float]]] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.method == "POST" and request.url.path.endswith("/precondition"):
            self.queries.append([p["s"] for p in json.loads(request.content)["points"]])
        return super().handle_request(request)


LENGTHS = (3, 5, 8)
"""Episode lengths of the three sub-environments: they end at different steps."""


def vector_env(mode: str = "NextStep") -> gymnasium.vector.SyncVectorEnv:
    from functools import partial

    from gymnasium.vector import AutoresetMode

    return gymnasium.vector.SyncVectorEnv(
        [partial(gymnasium.make, "precond/IcyLine-v0", max_episode_steps=n) for n in LENGTHS],
        autoreset_mode=AutoresetMode(mode),
    )


def test_a_vector_environment_never_judges_an_autoreset_step(make_server: MakeServer) -> None:
    server = make_server()
    transport = CountingPoints()
    with Client(server.url, transport=transport) as client:
        experiment(client)
        wrapped = PreconditionVectorWrapper(vector_env(), client, cost=True)
        obs, _ = wrapped.reset(seed=[1, 2, 3])
        rng = np.random.default_rng(0)
        ended = np.zeros(3, dtype=bool)
        resets = np.zeros(3, dtype=int)
        for _ in range(12):
            transport.queries.clear()
            actions = rng.uniform(-0.1, 0.1, (3, 1))
            nxt, _, terminated, truncated, info = wrapped.step(actions)
            p = info["precondition"]
            # The step after an episode ended only reset that sub-environment.
            np.testing.assert_array_equal(p["autoreset"], ended)
            sent = [s for q in transport.queries for s in q]
            assert sent == [obs[k].tolist() for k in range(3) if not ended[k]]
            assert not p["inside"][ended].any() and np.isnan(p["mu"][ended]).all()
            assert not p["in_domain"][ended].any()
            np.testing.assert_array_equal(info["cost"][ended], 0.0)
            assert p["in_domain"][~ended].all() and np.isfinite(p["mu"][~ended]).all()
            resets += ended
            obs, ended = nxt, terminated | truncated
        # Each sub-environment reset itself along the way: every 4, 6 and 9 steps.
        np.testing.assert_array_equal(resets, [3, 2, 1])


@pytest.mark.parametrize("mode", ["NextStep", "SameStep"])
def test_vector_episodes_are_posted_whole_and_never_across_a_reset(
    make_server: MakeServer, mode: str
) -> None:
    server = make_server()
    with Client(server.url) as client:
        experiment(client)

        def collect(run: str) -> CollectVectorEpisodes:
            env = CollectVectorEpisodes(vector_env(mode), client, label="vec", run=run)
            env.reset(seed=[1, 2, 3])
            rng = np.random.default_rng(0)
            for _ in range(16):
                env.step(rng.uniform(-0.1, 0.1, (3, 1)))
            env.close()
            return env

        env = collect("v1")
        runs = list(client.runs())
        # The sub-environments' episodes, whole, each of its own length (an episode still
        # running is posted by close()). Same-step autoreset: 16 steps hold 5 episodes of 3
        # steps and one of 1, 3 of 5 and one of 1, 2 of 8. Next-step autoreset spends a step
        # on each reset, which is not recorded: 4 of 3; 2 of 5 and one of 4; one of 8 and one
        # of 7.
        lengths = sorted(r.length for r in runs)
        if mode == "SameStep":
            assert lengths == sorted([3] * 5 + [1] + [5] * 3 + [1] + [8] * 2)
        else:
            assert lengths == sorted([3] * 4 + [5, 5, 4] + [8, 7])
        assert env.collected.episodes == len(runs) == env.collected.trajectories
        for r in runs:
            t = client.get_trajectory(r.trajectory_id or 0)
            # One episode: each transition starts where the previous one ended, and each is a
            # step of the environment (never a reset's jump, never the reset observation).
            for a, b in zip(t.transitions, t.transitions[1:], strict=False):
                np.testing.assert_allclose(a.s_next, b.s)
            for x in t.transitions:
                gain = 2.5 if ICE[0] <= x.s[0] < ICE[1] else 1.0
                np.testing.assert_allclose(x.s_next, np.clip(x.s + gain * x.a, 0.0, 1.0))
            assert r.source is not None and r.source.label == "vec"
        # Collected again under the same run name and seeds: nothing new is stored.
        again = collect("v1")
        assert again.collected.trajectory_ids == env.collected.trajectory_ids
        assert client.get_experiment().n_trajectories == len(runs)
