"""Logged data into an experiment: CSV and Parquet files, LeRobot v3 and Minari datasets.

Every reader yields :class:`LoggedEpisode` values, one per episode, streaming (a CSV file row
by row, Parquet batch by batch, a Minari dataset episode by episode); :func:`import_episodes`
posts each as one trajectory, labelled by the experiment's own model on ingest like any other,
with its provenance (``source``: the dataset, the episode, the step it starts at, a label).

**Columns** (CSV and Parquet) are found by the conventions of ``precond import``: ``s.<name>``
/ ``s_<name>`` (state), ``a.<name>`` / ``a_<name>`` (action), ``s_next.<name>`` /
``s_next_<name>`` (next state), or LeRobot's ``observation.state`` and ``action`` (list
columns, or numbered scalar columns); episodes by the first of ``episode_index``,
``episode``, ``episode_id``, ``trajectory_id``. Without a next-state column a transition's
next state is the next row's state in the episode. Any of them can be named instead.

**Idempotent and resumable, per episode.** Each trajectory is posted under the
``Idempotency-Key`` ``import-<dataset id>-<episode>-<part>``. The dataset id is the first 16 hex
digits of the SHA-256 of the dataset's *name* (:func:`dataset_identity`) — for a file its
absolute path by default, the same key ``precond import`` uses for the same file; for a LeRobot
dataset its directory's absolute path; for a Minari dataset its HDF5 file's path or its id —,
never of its bytes: importing again, after an interruption, after the log grew or after a bad
row was fixed, stores only the episodes not stored yet, and an episode whose content changed
since it was stored is refused by name (:class:`ImportFailed`, the server's ``409`` naming the
first field that differs) rather than stored twice.

**Limits.** An episode longer than ``max_transitions`` (the server's ``--max-transitions``,
10 000 by default) or whose request would pass ``max_body_bytes`` is posted as several
trajectories, each with its ``first_step``; the report counts them and a warning says so. The
readers hand over at most ``max_transitions`` transitions of an episode at a time, so memory
is bounded by one posted part, not by the episode (a CSV or Parquet file; a Minari episode is
read whole by ``minari`` or ``h5py``).

Parquet and LeRobot need ``pyarrow`` (``pip install precond-client[parquet]``); Minari needs
``minari`` or ``h5py`` (``[minari]``); a progress bar needs ``tqdm`` (``[progress]``; else
progress is logged).
"""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import errors
from .models import Array, Source, mat
from .protocols import TrajectoryPoster

log = logging.getLogger("precond_client")

EPISODE_COLUMNS = ("episode_index", "episode", "episode_id", "trajectory_id")
"""Episode columns looked for, in order."""

MAX_TRANSITIONS = 10_000
"""Transitions per posted trajectory (the server's default ``--max-transitions``)."""

MAX_BODY_BYTES = 4 * 1024 * 1024
"""Largest request body (the server's default ``--max-body-bytes``)."""


class DatasetError(errors.PrecondError, ValueError):
    """The data cannot be imported as it is: a column missing or of the wrong size, a value
    that is no finite number, an episode whose rows are not consecutive. The message names
    the file, the row and the column."""


class ImportFailed(errors.PrecondError):
    """The server refused a trajectory of an import. Trajectories posted before it are
    stored (importing again skips them).

    Attributes:
        dataset: The dataset.
        episode: The episode.
        first_step: The step of the episode the refused trajectory started at.
        cause: The server's error (an :class:`~precond_client.errors.ApiError`).
    """

    def __init__(self, dataset: str, episode: int, first_step: int, cause: errors.ApiError) -> None:
        hint = ""
        if isinstance(cause, errors.Conflict):
            field = (cause.details or {}).get("field") if isinstance(cause.details, dict) else None
            hint = (
                " (imported before and different now: its rows, the column mapping or the "
                f"label changed{f' — first at {field}' if field else ''}; nothing was stored "
                "for it; import it under another dataset_name to keep both)"
            )
        super().__init__(f"{dataset} episode {episode} from step {first_step}: {cause}{hint}")
        self.dataset = dataset
        self.episode = episode
        self.first_step = first_step
        self.cause = cause


