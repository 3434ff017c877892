"""Virtual depth cameras: deformed simulation state -> partial point cloud or depth images (GGNS, ICLR 2023).

An Open3D `RaycastingScene` holds the deformable object's surface and the collider; rays of
fixed pinhole cameras are cast, only hits on the deformable object are kept (the collider
still occludes), hits of all cameras are fused, voxel-down-sampled and optionally noised
(`DepthSensor.observe`, what the datasets store).

`DepthSensor.render` gives the same cast as one `DepthImage` per camera (depth along the optical
axis, 0 where nothing is hit, the object's pixels as a mask, the camera's intrinsics and
camera-to-world pose), the form a real depth camera delivers; `back_project` turns an image back
into world points. Sensor flaws (`SensorConfig`: depth noise growing with the square of the
distance, missing pixels at grazing angles and depth edges, flying pixels, an extrinsic calibration
error) are opt-in; with any of them `observe` fuses the back-projected flawed images, without them it
is the plain cast (the datasets' points, unchanged).

2D meshes are viewed as a thin prism slab z in [-h, h] (the plate extruded along z); the
returned points keep (x, y) only. All lengths are in simulation units.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..geometry import boundary_facets


def open3d_module():
    """Open3D, imported on first use: only raycasting (making datasets, rendering depth images) and the online
    depth path (`ggns.online.DepthProcessing`) need it; fitting, testing and benchmarking on datasets already
    written do not, so a machine without it (a GPU cluster's node, say) still trains."""
    try:
        import open3d
    except ImportError as error:
        raise ImportError("open3d is needed to raycast point clouds (generating a dataset) and to turn depth "
                          "images into them (ggns.online); install it "
                          "(scripts/setup.sh, or pip install open3d with the system library libusb-1.0), or "
                          "train on a dataset generated elsewhere") from error
    return open3d


def _vec3(name: str, value) -> tuple[float, float, float]:
    vec = tuple(float(v) for v in value)
    if len(vec) != 3 or not np.all(np.isfinite(vec)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return vec


RIGID_TOLERANCE = 1e-4  # the largest |R^T R - I| entry accepted as rounding (a pose written to 5 decimals has ~1e-5)


def check_rigid(matrix, dim: int, what: str, tolerance: float = RIGID_TOLERANCE) -> np.ndarray:
    """A homogeneous rigid transform [dim+1, dim+1] (float64) checked: finite, last row (0, ..., 0, 1),
    its rotation block orthonormal with determinant +1 to `tolerance` (the largest entry of R^T R - I);
    returned with the rotation block replaced by the nearest rotation (so that rounding does not scale or
    shear what it maps). ValueError naming `what`, the failed check and its residual otherwise."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (dim + 1, dim + 1):
        raise ValueError(f"{what} must be a [{dim + 1}, {dim + 1}] homogeneous transform, got shape {list(m.shape)}")
    if not np.isfinite(m).all():
        raise ValueError(f"{what} has non-finite entries")
    if np.abs(m[dim] - np.eye(dim + 1)[dim]).max() > tolerance:
        raise ValueError(f"{what}: its last row must be (0, ..., 0, 1), got {m[dim].tolist()}")
    rotation = m[:dim, :dim]
    residual = float(np.abs(rotation.T @ rotation - np.eye(dim)).max())
    if residual > tolerance or np.linalg.det(rotation) < 0:
        kind = "a reflection (determinant < 0)" if np.linalg.det(rotation) < 0 else \
            f"|R^T R - I| reaches {residual:.2g} > tolerance {tolerance:.2g} (scale or shear; a rounded pose passes " \
            f"with a larger tolerance)"
        raise ValueError(f"{what} is not a rigid transform: its rotation block R is {kind}")
    if residual <= 1e-12 and (m[dim] == np.eye(dim + 1)[dim]).all():
        return m  # rigid to the last bits: as given
    u, _, vt = np.linalg.svd(rotation)
    out = m.copy()
    out[:dim, :dim] = u @ vt
    out[dim] = np.eye(dim + 1)[dim]
    return out


def rotation_xyz(degrees) -> np.ndarray:
    """The rotation [3, 3] of angles (rx, ry, rz) in degrees about the x, then y, then z axis (Rz Ry Rx)."""
    rx, ry, rz = np.radians(np.asarray(degrees, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return z @ y @ x


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

    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels, the centre of pixel (u, v) (column, row) at (u, v): square pixels,
        fx = width_px / 2 / tan(fov_deg / 2), the principal point at the image centre (as Open3D casts
        `rays`: pixel (u, v)'s ray in camera coordinates is ((u - cx) / fx, (v - cy) / fy, 1))."""
        f = 0.5 * self.width_px / np.tan(0.5 * np.radians(self.fov_deg))
        return float(f), float(f), 0.5 * self.width_px - 0.5, 0.5 * self.height_px - 0.5

    def camera_to_world(self) -> np.ndarray:
        """The camera's pose [4, 4] float64: camera coordinates (x along image columns, y along image rows,
        z along the view direction) to world coordinates; its translation is `eye`. Open3D's pinhole rays
        put image column 0 on the side of +(view x up), so the x axis is (up x view) normalized and y = z x x."""
        z = np.subtract(self.look_at, self.eye)
        z = z / np.linalg.norm(z)
        x = np.cross(self.up, z)
        x = x / np.linalg.norm(x)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
        pose[:3, 3] = self.eye
        return pose

    def rays(self) -> np.ndarray:
        """Rays [height_px * width_px, 6] float32 as (origin, direction), row-major pixels; each direction's
        component along the view direction is 1, so a ray's hit distance t is the hit's depth."""
        o3d = open3d_module()
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


@dataclass(frozen=True, eq=False)
class DepthImage:
    """One depth frame of a pinhole camera, as a real depth camera (or `DepthSensor.render`) delivers it.

    Attributes:
        depth: [H, W] depth along the optical axis (the camera's z), in scene units (metres for a real
            camera before `world_to_task`); 0 or NaN: no measurement.
        intrinsics: (fx, fy, cx, cy) in pixels, the centre of pixel (u, v) (column, row) at (u, v)
            (OpenCV's convention): pixel (u, v) at depth z is ((u - cx) z / fx, (v - cy) z / fy, z) in
            camera coordinates.
        camera_to_world: [4, 4] the camera's pose, camera coordinates (x along columns, y along rows,
            z forward) to world coordinates.
        mask: [H, W] bool, the pixels of the object (a segmentation), or None (all pixels).
        depth_scale: scene units per depth unit, e.g. 0.001 for a camera's millimetres (a RealSense's or a
            Kinect's uint16 images) to metres; required for an integer image, None: the depth is in scene units.
        rigid_tolerance: how far camera_to_world's rotation may be from orthonormal (`check_rigid`).
    """

    depth: np.ndarray
    intrinsics: tuple[float, float, float, float]
    camera_to_world: np.ndarray
    mask: np.ndarray | None = None
    depth_scale: float | None = None
    rigid_tolerance: float = RIGID_TOLERANCE

    def __post_init__(self) -> None:
        depth = np.asarray(self.depth)
        if depth.ndim != 2 or depth.size == 0 or not np.issubdtype(depth.dtype, np.number) or depth.dtype == np.bool_:
            raise ValueError(f"depth image must be a non-empty numeric [H, W] array, got {depth.dtype} "
                             f"{list(depth.shape)}")
        if self.depth_scale is not None and not (np.isfinite(self.depth_scale) and float(self.depth_scale) > 0):
            raise ValueError(f"depth_scale must be a finite number > 0 (scene units per depth unit), got "
                             f"{self.depth_scale!r}")
        if np.issubdtype(depth.dtype, np.integer) and self.depth_scale is None:
            raise ValueError(f"depth image is {depth.dtype} (integer depth units, e.g. a depth camera's millimetres): "
                             f"give depth_scale, the scene units per unit (0.001 for millimetres to metres)")
        depth = depth.astype(np.float64 if depth.dtype == np.float64 else np.float32)
        if self.depth_scale is not None:
            depth = depth * np.float32(self.depth_scale) if depth.dtype == np.float32 else depth * float(self.depth_scale)
        if np.isinf(depth).any() or (depth < 0).any():
            raise ValueError("depth image has negative or infinite values (0 or NaN mark a missing pixel)")
        object.__setattr__(self, "depth", depth)
        intrinsics = tuple(float(v) for v in np.asarray(self.intrinsics, dtype=np.float64).ravel())
        if len(intrinsics) != 4 or not np.isfinite(intrinsics).all() or min(intrinsics[:2]) <= 0:
            raise ValueError(f"intrinsics must be 4 finite numbers (fx, fy, cx, cy) with fx, fy > 0, got "
                             f"{self.intrinsics!r}")
        object.__setattr__(self, "intrinsics", intrinsics)
        object.__setattr__(self, "camera_to_world",
                           check_rigid(self.camera_to_world, 3, "camera_to_world", float(self.rigid_tolerance)))
        if self.mask is not None:
            mask = np.asarray(self.mask)
            if mask.shape != depth.shape or mask.dtype != np.bool_:
                raise ValueError(f"mask must be a bool array of the depth image's shape {list(depth.shape)}, got "
                                 f"{mask.dtype} {list(mask.shape)}")
            object.__setattr__(self, "mask", mask)


def back_project(image: DepthImage) -> np.ndarray:
    """World points [P, 3] float64 of the image's measured pixels (depth > 0, finite, in the mask), in
    row-major pixel order."""
    depth = image.depth
    valid = np.isfinite(depth) & (depth > 0)
    if image.mask is not None:
        valid &= image.mask
    v, u = np.nonzero(valid)
    z = depth[v, u].astype(np.float64)
    fx, fy, cx, cy = image.intrinsics
    camera = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=1)
    pose = image.camera_to_world
    return camera @ pose[:3, :3].T + pose[:3, 3]


# The quadratic axial noise of a structured-light camera: Khoshelham & Elberink (2012), "Accuracy and
# resolution of Kinect depth data for indoor mapping applications", Sensors 12(2), 1437-1454: the random
# error of the Kinect's depth grows with the square of the distance and reaches 4 cm at its 5 m range,
# sigma_z = c z^2 with c = 0.04 m / (5 m)^2 = 1.6e-3 per metre. In scene units where one unit is s metres
# the coefficient is c * s (sigma in units = c (z s)^2 / s).
KINECT_AXIAL_NOISE = 1.6e-3  # per metre

# Named sensor presets: the flaws of a depth camera at the levels a real one shows, lengths in metres
# (`sensor_flaws` scales them to a scene). Where a value comes from:
#   axial_noise: the Kinect's quadratic axial noise (Khoshelham & Elberink 2012, above).
#   grazing_angle_deg: the Kinect's depth noise is about flat up to about 60-70 degrees between the ray and the
#     surface's normal and rises steeply beyond (Nguyen, Izadi & Lovell 2012, "Modeling Kinect sensor noise for
#     improved 3D reconstruction and tracking", 3DIMPVT); pixels beyond 70 degrees return nothing.
#   edge_threshold, outlier_fraction, outlier_range: ours: depth jumps over 3 cm (mixed pixels at an object's
#     edge) are dropped as an edge filter would, and 0.5 % of the pixels that remain fly up to 10 cm along
#     their rays.
SENSOR_FLAWS: dict[str, dict] = {
    "flawless": {},
    "axial": {"axial_noise": KINECT_AXIAL_NOISE},
    "realistic": {"axial_noise": KINECT_AXIAL_NOISE, "grazing_angle_deg": 70.0, "edge_threshold": 0.03,
                  "outlier_fraction": 0.005, "outlier_range": 0.1},
}
# Extrinsic calibration errors (rx, ry, rz degrees; tx, ty, tz metres): "mm", a camera-to-robot calibration
# as good as hand-eye calibration gets (a few tenths of a degree, 2 mm); "cm", one off by a degree and a
# centimetre on every axis (ours).
CALIBRATION_ERRORS: dict[str, tuple[float, ...]] = {
    "none": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "mm": (0.2, 0.2, 0.2, 0.002, 0.002, 0.002),
    "cm": (1.0, 1.0, 1.0, 0.01, 0.01, 0.01),
}


def sensor_flaws(preset: str = "realistic", metres_per_unit: float = 1.0, noise_scale: float = 1.0,
                 calibration: str = "none") -> dict:
    """The `SensorConfig` flaw fields of a named preset (`SENSOR_FLAWS`) for a scene whose unit is
    `metres_per_unit` metres: lengths divided by it, the axial coefficient (per metre) multiplied by it
    and by `noise_scale`; `calibration`: a named extrinsic error (`CALIBRATION_ERRORS`) added. Unknown
    names raise ValueError naming the known ones."""
    if preset not in SENSOR_FLAWS:
        raise ValueError(f"unknown sensor preset {preset!r} (known: {sorted(SENSOR_FLAWS)})")
    if calibration not in CALIBRATION_ERRORS:
        raise ValueError(f"unknown calibration error {calibration!r} (known: {sorted(CALIBRATION_ERRORS)})")
    if not float(metres_per_unit) > 0 or not float(noise_scale) >= 0:
        raise ValueError(f"metres_per_unit must be > 0 and noise_scale >= 0, got {metres_per_unit}, {noise_scale}")
    s = float(metres_per_unit)
    out = dict(SENSOR_FLAWS[preset])
    if "axial_noise" in out:
        out["axial_noise"] = out["axial_noise"] * s * float(noise_scale)
    for name in ("edge_threshold", "outlier_range"):
        if name in out:
            out[name] = out[name] / s
    error = CALIBRATION_ERRORS[calibration]
    if any(error):
        out["extrinsic_error"] = (*error[:3], *(v / s for v in error[3:]))
    return out


@dataclass(frozen=True)
class SensorConfig:
    """Cameras plus point-cloud post-processing, and the sensor's flaws (all off by default).

    voxel_size: edge of the down-sampling voxel; noise_std: std of the Gaussian noise added
    to each output coordinate; slab_half_thickness: h of the 2D extrusion z in [-h, h].

    The flaws act on each camera's depth image (`DepthSensor.render`, and `observe` fuses those images
    when any is on; off, `observe` is the plain cast the datasets were made with):
        axial_noise: c of the depth noise sigma_z = c z^2 (z the pixel's depth) of a structured-light
            or stereo camera, in 1 / scene unit; each pixel moves along its ray. The Kinect's c is
            `KINECT_AXIAL_NOISE` = 1.6e-3 per metre (Khoshelham & Elberink 2012); a scene whose unit is
            s metres takes 1.6e-3 * s (the plate's unit is a metre: 1.6e-3, 1.4 cm at its camera's 3 m).
        grazing_angle_deg: pixels whose ray meets the surface at more than this angle from its normal
            return nothing (90: off).
        edge_threshold: pixels with a 4-neighbour whose depth differs by more than this (scene units),
            or that returns nothing, return nothing (depth edges and silhouettes; 0: off).
        outlier_fraction: the fraction of returned pixels that are flying pixels, moved along their ray
            by a uniform draw in [-outlier_range, outlier_range] (scene units).
        extrinsic_error: (rx, ry, rz, tx, ty, tz): every camera's true pose is its configured one times
            this rigid transform (degrees about the camera's x, y, z axes, then a translation in camera
            coordinates, scene units), while its images report the configured pose (a calibration error).
    """

    cameras: tuple[PinholeCamera, ...]
    voxel_size: float
    noise_std: float = 0.0
    slab_half_thickness: float = 0.05
    axial_noise: float = 0.0
    grazing_angle_deg: float = 90.0
    edge_threshold: float = 0.0
    outlier_fraction: float = 0.0
    outlier_range: float = 0.1
    extrinsic_error: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

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
        for name in ("axial_noise", "edge_threshold", "outlier_range"):
            if not float(getattr(self, name)) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
            object.__setattr__(self, name, float(getattr(self, name)))
        if not 0.0 < float(self.grazing_angle_deg) <= 90.0:
            raise ValueError(f"grazing_angle_deg must be in (0, 90], got {self.grazing_angle_deg}")
        if not 0.0 <= float(self.outlier_fraction) <= 1.0:
            raise ValueError(f"outlier_fraction must be in [0, 1], got {self.outlier_fraction}")
        for name in ("grazing_angle_deg", "outlier_fraction"):
            object.__setattr__(self, name, float(getattr(self, name)))
        error = tuple(float(v) for v in self.extrinsic_error)
        if len(error) != 6 or not np.isfinite(error).all():
            raise ValueError(f"extrinsic_error must be 6 finite numbers (rx, ry, rz degrees, tx, ty, tz), got "
                             f"{self.extrinsic_error!r}")
        object.__setattr__(self, "extrinsic_error", error)

    @property
    def has_flaws(self) -> bool:
        """Whether any of the sensor flaws is on (then `observe` fuses the flawed depth images)."""
        return (self.axial_noise > 0 or self.grazing_angle_deg < 90 or self.edge_threshold > 0
                or self.outlier_fraction > 0 or any(v != 0 for v in self.extrinsic_error))

    @property
    def random_flaws(self) -> bool:
        """Whether a flaw draws random numbers (axial noise, flying pixels): `render` then needs an rng."""
        return self.axial_noise > 0 or (self.outlier_fraction > 0 and self.outlier_range > 0)

    def error_transform(self) -> np.ndarray:
        """`extrinsic_error` as a rigid transform [4, 4] in camera coordinates (true pose = configured @ it)."""
        error = np.eye(4)
        error[:3, :3] = rotation_xyz(self.extrinsic_error[:3])
        error[:3, 3] = self.extrinsic_error[3:]
        return error

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


def object_mesh(positions: np.ndarray, cells: np.ndarray, slab_half_thickness: float,
                surface: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The closed surface a camera sees of a deformable mesh, (vertices [V, 3] float64, triangles [F, 3]
    int64): in 2D (positions [N, 2], triangles [C, 3]) the slab z in [-h, h], h = slab_half_thickness; in 3D
    (tetrahedra [C, 4]) the boundary triangles of the cells, or `surface` [F, 3] when the caller has them.
    ValueError for other shapes."""
    positions = np.asarray(positions, dtype=np.float64)
    d = positions.shape[1] if positions.ndim == 2 else 0
    if d not in (2, 3) or np.ndim(cells) != 2 or np.shape(cells)[1] != d + 1:
        shapes = f"{positions.shape}, {np.shape(cells)}"
        raise ValueError(f"expected positions [N,2|3] and cells [C,d+1], got {shapes}")
    if d == 2:
        return _deformable_mesh_2d(positions, cells, slab_half_thickness)
    return positions, boundary_facets(cells, positions) if surface is None else np.asarray(surface, dtype=np.int64)


def collider_mesh(vertices: np.ndarray, faces: np.ndarray, dim: int,
                  slab_half_thickness: float) -> tuple[np.ndarray, np.ndarray]:
    """The closed surface of a collider, (vertices [V, 3] float64, triangles [F, 3] int64): in 2D the slab of
    its closed polyline (vertices [K, 2], segments [F, 2]), in 3D its triangles (vertices [K, 3], faces [F, 3])."""
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    return _collider_mesh_2d(vertices, faces, slab_half_thickness) if dim == 2 else (vertices, faces)


def depth_edges(depth: np.ndarray, returned: np.ndarray, threshold: float) -> np.ndarray:
    """[H, W] bool: the returned pixels with a 4-neighbour (inside the image) that returns nothing or whose
    depth differs by more than `threshold` (depth [H, W], returned [H, W] bool)."""
    edge = np.zeros_like(returned)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        jump = ~returned[a] | ~returned[b] | (np.abs(depth[a] - depth[b]) > threshold)
        edge[a] |= jump
        edge[b] |= jump
    return edge & returned


class DepthSensor:
    """Ray-casts the deformed object (and an occluding collider) from fixed pinhole cameras.

    Rays of all cameras are built once here and cast in one batch per `observe` or `render` call (with an
    `extrinsic_error`, from the cameras' true poses).
    """

    def __init__(self, config: SensorConfig):
        self.config = config
        rays = np.concatenate([cam.rays() for cam in config.cameras], axis=0)
        self._rays = rays.astype(np.float64)
        self._rays_tensor = open3d_module().core.Tensor(np.ascontiguousarray(rays, dtype=np.float32))
        self._offsets = np.cumsum([0] + [cam.width_px * cam.height_px for cam in config.cameras])
        self._true_rays, self._true_rays_tensor = self._rays, self._rays_tensor
        if any(v != 0 for v in config.extrinsic_error):
            self._true_rays = self._rays.copy()
            error = config.error_transform()
            for cam, start, stop in zip(config.cameras, self._offsets[:-1], self._offsets[1:]):
                pose = cam.camera_to_world()
                true = pose @ error
                turn = true[:3, :3] @ pose[:3, :3].T  # the configured view directions to the true ones
                self._true_rays[start:stop, :3] = true[:3, 3]
                self._true_rays[start:stop, 3:] = self._rays[start:stop, 3:] @ turn.T
            self._true_rays_tensor = open3d_module().core.Tensor(
                np.ascontiguousarray(self._true_rays, dtype=np.float32))

    def _scene(self, positions, cells, collider_vertices, collider_faces, occluders, surface):
        """(Open3D raycasting scene, the deformable object's geometry id, d) of one state (`observe`'s
        arguments); ValueError for bad shapes."""
        cfg = self.config
        if (collider_vertices is None) != (collider_faces is None):
            raise ValueError("collider_vertices and collider_faces: give both or neither")
        positions = np.asarray(positions, dtype=np.float64)
        meshes = [object_mesh(positions, cells, cfg.slab_half_thickness, surface)]
        d = positions.shape[1]
        if collider_vertices is not None and len(collider_faces) > 0:
            meshes.append(collider_mesh(collider_vertices, collider_faces, d, cfg.slab_half_thickness))
        if len(occluders) and d != 3:
            raise ValueError("occluders are 3D triangle meshes; a 2D scene's occluder is its collider")
        for i, (vertices, triangles) in enumerate(occluders):
            vertices, triangles = np.asarray(vertices, dtype=np.float64), np.asarray(triangles, dtype=np.int64)
            if vertices.ndim != 2 or vertices.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
                raise ValueError(f"occluder {i}: expected vertices [V,3] and triangles [F,3], got "
                                 f"{vertices.shape}, {triangles.shape}")
            meshes.append((vertices, triangles))

        o3c = open3d_module().core
        scene = open3d_module().t.geometry.RaycastingScene()
        ids = [
            scene.add_triangles(
                o3c.Tensor(np.ascontiguousarray(v, dtype=np.float32)),
                o3c.Tensor(np.ascontiguousarray(t, dtype=np.uint32)),
            )
            for v, t in meshes
        ]
        return scene, ids[0], d

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
        their orientation does not matter to the rays. With a sensor flaw on (`SensorConfig.has_flaws`)
        the points are the object's pixels of the flawed depth images (`render`, drawing from `rng`
        first), back-projected with the configured camera poses and fused.
        """
        cfg = self.config
        if cfg.noise_std > 0.0 and rng is None:
            raise ValueError("rng is required when noise_std > 0")
        if cfg.random_flaws and rng is None:
            raise ValueError("rng is required when the sensor's flaws draw noise (axial_noise, outlier_fraction)")
        scene, object_id, d = self._scene(positions, cells, collider_vertices, collider_faces, occluders, surface)
        o3d = open3d_module()
        if cfg.has_flaws:
            points = np.concatenate([np.zeros((0, 3))] + [back_project(image) for image in
                                                          self._images(scene, object_id, rng)])
        else:
            hits = scene.cast_rays(self._rays_tensor)
            mask = hits["geometry_ids"].numpy() == object_id
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

    def render(
        self,
        positions: np.ndarray,
        cells: np.ndarray,
        collider_vertices: np.ndarray | None = None,
        collider_faces: np.ndarray | None = None,
        rng: np.random.Generator | None = None,
        occluders: Sequence[tuple[np.ndarray, np.ndarray]] = (),
        surface: np.ndarray | None = None,
    ) -> list[DepthImage]:
        """One `DepthImage` per camera of the state (`observe`'s arguments): the depth of whatever each pixel's
        ray hits first (object, collider or occluder; 0 where it hits nothing), float32 [height_px, width_px],
        the deformable object's pixels as the mask, the camera's `intrinsics` and configured
        `camera_to_world`, with the configured flaws applied (drawn from `rng`, needed when
        `SensorConfig.random_flaws`). 2D scenes are rendered as their 3D slabs: back-projected points
        lie on the slab's faces, and their (x, y) are the plane's coordinates."""
        if self.config.random_flaws and rng is None:
            raise ValueError("rng is required when the sensor's flaws draw noise (axial_noise, outlier_fraction)")
        scene, object_id, _ = self._scene(positions, cells, collider_vertices, collider_faces, occluders, surface)
        return self._images(scene, object_id, rng)

    def _images(self, scene, object_id: int, rng: np.random.Generator | None) -> list[DepthImage]:
        """The depth images of a built scene (`render`): cast from the true camera poses, flaws applied per
        camera in this order: grazing angles, depth edges (both on the true depths), axial noise, flying pixels."""
        cfg = self.config
        hits = scene.cast_rays(self._true_rays_tensor)
        t_hit = hits["t_hit"].numpy().astype(np.float64)
        ids = hits["geometry_ids"].numpy()
        normals = hits["primitive_normals"].numpy().astype(np.float64) if cfg.grazing_angle_deg < 90 else None
        images = []
        for cam, start, stop in zip(cfg.cameras, self._offsets[:-1], self._offsets[1:]):
            shape = (cam.height_px, cam.width_px)
            returned = np.isfinite(t_hit[start:stop]).reshape(shape)
            depth = np.where(returned, t_hit[start:stop].reshape(shape), 0.0)
            kept = returned.copy()
            if normals is not None:  # incidence angle between the ray and the surface normal
                directions = self._true_rays[start:stop, 3:]
                cosine = np.abs(np.sum(directions * normals[start:stop], axis=1)) / np.linalg.norm(directions, axis=1)
                kept &= (cosine >= np.cos(np.radians(cfg.grazing_angle_deg))).reshape(shape)
            if cfg.edge_threshold > 0:
                kept &= ~depth_edges(depth, returned, cfg.edge_threshold)
            depth = np.where(kept, depth, 0.0)
            if cfg.axial_noise > 0:
                z = depth[kept]
                depth[kept] = z + rng.normal(0.0, 1.0, size=z.shape) * cfg.axial_noise * z * z
            if cfg.outlier_fraction > 0 and cfg.outlier_range > 0:
                rows, cols = np.nonzero(kept)
                flying = rng.random(len(rows)) < cfg.outlier_fraction
                rows, cols = rows[flying], cols[flying]
                depth[rows, cols] += rng.uniform(-cfg.outlier_range, cfg.outlier_range, size=len(rows))
            depth = np.where(kept, np.maximum(depth, 1e-6), 0.0)  # a draw past the camera stays a (wild) return
            images.append(DepthImage(depth.astype(np.float32), cam.intrinsics(), cam.camera_to_world(),
                                     mask=(ids[start:stop] == object_id).reshape(shape)))
        return images
