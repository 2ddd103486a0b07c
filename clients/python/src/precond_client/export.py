"""An exported model (``GET /v1/experiments/{id}/model/export``), evaluated with numpy alone:
the precondition inside a robot's control loop, without a round trip to the server.

:class:`ExportedModel` reads the ``precond-model`` document (format version 1 for one GP, 2
for local experts) — the domain's feature map ``φ(s, a)``, the fitted GP (or each expert's GP
and the experts' centres) as plain numbers and ``d_max`` — and answers ``μ`` and
``σ`` as ``POST /precondition`` does (to about 1e-12 relative; see the server's
``GpPredictor`` schema for the formulas), batched::

    model = client.export_model()
    model.save("mde.json")                     # later, on the robot: ExportedModel.load(...)
    mu, sigma = model.evaluate(states, actions)
    ok = model.inside(states, actions, beta=2.0)
    # features that read the model's prediction (custom domains' default): pass f̂(s, a)
    ok = model.inside(states, actions, predicted=f_hat(states, actions))

It is not a dataclass of :mod:`precond_client.models`, whose wire rules
(``tests/test_wire.py``) bind a class's fields to a schema's properties one to one: this class
holds numpy arrays derived from the document (the scaled points, the unpacked triangular
factors) rather than its properties, and the document is also a file format it writes back
unchanged (``raw``). ``tests/test_export.py`` checks instead that the keys it reads are exactly
the properties of the spec's ``ModelExport`` schemas.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

FORMAT = "precond-model"
"""The document's ``format``."""
FORMAT_VERSION = 1
"""The ``format_version`` of a document whose predictor is one GP."""
FORMAT_VERSION_EXPERTS = 2
"""The ``format_version`` of a document whose predictor is local experts (``centres``,
``experts``): a point is answered by the expert of the nearest centre."""

_FAR_R2 = 9.0e4
"""Squared scaled distance beyond which the server's kernels are exactly 0 (``r = 300``)."""

_CHUNK = 2048
"""Query points per block (bounds the ``chunk × n × d`` distance array)."""


def _vec(v: Any) -> Array:
    return np.asarray(v, dtype=np.float64).reshape(-1)


def _rows(v: ArrayLike, dim: int, what: str) -> Array:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 1:
        a = a.reshape(1, -1)
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{what}: expected rows of {dim} components, got shape {a.shape}")
    return a


def _unit(v: Array, low: Array, high: Array) -> Array:
    """``(v − low) / (high − low)``, 0 where the bounds coincide (as the server's ``to_unit``)."""
    width = high - low
    ok = width > 0
    return np.where(ok, (v - low) / np.where(ok, width, 1.0), 0.0)


class _Gp:
    """One GP of the document (``GpPredictor``): mean and latent variance at feature rows."""

    def __init__(self, d: Mapping[str, Any]) -> None:
        self.kernel = str(d["kernel"])
        if self.kernel not in ("matern12", "matern32", "matern52"):
            raise ValueError(f"unknown kernel {self.kernel!r}")
        self.inv_length = 1.0 / _vec(d["length_scales"])
        self.s2 = float(d["signal_variance"])
        self.prior_mean = float(d["prior_mean"])
        points = np.asarray(d["points"], dtype=np.float64)
        n = len(points)
        if points.ndim != 2 or points.shape[1] != len(self.inv_length):
            raise ValueError(f"points: expected rows of {len(self.inv_length)} features")
        self.points = points * self.inv_length
        self.weights = _vec(d["weights"])
        if self.weights.shape != (n,):
            raise ValueError(f"weights: expected {n} numbers")
        self.factor = self._triangle(d["factor"], n, "factor")
        self.correction = self._triangle(d["correction"], n, "correction")

    @staticmethod
    def _triangle(packed: Any, n: int, what: str) -> Array | None:
        if packed is None:
            return None
        p = _vec(packed)
        if len(p) != n * (n + 1) // 2:
            raise ValueError(f"{what}: expected {n * (n + 1) // 2} numbers, got {len(p)}")
        m = np.zeros((n, n))
        m[np.tril_indices(n)] = p  # packed by rows: (0,0), (1,0), (1,1), (2,0), …
        return m

    @property
    def dim(self) -> int:
        return len(self.inv_length)

    def kernel_matrix(self, x: Array) -> Array:
        """``k(x_j, p_i)`` for feature rows ``x`` (``N × n``)."""
        diff = self.points[None, :, :] - (x * self.inv_length)[:, None, :]
        r2 = np.einsum("jik,jik->ji", diff, diff)
        if self.kernel == "matern12":
            t = np.sqrt(r2)
            k = self.s2 * np.exp(-t)
        elif self.kernel == "matern32":
            t = math.sqrt(3.0) * np.sqrt(r2)
            k = self.s2 * (1.0 + t) * np.exp(-t)
        else:
            t = math.sqrt(5.0) * np.sqrt(r2)
            k = self.s2 * (1.0 + t + (5.0 / 3.0) * r2) * np.exp(-t)
        return np.where(r2 > _FAR_R2, 0.0, k)

    def mean_and_variance(self, x: Array, want_var: bool = True) -> tuple[Array, Array | None]:
        k = self.kernel_matrix(x)
        mean = self.prior_mean + k @ self.weights
        if not want_var or self.factor is None:
            return mean, None
        t = k @ self.factor.T
        var = self.s2 - np.einsum("ji,ji->j", t, t)
        if self.correction is not None:
            c = k @ self.correction.T
            var = var + np.einsum("ji,ji->j", c, c)
        return mean, np.clip(var, 0.0, self.s2)


