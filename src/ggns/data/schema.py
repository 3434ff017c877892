"""HDF5 dataset files: one file per split (train/val/test) of a scene, schema version 1.

The layout is documented for readers without this package in docs/dataset_format.md.
Shapes: T steps (initial state included), N mesh nodes, C cells, E edges, F collider faces,
K collider vertices, P points over all steps, d = spatial dimension (2 or 3).

Files are written to a hidden temporary file next to the final path and moved into place
with `os.replace` only after the `complete` flag is set, so a file at the final path is
always whole; `SplitReader` refuses anything else with a `DatasetError`.
"""
from __future__ import annotations

import json
import operator
import os
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator, NamedTuple

import h5py
import numpy as np

from ..trajectory import GROUND_TRUTH, Trajectory
from ..geometry import signed_volumes
from ..sim.material import Material

SCHEMA_VERSION = 1
FORMAT = "ggns-trajectories"

# (Trajectory field, dataset path in the trajectory group, dtype, units, description)
_ARRAYS = [
    ("rest_positions", "mesh/rest_positions", np.float64, "normalized",
     "rest state node positions [N,d]"),
    ("cells", "mesh/cells", np.int64, "",
     "simplices as node indices, positive rest volume [C,d+1]"),
    ("edges", "mesh/edges", np.int64, "", "undirected edges i<j, sorted, unique [E,2]"),
    ("positions", "mesh/positions", np.float64, "normalized", "node positions per step [T,N,d]"),
    ("fixed", "mesh/fixed", np.bool_, "", "Dirichlet (fixed) nodes [N]"),
    ("collider_faces", "collider/faces", np.int64, "",
     "surface segments (2D) / triangles (3D) as vertex indices [F,d]"),
    ("collider_positions", "collider/positions", np.float64, "normalized",
     "surface vertex positions per step [T,K,d]"),
    ("points", "point_cloud/points", np.float32, "normalized",
     "point clouds of all steps, concatenated [P,d]"),
    ("point_offsets", "point_cloud/offsets", np.int64, "",
     "step t owns points[offsets[t]:offsets[t+1]] [T+1]"),
]
_ROOT_ATTRS = ("scene", "split", "dim", "num_trajectories", "generator_config", "created")
_PARAM_TYPES = (bool, int, float, str, np.bool_, np.integer, np.floating)


def trajectory_nbytes(traj: Trajectory) -> int:
    """The size of a trajectory's stored arrays in memory (the arrays of the format, `_ARRAYS`)."""
    return sum(int(getattr(traj, name).nbytes) for name, _, _, _, _ in _ARRAYS)


class DatasetError(ValueError):
    """A dataset file (or a trajectory to be written into one) violates the format."""


