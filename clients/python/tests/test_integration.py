"""Integration tests: the client against the real precond server binary over loopback, with a
remote model served by ``serve_model`` and a server restart in the middle of the loop."""

from __future__ import annotations

import datetime
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import MakeServer

from precond_client import (
    Candidate,
    Client,
    Conflict,
    Forbidden,
    ModelUnavailable,
    NoPlan,
    NotFound,
    Unauthorized,
    ValidationFailed,
    serve_model,
    transitions_from_states,
)
from precond_client.models import Array, Proposal, Transition

pytestmark = pytest.mark.integration

ICE_LOW, ICE_HIGH, SLIP = 0.45, 0.75, 1.8


def model(states: Array, actions: Array) -> Array:
    """The robot's model: the point moves by the action (clipped to the table)."""
    return np.clip(states + actions, 0.0, 1.0)


def true_step(s: Array, a: Array) -> Array:
    """The true world: on the icy band ``ICE_LOW ≤ x ≤ ICE_HIGH`` the point slides further."""
    gain = SLIP if ICE_LOW <= s[0] <= ICE_HIGH else 1.0
    return np.clip(s + gain * a, 0.0, 1.0)


def execute(start: Array, actions: Array) -> Array:
    """Runs actions open loop in the true world; the observed states, the start first."""
    states = [np.asarray(start, dtype=np.float64)]
    for a in actions:
        states.append(true_step(states[-1], a))
    return np.array(states)


def settings(url: str, name: str) -> dict[str, Any]:
    return {
        "name": name,
        "d_max": 0.05,
        "seed": 3,
        "domain": {
            "kind": "custom",
            "state": {"names": ["x", "y"], "low": [0, 0], "high": [1, 1]},
            "action": {"names": ["dx", "dy"], "low": [-0.1, -0.1], "high": [0.1, 0.1]},
            "goal": {"radius": 0.08},
            "model": {"kind": "remote", "url": url, "timeout_ms": 5000},
        },
        "mde": {"noise": "homoscedastic", "restarts": 0},
        "learning": {"batch_size": 2, "iterations": 100, "n_candidates": 3, "max_extensions": 2000},
    }


