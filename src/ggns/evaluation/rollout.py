"""The one rollout engine: a learned step function applied autoregressively to a TrajectoryBatch.

`step_fn(graph, state) -> (displacement [sumN, d], new_state)` predicts x_{t+1} - x_t in world
(task-space) units from the graph of step t (`graphs.state.state_graph`) and carries any model
state (e.g. an LSTM hidden state); state None means a fresh start. Collider positions and point
clouds come from the data; fixed mesh nodes are set to their true positions every step.
Positions returned are [steps + 1, sumN, d]: index 0 is the start state.
"""
from __future__ import annotations

import copy
from typing import Any, Callable

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from .metrics import m_plus_10_starts
from .schedules import EveryK, Never, Schedule
from ..batch import TrajectoryBatch
from ..graphs.connectivity import Connectivity
from ..graphs.state import state_graph

StepFn = Callable[[HeteroData, Any], tuple[Tensor, Any]]


class RolloutError(RuntimeError):
    """A rollout produced non-finite positions, or a node escaped the scene; `step` is the prediction
    step (state step -> step + 1) where it happened."""

    def __init__(self, message: str, step: int | None = None):
        super().__init__(message)
        self.step = step


def rollout(step_fn: StepFn, batch: TrajectoryBatch, schedule: Schedule, connectivity: Connectivity,
            with_material: bool = False, start_positions: Tensor | None = None, start: int = 0,
            steps: int | None = None, state: Any = None) -> tuple[Tensor, Any]:
    """Predict states start+1 .. start+steps from the true state at `start` (or start_positions
    [sumN, d]); prediction step t uses the point clouds of state t iff schedule.uses_points(t).
    steps defaults to T-1-start. Returns (positions [steps+1, sumN, d], final state).
    Raises RolloutError naming the step and trajectories that went non-finite, or the first node
    that escaped (farther than ESCAPE_FACTOR x the start state's extent from its start)."""
    last = batch.num_steps - 1
    steps = last - start if steps is None else steps
    if start < 0 or steps < 0 or start + steps > last:
        raise ValueError(f"rollout start={start}, steps={steps} leaves the states 0..{last}")
    pos = batch.positions[start] if start_positions is None else start_positions.to(batch.positions)
    fixed = batch.fixed[:, None]
    out = [pos]
    origin, extent = pos, float((pos.amax(0) - pos.amin(0)).norm()) if len(pos) else 0.0
    with torch.no_grad():
        for t in range(start, start + steps):
            graph = state_graph(batch, t, pos, schedule.uses_points(t), connectivity, with_material)
            displacement, state = step_fn(graph, state)
            pos = torch.where(fixed, batch.positions[t + 1], pos + displacement)
            _check_finite(pos, batch, t)
            _check_bounded(pos, origin, extent, batch, t)
            out.append(pos)
    return torch.stack(out), state


def one_step_predictions(step_fn: StepFn, batch: TrajectoryBatch, schedule: Schedule, connectivity: Connectivity,
                         with_material: bool = False) -> Tensor:
    """Teacher-forced predictions: state t+1 predicted from the *true* state t for every t, with the
    point clouds of `schedule` and any model state (an LSTM's) carried along the true trajectory.
    Returns [T, sumN, d]: index 0 is the true S_0, index t the prediction of S_t."""
    batch.require_ground_truth("teacher-forced prediction")
    fixed = batch.fixed[:, None]
    out, state = [batch.positions[0]], None
    with torch.no_grad():
        for t in range(batch.num_steps - 1):
            graph = state_graph(batch, t, batch.positions[t], schedule.uses_points(t), connectivity, with_material)
            displacement, state = step_fn(graph, state)
            pos = torch.where(fixed, batch.positions[t + 1], batch.positions[t] + displacement)
            _check_finite(pos, batch, t)
            out.append(pos)
    return torch.stack(out)


def m_plus_10_rollouts(step_fn: StepFn, batch: TrajectoryBatch, connectivity: Connectivity, horizon: int = 10,
                       starts: list[int] | None = None, with_material: bool = False) -> dict[int, Tensor]:
    """The m+horizon rollouts of `metrics.m_plus_10_mse`: one chain with point clouds every step
    gives the state (and model state) after m steps, from which `horizon` steps run blind.
    Returns {m: [m+horizon+1, sumN, d]}, index i = prediction of state i (0..m: the chain)."""
    starts = sorted(m_plus_10_starts(batch.num_steps, horizon) if starts is None else starts)
    if starts and (starts[0] < 0 or starts[-1] + horizon > batch.num_steps - 1):
        raise ValueError(f"m+{horizon} starts {starts} need 0 <= m <= {batch.num_steps - 1 - horizon}")
    preds, chain, state = {}, [batch.positions[0]], None
    for m in range(starts[-1] + 1 if starts else 0):
        if m in starts:
            blind, _ = rollout(step_fn, batch, Never(), connectivity, with_material, chain[m], m, horizon,
                               copy.deepcopy(state))
            preds[m] = torch.cat([torch.stack(chain), blind[1:]])
        if m < starts[-1]:
            nxt, state = rollout(step_fn, batch, EveryK(1), connectivity, with_material, chain[m], m, 1, state)
            chain.append(nxt[1])
    return preds


# A node farther than this many times the start state's extent from where it started has left any
# scene (they are normalized to [-1, 1]^d): the rollout is reported as diverged rather than continued
# as garbage (checked in `rollout`, which runs long horizons; not in the one-step predictions).
ESCAPE_FACTOR = 100.0


def _check_bounded(pos: Tensor, start: Tensor, extent: float, batch: TrajectoryBatch, t: int) -> None:
    """Raise RolloutError if a node of pos [sumN, d] (the prediction of state t+1) lies farther than
    ESCAPE_FACTOR x `extent` (the start state's bounding-box diagonal) from its start position `start`."""
    distance = (pos - start).norm(dim=1)
    bad = distance > ESCAPE_FACTOR * extent
    if bad.any():
        first = int(torch.nonzero(bad)[0])
        trajectory = int(batch.mesh_batch[first])
        raise RolloutError(
            f"rollout diverged at prediction step {t} (state {t} -> {t + 1}): mesh node "
            f"{first - batch.node_offsets[trajectory]} of trajectory {trajectory} is {float(distance[first]):.4g} "
            f"from its start, more than {ESCAPE_FACTOR:g} x the start state's extent ({extent:.4g}); "
            f"{int(bad.sum())} node(s) that far", step=t)


def _check_finite(pos: Tensor, batch: TrajectoryBatch, t: int) -> None:
    """Raise RolloutError if pos [sumN, d] (the prediction of state t+1) is not finite, naming the
    step, the trajectories, and the first such node (its index within its trajectory) and value."""
    bad = ~torch.isfinite(pos).all(dim=1)
    if bad.any():
        trajectories = batch.mesh_batch[bad].unique().tolist()
        first = int(torch.nonzero(bad)[0])
        trajectory = int(batch.mesh_batch[first])
        node = first - batch.node_offsets[trajectory]
        raise RolloutError(
            f"rollout diverged at prediction step {t} (state {t} -> {t + 1}): non-finite positions "
            f"in trajectory index(es) {trajectories} of the batch; the first: mesh node {node} of trajectory "
            f"{trajectory}, predicted position {pos[first].tolist()}", step=t)
