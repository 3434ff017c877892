"""Evaluation: rollout metrics (MSE variants, 2D mesh IoU) and point-cloud schedules."""
from .metrics import (
    batch_iou,
    m_plus_10_mse,
    m_plus_10_starts,
    mesh_iou,
    one_step_mse,
    per_step_curve,
    rollout_mse,
    step_mse,
)
from .schedules import EveryK, FirstM, Never, Schedule, parse_schedule

__all__ = [
    "EveryK",
    "FirstM",
    "Never",
    "Schedule",
    "batch_iou",
    "m_plus_10_mse",
    "m_plus_10_starts",
    "mesh_iou",
    "one_step_mse",
    "parse_schedule",
    "per_step_curve",
    "rollout_mse",
    "step_mse",
]
