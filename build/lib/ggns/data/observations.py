"""A trajectory from a user's own arrays: a mesh, a collider path and depth point clouds, checked
before anything is rolled out (`trajectory_from_arrays`).

Shapes: N mesh nodes, C cells, d = 2 or 3, T steps (initial state included), K collider surface
vertices, F collider faces, P_t points seen at step t. Every coordinate (mesh, collider, points)
lives in the normalized task space [-1, 1]^d that the models were trained in.

Without the true positions only the initial state is known: the trajectory's positions are the
initial state repeated (fixed nodes keep it, as the rollout engine sets them from
`positions[t + 1]`) and its params say `ground_truth: False`, so that metrics, teacher forcing and
training refuse it (`TrajectoryBatch.require_ground_truth`). Without a Poisson's ratio, the ratio is
a placeholder 0.0 marked `poissons_ratio_known: False`, refused by the models told the material
(MGN(M), GGNS(M)); GGNS infers it from the point clouds.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from ..geometry import cell_edges, check_cells, signed_volumes
from ..trajectory import GROUND_TRUTH, MATERIAL_KNOWN, Trajectory, pack_point_clouds

# Sanity limits of the frame and units check (ours, loose enough for every generated scene: their
# coordinates stay within 2.7, their points lie a median 0.4 mesh edge lengths from the mesh or
# collider; see docs/dataset_format.md "Your own data").
COORDINATE_LIMIT = 10.0  # |coordinate| of mesh and collider in the normalized task space
POINT_DISTANCE_LIMIT = 3.0  # median distance of a step's points to the mesh or collider, in median mesh edge lengths
POINT_EXTENT_RATIO = 10.0  # bounding-box diagonal of a step's points over that of the mesh and collider
EXPECTED = "expected the normalized task space [-1, 1]^d shared by mesh, collider and points"


def trajectory_from_arrays(rest_positions: ArrayLike, cells: ArrayLike, fixed: ArrayLike, collider_faces: ArrayLike,
                           collider_positions: ArrayLike, point_clouds: Sequence, youngs_modulus: float,
                           poissons_ratio: float | None = None, *, true_positions: ArrayLike | None = None,
                           fix_orientation: bool = False,
                           params: dict | None = None) -> Trajectory:
    """A checked `Trajectory` from plain arrays; ValueError naming the first problem found.

    Args:
        rest_positions: [N, d] mesh nodes at rest, also the initial state (step 0) of a rollout.
        cells: [C, d+1] triangles (2D) or tetrahedra (3D) as node indices, positive area / volume.
        fixed: the fixed (Dirichlet) nodes, a bool mask [N] or a list of node indices.
        collider_faces: [F, d] collider surface segments (2D) / triangles (3D) as vertex indices.
        collider_positions: [T, K, d] collider surface vertices per step (K = 0: no collider).
        point_clouds: T arrays [P_t, d], one per step (None or empty: no points that step).
        youngs_modulus: E in Pa (stored; no model reads it).
        poissons_ratio: nu in (-1, 0.5), needed only by the models told the material (MGN(M)).
        true_positions: [T, N, d] the true mesh positions if known (then metrics can be computed);
            its step 0 must be rest_positions.
        fix_orientation: reorder the corners of negatively oriented cells instead of refusing them.
        params: extra scalar parameters to store with the trajectory (str keys; bool/int/float/str).

    Refused: shapes, d not 2 or 3, non-finite values, indices out of range, nodes in no cell,
    flat or inverted cells (unless fix_orientation, which cannot fix flat ones), fewer than 2
    steps, collider steps or true-position steps that differ from the point-cloud steps, and
    coordinates or point clouds that do not look like the normalized task space
    (`check_task_space`)."""
    rest = _float_array(rest_positions, "rest_positions")
    if rest.ndim != 2 or rest.shape[1] not in (2, 3) or len(rest) == 0:
        raise ValueError(f"rest_positions must be [N, d] with d = 2 or 3 and N > 0, got shape {list(rest.shape)}")
    n, dim = rest.shape
    cells = _cells(cells, rest, fix_orientation)
    unused = np.setdiff1d(np.arange(n), cells)
    if len(unused):
        raise ValueError(f"{len(unused)} of the {n} mesh nodes belong to no cell (first: {unused[:5].tolist()}); "
                         f"remove them, they would have no mesh edges")
    fixed = _fixed(fixed, n)

    num_steps = len(point_clouds)
    if num_steps < 2:
        raise ValueError(f"point_clouds has {num_steps} step(s): a rollout needs T >= 2 steps (the initial state "
                         f"and at least one to predict), one point cloud (possibly empty) per step")
    collider = _float_array(collider_positions, "collider_positions")
    if collider.ndim != 3 or collider.shape[2] != dim:
        raise ValueError(f"collider_positions must be [T, K, {dim}], got shape {list(collider.shape)}")
    if collider.shape[0] != num_steps:
        raise ValueError(f"collider_positions has {collider.shape[0]} steps but point_clouds has {num_steps}: "
                         f"both need one entry per step (the initial state included)")
    faces = np.asarray(collider_faces)
    if faces.size == 0:
        faces = np.zeros((0, dim), dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != dim or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"collider_faces must be integer [F, {dim}] ({'segments' if dim == 2 else 'triangles'}), "
                         f"got {faces.dtype} {list(faces.shape)}")
    k = collider.shape[1]
    if faces.size and (faces.min() < 0 or faces.max() >= k):
        raise ValueError(f"collider_faces index outside the {k} collider vertices (got [{faces.min()}, {faces.max()}])")
    clouds = [_cloud(c, t, dim) for t, c in enumerate(point_clouds)]

    if true_positions is None:
        positions = np.broadcast_to(rest, (num_steps, n, dim)).copy()
    else:
        positions = _float_array(true_positions, "true_positions")
        if positions.shape != (num_steps, n, dim):
            raise ValueError(f"true_positions must be [T={num_steps}, N={n}, {dim}] (one state per point-cloud "
                             f"step), got shape {list(positions.shape)}")
        gap = np.abs(positions[0] - rest).max()
        if gap > 1e-6 * max(1.0, np.abs(rest).max()):
            raise ValueError(f"true_positions[0] differs from rest_positions by up to {gap:.3g}: a rollout starts "
                             f"from rest_positions, so the first true state must be it")
    check_task_space(rest, cells, positions if true_positions is not None else None, collider, clouds)

    poissons = 0.0 if poissons_ratio is None else float(poissons_ratio)
    youngs_modulus = float(youngs_modulus)
    if not np.isfinite(youngs_modulus) or youngs_modulus <= 0:
        raise ValueError(f"youngs_modulus must be a positive number of Pa, got {youngs_modulus!r}")
    if not -1.0 < poissons < 0.5:
        raise ValueError(f"poissons_ratio must lie in (-1, 0.5), got {poissons_ratio!r}")
    stored = dict(params or {})
    clash = sorted({GROUND_TRUTH, MATERIAL_KNOWN} & set(stored))
    if clash:
        raise ValueError(f"params {clash} are set by trajectory_from_arrays itself")
    stored[GROUND_TRUTH] = true_positions is not None
    stored[MATERIAL_KNOWN] = poissons_ratio is not None
    points, offsets = pack_point_clouds(clouds)
    return Trajectory(rest_positions=rest, cells=cells, edges=cell_edges(cells), positions=positions, fixed=fixed,
                      collider_faces=faces.astype(np.int64), collider_positions=collider, points=points,
                      point_offsets=offsets, youngs_modulus=youngs_modulus, poissons_ratio=poissons, seed=-1,
                      params=stored)


def check_task_space(rest: np.ndarray, cells: np.ndarray, positions: np.ndarray | None, collider: np.ndarray,
                     clouds: list[np.ndarray]) -> None:
    """ValueError when mesh, collider or point clouds do not share the normalized task space: a
    coordinate beyond COORDINATE_LIMIT, a step's points spanning more than POINT_EXTENT_RATIO times
    the mesh and collider (other units), or lying a median of more than POINT_DISTANCE_LIMIT mesh
    edge lengths from every mesh node (at rest, or truly at that step when positions [T, N, d] are
    known) and collider vertex of the step (another frame)."""
    for name, x in (("rest_positions", rest), ("true_positions", positions), ("collider_positions", collider)):
        if x is not None and x.size and np.abs(x).max() > COORDINATE_LIMIT:
            raise ValueError(f"{name} reach {np.abs(x).max():.4g} (bounding box {_box(x.reshape(-1, x.shape[-1]))}); "
                             f"{EXPECTED} (other units, e.g. millimetres?)")
    edges = cell_edges(cells)
    h = float(np.median(np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)))
    scene = np.concatenate([rest, collider.reshape(-1, rest.shape[1])] +
                           ([positions.reshape(-1, rest.shape[1])] if positions is not None else []))
    scene_extent = float(np.linalg.norm(scene.max(0) - scene.min(0)))
    rest_tree = cKDTree(rest)
    for t, cloud in enumerate(clouds):
        if len(cloud) == 0:
            continue
        extent = float(np.linalg.norm(cloud.max(0) - cloud.min(0)))
        if extent > POINT_EXTENT_RATIO * scene_extent:
            raise ValueError(f"the point cloud of step {t} spans {extent:.4g} (bounding box {_box(cloud)}), the mesh "
                             f"and collider {scene_extent:.3g}: {EXPECTED} (points in other units, e.g. millimetres?)")
        distance = rest_tree.query(cloud)[0]
        for nodes in ([collider[t]] if collider.shape[1] else []) + ([positions[t]] if positions is not None else []):
            distance = np.minimum(distance, cKDTree(nodes).query(cloud)[0])
        far = distance > POINT_DISTANCE_LIMIT * h
        if np.median(distance) > POINT_DISTANCE_LIMIT * h:
            raise ValueError(f"{far.sum()} of the {len(cloud)} points of step {t} lie farther than "
                             f"{POINT_DISTANCE_LIMIT:g} mesh edge lengths ({POINT_DISTANCE_LIMIT * h:.3g}) from every "
                             f"mesh node and collider vertex (median distance {np.median(distance):.3g}; points in "
                             f"{_box(cloud)}, mesh in {_box(rest)}): {EXPECTED} (a cloud in the camera's frame?)")


def _box(x: np.ndarray) -> str:
    return f"[{', '.join(f'{a:.3g}' for a in x.min(0))}] .. [{', '.join(f'{b:.3g}' for b in x.max(0))}]"


def _float_array(x, name: str) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of numbers") from None
    if not np.isfinite(a).all():
        bad = np.argwhere(~np.isfinite(a))[0].tolist()
        raise ValueError(f"{name} contains NaN or inf (first at index {bad})")
    return a


def _cells(cells, rest: np.ndarray, fix_orientation: bool) -> np.ndarray:
    """Integer cells [C, d+1] in range with positive volume (negative ones reordered if asked)."""
    dim = rest.shape[1]
    cells = np.asarray(cells)
    if cells.size == 0:
        raise ValueError("cells is empty: the mesh needs at least one cell")
    cells = check_cells(cells, len(rest), corners=dim + 1).astype(np.int64)
    volumes = signed_volumes(rest, cells)
    scale = np.abs(volumes).max()
    flat = np.flatnonzero(np.abs(volumes) <= 1e-9 * scale)
    if len(flat):
        raise ValueError(f"{len(flat)} of the {len(cells)} cells are flat (zero {'area' if dim == 2 else 'volume'}; "
                         f"first: {flat[:5].tolist()}): remove them or fix their nodes")
    inverted = np.flatnonzero(volumes < 0)
    if len(inverted) and not fix_orientation:
        raise ValueError(f"{len(inverted)} of the {len(cells)} cells are inverted (negative "
                         f"{'area: clockwise triangles' if dim == 2 else 'volume: left-handed tetrahedra'}; first: "
                         f"{inverted[:5].tolist()}); pass fix_orientation=True to reorder their corners")
    cells = cells.copy()
    cells[inverted] = cells[inverted][:, [1, 0, *range(2, dim + 1)]]
    return cells


def _fixed(fixed, n: int) -> np.ndarray:
    """A bool mask [N] from a mask or a list of node indices."""
    a = np.asarray(fixed)
    if a.dtype == np.bool_:
        if a.shape != (n,):
            raise ValueError(f"fixed as a mask must be bool [N={n}], got shape {list(a.shape)}")
        return a.copy()
    if a.size == 0:
        return np.zeros(n, dtype=bool)
    if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"fixed must be a bool mask [N={n}] or a list of node indices, got {a.dtype} {list(a.shape)}")
    if a.min() < 0 or a.max() >= n:
        raise ValueError(f"fixed node index outside the {n} mesh nodes (got [{a.min()}, {a.max()}])")
    mask = np.zeros(n, dtype=bool)
    mask[a] = True
    return mask


def _cloud(cloud, t: int, dim: int) -> np.ndarray:
    """One step's points as float [P_t, d] (None or empty: [0, d])."""
    if cloud is None or np.size(cloud) == 0:
        return np.zeros((0, dim))
    c = _float_array(cloud, f"point_clouds[{t}]")
    if c.ndim != 2 or c.shape[1] != dim:
        raise ValueError(f"point_clouds[{t}] must be [P, {dim}] like the mesh, got shape {list(c.shape)}")
    return c
