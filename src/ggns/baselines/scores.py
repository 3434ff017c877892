"""The baselines scored like the learned models' test runs, in the runs' own metric format
({metric: {"mean", "std", "count"}} over test trajectories), so a sweep's summary tabulates them
with the learned models (`ggns.sweeps.summary.run_baselines` computes them on a sweep's test
trajectories and stores them beside its runs):

    generated_mesh_iou_<s>   mean IoU (steps 1..T-1, as `rollout_iou_<s>`) of a rollout under
                             schedule s that starts from a mesh GENERATED from the first point
                             cloud instead of the true initial mesh ("initial mesh generation",
                             `initial_mesh`); one file per finished run,
                             <run test dir>/generated_mesh_metrics.json
    alpha_shapes             a row of its own: every step's point cloud meshed by Alpha Shapes
                             (`alpha_shapes`), reported as generated_mesh_iou_k1
                             (a cloud every step, no initial mesh) and as rollout_iou_k1;
                             <output>/alpha_shapes/test_metrics.json
    static                   a reference row, not a paper baseline: the mesh held at its initial
                             state S_0 for the whole trajectory, scored as rollout_mse_never and
                             rollout_iou_never (3D: volumes, every 10th state); it shows how much motion a model has to predict
                             (a learned simulator above it has learned nothing useful);
                             <output>/static/test_metrics.json
"""
from __future__ import annotations

import numpy as np
import torch

from ..batch import TrajectoryBatch
from ..evaluation.evaluate import MetricTable, zero_motion_one_step_mse
from ..evaluation.metrics import batch_iou, rollout_mse, rollout_volume_iou
from ..evaluation.schedules import PAPER_SCHEDULES, effective_schedules, parse_schedule
from . import ALPHA_SHAPES, GENERATED_MESH_FILE, ROWS, STATIC  # noqa: F401 (importable from here as before)
from .alpha_shapes import trajectory_alpha_iou
from .initial_mesh import generated_trajectory, initial_mesh_rollout_ious



def summarize_values(values: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    """{name: per-trajectory values} -> the runs' format, {name: {"mean", "std", "count"}}."""
    table = MetricTable()
    table.add({name: torch.tensor(xs, dtype=torch.float64) for name, xs in values.items()})
    return table.summary()


def alpha_shapes_metrics(trajectories) -> dict[str, dict[str, float]]:
    """Alpha Shapes on every step's point cloud of each trajectory, scored like a rollout
    (mean IoU over steps 1..T-1 per trajectory)."""
    per_traj = [float(trajectory_alpha_iou(traj)[1:].mean()) for traj in trajectories]
    return summarize_values({"generated_mesh_iou_k1": per_traj, "rollout_iou_k1": per_traj})


def static_metrics(trajectories) -> dict[str, dict[str, float]]:
    """The mesh held at S_0 for every step, scored like a rollout without point clouds, and the
    one-step MSE of predicting no motion (S_t predicted as the true S_{t-1}): the reference that
    a model's one-step MSE is compared with (`one_step_mse` of this row)."""
    mse, iou, one_step = [], [], []
    for traj in trajectories:
        true = torch.as_tensor(np.asarray(traj.positions, dtype=np.float64))[None]  # [1, T, N, d]
        held = true[:, :1].expand_as(true)
        mse.append(rollout_mse(held, true)[0])
        if traj.dim == 2:
            iou.append(batch_iou(held, true, traj.cells)[0, 1:].mean().item())
        else:  # tetrahedra: volume IoU of every 10th state, as the models' rollout_iou_<s>
            iou.append(rollout_volume_iou(held, true, traj.cells))
        one_step.append(zero_motion_one_step_mse(TrajectoryBatch.from_trajectories([traj], dtype=torch.float64))[0])
    return summarize_values({"rollout_mse_never": mse, "one_step_mse": [float(v) for v in one_step],
                             "rollout_iou_never": iou})


def generated_mesh_metrics(model, trajectories, schedules=None) -> dict[str, dict[str, float]]:
    """IoU of `model`'s rollouts from meshes generated from each trajectory's first point cloud,
    under each schedule (default: the paper's, `PAPER_SCHEDULES`, as the model runs them), batched over
    trajectories."""
    generated = [generated_trajectory(traj) for traj in trajectories]
    values: dict[str, list[float]] = {}
    for text in (effective_schedules(PAPER_SCHEDULES, model.uses_points) if schedules is None else schedules):
        schedule = parse_schedule(text)
        ious = initial_mesh_rollout_ious(model, trajectories, schedule, generated)
        values[f"generated_mesh_iou_{schedule.key}"] = [float(iou[1:].mean()) for iou in ious]
    return summarize_values(values)