class _Predictor:
    """One GP on deviations and its noise (the server's ``Predictor``)."""

    def __init__(self, predictor: Mapping[str, Any], what: str) -> None:
        self.main = _Gp(predictor["main"])
        noise = predictor["noise"]
        self.noise_kind = str(noise["kind"])
        self._log_noise: _Gp | None = None
        if self.noise_kind == "homoscedastic":
            self._noise_variance = float(noise["noise_variance"])
        elif self.noise_kind == "heteroscedastic":
            self._log_noise = _Gp(noise["log_noise"])
            self._noise_clip = (
                float(noise["noise_variance_min"]),
                float(noise["noise_variance_max"]),
            )
        else:
            raise ValueError(f"{what}.noise: unknown noise kind {self.noise_kind!r}")
        if self.main.factor is None:
            raise ValueError(f"{what}.main.factor: the main GP needs its variance factor")

    @property
    def dim(self) -> int:
        return self.main.dim

    def evaluate(self, x: Array) -> tuple[Array, Array]:
        """``(μ, σ)`` at feature rows ``x``."""
        mean, var = self.main.mean_and_variance(x)
        assert var is not None
        if self._log_noise is None:
            noise = np.full(len(x), self._noise_variance)
        else:
            z, _ = self._log_noise.mean_and_variance(x, want_var=False)
            noise = np.clip(np.exp(z), *self._noise_clip)
        return mean, np.sqrt(var + noise)


