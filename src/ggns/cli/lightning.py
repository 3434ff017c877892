"""The Lightning CLI: `python -m ggns {fit,validate,test,predict} --config conf/plate/<model>.yaml`.

Any `GraphSimulator` subclass is a model (`--model ggns.models.simulators.GGNS` or a config's
`model.class_path`); the data is a `SimulationDataModule`. Configs are parsed in omegaconf mode
(so `${...}` interpolation works), the run's full config is saved next to its TensorBoard logs
(runs without a logger save none),
and `--ckpt_path` resumes a fit or picks the checkpoint to test (the model then takes the
checkpoint's hyperparameters; the test's settings are the `evaluation:` group's, `TestEvaluation`); `--ckpt_path
pretrained:plate/ggns` (or the shipped file's path) takes a shipped simulator, verified against its
manifest and refused for data of another scene (`ggns.pretrained`). Nothing given is
silently dropped for the checkpoint's: a checkpoint of another model class than the config's is
refused, and so is a model argument given on the command line that the checkpoint would replace
by a different value (`CheckpointMismatchError`). A trainer with a logger also logs the learning
rate of every optimizer step as `train/lr` (Lightning's LearningRateMonitor); every fit keeps its random
generators' states in its checkpoints (`RandomState`, unless the config already has it) and every test
computes and writes its metrics (`TestEvaluation`, configured by the `evaluation:` group). Model arguments of older versions (`--model.init_args.noise_std`,
`lr_decay_rate`, `type_partition`, ...) are refused naming their new place (`RENAMED_ARGS`), and
checkpoints written with them are converted when read (`upgrade_hparams`). A fit stopped by SIGTERM
(a cluster's pre-emption, `kill`) saves its state to last.ckpt before it ends (`LastCheckpointOnSigterm`),
and `python -m ggns` then exits with status 143, so a resume continues from the step it stopped at.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

from pytorch_lightning import Trainer
from pytorch_lightning.callbacks import LearningRateMonitor, ModelCheckpoint
from pytorch_lightning.cli import LightningCLI

from ..checkpoints import check_format, read_checkpoint
from ..config import base_chain, config_file, load_config
from ..data.module import SimulationDataModule
from ..callbacks import LastCheckpointOnSigterm, RandomState, RunConfigCallback, TestEvaluation
from ..models.graph_simulator import GraphSimulator, refuse_distributed
from ..models.loading import RENAMED_ARGS, upgrade_hparams
from ..pretrained import PREFIX, check_data, checkpoint_path, shipped_name

class CheckpointMismatchError(ValueError):
    """--ckpt_path names a checkpoint that contradicts the model the config or the command line asks for."""


def refuse_renamed_args(args: list[str]) -> None:
    """A model argument of an older version on the command line (`--model.init_args.noise_std`) raises
    ValueError naming where it is now (`RENAMED_ARGS`)."""
    old = sorted(command_line_model_args(args) & set(RENAMED_ARGS))
    if old:
        raise ValueError("model arguments of an older version: " +
                         "; ".join(f"{name} is now {RENAMED_ARGS[name]}" for name in old) +
                         " (e.g. --model.init_args.noise.std 0.01, --model.init_args.lr_schedule.lr 1e-3)")


# the modules the callbacks lived in before they moved into `ggns.callbacks`
MOVED_CALLBACKS = re.compile(r"\bggns\.(?:evaluation\.callbacks|models\.speed|models\.random_state|experiments\.clock"
                             r"|experiments\.learning)\.([A-Z]\w*)")


def refuse_moved_callbacks(args: list[str]) -> None:
    """A callback named by its module of an older version (`ggns.evaluation.callbacks.RolloutEvaluation`), on
    the command line or in a `--config` file, raises ValueError naming its place now (`ggns.callbacks.<Name>`)."""
    i = 0
    while i < len(args):
        where, text = "the command line", str(args[i])
        if args[i] == "--config" and i + 1 < len(args) and Path(args[i + 1]).is_file():
            where, text = str(args[i + 1]), Path(args[i + 1]).read_text()
            i += 1
        match = MOVED_CALLBACKS.search(text)
        if match:
            raise ValueError(f"{where}: {match.group(0)} is now ggns.callbacks.{match.group(1)} (every callback of the "
                             f"library is in ggns.callbacks)")
        i += 1


def command_line_model_args(args: list[str]) -> set[str]:
    """The model init arguments given on a command line (`--model.init_args.NAME[=V]` or `--model.NAME`; a
    component's field, `--model.init_args.noise.std`, names its component, `noise`)."""
    names = set()
    for arg in args:
        match = re.match(r"--model\.(?:init_args\.)?([A-Za-z_]\w*)(?:\.[A-Za-z_][\w.]*)?(?:=|$)", str(arg))
        if match and match.group(1) not in ("class_path", "init_args", "dict_kwargs"):
            names.add(match.group(1))
    return names


class SimulatorCLI(LightningCLI):
    """LightningCLI whose trainers, when they have a logger, log the learning rate per optimizer step
    (under the scheduler's name, `train/lr` for the simulators); without a logger the monitor would raise."""

    def instantiate_trainer(self, **kwargs) -> Trainer:
        trainer = super().instantiate_trainer(**kwargs)
        if trainer.loggers and not any(isinstance(c, LearningRateMonitor) for c in trainer.callbacks):
            trainer.callbacks.append(LearningRateMonitor(logging_interval="step"))
        if not any(isinstance(c, RandomState) for c in trainer.callbacks):
            trainer.callbacks.append(RandomState())
        # the `evaluation` group's TestEvaluation is the last one; a config's own (older configs list
        # TestReport, its former name) would compute the test metrics a second time
        evaluations = [c for c in trainer.callbacks if isinstance(c, TestEvaluation)]
        for callback in evaluations[:-1]:
            trainer.callbacks.remove(callback)
        # last.ckpt after every other checkpoint of the same hook, so that it holds their newest states (a
        # model config appends its best-k1 checkpoint after the base's `last`)
        for callback in [c for c in trainer.callbacks if isinstance(c, ModelCheckpoint) and c.filename == "last"]:
            trainer.callbacks.remove(callback)
            trainer.callbacks.append(callback)
        trainer.callbacks.append(LastCheckpointOnSigterm())
        return trainer

    def add_arguments_to_parser(self, parser) -> None:
        # the test's schedules, m+10 and IoU: `evaluation:` in a config, `--evaluation.schedules` on the command line
        parser.add_lightning_class_args(TestEvaluation, "evaluation")
        parser.add_argument("--base", type=str | None, default=None,
                            help="in a config file: the config it extends (a path relative to it, or a shipped "
                                 "config such as `trainer`), applied before it (ggns.cli.config_bases)")

    def before_instantiate_classes(self) -> None:
        """The saved config.yaml is the whole merged config: it extends nothing (`base` cleared)."""
        if self.subcommand is not None and "base" in self.config[self.subcommand]:
            self.config[self.subcommand]["base"] = None

    def _run_subcommand(self, subcommand: str) -> None:
        """Lightning's, after `refuse_distributed`: a run its processes cannot do is refused before the
        DDP launcher starts them (the model's setup would refuse it again on every rank)."""
        refuse_distributed(self.trainer, subcommand)
        super()._run_subcommand(subcommand)

    def parse_arguments(self, parser, args) -> None:
        if not isinstance(args, dict):
            args = shipped_configs([str(a) for a in (sys.argv[1:] if args is None else args)])
            refuse_renamed_args(args)
            refuse_moved_callbacks(args)
        self._given_args = args if not isinstance(args, dict) else []
        super().parse_arguments(parser, args)

    def _parse_ckpt_path(self) -> None:
        """Lightning's: the checkpoint's hyperparameters replace the model arguments (the evaluation
        settings are the `evaluation` group's, not the model's); refused when the checkpoint's model class differs from the config's, or
        when it would replace a model argument given on the command line by another value."""
        subcommand = self.config.get("subcommand")
        if not subcommand or not self.config[subcommand].get("ckpt_path"):
            return super()._parse_ckpt_path()
        self._check_pretrained(subcommand)
        model = self.config[subcommand].model
        init_args = model.get("init_args")
        asked_class = model.get("class_path")
        given = {k: init_args[k] for k in command_line_model_args(getattr(self, "_given_args", []))
                 if init_args is not None and k in init_args}
        self._parse_checkpoint_hparams(subcommand)
        model = self.config[subcommand].model
        path = self.config[subcommand].ckpt_path
        if asked_class and model.get("class_path") != asked_class:
            raise CheckpointMismatchError(
                f"{path} holds a {model.get('class_path')}, but the config asks for {asked_class}: test it "
                f"with that model's config (e.g. conf/plate/<model>.yaml) or pass --model {model.get('class_path')}")
        shadowed = {k: (v, model.init_args[k]) for k, v in given.items() if _differ(v, model.init_args.get(k))}
        if shadowed:
            raise CheckpointMismatchError(
                f"{path} was trained with other values of the model arguments given on the command line, which "
                "the checkpoint's would replace: " + ", ".join(f"{k}: given {a!r}, checkpoint {b!r}"
                                                               for k, (a, b) in shadowed.items()) +
                " (the evaluation settings, --evaluation.*, are the ones that change at test time)")

    def _parse_checkpoint_hparams(self, subcommand: str) -> None:
        """Lightning's `_parse_ckpt_path` on the checkpoint's hyperparameters as this version's init
        arguments (`upgrade_hparams`). The checkpoint is read as data (`ggns.checkpoints`), once, before
        Lightning reads it: a file that would run code or is of another format is refused with the reason
        rather than a traceback."""
        path = self.config[subcommand].ckpt_path
        checkpoint = read_checkpoint(path)
        check_format(checkpoint, path)
        hparams = dict(checkpoint.get("hyper_parameters", {}))
        hparams.pop("_instantiator", None)
        if not hparams:
            return
        hparams = upgrade_hparams(hparams)
        if "_class_path" in hparams:
            hparams = {"class_path": hparams.pop("_class_path"), "dict_kwargs": hparams}
        try:
            self.config = self.parser.parse_object({subcommand: {"model": hparams}}, self.config)
        except SystemExit:
            sys.stderr.write("Parsing of ckpt_path hyperparameters failed!\n")
            raise

    def _check_pretrained(self, subcommand: str) -> None:
        """`--ckpt_path pretrained:<task>/<model>` (or a shipped file's path): the verified shipped file
        (`ggns.pretrained.verify`), refused for data of another scene than it was trained on."""
        given = str(self.config[subcommand].ckpt_path)
        name = given.removeprefix(PREFIX) if given.startswith(PREFIX) else shipped_name(given)
        if name is None:
            return
        self.config[subcommand].ckpt_path = str(checkpoint_path(name))
        data = self.config[subcommand].get("data") or {}
        dataset = (data.get("init_args") or data).get("dataset") or "plate_small"
        check_data(name, load_config(dataset), source=f"data preset {dataset!r}")


def _differ(given, stored) -> bool:
    """Whether two argument values differ (lists and tuples compared by their items)."""
    normalize = (lambda v: list(v) if isinstance(v, (list, tuple)) else v)
    return normalize(given) != normalize(stored)


def shipped_configs(args: list[str]) -> list[str]:
    """`--config` values that name a shipped config (`plate/ggns`, or `conf/plate/ggns.yaml` from a folder
    without that file) replaced by the package's file (ggns.config.config_file), so that the presets work
    from any folder once ggns is installed; a config that names a `base` (`config_bases`) is preceded by
    its bases, each as a `--config` of its own, so that it extends them."""
    out, i = [], 0
    while i < len(args):
        arg = args[i]
        if arg == "--config" and i + 1 < len(args):
            value, i = args[i + 1], i + 2
        elif arg.startswith("--config="):
            value, i = arg.split("=", 1)[1], i + 1
        else:
            out.append(arg)
            i += 1
            continue
        path = config_file(value)
        for file in [*config_bases(path), path]:
            out += ["--config", str(file)]
    return out


def config_bases(path: Path) -> list[Path]:
    """The configs a Lightning config extends, outermost first: its top-level `base:` (a path relative to
    the config's folder, or a shipped config's name such as `trainer`), that one's base, and so on
    (`ggns.config.base_chain`, the inheritance of every kind of file). The config then applies over them:
    its keys replace theirs, and `callbacks+:` appends to their callbacks. A missing base or a cycle
    raises ValueError naming the config."""
    return base_chain(path)[:-1] if path.is_file() else []


def build_cli(args: list[str] | None = None, run: bool = True) -> LightningCLI:
    """Parse `args` (a subcommand first when run=True) and, if `run`, execute it."""
    return SimulatorCLI(
        GraphSimulator,
        SimulationDataModule,
        subclass_mode_model=True,
        parser_kwargs={"parser_mode": "omegaconf"},
        save_config_callback=RunConfigCallback,
        save_config_kwargs={"overwrite": True},
        seed_everything_default=0,
        args=args,
        run=run,
    )