@dataclass(frozen=True)
class LoggedEpisode:
    """One episode of logged data: ``T`` transitions ``(s, a, s_next)``."""

    episode: int
    """Its index in the dataset (``source.episode``)."""
    key: str
    """Its part of the idempotency key (the episode's value as the data spells it)."""
    s: Array
    """States, ``(T, n)``."""
    a: Array
    """Actions, ``(T, m)``."""
    s_next: Array
    """Next states, ``(T, n)``."""
    s_pred: Array | None = None
    """The client's predictions ``(T, n)``, for an experiment whose model is the client's."""
    first_step: int = 0
    """The step of the episode its first transition is: a reader hands a long episode over in
    pieces of consecutive transitions, each starting where the one before ended."""

    def __len__(self) -> int:
        return len(self.s)

    @classmethod
    def from_observations(
        cls, episode: int, observations: Any, actions: Any, key: str | None = None
    ) -> LoggedEpisode:
        """An episode from ``T + 1`` observed states (the first before the first action) and
        ``T`` actions — Gymnasium's and Minari's layout."""
        obs, act = mat(observations), mat(actions)
        if len(obs) != len(act) + 1:
            raise DatasetError(
                f"episode {episode}: {len(obs)} observations for {len(act)} actions "
                "(need one more observation)"
            )
        return cls(episode, key or str(episode), obs[:-1], act, obs[1:])


@dataclass
class ImportReport:
    """What an import did."""

    episodes: int = 0
    """Episodes read with at least one transition."""
    trajectories: int = 0
    """Trajectories posted (an episode split in parts posts several)."""
    created: int = 0
    """Of those, stored by this import."""
    replayed: int = 0
    """Of those, already stored by an earlier one (nothing stored)."""
    transitions: int = 0
    """Transitions in the posted trajectories."""
    split_episodes: int = 0
    """Episodes posted as several trajectories."""
    skipped_episodes: int = 0
    """Episodes without a transition (a single frame)."""
    trajectory_ids: list[int] = field(default_factory=list)
    """The posted (or already stored) trajectories, in order."""


# ---------------------------------------------------------------- identity and keys


def dataset_identity(name: str) -> str:
    """The dataset id in the idempotency keys: the first 16 hex digits of the SHA-256 of the
    dataset's name (``precond import`` computes the same for the same name)."""
    return hashlib.sha256(name.encode()).hexdigest()[:16]


def default_dataset_name(path: str | Path) -> str:
    """A file's dataset name by default: its absolute path, links resolved (the same from any
    working directory, as ``precond import`` names it)."""
    return str(Path(path).resolve())


_PLAIN = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


def key_part(value: str) -> str:
    """An episode's part of an idempotency key: its value when short and plain, else ``h``
    and a hash (as ``precond import`` spells it)."""
    if _PLAIN.match(value):
        return value
    return "h" + hashlib.sha256(value.encode()).hexdigest()[:16]


def _episode_value(value: Any, ordinal: int) -> tuple[str, int]:
    """The episode's text and ``source.episode``: the value when it is a whole number ≥ 0,
    else its position in the data."""
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        x = float(value)
        if x.is_integer() and 0 <= x < 9e15:
            return str(int(x)), int(x)
        return repr(x), ordinal
    if value is None:
        return "0", ordinal
    text = str(value)
    try:
        return _episode_value(float(text), ordinal) if text.strip() else ("0", ordinal)
    except ValueError:
        return text, ordinal


# ---------------------------------------------------------------- columns


@dataclass(frozen=True)
class Vector:
    """How one vector of a row is read: scalar columns in order, or one list column."""

    columns: tuple[str, ...]
    is_list: bool = False

    def describe(self) -> str:
        return f"{self.columns[0]} (list)" if self.is_list else ", ".join(self.columns)


