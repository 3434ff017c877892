"""The rollout callbacks shared by all simulators: rollout metrics on the validation split (for
checkpoint selection per metric family, `evaluation.selection`) and rollout pictures in
TensorBoard. Both run at the end of every validation epoch (set how often with the Trainer's
`check_val_every_n_epoch`), never during the sanity check, and roll out through the module's
`evaluate_model` / `rollout`, i.e. the one engine. `TestEvaluation` makes a `test`'s metrics and writes
them naming the checkpoint it evaluated; `RolloutWriter` writes the rollouts of `predict` as a predictions
file. The model knows none of them: it exposes its step and its rollout.
"""
from __future__ import annotations

import math
import time
import warnings
from pathlib import Path
from typing import Sequence

import pytorch_lightning as pl
import torch
from pytorch_lightning.loggers import TensorBoardLogger
from torch import Tensor

from ..batch import TrajectoryBatch
from ..checkpoints import sha256
from ..data.predictions import Predictions, write_predictions
from ..data.schema import SplitReader
from ..reports import metrics_markdown, write_json, write_text
from ..viz import figure_to_image
from ..evaluation.evaluate import MetricTable, evaluate_model, zero_motion_one_step_mse
from ..evaluation.pictures import rollout_picture
from ..evaluation.schedules import PAPER_SCHEDULES, EveryK, Never, Schedule, effective_schedule, effective_schedules, parse_schedule
from ..evaluation.selection import CHECKPOINT_KEY, M10, checkpoint_info, describe, val_metric


def _eval_batch(trainer: pl.Trainer, split: str, count: int | None, cache: dict) -> TrajectoryBatch:
    """The first `count` trajectories of `split`, this process's share of them under DDP (every
    world-size-th, from the rank)."""
    if "batch" not in cache:
        datamodule = trainer.datamodule
        if datamodule is None or not hasattr(datamodule, "eval_batch"):
            raise RuntimeError("rollout callbacks need a SimulationDataModule (trainer.datamodule.eval_batch)")
        available = len(datamodule.trajectories(split))
        if min(count or available, available) < trainer.world_size:
            raise ValueError(f"rollout validation shares the {split} trajectories among the {trainer.world_size} "
                             f"processes, but has {min(count or available, available)}: use at least one per process")
        cache["batch"] = datamodule.eval_batch(split, count, rank=trainer.global_rank, world=trainer.world_size)
    return cache["batch"].to(trainer.lightning_module.device)


def _mean_over_processes(trainer: pl.Trainer, values: dict[str, Tensor]) -> dict[str, float]:
    """{name: mean of every element of values[name] over all processes} (one process: the plain mean).
    Sums and counts in float64, summed across processes, then divided: each trajectory counts once."""
    names = sorted(values)
    totals = torch.stack([torch.stack([values[n].double().sum(), torch.tensor(values[n].numel(), dtype=torch.float64,
                                                                              device=values[n].device)])
                          for n in names])
    if trainer.world_size > 1:
        totals = trainer.strategy.reduce(totals, reduce_op="sum")
    return {n: (t[0] / t[1]).item() for n, t in zip(names, totals)}


