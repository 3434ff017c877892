"""Depth images -> the point cloud a simulator was trained on (`DepthProcessing.cloud`).

The path of one tick's depth images of one object: back-projected with each camera's intrinsics and pose
(`sensors.camera.back_project`), fused, mapped from the cameras' world frame into the task space
(`world_to_task`), projected onto the plane in 2D (as the virtual sensor keeps (x, y) of its slab),
cropped (an image with a mask: its masked pixels; one without: the points within `margin` of the
predicted object's surface and not within `collider_clearance` of the collider), down-sampled to the
density of the training data's sensor (a voxel grid of its `voxel_size`, or as many random points as
that grid has occupied voxels) and sorted as the sensor sorts them.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ..sensors.camera import DepthImage, back_project, collider_mesh, object_mesh, open3d_module

CROP_SLAB = 1.0  # half thickness of the 2D slabs the crop measures distances to (points lie at z = 0, inside)
DENSER = 2.0  # a cloud with more points than this times its occupied voxels is denser than the sensor's: thinned


class _Surface:
    """A closed triangle surface (vertices [V, 3], triangles [F, 3]) in an Open3D raycasting scene, asked which
    points lie inside it or within a distance of it."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray):
        o3d = open3d_module()
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                                 o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
        self.low, self.high = vertices.min(axis=0), vertices.max(axis=0)

    def within(self, points: np.ndarray, distance: float, among: np.ndarray | None = None) -> np.ndarray:
        """bool [P]: points [P, 3] inside the surface or at most `distance` from it (only those of `among`, bool
        [P], when given)."""
        o3c = open3d_module().core
        candidate = ((points >= self.low - distance) & (points <= self.high + distance)).all(axis=1)
        if among is not None:
            candidate &= among
        index = np.flatnonzero(candidate)
        query = np.ascontiguousarray(points[index], dtype=np.float32)
        out = np.zeros(len(points), dtype=bool)
        if not len(index):
            return out
        occupied = self.scene.compute_occupancy(o3c.Tensor(query)).numpy() > 0
        out[index[occupied]] = True
        if distance > 0 and not occupied.all():
            outside = index[~occupied]
            out[outside] = self.scene.compute_distance(o3c.Tensor(query[~occupied])).numpy() <= distance
        return out