@dataclass(frozen=True)
class ColumnMapping:
    """The roles of a table's columns (see the module docs)."""

    state: Vector
    action: Vector
    next_state: Vector | None
    predicted: Vector | None
    episode: str | None

    def columns(self) -> list[str]:
        out = [*self.state.columns, *self.action.columns]
        for v in (self.next_state, self.predicted):
            if v is not None:
                out += v.columns
        if self.episode is not None:
            out.append(self.episode)
        return out

    def describe(self) -> str:
        nxt = self.next_state.describe() if self.next_state else "the next row's state"
        ep = f"episodes by {self.episode}" if self.episode else "one episode"
        return f"state <- {self.state.describe()}; action <- {self.action.describe()}; " + (
            f"next state <- {nxt}; {ep}"
        )


def _by_prefix(
    columns: Sequence[str],
    lists: set[str],
    prefixes: Sequence[str],
    names: Sequence[str],
    exclude: Sequence[str] = (),
) -> Vector | None:
    for p in prefixes:
        bare = p.rstrip("._")
        if bare in lists:
            return Vector((bare,), True)
    for p in prefixes:
        found = [
            (c, c[len(p) :])
            for c in columns
            if c not in lists
            and c.startswith(p)
            and len(c) > len(p)
            and not any(c.startswith(x) for x in exclude)
        ]
        if not found:
            continue
        suffixes = [s for _, s in found]
        if len(suffixes) == len(names) and set(suffixes) == set(names):
            found.sort(key=lambda cs: list(names).index(cs[1]))
        elif all(s.isdigit() for s in suffixes):
            found.sort(key=lambda cs: int(cs[1]))
        return Vector(tuple(c for c, _ in found))
    return None


def _given(columns: Sequence[str], lists: set[str], given: Sequence[str], what: str) -> Vector:
    missing = [g for g in given if g not in columns]
    if missing:
        raise DatasetError(f"{what}: no column {missing[0]!r} (the data has {', '.join(columns)})")
    if len(given) == 1 and given[0] in lists:
        return Vector((given[0],), True)
    return Vector(tuple(given))


def resolve_columns(
    columns: Sequence[str],
    lists: set[str],
    state_names: Sequence[str],
    action_names: Sequence[str],
    *,
    state: Sequence[str] | None = None,
    action: Sequence[str] | None = None,
    next_state: Sequence[str] | None = None,
    predicted: Sequence[str] | None = None,
    episode: str | None = None,
    client_side: bool = False,
) -> ColumnMapping:
    """Which columns are the state, the action, the next state, the prediction and the
    episode (``episode="none"``: one episode); raises :class:`DatasetError` naming what is
    missing and what the data has."""
    have = ", ".join(columns)

    def check(v: Vector | None, dim: int, what: str) -> Vector | None:
        if v is not None and not v.is_list and len(v.columns) != dim:
            raise DatasetError(
                f"{what}: {len(v.columns)} columns ({v.describe()}) for the experiment's "
                f"{dim} components"
            )
        return v

    n, m = len(state_names), len(action_names)
    s = check(
        _given(columns, lists, state, "state")
        if state
        else _by_prefix(columns, lists, ("s.", "s_"), state_names, ("s_next", "s_pred"))
        or _by_prefix(columns, lists, ("observation.state.", "observation.state_"), state_names),
        n,
        "the state columns",
    )
    if s is None:
        raise DatasetError(
            f"no state columns found (s.<name>, s_<name> or observation.state; the data has "
            f"{have}): name them with state=[...]"
        )
    a = check(
        _given(columns, lists, action, "action")
        if action
        else _by_prefix(columns, lists, ("a.", "a_"), action_names)
        or _by_prefix(columns, lists, ("action.", "action_"), action_names),
        m,
        "the action columns",
    )
    if a is None:
        raise DatasetError(
            f"no action columns found (a.<name>, a_<name> or action; the data has {have}): "
            "name them with action=[...]"
        )
    nxt = check(
        _given(columns, lists, next_state, "next_state")
        if next_state
        else _by_prefix(columns, lists, ("s_next.", "s_next_"), state_names)
        or _by_prefix(columns, lists, ("next.observation.state.",), state_names),
        n,
        "the next-state columns",
    )
    pred: Vector | None = None
    if client_side:
        pred = check(
            _given(columns, lists, predicted, "predicted")
            if predicted
            else _by_prefix(columns, lists, ("s_pred.", "s_pred_"), state_names),
            n,
            "the predicted-state columns",
        )
        if pred is None:
            raise DatasetError(
                "the experiment's model is the client's: every transition needs its "
                "prediction (s_pred.<name> columns, or predicted=[...])"
            )
    if episode == "none":
        ep = None
    elif episode is not None:
        if episode not in columns:
            raise DatasetError(f"episode: no column {episode!r} (the data has {have})")
        ep = episode
    else:
        ep = next((c for c in EPISODE_COLUMNS if c in columns), None)
    mapping = ColumnMapping(s, a, nxt, pred, ep)
    used = mapping.columns()
    twice = {c for c in used if used.count(c) > 1}
    if twice:
        raise DatasetError(f"the column {sorted(twice)[0]!r} is given two roles")
    return mapping


