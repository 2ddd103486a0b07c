"""Logged data into an experiment (``precond_client.imports``), imported by the server's route:
round trips against the real server — CSV, Parquet, LeRobot v3 and Minari (HDF5) data in,
transitions read back equal with their labels and provenance, a second import storing nothing,
long episodes split, bad data named. The column conventions themselves are the server's
(``crates/precond/src/import``, tested there)."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import PrecondServer

from precond_client import Client
from precond_client.imports import (
    DatasetError,
    ImportFailed,
    LoggedEpisode,
    dataset_identity,
    import_episodes,
    write_episodes_csv,
)

MakeServer = Callable[..., PrecondServer]

GAIN = 0.8
"""The logged robot's pushes go 80 % of the way; its model (kinematic) expects all of it."""


Row = tuple[int, list[float], list[float], list[float]]
"""A logged step: episode, s, a, s_next."""


def logged(lengths: list[int], seed: int = 0) -> list[Row]:
    rng = np.random.default_rng(seed)
    rows = []
    for e, n in enumerate(lengths):
        s = rng.uniform(0.2, 0.8, 2)
        for _ in range(n):
            a = rng.uniform(-0.1, 0.1, 2)
            nxt = s + GAIN * a
            rows.append((e * 10, s.tolist(), a.tolist(), nxt.tolist()))
            s = nxt
    return rows


def write_csv(path: Path, rows: list[Row]) -> None:
    lines = ["episode,s_x,s_y,a_dx,a_dy,s_next_x,s_next_y"]
    lines += [f"{e},{s[0]!r},{s[1]!r},{a[0]!r},{a[1]!r},{n[0]!r},{n[1]!r}" for e, s, a, n in rows]
    path.write_text("\n".join(lines) + "\n")


def kinematic(client: Client, name: str) -> None:
    client.create_experiment(
        name=name,
        domain={"kind": "kinematic", "state_low": [-1, -1], "state_high": [2, 2]},
        learning={"batch_size": 1000},
    )


def expected_deviation(a: list[float]) -> float:
    return float(np.hypot((1 - GAIN) * a[0], (1 - GAIN) * a[1]))


# ---------------------------------------------------------------- episodes in memory (no server)


def test_episodes_are_written_in_preconds_own_columns_exactly(tmp_path: Path) -> None:
    # What the server's import reads for Minari's and any in-memory episodes: its own columns,
    # every number as the text that parses back to the same float.
    rng = np.random.default_rng(4)
    s = rng.uniform(0, 1, (3, 2))
    eps = [LoggedEpisode(5, "5", s, rng.uniform(-1, 1, (3, 1)), s + 1e-17 + 0.1)]
    path = tmp_path / "e.csv"
    write_episodes_csv(path, eps, ["x", "y"], ["u"])
    lines = path.read_text().splitlines()
    assert lines[0] == "episode,s.x,s.y,a.u,s_next.x,s_next.y"
    back = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    np.testing.assert_array_equal(back[:, 0], 5)
    np.testing.assert_array_equal(back[:, 1:], np.c_[eps[0].s, eps[0].a, eps[0].s_next])
    with pytest.raises(DatasetError, match=r"episode 5: a has shape \(3, 1\).*\(3, 2\)"):
        write_episodes_csv(path, eps, ["x", "y"], ["u", "v"])
    with pytest.raises(DatasetError, match=r"episode 5: .*no predictions"):
        write_episodes_csv(path, eps, ["x", "y"], ["u"], predicted=True)


def test_an_episode_from_observations_needs_one_more_observation() -> None:
    ep = LoggedEpisode.from_observations(3, np.zeros((5, 2)), np.ones((4, 1)))
    assert (len(ep), ep.s.shape, ep.s_next.shape, ep.a.shape) == (4, (4, 2), (4, 2), (4, 1))
    with pytest.raises(DatasetError, match="5 observations for 5 actions"):
        LoggedEpisode.from_observations(3, np.zeros((5, 2)), np.ones((5, 1)))


# ---------------------------------------------------------------- round trips


