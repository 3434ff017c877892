"""The Lightning CLI: `python -m ggns {fit,validate,test,predict} --config conf/plate/<model>.yaml`.

Any `GraphSimulator` subclass is a model (`--model ggns.models.simulators.GGNS` or a config's
`model.class_path`); the data is a `SimulationDataModule`. Configs are parsed in omegaconf mode
(so `${...}` interpolation works), the run's full config is saved next to its TensorBoard logs,
and `--ckpt_path` resumes a fit or picks the checkpoint to test.
"""
from __future__ import annotations

from pytorch_lightning.cli import LightningCLI

from .data.module import SimulationDataModule
from .models.simulators import GraphSimulator

SUBCOMMANDS = ("fit", "validate", "test", "predict")


def build_cli(args: list[str] | None = None, run: bool = True) -> LightningCLI:
    """Parse `args` (a subcommand first when run=True) and, if `run`, execute it."""
    return LightningCLI(
        GraphSimulator,
        SimulationDataModule,
        subclass_mode_model=True,
        parser_kwargs={"parser_mode": "omegaconf"},
        save_config_kwargs={"overwrite": True},
        seed_everything_default=0,
        args=args,
        run=run,
    )