# ---------------------------------------------------------------- rows to episodes


def _vector(row: Mapping[str, Any], v: Vector, dim: int, where: str) -> list[float]:
    if v.is_list:
        value = row.get(v.columns[0])
        if value is None or isinstance(value, (str, bytes)):
            raise DatasetError(
                f"{where}, {v.columns[0]}: expected a list of numbers, got {value!r}"
            )
        out = [float(x) for x in value]
        if len(out) != dim:
            raise DatasetError(
                f"{where}, {v.columns[0]}: {len(out)} numbers for the experiment's {dim} components"
            )
    else:
        out = []
        for c in v.columns:
            value = row.get(c)
            try:
                out.append(float(value))  # type: ignore[arg-type]
            except (TypeError, ValueError):
                raise DatasetError(f"{where}, {c}: expected a number, got {value!r}") from None
    for k, x in enumerate(out):
        if not np.isfinite(x):
            name = f"{v.columns[0]}[{k}]" if v.is_list else v.columns[k]
            raise DatasetError(f"{where}, {name}: {x} is not a finite number")
    return out


def episodes_from_rows(
    rows: Iterable[Mapping[str, Any]],
    mapping: ColumnMapping,
    dims: tuple[int, int],
    where: str,
    chunk: int | None = None,
) -> Iterator[LoggedEpisode]:
    """Groups consecutive rows by episode into :class:`LoggedEpisode` values; ``where`` names
    the data in errors. With ``chunk``, an episode is handed over in pieces of at most
    ``chunk`` transitions (each with its ``first_step``), so memory holds one piece, not the
    episode."""
    seen: set[str] = set()
    current: tuple[str, int] | None = None
    s: list[list[float]] = []
    a: list[list[float]] = []
    nxt: list[list[float]] = []
    pred: list[list[float]] = []
    frames: list[list[float]] = []
    ordinal = 0
    first_step = 0

    def piece(final: bool) -> LoggedEpisode | None:
        """What is buffered of the current episode (all of it when ``final``; else every
        transition whose next state is known), the buffers emptied."""
        nonlocal s, a, nxt, pred, frames, first_step
        if current is None:
            return None
        if mapping.next_state is None:
            # Frames: each row's action leads to the next row's state; the last has no next,
            # and stays buffered for the next piece.
            states, actions = frames, a
            if len(states) < 2:
                if final:
                    return LoggedEpisode(
                        current[1],
                        current[0],
                        mat([], dims[0]),
                        mat([], dims[1]),
                        mat([], dims[0]),
                        first_step=first_step,
                    )
                return None
            out = LoggedEpisode(
                current[1],
                current[0],
                np.asarray(states[:-1], dtype=np.float64),
                np.asarray(actions[:-1], dtype=np.float64),
                np.asarray(states[1:], dtype=np.float64),
                np.asarray(pred[:-1], dtype=np.float64) if pred else None,
                first_step=first_step,
            )
            frames, a, pred = frames[-1:], a[-1:], pred[-1:]
        else:
            out = LoggedEpisode(
                current[1],
                current[0],
                np.asarray(s, dtype=np.float64),
                np.asarray(a, dtype=np.float64),
                np.asarray(nxt, dtype=np.float64),
                np.asarray(pred, dtype=np.float64) if pred else None,
                first_step=first_step,
            )
            s, a, nxt, pred = [], [], [], []
        first_step += len(out)
        return out

    def finish() -> LoggedEpisode | None:
        return piece(final=True)

    for i, row in enumerate(rows):
        at = f"{where} row {i + 1}"
        value = row.get(mapping.episode) if mapping.episode else None
        if mapping.episode and (value is None or value == ""):
            raise DatasetError(f"{at}, {mapping.episode}: no episode value")
        text, index = _episode_value(value, ordinal)
        if current is None or text != current[0]:
            done = finish()
            if done is not None:
                yield done
            if text in seen:
                raise DatasetError(
                    f"{at}: episode {text} appears again after another episode: sort the data "
                    "by episode (an episode's rows must be consecutive)"
                )
            seen.add(text)
            ordinal += 1
            current = (text, index)
            s, a, nxt, pred, frames = [], [], [], [], []
            first_step = 0
        state = _vector(row, mapping.state, dims[0], at)
        action = _vector(row, mapping.action, dims[1], at)
        if mapping.predicted is not None:
            pred.append(_vector(row, mapping.predicted, dims[0], at))
        if mapping.next_state is None:
            frames.append(state)
            a.append(action)
        else:
            s.append(state)
            a.append(action)
            nxt.append(_vector(row, mapping.next_state, dims[0], at))
        buffered = len(frames) - 1 if mapping.next_state is None else len(s)
        if chunk is not None and buffered >= chunk:
            part = piece(final=False)
            if part is not None:
                yield part
    done = finish()
    if done is not None:
        yield done


