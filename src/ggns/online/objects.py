"""What an `OnlineSimulator` is given: the objects it steps (`online_object`, or recorded trajectories), and the
observations of them as they arrive (`Observation`); the array checks both share."""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from torch import Tensor

from ..data.observations import trajectory_from_arrays
from ..sensors.camera import DepthImage
from ..trajectory import Trajectory

GRASPED = "online_grasped"  # an online object's params key: the fixed nodes that move with its collider (in memory only)


@dataclass(frozen=True, eq=False)
class Observation:
    """What was seen of one object at one tick: a point cloud, or depth images.

    Attributes:
        points: [P, d] points on the object's surface in the task space, or None. A cloud denser than the
            training data's sensor is down-sampled as the sensor does (`DepthProcessing.thin`); one of its density
            is used as it is.
        images: depth images of the tick (`sensors.camera.DepthImage`: depth, intrinsics, camera-to-world
            pose, optional mask), turned into the cloud by the simulator's `DepthProcessing`; or ().
        tick: the tick whose state it shows; None: the tick being stepped (the current one). An earlier tick
            (a sensor's latency) corrects that tick's state and predicts forward again. Observations of one
            tick, in one call or several, are joined (cameras whose frames arrive apart).
    """

    points: Any = None
    images: Sequence[DepthImage] = ()
    tick: int | None = None

    def __post_init__(self) -> None:
        images = (self.images,) if isinstance(self.images, DepthImage) else tuple(self.images)
        if not all(isinstance(image, DepthImage) for image in images):
            raise ValueError("observation images must be DepthImage objects (ggns.sensors.camera.DepthImage)")
        object.__setattr__(self, "images", images)
        if (self.points is None) == (not images):
            raise ValueError("an observation holds either a point cloud (points) or depth images (images), "
                             "not both and not neither")
        if self.points is not None:
            object.__setattr__(self, "points", float_array(self.points, "observation points"))
        if self.tick is not None and (isinstance(self.tick, bool) or not isinstance(self.tick, (int, np.integer))
                                      or self.tick < 0):
            raise ValueError(f"observation tick must be an integer >= 0 or None, got {self.tick!r}")


def online_object(rest_positions: ArrayLike, cells: ArrayLike, fixed: ArrayLike,
                  collider_vertices: ArrayLike | None = None, collider_faces: ArrayLike | None = None,
                  poissons_ratio: float | None = None, initial_positions: ArrayLike | None = None,
                  youngs_modulus: float = 1.0, fix_orientation: bool = False,
                  grasped: ArrayLike | None = None) -> Trajectory:
    """An object for `OnlineSimulator` from plain arrays, checked as `data.observations.trajectory_from_arrays`
    checks a user's trajectory (ValueError naming the problem): a `Trajectory` of two states, both the initial one.

    Args:
        rest_positions: [N, d] mesh nodes at rest (task space), cells [C, d+1], fixed: bool mask [N] or indices.
        collider_vertices: [K, d] the collider's surface vertices at tick 0, the template its poses move
            (None: no collider); collider_faces [F, d] its segments (2D) or triangles (3D).
        poissons_ratio: for the models told the material (MGN(M), GGNS(M)); None: unknown.
        initial_positions: [N, d] the mesh at tick 0 (None: at rest).
        youngs_modulus: stored only (no model reads it).
        grasped: indices of fixed nodes held by the collider (a gripper's patch): they move with the collider's
            pose as a rigid body (a single-vertex collider: its translation) unless a step gives them.
    """
    rest = float_array(rest_positions, "rest_positions")
    dim = rest.shape[1] if rest.ndim == 2 else 2
    if collider_vertices is None:
        vertices, faces = np.zeros((0, dim)), np.zeros((0, dim), dtype=np.int64)
    else:
        vertices, faces = float_array(collider_vertices, "collider_vertices"), collider_faces
    trajectory = trajectory_from_arrays(rest, cells, fixed, faces, np.stack([vertices, vertices]), [None, None],
                                        youngs_modulus, poissons_ratio, fix_orientation=fix_orientation)
    if initial_positions is not None:
        initial = float_array(initial_positions, "initial_positions")
        if initial.shape != rest.shape:
            raise ValueError(f"initial_positions must be [N={len(rest)}, {dim}] like rest_positions, got "
                             f"{list(initial.shape)}")
        trajectory = dataclasses.replace(trajectory, positions=np.stack([initial, initial]))
    if grasped is not None:
        index = np.unique(np.asarray(grasped, dtype=np.int64).ravel())
        if len(index) and (index.min() < 0 or index.max() >= len(rest) or not trajectory.fixed[index].all()):
            raise ValueError("grasped must be indices of fixed nodes (0..N-1, each also in `fixed`)")
        if len(index) and not len(vertices):
            raise ValueError("grasped nodes need a collider to hold them (collider_vertices)")
        trajectory = dataclasses.replace(trajectory, params={**trajectory.params, GRASPED: tuple(index.tolist())})
    return trajectory


def grasped_nodes(trajectory: Trajectory) -> np.ndarray:
    """The fixed nodes an object's collider holds: an online object's `grasped`, else those of a recorded
    trajectory's fixed nodes that move during it (the tissue's gripped patch), else none."""
    if GRASPED in trajectory.params:
        return np.asarray(trajectory.params[GRASPED], dtype=np.int64)
    index = np.flatnonzero(trajectory.fixed)
    if not len(index) or trajectory.collider_positions.shape[1] == 0:
        return index[:0]
    moved = np.abs(trajectory.positions[:, index] - trajectory.positions[:1, index]).max(axis=(0, 2)) > 0
    return index[moved]


def float_array(value: Any, what: str, finite: bool = True) -> np.ndarray:
    """float64 array of a numeric array or tensor; ValueError naming `what` otherwise (or when not finite)."""
    if isinstance(value, Tensor):
        value = value.detach().cpu().numpy()
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be an array of numbers, got {type(value).__name__}") from None
    if finite and not np.isfinite(array).all():
        raise ValueError(f"{what}: NaN or inf values")
    return array


def rigid_motion(template: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """The rigid transform [d+1, d+1] taking a collider's template vertices [K, d] to `vertices` (least squares,
    Kabsch); a translation alone when the template does not fix a rotation (one vertex, or all on a line)."""
    dim = template.shape[1]
    out = np.eye(dim + 1)
    a, b = template.mean(axis=0), vertices.mean(axis=0)
    centred = template - a
    if len(template) > dim and np.linalg.matrix_rank(centred, tol=1e-9 * max(1.0, np.abs(centred).max())) == dim:
        u, _, vt = np.linalg.svd(centred.T @ (vertices - b))
        sign = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
        out[:dim, :dim] = vt.T @ np.diag([1.0] * (dim - 1) + [sign]) @ u.T
    out[:dim, dim] = b - out[:dim, :dim] @ a
    return out
