"""Evaluation: rollout metrics (MSE variants, 2D and 3D mesh IoU) and point-cloud schedules."""
from .metrics import (
    VolumeIoU,
    batch_iou,
    m_plus_10_mse,
    m_plus_10_pooled_mse,
    m_plus_10_starts,
    mesh_iou,
    one_step_mse,
    per_step_curve,
    rollout_mse,
    step_mse,
    tet_mesh_iou,
)
from .schedules import EveryK, FirstM, Never, Schedule, parse_schedule

__all__ = [
    "EveryK",
    "FirstM",
    "Never",
    "Schedule",
    "VolumeIoU",
    "batch_iou",
    "m_plus_10_mse",
    "m_plus_10_pooled_mse",
    "m_plus_10_starts",
    "mesh_iou",
    "one_step_mse",
    "parse_schedule",
    "per_step_curve",
    "rollout_mse",
    "step_mse",
    "tet_mesh_iou",
]
