"""The one rollout engine: a learned step function applied autoregressively to a TrajectoryBatch.

`step_fn(graph, state) -> (displacement [sumN, d], new_state)` predicts x_{t+1} - x_t in world
(task-space) units from the graph of step t (`graphs.state.state_graph`) and carries any model
state (e.g. an LSTM hidden state); state None means a fresh start. Collider positions and point
clouds come from the data; fixed mesh nodes are set to their true positions every step.
Positions returned are [steps + 1, sumN, d]: index 0 is the start state.

Divergence (non-finite positions, a node that escaped the scene) and the graphs' neighbour caps are
checked every step on the device (`ggns.checks`) and read every `check_every` steps and at the end
(default: every step on the CPU, where a read costs nothing; every `DEVICE_CHECK_EVERY` steps on a
GPU), so a GPU rollout does not stop at every step to ask. The error names the first step where it
happened. Non-finite positions are held at their last finite value until the read, so that no NaN
reaches the neighbour search.
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
from ..checks import DeferredCheck, reads_cost
from ..errors import RolloutError  # noqa: F401 (raised here; importable from here as before)
from ..graphs.build import NeighbourCheck
from ..graphs.connectivity import Connectivity
from ..graphs.state import state_graph
from ..phases import phase

StepFn = Callable[[HeteroData, Any], tuple[Tensor, Any]]


DEVICE_CHECK_EVERY = 32  # steps between reads of the rollout checks on a GPU


def check_interval(device: torch.device, check_every: int | None) -> int:
    """Steps between reads of a rollout's deferred checks: `check_every`, or every step on the CPU and
    every DEVICE_CHECK_EVERY steps on other devices."""
    if check_every is not None:
        if check_every < 1:
            raise ValueError(f"check_every must be >= 1, got {check_every}")
        return check_every
    return 1 if device.type == "cpu" else DEVICE_CHECK_EVERY


class DivergenceCheck:
    """The rollout's deferred checks: non-finite positions and escaped nodes (farther than ESCAPE_FACTOR x
    the start state's extent from their start), recorded per step without a sync, and the neighbour caps
    of its graphs (`neighbours`). `raise_if_failed(predictions)` reads them and raises RolloutError (or
    the neighbour check's ValueError) naming the first failing step, recomputing the details from that
    step's predicted positions."""

    def __init__(self, batch: TrajectoryBatch, origin: Tensor, connectivity: Connectivity, escape: bool = True):
        self.batch, self.origin, self.escape = batch, origin, escape
        self.extent = (origin.amax(0) - origin.amin(0)).norm() if len(origin) else origin.new_zeros(())
        self.diverged = DeferredCheck()
        self.neighbours = NeighbourCheck(connectivity, what="rollout")

    def observe(self, new: Tensor, previous: Tensor, t: int) -> Tensor:
        """Record step t's prediction `new` [sumN, d]; returns it with non-finite rows held at `previous`."""
        with phase("checks"):
            finite = torch.isfinite(new).all(dim=1)
            failed = ~finite.all()
            if self.escape:
                failed = failed | ((new - self.origin).norm(dim=1) > ESCAPE_FACTOR * self.extent).any()
            self.diverged.record(failed, t)
            if not reads_cost(new.device) and not bool(failed):  # the CPU: nothing to hold back
                return new
            return torch.where(finite[:, None], new, previous)

    def raise_if_failed(self, predictions: dict[int, Tensor]) -> None:
        """predictions: {t: the raw prediction of state t + 1}, holding at least the failing step's."""
        failure = self.diverged.failure()
        if failure is not None:
            self.diverged.reset()
            t = failure.step
            raise_divergence(predictions[t], self.origin, float(self.extent), self.batch, t)
        self.neighbours.raise_if_failed()


def predict_next(step_fn: StepFn, batch: TrajectoryBatch, t: int, positions: Tensor, use_points: bool | Tensor,
                 connectivity: Connectivity, with_material: bool, state: Any, neighbours=None) -> tuple[Tensor, Any]:
    """One prediction step of the engine: the graph of state t with the mesh at `positions` [sumN, d]
    (`state_graph`), the step function, and the fixed nodes set to their known positions at t + 1.
    Returns (positions at t + 1 [sumN, d], the model's new state); `rollout` and the online simulator
    (`ggns.online`) both step through it."""
    graph = state_graph(batch, t, positions, use_points, connectivity, with_material, neighbours)
    displacement, state = step_fn(graph, state)
    return torch.where(batch.fixed[:, None], batch.positions[t + 1], positions + displacement), state


def rollout(step_fn: StepFn, batch: TrajectoryBatch, schedule: Schedule, connectivity: Connectivity,
            with_material: bool = False, start_positions: Tensor | None = None, start: int = 0,
            steps: int | None = None, state: Any = None, check_every: int | None = None) -> tuple[Tensor, Any]:
    """Predict states start+1 .. start+steps from the true state at `start` (or start_positions
    [sumN, d]); prediction step t uses the point clouds of state t iff schedule.uses_points(t).
    steps defaults to T-1-start. Returns (positions [steps+1, sumN, d], final state).
    Raises RolloutError naming the step and trajectories that went non-finite, or the first node
    that escaped (farther than ESCAPE_FACTOR x the start state's extent from its start); the checks
    are read every `check_every` steps and at the end (module docstring)."""
    if getattr(step_fn, "whole_step", False):  # a `capture.StaticStep`: graph, model and checks in one step
        return step_fn.rollout(batch, schedule, start_positions, start, steps, state, check_every)
    last = batch.num_steps - 1
    steps = last - start if steps is None else steps
    if start < 0 or steps < 0 or start + steps > last:
        raise ValueError(f"rollout start={start}, steps={steps} leaves the states 0..{last}")
    pos = batch.positions[start] if start_positions is None else start_positions.to(batch.positions)
    out = [pos]
    check = DivergenceCheck(batch, pos, connectivity)
    every = check_interval(pos.device, check_every)
    with torch.no_grad():
        for i, t in enumerate(range(start, start + steps)):
            check.neighbours.step = t
            raw, state = predict_next(step_fn, batch, t, pos, schedule.uses_points(t), connectivity, with_material,
                                      state, check.neighbours)
            pos = check.observe(raw, pos, t)
            out.append(raw)
            if (i + 1) % every == 0 or i == steps - 1:
                check.raise_if_failed({s: out[s - start + 1] for s in range(start, t + 1)})
    return torch.stack(out), state


def one_step_predictions(step_fn: StepFn, batch: TrajectoryBatch, schedule: Schedule, connectivity: Connectivity,
                         with_material: bool = False) -> Tensor:
    """Teacher-forced predictions: state t+1 predicted from the *true* state t for every t, with the
    point clouds of `schedule` and any model state (an LSTM's) carried along the true trajectory.
    Returns [T, sumN, d]: index 0 is the true S_0, index t the prediction of S_t (non-finite ones raise
    RolloutError naming the first such step, read once at the end)."""
    batch.require_ground_truth("teacher-forced prediction")
    if getattr(step_fn, "whole_step", False):
        return step_fn.rollout(batch, schedule, teacher_forcing=True, check_every=batch.num_steps)[0]
    fixed = batch.fixed[:, None]
    out, state = [batch.positions[0]], None
    check = DivergenceCheck(batch, batch.positions[0], connectivity, escape=False)
    with torch.no_grad():
        for t in range(batch.num_steps - 1):
            check.neighbours.step = t
            graph = state_graph(batch, t, batch.positions[t], schedule.uses_points(t), connectivity, with_material,
                                check.neighbours)
            displacement, state = step_fn(graph, state)
            pos = torch.where(fixed, batch.positions[t + 1], batch.positions[t] + displacement)
            check.observe(pos, batch.positions[t], t)
            out.append(pos)
    check.raise_if_failed(dict(enumerate(out[1:])))
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
    if starts and getattr(step_fn, "whole_step", False) and not getattr(step_fn.model, "recurrent", True):
        # a stateless static step: the chain as one rollout, its checks read as in any rollout
        chain = list(rollout(step_fn, batch, EveryK(1), connectivity, with_material, steps=starts[-1])[0])
        for m in starts:
            blind, _ = rollout(step_fn, batch, Never(), connectivity, with_material, chain[m], m, horizon,
                               check_every=horizon)
            preds[m] = torch.cat([torch.stack(chain[:m + 1]), blind[1:]])
        return preds
    for m in range(starts[-1] + 1 if starts else 0):
        if m in starts:
            blind, _ = rollout(step_fn, batch, Never(), connectivity, with_material, chain[m], m, horizon,
                               copy.deepcopy(state), check_every=horizon)
            preds[m] = torch.cat([torch.stack(chain), blind[1:]])
        if m < starts[-1]:
            nxt, state = rollout(step_fn, batch, EveryK(1), connectivity, with_material, chain[m], m, 1, state)
            chain.append(nxt[1])
    return preds


# A node farther than this many times the start state's extent from where it started has left any
# scene (they are normalized to [-1, 1]^d): the rollout is reported as diverged rather than continued
# as garbage (checked in `rollout`, which runs long horizons; not in the one-step predictions).
ESCAPE_FACTOR = 100.0


def raise_divergence(prediction: Tensor, origin: Tensor, extent: float, batch: TrajectoryBatch, t: int) -> None:
    """Raise the RolloutError of a rollout whose prediction of state t + 1 (`prediction` [sumN, d]) is not
    finite or has a node farther than ESCAPE_FACTOR x `extent` from its start in `origin`; nothing if neither."""
    _check_finite(prediction, batch, t)
    _check_bounded(prediction, origin, extent, batch, t)


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
