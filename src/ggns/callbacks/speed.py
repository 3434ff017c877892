"""Speed settings of a run, as Lightning callbacks (add them with `--trainer.callbacks+=ggns.callbacks.<Name>`
or in a config's `trainer.callbacks`); what each does to speed and numbers is measured in docs/speed.md.

    StaticRollouts    validation, test and predict rollouts as whole static steps: CUDA-graph replays on a GPU
    StaticTraining    every training step (forward, backward, Adam) on static shapes: one CUDA-graph replay on a GPU
    MatmulPrecision   torch.set_float32_matmul_precision: TF32 products on NVIDIA GPUs ("high"); changes numbers
    CompileProcessor  torch.compile of the message-passing blocks (dynamic shapes); on the CPU it is slower

bf16 autocast is Lightning's own: `--trainer.precision bf16-mixed` (changes numbers; docs/speed.md).
"""
from __future__ import annotations

import warnings

import pytorch_lightning as pl
import torch

from ..models.speed import compile_processor


class StaticRollouts(pl.Callback):
    """Rollouts of validation, test and predict as whole static steps (`GraphSimulator.static_rollouts`): the
    graph, the model, the integration and the checks on static shapes (`evaluation.capture.StaticStep`), on a
    GPU one CUDA-graph replay per step, on the CPU the same tensor program eagerly (how the GPU path is
    tested; not faster there). GGNSID, whose step fuses a material estimate, keeps its eager rollouts, with
    a warning."""

    def setup(self, trainer: pl.Trainer, pl_module, stage: str) -> None:
        if pl_module.material_input:
            warnings.warn(f"StaticRollouts: {type(pl_module).__name__} fuses a material estimate between steps; its "
                          f"rollouts stay eager", stacklevel=2)
            return
        pl_module.static_rollouts = True


class StaticTraining(pl.Callback):
    """Every training step on static shapes (`GraphSimulator.static_training`, `models.static_training`): the
    window's graphs, the model, the loss, backward and the fused Adam step with no host read, one CUDA-graph
    replay on a GPU (autocast's weight cache off while it records; on the CPU the same program eagerly).
    Lightning stays the loop (logging, checkpoints, resume); the model switches to manual optimization.
    One process only (its backward is not DDP's), float32 or bf16 (no loss scaling). GGNSID keeps the eager
    step, with a warning."""

    def setup(self, trainer: pl.Trainer, pl_module, stage: str) -> None:
        if stage != "fit":
            return
        if pl_module.material_input:
            warnings.warn(f"StaticTraining: {type(pl_module).__name__}'s loss reads more than its graph; its training "
                          f"steps stay eager", stacklevel=2)
            return
        if trainer.world_size > 1:
            raise ValueError("StaticTraining runs in one process: its backward is not DDP's (whose all-reduce a "
                             "recorded step could not replay); use --trainer.devices 1 or leave it out")
        if str(trainer.precision).startswith("16"):
            raise ValueError(f"StaticTraining does not scale the loss, which float16 ({trainer.precision}) needs; "
                             f"use 32-true or bf16-mixed")
        pl_module.static_training = True
        pl_module.automatic_optimization = False


class MatmulPrecision(pl.Callback):
    """`torch.set_float32_matmul_precision(precision)` for the run: "highest" (float32 products, the default),
    "high" (TF32 tensor cores on NVIDIA GPUs since Ampere), "medium" (bf16 products). Opt-in: it changes
    numbers (docs/speed.md)."""

    def __init__(self, precision: str = "high"):
        if precision not in ("highest", "high", "medium"):
            raise ValueError(f"precision must be highest, high or medium, got {precision!r}")
        self.precision = precision

    def setup(self, trainer: pl.Trainer, pl_module, stage: str) -> None:
        torch.set_float32_matmul_precision(self.precision)


class CompileProcessor(pl.Callback):
    """`torch.compile` of each message-passing block in place (`nn.Module.compile`, so checkpoints keep their
    parameter names), with dynamic shapes (graphs change size every step). A block compiles to one graph
    without breaks; the first steps pay the compilation (tens of seconds on 2 CPU cores)."""

    def __init__(self, backend: str = "inductor", mode: str | None = None, dynamic: bool = True):
        self.options = dict(backend=backend, mode=mode, dynamic=dynamic)

    def setup(self, trainer: pl.Trainer, pl_module, stage: str) -> None:
        compile_processor(pl_module, **self.options)