class RolloutEvaluation(pl.Callback):
    """Validation scalars for checkpoint selection, one per metric family (`evaluation.selection`),
    from the first `num_trajectories` trajectories of `split` rolled out as one batch through the
    engine (`evaluate_model`):

        val/one_step_mse              teacher-forced next-step MSE
        val/one_step_mse_zero_motion  the same for predicting no motion (x_{t+1} = x_t); computed once
        val/one_step_ratio            one_step_mse / one_step_mse_zero_motion (below 1: better than no motion)
        val/rollout_mse_k1            full rollout, a point cloud every step (models with point clouds only)
        val/rollout_mse_never         full rollout without point clouds
        val/rollout_mse_<s>           each extra schedule in `schedules` (`Schedule.key`)
        val/m10_mse                   the m+10 MSE over every `m_plus_10_stride`-th start m (if m_plus_10)
        val/rollout_mse               alias of `primary` (a family above; default k1, or never without
                                      point clouds), kept for older configs
        val/evaluation_seconds        wall-clock time of this evaluation (of this process, under DDP)

    m+10 needs trajectories of more than 10 states; shorter ones raise at the start of `fit`. Under DDP
    each process rolls out every world-size-th of the trajectories and the sums and counts of the
    per-trajectory metrics are added across processes: the same means as one process, in a
    world-size-th of the time, and every process logs (and selects checkpoints on) the same values."""

    def __init__(self, num_trajectories: int | None = 27, schedules: Sequence[str] = (), m_plus_10: bool = True,
                 m_plus_10_stride: int = 10, primary: str | None = None, split: str = "val"):
        if m_plus_10_stride < 1:
            raise ValueError(f"m_plus_10_stride must be >= 1, got {m_plus_10_stride}")
        self.extra = [parse_schedule(s) for s in schedules]
        self.num_trajectories, self.split, self.primary = num_trajectories, split, primary
        self.m_plus_10, self.m_plus_10_stride = m_plus_10, m_plus_10_stride
        self._cache: dict = {}

    def schedules(self, pl_module) -> list[Schedule]:
        """The rollouts of a model: k1 (with point clouds), never, then the extra schedules, once each."""
        return effective_schedules([EveryK(1), Never(), *self.extra], pl_module.uses_points)

    def primary_family(self, pl_module) -> str:
        """The family `val/rollout_mse` aliases; ValueError when the model does not evaluate it."""
        primary = self.primary or ("k1" if pl_module.uses_points else "never")
        families = [s.key for s in self.schedules(pl_module)] + ([M10] if self.m_plus_10 else [])
        if primary not in families:
            raise ValueError(f"RolloutEvaluation: primary {primary!r} is not evaluated for {type(pl_module).__name__}; "
                             f"choose one of {families}")
        return primary

    def setup(self, trainer: pl.Trainer, pl_module, stage: str) -> None:
        if stage != "fit":
            return
        self.primary_family(pl_module)
        steps = _eval_batch(trainer, self.split, self.num_trajectories, self._cache).num_steps
        if self.m_plus_10 and steps <= 10:
            raise ValueError(f"RolloutEvaluation: val/m10_mse needs {self.split} trajectories of more than 10 states, "
                             f"these have {steps}; set m_plus_10: false (and drop the ModelCheckpoint monitoring "
                             f"val/m10_mse) for such data")

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module) -> None:
        if trainer.sanity_checking:
            return
        start = time.perf_counter()
        batch = _eval_batch(trainer, self.split, self.num_trajectories, self._cache)
        metrics = evaluate_model(pl_module, batch, self.schedules(pl_module), m_plus_10=self.m_plus_10, iou=False,
                                     m_plus_10_stride=self.m_plus_10_stride)
        metrics = {f"val/{name}": v for name, v in metrics.items()}
        if "zero_motion" not in self._cache:
            metrics["val/one_step_mse_zero_motion"] = zero_motion_one_step_mse(batch)
        values = _mean_over_processes(trainer, metrics)  # under DDP each process rolled out its share
        self._cache.setdefault("zero_motion", values.get("val/one_step_mse_zero_motion"))
        values["val/one_step_mse_zero_motion"] = self._cache["zero_motion"]
        zero = values["val/one_step_mse_zero_motion"]
        # nothing moves in these trajectories (e.g. a gripper that has not reached the body yet): no ratio
        values["val/one_step_ratio"] = values["val/one_step_mse"] / zero if zero > 0 else math.nan
        values["val/rollout_mse"] = values[val_metric(self.primary_family(pl_module))]
        values["val/evaluation_seconds"] = time.perf_counter() - start
        for name, value in values.items():  # the same value in every process
            pl_module.log(name, value, batch_size=batch.num_graphs)


class TestEvaluation(pl.Callback):
    """The test metrics of `python -m ggns test` (`--evaluation.*`, the CLI's `evaluation:` group): every
    test batch is rolled out under each schedule of `schedules` (the model's effective ones: a model
    without point clouds gets "never" once) through `evaluate_model`, with the m+10-step error if
    `m_plus_10` and the IoU if `iou` (2D: areas; 3D: volumes, every 10th state); the one-step MSE is
    always computed. At the end of the test each metric's mean over the test trajectories is logged as
    `test/<name>`, the table printed, and test_metrics.md and test_metrics.json (metric -> mean, std,
    count) written in `trainer.log_dir` (the logger's folder, else the trainer's default_root_dir), both
    naming the checkpoint that was evaluated (`selection.checkpoint_info`: path, global step, epoch and,
    for a best-* checkpoint, the scalar it was selected on; under "checkpoint" in the JSON). `results`
    holds the summary afterwards."""

    def __init__(self, schedules: Sequence[str] = PAPER_SCHEDULES, m_plus_10: bool = True, iou: bool = True):
        self.schedules = [parse_schedule(s) for s in schedules]  # none: the one-step (and m+10) metrics alone
        self.m_plus_10, self.iou = m_plus_10, iou
        self.results: dict | None = None
        self._table: MetricTable | None = None

    def on_test_epoch_start(self, trainer: pl.Trainer, pl_module) -> None:
        self._table, self.results = MetricTable(), None

    def on_test_batch_end(self, trainer: pl.Trainer, pl_module, outputs, batch, batch_idx: int,
                          dataloader_idx: int = 0) -> None:
        self._table.add(evaluate_model(pl_module, batch, effective_schedules(self.schedules, pl_module.uses_points),
                                       m_plus_10=self.m_plus_10, iou=self.iou))

    def on_test_epoch_end(self, trainer: pl.Trainer, pl_module) -> None:
        self.results = self._table.summary()
        for name, s in self.results.items():
            pl_module.log(f"test/{name}", s["mean"])

    def on_test_end(self, trainer: pl.Trainer, pl_module) -> None:
        if not trainer.is_global_zero or self.results is None:
            return
        table = metrics_markdown(self.results, f"{type(pl_module).__name__} test metrics")
        print("\n" + table)
        info = checkpoint_info(trainer.ckpt_path) if trainer.ckpt_path else None
        line = f"tested checkpoint: {describe(info)}" + (f", {info['path']}" if info else "")
        print(line)
        directory = Path(trainer.log_dir or ".")
        write_text(directory / "test_metrics.md", table + "\n" + line + "\n")
        write_json(directory / "test_metrics.json", {**self.results, CHECKPOINT_KEY: info})