def problems(n: int, seed: int = 0) -> list[tuple[Array, Array]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        start = np.array([rng.uniform(0.05, 0.3), rng.uniform(0.1, 0.9)])
        goal = np.array([rng.uniform(0.7, 0.95), rng.uniform(0.1, 0.9)])
        out.append((start, goal))
    return out


def test_a_loop_survives_server_and_robot_restarts_without_duplicates_or_losses(
    make_server: MakeServer,
) -> None:
    with serve_model(model, "127.0.0.1", 0) as served:
        server = make_server([f"http://127.0.0.1:{served.port}/"])
        client = Client(server.url, timeout=60, client_id="arm-1", backoff=0.05, retries=40)
        exp = client.ensure_experiment("restart loop", settings(served.url, "ignored"))
        assert exp.domain["model"]["url"] == served.url
        assert client.ensure_experiment("restart loop").id == exp.id

        posted: dict[int, int] = {}  # proposal id -> trajectory id
        lengths: dict[int, int] = {}
        learner = client.learn(problems(8))
        for i, ep in enumerate(learner):
            observed = execute(ep.start, ep.actions)
            if i == 2:
                # The server goes down while the robot executes; it is back a moment later,
                # and the post waits for it.
                server.stop()
                restarter = threading.Timer(0.5, server.start)
                restarter.start()
                created = ep.post(observed)
                restarter.join()
            else:
                created = ep.post(observed)
            assert not created.replayed
            posted[ep.proposal.id] = created.id
            lengths[created.id] = created.n_transitions
            if i == 3:
                # The answer was lost: the robot posts the same execution again after a restart.
                server.restart()
                again = client.post_trajectory(
                    [
                        {"s": s.tolist(), "a": a.tolist(), "s_next": n.tolist()}
                        for s, a, n in zip(observed[:-1], ep.actions, observed[1:], strict=True)
                    ],
                    proposal_id=ep.proposal.id,
                )
                assert again.replayed and again.id == created.id
        assert learner.episodes >= 4, "the loop must reach both restarts"
        assert server.starts == 3
        assert served.calls > 0  # the server planned and labelled with the Python model
        # ... in raw little-endian arrays: the handshake settled the binary encoding.
        assert served.binary_calls == served.calls

        # The robot's process dies holding a lease for one problem ...
        held = client.propose([0.1, 0.2], [0.35, 0.2])
        # ... and a new process of the same robot asks for another: it is handed the held one
        # first, then its own.
        robot2 = Client(server.url, timeout=60, client_id="arm-1", experiment_id=exp.id)
        seen = []
        for ep in robot2.learn([([0.1, 0.8], [0.35, 0.8])]):
            seen.append((ep.proposal.id, ep.resumed))
            created = ep.post(execute(ep.start, ep.actions))
            posted[ep.proposal.id] = created.id
            lengths[created.id] = created.n_transitions
        assert seen[0] == (held.id, True)
        assert len(seen) == 2 and not seen[1][1]

        # Every execution is stored exactly once.
        exp = client.get_experiment()
        assert exp.n_trajectories == len(posted) == len(set(posted.values()))
        stored = list(client.transitions(page_size=7))
        assert len(stored) == exp.n_transitions == sum(lengths.values())
        by_traj: dict[int, int] = {}
        for t in stored:
            by_traj[t.trajectory_id] = by_traj.get(t.trajectory_id, 0) + 1
        assert by_traj == lengths
        for pid in posted:
            assert client.get_proposal(pid).status == "executed"
        # The server labelled with the served model: s_pred is the Python model's prediction,
        # and deviations are non-zero only on the ice.
        s = np.array([t.s for t in stored])
        a = np.array([t.a for t in stored])
        s_next = np.array([t.s_next for t in stored])
        s_pred = np.array([t.s_pred for t in stored])
        dev = np.array([t.deviation for t in stored])
        np.testing.assert_allclose(s_pred, model(s, a), atol=1e-12)
        np.testing.assert_allclose(dev, np.linalg.norm(s_pred - s_next, axis=1), rtol=1e-9)
        on_ice = (s[:, 0] >= ICE_LOW) & (s[:, 0] <= ICE_HIGH)
        assert on_ice.any() and (~on_ice).any()
        np.testing.assert_allclose(dev[~on_ice], 0.0, atol=1e-9)
        assert dev[on_ice].max() > 0.05


def test_model_precondition_refit_and_plan_through_the_client(make_server: MakeServer) -> None:
    with serve_model(model, "127.0.0.1", 0) as served:
        server = make_server([f"http://127.0.0.1:{served.port}/"])
        client = Client(server.url, timeout=60)
        client.create_experiment(settings(served.url, "queries"))
        prior = client.model()
        assert prior.source == "prior" and prior.label_cap is None

        rng = np.random.default_rng(1)
        for _ in range(4):
            start = rng.uniform(0.1, 0.9, size=2)
            actions = rng.uniform(-0.1, 0.1, size=(8, 2))
            states = execute(start, actions)
            client.post_trajectory(transitions_from_states(states, actions))
        fitted = client.refit()
        assert fitted.source == "fit" and fitted.n_train == 32 and fitted.version >= 1
        # One per feature: x, y, dx, dy, the action's length, then the remote model's
        # prediction (x̂, ŷ) and the predicted move's length (on by default for a model
        # the service asks itself).
        assert len(fitted.feature_names) == 8, fitted.feature_names
        # The exact GP (the default at this size) has one set of hyperparameters.
        assert fitted.hyperparameters is not None and prior.hyperparameters is not None
        assert len(fitted.hyperparameters.length_scales) == 8
        assert fitted.label_cap in (2.0, 5.0, 0.0)  # chosen at the fit ("auto")
        assert len(fitted.raw["label_cap_trials"]) == 3
        # The prior already names the kernel every fit of the experiment uses.
        assert fitted.hyperparameters.kernel in ("matern12", "matern32", "matern52")
        assert prior.hyperparameters.kernel == fitted.hyperparameters.kernel

        grid = np.array([[x, 0.5, 0.1, 0.0] for x in (0.2, 0.6, 0.9)])
        ans = client.precondition(grid, beta=0.0)
        assert ans.mu.shape == (3,) and ans.inside.shape == (3,)
        assert ans.model_version == fitted.version
        np.testing.assert_allclose(ans.upper, ans.mu, atol=1e-12)  # β = 0
        split = client.precondition((grid[:, :2], grid[:, 2:]), beta=2.0)
        np.testing.assert_allclose(split.upper, split.mu + 2.0 * split.sigma, rtol=1e-9)

        plan = client.plan([0.1, 0.2], [0.3, 0.2], beta=-3.0)
        assert plan.found and plan.trajectory is not None
        assert plan.trajectory.states.shape[1] == 2
        mine = Candidate([[0.1, 0.2], [0.2, 0.2], [0.3, 0.2]], [[0.1, 0.0], [0.1, 0.0]])
        scored = client.plan([0.1, 0.2], [0.3, 0.2], beta=-3.0, candidates=[mine])
        assert scored.candidates is not None and scored.candidates[0].reaches_goal
        # Nothing is trusted at β = 1000, so a search spends the whole budget it asks for.
        short = client.plan([0.1, 0.2], [0.9, 0.8], beta=1000.0, max_extensions=7)
        assert not short.found and short.extensions == 7


def test_every_further_model_labels_every_posted_transition(make_server: MakeServer) -> None:
    """Two models of one robot: the domain's (served, ``s + a``) and a coarse one that ignores
    the action, declared as a further model; each labels every transition, and a further model
    that cannot answer leaves only its own label missing."""
    with serve_model(model, "127.0.0.1", 0) as served:
        server = make_server([f"http://127.0.0.1:{served.port}/"])
        client = Client(server.url, timeout=60)
        still = {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[0, 0], [0, 0]]}
        gone = {"kind": "remote", "url": f"http://127.0.0.1:{served.port}/nothing-here"}
        exp = client.create_experiment(
            settings(served.url, "two models"),
            models=[
                {"name": "still", "cost": 0.01, "model": still},
                {"name": "gone", "model": gone},
            ],
        )
        assert exp.models is not None
        assert [m["name"] for m in exp.models] == ["still", "gone"]
        assert exp.models[0]["cost"] == 0.01 and exp.models[1]["cost"] == 1.0

        start = np.array([0.3, 0.5])
        actions = np.array([[0.1, 0.0], [0.1, 0.0], [0.1, 0.05]])
        states = execute(start, actions)
        client.post_trajectory(transitions_from_states(states, actions))
        stored = list(client.transitions())
        assert len(stored) == 3
        for t in stored:
            assert t.labels is not None and [x.model for x in t.labels] == ["still", "gone"]
            still_label, gone_label = t.labels
            assert still_label.s_pred is not None
            np.testing.assert_allclose(still_label.s_pred, t.s)
            moved = float(np.linalg.norm(t.s_next - t.s))
            assert t.deviation_of("still") == pytest.approx(moved, abs=1e-9)
            assert t.deviation_of("domain") == t.deviation
            assert gone_label.deviation is None and gone_label.missing
        with pytest.raises(KeyError):
            stored[0].deviation_of("sim")
        summary = client.labels()
        assert [m.model for m in summary.items] == ["domain", "still", "gone"]
        assert summary.of("domain").kind == "remote" and summary.of("domain").n_labelled == 3
        # What the stored labels say, summed up: the last step slid on the ice; `still` misses
        # every 0.1 move (d_max 0.05).
        right = [t.deviation < 0.05 for t in stored]
        assert right == [True, True, False]
        assert summary.of("domain").share_within_d_max == pytest.approx(2 / 3)
        assert summary.of("domain").max_deviation == pytest.approx(max(t.deviation for t in stored))
        assert summary.of("still").share_within_d_max == 0.0
        assert summary.of("gone").n_missing == 3 and summary.of("gone").mean_deviation is None

        # One fit learns the domain model's precondition and `still`'s, each from its labels;
        # `gone` has none, so there is no precondition of it to ask for.
        rng = np.random.default_rng(2)
        for _ in range(6):
            begin = rng.uniform(0.1, 0.9, size=2)
            acts = rng.uniform(-0.1, 0.1, size=(8, 2))
            client.post_trajectory(transitions_from_states(execute(begin, acts), acts))
        fitted = client.refit()
        probe = (np.array([[0.2, 0.5], [0.2, 0.5]]), np.array([[0.0, 0.0], [0.1, 0.0]]))
        own = client.precondition(probe, beta=0.0)
        assert own.model is None and own.model_version == fitted.version
        by_still = client.precondition(probe, beta=0.0, model="still")
        assert by_still.model == "still"
        # Standing still is what `still` predicts; a 0.1 move it misses by 0.1 > d_max.
        assert by_still.mu[1] > by_still.mu[0]
        assert not by_still.inside[1]
        exported = client.export_model(model="still")
        assert exported.model == "still" and client.export_model().model is None
        # `still` predicts the state itself: its features read that prediction.
        mu, _ = exported.evaluate(probe[0], probe[1], probe[0])
        np.testing.assert_allclose(mu, by_still.mu, rtol=1e-9, atol=1e-12)
        with pytest.raises(Conflict):
            client.precondition(probe, model="gone")
        with pytest.raises(ValidationFailed):
            client.precondition(probe, model="sim")


