"""The one place that turns a simulation state into model input: `state_graph`, the batched
HeteroData of step t -> t+1 of a `TrajectoryBatch` (mesh at given positions, collider, optional
point clouds, optional material), and `ConstructionTimer`, which sums the time spent in it (the
benchmarks' graph construction share)."""
from __future__ import annotations

import time

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from ..batch import TrajectoryBatch
from .build import NeighbourCheck, build_graph
from .connectivity import Connectivity


_ACTIVE_TIMERS: list["ConstructionTimer"] = []


class ConstructionTimer:
    """`with ConstructionTimer(device) as timer:` sums, in timer.seconds and timer.calls, the time
    spent in `state_graph` inside the block, synchronizing `device` (CUDA) around each call so that
    the time is the construction's own. Nested timers all count."""

    def __init__(self, device: torch.device | str | None = None):
        self.device = torch.device(device) if device is not None else None
        self.seconds, self.calls = 0.0, 0

    def __enter__(self) -> ConstructionTimer:
        _ACTIVE_TIMERS.append(self)
        return self

    def __exit__(self, *exc) -> None:
        _ACTIVE_TIMERS.remove(self)

    def reset(self) -> None:
        self.seconds, self.calls = 0.0, 0

    def sync(self) -> None:
        if self.device is not None and self.device.type == "cuda":
            torch.cuda.synchronize(self.device)


def state_graph(batch: TrajectoryBatch, t: int, mesh_pos: Tensor, use_points: bool | Tensor,
                connectivity: Connectivity, with_material: bool = False,
                neighbours: NeighbourCheck | None = None) -> HeteroData:
    """`build_state_graph`, timed by the active `ConstructionTimer`s (if any)."""
    if not _ACTIVE_TIMERS:
        return build_state_graph(batch, t, mesh_pos, use_points, connectivity, with_material, neighbours)
    for timer in _ACTIVE_TIMERS:
        timer.sync()
    start = time.perf_counter()
    graph = build_state_graph(batch, t, mesh_pos, use_points, connectivity, with_material, neighbours)
    for timer in _ACTIVE_TIMERS:
        timer.sync()
    elapsed = time.perf_counter() - start
    for timer in _ACTIVE_TIMERS:
        timer.seconds += elapsed
        timer.calls += 1
    return graph


def build_state_graph(batch: TrajectoryBatch, t: int, mesh_pos: Tensor, use_points: bool | Tensor,
                      connectivity: Connectivity, with_material: bool = False,
                      neighbours: NeighbourCheck | None = None) -> HeteroData:
    """The batched model input for step t -> t+1 (0 <= t <= T-2): mesh at mesh_pos [sumN, d],
    collider at t with velocity to t+1, the point clouds at t of the trajectories whose
    use_points (bool, or bool [B] per trajectory, best on the host: the points are then cut out by
    the batch's host offsets without a device sync) is True, Poisson ratios if with_material
    (ValueError when a trajectory's ratio is a placeholder, `TrajectoryBatch.require_material`).
    neighbours: record the neighbour caps there (a deferred check) instead of checking them at once.
    The batch's value checks run once per batch (`TrajectoryBatch.inputs_checked`)."""
    if not 0 <= t < batch.num_steps - 1:
        raise IndexError(f"graph step t={t} outside [0, {batch.num_steps - 2}] (needs the collider at t+1)")
    if with_material:
        batch.require_material("this model")
    points, point_batch = None, None
    if isinstance(use_points, Tensor):
        if use_points.shape != (batch.num_graphs,) or use_points.dtype != torch.bool:
            raise ValueError(f"use_points must be a bool or a bool tensor [B={batch.num_graphs}], "
                             f"got {use_points.dtype} {tuple(use_points.shape)}")
        keep = use_points.tolist()
        points, point_batch = select_points(batch, t, keep)
    else:
        keep = [bool(use_points)] * batch.num_graphs
        if use_points:
            points, point_batch = batch.points[t], batch.point_batch[t]
    has_collider = batch.collider is not None
    graph = build_graph(
        mesh_pos=mesh_pos,
        mesh_rest=batch.rest,
        mesh_edges=batch.edges,
        fixed=batch.fixed,
        mesh_batch=batch.mesh_batch,
        collider_pos=batch.collider[t] if has_collider else None,
        collider_next=batch.collider[t + 1] if has_collider else None,
        collider_batch=batch.collider_batch,
        points=points,
        point_batch=point_batch,
        connectivity=connectivity,
        num_graphs=batch.num_graphs,
        material=batch.material if with_material else None,
        neighbours=neighbours,
        check_inputs=not batch.inputs_checked,
    )
    batch.inputs_checked = True
    offsets = batch.point_range(t) if connectivity.uses_points else None
    # host flags: which trajectories' point clouds are in the graph (kept and not empty)
    graph.points_seen = tuple(bool(connectivity.uses_points and k and offsets[b + 1] > offsets[b])
                              for b, k in enumerate(keep))
    return graph


def select_points(batch: TrajectoryBatch, t: int, keep: list[bool]) -> tuple[Tensor, Tensor]:
    """The points at step t of the trajectories b with keep[b], and their batch vector: contiguous runs of
    kept trajectories cut out by the batch's host offsets (views; one concatenation)."""
    offsets = batch.point_range(t)
    runs, start = [], None
    for b, k in enumerate(keep + [False]):
        if k and start is None:
            start = b
        elif not k and start is not None:
            runs.append(slice(offsets[start], offsets[b]))
            start = None
    points, owner = batch.points[t], batch.point_batch[t]
    if len(runs) == 1:
        return points[runs[0]], owner[runs[0]]
    if not runs:
        return points[:0], owner[:0]
    return torch.cat([points[r] for r in runs]), torch.cat([owner[r] for r in runs])
