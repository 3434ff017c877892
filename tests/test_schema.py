"""HDF5 split files: exact round trips, atomic writes and refusal of bad files."""
from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from ggns.data.schema import (
    SCHEMA_VERSION,
    DatasetError,
    SplitReader,
    SplitWriter,
    read_trajectories,
)
from ggns.trajectory import Trajectory
from ggns.geometry import cell_edges

SRC = Path(__file__).resolve().parents[1] / "src"
CONFIG = {"scene": "plate", "num_steps": 3, "camera": {"resolution": [32, 24]}, "noise": None}


def make_trajectory(dim: int, seed: int = 0) -> Trajectory:
    """A tiny valid trajectory: T=3 steps, ragged point clouds of 2, 0 and 3 points."""
    rng = np.random.default_rng(seed)
    if dim == 2:
        rest = np.array([[0.0, 0.0], [0.5, 0.0], [0.5, 0.5], [0.0, 0.5]])
        cells = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
        faces = np.array([[0, 1]], dtype=np.int64)
    else:
        rest = np.array([[0.0, 0.0, 0.0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]])
        cells = np.array([[0, 1, 2, 3]], dtype=np.int64)
        faces = np.array([[0, 1, 2]], dtype=np.int64)
    t, k = 3, faces.shape[1]
    counts = [2, 0, 3]
    return Trajectory(
        rest_positions=rest,
        cells=cells,
        edges=cell_edges(cells),
        positions=rest + 0.01 * rng.standard_normal((t, *rest.shape)),
        fixed=np.arange(len(rest)) == 0,
        collider_faces=faces,
        collider_positions=rng.uniform(-1, 1, (t, k, dim)),
        points=rng.uniform(-1, 1, (sum(counts), dim)).astype(np.float32),
        point_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        youngs_modulus=float(rng.uniform(1e4, 1e6)),
        poissons_ratio=0.3,
        seed=seed,
        params={"thickness": 0.1, "num_holes": 2, "material": "rubber", "clamped": True},
        diagnostics={
            "residual": rng.uniform(0, 1e-8, t),
            "newton_iterations": np.array([0, 3, 4], dtype=np.int64),
        },
    )


def write(path: Path, trajectories: list[Trajectory], dim: int, **kwargs) -> None:
    with SplitWriter(path, scene="plate", split="train", dim=dim, generator_config=CONFIG,
                     **kwargs) as w:
        for traj in trajectories:
            w.append(traj)


def assert_same(a: Trajectory, b: Trajectory) -> None:
    for f in dataclasses.fields(Trajectory):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        elif f.name == "diagnostics":
            assert x.keys() == y.keys()
            for key in x:
                assert x[key].dtype == y[key].dtype
                np.testing.assert_array_equal(x[key], y[key])
        else:
            assert x == y and type(x) is type(y), f.name
    for key, value in a.params.items():
        assert type(b.params[key]) is type(value), key


@pytest.fixture
def valid_file(tmp_path: Path) -> Path:
    path = tmp_path / "train.h5"
    write(path, [make_trajectory(2, seed) for seed in range(3)], dim=2)
    return path


@pytest.mark.parametrize("dim", [2, 3])
def test_round_trip_is_exact(tmp_path: Path, dim: int) -> None:
    trajectories = [make_trajectory(dim, seed) for seed in range(3)]
    path = tmp_path / "sub" / "dir" / "test.h5"  # parent directories are created
    write(path, trajectories, dim)
    read = read_trajectories(path)
    assert len(read) == 3
    for a, b in zip(trajectories, read):
        assert_same(a, b)
    assert read[0].point_cloud(1).shape == (0, dim)
    np.testing.assert_array_equal(read[0].point_cloud(2), trajectories[0].points[2:5])
    assert os.listdir(path.parent) == ["test.h5"]


def test_reader_attributes_and_indexing(valid_file: Path) -> None:
    with SplitReader(valid_file) as reader:
        assert (reader.scene, reader.split, reader.dim) == ("plate", "train", 2)
        assert reader.schema_version == SCHEMA_VERSION
        assert reader.generator_config == CONFIG
        assert len(reader) == 3
        assert reader[-1].seed == 2
        assert [t.seed for t in reader] == [0, 1, 2]
        with pytest.raises(IndexError):
            reader[3]
    with h5py.File(valid_file) as f:
        assert f.attrs["format"] == "ggns-trajectories" and f.attrs["complete"]
        assert f.attrs["num_trajectories"] == 3
        assert f["trajectories/000002/mesh/positions"].attrs["units"] == "normalized"


def _read_in_child(reader: SplitReader) -> None:
    os._exit(0 if reader[1].seed == 1 else 1)


def test_reader_is_picklable_and_fork_safe(valid_file: Path) -> None:
    reader = SplitReader(valid_file)
    assert reader[0].seed == 0  # the handle is open now
    clone = pickle.loads(pickle.dumps(reader))
    assert_same(clone[0], reader[0])
    child = multiprocessing.get_context("fork").Process(target=_read_in_child, args=(reader,))
    child.start()
    child.join(10)
    assert child.exitcode == 0
    assert reader[2].seed == 2
    reader.close()
    clone.close()


def test_overwrite_refused_keeps_old_file(valid_file: Path) -> None:
    before = valid_file.read_bytes()
    with pytest.raises(FileExistsError, match="train.h5"):
        write(valid_file, [make_trajectory(2, 7)], dim=2)
    assert valid_file.read_bytes() == before
    write(valid_file, [make_trajectory(2, 7)], dim=2, overwrite=True)
    assert [t.seed for t in read_trajectories(valid_file)] == [7]