class _FeatureMap:
    """The document's ``feature_map``, parsed once: ``φ(s, a)`` for rows of states and actions."""

    def __init__(self, m: Mapping[str, Any], state_dim: int, action_dim: int) -> None:
        self.kind = str(m["kind"])
        if self.kind == "unit_box":
            self.low = _vec(m["state_low"]), _vec(m["action_low"])
            self.high = _vec(m["state_high"]), _vec(m["action_high"])
            self.components = (
                [int(i) for i in m["state_components"]],
                [int(i) for i in m["action_components"]],
            )
            if len(self.low[0]) != state_dim or len(self.low[1]) != action_dim:
                raise ValueError("feature_map: bounds do not match state_dim and action_dim")
            self.action_length = bool(m.get("action_length", False))
            if self.action_length and not self.components[1]:
                raise ValueError("feature_map.action_length: needs an action component")
            self.prediction = [int(i) for i in m.get("prediction_components", [])]
            self.weights = _vec(m.get("weights", []))
            self.move_length = bool(m.get("move_length", False))
            if self.move_length and len(self.weights) != state_dim:
                raise ValueError("feature_map.weights: move_length needs one weight per state")
            # Angles: two features each (cos, sin), the move's length the short way round.
            self.periodic = [int(i) for i in m.get("periodic", [])]
            if any(not 0 <= i < state_dim for i in self.periodic):
                raise ValueError("feature_map.periodic: not a state component")
        elif self.kind == "kinematic_prediction":
            self.low = _vec(m["state_low"]), _vec(m["action_low"])
            self.high = _vec(m["state_high"]), _vec(m["action_high"])
            if len(self.low[0]) != state_dim or len(self.low[1]) != action_dim:
                raise ValueError("feature_map: bounds do not match state_dim and action_dim")
            if state_dim != action_dim:
                raise ValueError(
                    "feature_map: the prediction s + a needs actions of the state's size"
                )
            self.move_length = bool(m.get("move_length", False))
        elif self.kind == "per_move":
            self.low = _vec(m["state_low"]), np.zeros(0)
            self.high = _vec(m["state_high"]), np.zeros(0)
            self.moves = np.asarray(m["moves"], dtype=np.float64)
            self.tolerance = float(m["tolerance"])
            if self.moves.ndim != 2 or self.moves.shape[1] != action_dim:
                raise ValueError(f"feature_map.moves: rows of {action_dim} numbers")
        elif self.kind == "action_and_rotation":
            self.low = np.zeros(0), _vec(m["action_low"])
            self.high = np.zeros(0), _vec(m["action_high"])
            self.angles = int(m["state_angle"]), int(m["action_angle"])
            self.tolerance = float(m["tolerance"])
        else:
            raise ValueError(f"unknown feature map {self.kind!r}")

    @property
    def dim(self) -> int:
        """How many features the map computes."""
        if self.kind == "unit_box":
            return (
                sum(len(c) for c in self.components)
                + int(self.action_length)
                + len(self.prediction)
                + int(self.move_length)
                + sum(i in self.periodic for i in [*self.components[0], *self.prediction])
            )
        if self.kind == "kinematic_prediction":
            return 3 * len(self.low[0]) + int(self.move_length)
        if self.kind == "per_move":
            return 3 * len(self.moves)
        return len(self.low[1]) + 1

    @property
    def uses_prediction(self) -> bool:
        """Whether ``φ`` reads the model's prediction ``ŝ' = f̂(s, a)``."""
        return self.kind == "unit_box" and (bool(self.prediction) or self.move_length)

    def _state_part(self, s: Array, components: list[int]) -> Array:
        """The listed state components in the unit box, an angle as ``((1 + cos)/2, (1 + sin)/2)``
        of ``2π`` times its unit value."""
        u = _unit(s, self.low[0], self.high[0])
        cols: list[Array] = []
        for i in components:
            if i in self.periodic:
                t = 2.0 * np.pi * u[:, i]
                cols += [0.5 * (1.0 + np.cos(t)), 0.5 * (1.0 + np.sin(t))]
            else:
                cols.append(u[:, i])
        return np.stack(cols, axis=1) if cols else np.zeros((len(s), 0))

    def __call__(self, s: Array, a: Array, predicted: Array | None = None) -> Array:
        if self.kind == "unit_box":
            parts = [
                self._state_part(s, self.components[0]),
                _unit(a, self.low[1], self.high[1])[:, self.components[1]],
            ]
            if self.action_length:
                # The listed action components' length, each over its largest magnitude (RMS).
                comps = self.components[1]
                reach = np.maximum(np.abs(self.low[1]), np.abs(self.high[1]))[comps]
                safe = np.where(reach > 0.0, reach, 1.0)
                share = np.where(reach > 0.0, a[:, comps] / safe, 0.0)
                length = np.minimum(np.sqrt(np.mean(share**2, axis=1)), 1.0)
                parts.append(length[:, None])
            if self.uses_prediction:
                assert predicted is not None
                parts.append(self._state_part(predicted, self.prediction))
                if self.move_length:
                    # The predicted move's weighted length over the state box's diagonal.
                    diff = predicted - s
                    for i in self.periodic:
                        period = self.high[0][i] - self.low[0][i]
                        if period > 0.0:
                            diff[:, i] -= period * np.round(diff[:, i] / period)
                    moved = np.sqrt(np.sum(self.weights * diff**2, axis=1))
                    diagonal = math.sqrt(
                        float(np.sum(self.weights * (self.high[0] - self.low[0]) ** 2))
                    )
                    fraction = moved / diagonal if diagonal > 0.0 else np.zeros(len(s))
                    parts.append(fraction[:, None])
            return np.hstack(parts)
        if self.kind == "kinematic_prediction":
            predicted = np.clip(s + a, self.low[0], self.high[0])
            parts = [
                _unit(s, self.low[0], self.high[0]),
                _unit(a, self.low[1], self.high[1]),
                _unit(predicted, self.low[0], self.high[0]),
            ]
            if self.move_length:
                # The predicted move's length over the longest commandable one (0 if none).
                moved = np.sum((predicted - s) ** 2, axis=1)
                longest = float(np.sum(np.maximum(np.abs(self.low[1]), np.abs(self.high[1])) ** 2))
                fraction = np.sqrt(moved / longest) if longest > 0.0 else np.zeros(len(s))
                parts.append(fraction[:, None])
            return np.hstack(parts)
        if self.kind == "per_move":
            k_moves = len(self.moves)
            near = np.all(np.abs(self.moves[None, :, :] - a[:, None, :]) <= self.tolerance, axis=2)
            k = np.where(near.any(axis=1), near.argmax(axis=1), 0)
            out = np.zeros((len(s), 3 * k_moves))
            rows = np.arange(len(s))
            unit = _unit(s, self.low[0], self.high[0])
            for i in range(min(2, unit.shape[1])):
                out[rows, 2 * k + i] = unit[:, i]
            out[rows, 2 * k_moves + k] = 1.0
            return out
        fa = np.clip(_unit(a, self.low[1], self.high[1]), 0.0, 1.0)
        rotates = np.abs(a[:, self.angles[1]] - s[:, self.angles[0]]) > self.tolerance
        return np.hstack([fa, rotates.astype(np.float64)[:, None]])


