"""The learning-rate schedule of the simulators (`LRSchedule`): Adam with an optional linear warm-up,
then an exponential decay towards a floor as in MeshGraphNets (lr 1e-4 -> 1e-6, decay rate 0.1 per 5M
steps):

    lr(step) = w(step) * (final + (lr - final) * decay_rate ** (step / decay_steps))
    w(step)  = min(1, (step + 1) / warmup_steps)   (1 without warm-up)

`step` counts optimizer steps from 0 (the lr of the first step is lr(0)). decay_rate = 1 (the
default) keeps the lr constant at `lr`, the paper's Adam 5e-4.

Why the schedule is a component of the model and not LightningCLI's `optimizer` / `lr_scheduler`
arguments: those exist only in a CLI run's config, while the schedule is part of a simulator's
training recipe. Kept in the model's hyperparameters, it travels with every checkpoint, so a fit
resumed or fine-tuned from Python (`pretrained.load`, the sweeps, the benchmarks), not only from
the CLI, continues with the same optimizer and the same lr at the same step.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from ..config import dataclass_of


@dataclass(frozen=True)
class LRSchedule:
    """Adam's learning rate per optimizer step (module docstring).

    Args:
        lr: the initial (peak) learning rate (paper: 5e-4).
        final: the floor the decay approaches, in [0, lr].
        decay_rate: factor per `decay_steps` optimizer steps, in (0, 1] (1: constant lr).
        decay_steps: optimizer steps per `decay_rate` factor (>= 1).
        warmup_steps: optimizer steps of the linear warm-up (0: none).
    """

    lr: float = 5e-4
    final: float = 0.0
    decay_rate: float = 1.0
    decay_steps: int = 1
    warmup_steps: int = 0

    def __post_init__(self):
        validate_schedule(self.lr, self.final, self.decay_rate, self.decay_steps, self.warmup_steps)

    @classmethod
    def of(cls, value: LRSchedule | Mapping | None) -> LRSchedule:
        """The part from itself, a mapping of its fields or None (the defaults); an unknown field is
        refused by name (`ggns.config.dataclass_of`)."""
        return dataclass_of(cls, value, "lr_schedule")

    def at(self, step: int) -> float:
        """The learning rate of optimizer step `step` (0-based)."""
        return scheduled_lr(step, self.lr, self.final, self.decay_rate, self.decay_steps, self.warmup_steps)

    def optimizers(self, parameters) -> dict:
        """What a LightningModule's `configure_optimizers` returns: a fused Adam (one kernel for all
        parameters) and this schedule stepped after every optimizer step, named `train/lr`."""
        optimizer = torch.optim.Adam(parameters, lr=self.lr, fused=True)
        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: self.at(step) / self.lr)
        return {"optimizer": optimizer,
                "lr_scheduler": {"scheduler": scheduler, "interval": "step", "frequency": 1, "name": "train/lr"}}


def validate_schedule(lr: float, final: float, decay_rate: float, decay_steps: int, warmup_steps: int) -> None:
    """Raise ValueError naming the first bad field of `LRSchedule`."""
    if not (lr > 0 and math.isfinite(lr)):
        raise ValueError(f"lr_schedule.lr must be a finite number > 0, got {lr}")
    if not 0 <= final <= lr:
        raise ValueError(f"lr_schedule.final must lie in [0, lr = {lr}], got {final}")
    if not 0 < decay_rate <= 1:
        raise ValueError(f"lr_schedule.decay_rate must lie in (0, 1] (1: constant lr), got {decay_rate}")
    if isinstance(decay_steps, bool) or not isinstance(decay_steps, int) or decay_steps < 1:
        raise ValueError(f"lr_schedule.decay_steps must be an integer >= 1 (optimizer steps), got {decay_steps!r}")
    if isinstance(warmup_steps, bool) or not isinstance(warmup_steps, int) or warmup_steps < 0:
        raise ValueError(f"lr_schedule.warmup_steps must be an integer >= 0 (optimizer steps), got {warmup_steps!r}")


def scheduled_lr(step: int, lr: float, final: float = 0.0, decay_rate: float = 1.0, decay_steps: int = 1,
                 warmup_steps: int = 0) -> float:
    """The learning rate of optimizer step `step` (0-based), module docstring."""
    decayed = final + (lr - final) * decay_rate ** (step / decay_steps)
    return decayed * min(1.0, (step + 1) / warmup_steps) if warmup_steps else decayed