def test_exception_in_writer_leaves_no_files(tmp_path: Path) -> None:
    path = tmp_path / "val.h5"
    with pytest.raises(RuntimeError, match="boom"):
        with SplitWriter(path, scene="plate", split="val", dim=2, generator_config=CONFIG) as w:
            w.append(make_trajectory(2))
            raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []


def test_failed_overwrite_keeps_old_file(valid_file: Path) -> None:
    before = valid_file.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        with SplitWriter(valid_file, scene="plate", split="train", dim=2, generator_config=CONFIG,
                         overwrite=True) as w:
            w.append(make_trajectory(2))
            raise KeyboardInterrupt
    assert valid_file.read_bytes() == before
    assert os.listdir(valid_file.parent) == [valid_file.name]


def test_killed_writer_leaves_no_final_file(tmp_path: Path) -> None:
    path = tmp_path / "train.h5"
    script = textwrap.dedent(f"""
        import itertools, sys, time
        import numpy as np
        from ggns.data.schema import SplitWriter
        from ggns.trajectory import Trajectory
        x = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
        i64 = lambda a: np.array(a, dtype=np.int64)
        traj = Trajectory(x, i64([[0, 1, 2]]), i64([[0, 1], [0, 2], [1, 2]]), np.stack([x, x]),
                          np.zeros(3, bool), i64([[0, 1]]), np.zeros((2, 2, 2)),
                          np.zeros((1, 2), np.float32), i64([0, 1, 1]), 1e5, 0.3, 0)
        with SplitWriter({str(path)!r}, scene="plate", split="train", dim=2,
                         generator_config={{}}) as w:
            for i in itertools.count():
                w.append(traj)
                if i == 0:
                    print("started", flush=True)
                time.sleep(0.01)
    """)
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, env=env,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == "started"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    assert not path.exists()
    leftovers = list(tmp_path.iterdir())
    assert len(leftovers) == 1, leftovers  # the writer had appended a trajectory when it was killed
    for leftover in leftovers:
        assert leftover.name.startswith(".train.h5.partial-")
        with pytest.raises(DatasetError, match="incomplete|not a readable HDF5 file"):
            SplitReader(leftover)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nope.h5"):
        SplitReader(tmp_path / "nope.h5")


def test_wrong_schema_version(valid_file: Path) -> None:
    with h5py.File(valid_file, "r+") as f:
        f.attrs["schema_version"] = 2
    with pytest.raises(DatasetError, match="schema version 2, this code reads version 1"):
        SplitReader(valid_file)


def test_incomplete_flag_missing(valid_file: Path) -> None:
    with h5py.File(valid_file, "r+") as f:
        del f.attrs["complete"]
    with pytest.raises(DatasetError, match="incomplete file"):
        SplitReader(valid_file)


def test_truncated_file(valid_file: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken.h5"
    shutil.copy(valid_file, broken)
    os.truncate(broken, broken.stat().st_size // 2)
    with pytest.raises(DatasetError, match="broken.h5: not a readable HDF5 file"):
        SplitReader(broken)


def test_missing_dataset_named_on_read(valid_file: Path) -> None:
    with h5py.File(valid_file, "r+") as f:
        del f["trajectories/000001/mesh/positions"]
    reader = SplitReader(valid_file)
    assert reader[0].seed == 0
    with pytest.raises(DatasetError, match="trajectory 1 lacks dataset mesh/positions"):
        reader[1]


def _nan_positions(t: Trajectory) -> None:
    t.positions[1, 2, 0] = np.nan


def _bad_offsets(t: Trajectory) -> None:
    t.point_offsets[-1] -= 1


def _float32_positions(t: Trajectory) -> None:
    t.positions = t.positions.astype(np.float32)


def _edge_out_of_range(t: Trajectory) -> None:
    t.edges[-1, 1] = 99


def _inverted_cell(t: Trajectory) -> None:
    t.cells[0, [0, 1]] = t.cells[0, [1, 0]]


def _short_collider(t: Trajectory) -> None:
    t.collider_positions = t.collider_positions[:-1]


def _huge_param(t: Trajectory) -> None:
    t.params["n"] = 2**64


@pytest.mark.parametrize("corrupt, field", [
    (_nan_positions, "mesh/positions.*NaN"),
    (_bad_offsets, "point_cloud/offsets"),
    (_float32_positions, "mesh/positions.*float64"),
    (_edge_out_of_range, "mesh/edges"),
    (_inverted_cell, "mesh/cells"),
    (_short_collider, "collider/positions"),
    (_huge_param, "params"),
])
def test_invalid_trajectory_rejected_before_writing(tmp_path: Path, corrupt, field) -> None:
    path = tmp_path / "train.h5"
    bad = make_trajectory(2, seed=5)
    corrupt(bad)
    with SplitWriter(path, scene="plate", split="train", dim=2, generator_config=CONFIG) as w:
        w.append(make_trajectory(2, seed=0))
        with pytest.raises(DatasetError, match=f"train.h5: trajectory 1: {field}"):
            w.append(bad)
        w.append(make_trajectory(2, seed=1))
    assert [t.seed for t in read_trajectories(path)] == [0, 1]


def test_wrong_dim_rejected(tmp_path: Path) -> None:
    with SplitWriter(tmp_path / "x.h5", scene="plate", split="train", dim=2,
                     generator_config=CONFIG) as w:
        with pytest.raises(DatasetError, match=r"trajectory 0: mesh/rest_positions.*dim=2"):
            w.append(make_trajectory(3))
