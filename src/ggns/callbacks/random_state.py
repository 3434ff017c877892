"""`RandomState`: a fit's checkpoints keep the random generators' states, and a fit resumed from one
takes them back, so that the resumed fit repeats what the uninterrupted one would have done.

The training noise and the imputation draws come from torch's global generator (the data loaders
have their own, `ggns.data.module`). Every checkpoint a fit writes gets the state of torch's CPU
generator of every process, and the CUDA one of each process's device on a GPU, as uint8 tensors
[world size, n] under `RNG_KEY` (plain tensors: checkpoints stay data, `ggns.checkpoints`). A fit
resumed from it (`fit --ckpt_path`) sets them back just before its first batch: nothing between
loading and there (validation, loaders) draws from them. With the data order that
`SimulationDataModule` resumes, the resumed fit ends with the uninterrupted fit's weights
(tests/test_faults.py). `ggns.cli` adds this callback to every fit.
"""
from __future__ import annotations

import warnings

import pytorch_lightning as pl
import torch
from torch import Tensor

RNG_KEY = "ggns_rng_states"


class RandomState(pl.Callback):
    """Saves the generators' states in a fit's checkpoints and restores them when the fit resumes
    (module docstring). A checkpoint of a fit with another number of processes cannot be restored
    rank by rank: the fit then warns and its generators start afresh."""

    def __init__(self):
        self._saved: dict[str, Tensor] | None = None

    @staticmethod
    def states(pl_module: pl.LightningModule) -> dict[str, Tensor]:
        """{generator: state of every rank [world size, n] uint8} (gathered from every rank under DDP:
        all ranks save together)."""
        states = {"cpu": torch.get_rng_state()}
        if pl_module.device.type == "cuda":
            states["cuda"] = torch.cuda.get_rng_state(pl_module.device)
        trainer = pl_module._trainer
        if trainer is not None and trainer.world_size > 1:
            return {k: pl_module.all_gather(v.to(pl_module.device)).cpu() for k, v in states.items()}
        return {k: v[None] for k, v in states.items()}

    def on_save_checkpoint(self, trainer: pl.Trainer, pl_module: pl.LightningModule, checkpoint: dict) -> None:
        if trainer.state.fn == "fit":  # a fit's checkpoint: resumable
            checkpoint[RNG_KEY] = self.states(pl_module)

    def on_load_checkpoint(self, trainer: pl.Trainer, pl_module: pl.LightningModule, checkpoint: dict) -> None:
        self._saved = checkpoint.get(RNG_KEY)  # taken back by on_train_start

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        states, self._saved = self._saved, None
        if states is None or trainer.ckpt_path is None:
            return
        rank, world = trainer.global_rank, trainer.world_size
        if any(v.shape[0] != world for v in states.values()):
            warnings.warn(f"the checkpoint was written by a fit of {next(iter(states.values())).shape[0]} processes, "
                          f"this one has {world}: its random generators start afresh and the resumed fit "
                          "differs from an uninterrupted one", stacklevel=2)
            return
        torch.set_rng_state(states["cpu"][rank].clone())
        if "cuda" in states and pl_module.device.type == "cuda":
            torch.cuda.set_rng_state(states["cuda"][rank].clone(), pl_module.device)
