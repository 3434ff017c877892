"""Checkpoint selection per metric family, in one place: the validation scalar a best checkpoint
is selected on, its file name, the family each test metric belongs to, and what a tested
checkpoint was (step, epoch, the scalar it was selected on).

A family is one kind of evaluation that gets its own best checkpoint (`RolloutEvaluation` logs
the scalars; the configs' ModelCheckpoints keep `best-<family>-step=<N>.ckpt`):

    k<K>, first<M>, never   full-rollout MSE under that schedule (`Schedule.key`): val/rollout_mse_<family>
    m10                     the m+10-step MSE: val/m10_mse

Test metric -> family (`metric_family`): rollout_mse_<s>, rollout_iou_<s> and generated_mesh_iou_<s>
-> s; m10_mse and m10_pooled_mse -> m10; one_step_mse -> "one_step", which is tested with the k1 checkpoint where
there is one (its predictions see a point cloud every step) and the never checkpoint otherwise.
A family without a best checkpoint of its own falls back along `candidates`.
"""
from __future__ import annotations

import re
from pathlib import Path

M10 = "m10"
ONE_STEP = "one_step"
CHECKPOINT_KEY = "checkpoint"  # test_metrics.json: `checkpoint_info` of the tested checkpoint
CHECKPOINTS_KEY = "checkpoints"  # a sweep run's merged test_metrics.json: {family: checkpoint_info + note, metrics}
FAMILY_CHECKPOINT = re.compile(r"^best-(k\d+|first\d+|never|m10)-.*\.ckpt$")
_PREFIXES = ("rollout_mse_", "rollout_iou_", "generated_mesh_iou_")


def val_metric(family: str) -> str:
    """The validation scalar a family's best checkpoint is selected on: "k1" -> "val/rollout_mse_k1"."""
    return "val/m10_mse" if family == M10 else f"val/rollout_mse_{family}"


def checkpoint_glob(family: str) -> str:
    """File pattern of a family's best checkpoints ("best-k1-*.ckpt"; never matches best-k10-...)."""
    return f"best-{family}-*.ckpt"


def metric_family(metric: str) -> str:
    """The family a test metric is tested with (module docstring)."""
    if metric in ("m10_mse", "m10_pooled_mse"):
        return M10
    if metric == "one_step_mse":
        return ONE_STEP
    for prefix in _PREFIXES:
        if metric.startswith(prefix):
            return metric[len(prefix):]
    raise ValueError(f"test metric {metric!r} belongs to no checkpoint family (expected one_step_mse, m10_mse or "
                     f"{', '.join(p + '<schedule>' for p in _PREFIXES)})")


def candidates(family: str) -> list[str]:
    """The families whose best checkpoint `family` is tested with, in order of preference: its own,
    then k1 (point clouds every step), then never."""
    own = [] if family == ONE_STEP else [family]
    return own + [f for f in ("k1", "never") if f not in own]


def checkpoint_info(path: str | Path) -> dict:
    """What a checkpoint is: {"path", "name", "global_step", "epoch", "selected_on", "score"}, where
    selected_on / score are the monitored scalar and value of the ModelCheckpoint that wrote it as
    its best (matched by file name), or None (last.ckpt, a copied or renamed file)."""
    from ..checkpoints import read_checkpoint

    path = Path(path)
    checkpoint = read_checkpoint(path)
    selected_on, score = None, None
    for key, state in checkpoint.get("callbacks", {}).items():
        best = state.get("best_model_path") if isinstance(state, dict) else None
        if key.startswith("ModelCheckpoint") and state.get("monitor") and best and Path(best).name == path.name:
            selected_on, score = state["monitor"], state.get("best_model_score")
            score = None if score is None else float(score)
    return {"path": str(path), "name": path.name, "global_step": checkpoint.get("global_step"),
            "epoch": checkpoint.get("epoch"), "selected_on": selected_on, "score": score}


def describe(info: dict | None) -> str:
    """One line naming a tested checkpoint (`checkpoint_info`, or None: the module's own weights)."""
    if info is None:
        return "tested the module's current weights (no checkpoint)"
    text = f"{info['name']} (global step {info['global_step']}, epoch {info['epoch']}"
    if info.get("selected_on"):
        text += f"; best {info['selected_on']}"
        if info.get("score") is not None:
            text += f" = {info['score']:.4e}"
    return text + ")"
