"""Virtual depth cameras: deformed simulation state -> partial point cloud (GGNS, ICLR 2023).

An Open3D `RaycastingScene` holds the deformable object's surface and the collider; rays of
fixed pinhole cameras are cast, only hits on the deformable object are kept (the collider
still occludes), hits of all cameras are fused, voxel-down-sampled and optionally noised.

2D meshes are viewed as a thin prism slab z in [-h, h] (the plate extruded along z); the
returned points keep (x, y) only. All lengths are in simulation units.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..geometry import boundary_facets


def _open3d():
    """Open3D, imported on first use: only raycasting (making datasets) needs it; fitting, testing and
    benchmarking on datasets already written do not, so a machine without it (a GPU cluster's node,
    say) still trains."""
    try:
        import open3d
    except ImportError as error:
        raise ImportError("open3d is needed to raycast point clouds (generating a dataset); install it "
                          "(scripts/setup.sh, or pip install open3d with the system library libusb-1.0), or "
                          "train on a dataset generated elsewhere") from error
    return open3d


def _vec3(name: str, value) -> tuple[float, float, float]:
    vec = tuple(float(v) for v in value)
    if len(vec) != 3 or not np.all(np.isfinite(vec)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return vec


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole camera looking from `eye` at `look_at`; `fov_deg` is the horizontal field of view."""

    eye: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_deg: float
    width_px: int
    height_px: int

    def __post_init__(self) -> None:
        for name in ("eye", "look_at", "up"):
            object.__setattr__(self, name, _vec3(name, getattr(self, name)))
        if not 0.0 < float(self.fov_deg) < 180.0:
            raise ValueError(f"fov_deg must be in (0, 180), got {self.fov_deg}")
        for name in ("width_px", "height_px"):
            if int(getattr(self, name)) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "fov_deg", float(self.fov_deg))
        view = np.subtract(self.look_at, self.eye)
        if np.linalg.norm(view) == 0.0:
            raise ValueError("look_at must differ from eye")
        up = np.asarray(self.up)
        if np.linalg.norm(np.cross(view, up)) <= 1e-9 * np.linalg.norm(view) * np.linalg.norm(up):
            raise ValueError("up must not be zero or parallel to the view direction")

    def rays(self) -> np.ndarray:
        """Rays [height_px * width_px, 6] float32 as (origin, direction), row-major pixels."""
        o3d = _open3d()
        o3c = o3d.core
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            fov_deg=self.fov_deg,
            center=o3c.Tensor(self.look_at, dtype=o3c.float32),
            eye=o3c.Tensor(self.eye, dtype=o3c.float32),
            up=o3c.Tensor(self.up, dtype=o3c.float32),
            width_px=self.width_px,
            height_px=self.height_px,
        )
        return rays.numpy().reshape(-1, 6)


@dataclass(frozen=True)
class SensorConfig:
    """Cameras plus point-cloud post-processing.

    voxel_size: edge of the down-sampling voxel; noise_std: std of the Gaussian noise added
    to each output coordinate; slab_half_thickness: h of the 2D extrusion z in [-h, h].
    """

    cameras: tuple[PinholeCamera, ...]
    voxel_size: float
    noise_std: float = 0.0
    slab_half_thickness: float = 0.05

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        if not self.cameras:
            raise ValueError("cameras must contain at least one PinholeCamera")
        if not all(isinstance(c, PinholeCamera) for c in self.cameras):
            raise ValueError("cameras must be PinholeCamera instances")
        if not float(self.voxel_size) > 0.0:
            raise ValueError(f"voxel_size must be > 0, got {self.voxel_size}")
        if not float(self.noise_std) >= 0.0:
            raise ValueError(f"noise_std must be >= 0, got {self.noise_std}")
        if not float(self.slab_half_thickness) > 0.0:
            raise ValueError(f"slab_half_thickness must be > 0, got {self.slab_half_thickness}")
        for name in ("voxel_size", "noise_std", "slab_half_thickness"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @classmethod
    def from_dict(cls, d: Mapping) -> SensorConfig:
        """Build from a plain or omegaconf mapping with `cameras` as a list of mappings."""
        cameras = tuple(PinholeCamera(**{str(k): cam[k] for k in cam}) for cam in d["cameras"])
        rest = {str(k): d[k] for k in d if k != "cameras"}
        return cls(cameras=cameras, **rest)


def _extrude(vertices: np.ndarray, caps: np.ndarray, walls: np.ndarray, h: float):
    """Prism of a 2D region: vertices [K,2] -> [2K,3] (front z=+h, back z=-h).

    caps [T,3] triangles (counter-clockwise) covering the region, walls [S,2] its
    counter-clockwise boundary segments. Returns (vertices [2K,3], triangles [2T+2S,3]),
    outward oriented.
    """
    k = len(vertices)
    xy = np.concatenate([vertices, vertices], axis=0)
    z = np.repeat([h, -h], k)[:, None]
    a, b = walls[:, 0], walls[:, 1]
    tris = np.concatenate(
        [
            caps,
            caps[:, ::-1] + k,
            np.stack([a, a + k, b + k], axis=1),
            np.stack([a, b + k, b], axis=1),
        ]
    )
    return np.concatenate([xy, z], axis=1), tris


def _deformable_mesh_2d(positions, cells, h):
    """Closed slab of a triangle mesh [N,2] / [C,3]."""
    cells = np.asarray(cells, dtype=np.int64)
    a, b, c = (positions[cells[:, j]] for j in range(3))
    area2 = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    caps = np.where((area2 < 0)[:, None], cells[:, ::-1], cells)
    return _extrude(positions, caps, boundary_facets(cells, positions), h)


def _collider_mesh_2d(vertices, segments, h):
    """Closed slab of a closed polyline [K,2] / [F,2]; caps are a fan from the vertex centroid.

    The fan (and thus occlusion through the caps) is only valid for colliders that are
    star-shaped with respect to their vertex centroid.
    """
    segments = np.asarray(segments, dtype=np.int64)
    centroid = vertices.mean(axis=0, keepdims=True)
    verts = np.concatenate([vertices, centroid], axis=0)
    c = np.full((len(segments), 1), len(vertices))
    caps = np.concatenate([c, segments], axis=1)
    a, b = verts[caps[:, 1]] - centroid, verts[caps[:, 2]] - centroid
    ccw = np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]) >= 0  # polyline orientation
    if not ccw:
        caps, segments = caps[:, [0, 2, 1]], segments[:, ::-1]
    return _extrude(verts, caps, segments, h)


