"""Predictions files (`ggns-predictions`, schema version 1): the rollouts of a learned simulator,
each beside a copy of the trajectory it was rolled out from, and what produced them (checkpoint and
its sha256, model class, point-cloud schedule, input file and trajectory indices). Written by
`python -m ggns rollout` and by the Lightning CLI's `predict` (`RolloutWriter`); layout documented
in docs/dataset_format.md ("Predictions files"). `write_predictions` and `read_predictions` are
its one writer and one reader; the inputs are stored in the split files' trajectory layout
(`schema.write_trajectory_group`) and the file is written atomically (`schema.AtomicHDF5`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..trajectory import Trajectory
from .schema import AtomicHDF5, DatasetError, read_trajectory_group, validate_trajectory, write_trajectory_group

PREDICTIONS_FORMAT = "ggns-predictions"
PREDICTIONS_SCHEMA_VERSION = 1
_ROOT_STRINGS = ("model_class", "schedule", "checkpoint", "checkpoint_sha256", "input_file", "scene")  # + created


@dataclass
class Predictions:
    """What a predictions file holds; shapes per trajectory: T steps, N mesh nodes, d dims."""

    positions: list[np.ndarray]  # [T, N, d] float32 predicted mesh positions; [0] is the initial state
    inputs: list[Trajectory]  # what each was rolled out from (positions are true only where has_ground_truth)
    model_class: str  # e.g. "GGNS"
    schedule: str  # the point-cloud schedule the model ran ("never" for models without point clouds)
    checkpoint: str = ""  # the pretrained name or .ckpt path the model came from
    checkpoint_sha256: str = ""  # sha256 of that checkpoint file (`ggns.checkpoints.sha256`; "" when unknown)
    input_file: str = ""  # the split file the inputs came from ("" when built from arrays)
    input_indices: list[int] = field(default_factory=list)  # each input's index in input_file (default 0..n-1)
    scene: str = ""  # the input file's scene ("" when unknown)
    created: str = ""  # ISO-8601 UTC time the file was written (set by the writer)

    @property
    def dim(self) -> int:
        return self.inputs[0].dim


def write_predictions(path: str | os.PathLike, predictions: Predictions, overwrite: bool = False) -> Path:
    """Write `predictions` to `path` atomically (FileExistsError when it exists and not overwrite);
    ValueError when a rollout does not match its input's [T, N, d] or is not finite."""
    p = predictions
    if not p.inputs or len(p.positions) != len(p.inputs):
        raise ValueError(f"predictions need one rollout per input, got {len(p.positions)} rollouts and "
                         f"{len(p.inputs)} inputs")
    indices = list(p.input_indices) or list(range(len(p.inputs)))
    if len(indices) != len(p.inputs):
        raise ValueError(f"input_indices has {len(indices)} entries for {len(p.inputs)} inputs")
    dim = p.dim
    for i, (x, traj) in enumerate(zip(p.positions, p.inputs)):
        try:
            validate_trajectory(traj, dim)
        except ValueError as e:
            raise ValueError(f"input {i}: {e}") from None
        if np.shape(x) != traj.positions.shape:
            raise ValueError(f"rollout {i} has shape {list(np.shape(x))}, its input {list(traj.positions.shape)}")
        if not np.isfinite(x).all():
            raise ValueError(f"rollout {i} is not finite")
    with AtomicHDF5(path, overwrite) as f:
        a = f.attrs
        a["format"], a["schema_version"] = PREDICTIONS_FORMAT, PREDICTIONS_SCHEMA_VERSION
        a["dim"], a["num_trajectories"] = dim, len(p.inputs)
        for key in _ROOT_STRINGS:
            a[key] = str(getattr(p, key))
        a["input_trajectories"] = np.asarray(indices, dtype=np.int64)
        group = f.create_group("predictions", track_order=True)
        for i, (x, traj, index) in enumerate(zip(p.positions, p.inputs, indices)):
            g = group.create_group(f"{i:06d}", track_order=True)
            g.attrs["input_index"] = int(index)
            ds = g.create_dataset("positions", data=np.asarray(x, dtype=np.float32))
            ds.attrs["description"] = "predicted mesh node positions per step, [0] the initial state [T,N,d]"
            ds.attrs["units"] = "normalized"
            write_trajectory_group(g.create_group("input", track_order=True), traj)
    return Path(path)


def read_predictions(path: str | os.PathLike) -> Predictions:
    """The whole predictions file; FileNotFoundError, or DatasetError naming what is wrong (another
    format, another schema version, an incomplete or corrupt file)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: predictions file not found")
    try:
        with h5py.File(path, "r") as f:
            return _read(f, path)
    except (OSError, KeyError, RuntimeError):
        raise DatasetError(f"{path}: not a readable predictions file (truncated or corrupt)") from None


def _read(f: h5py.File, path: Path) -> Predictions:
    a = f.attrs
    if a.get("format") != PREDICTIONS_FORMAT:
        raise DatasetError(f"{path}: not a {PREDICTIONS_FORMAT} file (format attribute is {a.get('format')!r})")
    if int(a.get("schema_version", -1)) != PREDICTIONS_SCHEMA_VERSION:
        raise DatasetError(f"{path}: schema version {a.get('schema_version')}, this code reads version "
                           f"{PREDICTIONS_SCHEMA_VERSION}")
    if not a.get("complete", False):
        raise DatasetError(f"{path}: incomplete file (no 'complete' flag): the writer was interrupted")
    missing = [k for k in (*_ROOT_STRINGS, "created", "dim", "num_trajectories", "input_trajectories") if k not in a]
    if missing:
        raise DatasetError(f"{path}: lacks root attributes {missing}")
    n, dim = int(a["num_trajectories"]), int(a["dim"])
    group = f["predictions"]
    if set(group) != {f"{i:06d}" for i in range(n)}:
        raise DatasetError(f"{path}: num_trajectories is {n} but the file holds {len(group)} prediction groups")
    positions, inputs = [], []
    for i in range(n):
        g = group[f"{i:06d}"]
        try:
            traj = read_trajectory_group(g["input"])
            validate_trajectory(traj, dim)
        except ValueError as e:
            raise DatasetError(f"{path}: prediction {i}: input {e}") from None
        x = g["positions"][()]
        if x.shape != traj.positions.shape:
            raise DatasetError(f"{path}: prediction {i}: positions {list(x.shape)}, input {list(traj.positions.shape)}")
        positions.append(x)
        inputs.append(traj)
    strings = {k: a[k].decode() if isinstance(a[k], bytes) else str(a[k]) for k in (*_ROOT_STRINGS, "created")}
    return Predictions(positions=positions, inputs=inputs, input_indices=[int(i) for i in a["input_trajectories"]],
                       **strings)