# ---------------------------------------------------------------- readers


def _csv_rows(path: Path) -> tuple[list[str], Iterator[dict[str, Any]]]:
    f = open(path, newline="", encoding="utf-8")  # noqa: SIM115 - closed by the generator
    reader = csv.DictReader(f, skipinitialspace=True)
    columns = [c.strip() for c in (reader.fieldnames or [])]
    reader.fieldnames = columns

    def rows() -> Iterator[dict[str, Any]]:
        with f:
            yield from reader

    return columns, rows()


def _parquet(path: Path) -> Any:
    try:
        import pyarrow.parquet as pq
    except ImportError as e:  # pragma: no cover - exercised without pyarrow
        raise ImportError(
            "reading Parquet needs pyarrow: pip install 'precond-client[parquet]'"
        ) from e
    try:
        return pq.ParquetFile(path)
    except FileNotFoundError:
        raise
    except Exception as e:  # pyarrow's ArrowInvalid, ArrowIOError, OSError
        raise DatasetError(f"{path}: not a readable Parquet file ({e})") from e


def _parquet_columns(pf: Any) -> tuple[list[str], set[str]]:
    import pyarrow as pa

    schema = pf.schema_arrow
    names = list(schema.names)
    lists = {
        f.name
        for f in schema
        if pa.types.is_list(f.type)
        or pa.types.is_large_list(f.type)
        or pa.types.is_fixed_size_list(f.type)
    }
    return names, lists


def _parquet_rows(pf: Any, columns: list[str], batch_size: int = 4096) -> Iterator[dict[str, Any]]:
    for batch in pf.iter_batches(batch_size=batch_size, columns=columns):
        yield from batch.to_pylist()


