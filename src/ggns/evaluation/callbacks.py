"""Lightning callbacks shared by all simulators: rollout metrics on the validation split (for
checkpoint selection) and rollout pictures in TensorBoard. Both run at the end of every
validation epoch (set how often with the Trainer's `check_val_every_n_epoch`), never during the
sanity check, and roll out through the module's `evaluate` / `rollout`, i.e. the one engine.
`RolloutWriter` saves the rollouts of `predict`.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import BasePredictionWriter
from pytorch_lightning.loggers import TensorBoardLogger

from ..graphs.state import TrajectoryBatch
from .evaluate import schedule_key
from .schedules import Never, Schedule, parse_schedule


def _eval_batch(trainer: pl.Trainer, split: str, count: int | None, cache: dict) -> TrajectoryBatch:
    if "batch" not in cache:
        datamodule = trainer.datamodule
        if datamodule is None or not hasattr(datamodule, "eval_batch"):
            raise RuntimeError("rollout callbacks need a SimulationDataModule (trainer.datamodule.eval_batch)")
        cache["batch"] = datamodule.eval_batch(split, count)
    return cache["batch"].to(trainer.lightning_module.device)


def _effective(schedule: Schedule, pl_module) -> Schedule:
    """A model without point edges never sees point clouds, whatever the schedule says."""
    return schedule if pl_module.uses_points else Never()


class RolloutEvaluation(pl.Callback):
    """Logs `val/rollout_mse` (full-rollout MSE from S_0 under `schedule` on the first
    `num_trajectories` trajectories of `split`, all rolled out as one batch), the same value under
    `val/rollout_mse_<schedule>`, and `val/one_step_mse`; monitor `val/rollout_mse` with a
    ModelCheckpoint to select checkpoints on rollout quality."""

    def __init__(self, schedule: str = "every:5", num_trajectories: int | None = 16, split: str = "val"):
        self.schedule = parse_schedule(schedule)
        self.num_trajectories, self.split = num_trajectories, split
        self._cache: dict = {}

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module) -> None:
        if trainer.sanity_checking:
            return
        batch = _eval_batch(trainer, self.split, self.num_trajectories, self._cache)
        schedule = _effective(self.schedule, pl_module)
        metrics = pl_module.evaluate(batch, [schedule], m_plus_10=False, iou=False)
        value = metrics[f"rollout_mse_{schedule_key(schedule)}"].mean()
        pl_module.log("val/rollout_mse", value, batch_size=batch.num_graphs)
        pl_module.log(f"val/rollout_mse_{schedule_key(schedule)}", value, batch_size=batch.num_graphs)
        pl_module.log("val/one_step_mse", metrics["one_step_mse"].mean(), batch_size=batch.num_graphs)


class RolloutPictures(pl.Callback):
    """Adds a picture of ground truth vs. rollout (point clouds overlaid at the steps that used
    them) of validation trajectory `trajectory` to TensorBoard as `rollout/<split>_<index>`.
    2D scenes only; other loggers than TensorBoard get nothing (with one warning)."""

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
            self._cache["batch"] = TrajectoryBatch.from_trajectories([trajs[self.trajectory]])
            self._cache["faces"] = trajs[self.trajectory].collider_faces
        batch = self._cache["batch"].to(pl_module.device)
        if batch.positions.shape[-1] != 2:
            return
        from ..viz import figure_to_image, rollout_figure

        schedule = _effective(self.schedule, pl_module)
        pred = pl_module.rollout(batch, schedule)
        steps = batch.num_steps
        points = [batch.points[t].cpu() if t < steps - 1 and schedule.uses_points(t) else None for t in range(steps)]
        fig = rollout_figure(batch.cells.cpu(), batch.positions.cpu(), {f"{type(pl_module).__name__} {schedule}": pred.cpu()},
                             points=points, collider=None if batch.collider is None else batch.collider.cpu(),
                             collider_faces=self._cache["faces"], num_frames=self.num_frames,
                             title=f"epoch {trainer.current_epoch}")
        logger.experiment.add_image(f"rollout/{self.split}_{self.trajectory}", figure_to_image(fig),
                                    trainer.global_step, dataformats="HWC")



class RolloutWriter(BasePredictionWriter):
    """Saves what `predict` returns (per batch: the schedule, rollout positions [T, sumN, d] and
    the node offsets of its trajectories) to `<log dir>/predictions.pt` with torch.save."""

    def __init__(self, filename: str = "predictions.pt"):
        super().__init__(write_interval="epoch")
        self.filename = filename

    def write_on_epoch_end(self, trainer: pl.Trainer, pl_module, predictions, batch_indices) -> None:
        directory = Path(trainer.log_dir or ".")
        directory.mkdir(parents=True, exist_ok=True)
        torch.save(predictions, directory / self.filename)
        print(f"wrote {directory / self.filename}")
