"""The learning-rate schedule of the simulators: an optional linear warm-up, then an exponential
decay towards a floor as in MeshGraphNets (lr 1e-4 -> 1e-6, decay rate 0.1 per 5M steps):

    lr(step) = w(step) * (lr_final + (lr - lr_final) * decay_rate ** (step / decay_steps))
    w(step)  = min(1, (step + 1) / warmup_steps)   (1 without warm-up)

`step` counts optimizer steps from 0 (the lr of the first step is lr(0)). decay_rate = 1 (the
default) keeps the lr constant at `lr`, the paper's Adam 5e-4.
"""
from __future__ import annotations

import math


def validate_schedule(lr: float, lr_final: float, decay_rate: float, decay_steps: int, warmup_steps: int) -> None:
    """Raise ValueError naming the first bad argument (the names are the simulators' init args)."""
    if not (lr > 0 and math.isfinite(lr)):
        raise ValueError(f"lr must be a finite number > 0, got {lr}")
    if not 0 <= lr_final <= lr:
        raise ValueError(f"lr_final must lie in [0, lr = {lr}], got {lr_final}")
    if not 0 < decay_rate <= 1:
        raise ValueError(f"lr_decay_rate must lie in (0, 1] (1: constant lr), got {decay_rate}")
    if isinstance(decay_steps, bool) or not isinstance(decay_steps, int) or decay_steps < 1:
        raise ValueError(f"lr_decay_steps must be an integer >= 1 (optimizer steps), got {decay_steps!r}")
    if isinstance(warmup_steps, bool) or not isinstance(warmup_steps, int) or warmup_steps < 0:
        raise ValueError(f"lr_warmup_steps must be an integer >= 0 (optimizer steps), got {warmup_steps!r}")


def scheduled_lr(step: int, lr: float, lr_final: float = 0.0, decay_rate: float = 1.0, decay_steps: int = 1,
                 warmup_steps: int = 0) -> float:
    """The learning rate of optimizer step `step` (0-based), module docstring."""
    decayed = lr_final + (lr - lr_final) * decay_rate ** (step / decay_steps)
    return decayed * min(1.0, (step + 1) / warmup_steps) if warmup_steps else decayed