def validate_trajectory(traj: Trajectory, dim: int) -> None:
    """Check shapes, dtypes, index ranges and finiteness; raise ValueError naming the field."""
    arrays = {}
    for name, key, dtype, _, _ in _ARRAYS:
        a = getattr(traj, name)
        where = f"{key} (Trajectory.{name})"
        if not isinstance(a, np.ndarray) or a.dtype != dtype:
            got = a.dtype if isinstance(a, np.ndarray) else type(a).__name__
            raise ValueError(f"{where}: expected a {np.dtype(dtype)} array, got {got}")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ValueError(f"{where}: contains NaN or inf")
        arrays[name] = (a, where)

    def shape(name: str, *expected: int | None) -> None:
        a, where = arrays[name]
        if a.ndim != len(expected) or any(e not in (None, s) for e, s in zip(expected, a.shape)):
            want = ", ".join("*" if e is None else str(e) for e in expected)
            raise ValueError(f"{where}: expected shape [{want}] (dim={dim}), got {list(a.shape)}")

    def index_range(name: str, n: int) -> None:
        a, where = arrays[name]
        if a.size and (a.min() < 0 or a.max() >= n):
            raise ValueError(f"{where}: indices must lie in [0, {n}), got [{a.min()}, {a.max()}]")

    shape("rest_positions", None, dim)
    n = traj.rest_positions.shape[0]
    shape("positions", None, n, dim)
    t = traj.positions.shape[0]
    if t < 1:
        raise ValueError("mesh/positions (Trajectory.positions): needs at least the initial state")
    shape("cells", None, dim + 1)
    index_range("cells", n)
    if traj.cells.size and not (signed_volumes(traj.rest_positions, traj.cells) > 0).all():
        raise ValueError("mesh/cells (Trajectory.cells): cells must have positive volume in "
                         "rest_positions (counter-clockwise triangles, right-handed tetrahedra)")
    shape("edges", None, 2)
    index_range("edges", n)
    e = traj.edges
    if e.size and (not (e[:, 0] < e[:, 1]).all() or not (np.diff(e[:, 0] * n + e[:, 1]) > 0).all()):
        raise ValueError("mesh/edges (Trajectory.edges): need i < j, sorted and unique rows")
    shape("fixed", n)
    shape("collider_positions", t, None, dim)
    shape("collider_faces", None, dim)
    index_range("collider_faces", traj.collider_positions.shape[1])
    shape("points", None, dim)
    shape("point_offsets", t + 1)
    off = traj.point_offsets
    if off[0] != 0 or off[-1] != len(traj.points) or (np.diff(off) < 0).any():
        raise ValueError(f"point_cloud/offsets (Trajectory.point_offsets): must start at 0, be "
                         f"non-decreasing and end at len(points) = {len(traj.points)}, got "
                         f"start {off[0]}, end {off[-1]}")
    for name in ("youngs_modulus", "poissons_ratio"):
        value = getattr(traj, name)
        if not isinstance(value, (int, float, np.integer, np.floating)) or not np.isfinite(value):
            raise ValueError(f"attribute {name}: expected a finite number, got {value!r}")
    try:  # the simulator's own range check of a material
        Material(float(traj.youngs_modulus), float(traj.poissons_ratio))
    except ValueError as error:
        raise ValueError(f"attributes youngs_modulus, poissons_ratio: {error}") from None
    if not isinstance(traj.seed, (int, np.integer)) or isinstance(traj.seed, bool):
        raise ValueError(f"attribute seed: expected an integer, got {traj.seed!r}")
    for key, value in traj.params.items():
        if not isinstance(key, str) or not key or not isinstance(value, _PARAM_TYPES):
            raise ValueError(f"params[{key!r}]: expected a str key and a bool/int/float/str value, "
                             f"got {type(value).__name__}")
        if isinstance(value, int) and not -(2**63) <= value < 2**63:
            raise ValueError(f"params[{key!r}]: integer {value} does not fit int64")
    for key, value in traj.diagnostics.items():
        d = np.asarray(value)
        if not isinstance(key, str) or not key or "/" in key or key == ".":
            raise ValueError(f"diagnostics[{key!r}]: name must be a non-empty str without '/'")
        if d.shape != (t,) or d.dtype.kind not in "biuf":
            raise ValueError(f"diagnostics/{key}: expected a numeric [T={t}] array, "
                             f"got {d.dtype} {list(d.shape)}")


class AtomicHDF5:
    """An HDF5 file written whole or not at all: `open` creates a hidden temporary file beside `path`
    (`.<name>.partial-<pid>`) with the root attribute `created`; `commit` sets `complete = True`
    (the last write), fsyncs and moves it onto `path` with `os.replace`; `discard` removes it. As a
    context manager (`with AtomicHDF5(path) as f:`) it commits on a clean exit and discards on an
    exception, so an existing file at `path` is never damaged. Split and predictions files are
    written through it."""

    def __init__(self, path: str | os.PathLike, overwrite: bool = False) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path}: already exists (overwrite=True replaces it)")
        self._tmp = self.path.with_name(f".{self.path.name}.partial-{os.getpid()}")
        self.file: h5py.File | None = None

    def open(self) -> h5py.File:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.file = h5py.File(self._tmp, "w", track_order=True)
        try:
            self.file.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        except BaseException:
            self.discard()
            raise
        return self.file

    def commit(self) -> None:
        f, self.file = self.file, None
        try:
            f.attrs["complete"] = True  # last write: marks the file whole
            f.flush()
            f.close()
            _fsync(self._tmp)
            os.replace(self._tmp, self.path)
            _fsync(self.path.parent)
        except BaseException:
            self._discard(f)
            raise

    def discard(self) -> None:
        f, self.file = self.file, None
        self._discard(f)

    def _discard(self, f: h5py.File | None) -> None:
        try:
            if f is not None:
                f.close()
        finally:
            self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> h5py.File:
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.discard()


