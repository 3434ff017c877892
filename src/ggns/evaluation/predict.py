"""Rollouts of whole trajectories for a predictions file (`python -m ggns rollout`, notebooks): the
check that a model fits the data (`check_model_fits`) and the batched rollouts of a list of
trajectories through the model's rollout step and the one engine (`evaluation.rollout`, `rollout_trajectories`).

A model's task is read from its connectivity preset's name (`plate_full_graph` -> plate,
`tissue_mgn` -> tissue), which every config of conf/plate and conf/tissue follows.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ..batch import TrajectoryBatch
from ..scenes import SCENES
from ..trajectory import Trajectory
from .evaluate import split_trajectories
from .rollout import rollout
from .schedules import Schedule, effective_schedule


def model_scene(model) -> str | None:
    """The scene a simulator was trained for: its checkpoint's training-data scene (`scene`, written with every
    checkpoint of a fit), else the scene its connectivity preset is named after (a checkpoint written before the
    scene was, or a model built from a preset's name); None if neither tells."""
    scene = getattr(model, "scene", None)
    if scene is None:
        connectivity = model.hparams.get("connectivity", "")
        scene = Path(connectivity).stem.split("_")[0] if isinstance(connectivity, str) else None
    return scene if scene in SCENES else None


def check_model_fits(model, dim: int, scene: str | None = None, task: str | None = None) -> None:
    """ValueError when `model` cannot roll out data of dimension `dim` (and of `scene`): a model of
    another dimension, or one trained for another task (`task`, e.g. from a pretrained registry, else
    `model_scene`). The task is compared only when both it and `scene` name a scene of ggns.scenes (a
    split written from your own arrays may name its scene anything)."""
    model_dim = int(model.hparams.get("dim", dim))
    name = type(model).__name__
    if model_dim != dim:
        raise ValueError(f"the {name} model is {model_dim}D, the data are {dim}D: use a checkpoint trained on "
                         f"{dim}D data")
    task = task or model_scene(model)
    if scene in SCENES and task in SCENES and scene != task:
        raise ValueError(f"the {name} model was trained for the {task} task, the data are of the {scene} scene: "
                         f"use a checkpoint of the {scene} task")


def rollout_trajectories(model, trajectories: Sequence[Trajectory], schedule: Schedule | str,
                         batch_size: int = 8) -> list[np.ndarray]:
    """Each trajectory's rollout from its initial state under the model's effective schedule (never
    for a model without point clouds), [T, N, d] float32 on the CPU, in order; consecutive
    trajectories with equal T are rolled out `batch_size` at a time on the model's device."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if not trajectories:
        return []
    dims = {t.dim for t in trajectories}
    if len(dims) > 1:
        raise ValueError(f"the trajectories mix dimensions {sorted(dims)}")
    check_model_fits(model, dims.pop())
    plan = effective_schedule(schedule, model.uses_points)
    out: list[np.ndarray] = []
    start = 0
    while start < len(trajectories):
        stop = start + 1
        while (stop < len(trajectories) and stop - start < batch_size
               and trajectories[stop].num_steps == trajectories[start].num_steps):
            stop += 1
        batch = TrajectoryBatch.from_trajectories(list(trajectories[start:stop]), device=model.device)
        with torch.no_grad():
            positions = rollout(model.rollout_step(), batch, plan, model.connectivity, model.with_material)[0]
        out += [x[0].numpy() for x in split_trajectories(positions, batch)]
        start = stop
    return out
