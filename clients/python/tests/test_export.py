"""The exported model: the document :class:`ExportedModel` reads is the spec's ``ModelExport``
(every key it reads is a property, every required property is read), and — against the real
server — its numpy evaluation answers what ``POST /precondition`` answers, to 1e-9."""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import PrecondServer
from test_wire import spec

from precond_client import Client, Conflict, ExportedModel

MakeServer = Callable[..., PrecondServer]


def gp(n: int, d: int, *, variance: bool, correction: bool = False) -> dict[str, Any]:
    rng = np.random.default_rng(n)
    tri = [float(v) for v in rng.uniform(0.1, 0.5, n * (n + 1) // 2)]
    return {
        "kernel": "matern52",
        "length_scales": [0.5] * d,
        "signal_variance": 0.3,
        "prior_mean": 0.01,
        "points": rng.uniform(0, 1, (n, d)).tolist(),
        "weights": rng.normal(size=n).tolist(),
        "factor": tri if variance else None,
        "correction": tri if correction else None,
    }


def documents() -> Iterator[dict[str, Any]]:
    """Small valid documents, one per feature map and noise kind."""
    base: dict[str, Any] = {
        "format": "precond-model",
        "format_version": 1,
        "experiment_id": 1,
        "model_version": 2,
        "estimator": "exact",
        "n_train": 3,
        "d_max": 0.1,
        "test_beta": 2.0,
        "state_dim": 2,
        "action_dim": 2,
        # y is an angle: its cosine and sine, in the state and in the prediction.
        "feature_names": [
            "x",
            "cos y",
            "sin y",
            "dx",
            "dy",
            "action_length",
            "x'",
            "cos y'",
            "sin y'",
            "move_length",
        ],
        "feature_map": {
            "kind": "unit_box",
            "state_low": [0, 0],
            "state_high": [1, 1],
            "action_low": [-0.1, -0.1],
            "action_high": [0.1, 0.1],
            "state_components": [0, 1],
            "action_components": [0, 1],
            "action_length": True,
            "prediction_components": [0, 1],
            "weights": [1.0, 2.0],
            "move_length": True,
            "periodic": [1],
        },
        "predictor": {
            "main": gp(3, 10, variance=True),
            "noise": {"kind": "homoscedastic", "noise_variance": 1e-4},
        },
    }
    yield base
    hetero = copy.deepcopy(base)
    hetero["estimator"] = "sparse"
    hetero["predictor"] = {
        "main": gp(3, 10, variance=True, correction=True),
        "noise": {
            "kind": "heteroscedastic",
            "log_noise": gp(2, 10, variance=False),
            "noise_variance_min": 1e-6,
            "noise_variance_max": 1.0,
        },
    }
    yield hetero
    grid = copy.deepcopy(base)
    grid["feature_names"] = [f"f{i}" for i in range(12)]
    grid["feature_map"] = {
        "kind": "per_move",
        "state_low": [0, 0],
        "state_high": [11, 11],
        "moves": [[1, 0], [-1, 0], [0, 1], [0, -1]],
        "tolerance": 1e-9,
    }
    grid["predictor"]["main"] = gp(3, 12, variance=True)
    yield grid
    water = copy.deepcopy(base)
    water["state_dim"], water["action_dim"] = 7, 3
    water["feature_names"] = ["f0", "f1", "f2", "rotation"]
    water["predictor"]["main"] = gp(3, 4, variance=True)
    water["feature_map"] = {
        "kind": "action_and_rotation",
        "action_low": [0, 0, 0],
        "action_high": [1, 1, 3.14],
        "state_angle": 2,
        "action_angle": 2,
        "tolerance": 1e-6,
    }
    yield water
    further = copy.deepcopy(base)
    further["model"] = "still"  # a further model's estimator (features of its prediction)
    yield further
    experts = copy.deepcopy(base)
    experts["estimator"] = "local_experts"
    experts["format_version"] = 2
    experts["predictor"] = {
        "centres": [[0.2] * 10, [0.8] * 10],
        "experts": [base["predictor"], hetero["predictor"]],
    }
    yield experts


def schema_required(name: str) -> set[str]:
    """The properties an object schema requires (none for a ``oneOf``)."""
    return set(spec()["components"]["schemas"][name].get("required", []))


def schema_properties(name: str) -> dict[str, set[str]]:
    """A schema's properties (object) or those of each ``oneOf`` variant, by ``kind``."""
    schemas = spec()["components"]["schemas"]
    s = schemas[name]
    if "oneOf" in s:
        out = {}
        for variant in s["oneOf"]:
            v = schemas[variant["$ref"].rsplit("/", 1)[1]]
            out[v["properties"]["kind"]["const"]] = set(v["properties"])
        return out
    return {"": set(s["properties"])}


def keyed_parts(doc: dict[str, Any]) -> Iterator[tuple[str, dict[str, Any]]]:
    """Every object of a document with the schema it is an instance of."""
    yield "ModelExport", doc
    yield "FeatureMap", doc["feature_map"]
    predictors = [doc["predictor"]]
    if "experts" in doc["predictor"]:
        yield "ExpertsPredictor", doc["predictor"]
        predictors = doc["predictor"]["experts"]
    for predictor in predictors:
        yield "Predictor", predictor
        yield "GpPredictor", predictor["main"]
        noise = predictor["noise"]
        yield "NoisePredictor", noise
        if "log_noise" in noise:
            yield "GpPredictor", noise["log_noise"]


def test_the_documents_read_are_the_specs_model_export() -> None:
    for doc in documents():
        for schema, part in keyed_parts(doc):
            props = schema_properties(schema)
            allowed = props[part.get("kind", "") if len(props) > 1 else ""]
            if len(props) > 1:
                assert set(part) == allowed, schema
            else:
                # Every required property, and no other than the schema's.
                assert schema_required(schema) <= set(part) <= allowed, schema
        model = ExportedModel.from_json(doc)
        assert model.model == doc.get("model")
        states = np.full((5, doc["state_dim"]), 0.5)
        predicted = states + 0.01 if model.uses_prediction else None
        mu, sigma = model.evaluate(states, np.zeros((5, 3))[:, : doc["action_dim"]], predicted)
        assert mu.shape == sigma.shape == (5,) and np.all(np.isfinite(sigma))
        # Every property is read: without it the document is refused.
        for schema, part in keyed_parts(doc):
            optional = (
                set(part) - schema_required(schema)
                if "oneOf" not in spec()["components"]["schemas"][schema]
                else set()
            )
            for key in list(part):
                if key == "kind" or part[key] is None or key in optional:
                    continue
                saved = part.pop(key)
                with pytest.raises((KeyError, ValueError)):
                    ExportedModel.from_json(doc)
                part[key] = saved


def test_an_unknown_format_or_version_is_refused() -> None:
    doc = next(documents())
    with pytest.raises(ValueError, match="format_version"):
        ExportedModel.from_json({**doc, "format_version": 2})
    experts = list(documents())[-1]
    with pytest.raises(ValueError, match="format_version"):
        ExportedModel.from_json({**experts, "format_version": 1})
    with pytest.raises(ValueError, match="precond-model"):
        ExportedModel.from_json({**doc, "format": "other"})


def kinematic_trajectory(rng: np.random.Generator, n: int) -> list[dict[str, Any]]:
    """A random walk on the unit square; the world pushes up by 0.08 where ``x > 0.5``."""
    transitions = []
    s = rng.uniform(0.05, 0.95, size=2)
    for _ in range(n):
        a = rng.uniform(-0.1, 0.1, size=2)
        push = np.array([0.0, 0.08 if s[0] > 0.5 else 0.0]) + rng.normal(0, 0.005, size=2)
        nxt = np.clip(s + a + push, 0.0, 1.0)
        transitions.append({"s": s.tolist(), "a": a.tolist(), "s_next": nxt.tolist()})
        s = nxt
    return transitions


# A custom domain whose linear model is the kinematic one, ``clip(s + a)``, with action
# bounds of different sizes (its features end with the action's length).
CUSTOM_DOMAIN: dict[str, Any] = {
    "kind": "custom",
    "state": {"low": [0, 0], "high": [1, 1]},
    "action": {"low": [-0.1, -0.2], "high": [0.1, 0.2]},
    "model": {"kind": "linear", "A": [[1, 0], [0, 1]], "B": [[1, 0], [0, 1]]},
}
# The same with its second state component an angle of period 1 (two features, cos and sin,
# wherever it feeds the MDE; its prediction wrapped rather than clipped).
CUSTOM_PERIODIC: dict[str, Any] = {
    **CUSTOM_DOMAIN,
    "state": {"low": [0, 0], "high": [1, 1], "periodic": [1]},
}


@pytest.mark.integration
@pytest.mark.parametrize(
    ("estimator", "features"),
    [
        ("exact", "state_action_prediction_length"),
        ("exact", "state_action_prediction"),
        ("sparse", "state_action"),
        ("exact", "custom"),
        ("exact", "custom_periodic"),
        ("local_experts", "state_action"),
    ],
)
def test_an_exported_model_answers_as_the_server(
    make_server: MakeServer, tmp_path: Path, estimator: str, features: str
) -> None:
    server = make_server()
    client = Client(server.url, timeout=60)
    mde: dict[str, Any] = {"restarts": 0, "estimator": estimator}
    if estimator == "sparse":
        mde["inducing_points"] = 24
    if estimator == "local_experts":
        mde["expert_size"] = 50  # 80 transitions: two regions
    custom = features.startswith("custom")
    client.create_experiment(
        domain={"custom": CUSTOM_DOMAIN, "custom_periodic": CUSTOM_PERIODIC}.get(
            features, {"kind": "kinematic", "features": features}
        ),
        mde=mde,
        learning={"batch_size": 2},
        d_max=0.05,
    )
    with pytest.raises(Conflict):
        client.export_model()
    rng = np.random.default_rng(5)
    for _ in range(2):
        client.post_trajectory(kinematic_trajectory(rng, 40))
    fitted = client.wait_for_model(2)
    assert fitted.estimator == estimator

    model = client.export_model()
    assert model.model_version == fitted.version and model.n_train == 80
    if estimator == "local_experts":
        assert model.raw["format_version"] == 2
        assert len(model.raw["predictor"]["experts"]) == 2
        assert fitted.hyperparameters is None  # each expert has its own
    feature_map = model.raw["feature_map"]
    assert feature_map["kind"] == (
        "unit_box" if features == "state_action" or custom else "kinematic_prediction"
    )
    assert feature_map.get("action_length", False) == custom
    assert feature_map.get("periodic", []) == ([1] if features == "custom_periodic" else [])
    # A custom domain's features read the model's prediction by default (where the move
    # ends, and its length): the robot passes its own model's f̂(s, a) to the document.
    assert feature_map.get("prediction_components", []) == ([0, 1] if custom else [])
    assert feature_map.get("move_length", False) == (
        features == "state_action_prediction_length" or custom
    )
    assert model.uses_prediction == custom
    # x, y, the action (2), its length, x̂, ŷ, the move's length; an angle y counts twice.
    assert len(model.feature_names) == {"custom": 8, "custom_periodic": 10}.get(
        features, len(model.feature_names)
    )
    path = tmp_path / "mde.json"
    model.save(path)
    loaded = ExportedModel.load(path)

    states = rng.uniform(0, 1, size=(200, 2))
    actions = rng.uniform(-0.1, 0.1, size=(200, 2))
    # The custom domain's linear model: clip(s + a) to the state's box.
    predicted = np.clip(states + actions, 0.0, 1.0) if model.uses_prediction else None
    if predicted is not None and features == "custom_periodic":
        predicted[:, 1] = np.mod(states[:, 1] + actions[:, 1], 1.0)  # wrapped, not clipped
    if model.uses_prediction:
        with pytest.raises(ValueError, match="predicted"):
            model.evaluate(states, actions)
    server_answer = client.precondition((states, actions), beta=1.5)
    for m in (model, loaded):
        mu, sigma = m.evaluate(states, actions, predicted)
        np.testing.assert_allclose(mu, server_answer.mu, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(sigma, server_answer.sigma, rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(
            m.inside(states, actions, beta=1.5, predicted=predicted), server_answer.inside
        )
    worst = max(
        float(np.max(np.abs(mu - server_answer.mu) / (1 + np.abs(server_answer.mu)))),
        float(np.max(np.abs(sigma - server_answer.sigma) / (1 + server_answer.sigma))),
    )

    # Time per point (best of 5, the machine may be busy): a batch, and one point at a time
    # as in a control loop.
    def best(f: Callable[[], object]) -> float:
        times = []
        for _ in range(5):
            started = time.perf_counter()
            f()
            times.append(time.perf_counter() - started)
        return min(times)

    batch = best(lambda: model.evaluate(states, actions, predicted)) / len(states)
    one = None if predicted is None else predicted[0]
    single = best(lambda: model.evaluate(states[0], actions[0], one))
    print(
        f"{estimator}: worst relative difference {worst:.1e}; "
        f"{batch * 1e6:.1f} µs a point in a batch, {single * 1e6:.0f} µs for one point"
    )