class SplitWriter:
    """Write one split file atomically (`AtomicHDF5`); use as a context manager.

    >>> with SplitWriter("data/plate/train.h5", scene="plate", split="train", dim=2,
    ...                  generator_config=cfg) as w:
    ...     for traj in trajectories:
    ...         w.append(traj)

    The final path appears only on a clean exit of the `with` block; on an exception the
    temporary file is removed and an existing final file is left untouched.
    """

    def __init__(self, path: str | os.PathLike, *, scene: str, split: str, dim: int,
                 generator_config: dict, overwrite: bool = False) -> None:
        self.path = Path(path)
        self._atomic = AtomicHDF5(self.path, overwrite)
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        self.scene, self.split, self.dim = scene, split, dim
        self._config = json.dumps(generator_config)
        self._count = 0

    def __enter__(self) -> SplitWriter:
        f = self._atomic.open()
        try:
            a = f.attrs
            a["format"], a["schema_version"] = FORMAT, SCHEMA_VERSION
            a["scene"], a["split"], a["dim"] = self.scene, self.split, self.dim
            a["generator_config"] = self._config
            f.create_group("trajectories", track_order=True)
        except BaseException:
            self._atomic.discard()
            raise
        return self

    def append(self, traj: Trajectory) -> int:
        """Validate and write `traj` as the next trajectory; return its index.

        A trajectory that fails validation raises DatasetError; a failed append (for any
        reason) leaves nothing of the trajectory in the file.
        """
        if self._atomic.file is None:
            raise RuntimeError("SplitWriter.append needs a `with SplitWriter(...)` block")
        i = self._count
        try:
            validate_trajectory(traj, self.dim)
        except ValueError as e:
            raise DatasetError(f"{self.path}: trajectory {i}: {e}") from None
        group = self._atomic.file["trajectories"]
        try:
            write_trajectory_group(group.create_group(f"{i:06d}"), traj)
        except BaseException:
            if f"{i:06d}" in group:
                del group[f"{i:06d}"]
            raise
        self._count += 1
        return i

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self._atomic.discard()
            return
        try:
            self._atomic.file.attrs["num_trajectories"] = self._count
        except BaseException:
            self._atomic.discard()
            raise
        self._atomic.commit()


def write_trajectory_group(g: h5py.Group, traj: Trajectory) -> None:
    """Write `traj` (validated by the caller) into the empty group `g` in the layout of a trajectory
    group (docs/dataset_format.md): attributes, `params`, the arrays, `diagnostics`."""
    g.attrs["youngs_modulus"] = float(traj.youngs_modulus)
    g.attrs["poissons_ratio"] = float(traj.poissons_ratio)
    g.attrs["seed"] = int(traj.seed)
    params = g.create_group("params", track_order=True)
    for key, value in traj.params.items():
        params.attrs[key] = value.item() if isinstance(value, np.generic) else value
    for name, key, _, units, description in _ARRAYS:
        ds = g.create_dataset(key, data=getattr(traj, name))
        ds.attrs["description"] = description
        if units:
            ds.attrs["units"] = units
    diagnostics = g.create_group("diagnostics", track_order=True)
    for key, value in traj.diagnostics.items():
        ds = diagnostics.create_dataset(key, data=np.asarray(value))
        ds.attrs["description"] = "per-step simulator diagnostic [T]"


def read_trajectory_group(g: h5py.Group) -> Trajectory:
    """The trajectory in group `g` (`write_trajectory_group`'s layout), not validated yet (that is
    `validate_trajectory`); DatasetError("lacks <what>") when a dataset, group or attribute is missing."""
    for key in [k for _, k, _, _, _ in _ARRAYS]:
        if key not in g:
            raise DatasetError(f"lacks dataset {key}")
    for key in ("params", "diagnostics"):
        if key not in g:
            raise DatasetError(f"lacks group {key}")
    for key in ("youngs_modulus", "poissons_ratio", "seed"):
        if key not in g.attrs:
            raise DatasetError(f"lacks attribute {key}")
    return Trajectory(
        **{name: g[key][()] for name, key, _, _, _ in _ARRAYS},
        youngs_modulus=float(g.attrs["youngs_modulus"]),
        poissons_ratio=float(g.attrs["poissons_ratio"]),
        seed=int(g.attrs["seed"]),
        params={k: _python_scalar(v) for k, v in g["params"].attrs.items()},
        diagnostics={k: ds[()] for k, ds in g["diagnostics"].items()},
    )


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class TrajectoryInfo(NamedTuple):
    """What a split file says about a trajectory without reading its arrays (`SplitReader.info`)."""

    num_steps: int  # T, the initial state included
    nbytes: int  # its arrays' size in memory (float64 positions etc., as read)
    has_ground_truth: bool  # Trajectory.has_ground_truth
    seed: int  # the stored seed (`SplitReader.seed`)


