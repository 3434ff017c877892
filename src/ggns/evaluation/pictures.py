"""Rollout pictures: the ground truth of one trajectory against the rollouts of one or more learned
simulators under a point-cloud schedule (each model under its effective schedule), with the point
clouds overlaid at the steps that use them. Used by the `RolloutPictures` callback (TensorBoard),
the demo's report and `python -m ggns export` (the same rollouts as ParaView files)."""
from __future__ import annotations

from collections.abc import Mapping

from matplotlib.figure import Figure

from ..batch import TrajectoryBatch
from ..viz import rollout_figure
from .schedules import Schedule, effective_schedule


def rollout_series(batch: TrajectoryBatch, models: Mapping[str, object], schedule: Schedule) -> tuple[dict, list]:
    """Each model's rollout of the single trajectory in `batch` under its effective schedule
    ({"<name> (<effective schedule>)": [T, N, d] on the CPU}) and the point clouds shown with them
    (T entries, None where `schedule` gives none or no model uses points)."""
    if batch.num_graphs != 1:
        raise ValueError(f"rollout_series takes one trajectory, the batch holds {batch.num_graphs}")
    preds = {}
    for name, model in models.items():
        effective = effective_schedule(schedule, model.uses_points)
        preds[f"{name} ({effective})"] = model.rollout(batch.to(model.device), effective).cpu()
    steps = batch.num_steps
    shown = any(model.uses_points for model in models.values())
    points = [batch.points[t].cpu() if shown and t < steps - 1 and schedule.uses_points(t) else None
              for t in range(steps)]
    return preds, points


def rollout_picture(batch: TrajectoryBatch, collider_faces, models: Mapping[str, object], schedule: Schedule,
                    num_frames: int = 4, title: str | None = None) -> Figure:
    """A figure (`viz.rollout_figure`, 2D or 3D) of the single trajectory in `batch` (ground truth)
    against each model's rollout (row label: `<name> (<effective schedule>)`); point clouds drawn
    at the steps where `schedule` gives one, when any model uses them."""
    preds, points = rollout_series(batch, models, schedule)
    return rollout_figure(batch.cells.cpu(), batch.positions.cpu(), preds, points=points,
                          collider=None if batch.collider is None else batch.collider.cpu(),
                          collider_faces=collider_faces, num_frames=num_frames, title=title)
