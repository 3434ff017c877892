"""Alpha-shape baseline of the GGNS paper for the 2D Deformable Plate (non-learned).

Per time step the observed point cloud is voxel-subsampled to about as many points as the true
mesh has nodes, an alpha shape (a possibly non-convex region) is built from the subsampled
points, and it is scored by the IoU with the area covered by the true mesh triangles (the same
union-of-triangles region as `ggns.evaluation.metrics`).

Alpha convention: `alpha` is an inverse length, alpha = 1 / radius. The alpha shape used here is
the union of the Delaunay triangles whose circumradius is < 1 / alpha; a larger alpha keeps fewer
(smaller) triangles and gives a tighter, more concave shape, alpha -> 0 gives the convex hull.

The paper gives no alpha value (its reference code used alpha = 10 on the full point cloud,
without subsampling); `default_alpha` is this module's own rule of thumb, not the paper's.
"""
from __future__ import annotations

import numpy as np
import shapely
from scipy.spatial import Delaunay, QhullError

from ..evaluation.metrics import check_cells, mesh_region, region_iou

# circumradius threshold of `default_alpha`, in voxel sizes
DEFAULT_RADIUS_VOXELS = 1.5


def points_2d(points, name: str = "points") -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"{name} must be [P, 2], got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError(f"{name} has non-finite values")
    return points


def voxel_centroids(points: np.ndarray, size: float) -> np.ndarray:
    """Centroid of the points in each occupied square voxel of side `size` (grid anchored at the
    points' minimum corner), ordered by voxel index: [V, 2]."""
    cell = np.floor((points - points.min(axis=0)) / size).astype(np.int64)
    keys = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]  # row-major voxel id
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.zeros((counts.size, 2))
    np.add.at(sums, inverse, points)
    return sums / counts[:, None]


def voxel_size_for(points, target: int, iterations: int = 40) -> float:
    """Voxel size whose subsampling keeps about `target` points.

    Bisection on log(size) for the largest size that still keeps >= `target` voxels (capped at
    the number of distinct points), between 1e-9 and 2 times the bounding-box extent; of the two
    final brackets the one whose count is closer to `target` is returned (the larger on a tie).
    Taking the largest such size matters when the cloud is sparser than `target` allows: any tiny
    size would then hit the count, but the voxel size should reflect the point spacing.
    """
    points = points_2d(points)
    if len(points) == 0:
        raise ValueError("points is empty")
    if target < 3:
        raise ValueError(f"target must be >= 3, got {target}")
    extent = float((points.max(axis=0) - points.min(axis=0)).max())
    if extent == 0.0:
        raise ValueError("all points coincide")
    count = lambda log_size: len(voxel_centroids(points, float(np.exp(log_size))))  # noqa: E731
    lo, hi = np.log(extent * 1e-9), np.log(extent * 2.0)  # count(hi) == 1: one voxel holds all
    target = min(target, count(lo))  # invariant: count(lo) >= target > count(hi)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if count(mid) >= target:
            lo = mid
        else:
            hi = mid
    best = lo if abs(count(lo) - target) <= abs(count(hi) - target) else hi
    return float(np.exp(best))


def voxel_subsample(points, target: int) -> np.ndarray:
    """Grid voxel subsampling of points [P, 2] to about `target` points (centroid per occupied
    voxel, voxel size from `voxel_size_for`). Deterministic. Returns float64 [P', 2]."""
    points = points_2d(points)
    return voxel_centroids(points, voxel_size_for(points, target))


def default_alpha(voxel_size: float) -> float:
    """Rule of thumb (this module's, not the paper's): keep triangles with circumradius below
    1.5 voxel sizes, i.e. alpha = 1 / (1.5 * voxel). Subsampled points are roughly one voxel apart,
    whose Delaunay triangles have circumradii of about 0.7 voxel; 1.5 tolerates irregular spacing
    while still leaving holes and concavities wider than ~3 voxels open."""
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    return 1.0 / (DEFAULT_RADIUS_VOXELS * voxel_size)


def alpha_shape(points, alpha: float):
    """Alpha shape of points [P, 2]: the union (a shapely geometry) of the Delaunay triangles with
    circumradius < 1 / alpha. Collinear/degenerate triangles have infinite circumradius and are
    dropped; if every triangle is rejected (or all points are collinear) the result is an empty
    geometry."""
    points = points_2d(points)
    if not alpha > 0:
        raise ValueError(f"alpha must be > 0 (alpha = 1 / radius), got {alpha}")
    if len(points) < 3:
        raise ValueError(f"an alpha shape needs >= 3 points, got {len(points)}")
    try:
        tri = Delaunay(points).simplices
    except QhullError:  # all points collinear or coincident: no 2D triangle
        return shapely.Polygon()
    p = points[tri]  # [C, 3, 2]
    a = np.linalg.norm(p[:, 1] - p[:, 2], axis=1)
    b = np.linalg.norm(p[:, 0] - p[:, 2], axis=1)
    c = np.linalg.norm(p[:, 0] - p[:, 1], axis=1)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.where(area > 0, a * b * c / (4.0 * area), np.inf)
    keep = tri[radius < 1.0 / alpha]
    if len(keep) == 0:
        return shapely.Polygon()
    return mesh_region(points, keep)


def alpha_shape_iou(points, true_positions, cells, alpha: float | None = None, target: int | None = None) -> float:
    """IoU of the alpha shape of the voxel-subsampled point cloud with the true mesh region.

    points [P, 2]; true_positions [N, 2]; cells [C, 3]; target: subsample size (default N);
    alpha: 1 / radius, default `default_alpha(voxel size)`. An empty alpha shape scores 0.
    """
    true_positions = points_2d(true_positions, "true_positions")
    cells = check_cells(cells, len(true_positions))
    points = points_2d(points)
    target = len(true_positions) if target is None else int(target)
    voxel = voxel_size_for(points, target)
    sub = voxel_centroids(points, voxel)
    shape = alpha_shape(sub, default_alpha(voxel) if alpha is None else alpha)
    truth = mesh_region(true_positions, cells)
    if not shapely.area(truth) > 0:
        raise ValueError("the true mesh covers zero area")
    return float(region_iou(shape, truth))


def trajectory_alpha_iou(traj, alpha: float | None = None, target: int | None = None) -> np.ndarray:
    """Per-step alpha-shape IoU of a 2D `Trajectory`: float64 [T] (see `alpha_shape_iou`)."""
    if traj.dim != 2:
        raise ValueError(f"the alpha-shape baseline is 2D only, got dim {traj.dim}")
    return np.array([
        alpha_shape_iou(traj.point_cloud(t), traj.positions[t], traj.cells, alpha, target)
        for t in range(traj.num_steps)
    ])