@pytest.mark.integration
def test_a_csv_import_round_trips_and_runs_once(
    make_server: MakeServer, tmp_path: Path, precond_binary: Path
) -> None:
    server = make_server()
    rows = logged([5, 3, 7])
    path = tmp_path / "pushes.csv"
    write_csv(path, rows)
    with Client(server.url) as client:
        kinematic(client, "csv")
        report = client.import_file(path, label="teleop", max_transitions=3, progress=False)
        # Episode 20's 7 transitions become 3 trajectories (3 + 3 + 1).
        assert (report.episodes, report.trajectories, report.created, report.replayed) == (
            3,
            2 + 1 + 3,
            6,
            0,
        )
        assert (report.transitions, report.split_episodes) == (15, 2)
        stored = list(client.transitions())
        assert len(stored) == len(rows)
        for t, (_, s, a, n) in zip(stored, rows, strict=True):
            np.testing.assert_array_equal(t.s, s)
            np.testing.assert_array_equal(t.a, a)
            np.testing.assert_array_equal(t.s_next, n)
            assert t.deviation == pytest.approx(expected_deviation(a), abs=1e-12)
        runs = list(client.runs())
        seen = sorted((r.source.episode, r.source.first_step, r.length) for r in runs if r.source)
        assert seen == [(0, 0, 3), (0, 3, 2), (10, 0, 3), (20, 0, 3), (20, 3, 3), (20, 6, 1)]
        assert all(r.status == "unsolicited" and not r.deviating for r in runs)
        traj = client.get_trajectory(runs[0].trajectory_id or 0)
        assert traj.source is not None
        assert (traj.source.dataset, traj.source.label) == (str(path.resolve()), "teleop")
        np.testing.assert_array_equal(traj.deviations, [x.deviation for x in traj.transitions])

        again = client.import_file(path, label="teleop", max_transitions=3, progress=False)
        assert (again.created, again.replayed) == (0, 6)
        assert again.trajectory_ids == report.trajectory_ids
        assert client.get_experiment().n_trajectories == 6
        with pytest.raises(ImportFailed, match="imported before and different now") as e:
            client.import_file(path, label="other", max_transitions=3, progress=False)
        assert e.value.cause.details["field"] == "source.label"

        assert client.get_experiment().n_trajectories == 6

        # precond import and the client key a file alike: the command line finds it all stored.
        out = subprocess.run(
            [str(precond_binary), "import", "--server", server.url, "--experiment",
             str(client.experiment_id), "--label", "teleop", "--max-transitions", "3",
             "--no-progress", str(path)],
            capture_output=True, text=True, check=True, timeout=60,
        )  # fmt: skip
        assert "(0 stored now, 6 already stored)" in out.stdout, out.stdout + out.stderr