def read_table(
    path: str | Path,
    state_names: Sequence[str],
    action_names: Sequence[str],
    *,
    format: str | None = None,
    client_side: bool = False,
    chunk: int | None = None,
    **mapping: Any,
) -> tuple[ColumnMapping, Iterator[LoggedEpisode]]:
    """A CSV or Parquet file's mapping and its episodes, streamed (``format``: ``csv`` or
    ``parquet``; default by extension), a long episode in pieces of at most ``chunk``
    transitions. ``mapping`` takes ``state``, ``action``, ``next_state``, ``predicted`` and
    ``episode`` as in :func:`resolve_columns`."""
    p = Path(path)
    fmt = format or ("parquet" if p.suffix.lower() in (".parquet", ".pq") else "csv")
    if fmt == "parquet":
        pf = _parquet(p)
        columns, lists = _parquet_columns(pf)
        m = resolve_columns(
            columns, lists, state_names, action_names, client_side=client_side, **mapping
        )
        rows: Iterable[Mapping[str, Any]] = _parquet_rows(pf, m.columns())
    elif fmt == "csv":
        columns, csv_rows = _csv_rows(p)
        m = resolve_columns(
            columns, set(), state_names, action_names, client_side=client_side, **mapping
        )
        rows = csv_rows
    else:
        raise ValueError(f"format {format!r}: use 'csv' or 'parquet'")
    return m, episodes_from_rows(rows, m, (len(state_names), len(action_names)), str(p), chunk)


def lerobot_files(root: str | Path) -> list[Path]:
    """The Parquet files of a LeRobot v3 dataset (``data/chunk-*/file-*.parquet``), in order;
    raises :class:`DatasetError` when ``root`` is no LeRobot dataset."""
    r = Path(root)
    info = r / "meta" / "info.json"
    if not info.is_file():
        raise DatasetError(f"{r}: no meta/info.json, not a LeRobot dataset")
    version = str(json.loads(info.read_text(encoding="utf-8")).get("codebase_version", ""))
    if version and not version.startswith("v3"):
        log.warning("%s: codebase_version %s, read as v3 (data/**/*.parquet)", r, version)
    files = sorted((r / "data").glob("**/*.parquet"))
    if not files:
        raise DatasetError(f"{r}: no Parquet files under data/")
    return files


def read_lerobot(
    root: str | Path,
    state_dim: int,
    action_dim: int,
    *,
    state: str = "observation.state",
    action: str = "action",
    chunk: int | None = None,
) -> Iterator[LoggedEpisode]:
    """The episodes of a LeRobot v3 dataset: frames of ``data/**/*.parquet`` grouped by
    ``episode_index``; a transition goes from a frame's ``state`` with its ``action`` to the
    next frame's ``state`` in the same episode (an episode may span files)."""
    files = lerobot_files(root)
    for f in files:
        columns, _ = _parquet_columns(_parquet(f))
        for c in (state, action, "episode_index"):
            if c not in columns:
                raise DatasetError(f"{f}: no column {c!r} (the file has {', '.join(columns)})")
    mapping = ColumnMapping(
        Vector((state,), True), Vector((action,), True), None, None, "episode_index"
    )

    def rows() -> Iterator[Mapping[str, Any]]:
        for f in files:
            yield from _parquet_rows(_parquet(f), [state, action, "episode_index"])

    return episodes_from_rows(rows(), mapping, (state_dim, action_dim), str(root), chunk)


def _observations(obs: Any, key: str | None, where: str) -> Array:
    """Minari observations as a ``(T + 1, n)`` array: an array as it is, a dict by ``key``."""
    if isinstance(obs, Mapping) or hasattr(obs, "keys"):
        keys = list(obs.keys())
        if key is None:
            if "observation" in keys:
                key = "observation"
            else:
                raise DatasetError(
                    f"{where}: observations are a dict ({', '.join(keys)}): pick one with "
                    "observation_key="
                )
        if key not in keys:
            raise DatasetError(f"{where}: no observation {key!r} (the dict has {', '.join(keys)})")
        obs = obs[key]
    a = np.asarray(obs, dtype=np.float64)
    return a.reshape(len(a), -1)


