"""The paper's evaluation of a step function on a batch of trajectories, used by `test`, the
rollout callbacks and the benchmarks alike.

`evaluate_batch` returns per-trajectory values {metric name: float64 [B]}; `MetricTable`
accumulates them over batches and reports the mean (and std over trajectories). Names:
    one_step_mse        teacher-forced next-step error (`one_step_predictions`)
    rollout_mse_<s>     full-rollout error from S_0 under point-cloud schedule s
    rollout_iou_<s>     mean IoU over the predicted states of that rollout (2D: areas, every state;
                        3D: volumes of the tetrahedral meshes, every 10th state, `rollout_volume_iou`)
    m10_mse             the m+10-step error (`metrics.m_plus_10_mse`), averaged over m (every m, or
                        every `m_plus_10_stride`-th for a cheaper estimate during training)
    m10_pooled_mse      the same rollouts scored as the authors' code did (`metrics.m_plus_10_pooled_mse`:
                        every step of each rollout pooled, point-cloud prefix included), to set beside
                        the paper's m+10 numbers
with <s> = k1, k2, k5, k10 (a point cloud every k steps), never, first<m> (`Schedule.key`).
Errors average over all mesh nodes and coordinates, as in the paper (fixed nodes are set to
their known positions and contribute zero error).
"""
from __future__ import annotations

from typing import Iterable

import torch
from torch import Tensor

from ..graphs.connectivity import Connectivity
from ..batch import TrajectoryBatch
from .metrics import (batch_iou, m_plus_10_mse, m_plus_10_pooled_mse, m_plus_10_starts, one_step_mse, rollout_mse,
                      rollout_volume_iou)
from .rollout import StepFn, m_plus_10_rollouts, one_step_predictions, rollout
from .schedules import PAPER_SCHEDULES, EveryK, Never, Schedule, effective_schedule, effective_schedules, parse_schedule

def split_trajectories(positions: Tensor, batch: TrajectoryBatch) -> list[Tensor]:
    """[T, sumN, d] -> B tensors [1, T, N_b, d] (the metrics' layout), on the CPU."""
    o = batch.node_offsets
    positions = positions.detach().cpu()
    return [positions[None, :, o[b]:o[b + 1]] for b in range(batch.num_graphs)]


def trajectory_cells(batch: TrajectoryBatch, b: int) -> Tensor:
    """Cells of trajectory b with local node indices, on the CPU."""
    c, o = batch.cell_offsets, batch.node_offsets
    return (batch.cells[c[b]:c[b + 1]] - o[b]).cpu()


def evaluate_batch(step_fn: StepFn, batch: TrajectoryBatch, connectivity: Connectivity,
                   schedules: Iterable[Schedule] = (Never(),), *, with_material: bool = False,
                   one_step_schedule: Schedule = Never(), m_plus_10: bool = True, iou: bool = True,
                   horizon: int = 10, m_plus_10_stride: int = 1) -> dict[str, Tensor]:
    """Per-trajectory metrics {name: float64 [B]} (module docstring) of `step_fn` on `batch`.
    m_plus_10 is skipped when trajectories are too short (T <= horizon) and averages over every
    `m_plus_10_stride`-th start m (1: all, the paper's metric)."""
    if m_plus_10_stride < 1:
        raise ValueError(f"m_plus_10_stride must be >= 1, got {m_plus_10_stride}")
    batch.require_ground_truth("computing metrics")
    true = split_trajectories(batch.positions, batch)
    out: dict[str, list[float]] = {}

    def add(name: str, per_traj: list[float]) -> None:
        out[name] = torch.tensor(per_traj, dtype=torch.float64)

    one_step = split_trajectories(one_step_predictions(step_fn, batch, one_step_schedule, connectivity, with_material), batch)
    add("one_step_mse", [one_step_mse(p[:, 1:], t[:, 1:])[0] for p, t in zip(one_step, true)])
    for schedule in schedules:
        key = schedule.key
        pred = split_trajectories(rollout(step_fn, batch, schedule, connectivity, with_material)[0], batch)
        add(f"rollout_mse_{key}", [rollout_mse(p, t)[0] for p, t in zip(pred, true)])
        if iou and batch.positions.shape[-1] == 2:
            add(f"rollout_iou_{key}", [batch_iou(p, t, trajectory_cells(batch, b))[0, 1:].mean().item()
                                       for b, (p, t) in enumerate(zip(pred, true))])
        elif iou:
            add(f"rollout_iou_{key}", [rollout_volume_iou(p, t, trajectory_cells(batch, b))
                                       for b, (p, t) in enumerate(zip(pred, true))])
    if m_plus_10 and batch.num_steps > horizon:
        preds = m_plus_10_rollouts(step_fn, batch, connectivity, horizon,
                                   m_plus_10_starts(batch.num_steps, horizon)[::m_plus_10_stride],
                                   with_material)
        per_m = {m: split_trajectories(p, batch) for m, p in preds.items()}
        add("m10_mse", [m_plus_10_mse({m: p[b] for m, p in per_m.items()}, t, horizon=horizon)[0]
                        for b, t in enumerate(true)])
        add("m10_pooled_mse", [m_plus_10_pooled_mse({m: p[b] for m, p in per_m.items()}, t, horizon=horizon)
                               for b, t in enumerate(true)])
    return out


