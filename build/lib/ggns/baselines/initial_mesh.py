"""Initial mesh generation (GGNS paper, 2D Deformable Plate): start a learned simulator not from
the true initial mesh but from a mesh generated from the FIRST point cloud, roll it out with the
point clouds of the schedule, and score it by the IoU of the covered areas (the generated and
true meshes have different nodes, so node-wise MSE is undefined).

The generated mesh: the first point cloud is voxel-subsampled to about `target_nodes` points
(`alpha_shapes.voxel_subsample`), Delaunay-triangulated, and only the triangles of the alpha shape
(circumradius < 1 / alpha, default `alpha_shapes.default_alpha`) are kept; nodes no kept triangle
uses are dropped. The plate's bottom edge is the Dirichlet boundary: generated nodes in the bottom
voxel row (see `generated_trajectory`) are fixed.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch
from scipy.spatial import Delaunay, QhullError

from ..batch import TrajectoryBatch
from ..evaluation.evaluate import split_trajectories
from ..evaluation.metrics import mesh_iou
from ..geometry import cell_edges, signed_volumes
from ..trajectory import Trajectory
from .alpha_shapes import default_alpha, points_2d, voxel_centroids, voxel_size_for


def _generate(points, target_nodes: int, alpha: float | None):
    """(nodes, cells, edges, voxel size) of `mesh_from_point_cloud`."""
    points = points_2d(points)
    target_nodes = int(target_nodes)
    if target_nodes < 3:
        raise ValueError(f"target_nodes must be >= 3, got {target_nodes}")
    voxel = voxel_size_for(points, target_nodes)  # ValueError on empty / coincident clouds
    sub = voxel_centroids(points, voxel)
    alpha = default_alpha(voxel) if alpha is None else float(alpha)
    if not alpha > 0:
        raise ValueError(f"alpha must be > 0 (alpha = 1 / radius), got {alpha}")
    if len(sub) < 3:
        raise ValueError(f"only {len(sub)} points after subsampling, a mesh needs >= 3")
    try:
        tri = Delaunay(sub).simplices.astype(np.int64)
    except QhullError as err:
        raise ValueError("the subsampled points are collinear: no triangle") from err
    p = sub[tri]
    a = np.linalg.norm(p[:, 1] - p[:, 2], axis=1)
    b = np.linalg.norm(p[:, 0] - p[:, 2], axis=1)
    c = np.linalg.norm(p[:, 0] - p[:, 1], axis=1)
    area = np.abs(signed_volumes(sub, tri))
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.where(area > 0, a * b * c / (4.0 * area), np.inf)
    cells = tri[radius < 1.0 / alpha]
    if len(cells) == 0:
        raise ValueError(f"no triangle of the alpha shape is left (alpha={alpha:g}, voxel={voxel:g})")
    used = np.unique(cells)
    remap = np.full(len(sub), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    nodes, cells = sub[used], remap[cells]
    clockwise = signed_volumes(nodes, cells) < 0
    cells[clockwise] = cells[clockwise][:, [0, 2, 1]]
    return nodes, cells, cell_edges(cells), voxel


def mesh_from_point_cloud(points, target_nodes: int, alpha: float | None = None):
    """Triangle mesh generated from a 2D point cloud [P, 2].

    Voxel-subsample to about `target_nodes` points, Delaunay-triangulate, keep the triangles with
    circumradius < 1 / alpha (default `default_alpha(voxel size)`), drop unused nodes and reindex.
    Returns (nodes float64 [N', 2], cells int64 [C, 3] counter-clockwise, edges int64 [E, 2] with
    i < j, sorted). ValueError on bad input or when no triangle is left.
    """
    nodes, cells, edges, _ = _generate(points, target_nodes, alpha)
    return nodes, cells, edges


def generated_trajectory(traj: Trajectory, target_nodes: int | None = None, alpha: float | None = None,
                         fixed_tolerance: float | None = None) -> Trajectory:
    """A copy of the 2D `traj` whose mesh is generated from its first point cloud.

    target_nodes defaults to the true mesh's node count. rest_positions and positions[t] for all t
    are the generated nodes: the true later states of these nodes are unknown, so positions[1:]
    are PLACEHOLDERS. A rollout only reads positions[0] and, for fixed nodes, positions[t] (which
    is right: the fixed bottom edge does not move); never score against them. Fixed nodes: those
    within `fixed_tolerance` above the lowest point of the first cloud; the default is one voxel
    size, i.e. the bottom voxel row (the voxel grid is anchored at the lowest point, and the
    centroids of that row lie about half a voxel above it, so half a voxel would be a coin flip).
    Collider, point clouds, material, params and diagnostics are unchanged.
    """
    if traj.dim != 2:
        raise ValueError(f"initial mesh generation is 2D only, got dim {traj.dim}")
    cloud = points_2d(traj.point_cloud(0), "first point cloud")
    target = len(traj.rest_positions) if target_nodes is None else int(target_nodes)
    nodes, cells, edges, voxel = _generate(cloud, target, alpha)
    tol = voxel if fixed_tolerance is None else float(fixed_tolerance)
    if not tol >= 0:
        raise ValueError(f"fixed_tolerance must be >= 0, got {fixed_tolerance}")
    fixed = nodes[:, 1] <= cloud[:, 1].min() + tol
    return dataclasses.replace(
        traj,
        rest_positions=nodes.copy(),
        cells=cells,
        edges=edges,
        positions=np.repeat(nodes[None], traj.num_steps, axis=0),
        fixed=fixed,
    )


def initial_mesh_rollout_ious(model, trajectories: list[Trajectory], schedule, generated: list[Trajectory] | None = None,
                              target_nodes: int | None = None, alpha: float | None = None,
                              fixed_tolerance: float | None = None) -> list[np.ndarray]:
    """Roll out `model` (a `GraphSimulator`) from the meshes generated from the first point cloud
    of each trajectory (one batch) under `schedule` (a Schedule or e.g. "every:5") and return,
    per trajectory, the IoU with the true mesh of every step: float64 [T]; index 0 scores the
    generated mesh itself. `generated`: the `generated_trajectory`s, when already made."""
    if generated is None:
        generated = [generated_trajectory(t, target_nodes, alpha, fixed_tolerance) for t in trajectories]
    batch = TrajectoryBatch.from_trajectories(generated, device=model.device, dtype=model.dtype)
    preds = split_trajectories(model.rollout(batch, schedule), batch)  # [1, T, N', d] each, CPU
    return [np.array([mesh_iou(p[0, t].to(torch.float64).numpy(), gen.cells, traj.positions[t], traj.cells)
                      for t in range(traj.num_steps)])
            for p, gen, traj in zip(preds, generated, trajectories)]


def initial_mesh_rollout_iou(model, traj: Trajectory, schedule, target_nodes: int | None = None,
                             alpha: float | None = None, fixed_tolerance: float | None = None) -> np.ndarray:
    """`initial_mesh_rollout_ious` of one trajectory: float64 [T]."""
    return initial_mesh_rollout_ious(model, [traj], schedule, None, target_nodes, alpha, fixed_tolerance)[0]
