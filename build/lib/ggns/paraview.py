"""Rollouts as files ParaView opens: VTK XML unstructured grids (.vtu, ASCII) per step, gathered
over time by a ParaView collection (.pvd) per series.

`write_rollout` writes, for one trajectory, the ground truth (when known), each prediction (with its per-node
error against the truth as point data) and the point clouds (as vertex cells), e.g.
`truth.pvd`, `GGNS.pvd`, `points.pvd`: open the .pvd files in ParaView and play the time steps.
2D meshes are written in the plane z = 0. No dependency beyond numpy (the format is plain XML).
"""
from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .geometry import check_cells
from .reports import write_text

VTK_VERTEX, VTK_TRIANGLE, VTK_TETRA = 1, 5, 10
_CELL_TYPES = {1: VTK_VERTEX, 3: VTK_TRIANGLE, 4: VTK_TETRA}


def _array(name: str | None, values: np.ndarray, kind: str, components: int = 1) -> str:
    head = f'<DataArray type="{kind}"' + (f' Name="{name}"' if name else "") + f' NumberOfComponents="{components}" format="ascii">'
    body = " ".join(repr(float(v)) if kind.startswith("Float") else str(int(v)) for v in np.asarray(values).ravel())
    return f"{head}{body}</DataArray>"


def write_vtu(path: str | Path, positions, cells, point_data: Mapping[str, np.ndarray] | None = None) -> Path:
    """One unstructured grid: positions [N, 2|3] (2D at z = 0), cells [C, 1|3|4] (vertices,
    triangles or tetrahedra), point_data {name: [N] or [N, k]} (float). ValueError on NaN/inf or
    shapes that do not fit."""
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] not in (2, 3):
        raise ValueError(f"positions must be [N, 2|3], got {positions.shape}")
    if not np.isfinite(positions).all():
        raise ValueError(f"{path}: positions hold NaN or infinite values")
    cells = np.asarray(cells)
    if cells.ndim != 2 or cells.shape[1] not in _CELL_TYPES:
        raise ValueError(f"cells must be [C, 1|3|4] (vertices, triangles, tetrahedra), got {cells.shape}")
    cells = check_cells(cells, len(positions), corners=cells.shape[1])
    if positions.shape[1] == 2:
        positions = np.concatenate([positions, np.zeros((len(positions), 1))], axis=1)
    arrays = []
    for name, values in (point_data or {}).items():
        values = np.asarray(values, dtype=np.float64)
        if values.shape[0] != len(positions) or values.ndim > 2:
            raise ValueError(f"point data {name!r} must be [N] or [N, k] with N = {len(positions)}, got {values.shape}")
        if not re.fullmatch(r"[A-Za-z_][\w ]*", name):
            raise ValueError(f"point data name {name!r}: letters, digits, '_' and spaces only")
        arrays.append(_array(name, values, "Float64", 1 if values.ndim == 1 else values.shape[1]))
    corners = cells.shape[1]
    text = "\n".join([
        '<?xml version="1.0"?>',
        '<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64">',
        "<UnstructuredGrid>",
        f'<Piece NumberOfPoints="{len(positions)}" NumberOfCells="{len(cells)}">',
        "<Points>", _array(None, positions, "Float64", 3), "</Points>",
        "<Cells>",
        _array("connectivity", cells, "Int64"),
        _array("offsets", corners * np.arange(1, len(cells) + 1), "Int64"),
        _array("types", np.full(len(cells), _CELL_TYPES[corners]), "UInt8"),
        "</Cells>",
        "<PointData>", *arrays, "</PointData>",
        "</Piece>", "</UnstructuredGrid>", "</VTKFile>", ""])
    return write_text(path, text)


def write_collection(path: str | Path, files: Sequence[str | Path], times: Sequence[float]) -> Path:
    """A ParaView collection (.pvd) of `files` (paths relative to the .pvd's folder) at `times`."""
    if len(files) != len(times):
        raise ValueError(f"{len(files)} files but {len(times)} times")
    entries = [f'<DataSet timestep="{float(t)!r}" group="" part="0" file="{Path(f).as_posix()}"/>'
               for f, t in zip(files, times)]
    return write_text(path, "\n".join(['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1">',
                                       "<Collection>", *entries, "</Collection>", "</VTKFile>", ""]))


def write_rollout(directory: str | Path, cells, truth, predictions: Mapping[str, object] | None = None,
                  points: Sequence | None = None, frame_dt: float = 1.0) -> list[Path]:
    """The truth [T, N, d] and each prediction {name: [T, N, d]} as one .vtu per step plus a .pvd per
    series in `directory`, predictions with point data "error" (the distance to the true node); point
    clouds (T entries [P_t, d], None for none) as vertex cells in `points.pvd`. Returns the .pvd paths.
    truth None (a trajectory whose true positions are unknown): the predictions alone, without error."""
    directory = Path(directory)
    series = {str(k): np.asarray(v.detach().cpu() if hasattr(v, "detach") else v, dtype=np.float64)
              for k, v in (predictions or {}).items()}
    if truth is not None:
        series = {"truth": np.asarray(truth, dtype=np.float64), **series}
    if not series:
        raise ValueError("nothing to write: no truth and no predictions")
    first = next(iter(series.values()))
    for name, positions in series.items():
        if positions.shape != first.shape:
            raise ValueError(f"series {name!r} has shape {positions.shape}, {next(iter(series))!r} {first.shape}")
        if not re.fullmatch(r"[\w.+-]+", name):
            raise ValueError(f"series name {name!r}: letters, digits and _ . + - only (it names files)")
    times = [t * frame_dt for t in range(len(first))]
    written = []
    for name, positions in series.items():
        files = []
        for t, x in enumerate(positions):
            data = {} if name == "truth" or truth is None else {"error": np.linalg.norm(x - series["truth"][t], axis=1)}
            files.append(write_vtu(directory / name / f"{t:04d}.vtu", x, cells, data).relative_to(directory))
        written.append(write_collection(directory / f"{name}.pvd", files, times))
    if points is not None:
        if len(points) != len(first):
            raise ValueError(f"points has {len(points)} entries, expected one per step ({len(first)})")
        files, shown = [], []
        for t, cloud in enumerate(points):
            if cloud is None or len(cloud) == 0:
                continue
            cloud = np.asarray(cloud, dtype=np.float64)
            files.append(write_vtu(directory / "points" / f"{t:04d}.vtu", cloud, np.arange(len(cloud))[:, None])
                         .relative_to(directory))
            shown.append(times[t])
        written.append(write_collection(directory / "points.pvd", files, shown))
    return written