class ExportedModel:
    """A fitted MDE version read from its exported document; see the module documentation."""

    def __init__(self, document: Mapping[str, Any]) -> None:
        d = document
        if "error" in d and d.get("format") is None:
            error = d["error"]
            raise ValueError(f"not a model but the server's error: {error}")
        if d.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} document (format {d.get('format')!r})")
        predictor = d.get("predictor") or {}
        expected = FORMAT_VERSION_EXPERTS if "experts" in predictor else FORMAT_VERSION
        if d.get("format_version") != expected:
            raise ValueError(
                f"format_version {d.get('format_version')!r} is not supported for this "
                f"predictor (this client reads {FORMAT_VERSION} for one GP, "
                f"{FORMAT_VERSION_EXPERTS} for local experts); upgrade precond-client"
            )
        self.raw: dict[str, Any] = dict(d)
        """The document as read (what :meth:`save` writes)."""
        self.experiment_id = int(d["experiment_id"])
        self.model_version = int(d["model_version"])
        self.estimator = str(d["estimator"])
        """``exact``, ``sparse`` or ``local_experts``."""
        self.n_train = int(d["n_train"])
        self.d_max = float(d["d_max"])
        self.test_beta = float(d["test_beta"])
        """The experiment's test β, the default of :meth:`inside`."""
        self.state_dim = int(d["state_dim"])
        self.action_dim = int(d["action_dim"])
        self.feature_names = [str(n) for n in d["feature_names"]]
        self.model: str | None = None if d.get("model") is None else str(d["model"])
        """The further model whose precondition this is (pass *its* predictions where the
        features read one); ``None`` for the domain's own model's."""
        self._map = _FeatureMap(d["feature_map"], self.state_dim, self.action_dim)
        if "experts" in predictor:
            self._experts = [
                _Predictor(e, f"predictor.experts[{i}]") for i, e in enumerate(predictor["experts"])
            ]
            self._centres = np.array(predictor["centres"], dtype=np.float64).reshape(
                len(predictor["centres"]), -1
            )
            if not self._experts or len(self._centres) != len(self._experts):
                raise ValueError("predictor.experts: one per centre and at least one")
        else:
            self._experts = [_Predictor(predictor, "predictor")]
            self._centres = np.zeros((1, self._experts[0].dim))
        dim = self._experts[0].dim
        if any(e.dim != dim for e in self._experts) or self._centres.shape[1] != dim:
            raise ValueError(f"predictor: every expert and centre reads {dim} features")
        if len(self.feature_names) != dim:
            raise ValueError(f"{len(self.feature_names)} feature names for {dim} features")
        if self._map.dim != dim:
            raise ValueError(f"feature_map: computes {self._map.dim} features, the GP reads {dim}")

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> ExportedModel:
        """Reads the parsed JSON document."""
        return cls(document)

    def save(self, path: str | Path) -> None:
        """Writes the document as JSON (floats round-trip exactly)."""
        Path(path).write_text(json.dumps(self.raw), encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> ExportedModel:
        """Reads a document written by :meth:`save` (or saved from the endpoint)."""
        return cls(json.loads(Path(path).read_text(encoding="utf-8")))

    @property
    def uses_prediction(self) -> bool:
        """Whether the features read the model's prediction ``ŝ' = f̂(s, a)`` (a custom
        domain's ``features.prediction`` or ``move_length``): then every call needs
        ``predicted``, from the robot's own model, since the document does not hold it."""
        return self._map.uses_prediction

    def features(
        self, states: ArrayLike, actions: ArrayLike, predicted: ArrayLike | None = None
    ) -> Array:
        """``φ(s, a)`` per row, ``(N, D)``, exactly as the server computes it; ``predicted``
        holds the model's ``f̂(s, a)`` per row when :attr:`uses_prediction`."""
        s = _rows(states, self.state_dim, "states")
        a = _rows(actions, self.action_dim, "actions")
        if len(s) != len(a):
            raise ValueError(f"{len(s)} states for {len(a)} actions")
        p: Array | None = None
        if self._map.uses_prediction:
            if predicted is None:
                raise ValueError(
                    "predicted: the features read the model's prediction f̂(s, a); "
                    "pass one row per state"
                )
            p = _rows(predicted, self.state_dim, "predicted")
            if len(p) != len(s):
                raise ValueError(f"{len(p)} predictions for {len(s)} states")
        return self._map(s, a, p)

    def evaluate(
        self, states: ArrayLike, actions: ArrayLike, predicted: ArrayLike | None = None
    ) -> tuple[Array, Array]:
        """``(μ, σ)`` per row of ``states`` ``(N, n)`` and ``actions`` ``(N, m)`` (one row
        each may be a plain vector; ``predicted`` ``(N, n)`` when :attr:`uses_prediction`);
        ``σ`` includes the noise, as the server's."""
        x = self.features(states, actions, predicted)
        mu = np.empty(len(x))
        sigma = np.empty(len(x))
        for lo in range(0, len(x), _CHUNK):
            xc = x[lo : lo + _CHUNK]
            if len(self._experts) == 1:
                owner = np.zeros(len(xc), dtype=np.int64)
            else:
                d2 = ((xc[:, None, :] - self._centres[None, :, :]) ** 2).sum(axis=2)
                owner = np.argmin(d2, axis=1)  # ties to the first centre, as the server
            for e, expert in enumerate(self._experts):
                rows = np.nonzero(owner == e)[0]
                if len(rows) == 0:
                    continue
                m, s = expert.evaluate(xc[rows])
                mu[lo + rows] = m
                sigma[lo + rows] = s
        return mu, sigma

    def upper(
        self,
        states: ArrayLike,
        actions: ArrayLike,
        beta: float | None = None,
        predicted: ArrayLike | None = None,
    ) -> Array:
        """``μ + βσ`` per row (``beta`` default :attr:`test_beta`)."""
        mu, sigma = self.evaluate(states, actions, predicted)
        b = self.test_beta if beta is None else float(beta)
        upper: Array = mu + b * sigma
        return upper

    def inside(
        self,
        states: ArrayLike,
        actions: ArrayLike,
        beta: float | None = None,
        predicted: ArrayLike | None = None,
    ) -> NDArray[np.bool_]:
        """Whether each row lies in the precondition ``μ + βσ < d_max`` (NaN: outside)."""
        inside: NDArray[np.bool_] = self.upper(states, actions, beta, predicted) < self.d_max
        return inside

    def __repr__(self) -> str:
        return (
            f"ExportedModel(experiment {self.experiment_id}, version {self.model_version}, "
            f"{self.estimator}, {len(self._experts)} GP(s), "
            f"{sum(e.main.points.shape[0] for e in self._experts)} points, d_max={self.d_max})"
        )
