"""Rollout pictures: the ground truth of one trajectory against the rollouts of one or more learned
simulators under a point-cloud schedule (each model under its effective schedule, labelled
"<name> (<effective schedule>)"), with the point clouds overlaid on the panels of the models that use
them at the steps that give them; and the error over time of every model and schedule. Used by the
`RolloutPictures` callback (TensorBoard), the demo's report and `python -m ggns export` (the same
rollouts as ParaView files).

`rollout_series` rolls out once; `rollout_picture` (a figure), `rollout_animation` (a GIF) and
`series_errors` (per-step error curves) accept its result, so one rollout feeds every picture.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from ..batch import TrajectoryBatch
from ..viz import rollout_animation as animate_rollout
from ..viz import rollout_figure
from .evaluate import split_trajectories
from .metrics import per_step_curve
from .schedules import Schedule, effective_schedule, effective_schedules, parse_schedule


def series_label(name: str, model, schedule: Schedule | str) -> str:
    """The label of `model`'s rollout under `schedule`: "<name> (<effective schedule>)"."""
    return f"{name} ({effective_schedule(schedule, model.uses_points)})"


def point_labels(models: Mapping[str, object], schedule: Schedule | str) -> set[str]:
    """The labels of the models that use point clouds: the panels that show them."""
    return {series_label(name, model, schedule) for name, model in models.items() if model.uses_points}


def _rollout(model, batch: TrajectoryBatch, schedule: Schedule) -> torch.Tensor:
    """`model`'s rollout [T, sumN, d] of `batch` under its effective `schedule`, on the CPU."""
    return model.rollout(batch.to(model.device), effective_schedule(schedule, model.uses_points)).cpu()


def rollout_series(batch: TrajectoryBatch, models: Mapping[str, object], schedule: Schedule) -> tuple[dict, list]:
    """Each model's rollout of the single trajectory in `batch` under its effective schedule
    ({"<name> (<effective schedule>)": [T, N, d] on the CPU}) and the point clouds shown with them
    (T entries, None where `schedule` gives none or no model uses points)."""
    if batch.num_graphs != 1:
        raise ValueError(f"rollout_series takes one trajectory, the batch holds {batch.num_graphs}")
    schedule = parse_schedule(schedule)
    preds = {series_label(name, model, schedule): _rollout(model, batch, schedule) for name, model in models.items()}
    steps = batch.num_steps
    shown = any(model.uses_points for model in models.values())
    points = [batch.points[t].cpu() if shown and t < steps - 1 and schedule.uses_points(t) else None
              for t in range(steps)]
    return preds, points


def rollout_picture(batch: TrajectoryBatch, collider_faces, models: Mapping[str, object], schedule: Schedule,
                    num_frames: int = 4, title: str | None = None, series: tuple[dict, list] | None = None) -> Figure:
    """A figure (`viz.rollout_figure`, 2D or 3D) of the single trajectory in `batch` (ground truth)
    against each model's rollout (row label: `<name> (<effective schedule>)`); point clouds drawn
    on the rows of the models that use them, at the steps where `schedule` gives one. `series`:
    the result of `rollout_series(batch, models, schedule)` when the caller has it (no second
    rollout)."""
    preds, points = rollout_series(batch, models, schedule) if series is None else series
    return rollout_figure(batch.cells.cpu(), batch.positions.cpu(), preds, points=points,
                          collider=None if batch.collider is None else batch.collider.cpu(),
                          collider_faces=collider_faces, num_frames=num_frames, title=title,
                          points_on=point_labels(models, schedule))


def rollout_animation(batch: TrajectoryBatch, collider_faces, models: Mapping[str, object], schedule: Schedule,
                      path: str | Path, fps: int = 10, title: str | None = None,
                      view: tuple[float, float] = (30.0, -60.0), series: tuple[dict, list] | None = None) -> Path:
    """`rollout_picture` as an animation (`viz.rollout_animation`): every step of the single
    trajectory in `batch` one frame, panels truth then each model; writes `path` (.gif) and returns
    it. `series`: the result of `rollout_series(batch, models, schedule)` when the caller has it."""
    preds, points = rollout_series(batch, models, schedule) if series is None else series
    return animate_rollout(batch.cells.cpu(), batch.positions.cpu(), preds, path, points=points,
                           collider=None if batch.collider is None else batch.collider.cpu(),
                           collider_faces=collider_faces, fps=fps, view=view, title=title,
                           points_on=point_labels(models, schedule))


def series_errors(batch: TrajectoryBatch, preds: Mapping[str, object]) -> dict[str, np.ndarray]:
    """Per-step error curve of each rollout {label: [T, sumN, d]} of `batch` against its ground truth:
    `metrics.per_step_curve` of each trajectory (all nodes, as the paper's metrics), averaged over
    the trajectories; {label: float64 [T]}, 0 at t = 0 (S_0 is given)."""
    true = split_trajectories(batch.positions, batch)
    return {label: torch.stack([per_step_curve(p, t) for p, t in zip(split_trajectories(torch.as_tensor(pred), batch),
                                                                    true)]).mean(dim=0).numpy()
            for label, pred in preds.items()}


def error_curves(batch: TrajectoryBatch, models: Mapping[str, object],
                 schedules: Iterable[Schedule | str]) -> dict[str, np.ndarray]:
    """The per-step error curve (`series_errors`) of every model under every schedule, each model
    rolled out once per effective schedule (MGN: `never` once, whatever the schedules):
    {"<name> (<effective schedule>)": float64 [T]}, for `viz.plot_error_over_time`."""
    schedules = [parse_schedule(s) for s in schedules]
    preds = {series_label(name, model, s): _rollout(model, batch, s)
             for name, model in models.items() for s in effective_schedules(schedules, model.uses_points)}
    return series_errors(batch, preds)