class SplitReader:
    """Read a split file; validates the file on construction.

    Indexable (`reader[i] -> Trajectory`, negative indices allowed) and iterable. Picklable
    for DataLoader workers: the HDF5 handle is not pickled and is reopened lazily in each
    process.

    Args:
        path: the split (or shard) file.
        metadata_cache: the most bytes of HDF5's metadata cache for this file (its object headers,
            B-tree nodes, heaps), or None for HDF5's adaptive default, which grows with the
            trajectories visited while the file is open (measured: about 50 KB of resident memory per
            trajectory whose arrays were opened); a streaming reader caps it (docs/streaming.md).
    """

    def __init__(self, path: str | os.PathLike, metadata_cache: int | None = None) -> None:
        self.path = Path(path)
        self.metadata_cache = metadata_cache
        self._file: h5py.File | None = None
        self._pid = -1
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: dataset file not found")
        try:
            self._check_root()
        except (OSError, KeyError, RuntimeError):  # h5py's errors for unreadable structures
            self.close()
            raise self._error("not a readable HDF5 file (truncated or corrupt)") from None
        except DatasetError:
            self.close()
            raise

    def _check_root(self) -> None:
        a = self._h5().attrs
        if a.get("format") != FORMAT:
            raise self._error(f"not a {FORMAT} file (format attribute is {a.get('format')!r})")
        self.schema_version = int(a.get("schema_version", -1))
        if self.schema_version != SCHEMA_VERSION:
            raise self._error(f"schema version {self.schema_version}, "
                              f"this code reads version {SCHEMA_VERSION}")
        if not a.get("complete", False):
            raise self._error("incomplete file (no 'complete' flag): the writer was interrupted")
        missing = [k for k in _ROOT_ATTRS if k not in a]
        if missing:
            raise self._error(f"lacks root attributes {missing}")
        self.scene, self.split, self.dim = str(a["scene"]), str(a["split"]), int(a["dim"])
        try:
            self.generator_config: dict = json.loads(a["generator_config"])
        except json.JSONDecodeError as e:
            raise self._error(f"generator_config is not valid JSON ({e})") from None
        self._len = int(a["num_trajectories"])
        names = set(self._h5().get("trajectories", {}))
        if names != {f"{i:06d}" for i in range(self._len)}:
            raise self._error(f"num_trajectories is {self._len} but the file holds "
                              f"{len(names)} trajectory groups (or misnamed ones)")

    def _error(self, problem: str) -> DatasetError:
        return DatasetError(f"{self.path}: {problem}")

    def _h5(self) -> h5py.File:
        if self._file is None or self._pid != os.getpid():
            self._file, self._pid = h5py.File(self.path, "r"), os.getpid()
            if self.metadata_cache is not None:
                cap = self._file.id.get_mdc_config()
                cap.set_initial_size, cap.initial_size = True, self.metadata_cache // 2
                cap.min_size, cap.max_size = self.metadata_cache // 4, self.metadata_cache
                self._file.id.set_mdc_config(cap)
        return self._file

    @property
    def is_open(self) -> bool:
        """Whether this process holds the file open."""
        return self._file is not None and self._pid == os.getpid()

    def __len__(self) -> int:
        return self._len

    def seed(self, i: int) -> int:
        """The stored seed of trajectory i, without reading its arrays."""
        i = operator.index(i)
        if not 0 <= i < self._len:
            raise IndexError(f"trajectory index {i} out of range for {self._len} trajectories")
        try:
            return int(self._h5()["trajectories"][f"{i:06d}"].attrs["seed"])
        except (OSError, KeyError, RuntimeError):
            raise self._error(f"trajectory {i} is not readable (truncated or corrupt)") from None

    def info(self, i: int) -> TrajectoryInfo:
        """Trajectory i's state count, size in memory, ground-truth flag and seed, from its metadata alone
        (no array is read): what a streaming reader plans its reads with."""
        i = operator.index(i)
        if not 0 <= i < self._len:
            raise IndexError(f"trajectory index {i} out of range for {self._len} trajectories")
        try:
            g = self._h5()["trajectories"][f"{i:06d}"]
            arrays = {key: g.get(key) for _, key, _, _, _ in _ARRAYS}  # one lookup each
            missing = [key for key, ds in arrays.items() if ds is None]
            if missing:
                raise self._error(f"trajectory {i} lacks dataset {missing[0]}")
            params = g["params"].attrs if "params" in g else {}
            return TrajectoryInfo(num_steps=int(arrays["mesh/positions"].shape[0]),
                                  nbytes=sum(int(ds.nbytes) for ds in arrays.values()),
                                  has_ground_truth=bool(params.get(GROUND_TRUTH, True)), seed=int(g.attrs["seed"]))
        except (OSError, KeyError, RuntimeError):
            raise self._error(f"trajectory {i} is not readable (truncated or corrupt)") from None

    def __getitem__(self, i: int) -> Trajectory:
        i = operator.index(i)
        if not -self._len <= i < self._len:
            raise IndexError(f"trajectory index {i} out of range for {self._len} trajectories")
        i %= self._len
        try:
            traj = read_trajectory_group(self._h5()["trajectories"][f"{i:06d}"])
        except DatasetError as e:
            raise self._error(f"trajectory {i} {e}") from None
        except (OSError, KeyError, RuntimeError):
            raise self._error(f"trajectory {i} is not readable (truncated or corrupt)") from None
        try:
            validate_trajectory(traj, self.dim)
        except ValueError as e:
            raise self._error(f"trajectory {i}: {e}") from None
        return traj

    def __iter__(self) -> Iterator[Trajectory]:
        return (self[i] for i in range(self._len))

    def close(self) -> None:
        """Close the HDF5 handle of this process (a later access reopens it)."""
        if self._file is not None and self._pid == os.getpid():
            self._file.close()
        self._file = None

    def __enter__(self) -> SplitReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_file": None, "_pid": -1}