# their names in configs written before the test metrics moved from the model into the callback
TestReport = TestedCheckpoint = TestEvaluation


class RolloutPictures(pl.Callback):
    """Adds a picture of ground truth vs. rollout (point clouds overlaid at the steps that used
    them) of validation trajectory `trajectory` to TensorBoard as `rollout/<split>_<index>` (3D
    scenes: two views per model); other loggers than TensorBoard, and meshes without cells (the
    authors' 3D datasets), get nothing (with one warning)."""

    def __init__(self, schedule: str = "every:5", trajectory: int = 0, num_frames: int = 4, split: str = "val"):
        self.schedule = parse_schedule(schedule)
        self.trajectory, self.num_frames, self.split = trajectory, num_frames, split
        self._cache: dict = {}
        self._warned = False

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        logger = next((lg for lg in trainer.loggers if isinstance(lg, TensorBoardLogger)), None)
        if logger is None:
            if not self._warned:
                warnings.warn("RolloutPictures needs a TensorBoardLogger; no pictures are logged", stacklevel=2)
                self._warned = True
            return
        if "batch" not in self._cache:
            trajs = trainer.datamodule.trajectories(self.split)
            if not 0 <= self.trajectory < len(trajs):
                raise IndexError(f"RolloutPictures: trajectory {self.trajectory} not in the {len(trajs)} {self.split} trajectories")
            if not len(trajs[self.trajectory].cells):
                warnings.warn(f"RolloutPictures: {self.split} trajectory {self.trajectory} has no cells (the authors' "
                              "3D datasets hold none, docs/dataset_format.md); no pictures are logged", stacklevel=2)
            self._cache["batch"] = TrajectoryBatch.from_trajectories([trajs[self.trajectory]])
            self._cache["faces"] = trajs[self.trajectory].collider_faces
        if not len(self._cache["batch"].cells):
            return
        batch = self._cache["batch"].to(pl_module.device)
        fig = rollout_picture(batch, self._cache["faces"], {type(pl_module).__name__: pl_module}, self.schedule,
                              num_frames=self.num_frames, title=f"epoch {trainer.current_epoch}")
        logger.experiment.add_image(f"rollout/{self.split}_{self.trajectory}", figure_to_image(fig),
                                    trainer.global_step, dataformats="HWC")


class RolloutWriter(pl.Callback):
    """The rollouts of `predict`: every trajectory of the test split rolled out from its first state under
    `schedule` (the model's effective one: "never" for a model without point clouds), written as a
    predictions file (`ggns.data.predictions`, documented in docs/dataset_format.md) to
    `<log dir>/<filename>`: each rollout beside a copy of its test trajectory, with the checkpoint
    (`--ckpt_path`) and its sha256, the model class, the schedule and the test split file. An existing
    file is refused (before any rollout) unless `overwrite`."""

    def __init__(self, filename: str = "predictions.h5", overwrite: bool = False, schedule: str = "every:1"):
        self.filename, self.overwrite = filename, overwrite
        self.schedule = parse_schedule(schedule)
        self._positions: list = []

    def path(self, trainer: pl.Trainer) -> Path:
        return Path(trainer.log_dir or ".") / self.filename

    def on_predict_start(self, trainer: pl.Trainer, pl_module) -> None:
        if self.path(trainer).exists() and not self.overwrite:  # refused before the rollouts, not after
            raise FileExistsError(f"{self.path(trainer)}: already exists (RolloutWriter overwrite=True replaces it)")
        self._positions = []

    def on_predict_batch_end(self, trainer: pl.Trainer, pl_module, outputs, batch, batch_idx: int,
                             dataloader_idx: int = 0) -> None:
        plan = effective_schedule(self.schedule, pl_module.uses_points)
        positions = pl_module.rollout(batch, plan).cpu()
        self._positions += [positions[:, a:b].numpy() for a, b in zip(batch.node_offsets[:-1], batch.node_offsets[1:])]

    def on_predict_end(self, trainer: pl.Trainer, pl_module) -> None:
        datamodule = trainer.datamodule
        inputs = datamodule.trajectories("test")
        if len(self._positions) != len(inputs):
            raise RuntimeError(f"RolloutWriter: {len(self._positions)} rollouts for {len(inputs)} test trajectories")
        with SplitReader(datamodule.path("test")) as split:
            scene = split.scene
        checkpoint = str(trainer.ckpt_path or "")
        path = write_predictions(self.path(trainer), Predictions(
            positions=self._positions, inputs=inputs, model_class=type(pl_module).__name__,
            schedule=str(effective_schedule(self.schedule, pl_module.uses_points)), checkpoint=checkpoint,
            checkpoint_sha256=sha256(checkpoint) if checkpoint else "",
            input_file=str(Path(datamodule.path("test")).resolve()), scene=scene), overwrite=self.overwrite)
        print(f"wrote {path}")