def sand_step(s: Array, a: Array) -> Array:
    """The sand world: right of ``x = 0.5`` the point moves half as far as its action says."""
    return s + (1.0 if s[0] < 0.5 else 0.5) * a


def test_a_plan_steps_with_whichever_model_is_trusted_there(make_server: MakeServer) -> None:
    """Two linear models of one robot, each right on one half of the table: a plan across
    the sand needs both, and says which model each step relied on."""
    server = make_server([])
    client = Client(server.url, timeout=60)
    moves = [[0.1, 0.0], [-0.1, 0.0], [0.0, 0.1], [0.0, -0.1]]
    exp = client.create_experiment(
        {
            "name": "sand",
            "d_max": 0.02,
            "learning": {"batch_size": 1000},
            "domain": {
                "kind": "custom",
                "state": {"low": [0, 0], "high": [1, 1]},
                "action": {"values": moves},
                "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]},
            },
        },
        models=[
            {
                "name": "slow",
                "cost": 4,
                "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[0.5, 0], [0, 0.5]]},
            }
        ],
    )
    assert exp.models is not None
    for x in np.arange(0.1, 0.95, 0.1):
        transitions = []
        for y in np.arange(0.1, 0.95, 0.1):
            for a in moves:
                s, act = np.array([x, y]), np.array(a)
                transitions.append({"s": s.tolist(), "a": a, "s_next": sand_step(s, act).tolist()})
        client.post_trajectory(transitions)
    client.refit()
    start, goal = [0.2, 0.5], [0.8, 0.5]
    for alone in ["domain", "slow"]:
        plan = client.plan(start, goal, beta=0.0, models=[alone])
        assert not plan.found
        assert plan.model_calls is not None and [m.model for m in plan.model_calls] == [alone]
    plan = client.plan(start, goal, beta=0.0)
    assert plan.found and plan.trajectory is not None and plan.step_models is not None
    for s, m in zip(plan.trajectory.states, plan.step_models, strict=False):
        assert m == ("domain" if s[0] < 0.5 else "slow")
    assert plan.model_calls is not None
    assert [(m.model, m.cost) for m in plan.model_calls] == [("domain", 1.0), ("slow", 4.0)]
    cost = plan.cost()
    assert cost is not None and cost > plan.model_calls[0].calls
    # Closed loop, re-planning across the models from every state the robot reaches.
    run = client.execute_plan(start, goal, sand_step, beta=0.0)
    assert run.success, run.status
    assert (
        client.execute_plan(start, goal, sand_step, beta=0.0, models=["slow"]).status == "no_plan"
    )
    with pytest.raises(ValidationFailed):
        client.plan(start, goal, models=["sim"])
    # A proposal steps with the models the same way, and says so; the learner may name them.
    proposal = client.propose(start, goal, client_id="sand", models=["slow", "domain"])
    assert proposal.models == ["domain", "slow"] and proposal.step_models is not None
    assert {"domain", "slow"} <= set(proposal.step_models)
    client.abandon(proposal.id)
    learner = client.learn([(start, [0.4, 0.5])], models=lambda _: ["domain"], verbose=False)
    for episode in learner:
        assert episode.proposal.models is None and episode.proposal.step_models is None
        episode.abandon()