class DepthSensor:
    """Ray-casts the deformed object (and an occluding collider) from fixed pinhole cameras.

    Rays of all cameras are built once here and cast in one batch per `observe` call.
    """

    def __init__(self, config: SensorConfig):
        self.config = config
        rays = np.concatenate([cam.rays() for cam in config.cameras], axis=0)
        self._rays = rays.astype(np.float64)
        self._rays_tensor = _open3d().core.Tensor(np.ascontiguousarray(rays, dtype=np.float32))

    def observe(
        self,
        positions: np.ndarray,
        cells: np.ndarray,
        collider_vertices: np.ndarray | None,
        collider_faces: np.ndarray | None,
        rng: np.random.Generator | None = None,
        occluders: Sequence[tuple[np.ndarray, np.ndarray]] = (),
        surface: np.ndarray | None = None,
    ) -> np.ndarray:
        """Point cloud [P,d] float32 of the deformable object's visible surface.

        positions [N,d] (d = 2 or 3), cells [C,d+1]; collider_vertices [K,d] and
        collider_faces [F,d] (segments of a closed polyline in 2D, triangles in 3D) or both
        None. occluders (3D only): further triangle meshes (vertices [V,3], triangles [F,3]) that
        block rays and give no points, e.g. a static organ in front of the object or a gripper.
        Points are voxel-down-sampled, sorted lexicographically and, when noise_std > 0,
        perturbed with N(0, noise_std^2) drawn from `rng`. surface (3D only): the boundary triangles
        [F, 3] of `cells` when the caller has them (a fixed topology: found once, not per step);
        their orientation does not matter to the rays.
        """
        cfg = self.config
        if cfg.noise_std > 0.0 and rng is None:
            raise ValueError("rng is required when noise_std > 0")
        if (collider_vertices is None) != (collider_faces is None):
            raise ValueError("collider_vertices and collider_faces: give both or neither")
        positions = np.asarray(positions, dtype=np.float64)
        d = positions.shape[1]
        if d not in (2, 3) or np.shape(cells)[1] != d + 1:
            shapes = f"{positions.shape}, {np.shape(cells)}"
            raise ValueError(f"expected positions [N,2|3] and cells [C,d+1], got {shapes}")
        h = cfg.slab_half_thickness
        if d == 2:
            meshes = [_deformable_mesh_2d(positions, cells, h)]
        else:
            meshes = [(positions, boundary_facets(cells, positions) if surface is None else np.asarray(surface, dtype=np.int64))]
        if collider_vertices is not None and len(collider_faces) > 0:
            cv = np.asarray(collider_vertices, dtype=np.float64)
            cf = np.asarray(collider_faces, dtype=np.int64)
            meshes.append(_collider_mesh_2d(cv, cf, h) if d == 2 else (cv, cf))
        if len(occluders) and d != 3:
            raise ValueError("occluders are 3D triangle meshes; a 2D scene's occluder is its collider")
        for i, (vertices, triangles) in enumerate(occluders):
            vertices, triangles = np.asarray(vertices, dtype=np.float64), np.asarray(triangles, dtype=np.int64)
            if vertices.ndim != 2 or vertices.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
                raise ValueError(f"occluder {i}: expected vertices [V,3] and triangles [F,3], got "
                                 f"{vertices.shape}, {triangles.shape}")
            meshes.append((vertices, triangles))

        o3d = _open3d()
        o3c = o3d.core
        scene = o3d.t.geometry.RaycastingScene()
        ids = [
            scene.add_triangles(
                o3c.Tensor(np.ascontiguousarray(v, dtype=np.float32)),
                o3c.Tensor(np.ascontiguousarray(t, dtype=np.uint32)),
            )
            for v, t in meshes
        ]
        hits = scene.cast_rays(self._rays_tensor)
        mask = hits["geometry_ids"].numpy() == ids[0]
        rays, t_hit = self._rays[mask], hits["t_hit"].numpy()[mask].astype(np.float64)
        points = rays[:, :3] + t_hit[:, None] * rays[:, 3:]
        if d == 2:
            points[:, 2] = 0.0  # down-sample on the (x, y) grid of the plate plane
        if len(points):  # legacy API: ~7x faster than o3d.t here; grid anchored at the bbox min
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            points = np.asarray(cloud.voxel_down_sample(cfg.voxel_size).points)
        points = points[:, :d]
        points = points[np.lexsort(points.T[::-1])]
        if cfg.noise_std > 0.0:
            points = points + rng.normal(0.0, cfg.noise_std, size=points.shape)
        return points.astype(np.float32)
