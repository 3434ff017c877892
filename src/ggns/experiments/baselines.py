"""The paper's two point-cloud baselines of a sweep, scored on its test trajectories and stored
beside its runs in the runs' own metric format ({metric: {"mean", "std", "count"}} over test
trajectories), so `summarize` tabulates them with the learned models.

    generated_mesh_iou_<s>   mean IoU (steps 1..T-1, as `rollout_iou_<s>`) of a rollout under
                             schedule s that starts from a mesh GENERATED from the first point
                             cloud instead of the true initial mesh ("initial mesh generation",
                             `ggns.baselines.initial_mesh`); one file per finished run,
                             <run test dir>/generated_mesh_metrics.json
    alpha_shapes             a row of its own: every step's point cloud meshed by Alpha Shapes
                             (`ggns.baselines.alpha_shapes`), reported as generated_mesh_iou_k1
                             (a cloud every step, no initial mesh) and as rollout_iou_k1;
                             <output>/alpha_shapes/test_metrics.json
    static                   a reference row, not a paper baseline: the mesh held at its initial
                             state S_0 for the whole trajectory, scored as rollout_mse_never and
                             rollout_iou_never; it shows how much motion a model has to predict
                             (a learned simulator above it has learned nothing useful);
                             <output>/static/test_metrics.json

Configured by the sweep file's optional `baselines` section (2D datasets only):

    baselines:
      dataset: plate_small      # data preset whose test split is scored
      data_dir: null            # overrides the preset's directory
      max_trajectories: 9       # the first n test trajectories, as the runs' test (null: all)
      alpha_shapes: true
      static: true
      initial_mesh: [ggns, mgn] # sweep models rolled out from the generated mesh, each under its
                                # own evaluation schedules (the model's `eval_schedules`), each
                                # schedule with the checkpoint its family was tested with

Existing result files are kept (an interrupted sweep resumes); delete them to recompute.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ..evaluation.evaluate import MetricTable

ALPHA_SHAPES = "alpha_shapes"
STATIC = "static"
ROWS = (ALPHA_SHAPES, STATIC)  # baseline rows of their own, <output>/<row>/test_metrics.json
GENERATED_MESH_FILE = "generated_mesh_metrics.json"


def _summary(values: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    """{name: per-trajectory values} -> the runs' format, {name: {"mean", "std", "count"}}."""
    table = MetricTable()
    table.add({name: torch.tensor(xs, dtype=torch.float64) for name, xs in values.items()})
    return table.summary()


def write_json(path: Path, data: dict) -> None:
    """Write via a temporary file and rename, so an interrupted write leaves no partial result."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    tmp.replace(path)


def alpha_shapes_metrics(trajectories) -> dict[str, dict[str, float]]:
    """Alpha Shapes on every step's point cloud of each trajectory, scored like a rollout
    (mean IoU over steps 1..T-1 per trajectory)."""
    from ..baselines.alpha_shapes import trajectory_alpha_iou

    per_traj = [float(trajectory_alpha_iou(traj)[1:].mean()) for traj in trajectories]
    return _summary({"generated_mesh_iou_k1": per_traj, "rollout_iou_k1": per_traj})


def static_metrics(trajectories) -> dict[str, dict[str, float]]:
    """The mesh held at S_0 for every step, scored like a rollout without point clouds, and the
    one-step MSE of predicting no motion (S_t predicted as the true S_{t-1}): the reference that
    a model's one-step MSE is compared with (`one_step_mse` of this row)."""
    from ..evaluation.evaluate import zero_motion_one_step_mse
    from ..evaluation.metrics import batch_iou, rollout_mse
    from ..graphs.state import TrajectoryBatch

    mse, iou, one_step = [], [], []
    for traj in trajectories:
        true = torch.as_tensor(np.asarray(traj.positions, dtype=np.float64))[None]  # [1, T, N, d]
        held = true[:, :1].expand_as(true)
        mse.append(rollout_mse(held, true)[0])
        if traj.dim == 2:
            iou.append(batch_iou(held, true, traj.cells)[0, 1:].mean().item())
        one_step.append(zero_motion_one_step_mse(TrajectoryBatch.from_trajectories([traj], dtype=torch.float64))[0])
    return _summary({"rollout_mse_never": mse, "one_step_mse": [float(v) for v in one_step],
                     **({"rollout_iou_never": iou} if iou else {})})


