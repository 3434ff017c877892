"""One tick of the rollout engine, for a simulator stepped by its caller (`OnlineSimulator`).

The offline engine (`evaluation.rollout.rollout`) predicts state t + 1 of a recorded `TrajectoryBatch`
from the graph of state t (`graphs.state.state_graph`), the model's step function and the fixed nodes set
to their known positions. Online only the current state and the inputs of one tick exist: `tick_batch`
puts them into a `TrajectoryBatch` of two states (the static parts, mesh, cells, fixed mask, material,
shared by every tick), and `advance` makes the step of `rollout`'s loop on it (`evaluation.rollout.predict_next`,
the one prediction step both call), so that fed the recorded inputs it returns what `rollout` returns.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import Tensor

from ..batch import TrajectoryBatch
from ..evaluation.rollout import StepFn, predict_next
from ..graphs.connectivity import Connectivity


def tick_batch(static: TrajectoryBatch, positions: Tensor, fixed_next: Tensor, collider: Tensor | None,
               collider_next: Tensor | None, points: list[Tensor | None]) -> TrajectoryBatch:
    """The two-state batch of one tick (state t -> t + 1) of B objects.

    Args:
        static: the objects' static parts, a batch of 2 states built once (`TrajectoryBatch.from_trajectories`
            of the objects; its values were checked there).
        positions: [sumN, d] the mesh at tick t (state 0 of the batch).
        fixed_next: [sumN, d] whose fixed rows are the fixed nodes' positions at t + 1 (state 1; its other
            rows are not read).
        collider, collider_next: [sumK, d] the collider vertices at t and t + 1 (None without colliders).
        points: B point clouds [P_b, d] of tick t on the batch's device and dtype, None where an object has none.

    Returns:
        the batch; its point clouds at state 0 are the objects' clouds concatenated (empty for None), with
        their host offsets, none at state 1.
    """
    clouds = [p if p is not None else positions.new_zeros(0, positions.size(1)) for p in points]
    counts = [len(p) for p in clouds]
    offsets = [0]
    for count in counts:
        offsets.append(offsets[-1] + count)
    owner = torch.repeat_interleave(torch.arange(len(clouds), device=positions.device),
                                    torch.as_tensor(counts, device=positions.device))
    empty = positions.new_zeros(0, positions.size(1))
    return dataclasses.replace(
        static,
        positions=torch.stack([positions, fixed_next]),
        collider=None if collider is None else torch.stack([collider, collider_next]),
        points=[torch.cat(clouds), empty],
        point_batch=[owner, owner[:0]],
        point_offsets=(tuple(offsets), (0,) * len(offsets)),
        inputs_checked=True,  # the static parts were checked once; the point batch vector is sorted by construction
    )


def points_flags(points: list[Tensor | None]) -> bool | Tensor:
    """`state_graph`'s use_points for the objects' clouds of one tick: True when every object has one, False when
    none has, else a bool [B] (the clouds of the objects without one left out)."""
    given = [p is not None for p in points]
    if all(given) or not any(given):
        return all(given)
    return torch.tensor(given, dtype=torch.bool)


def advance(step_fn: StepFn, batch: TrajectoryBatch, positions: Tensor, use_points: bool | Tensor,
            connectivity: Connectivity, with_material: bool, state: Any) -> tuple[Tensor, Any]:
    """The rollout engine's prediction of state 1 of a `tick_batch` from the mesh `positions` [sumN, d] at
    state 0: the graph (`state_graph`), the step function (displacement [sumN, d] and the new model state)
    and the fixed nodes set to state 1's. Returns (positions [sumN, d], new model state); a neighbour count
    over the connectivity's cap raises the graph builder's ValueError at once."""
    with torch.no_grad():
        return predict_next(step_fn, batch, 0, positions, use_points, connectivity, with_material, state)
