"""`TrainingClock`: training seconds without validation, logged as `time/train_seconds` (read by
`ggns.sweeps.curves`; added to every fit of `python -m ggns bench learning`)."""
from __future__ import annotations

import time

import pytorch_lightning as pl

from ..sweeps.curves import CLOCK


class TrainingClock(pl.Callback):
    """Logs `time/train_seconds` with the training metrics (every `log_every_n_steps`) and at every
    validation: wall seconds since training started minus the seconds spent in validation loops.
    The normalization pass and the sanity check (both before training starts) are not counted;
    checkpoint writing is. The count is saved in checkpoints, so a resumed fit continues it."""

    def __init__(self):
        self.train_seconds = 0.0
        self._since: float | None = None  # None while not training
        self._paused = False  # in a validation loop that interrupted training

    def _lap(self) -> None:
        if self._since is not None:
            now = time.perf_counter()
            self.train_seconds += now - self._since
            self._since = now

    def on_train_start(self, trainer, pl_module) -> None:
        self._since = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self._lap()
        pl_module.log(CLOCK, self.train_seconds, on_step=True, on_epoch=False, batch_size=1)

    def on_validation_start(self, trainer, pl_module) -> None:
        if self._since is not None:
            self._lap()
            self._since, self._paused = None, True

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        if not trainer.sanity_checking:
            pl_module.log(CLOCK, self.train_seconds, batch_size=1)

    def on_validation_end(self, trainer, pl_module) -> None:
        if self._paused:
            self._since, self._paused = time.perf_counter(), False

    def state_dict(self) -> dict:
        return {"train_seconds": self.train_seconds}

    def load_state_dict(self, state_dict: dict) -> None:
        self.train_seconds = float(state_dict["train_seconds"])