def test_a_client_side_further_model_labels_from_the_posted_predictions(
    make_server: MakeServer,
) -> None:
    """A further model that is the client's own: its prediction rides with each transition,
    and one left out leaves its label missing, never the transition."""
    server = make_server([])
    client = Client(server.url, timeout=60)
    moves = [[0.1, 0.0], [-0.1, 0.0], [0.0, 0.1], [0.0, -0.1]]
    client.create_experiment(
        {
            "name": "mine",
            "d_max": 0.02,
            "domain": {
                "kind": "custom",
                "state": {"low": [0, 0], "high": [1, 1]},
                "action": {"values": moves},
                "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]},
            },
        },
        models=[{"name": "mine", "cost": 2, "model": {"kind": "client"}}],
    )
    s, a = np.array([0.7, 0.5]), np.array([0.1, 0.0])
    s_next = sand_step(s, a)
    client.post_trajectory(
        [
            Transition(s, a, s_next, predictions={"mine": s + 0.5 * a}),
            Transition(s_next, a, sand_step(s_next, a)),
        ]
    )
    mine = client.labels().of("mine")
    assert (mine.n_labelled, mine.n_missing) == (1, 1)
    assert mine.max_deviation is not None and mine.max_deviation < 1e-9
    with pytest.raises(ValidationFailed):
        client.post_trajectory([Transition(s, a, s_next, predictions={"sim": s})])


