"""The callbacks of a command-line run itself: its config saved beside its logs (`RunConfigCallback`),
its state saved when a SIGTERM stops a fit (`LastCheckpointOnSigterm`), and a fit started from another
checkpoint's weights (`InitialWeights`: fine-tuning a trained simulator, e.g. a shipped one, on new data)."""
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


class InitialWeights(Callback):
    """A fit that starts from the weights (and the normalization statistics) of a trained simulator's
    checkpoint, e.g. a shipped one fine-tuned on one's own data or sensor: `--trainer.callbacks+='{"class_path":
    "ggns.callbacks.InitialWeights", "init_args": {"checkpoint": "pretrained:tissue/ggns"}}'` (a shipped
    simulator's name, verified against its manifest, or a checkpoint file).
    The optimizer, the lr schedule and the step count start afresh; the statistics are the checkpoint's
    (no normalization pass). A fit resumed from its own checkpoint (`ckpt_path`) keeps that one's weights.
    The checkpoint is read as data (`ggns.pretrained.load_model`); one of another class or with
    other parameter shapes is refused naming the first difference."""

    def __init__(self, checkpoint: str):
        self.checkpoint = str(checkpoint)

    def on_fit_start(self, trainer: Trainer, pl_module) -> None:
        if trainer.ckpt_path is not None:
            return
        from ..pretrained import load_model

        try:
            trained = load_model(self.checkpoint)
        except (OSError, ValueError) as error:
            raise ValueError(f"initial weights {self.checkpoint}: {error}") from error
        if type(trained) is not type(pl_module):
            raise ValueError(f"initial weights {self.checkpoint}: a {type(trained).__name__}, the fit's model is a "
                             f"{type(pl_module).__name__}")
        own, theirs = pl_module.state_dict(), trained.state_dict()
        for key in sorted(set(own) | set(theirs)):
            if key not in own or key not in theirs or own[key].shape != theirs[key].shape:
                shapes = [tuple(d[key].shape) if key in d else "missing" for d in (own, theirs)]
                raise ValueError(f"initial weights {self.checkpoint}: {key} is {shapes[1]} there and {shapes[0]} in "
                                 f"the fit's model (its hyperparameters differ)")
        pl_module.load_state_dict(theirs, strict=True)
