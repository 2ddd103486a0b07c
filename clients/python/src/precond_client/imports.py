"""Logged data into an experiment: CSV and Parquet files, LeRobot v3 and Minari datasets.

The import itself runs on the server (``POST /v1/experiments/{id}/imports``), in the code
``precond import`` runs where the files are: one implementation of the column conventions, the
episodes, the keys and the splitting, whichever tool a lab uses. This module hands it the data:

- a CSV or Parquet file as it is (:meth:`~precond_client.Client.import_file`);
- a LeRobot v3 dataset as one Parquet file of its ``observation.state``, ``action`` and
  ``episode_index`` columns, its data files concatenated (an episode may span two;
  :func:`lerobot_table`);
- episodes in memory — a Minari dataset's (:func:`read_minari`), or any
  :class:`LoggedEpisode` — as a CSV file of precond's own columns (:func:`import_episodes`).

**Columns** are found as ``precond import`` finds them: ``s.<name>`` / ``s_<name>`` (state),
``a.<name>`` / ``a_<name>`` (action), ``s_next.<name>`` / ``s_next_<name>`` (next state), or
LeRobot's ``observation.state`` and ``action`` (list columns, or numbered scalar columns);
episodes by the first of ``episode_index``, ``episode``, ``episode_id``, ``trajectory_id``.
Without a next-state column a transition's next state is the next row's state in the episode.
Any of them can be named instead.

**Idempotent and resumable, per episode.** The server stores each trajectory under the
``Idempotency-Key`` ``import-<dataset id>-<episode>-<part>``, the dataset id the first 16 hex
digits of the SHA-256 of the dataset's *name* (:func:`dataset_identity`) — for a file its
absolute path by default, the key ``precond import`` uses for the same file —, never of its
bytes: importing again, after an interruption, after the log grew or after a bad row was fixed,
stores only the episodes not stored yet, and an episode whose content changed since it was
stored is refused by name (:class:`ImportFailed`, the server's ``409`` naming the first field
that differs) rather than stored twice.

**Limits.** A file is sent whole, as the request's body, up to the server's
``--max-import-bytes`` (256 MiB by default; a larger log: ``precond import``, which streams it
from disk, or a higher limit). An episode longer than ``max_transitions`` (at most the server's
``--max-transitions``, 10 000 by default) is stored as several trajectories, each with its
``first_step``. The client holds nothing of a file in memory; a LeRobot dataset is rewritten a
batch at a time, a Minari episode is read whole by ``minari`` or ``h5py``.

LeRobot needs ``pyarrow`` (``pip install precond-client[parquet]``); Minari needs ``minari`` or
``h5py`` (``[minari]``); a progress bar of the upload needs ``tqdm`` (``[progress]``).
"""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import re
import tempfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import errors
from .execution import client_side
from .models import Array, ImportReport, ImportStop, mat
from .protocols import FileImporter

log = logging.getLogger("precond_client")

_PLAIN = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
"""A dataset id the server takes as it is (and an episode key it does not hash)."""


class DatasetError(errors.PrecondError, ValueError):
    """The data cannot be imported as it is: a column missing or of the wrong size, a value
    that is no finite number, an episode whose rows are not consecutive. The message names
    the dataset, the line or row and the column.

    Attributes:
        stored_before: What the import stored before the bad row (an :class:`ImportReport`;
            importing again skips it), when the server read that far.
    """

    def __init__(self, message: str, stored_before: ImportReport | None = None) -> None:
        super().__init__(message)
        self.stored_before = stored_before


class ImportFailed(errors.PrecondError):
    """The server refused a trajectory of an import. Trajectories stored before it stay
    stored (importing again skips them).

    Attributes:
        dataset: The dataset.
        episode: The episode.
        first_step: The step of the episode the refused trajectory started at.
        cause: The server's error (an :class:`~precond_client.errors.ApiError`; its
            ``details`` are the refusal's, e.g. ``details["field"]``).
        stored_before: What the import stored before it (an :class:`ImportReport`), as the
            server said.
    """

    def __init__(
        self,
        dataset: str,
        episode: int,
        first_step: int,
        cause: errors.ApiError,
        stored_before: ImportReport | None = None,
    ) -> None:
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
        self.stored_before = stored_before


@dataclass(frozen=True)
class LoggedEpisode:
    """One episode of logged data: ``T`` transitions ``(s, a, s_next)``."""

    episode: int
    """Its index in the dataset (``source.episode``)."""
    key: str
    """Its value in the episode column, which keys its trajectories; a whole number ≥ 0 is
    also its ``source.episode`` (the server's rule), so keep it ``str(episode)``."""
    s: Array
    """States, ``(T, n)``."""
    a: Array
    """Actions, ``(T, m)``."""
    s_next: Array
    """Next states, ``(T, n)``."""
    s_pred: Array | None = None
    """The client's predictions ``(T, n)``, for an experiment whose model is the client's."""

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


# ---------------------------------------------------------------- identity


def dataset_identity(name: str) -> str:
    """The dataset id in the idempotency keys: the first 16 hex digits of the SHA-256 of the
    dataset's name (the server and ``precond import`` compute the same for the same name)."""
    return hashlib.sha256(name.encode()).hexdigest()[:16]


def default_dataset_name(path: str | Path) -> str:
    """A file's dataset name by default: its absolute path, links resolved (the same from any
    working directory, as ``precond import`` names it)."""
    return str(Path(path).resolve())


def check_dataset_id(dataset_id: str) -> None:
    """Raises ``ValueError`` for a dataset id the server would refuse (before any upload)."""
    if not _PLAIN.match(dataset_id):
        raise ValueError(
            f"dataset_id {dataset_id!r}: letters, digits, '.', '_' and '-' only, at most 64"
        )


