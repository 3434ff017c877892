"""A Lightning callback that kills its own process with SIGKILL at a chosen point of a fit, for the
fault-injection tests (tests/test_faults.py): GGNS_KILL_AT=<hook>:<global step> names the point,
<hook> one of batch_start, before_optimizer_step (gradients computed, weights not yet changed) and
batch_end (weights changed, that step's checkpoint not yet written: Lightning runs ModelCheckpoint
after the other callbacks). Unset, it does nothing. A real signal: nothing in the process runs after it.

GGNS_KILL_AT=requeue:<global step> plays a SLURM time limit at that step's batch end: SIGUSR1 first
(sbatch --signal=SIGUSR1@90; Lightning's handler saves an hpc checkpoint and calls `scontrol requeue`),
then SIGKILL, as SLURM ends the job when its time is up."""
from __future__ import annotations

import os
import signal

import pytorch_lightning as pl

HOOKS = ("batch_start", "before_optimizer_step", "batch_end")
REQUEUE = "requeue"


class KillAt(pl.Callback):
    def __init__(self) -> None:
        spec = os.environ.get("GGNS_KILL_AT")
        self.hook, self.step = (spec.split(":")[0], int(spec.split(":")[1])) if spec else (None, -1)
        if self.hook is not None and self.hook not in (*HOOKS, REQUEUE):
            raise ValueError(f"GGNS_KILL_AT hook must be one of {(*HOOKS, REQUEUE)}, got {self.hook!r}")

    def _kill_at(self, hook: str, trainer: pl.Trainer) -> None:
        if hook == self.hook and trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGKILL)

    def on_train_batch_start(self, trainer, *args) -> None:
        self._kill_at("batch_start", trainer)

    def on_before_optimizer_step(self, trainer, *args) -> None:
        self._kill_at("before_optimizer_step", trainer)

    def on_train_batch_end(self, trainer, *args) -> None:
        self._kill_at("batch_end", trainer)
        if self.hook == REQUEUE and trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGUSR1)  # Python runs the handler before the next line
            os.kill(os.getpid(), signal.SIGKILL)