def test_a_bad_run_is_excluded_from_the_model_and_restored(make_server: MakeServer) -> None:
    with serve_model(model, "127.0.0.1", 0) as served:
        server = make_server([f"http://127.0.0.1:{served.port}/"])
        client = Client(server.url, timeout=60)
        client.create_experiment(settings(served.url, "hygiene"))
        rng = np.random.default_rng(2)
        posted = []
        for _ in range(3):
            start = rng.uniform(0.1, 0.9, size=2)
            actions = rng.uniform(-0.1, 0.1, size=(6, 2))
            states = execute(start, actions)
            posted.append(client.post_trajectory(transitions_from_states(states, actions)))
        fitted = client.refit()
        assert fitted.n_train == 18 and fitted.exclusions == []

        made = client.exclude_trajectory(posted[1].id, "the arm hit the table")
        assert made.status == "in_effect" and made.trajectory_ids == [posted[1].id]
        assert made.n_transitions == 6 and made.reason == "the arm hit the table"
        deadline = time.monotonic() + 120
        while (without := client.model()).version == fitted.version:
            assert time.monotonic() < deadline, "the refit the exclusion requested ran"
            time.sleep(0.05)
        assert without.n_train == 12 and without.exclusions == [made.id]
        [listed] = list(client.exclusions())
        assert listed.id == made.id and listed.applied
        excluded = {r.trajectory_id: r.excluded_by for r in client.runs()}
        assert excluded == {posted[0].id: None, posted[1].id: made.id, posted[2].id: None}

        restored = client.restore_exclusion(made.id)
        assert restored.status == "restored" and restored.restored_at is not None
        while (back := client.model()).version == without.version:
            assert time.monotonic() < deadline, "the refit the restore requested ran"
            time.sleep(0.05)
        assert back.n_train == 18 and back.exclusions == []

        day = client.exclude_time_range(
            posted[2].created_at,
            datetime.datetime(2999, 1, 1, tzinfo=datetime.timezone.utc),
            "a bad day",
        )
        assert day.trajectory_ids == [posted[2].id] and day.since is not None
        with pytest.raises(ValueError, match="time zone"):
            client.exclude_time_range(datetime.datetime(2026, 1, 1), "2999-01-01T00:00:00Z", "x")
        with pytest.raises(ValidationFailed) as refused:
            client.exclude_trajectory(999, "no such run")
        assert refused.value.field == "trajectory_id"


def test_a_proposal_continues_from_where_the_robot_is(make_server: MakeServer) -> None:
    with serve_model(model, "127.0.0.1", 0) as served:
        server = make_server([f"http://127.0.0.1:{served.port}/"])
        client = Client(server.url, timeout=60, client_id="arm-1")
        client.create_experiment(settings(served.url, "closed-loop"))
        start, goal = np.array([0.1, 0.2]), np.array([0.5, 0.2])
        first = client.propose(start, goal)
        actions = first.trajectory.actions
        assert len(actions) >= 2
        states = execute(start, actions[:2])
        prefix = transitions_from_states(states, actions[:2])

        step = client.continue_proposal(first.id, prefix)
        assert step.trajectory.partial and step.trajectory.proposal_id == first.id
        assert step.trajectory.n_transitions == 2 and not step.trajectory.replayed
        assert step.proposal.id != first.id and step.proposal.client_id == "arm-1"
        np.testing.assert_allclose(step.proposal.start, states[-1])
        np.testing.assert_allclose(step.proposal.goal, goal)
        assert client.get_proposal(first.id).status == "executed"

        again = client.continue_proposal(first.id, prefix)
        assert again.trajectory.replayed and again.trajectory.id == step.trajectory.id
        assert again.proposal.id == step.proposal.id
        assert len(list(client.transitions())) == 2