@dataclass(frozen=True)
class DepthProcessing:
    """How depth images become a tick's point cloud (module docstring).

    Attributes:
        voxel_size: the down-sampling voxel of the training data's sensor (`sensor.voxel_size` of its data
            config; `for_model` reads it from a shipped simulator's manifest).
        downsample: "voxel" (the mean point of each occupied voxel, as the sensor does) or "random" (as many of
            the measured points, drawn at random, as the grid has occupied voxels).
        margin: the crop of an image without a mask keeps the points within this distance (task units) of the
            predicted object's surface (None: 2 voxels).
        collider_clearance: and drops those within this distance of the collider's surface or inside it
            (None: half a voxel; 0: only those inside).
        world_to_task: [4, 4] the map from the cameras' world frame to the task space, a similarity
            (scale times a rotation, and a translation), e.g. metres of a robot's base frame to the
            normalized task space; None: the identity (the virtual cameras see the task space).
        seed: the random down-sampling's seed (combined with the tick, so a tick's draw is reproducible).
    """

    voxel_size: float
    downsample: Literal["voxel", "random"] = "voxel"
    margin: float | None = None
    collider_clearance: float | None = None
    world_to_task: Any = None
    seed: int = 0

    def __post_init__(self) -> None:
        if not np.isfinite(self.voxel_size) or not float(self.voxel_size) > 0:
            raise ValueError(f"voxel_size must be a finite number > 0, got {self.voxel_size!r}")
        object.__setattr__(self, "voxel_size", float(self.voxel_size))
        if self.downsample not in ("voxel", "random"):
            raise ValueError(f"downsample must be 'voxel' or 'random', got {self.downsample!r}")
        for name, default in (("margin", 2.0 * self.voxel_size), ("collider_clearance", 0.5 * self.voxel_size)):
            value = default if getattr(self, name) is None else float(getattr(self, name))
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        transform = np.eye(4) if self.world_to_task is None else np.asarray(self.world_to_task, dtype=np.float64)
        if transform.shape != (4, 4) or not np.isfinite(transform).all():
            raise ValueError(f"world_to_task must be a finite [4, 4] matrix, got shape {list(transform.shape)}")
        linear = transform[:3, :3]
        scale = np.cbrt(np.linalg.det(linear))
        if not scale > 0 or np.abs(linear.T @ linear - scale**2 * np.eye(3)).max() > 1e-6 * scale**2 \
                or np.abs(transform[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise ValueError("world_to_task must be a similarity: a positive scale times a rotation, a translation, "
                             "and the last row (0, 0, 0, 1)")
        object.__setattr__(self, "world_to_task", transform)

    @classmethod
    def from_sensor_config(cls, sensor: Mapping, **kwargs: Any) -> DepthProcessing:
        """The processing for data made with this sensor config (a data preset's `sensor` section, or a
        `SensorConfig`): its `voxel_size`; kwargs: the other fields."""
        voxel = sensor.voxel_size if hasattr(sensor, "voxel_size") else sensor["voxel_size"]
        return cls(voxel_size=float(voxel), **kwargs)

    @classmethod
    def for_model(cls, model: Any, **kwargs: Any) -> DepthProcessing:
        """The processing for a shipped simulator (`ggns.pretrained.load`): the voxel size of the sensor of its
        training data, from its manifest. ValueError for a simulator without one (a checkpoint of one's
        own: use `from_sensor_config` with its data preset's sensor, e.g.
        `ggns.config.load_config("plate")["sensor"]`)."""
        manifest = getattr(model, "manifest", None)
        sensor = ((manifest or {}).get("data") or {}).get("config", {}).get("sensor")
        if not sensor or "voxel_size" not in sensor:
            raise ValueError("the simulator does not say which point density it was trained on (no manifest with the "
                             "data's sensor config); give OnlineSimulator a DepthProcessing, e.g. "
                             "DepthProcessing.from_sensor_config(load_config('<data preset>')['sensor'])")
        return cls.from_sensor_config(sensor, **kwargs)

    def cloud(self, images: Sequence[DepthImage], dim: int, positions: np.ndarray, cells: np.ndarray,
              collider: tuple[np.ndarray, np.ndarray] | None = None, tick: int = 0) -> np.ndarray:
        """The point cloud [P, dim] float32 (task space) of one object from one tick's depth images.

        Args:
            images: the tick's depth images (their masks, where given, the object's pixels).
            dim: the task's dimension; 2: the points' (x, y) after `world_to_task`.
            positions: [N, dim] the object's mesh as predicted for that tick (the crop's region), cells [C, dim+1].
            collider: (vertices [K, dim], faces [F, dim]) of the collider at that tick, or None.
            tick: the tick (the random down-sampling's draw).
        """
        kept = []
        region = None
        for image in images:
            points = self._to_task(back_project(image), dim)
            if image.mask is None and len(points):
                region = region or self._region(dim, positions, cells, collider)
                points = points[region(points)]
            kept.append(points)
        points = np.concatenate([np.zeros((0, 3))] + kept)
        return self._downsample(points, dim, tick)

    def thin(self, points: np.ndarray, dim: int, tick: int = 0) -> np.ndarray:
        """A point cloud [P, dim] given as points, at the training data's density: down-sampled as `cloud` does
        when it is denser than the sensor's (more than `DENSER` points per occupied voxel of the grid), else as
        given (a cloud of the sensor's own density, e.g. a dataset's, is not changed)."""
        points = np.asarray(points)
        if len(points) < 2:
            return points
        corner = points.min(axis=0) - 0.5 * self.voxel_size
        occupied = len(np.unique(np.floor((points - corner) / self.voxel_size).astype(np.int64), axis=0))
        if len(points) <= DENSER * occupied:
            return points
        padded = np.concatenate([points, np.zeros((len(points), 3 - dim))], axis=1) if dim < 3 else points
        return self._downsample(np.asarray(padded, dtype=np.float64), dim, tick)

    def _to_task(self, points: np.ndarray, dim: int) -> np.ndarray:
        """World points [P, 3] in the task space, [P, 3]; in 2D projected onto the plane z = 0."""
        transform = self.world_to_task
        points = points @ transform[:3, :3].T + transform[:3, 3]
        if dim == 2:
            points[:, 2] = 0.0
        return points

    def _region(self, dim: int, positions: np.ndarray, cells: np.ndarray, collider):
        """points [P, 3] -> bool [P]: inside the object's closed surface or within `margin` of it, and neither
        inside the collider's nor within `collider_clearance` of it (Open3D's occupancy and distance queries;
        2D: the slabs of a large half thickness, the points lying in their mid-plane). Only the points in a
        surface's bounding box (grown by the distance) are queried."""
        near_object = _Surface(*object_mesh(positions, cells, CROP_SLAB))
        near_collider = None
        if collider is not None and len(collider[1]):
            near_collider = _Surface(*collider_mesh(collider[0], collider[1], dim, CROP_SLAB))

        def inside(points: np.ndarray) -> np.ndarray:
            keep = near_object.within(points, self.margin)
            if near_collider is not None:
                keep &= ~near_collider.within(points, self.collider_clearance, keep)
            return keep

        return inside

    def _downsample(self, points: np.ndarray, dim: int, tick: int) -> np.ndarray:
        """[P, 3] -> [P', dim] float32 at the training data's density, sorted lexicographically (as the sensor)."""
        if len(points) and self.downsample == "voxel":  # the sensor's own down-sampling (grid at the bbox min)
            o3d = open3d_module()
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            points = np.asarray(cloud.voxel_down_sample(self.voxel_size).points)
        elif len(points):
            corner = points.min(axis=0) - 0.5 * self.voxel_size  # Open3D's grid
            cells = np.floor((points - corner) / self.voxel_size).astype(np.int64)
            occupied = len(np.unique(cells, axis=0))
            rng = np.random.default_rng([self.seed, tick])
            points = points[np.sort(rng.choice(len(points), size=occupied, replace=False))]
        points = points[:, :dim]
        return points[np.lexsort(points.T[::-1])].astype(np.float32)
