"""Speed settings of a run, as Lightning callbacks (add them with `--trainer.callbacks+=ggns.models.speed.<Name>`
or in a config's `trainer.callbacks`); what each does to speed and numbers is measured in docs/speed.md.

    StaticRollouts    validation, test and predict rollouts on static-shape graphs: CUDA-graph replays on a GPU
    MatmulPrecision   torch.set_float32_matmul_precision: TF32 products on NVIDIA GPUs ("high"); changes numbers
    CompileProcessor  torch.compile of the message-passing blocks (dynamic shapes); on the CPU it is slower

bf16 autocast is Lightning's own: `--trainer.precision bf16-mixed` (changes numbers; docs/speed.md).
"""
from __future__ import annotations

import warnings

import pytorch_lightning as pl
import torch


class StaticRollouts(pl.Callback):
    """Rollouts of validation, test and predict on static-shape graphs (`GraphSimulator.static_rollouts`):
    on a GPU every rollout step is a CUDA graph replay (`evaluation.capture.StaticStep`), on the CPU the
    padded step runs eagerly (no faster there: it is how the GPU path is tested). Models whose step has
    state (GGNS+LSTM, GGNSID) keep their eager rollouts, with a warning."""

    def setup(self, trainer: pl.Trainer, pl_module, stage: str) -> None:
        if pl_module.recurrent or pl_module.material_input:
            warnings.warn(f"StaticRollouts: {type(pl_module).__name__} has a step with state; its rollouts stay eager",
                          stacklevel=2)
            return
        pl_module.static_rollouts = True


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


def compile_processor(model, backend: str = "inductor", mode: str | None = None, dynamic: bool = True) -> None:
    """Compile `model.core.processor`'s blocks in place (see `CompileProcessor`)."""
    for block in model.core.processor:
        block.compile(backend=backend, mode=mode, dynamic=dynamic)