def read_minari(
    dataset: str | Path, *, observation_key: str | None = None
) -> tuple[str, str, Iterator[LoggedEpisode]]:
    """The episodes of a Minari dataset as ``(name, dataset id, episodes)``: by its id with
    ``minari`` installed (``minari.load_dataset``), or, with ``h5py``, from its HDF5 file (a
    ``main_data.hdf5`` or a dataset directory holding ``data/main_data.hdf5``): each episode's
    ``observations`` (``T + 1``; a dict picks ``observation_key``) and ``actions`` (``T``)."""
    p = Path(dataset)
    h5 = p if p.is_file() else p / "data" / "main_data.hdf5"
    if h5.is_file():
        try:
            import h5py
        except ImportError as e:  # pragma: no cover - exercised without h5py
            raise ImportError(
                "reading a Minari file needs h5py: pip install 'precond-client[minari]'"
            ) from e

        def from_file() -> Iterator[LoggedEpisode]:
            with h5py.File(h5, "r") as f:
                names = sorted(
                    (k for k in f if k.startswith("episode_")), key=lambda k: int(k.split("_")[1])
                )
                for name in names:
                    group = f[name]
                    where = f"{h5} {name}"
                    for part in ("observations", "actions"):
                        if part not in group:
                            raise DatasetError(f"{where}: no {part}")
                    obs = group["observations"]
                    obs = {k: obs[k][()] for k in obs} if hasattr(obs, "keys") else obs[()]
                    index = int(name.split("_")[1])
                    yield LoggedEpisode.from_observations(
                        index,
                        _observations(obs, observation_key, where),
                        np.asarray(group["actions"][()], dtype=np.float64).reshape(
                            len(group["actions"]), -1
                        ),
                    )

        # A dataset is named by its directory, whether given as it or as its file.
        named = h5.parent.parent if (h5.name, h5.parent.name) == ("main_data.hdf5", "data") else h5
        return f"minari:{named}", dataset_identity(str(h5.resolve())), from_file()
    try:
        import minari
    except ImportError as e:
        raise DatasetError(
            f"{dataset}: no Minari HDF5 file there, and minari is not installed to load it by "
            "id (pip install 'precond-client[minari]')"
        ) from e
    ds = minari.load_dataset(str(dataset))
    ident = dataset_identity(f"minari:{dataset}")

    def from_minari() -> Iterator[LoggedEpisode]:
        for ep in ds.iterate_episodes():
            where = f"{dataset} episode {ep.id}"
            yield LoggedEpisode.from_observations(
                int(ep.id),
                _observations(ep.observations, observation_key, where),
                np.asarray(ep.actions, dtype=np.float64).reshape(len(ep.actions), -1),
            )

    return f"minari:{dataset}", ident, from_minari()


# ---------------------------------------------------------------- posting


def _parts(
    ep: LoggedEpisode, max_transitions: int, max_body_bytes: int
) -> Iterator[tuple[int, list[dict[str, Any]]]]:
    """An episode's transitions as JSON, in parts of at most ``max_transitions`` and about
    ``max_body_bytes``: ``(first_step, transitions)``."""
    budget = max(1024, max_body_bytes - 16 * 1024)
    part: list[dict[str, Any]] = []
    size, first = 0, 0
    for k in range(len(ep)):
        t: dict[str, Any] = {
            "s": [float(x) for x in ep.s[k]],
            "a": [float(x) for x in ep.a[k]],
            "s_next": [float(x) for x in ep.s_next[k]],
        }
        if ep.s_pred is not None:
            t["s_pred"] = [float(x) for x in ep.s_pred[k]]
        n = len(json.dumps(t)) + 1
        if part and (len(part) >= max_transitions or size + n > budget):
            yield first, part
            first += len(part)
            part, size = [], 0
        part.append(t)
        size += n
    if part:
        yield first, part


