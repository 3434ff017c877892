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
from .build import build_graph
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
                connectivity: Connectivity, with_material: bool = False) -> HeteroData:
    """`build_state_graph`, timed by the active `ConstructionTimer`s (if any)."""
    if not _ACTIVE_TIMERS:
        return build_state_graph(batch, t, mesh_pos, use_points, connectivity, with_material)
    for timer in _ACTIVE_TIMERS:
        timer.sync()
    start = time.perf_counter()
    graph = build_state_graph(batch, t, mesh_pos, use_points, connectivity, with_material)
    for timer in _ACTIVE_TIMERS:
        timer.sync()
    elapsed = time.perf_counter() - start
    for timer in _ACTIVE_TIMERS:
        timer.seconds += elapsed
        timer.calls += 1
    return graph


def build_state_graph(batch: TrajectoryBatch, t: int, mesh_pos: Tensor, use_points: bool | Tensor,
                      connectivity: Connectivity, with_material: bool = False) -> HeteroData:
    """The batched model input for step t -> t+1 (0 <= t <= T-2): mesh at mesh_pos [sumN, d],
    collider at t with velocity to t+1, the point clouds at t of the trajectories whose
    use_points (bool, or bool [B] per trajectory) is True, Poisson ratios if with_material (ValueError when
    a trajectory's ratio is a placeholder, `TrajectoryBatch.require_material`)."""
    if not 0 <= t < batch.num_steps - 1:
        raise IndexError(f"graph step t={t} outside [0, {batch.num_steps - 2}] (needs the collider at t+1)")
    if with_material:
        batch.require_material("this model")
    points, point_batch = None, None
    if isinstance(use_points, Tensor):
        if use_points.shape != (batch.num_graphs,) or use_points.dtype != torch.bool:
            raise ValueError(f"use_points must be a bool or a bool tensor [B={batch.num_graphs}], "
                             f"got {use_points.dtype} {tuple(use_points.shape)}")
        keep = use_points.to(batch.device)[batch.point_batch[t]]
        points, point_batch = batch.points[t][keep], batch.point_batch[t][keep]
    elif use_points:
        points, point_batch = batch.points[t], batch.point_batch[t]
    has_collider = batch.collider is not None
    return build_graph(
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
    )
