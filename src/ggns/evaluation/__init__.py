"""Evaluation: rollout metrics (MSE variants, 2D and 3D mesh IoU) and point-cloud schedules.

The names below are imported on first use (PEP 562), so that importing a light submodule (`selection`)
does not import the metrics and torch_geometric with it."""
from __future__ import annotations

import importlib

_EXPORTS = {
    **dict.fromkeys(("VolumeIoU", "batch_iou", "m_plus_10_mse", "m_plus_10_pooled_mse", "m_plus_10_starts", "mesh_iou",
                     "one_step_mse", "per_step_curve", "rollout_mse", "step_mse", "tet_mesh_iou"), "metrics"),
    **dict.fromkeys(("EveryK", "FirstM", "Never", "Schedule", "parse_schedule"), "schedules"),
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
