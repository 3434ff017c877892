"""The Lightning CLI: `python -m ggns {fit,validate,test,predict} --config conf/plate/<model>.yaml`.

Any `GraphSimulator` subclass is a model (`--model ggns.models.simulators.GGNS` or a config's
`model.class_path`); the data is a `SimulationDataModule`. Configs are parsed in omegaconf mode
(so `${...}` interpolation works), the run's full config is saved next to its TensorBoard logs,
and `--ckpt_path` resumes a fit or picks the checkpoint to test (the model then takes the
checkpoint's hyperparameters, except the evaluation settings `EVALUATION_ARGS`). A trainer with a
logger also logs the learning rate of every optimizer step as `train/lr` (Lightning's
LearningRateMonitor).
"""
from __future__ import annotations

from pytorch_lightning import Trainer
from pytorch_lightning.callbacks import LearningRateMonitor
from pytorch_lightning.cli import LightningCLI

from .data.module import SimulationDataModule
from .models.simulators import GraphSimulator

SUBCOMMANDS = ("fit", "validate", "test", "predict")
# Evaluation settings, not part of a trained model: with --ckpt_path they still come from the command
# line and config (Lightning replaces every other model argument by the checkpoint's hyperparameters).
EVALUATION_ARGS = ("eval_schedules", "test_m_plus_10", "test_iou")


class SimulatorCLI(LightningCLI):
    """LightningCLI whose trainers, when they have a logger, log the learning rate per optimizer step
    (under the scheduler's name, `train/lr` for the simulators); without a logger the monitor would raise."""

    def instantiate_trainer(self, **kwargs) -> Trainer:
        trainer = super().instantiate_trainer(**kwargs)
        if trainer.loggers and not any(isinstance(c, LearningRateMonitor) for c in trainer.callbacks):
            trainer.callbacks.append(LearningRateMonitor(logging_interval="step"))
        return trainer

    def _parse_ckpt_path(self) -> None:
        """Lightning's: the checkpoint's hyperparameters replace the model arguments, except EVALUATION_ARGS."""
        subcommand = self.config.get("subcommand")
        init_args = self.config[subcommand].model.get("init_args") if subcommand else None
        kept = {k: init_args[k] for k in EVALUATION_ARGS if init_args is not None and k in init_args}
        super()._parse_ckpt_path()
        for key, value in kept.items():
            self.config[subcommand].model.init_args[key] = value


def build_cli(args: list[str] | None = None, run: bool = True) -> LightningCLI:
    """Parse `args` (a subcommand first when run=True) and, if `run`, execute it."""
    return SimulatorCLI(
        GraphSimulator,
        SimulationDataModule,
        subclass_mode_model=True,
        parser_kwargs={"parser_mode": "omegaconf"},
        save_config_kwargs={"overwrite": True},
        seed_everything_default=0,
        args=args,
        run=run,
    )
