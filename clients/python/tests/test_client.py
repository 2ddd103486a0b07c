"""Unit tests of the client against a scripted transport (no server)."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import httpx
import numpy as np
import pytest

import precond_client.client as client_mod
from precond_client import (
    Client,
    Conflict,
    ModelUnavailable,
    NoPlan,
    NotFound,
    Transition,
    TransportError,
    ValidationFailed,
)
from precond_client.models import transitions_from_states

Handler = Callable[[httpx.Request], httpx.Response]


def make_client(handler: Handler, **kw: Any) -> Client:
    c = Client("http://precond.test", transport=httpx.MockTransport(handler), **kw)
    c._sleep = lambda _s: None
    return c


def scripted(*answers: Handler) -> tuple[Handler, list[httpx.Request]]:
    """A handler that answers its n-th request with ``answers[n]`` (the last one answers every
    later request), and the list of the requests it was sent."""
    sent: list[httpx.Request] = []

    def handler(req: httpx.Request) -> httpx.Response:
        sent.append(req)
        return answers[min(len(sent), len(answers)) - 1](req)

    return handler, sent


def raises(failure: type[httpx.TransportError], message: str) -> Handler:
    """A handler whose every request fails in transport with ``failure``."""

    def handler(req: httpx.Request) -> httpx.Response:
        raise failure(message, request=req)

    return handler


def error(status: int, code: str, message: str = "m", details: Any = None) -> httpx.Response:
    return httpx.Response(
        status, json={"error": {"code": code, "message": message, "details": details}}
    )


def experiment_json(eid: int = 1, name: str = "e", n: int = 2, m: int = 2) -> dict[str, Any]:
    return {
        "id": eid,
        "name": name,
        "domain": {"kind": "kinematic"},
        "d_max": 0.1,
        "seed": 0,
        "mde": {},
        "learning": {},
        "state_space": {"names": [f"s{i}" for i in range(n)], "low": [0] * n, "high": [1] * n},
        "action_space": {"names": [f"a{i}" for i in range(m)], "low": [0] * m, "high": [1] * m},
        "feature_names": [],
        "created_at": "t",
        "n_trajectories": 0,
        "n_transitions": 0,
        "iteration": 0,
        "model_version": 0,
        "n_refused": 0,
        "last_activity": "t",
    }


def created_json(tid: int = 1, pid: int | None = None) -> dict[str, Any]:
    return {
        "id": tid,
        "experiment_id": 1,
        "proposal_id": pid,
        "partial": False,
        "deviating": False,
        "source": None,
        "n_transitions": 1,
        "deviations": [0.5],
        "iteration": 0,
        "model_version": 0,
        "n_trajectories": tid,
        "created_at": "t",
    }


def proposal_json(pid: int, start: list[float], goal: list[float]) -> dict[str, Any]:
    return {
        "id": pid,
        "status": "open",
        "deviating": False,
        "client_id": "r1",
        "iteration": 0,
        "beta": -1.97,
        "strategy": "active",
        "model_version": 0,
        "start": start,
        "goal": goal,
        "created_at": "t",
        "expires_at": "t",
        "trajectory": {
            "states": [start, goal],
            "actions": [[g - s for s, g in zip(start, goal, strict=True)]],
            "mu": [0.0],
            "sigma": [1.0],
            "alpha_step": [-1.0],
            "alpha": -1.0,
        },
        "candidates": [{"alpha": -1.0, "length": 1}],
        "chosen_index": 0,
        "extensions": 3,
    }


def test_errors_carry_code_message_and_details() -> None:
    details = {"field": "transitions[0].a", "reason": "bad"}
    c = make_client(lambda r: error(422, "validation_failed", "wrong a", details), experiment_id=1)
    with pytest.raises(ValidationFailed) as e:
        c.post_trajectory([Transition([0, 0], [1, 1], [1, 1])])
    assert e.value.status == 422
    assert e.value.code == "validation_failed"
    assert e.value.message == "wrong a"
    assert e.value.details == details
    assert e.value.field == "transitions[0].a"


def test_a_non_json_error_is_still_an_api_error() -> None:
    c = make_client(lambda r: httpx.Response(404, text="<html>nope</html>"), experiment_id=1)
    with pytest.raises(Exception) as e:
        c.model()
    assert getattr(e.value, "code", None) == "http_404"


def test_a_lease_conflict_exposes_the_held_proposal() -> None:
    lease = {"proposal_id": 7, "client_id": "r1", "start": [0, 0], "goal": [1, 1]}
    c = make_client(lambda r: error(409, "conflict", "held", lease), experiment_id=1)
    with pytest.raises(Conflict) as e:
        c.propose([0.5, 0.5], [1, 1], client_id="r1")
    assert e.value.lease == lease


def test_connection_errors_and_5xx_are_retried_then_succeed() -> None:
    handler, calls = scripted(
        raises(httpx.ConnectError, "refused"),
        lambda _r: error(503, "unavailable"),
        lambda _r: error(503, "unavailable"),
        lambda _r: httpx.Response(200, json=experiment_json()),
    )
    c = make_client(handler)
    assert c.get_experiment(1).id == 1
    assert len(calls) == 4


def test_429_and_retry_after_are_honoured() -> None:
    slept: list[float] = []
    handler, _ = scripted(
        lambda _r: httpx.Response(429, headers={"Retry-After": "0.25"}, text="slow down"),
        lambda _r: httpx.Response(200, json={"items": []}),
    )
    c = make_client(handler)
    c._sleep = slept.append
    assert c.list_experiments() == []
    assert slept == [0.25]


def test_retries_give_up_with_a_transport_error() -> None:
    c = make_client(raises(httpx.ConnectError, "refused"), retries=3)
    with pytest.raises(TransportError):
        c.list_experiments()


def test_a_persistent_5xx_is_raised_with_its_code_after_the_retries() -> None:
    handler, calls = scripted(
        lambda _r: error(502, "model_unavailable", "down", {"model": "http://m", "reason": "x"})
    )
    c = make_client(handler, retries=2, experiment_id=1)
    with pytest.raises(ModelUnavailable) as e:
        c.plan([0, 0], [1, 1])
    assert e.value.details["model"] == "http://m"
    assert len(calls) == 3


def test_creating_an_experiment_is_not_repeated_once_it_may_have_arrived() -> None:
    handler, calls = scripted(
        raises(httpx.ReadError, "connection reset"),
        lambda _r: httpx.Response(201, json=experiment_json()),
    )
    c = make_client(handler)
    with pytest.raises(TransportError):
        c.create_experiment(name="x")
    assert len(calls) == 1


def test_creating_an_experiment_is_retried_when_the_connection_was_refused() -> None:
    handler, _ = scripted(
        raises(httpx.ConnectError, "refused"),
        lambda _r: httpx.Response(201, json=experiment_json(eid=4)),
    )
    c = make_client(handler)
    assert c.create_experiment(name="x").id == 4
    assert c.experiment_id == 4


def test_ensure_experiment_finds_by_name_before_creating() -> None:
    created: list[Any] = []
    existing = [experiment_json(1, "a"), experiment_json(2, "b")]

    def handler(req: httpx.Request) -> httpx.Response:
        if req.method == "GET":
            return httpx.Response(200, json={"items": existing})
        body = json.loads(req.content)
        created.append(body)
        return httpx.Response(201, json=experiment_json(3, body["name"]))

    c = make_client(handler)
    assert c.ensure_experiment("b").id == 2
    assert created == []
    exp = c.ensure_experiment("c", {"d_max": 0.2})
    assert exp.id == 3 and c.experiment_id == 3
    assert created == [{"d_max": 0.2, "name": "c"}]


def test_experiment_calls_need_a_current_experiment() -> None:
    c = make_client(lambda r: httpx.Response(200, json={}))
    with pytest.raises(ValueError, match="no current experiment"):
        c.model()


def test_every_trajectory_carries_an_idempotency_key_kept_across_retries() -> None:
    keys: list[str | None] = []
    bodies: list[Any] = []

    def handler(req: httpx.Request) -> httpx.Response:
        keys.append(req.headers.get("Idempotency-Key"))
        bodies.append(json.loads(req.content))
        if len(keys) == 1:
            raise httpx.ReadTimeout("lost answer", request=req)
        return httpx.Response(
            201, json=created_json(pid=9), headers={"idempotent-replayed": "true"}
        )

    c = make_client(handler, experiment_id=1)
    t = c.post_trajectory(
        transitions_from_states([[0.0, 0.0], [0.1, 0.0]], [[0.1, 0.0]]), proposal_id=9
    )
    assert keys == ["proposal-9", "proposal-9"]
    assert bodies[0] == bodies[1]
    assert bodies[0]["transitions"] == [{"s": [0.0, 0.0], "a": [0.1, 0.0], "s_next": [0.1, 0.0]}]
    assert bodies[0]["proposal_id"] == 9
    assert t.replayed and t.proposal_id == 9
    np.testing.assert_allclose(t.deviations, [0.5])


def test_unsolicited_trajectories_get_fresh_random_keys() -> None:
    keys: list[str | None] = []

    def handler(req: httpx.Request) -> httpx.Response:
        keys.append(req.headers.get("Idempotency-Key"))
        return httpx.Response(201, json=created_json())

    c = make_client(handler, experiment_id=1)
    c.post_trajectory([Transition([0, 0], [1, 0], [1, 0])])
    c.post_trajectory([{"s": [0, 0], "a": [1, 0], "s_next": [1, 0]}])
    assert all(k and k.startswith("py-") for k in keys)
    assert keys[0] != keys[1]


def test_non_finite_numbers_are_refused_before_sending() -> None:
    c = make_client(lambda r: httpx.Response(201, json=created_json()), experiment_id=1)
    with pytest.raises(ValueError, match="non-finite"):
        c.post_trajectory([Transition([0, float("nan")], [1, 0], [1, 0])])


def test_transitions_iterate_over_every_page() -> None:
    pages: dict[int, dict[str, Any]] = {
        0: {"items": [{"id": 1}, {"id": 2}], "next": 2},
        2: {"items": [{"id": 3}], "next": None},
    }
    asked: list[tuple[str, str]] = []

    def handler(req: httpx.Request) -> httpx.Response:
        after = int(req.url.params["after"])
        asked.append((req.url.params["after"], req.url.params["limit"]))
        items = [
            {
                "id": it["id"],
                "trajectory_id": 1,
                "step": it["id"] - 1,
                "s": [0],
                "a": [1],
                "s_next": [1],
                "s_pred": [1],
                "deviation": 0.0,
            }
            for it in pages[after]["items"]
        ]
        return httpx.Response(200, json={"items": items, "next": pages[after]["next"]})

    c = make_client(handler, experiment_id=1)
    it = c.transitions(page_size=2)
    first = next(it)
    assert first.id == 1 and len(asked) == 1  # pages are fetched lazily
    assert [t.id for t in it] == [2, 3]
    assert asked == [("0", "2"), ("2", "2")]


def test_precondition_takes_arrays_splits_columns_and_chunks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(client_mod, "PRECONDITION_CHUNK", 3)
    sent: list[list[dict[str, list[float]]]] = []

    def handler(req: httpx.Request) -> httpx.Response:
        if req.method == "GET":
            return httpx.Response(200, json=experiment_json(n=2, m=1))
        body = json.loads(req.content)
        assert body["beta"] == 1.5
        sent.append(body["points"])
        results = [
            {"mu": p["s"][0], "sigma": 0.1, "upper": p["s"][0] + 0.15, "inside": p["s"][0] < 0.3}
            for p in body["points"]
        ]
        return httpx.Response(
            200,
            json={
                "model_version": 2,
                "source": "fit",
                "beta": 1.5,
                "d_max": 0.45,
                "results": results,
            },
        )

    c = make_client(handler, experiment_id=1)
    pts = np.column_stack([np.arange(8) / 10, np.zeros(8), np.ones(8)])
    ans = c.precondition(pts, beta=1.5)
    assert [len(p) for p in sent] == [3, 3, 2]
    assert sent[0][1] == {"s": [0.1, 0.0], "a": [1.0]}
    np.testing.assert_allclose(ans.mu, pts[:, 0])
    assert ans.inside.dtype == np.bool_
    assert ans.inside.tolist() == [bool(x < 0.3) for x in pts[:, 0]]
    assert ans.model_version == 2
    same = c.precondition((pts[:, :2], pts[:, 2:]), beta=1.5)
    np.testing.assert_allclose(same.upper, ans.upper)


def test_the_token_is_sent_as_a_bearer() -> None:
    seen: list[str | None] = []

    def handler(req: httpx.Request) -> httpx.Response:
        seen.append(req.headers.get("Authorization"))
        return httpx.Response(200, json={"items": []})

    make_client(handler, token="s3cret").list_experiments()
    assert seen == ["Bearer s3cret"]


def test_propose_sends_candidates_and_the_default_client_id() -> None:
    from precond_client import Candidate

    bodies: list[Any] = []

    def handler(req: httpx.Request) -> httpx.Response:
        bodies.append(json.loads(req.content))
        return httpx.Response(201, json=proposal_json(1, [0.0, 0.0], [1.0, 0.0]))

    c = make_client(handler, experiment_id=1, client_id="arm-1")
    p = c.propose(np.array([0, 0]), [1, 0], candidates=[Candidate([[0, 0], [1, 0]], [[1, 0]])])
    assert bodies[0]["client_id"] == "arm-1"
    assert bodies[0]["candidates"] == [
        {"states": [[0.0, 0.0], [1.0, 0.0]], "actions": [[1.0, 0.0]]}
    ]
    assert p.actions.shape == (1, 2) and p.states.shape == (2, 2)
    assert p.trajectory.alpha == -1.0


def model_json(version: int, n_trajectories: int) -> dict[str, Any]:
    return {
        "experiment_id": 1,
        "version": version,
        "source": "fit" if version else "prior",
        "n_train": 3 * n_trajectories,
        "noise": None,
        "feature_names": ["s0", "s1", "a0", "a1"],
        "hyperparameters": {
            "length_scales": [0.5] * 4,
            "signal_variance": 1.0,
            "noise_variance": 0.0,
            "prior_mean": 0.0,
            "kernel": "matern12",
        },
        "noise_model": None,
        "log_marginal_likelihood": None,
        "fit_seconds": None,
        "fitted_at": None,
        "n_trajectories": n_trajectories,
        "label_cap": None,
        "label_cap_trials": [],
        "estimator": "exact",
        "online_trajectories": 0,
        "last_fit_refusal": None,
        "kernel_trials": [],
        "beta_choice": None,
        "test_beta": 2.0,
        "exclusions": [],
    }


class FakeLoopServer:
    """Proposals with leases, as the server keeps them, for the loop's unit tests; with
    ``batch_size``, a background refit after each batch that answers ``GET …/model`` only after
    ``fit_polls`` polls."""

    def __init__(self, batch_size: int | None = None, fit_polls: int = 0) -> None:
        self.proposals: dict[int, dict[str, Any]] = {}
        self.posted: list[int] = []
        self.abandoned: list[int] = []
        self.no_plan_goals: set[tuple[float, ...]] = set()
        self.at_goal_starts: set[tuple[float, ...]] = set()
        self.batch_size = batch_size
        self.fit_polls = fit_polls
        self.polls_left = 0
        self.model = model_json(0, 0)
        self.fitted = model_json(0, 0)
        self.log: list[str] = []

    def held(self, client_id: str) -> dict[str, Any] | None:
        for p in self.proposals.values():
            if p["client_id"] == client_id and p["status"] == "open":
                return p
        return None

    def __call__(self, req: httpx.Request) -> httpx.Response:
        path = req.url.path
        if path.endswith("/model"):
            if self.polls_left > 0:
                self.polls_left -= 1
            else:
                self.model = self.fitted
            self.log.append(f"model {self.model['n_trajectories']}")
            return httpx.Response(200, json=self.model)
        if path == "/v1/experiments/1":
            exp = experiment_json(1)
            exp["learning"] = {"batch_size": self.batch_size}
            return httpx.Response(200, json=exp)
        if path.endswith("/proposals"):
            body = json.loads(req.content)
            self.log.append("propose")
            if tuple(body["start"]) in self.at_goal_starts:
                reason = "the start already satisfies the goal: there is nothing to plan"
                return error(
                    422, "validation_failed", f"goal: {reason}", {"field": "goal", "reason": reason}
                )
            held = self.held(body["client_id"])
            if held is not None:
                if held["start"] == body["start"] and held["goal"] == body["goal"]:
                    return httpx.Response(200, json=held)
                lease = {k: held[k] for k in ("client_id", "start", "goal")}
                return error(409, "conflict", "held", {"proposal_id": held["id"], **lease})
            if tuple(body["goal"]) in self.no_plan_goals:
                return error(422, "no_plan", "none", {"extensions": 5000})
            pid = len(self.proposals) + 1
            p = proposal_json(pid, body["start"], body["goal"])
            p["client_id"] = body["client_id"]
            self.proposals[pid] = p
            return httpx.Response(201, json=p)
        if path.endswith("/abandon"):
            pid = int(path.split("/")[-2])
            self.proposals[pid]["status"] = "abandoned"
            self.abandoned.append(pid)
            return httpx.Response(200, json=self.proposals[pid])
        if "/proposals/" in path:
            return httpx.Response(200, json=self.proposals[int(path.split("/")[-1])])
        if path.endswith("/trajectories"):
            body = json.loads(req.content)
            pid = body["proposal_id"]
            assert req.headers["Idempotency-Key"] == f"proposal-{pid}"
            self.proposals[pid]["status"] = "executed"
            self.posted.append(pid)
            self.log.append("post")
            created = created_json(len(self.posted), pid)
            if self.batch_size is not None:
                created["iteration"] = len(self.posted) // self.batch_size
                created["model_version"] = self.fitted["version"]
                if len(self.posted) % self.batch_size == 0:  # the batch's refit starts
                    self.fitted = model_json(self.fitted["version"] + 1, len(self.posted))
                    self.polls_left = self.fit_polls
            return httpx.Response(201, json=created)
        return error(404, "not_found")


def test_learn_proposes_yields_and_posts_each_problem() -> None:
    server = FakeLoopServer()
    server.no_plan_goals.add((0.5, 0.5))
    c = make_client(server, experiment_id=1, client_id="r1")
    problems = [([0.0, 0.0], [1.0, 0.0]), ([0.0, 0.0], [0.5, 0.5]), ([0.0, 0.0], [0.0, 1.0])]
    learner = c.learn(problems)
    for ep in learner:
        assert not ep.resumed
        observed = np.vstack([ep.start, ep.start + ep.actions[0] * 0.9])
        res = ep.post(observed)
        assert not res.partial
    assert server.posted == [1, 2]
    assert (learner.episodes, learner.posted, learner.no_plan) == (2, 2, 1)


def test_learn_resumes_the_lease_a_crashed_process_held() -> None:
    server = FakeLoopServer()
    first = make_client(server, experiment_id=1, client_id="r1")
    loop = iter(first.learn([([0.0, 0.0], [1.0, 0.0])]))
    ep = next(loop)
    assert ep.proposal.id == 1
    del loop  # the process dies while the robot executes: the lease stays open

    again = make_client(server, experiment_id=1, client_id="r1")
    learner = again.learn([([0.2, 0.0], [0.0, 1.0])])
    seen = []
    for ep in learner:
        seen.append((ep.proposal.id, ep.resumed))
        ep.post(np.vstack([ep.start, ep.start + ep.actions[0]]))
    assert seen == [(1, True), (2, False)]
    assert server.posted == [1, 2]
    assert learner.resumed == 1


def test_learn_can_abandon_a_held_lease_instead() -> None:
    server = FakeLoopServer()
    c = make_client(server, experiment_id=1, client_id="r1")
    c.propose([0, 0], [1, 0])
    got = []
    for ep in c.learn([([0.0, 0.0], [0.0, 1.0])], resume=False):
        got.append(ep.proposal.id)
        ep.post(np.vstack([ep.start, ep.start + ep.actions[0]]))
    assert server.abandoned == [1]
    assert got == [2] and server.posted == [2]


def test_an_episode_not_reported_is_abandoned_before_the_next() -> None:
    server = FakeLoopServer()
    c = make_client(server, experiment_id=1, client_id="r1")
    learner = c.learn([([0.0, 0.0], [1.0, 0.0]), ([0.0, 0.0], [0.0, 1.0])])
    ids = [ep.proposal.id for ep in learner]  # the robot reports neither
    assert ids == [1, 2]
    assert server.abandoned == [1, 2]
    assert learner.abandoned == 2


def test_a_partial_execution_posts_the_executed_prefix() -> None:
    server = FakeLoopServer()
    c = make_client(server, experiment_id=1, client_id="r1")
    p = c.propose([0, 0], [1, 0])
    p.raw["trajectory"]["actions"] = [[0.5, 0], [0.5, 0]]
    bodies: list[Any] = []

    def spy(req: httpx.Request) -> httpx.Response:
        if req.url.path.endswith("/trajectories"):
            bodies.append(json.loads(req.content))
        return server(req)

    c2 = make_client(spy, experiment_id=1, client_id="r1")
    ep = next(iter(c2.learn([([0.0, 0.0], [1.0, 0.0])])))
    two_step = type(ep.proposal).from_json(p.raw)
    ep.proposal = two_step
    ep.post([[0.0, 0.0], [0.4, 0.0]])
    assert bodies[0]["partial"] is True
    assert bodies[0]["transitions"] == [{"s": [0.0, 0.0], "a": [0.5, 0.0], "s_next": [0.4, 0.0]}]


def test_no_plan_can_be_raised_instead_of_skipped() -> None:
    server = FakeLoopServer()
    server.no_plan_goals.add((1.0, 0.0))
    c = make_client(server, experiment_id=1, client_id="r1")
    with pytest.raises(NoPlan):
        list(c.learn([([0.0, 0.0], [1.0, 0.0])], skip_no_plan=False))


def test_not_found_is_not_retried() -> None:
    handler, calls = scripted(lambda _r: error(404, "not_found", "no experiment 9"))
    with pytest.raises(NotFound):
        make_client(handler).get_experiment(9)
    assert len(calls) == 1


def test_learn_sends_the_clients_own_candidates_for_each_problem() -> None:
    from precond_client import Candidate

    server = FakeLoopServer()
    sent: list[Any] = []

    def spy(req: httpx.Request) -> httpx.Response:
        if req.url.path.endswith("/proposals"):
            sent.append(json.loads(req.content).get("candidates"))
        return server(req)

    def planner(start: np.ndarray, goal: np.ndarray) -> list[Candidate]:
        return [Candidate(np.vstack([start, goal]), (goal - start)[None])]

    c = make_client(spy, experiment_id=1, client_id="r1")
    for ep in c.learn([([0.0, 0.0], [0.5, 0.0])], candidates=planner):
        ep.post(np.vstack([ep.start, ep.start + ep.actions[0]]))
    assert sent == [[{"states": [[0.0, 0.0], [0.5, 0.0]], "actions": [[0.5, 0.0]]}]]


def run_loop(learner: Any) -> list[int]:
    """Executes every episode exactly as proposed; the proposal ids in order."""
    ids = []
    for ep in learner:
        ids.append(ep.proposal.id)
        ep.post(np.vstack([ep.start, ep.start + ep.actions[0]]))
    return ids


def test_learn_skips_a_start_that_already_satisfies_its_goal_and_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    server = FakeLoopServer()
    server.at_goal_starts.add((0.5, 0.5))
    c = make_client(server, experiment_id=1, client_id="r1")
    problems = [([0.0, 0.0], [1.0, 0.0]), ([0.5, 0.5], [0.51, 0.5]), ([0.0, 0.0], [0.0, 1.0])]
    with caplog.at_level("WARNING", logger="precond_client"):
        learner = c.learn(problems)
        assert run_loop(learner) == [1, 2]
    assert (learner.episodes, learner.posted, learner.at_goal, learner.no_plan) == (2, 2, 1, 0)
    assert any(
        "problem 1" in r.message and "already satisfies the goal" in r.message
        for r in caplog.records
    )


def test_learn_still_raises_other_validation_failures() -> None:
    def handler(req: httpx.Request) -> httpx.Response:
        return error(422, "validation_failed", "goal: outside", {"field": "goal", "reason": "x"})

    c = make_client(handler, experiment_id=1, client_id="r1")
    with pytest.raises(ValidationFailed):
        list(c.learn([([0.0, 0.0], [9.0, 0.0])]))


def test_learn_waits_for_the_refit_of_each_completed_batch_before_proposing() -> None:
    server = FakeLoopServer(batch_size=2, fit_polls=3)
    c = make_client(server, experiment_id=1, client_id="r1")
    problems = [([0.0, 0.0], [float(i), 1.0]) for i in range(1, 6)]
    learner = c.learn(problems)
    assert run_loop(learner) == [1, 2, 3, 4, 5]
    # After the 2nd and 4th posts the loop polls until the model covers the batch (3 polls
    # answer the old model, the 4th the refit), and it proposes only then; after the 5th (an
    # incomplete batch) it does not wait.
    assert server.log == [
        *["propose", "post", "propose", "post"],
        *["model 0"] * 3,
        "model 2",
        *["propose", "post", "propose", "post"],
        *["model 2"] * 3,
        "model 4",
        *["propose", "post"],
    ]
    assert learner.model_version == 2


def test_learn_waits_for_the_last_batch_when_the_problems_run_out() -> None:
    server = FakeLoopServer(batch_size=2, fit_polls=1)
    c = make_client(server, experiment_id=1, client_id="r1")
    learner = c.learn([([0.0, 0.0], [1.0, 1.0]), ([0.0, 0.0], [2.0, 1.0])])
    run_loop(learner)
    assert server.log[-2:] == ["model 0", "model 2"]
    assert learner.model_version == 1


def test_learn_need_not_wait_for_the_model() -> None:
    server = FakeLoopServer(batch_size=1, fit_polls=5)
    c = make_client(server, experiment_id=1, client_id="r1")
    run_loop(c.learn([([0.0, 0.0], [float(i), 1.0]) for i in range(1, 4)], wait_for_model=False))
    assert server.log == ["propose", "post"] * 3


def test_a_model_that_does_not_come_is_waited_for_once_then_the_loop_goes_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    server = FakeLoopServer(batch_size=1, fit_polls=10**9)
    c = make_client(server, experiment_id=1, client_id="r1")
    with caplog.at_level("WARNING", logger="precond_client"):
        learner = c.learn([([0.0, 0.0], [1.0, 1.0]), ([0.0, 0.0], [2.0, 1.0])], model_timeout=0.0)
        assert run_loop(learner) == [1, 2]
    assert server.log.count("propose") == 2 and server.log.count("post") == 2
    timeouts = [r for r in caplog.records if "going on with the model that answers" in r.message]
    assert len(timeouts) == 2  # after each post, once


def test_learn_reports_its_progress_to_a_callback_and_the_log(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from precond_client import Progress

    server = FakeLoopServer(batch_size=2)
    server.no_plan_goals.add((9.0, 9.0))
    server.at_goal_starts.add((0.5, 0.5))
    c = make_client(server, experiment_id=1, client_id="r1")
    seen: list[Progress] = []
    problems = [
        ([0.0, 0.0], [1.0, 0.0]),
        ([0.0, 0.0], [9.0, 9.0]),
        ([0.5, 0.5], [0.5, 0.5]),
        ([0.0, 0.0], [2.0, 0.0]),
    ]
    with caplog.at_level("INFO", logger="precond_client"):
        run_loop(c.learn(problems, progress=seen.append))
    assert [(p.event, p.problem) for p in seen] == [
        ("posted", 0),
        ("no_plan", 1),
        ("at_goal", 2),
        ("posted", 3),
        ("model", 3),
    ]
    last = seen[-1]
    assert (last.episodes, last.posted, last.no_plan, last.at_goal, last.model_version) == (
        2,
        2,
        1,
        1,
        1,
    )
    assert seen[0].result is not None and seen[0].proposal_id == 1
    messages = [r.message for r in caplog.records]
    assert any(m.startswith("episode 1: proposal 1 posted") for m in messages)
    assert any("problem 1: no trajectory" in m for m in messages)
    assert any(m.startswith("model version 1 covers 2 trajectories") for m in messages)


def test_ensure_experiment_refuses_an_experiment_with_other_settings() -> None:
    from precond_client import ExperimentMismatch

    stored = experiment_json(1, "arm")
    stored["d_max"] = 0.05
    stored["domain"] = {
        "kind": "custom",
        "state": {"names": ["s0", "s1"], "low": [0.0, 0.0], "high": [1.0, 1.0]},
        "goal": {"components": None, "radius": 0.05},
        "model": {"kind": "remote", "url": "http://127.0.0.1:9000/predict", "timeout_ms": 2000},
    }
    stored["learning"] = {"batch_size": 5, "preset": "default"}
    created: list[Any] = []

    def handler(req: httpx.Request) -> httpx.Response:
        if req.method == "GET":
            return httpx.Response(200, json={"items": [stored]})
        created.append(req)
        return httpx.Response(201, json=stored)

    c = make_client(handler)
    # Only what is asked is compared: the defaults the server resolved do not count, integers
    # equal floats, None means "the default".
    same = {
        "kind": "custom",
        "state": {"low": [0, 0], "high": [1, 1]},
        "model": {"kind": "remote", "url": "http://127.0.0.1:9000/predict"},
        "goal": {"components": None},
    }
    assert c.ensure_experiment("arm", d_max=0.05, domain=same, learning={"batch_size": 5}).id == 1
    assert c.ensure_experiment("arm", {"name": "ignored", "d_max": None}).id == 1

    c.experiment_id = None
    other = {**same, "model": {"kind": "remote", "url": "http://127.0.0.1:9001/predict"}}
    with pytest.raises(ExperimentMismatch) as e:
        c.ensure_experiment("arm", d_max=0.03, domain=other, learning={"relax_beta": False})
    assert e.value.differences == [
        ("d_max", 0.03, 0.05),
        ("domain.model.url", "http://127.0.0.1:9001/predict", "http://127.0.0.1:9000/predict"),
        ("learning.relax_beta", False, "<absent>"),
    ]
    assert e.value.experiment.id == 1
    assert "experiment 1 'arm' exists with other settings" in str(e.value)
    assert "d_max: asked 0.03, stored 0.05" in str(e.value)
    assert c.experiment_id is None and created == []
    with pytest.raises(ExperimentMismatch):
        c.ensure_experiment("arm", domain={"state": {"low": [0, 0, 0]}})