@pytest.mark.integration
def test_a_grown_file_imports_only_what_is_new_and_a_changed_episode_is_refused(
    make_server: MakeServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    server = make_server()
    rows = logged([4, 3, 5, 2])
    path = tmp_path / "log.csv"
    write_csv(path, rows[:7])
    with Client(server.url) as client:
        kinematic(client, "grown")
        first = client.import_file(path, progress=False)
        assert (first.created, first.replayed) == (2, 0)
        write_csv(path, rows)
        # From another working directory: the same dataset.
        sub = tmp_path / "sub"
        sub.mkdir()
        monkeypatch.chdir(sub)
        grown = client.import_file(Path("..") / "log.csv", progress=False)
        assert (grown.created, grown.replayed) == (2, 2)
        assert client.get_experiment().n_trajectories == 4
        changed = list(rows)
        e, s, a, n = changed[8]
        changed[8] = (e, s, [a[0] + 0.01, a[1]], n)
        write_csv(path, changed)
        with pytest.raises(ImportFailed, match="episode 20 from step 0") as err:
            client.import_file(path, progress=False)
        assert err.value.cause.details["field"] == "transitions[1].a[0]"
        assert client.get_experiment().n_trajectories == 4


@pytest.mark.integration
def test_parquet_files_round_trip_flat_and_as_lists(
    make_server: MakeServer, tmp_path: Path
) -> None:
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    server = make_server()
    rows = logged([4, 6], seed=1)
    flat = pa.table(
        {
            "episode": [e for e, *_ in rows],
            **{f"s_{k}": [s[i] for _, s, _, _ in rows] for i, k in enumerate("xy")},
            **{f"a_d{k}": [a[i] for _, _, a, _ in rows] for i, k in enumerate("xy")},
            **{f"s_next_{k}": [n[i] for *_, n in rows] for i, k in enumerate("xy")},
        }
    )
    pq.write_table(flat, tmp_path / "flat.parquet", row_group_size=3)
    # Frames as LeRobot writes them: float32 lists, the next state is the next frame's.
    frames = pa.table(
        {
            "observation.state": pa.array([s for _, s, _, _ in rows], pa.list_(pa.float32())),
            "action": pa.array([a for _, _, a, _ in rows], pa.list_(pa.float32())),
            "episode_index": [e for e, *_ in rows],
        }
    )
    pq.write_table(frames, tmp_path / "frames.parquet", compression="zstd", row_group_size=4)
    with Client(server.url) as client:
        kinematic(client, "parquet")
        report = client.import_file(tmp_path / "flat.parquet", progress=False)
        assert (report.episodes, report.transitions) == (2, 10)
        stored = list(client.transitions())
        for t, (_, s, a, n) in zip(stored, rows, strict=True):
            np.testing.assert_array_equal(np.r_[t.s, t.a, t.s_next], np.r_[s, a, n])
        report = client.import_file(tmp_path / "frames.parquet", progress=False)
        assert (report.episodes, report.transitions) == (2, 3 + 5)
        new = list(client.transitions())[10:]
        f32 = [(e, np.asarray(s, np.float32), np.asarray(a, np.float32)) for e, s, a, _ in rows]
        expected = [
            (fs, fa, f32[k + 1][1])
            for k, (e, fs, fa) in enumerate(f32)
            if k + 1 < len(f32) and f32[k + 1][0] == e
        ]
        assert len(new) == len(expected)
        for t, (fs, fa, fn) in zip(new, expected, strict=True):
            np.testing.assert_array_equal(np.r_[t.s, t.a, t.s_next], np.r_[fs, fa, fn])
        assert client.import_file(tmp_path / "frames.parquet", progress=False).created == 0
        # A truncated file is named, in the package's own error.
        data = (tmp_path / "flat.parquet").read_bytes()
        (tmp_path / "half.parquet").write_bytes(data[: len(data) // 2])
        with pytest.raises(DatasetError, match=r"half.parquet: not a readable Parquet file"):
            client.import_file(tmp_path / "half.parquet", progress=False)


def write_lerobot(root: Path, episodes: list[np.ndarray]) -> None:
    """A LeRobot v3 dataset: meta/info.json and two data files, an episode across both."""
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(
        json.dumps({"codebase_version": "v3.0", "fps": 10, "total_episodes": len(episodes)})
    )
    rows = []
    for e, states in enumerate(episodes):
        for k, s in enumerate(states):
            nxt = states[k + 1] if k + 1 < len(states) else s
            rows.append({"observation.state": s.tolist(), "action": (nxt - s).tolist(),
                         "episode_index": e, "frame_index": k})  # fmt: skip
    half = len(rows) // 2 + 1
    chunk = root / "data" / "chunk-000"
    chunk.mkdir(parents=True)
    for i, part in enumerate([rows[:half], rows[half:]]):
        table = pa.table(
            {
                "observation.state": pa.array(
                    [r["observation.state"] for r in part], pa.list_(pa.float32())
                ),
                "action": pa.array([r["action"] for r in part], pa.list_(pa.float32())),
                "episode_index": pa.array([r["episode_index"] for r in part], pa.int64()),
                "frame_index": pa.array([r["frame_index"] for r in part], pa.int64()),
            }
        )
        pq.write_table(table, chunk / f"file-{i:03d}.parquet")


@pytest.mark.integration
def test_a_lerobot_dataset_imports_frame_to_frame(make_server: MakeServer, tmp_path: Path) -> None:
    pytest.importorskip("pyarrow")
    server = make_server()
    rng = np.random.default_rng(2)
    episodes = [
        np.cumsum(rng.uniform(-0.05, 0.05, (n, 2)), axis=0).astype(np.float32) + 0.5
        for n in (6, 1, 5)
    ]
    root = tmp_path / "pusht_sim"
    write_lerobot(root, episodes)
    with Client(server.url) as client:
        kinematic(client, "lerobot")
        report = client.import_lerobot(root, label="demo", progress=False)
        assert (report.episodes, report.skipped_episodes, report.transitions) == (2, 1, 5 + 4)
        stored = list(client.transitions())
        expected = [
            (ep[k], ep[k + 1] - ep[k], ep[k + 1]) for ep in episodes for k in range(len(ep) - 1)
        ]
        for t, (s, a, n) in zip(stored, expected, strict=True):
            np.testing.assert_array_equal(np.r_[t.s, t.a, t.s_next], np.r_[s, a, n])
        sources = sorted((r.source.dataset, r.source.episode) for r in client.runs() if r.source)
        assert sources == [("lerobot:pusht_sim", 0), ("lerobot:pusht_sim", 2)]
        assert client.import_lerobot(root, label="demo", progress=False).replayed == 2
    with pytest.raises(DatasetError, match="not a LeRobot dataset"):
        Client(server.url, experiment_id=1).import_lerobot(tmp_path)


@pytest.mark.integration
def test_a_minari_file_imports_with_h5py(make_server: MakeServer, tmp_path: Path) -> None:
    h5py = pytest.importorskip("h5py")
    server = make_server()
    rng = np.random.default_rng(3)
    path = tmp_path / "dataset" / "data" / "main_data.hdf5"
    path.parent.mkdir(parents=True)
    episodes = []
    with h5py.File(path, "w") as f:
        for i, n in enumerate((4, 6)):
            obs = np.cumsum(rng.uniform(-0.05, 0.05, (n + 1, 2)), axis=0) + 0.5
            act = rng.uniform(-0.1, 0.1, (n, 2))
            g = f.create_group(f"episode_{i}")
            # Goal-conditioned environments store a dict of observations.
            g.create_dataset("observations/observation", data=obs)
            g.create_dataset("observations/desired_goal", data=np.zeros((n + 1, 2)))
            g.create_dataset("actions", data=act)
            episodes.append((obs, act))
    with Client(server.url) as client:
        kinematic(client, "minari")
        report = client.import_minari(tmp_path / "dataset", progress=False)
        assert (report.episodes, report.transitions, report.created) == (2, 10, 2)
        stored = list(client.transitions())
        expected = [(o[k], a[k], o[k + 1]) for o, a in episodes for k in range(len(a))]
        for t, (s, a, n) in zip(stored, expected, strict=True):
            np.testing.assert_array_equal(np.r_[t.s, t.a, t.s_next], np.r_[s, a, n])
        assert {r.source.dataset for r in client.runs() if r.source} == {
            f"minari:{tmp_path / 'dataset'}"
        }
        assert client.import_minari(path, progress=False).replayed == 2, "the file is the dataset"
        with pytest.raises(DatasetError, match="desired_goal, observation"):
            client.import_minari(path, observation_key="achieved_goal", progress=False)


@pytest.mark.integration
def test_bad_data_is_named_and_refusals_say_which_episode(
    make_server: MakeServer, tmp_path: Path
) -> None:
    server = make_server()
    with Client(server.url) as client:
        kinematic(client, "bad")
        bad = tmp_path / "bad.csv"
        bad.write_text("episode,s_x,s_y,a_dx,a_dy\n0,0.1,0.1,0.05,0\n0,0.2,nan,0.05,0\n")
        with pytest.raises(DatasetError, match=r"bad.csv: line 3: s_y: NaN is not a finite number"):
            client.import_file(bad, progress=False)
        unsorted = tmp_path / "unsorted.csv"
        write_csv(unsorted, logged([2, 2]) + logged([1]))
        with pytest.raises(DatasetError, match="line 6: episode 0 appears again") as bad_row:
            client.import_file(unsorted, progress=False)
        # The episodes before the bad row were stored, and the error says so.
        assert bad_row.value.stored_before is not None
        assert bad_row.value.stored_before.created == 2
        outside = [LoggedEpisode(7, "7", np.array([[5.0, 0.1]]), np.zeros((1, 2)),
                                 np.array([[5.0, 0.1]]))]  # fmt: skip
        with pytest.raises(ImportFailed, match=r"logs episode 7 from step 0: 422") as e:
            import_episodes(client, outside, dataset="logs", dataset_id="x1", progress=False)
        assert e.value.cause.details["field"] == "transitions[0].s"
        with pytest.raises(ValueError, match="dataset_id"):
            import_episodes(client, outside, dataset="logs", dataset_id="no spaces")
    assert len(dataset_identity(str(bad))) == 16
    # A file larger than the server takes: what to do instead, and nothing stored.
    small = make_server(extra_args=["--max-import-bytes", "1000"])
    with Client(small.url) as client:
        kinematic(client, "small")
        big = tmp_path / "big.csv"
        write_csv(big, logged([200]))
        with pytest.raises(DatasetError, match=r"larger than the server takes \(1000 bytes"):
            client.import_file(big, progress=False)
        assert client.get_experiment().n_trajectories == 0


@pytest.mark.integration
def test_the_servers_import_route_and_the_client_key_a_file_alike(
    make_server: MakeServer, tmp_path: Path
) -> None:
    """``POST /v1/experiments/{id}/imports``, posted by hand as curl would, and
    ``Client.import_file`` key a file alike: the client finds every episode stored."""
    server = make_server()
    rows = logged([3, 4])
    path = tmp_path / "route.csv"
    write_csv(path, rows)
    with Client(server.url) as client:
        kinematic(client, "route")
        answer = httpx.post(
            f"{server.url}/v1/experiments/{client.experiment_id}/imports",
            params={"dataset": str(path.resolve()), "label": "teleop"},
            headers={"content-type": "text/csv"},
            content=path.read_bytes(),
            timeout=60,
        )
        assert answer.status_code == 200, answer.text
        report = answer.json()
        assert (report["episodes"], report["created"], report["transitions"]) == (2, 2, 7)
        again = client.import_file(path, label="teleop", progress=False)
        assert (again.created, again.replayed) == (0, 2)
        assert client.get_experiment().n_trajectories == 2