def _progress(total: int | None, desc: str, show: bool | None) -> Any:
    if show is False:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=desc, unit="episode")


def import_episodes(
    client: TrajectoryPoster,
    episodes: Iterable[LoggedEpisode],
    *,
    dataset: str,
    dataset_id: str,
    label: str | None = None,
    max_transitions: int = MAX_TRANSITIONS,
    max_body_bytes: int = MAX_BODY_BYTES,
    progress: bool | None = None,
    total: int | None = None,
    on_posted: Callable[[LoggedEpisode, int], None] | None = None,
) -> ImportReport:
    """Posts each episode as one trajectory (or several, split at the limits) into the
    client's current experiment, under the key ``import-<dataset_id>-<episode>-<part>`` with
    ``source = {dataset, episode, first_step, label}``; see the module docs.

    ``progress``: a tqdm bar when tqdm is installed (``None``: if it is; ``False``: never);
    otherwise progress is logged every 100 episodes. ``on_posted(episode, trajectory_id)`` is
    called after each posted part. Raises :class:`ImportFailed` when the server refuses a
    trajectory (those posted before it stay stored)."""
    if not _PLAIN.match(dataset_id):
        raise ValueError(
            f"dataset_id {dataset_id!r}: letters, digits, '.', '_' and '-' only, at most 64"
        )
    report = ImportReport()
    bar = _progress(total, dataset, progress)
    # The episode being posted (pieces of one episode arrive one after the other): its key,
    # the parts posted so far and its transitions.
    episode_key: str | None = None
    parts_posted = 0
    episode_length = 0

    def end_episode() -> None:
        if episode_key is None:
            return
        if parts_posted > 1:
            report.split_episodes += 1
            log.warning(
                "%s episode %s: %d transitions, posted as %d trajectories (at most %d "
                "transitions or %d bytes each)",
                dataset,
                episode_key,
                episode_length,
                parts_posted,
                max_transitions,
                max_body_bytes,
            )
        report.episodes += 1
        if bar is not None:
            bar.update(1)
            bar.set_postfix(stored=report.created, already=report.replayed)
        elif report.episodes % 100 == 0:
            log.info(
                "%s: %d episodes (%d stored, %d already there)",
                dataset,
                report.episodes,
                report.created,
                report.replayed,
            )

    try:
        for ep in episodes:
            if ep.key != episode_key or ep.first_step == 0:
                end_episode()
                episode_key, parts_posted, episode_length = None, 0, 0
            if len(ep) == 0:
                if ep.first_step == 0:
                    report.skipped_episodes += 1
                continue
            episode_key = ep.key
            episode_length += len(ep)
            for first, transitions in _parts(ep, max(1, max_transitions), max_body_bytes):
                step = ep.first_step + first
                source = Source(dataset, ep.episode, step, label)
                try:
                    created = client.post_trajectory(
                        transitions,
                        idempotency_key=f"import-{dataset_id}-{key_part(ep.key)}-{parts_posted}",
                        source=source,
                    )
                except errors.ApiError as e:
                    raise ImportFailed(dataset, ep.episode, step, e) from e
                parts_posted += 1
                report.trajectories += 1
                report.transitions += created.n_transitions
                report.trajectory_ids.append(created.id)
                if created.replayed:
                    report.replayed += 1
                else:
                    report.created += 1
                if on_posted is not None:
                    on_posted(ep, created.id)
        end_episode()
    finally:
        if bar is not None:
            bar.close()
    log.info(
        "%s: %d episodes as %d trajectories (%d transitions): %d stored, %d already there",
        dataset,
        report.episodes,
        report.trajectories,
        report.transitions,
        report.created,
        report.replayed,
    )
    return report