def generated_mesh_metrics(model, trajectories, schedules=None) -> dict[str, dict[str, float]]:
    """IoU of `model`'s rollouts from meshes generated from each trajectory's first point cloud,
    under each schedule (default: the model's `eval_schedules`), batched over trajectories."""
    from ..baselines.initial_mesh import generated_trajectory, initial_mesh_rollout_ious
    from ..evaluation.evaluate import schedule_key
    from ..evaluation.schedules import parse_schedule

    generated = [generated_trajectory(traj) for traj in trajectories]
    values: dict[str, list[float]] = {}
    for text in (model.hparams.eval_schedules if schedules is None else schedules):
        schedule = parse_schedule(text) if isinstance(text, str) else text
        ious = initial_mesh_rollout_ious(model, trajectories, schedule, generated)
        values[f"generated_mesh_iou_{schedule_key(schedule)}"] = [float(iou[1:].mean()) for iou in ious]
    return _summary(values)


def _test_trajectories(spec: dict):
    from ..data.module import SimulationDataModule

    module = SimulationDataModule(spec.get("dataset", "plate_small"), data_dir=spec.get("data_dir"),
                                  max_eval_trajectories=spec.get("max_trajectories"), generate_missing=False)
    return module.trajectories("test")


def baseline_spec(sweep: dict) -> dict:
    """The sweep's `baselines` section, checked ({} when absent)."""
    spec = sweep.get("baselines") or {}
    unknown = set(spec) - {"dataset", "data_dir", "max_trajectories", "alpha_shapes", "static", "initial_mesh"}
    if unknown:
        raise ValueError(f"sweep baselines: unknown keys {sorted(unknown)}")
    models = spec.get("initial_mesh") or []
    if isinstance(models, str):
        models = [models]
    missing = [m for m in models if m not in sweep["models"]]
    if missing:
        raise ValueError(f"sweep baselines: initial_mesh names models {missing} that the sweep does not have "
                         f"({sorted(sweep['models'])})")
    return {**spec, "initial_mesh": list(models)}


def run_baselines(sweep: dict, log=print) -> list[Path]:
    """Compute the missing baseline results of the sweep (see the module docstring): Alpha Shapes
    and the static reference once, and the generated-mesh rollouts for every finished run of the `initial_mesh` models.
    Returns the files written."""
    from ..models.simulators import load_simulator
    from .sweep import runs_of

    spec = baseline_spec(sweep)
    written: list[Path] = []
    trajectories = None
    for row, compute in ((ALPHA_SHAPES, alpha_shapes_metrics), (STATIC, static_metrics)):
        path = Path(sweep["output"]) / row / "test_metrics.json"
        if spec.get(row) and not path.is_file():
            trajectories = trajectories if trajectories is not None else _test_trajectories(spec)
            log(f"baseline {row} on {len(trajectories)} test trajectories")
            write_json(path, compute(trajectories))
            written.append(path)
    for run in runs_of(sweep):
        path = run.test_dir / GENERATED_MESH_FILE
        if run.model not in spec["initial_mesh"] or not run.finished or path.is_file():
            continue
        trajectories = trajectories if trajectories is not None else _test_trajectories(spec)
        log(f"baseline initial mesh generation: {run.model} seed {run.seed}")
        metrics = {}
        for part in run.test_parts():  # each schedule with the checkpoint selected on its family
            if part.schedules:
                model = load_simulator(part.checkpoint, map_location="cpu")
                metrics.update(generated_mesh_metrics(model, trajectories, part.schedules))
        write_json(path, metrics)
        written.append(path)
    return written
