"""The callbacks of a command-line run itself: its config saved beside its logs (`RunConfigCallback`) and
its state saved when a SIGTERM stops a fit (`LastCheckpointOnSigterm`)."""
from __future__ import annotations

from pytorch_lightning import Trainer
from pytorch_lightning.callbacks import Callback, ModelCheckpoint
from pytorch_lightning.cli import SaveConfigCallback
from pytorch_lightning.trainer.states import TrainerFn
from pytorch_lightning.utilities.exceptions import SIGTERMException


class RunConfigCallback(SaveConfigCallback):
    """Saves the run's full config next to its logs; a run without a logger has no log directory
    of its own (Lightning would write config.yaml into the working directory) and saves none."""

    def setup(self, trainer: Trainer, pl_module, stage: str) -> None:
        if trainer.loggers:
            super().setup(trainer, pl_module, stage)


class LastCheckpointOnSigterm(Callback):
    """On SIGTERM (Lightning stops at the end of the running batch), saves the fit's state where its
    `last` ModelCheckpoint keeps it, so that resuming from last.ckpt loses no finished step."""

    def on_exception(self, trainer: Trainer, pl_module, exception: BaseException) -> None:
        if not isinstance(exception, SIGTERMException) or trainer.state.fn != TrainerFn.FITTING:
            return
        for callback in trainer.checkpoint_callbacks:
            if isinstance(callback, ModelCheckpoint) and callback.filename == "last" and callback.dirpath:
                trainer.save_checkpoint(callback.format_checkpoint_name({}, callback.filename))