@torch.no_grad()
def evaluate_model(model, batch: TrajectoryBatch, schedules=None, **kwargs) -> dict[str, Tensor]:
    """Per-trajectory paper metrics of a simulator (`GraphSimulator`) on `batch`, through its rollout step
    (`evaluate_batch`).

    Args:
        model: the simulator (its `rollout_step`, `connectivity`, `with_material`, `uses_points`).
        batch: B trajectories of T states each (`TrajectoryBatch.from_trajectories`).
        schedules: point-cloud schedules of the full rollouts (`Schedule` objects, or their text forms);
            None: the paper's (`PAPER_SCHEDULES`) as the model runs them (`effective_schedules`: "never"
            alone for a model without point clouds).
        **kwargs: `evaluate_batch`'s options (`m_plus_10`, `iou`, `m_plus_10_stride`, ...).

    Returns:
        metric name (`one_step_mse`, `rollout_mse_k1`, `rollout_iou_k1`, ..., `rollout_mse_never`,
        `m10_mse` when computed) -> a [B] tensor, one value per trajectory (MSE in squared task-space units).
    """
    schedules = (effective_schedules(PAPER_SCHEDULES, model.uses_points) if schedules is None
                 else [parse_schedule(s) for s in schedules])
    one_step = effective_schedule(EveryK(1), model.uses_points)
    with torch.no_grad():
        return evaluate_batch(model.rollout_step(), batch, model.connectivity, schedules,
                              with_material=model.with_material, one_step_schedule=one_step, **kwargs)


def m_plus_10_profile(model, batch: TrajectoryBatch, starts: list[int], horizon: int = 10) -> list[dict]:
    """Where a model's m+10 error comes from, per start m (`python -m ggns diagnose --m-plus-10-stride`):
    {"m", "m10_mse": the error at S_{m+horizon} after m point clouds and `horizon` blind steps (mean
    over trajectories, as `m10_mse`), "m10_pooled_mse": that rollout's steps 1..m+horizon pooled (as
    `m10_pooled_mse` per m), and, for a model that carries a material estimate (`material_estimate`,
    GGNSID), "material_error": the mean |estimate - Poisson's ratio| after the m point clouds}."""
    connectivity, with_material = model.connectivity, model.with_material
    preds = m_plus_10_rollouts(model.step, batch, connectivity, horizon, starts, with_material)
    true = split_trajectories(batch.positions, batch)
    rows = []
    for m, pred in sorted(preds.items()):
        per_traj = split_trajectories(pred, batch)
        rows.append({"m": m,
                     "m10_mse": sum(m_plus_10_mse({m: p}, t, horizon=horizon)[0] for p, t in zip(per_traj, true)) / len(true),
                     "m10_pooled_mse": sum(m_plus_10_pooled_mse({m: p}, t, horizon=horizon)
                                           for p, t in zip(per_traj, true)) / len(true)})
    if hasattr(model, "material_estimate"):
        position, state, estimates = batch.positions[0], None, {}
        for t in range(max(starts) + 1):
            if t in starts:
                estimates[t] = None if state is None else model.material_estimate(state)
            if t < max(starts):
                nxt, state = rollout(model.step, batch, EveryK(1), connectivity, with_material, position, t, 1, state)
                position = nxt[1]
        for row in rows:
            estimate = estimates[row["m"]]
            row["material_error"] = (float("nan") if estimate is None
                                     else (estimate - batch.material).abs().mean().item())
    return rows


def pooled_over(profile: list[dict], horizon: int = 10) -> float:
    """`m10_pooled_mse` over the rollouts of a `m_plus_10_profile`: each m's pooled value weighs by its
    m + horizon steps (the same as scoring those rollouts together)."""
    return sum(r["m10_pooled_mse"] * (r["m"] + horizon) for r in profile) / sum(r["m"] + horizon for r in profile)


def zero_motion_one_step_mse(batch: TrajectoryBatch) -> Tensor:
    """`one_step_mse` per trajectory (float64 [B]) of predicting no motion: S_t predicted as the true
    S_{t-1}, fixed nodes at their known positions (as `one_step_predictions` sets them)."""
    batch.require_ground_truth("computing metrics")
    positions = batch.positions
    pred = torch.cat([positions[:1], torch.where(batch.fixed[:, None], positions[1:], positions[:-1])])
    return torch.tensor([one_step_mse(p[:, 1:], t[:, 1:])[0]
                         for p, t in zip(split_trajectories(pred, batch), split_trajectories(positions, batch))],
                        dtype=torch.float64)


class MetricTable:
    """Per-trajectory metric values accumulated over batches."""

    def __init__(self):
        self.values: dict[str, list[Tensor]] = {}

    def add(self, metrics: dict[str, Tensor]) -> None:
        for name, per_traj in metrics.items():
            self.values.setdefault(name, []).append(per_traj.detach().cpu().to(torch.float64))

    def summary(self) -> dict[str, dict[str, float]]:
        """{name: {"mean", "std" (over trajectories, population), "count"}}."""
        out = {}
        for name, parts in self.values.items():
            v = torch.cat(parts)
            out[name] = {"mean": v.mean().item(), "std": v.std(unbiased=False).item(), "count": len(v)}
        return out

    def means(self) -> dict[str, float]:
        return {name: s["mean"] for name, s in self.summary().items()}