def import_error(dataset: str, e: errors.ApiError) -> errors.PrecondError:
    """The error of a refused import: :class:`ImportFailed` when the server stopped at a
    refused episode, :class:`DatasetError` when it could not read the data or the file is
    larger than it takes, else ``e``."""
    details = e.details if isinstance(e.details, dict) else {}
    if isinstance(e, errors.PayloadTooLarge):
        limit = details.get("limit_bytes", "its")
        return DatasetError(
            f"{dataset}: larger than the server takes ({limit} bytes, --max-import-bytes): "
            "import it with `precond import`, which streams files of any size, or ask the "
            "operator for a higher limit"
        )
    stop = ImportStop.from_json(details["import"]) if "import" in details else None
    before = stop.stored_before if stop else None
    if stop and stop.episode is not None:
        return ImportFailed(dataset, stop.episode, stop.first_step or 0, e, before)
    if details.get("field") == "body":
        stored = f" ({before.trajectories} trajectories stored before it)" if before else ""
        return DatasetError(f"{dataset}: {details.get('reason', e.message)}{stored}", before)
    return e


# ---------------------------------------------------------------- LeRobot


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


def lerobot_table(root: str | Path, out: Path, columns: Sequence[str]) -> None:
    """Writes the ``columns`` of a LeRobot v3 dataset's data files, in order, to one Parquet
    file ``out`` (a batch at a time): an episode that spans two files is one episode there."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as e:  # pragma: no cover - exercised without pyarrow
        raise ImportError(
            "reading a LeRobot dataset needs pyarrow: pip install 'precond-client[parquet]'"
        ) from e
    writer = None
    try:
        for f in lerobot_files(root):
            try:
                pf = pq.ParquetFile(f)
            except (OSError, pa.ArrowInvalid) as e:
                raise DatasetError(f"{f}: not a readable Parquet file ({e})") from e
            names = pf.schema_arrow.names
            for c in columns:
                if c not in names:
                    raise DatasetError(f"{f}: no column {c!r} (the file has {', '.join(names)})")
            for batch in pf.iter_batches(columns=list(columns)):
                table = pa.Table.from_batches([batch])
                if writer is None:
                    writer = pq.ParquetWriter(out, table.schema)
                writer.write_table(table.cast(writer.schema))
    finally:
        if writer is not None:
            writer.close()
    if writer is None:
        raise DatasetError(f"{root}: no frames in its data files")


# ---------------------------------------------------------------- Minari


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


# ---------------------------------------------------------------- episodes in memory


def write_episodes_csv(
    out: Path,
    episodes: Iterable[LoggedEpisode],
    state_names: Sequence[str],
    action_names: Sequence[str],
    *,
    predicted: bool = False,
) -> None:
    """Writes ``episodes`` to ``out`` as a CSV file in precond's own columns (``episode``,
    ``s.<name>``, ``a.<name>``, ``s_next.<name>``, and ``s_pred.<name>`` when ``predicted``),
    every number as Python's shortest exact text, an episode at a time. An episode of other
    dimensions than the names is refused by its index."""
    n, m = len(state_names), len(action_names)
    header = ["episode"]
    header += [f"s.{x}" for x in state_names] + [f"a.{x}" for x in action_names]
    header += [f"s_next.{x}" for x in state_names]
    if predicted:
        header += [f"s_pred.{x}" for x in state_names]
    with out.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(header)
        for ep in episodes:
            parts = [ep.s, ep.a, ep.s_next]
            if predicted:
                if ep.s_pred is None:
                    raise DatasetError(
                        f"episode {ep.episode}: the experiment's model is the client's, and "
                        "the episode has no predictions (s_pred)"
                    )
                parts.append(ep.s_pred)
            dims = [n, m, n, n][: len(parts)]
            for what, x, d in zip(("s", "a", "s_next", "s_pred"), parts, dims, strict=False):
                if x.ndim != 2 or x.shape[1] != d or len(x) != len(ep.s):
                    raise DatasetError(
                        f"episode {ep.episode}: {what} has shape {x.shape}, the experiment "
                        f"needs ({len(ep.s)}, {d})"
                    )
            for k in range(len(ep)):
                row = [ep.key]
                for x in parts:
                    row += [repr(float(v)) for v in x[k]]
                w.writerow(row)


def import_episodes(
    client: FileImporter,
    episodes: Iterable[LoggedEpisode],
    *,
    dataset: str,
    dataset_id: str,
    label: str | None = None,
    max_transitions: int | None = None,
    progress: bool | None = None,
) -> ImportReport:
    """Imports episodes held in memory into the client's current experiment: written to a
    temporary CSV file in precond's own columns (:func:`write_episodes_csv`) and imported
    by the server as a file is, under the dataset name ``dataset`` and the id ``dataset_id``
    in the keys (see the module docs). Raises :class:`ImportFailed` when the server refuses a
    trajectory (those stored before it stay stored)."""
    check_dataset_id(dataset_id)
    exp = client.get_experiment()
    with tempfile.TemporaryDirectory(prefix="precond-import-") as tmp:
        path = Path(tmp) / "episodes.csv"
        write_episodes_csv(
            path,
            episodes,
            exp.state_space.names,
            exp.action_space.names,
            predicted=client_side(exp),
        )
        return client.import_file(
            path,
            format="csv",
            label=label,
            dataset_name=dataset,
            dataset_id=dataset_id,
            max_transitions=max_transitions,
            progress=progress,
        )