def _python_scalar(value):
    """HDF5 attribute value -> python bool/int/float/str."""
    if isinstance(value, bytes):
        return value.decode()
    return value.item() if isinstance(value, np.generic) else value


# The parts of a generator configuration that define what a trajectory is (the split sizes, seed,
# output directory and worker count only say how many were made, where and how fast).
DEFINING_SECTIONS = ("scene", "solver", "sensor")
# Solver settings added after data was first generated, at the value that generated it (sim.solver.SolverConfig)
SOLVER_DEFAULTS = {"friction": 0.0}


def config_differences(stored: dict, expected: dict, sections=DEFINING_SECTIONS) -> list[str]:
    """Dotted keys under `sections` whose values differ between two generator configurations
    (a key present on one side only differs too, except a solver setting at its default, which a file
    written before the setting existed does not name: `SOLVER_DEFAULTS`)."""
    def flat(d, prefix=""):
        if not isinstance(d, dict):
            return {prefix[:-1]: d}
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}."))
        return out

    a = flat({k: stored.get(k) for k in sections})
    b = flat({k: expected.get(k) for k in sections})
    defaults = {f"solver.{k}": v for k, v in SOLVER_DEFAULTS.items()} if "solver" in sections else {}

    def value(side: dict, key: str):
        return side.get(key, defaults.get(key, "<absent>"))

    return sorted(k for k in a.keys() | b.keys() if value(a, k) != value(b, k))


def read_trajectories(path: str | os.PathLike, expected_config: dict | None = None) -> list[Trajectory]:
    """All trajectories of a split file, in order. With `expected_config` (a generator config,
    e.g. a data preset), a file generated with another scene, solver or sensor is refused with a
    DatasetError naming the differing keys, so files of an earlier scene never mix silently
    with a preset that has changed."""
    with SplitReader(path) as reader:
        if expected_config is not None:
            check_config(reader, expected_config)
        return list(reader)


def check_config(reader: SplitReader, expected_config: dict) -> None:
    """Refuse (DatasetError naming the file and the differing keys) a split file generated with another
    scene, solver or sensor configuration than `expected_config` (`read_trajectories`, the streaming reader)."""
    differ = config_differences(reader.generator_config, expected_config)
    if differ:
        shown = ", ".join(f"{k} (file: {_lookup(reader.generator_config, k)!r}, preset: "
                          f"{_lookup(expected_config, k)!r})" for k in differ[:6])
        raise reader._error(
            f"generated with another configuration than the preset asks for: {shown}"
            f"{' and more' if len(differ) > 6 else ''}. Regenerate it (python -m ggns generate --config "
            f"<preset> --overwrite) or point the data module at the matching preset")


def _lookup(config: dict, dotted: str):
    for key in dotted.split("."):
        if not isinstance(config, dict) or key not in config:
            return "<absent>"
        config = config[key]
    return config


def content_hash(path: str | os.PathLike) -> str:
    """sha256 of a split file's content: every trajectory's arrays (`_ARRAYS`, in order, with their
    shapes and dtypes), material and seed. Unlike the file's bytes it does not change with the
    creation time or HDF5's layout, so the same generator config and seed give the same hash."""
    import hashlib

    digest = hashlib.sha256()
    with SplitReader(path) as reader:
        for traj in reader:
            for name, _, dtype, _, _ in _ARRAYS:
                array = np.ascontiguousarray(getattr(traj, name), dtype=dtype)
                digest.update(f"{name}{array.shape}{array.dtype.str}".encode())
                digest.update(array.tobytes())
            digest.update(repr((float(traj.youngs_modulus), float(traj.poissons_ratio), int(traj.seed))).encode())
    return digest.hexdigest()