def test_a_training_problem_beyond_the_precondition_is_relaxed_unless_the_paper_preset(
    make_server: MakeServer,
) -> None:
    server = make_server()
    client = Client(server.url, timeout=60)
    grid = {"kind": "icy_gridworld", "map": ["..#...", *["......"] * 5]}
    # One trajectory per iteration, one iteration, a steep schedule: β_j ≈ 2 from then on.
    steep = {"iterations": 1, "batch_size": 1, "k2": 10.0}
    executed = transitions_from_states([[0, 0], [1, 0], [1, 0]], [[1, 0], [1, 0]])
    proposals: list[Proposal | None] = []
    for preset in ("default", "paper"):
        client.create_experiment(domain=grid, learning={**steep, "preset": preset})
        client.post_trajectory(executed)
        client.refit()
        try:
            proposals.append(client.propose([5, 1], [5, 5]))
        except NoPlan:
            proposals.append(None)
    relaxed, paper = proposals
    assert relaxed is not None and relaxed.relaxed_from_beta is not None
    assert relaxed.beta < relaxed.relaxed_from_beta
    assert relaxed.relaxed_from_beta > 1.9
    assert paper is None  # the paper's method answers no_plan


def test_server_errors_arrive_as_exceptions_with_code_and_details(
    make_server: MakeServer,
) -> None:
    with serve_model(model, "127.0.0.1", 0) as served:
        server = make_server([f"http://127.0.0.1:{served.port}/"])
        client = Client(server.url, timeout=60, retries=2, backoff=0.01, client_id="r1")
        with pytest.raises(NotFound):
            client.get_experiment(999)
        client.create_experiment(settings(served.url, "errors"))
        with pytest.raises(ValidationFailed) as bad:
            client.post_trajectory([{"s": [0.1, 0.1], "a": [0.5, 0.0], "s_next": [0.2, 0.1]}])
        assert bad.value.field == "transitions[0].a"
        held = client.propose([0.1, 0.5], [0.4, 0.5])
        assert client.propose([0.1, 0.5], [0.4, 0.5]).id == held.id
        with pytest.raises(Conflict) as conflict:
            client.propose([0.2, 0.5], [0.4, 0.5])
        assert conflict.value.lease is not None
        assert conflict.value.lease["proposal_id"] == held.id
        assert client.abandon(held.id).status == "abandoned"
        with pytest.raises(ValidationFailed) as url:
            client.create_experiment(settings("http://127.0.0.1:1/elsewhere", "not allowed"))
        assert url.value.field == "domain.model.url"
    # The model server is gone: the service answers 502 naming it, after the client's retries.
    t0 = time.monotonic()
    with pytest.raises(ModelUnavailable) as down:
        client.propose([0.1, 0.5], [0.4, 0.5])
    assert served.url in str(down.value.details)
    assert time.monotonic() - t0 < 30


def test_the_server_checks_tokens_by_role_and_experiment(
    make_server: MakeServer, tmp_path: Path
) -> None:
    admin, robot, reader = "a" * 32, "w" * 32, "r" * 32
    tokens = tmp_path / "tokens"
    tokens.write_text(f"{admin} admin *\n{robot} write 1\n{reader} read *\n")
    server = make_server(extra_args=["--token-file", str(tokens)])
    grid = {"kind": "icy_gridworld"}

    with pytest.raises(Unauthorized):
        Client(server.url, retries=0).list_experiments()
    with pytest.raises(Unauthorized):
        Client(server.url, token="x" * 32, retries=0).list_experiments()

    operator = Client(server.url, token=admin, timeout=60)
    first = operator.ensure_experiment("bench 2", domain=grid)
    second = operator.create_experiment(domain=grid, name="elsewhere")
    assert (first.id, second.id) == (1, 2)

    # The robot's write token reaches experiment 1 only: it finds it by name, proposes and
    # posts there, but cannot create an experiment nor reach experiment 2.
    arm = Client(server.url, token=robot, timeout=60, client_id="arm")
    assert [e.id for e in arm.list_experiments()] == [1]
    assert arm.ensure_experiment("bench 2", domain=grid).id == 1
    with pytest.raises(Forbidden):
        arm.ensure_experiment("new bench", domain=grid)
    with pytest.raises(Forbidden):
        arm.get_experiment(2)
    proposal = arm.propose([0, 0], [3, 0])
    arm.post_trajectory(
        transitions_from_states(proposal.states, proposal.actions), proposal_id=proposal.id
    )

    # A read token queries but does not propose.
    dashboard = Client(server.url, token=reader, timeout=60, experiment_id=1)
    assert dashboard.get_experiment().n_trajectories == 1
    with pytest.raises(Forbidden):
        dashboard.propose([0, 0], [3, 0])
