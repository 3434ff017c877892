"""Multi-seed sweeps: a grid of model configs x seeds, each run a Lightning `fit` then `test`
through the CLI in its own process, several at once, resumable.

A sweep file (conf/sweeps/<name>.yaml, a checkout's experiments/<experiment>/sweeps/<name>.yaml, or a path) holds:
    output: lightning_logs/sweeps/plate     # runs go to <output>/<model>/seed_<s>[_test]
    seeds: [0, 1, 2]
    parallel: 2                             # runs at once on this machine
    configs: [conf/profiles/cpu.yaml]       # optional: config files stacked after each model's config
    overrides:                              # optional: Lightning settings of every run, a mapping of its keys
      data: {dataset: plate_small}
    models:                                 # name -> its Lightning config (+ its own files and settings)
      ggns: {config: conf/plate/ggns.yaml, overrides: {trainer: {max_time: "00:00:40:00"}}}
      mgn:  {config: conf/plate/mgn.yaml, configs: [my_profile.yaml]}
    findings_ggns: [ggns_id]                # optional: variants of GGNS that the summary also judges
                                            # in GGNS's place (the paper's findings, the targets)

A run's fit is `python -m ggns fit --config <model config> --config <each of configs, then the model's
configs> --seed_everything <seed> --trainer.logger... <overrides>`: the files stack in that order (a
later file wins key by key), then the sweep's `overrides` merged with the model's (the model's win) as
`--dotted.key value` arguments (`ggns.config.command_line`), which win over every file. A sweep file may
extend another (`base: <sweep file>`, `ggns.config.base_chain`): its keys over the base's, `models`
replaced whole when it has them.

Each metric family of a run is tested with the checkpoint selected on that family
(`ggns.evaluation.selection`; `Run.checkpoints`): one `test` per distinct checkpoint, computing
only the metrics of the families it was selected for (`TestPart`, in
<output>/<model>/seed_<s>_test/<checkpoint name>/), then merged into
<output>/<model>/seed_<s>_test/test_metrics.{json,md}, whose "checkpoints" entry names, per
family, the checkpoint (global step, the scalar it was selected on) and any fallback.

A run is finished when that merged `test_metrics.json` exists; finished runs are skipped, a test
part whose `test_metrics.json` exists is not run again (nor the fit, which ended before it), and a
fit that left `last.ckpt` behind is resumed from it, so an interrupted sweep continues where it
stopped. `summarize` aggregates the finished runs into <output>/summary.{md,csv}. On a cluster,
`slurm_script` renders a job array with one task per run (`python -m ggns sweep --config ...
--task $SLURM_ARRAY_TASK_ID`).

`run_baselines` scores the baselines of `ggns.baselines.scores` on the sweep's test trajectories and
stores them beside its runs. It is configured by the sweep file's optional `baselines` section
(Alpha Shapes and initial-mesh generation: 2D datasets only; the static row: 2D and 3D):


    baselines:
      dataset: plate_small      # data preset whose test split is scored
      data_dir: null            # overrides the preset's directory
      max_trajectories: 9       # the first n test trajectories, as the runs' test (null: all)
      alpha_shapes: true
      static: true
      initial_mesh: [ggns, mgn] # sweep models rolled out from the generated mesh, each under its
                                # own test schedules (its fit's `evaluation.schedules`), each
                                # schedule with the checkpoint its family was tested with

Existing result files are kept (an interrupted sweep resumes); delete them to recompute.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Callable

from omegaconf import OmegaConf

from ..reports import markdown_table, metrics_markdown, write_json, write_text
from ..config import (LIGHTNING_KEYS, command_line, config_file, load_config, load_layered, merge_overrides,
                      old_form_error, resolve_preset, settings)
from ..data import DEFAULT_DATASET, SPLITS, split_path
from ..evaluation.schedules import PAPER_SCHEDULES, effective_schedules, parse_schedule
from ..evaluation.selection import (CHECKPOINT_KEY, CHECKPOINTS_KEY, FAMILY_CHECKPOINT, M10, ONE_STEP, candidates,
                                    checkpoint_glob, checkpoint_info, describe, metric_family)

# The orchestration (which runs and test parts, their processes, merging) imports neither Lightning nor the
# models (each fit and test it starts imports them itself), so a sweep process starts in the time torch takes
# to import. The data module, the models, the baselines and the figures are imported where they are used.


FIT_ENDED = "fit_ended"  # in a run's fit directory once its fit process returned 0


@dataclass(frozen=True)
class Selection:
    """The checkpoint a metric family is tested with; `note` says so when it is not the family's own best."""
    family: str
    checkpoint: Path
    note: str = ""


class _Tested:
    """Finished once its `test_dir` holds a test_metrics.json."""

    @property
    def metrics_path(self) -> Path:
        return self.test_dir / "test_metrics.json"

    @property
    def finished(self) -> bool:
        return self.metrics_path.is_file()


@dataclass(frozen=True)
class TestPart(_Tested):
    """One `test` of a run: a checkpoint, tested only on the metrics of `families` (the eval
    `schedules` among them, and m+10 if `m_plus_10`; the one-step MSE is always computed), logging
    to `test_dir`."""
    checkpoint: Path
    families: tuple[str, ...]
    schedules: tuple[str, ...]
    m_plus_10: bool
    test_dir: Path


@dataclass(frozen=True)
class Run(_Tested):
    """One fit (and its tests): `config` (a Lightning config), then the config files `configs` stacked
    after it, then the command-line `args` (the run's overrides, `ggns.config.command_line`)."""
    model: str
    seed: int
    config: str
    args: tuple[str, ...]
    output: Path
    configs: tuple[str, ...] = ()

    def setting(self, key: str):
        """The value of a Lightning setting (a dotted key, `data.dataset`) that the run's config files and
        arguments make (`ggns.config.settings`), None if none of them sets it."""
        files = [f for f in (self.config, *self.configs) if config_file(f).is_file()]  # each with its bases
        return settings(self.args, files).get(key)

    @property
    def fit_dir(self) -> Path:
        return self.output / self.model / f"seed_{self.seed}"

    @property
    def test_dir(self) -> Path:
        return self.output / self.model / f"seed_{self.seed}_test"

    def _cli(self, subcommand: str, version: str) -> list[str]:
        stacked = [part for path in self.configs for part in ("--config", path)]
        return [sys.executable, "-m", "ggns", subcommand, "--config", self.config, *stacked,
                "--seed_everything", str(self.seed),
                "--trainer.logger.init_args.save_dir", str(self.output),
                "--trainer.logger.init_args.name", self.model,
                "--trainer.logger.init_args.version", version, *self.args]

    def fit_command(self) -> list[str]:
        cmd = self._cli("fit", f"seed_{self.seed}")
        last = self.fit_dir / "checkpoints" / "last.ckpt"
        return cmd + (["--ckpt_path", str(last)] if last.is_file() else [])

    def test_command(self, part: TestPart) -> list[str]:
        version = f"seed_{self.seed}_test/{part.test_dir.name}"
        return self._cli("test", version) + [
            "--ckpt_path", str(part.checkpoint), "--evaluation.schedules", json.dumps(list(part.schedules)),
            "--evaluation.m_plus_10", str(part.m_plus_10).lower()]

    def _eval_settings(self) -> tuple[list[str], bool]:
        """The run's test settings, (schedules, m_plus_10): its fit's `evaluation:` group (in the config.yaml
        the fit saved beside its logs; fits from before the group: their checkpoint's `eval_schedules` and
        `test_m_plus_10` hyperparameters; neither: `TestEvaluation`'s defaults), as the model's effective
        schedules (a model without point clouds: "never" once)."""
        from ..checkpoints import read_checkpoint
        from ..graphs.connectivity import Connectivity

        directory = self.fit_dir / "checkpoints"
        path = next((p for p in [directory / "last.ckpt", *sorted(directory.glob("*.ckpt"))] if p.is_file()), None)
        if path is None:
            raise FileNotFoundError(f"{directory}: the fit of {self.model} seed {self.seed} left no checkpoint")
        checkpoint = read_checkpoint(path)
        hparams = checkpoint["hyper_parameters"]
        saved = self.fit_dir / "config.yaml"
        evaluation = dict(OmegaConf.load(saved).get("evaluation") or {}) if saved.is_file() else {}
        if "eval_schedules" in hparams:
            schedules, m_plus_10 = list(hparams["eval_schedules"]), bool(hparams.get("test_m_plus_10", True))
        else:
            schedules = list(evaluation.get("schedules") or PAPER_SCHEDULES)
            m_plus_10 = bool(evaluation.get("m_plus_10", True))
        connectivity = checkpoint.get("connectivity")
        uses_points = Connectivity.from_dict(connectivity).uses_points if connectivity is not None else True
        return [str(s) for s in effective_schedules(schedules, uses_points)], m_plus_10

    def checkpoints(self) -> dict[str, Selection]:
        """The checkpoint each metric family of the run's test is tested with (`selection`): the first
        of `selection.candidates(family)` with a best checkpoint (the newest best-<family>-*.ckpt),
        else the single best checkpoint of a fit from before per-family selection (best-epoch=N.ckpt),
        else last.ckpt. Families: the eval schedules' keys, m10 (if tested) and one_step."""
        schedules, m_plus_10 = self._eval_settings()
        directory = self.fit_dir / "checkpoints"

        def newest(pattern: str, keep=lambda path: True) -> Path | None:
            found = sorted((p for p in directory.glob(pattern) if keep(p)), key=lambda p: p.stat().st_mtime)
            return found[-1] if found else None

        legacy = newest("best-*.ckpt", lambda p: not FAMILY_CHECKPOINT.match(p.name))
        last = directory / "last.ckpt"
        families = [parse_schedule(s).key for s in schedules] + ([M10] if m_plus_10 else []) + [ONE_STEP]
        out = {}
        for family in dict.fromkeys(families):
            found = [(c, newest(checkpoint_glob(c))) for c in candidates(family)]
            used = next(((c, path) for c, path in found if path is not None), None)
            if used is not None:
                note = "" if used[0] == family or family == ONE_STEP else f"no best-{family} checkpoint: {used[0]}'s"
                out[family] = Selection(family, used[1], note)
            elif legacy is not None:
                out[family] = Selection(family, legacy, "no per-family best checkpoint: the fit's single best "
                                                        "(selected before per-family selection)")
            elif last.is_file():
                out[family] = Selection(family, last, "no best checkpoint (no validation ran): the last one")
            else:
                raise FileNotFoundError(f"{directory}: the fit of {self.model} seed {self.seed} left no checkpoint")
        return out

    def test_parts(self) -> list[TestPart]:
        """One `TestPart` per distinct checkpoint of `checkpoints`, in `<test_dir>/<checkpoint name>`."""
        schedules = {parse_schedule(s).key: s for s in self._eval_settings()[0]}
        groups: dict[Path, list[str]] = {}
        for family, selection in self.checkpoints().items():
            groups.setdefault(selection.checkpoint, []).append(family)
        return [TestPart(path, tuple(families), tuple(schedules[f] for f in families if f in schedules),
                         M10 in families, self.test_dir / path.stem) for path, families in groups.items()]

    def merge_tests(self) -> dict:
        """The finished test parts merged into the run's test metrics: each metric from the part of its
        family, plus CHECKPOINTS_KEY: {family: `checkpoint_info` + note + the metrics tested with it}."""
        selections = self.checkpoints()
        merged, checkpoints = {}, {}
        for part in self.test_parts():
            data = json.loads(part.metrics_path.read_text())
            info = checkpoint_info(part.checkpoint)
            for family in part.families:
                names = [m for m in data if m != CHECKPOINT_KEY and metric_family(m) == family]
                merged.update({m: data[m] for m in names})
                checkpoints[family] = {**info, "note": selections[family].note, "metrics": names}
        return {**merged, CHECKPOINTS_KEY: checkpoints}


def check_stack(source: str, spec: dict) -> None:
    """`configs` (a list of existing config files) and `overrides` (a mapping of Lightning keys) of a sweep,
    one of its models, a learning file's run or variant, checked; the former `args` (a list of command-line
    strings) is refused, naming the mapping that says the same."""
    if "args" in spec:
        raise old_form_error(f"{source}: `args`", spec["args"] or [])
    configs = spec.get("configs") or []
    if not isinstance(configs, list) or not all(isinstance(c, str) for c in configs):
        raise ValueError(f"{source}: `configs` must be a list of config files, got {configs!r}")
    for config in configs:
        if not config_file(config).is_file():
            raise FileNotFoundError(f"{source}: config {config} not found")
    overrides = spec.get("overrides") or {}
    if isinstance(overrides, list):
        raise old_form_error(f"{source}: `overrides`", overrides)
    if not isinstance(overrides, dict):
        raise ValueError(f"{source}: `overrides` must be a mapping of Lightning settings, got {overrides!r}")
    unknown = sorted({str(k).split(".")[0] for k in overrides} - set(LIGHTNING_KEYS))
    if unknown:
        raise ValueError(f"{source}: `overrides` has keys {unknown}, which are not Lightning's "
                         f"(known: {list(LIGHTNING_KEYS)})")


def load_sweep(name_or_path: str | Path, overrides: list[str] = ()) -> dict:
    """The sweep file (module docstring) over its bases, with `key=value` overrides, checked."""
    path = resolve_preset(name_or_path, "sweeps")
    cfg = OmegaConf.merge(load_layered(path, "sweeps", replace=("models",)), OmegaConf.from_dotlist(list(overrides)))
    sweep = OmegaConf.to_container(cfg, resolve=True)
    missing = [k for k in ("output", "seeds", "models") if k not in sweep]
    if missing:
        raise ValueError(f"{path}: sweep lacks {missing}")
    if not sweep["models"] or not sweep["seeds"]:
        raise ValueError(f"{path}: a sweep needs at least one model and one seed")
    check_stack(str(path), sweep)
    for name, spec in sweep["models"].items():
        if not isinstance(spec, dict) or "config" not in spec:
            raise ValueError(f"{path}: model {name!r} needs a `config` (a Lightning config file)")
        unknown = sorted(set(spec) - {"config", "configs", "overrides", "args"})
        if unknown:
            raise ValueError(f"{path}: model {name!r} has unknown keys {unknown} (a model has `config` and may have "
                             f"`configs` and `overrides`)")
        if not config_file(str(spec["config"])).is_file():
            raise FileNotFoundError(f"{path}: model {name!r}: config {spec['config']} not found")
        check_stack(f"{path}: model {name!r}", spec)
    unknown = [m for m in sweep.get("findings_ggns", []) if m not in sweep["models"]]
    if unknown:
        raise ValueError(f"{path}: findings_ggns names {unknown}, which are not models of the sweep "
                         f"(have {list(sweep['models'])})")
    if len(set(sweep["seeds"])) != len(sweep["seeds"]):
        raise ValueError(f"{path}: repeated seeds {sweep['seeds']}")
    return sweep


def runs_of(sweep: dict) -> list[Run]:
    """The grid in a fixed order (models as listed, then seeds): task i of a job array is runs[i]. A run's
    files: its model's config, the sweep's `configs`, the model's `configs`; its arguments: the sweep's
    `overrides` merged with the model's (module docstring)."""
    output = Path(sweep["output"])
    runs = []
    for name, spec in sweep["models"].items():
        configs = tuple(str(c) for c in [*(sweep.get("configs") or []), *(spec.get("configs") or [])])
        args = tuple(command_line(merge_overrides(sweep.get("overrides") or {}, spec.get("overrides") or {})))
        runs += [Run(name, int(seed), str(spec["config"]), args, output, configs) for seed in sweep["seeds"]]
    return runs


def checkpoints_markdown(checkpoints: dict[str, dict]) -> str:
    """The "checkpoints" entry of a merged test (`Run.merge_tests`) as a markdown table."""
    return markdown_table(["family", "tested checkpoint", "note"],
                          [(family, describe(info), info.get("note") or "") for family, info in checkpoints.items()]) + "\n"


class RunFailed(RuntimeError):
    """A fit or test that a sweep (or `bench learning`) ran as a subprocess ended with an error status;
    the message carries the subprocess's own `error: ...` line when it wrote one, and its log file."""

    @classmethod
    def of(cls, what: str, status: int, log_path: str | Path) -> RunFailed:
        lines = Path(log_path).read_text(errors="replace").splitlines() if Path(log_path).is_file() else []
        reason = next((line for line in reversed(lines) if line.startswith("error: ")), None)
        return cls(f"{what} failed (exit {status})" + (f": {reason.removeprefix('error: ')}" if reason else "")
                   + f"; see {log_path}")


Launch = Callable[[list[str], IO[str], dict[str, str]], int]
"""How a sweep or `bench learning` runs one `python -m ggns fit|test` command: (command, the open log file
that takes its stdout and stderr, its environment) -> its exit status (negative: killed by that signal)."""


def launch_process(command: list[str], out: IO[str], env: dict[str, str]) -> int:
    """The default `Launch`: `command` as its own process, waited for.

    Args:
        command: the full command line, `[sys.executable, "-m", "ggns", "fit" | "test", ...]`.
        out: the run's open log file; the process writes its stdout and stderr there.
        env: the process's whole environment (the sweep sets OMP_NUM_THREADS in it).

    Returns:
        the exit status: 0 on success, negative when a signal killed it.
    """
    return subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, env=env).returncode


def execute(run: Run, threads: int | None = None, log: Callable[[str], None] = print,
            launch: Launch = launch_process) -> Run:
    """fit (resuming a left-over last.ckpt) then the test parts, merged; a finished run is skipped,
    and so is the fit once it has ended (`FIT_ENDED`, written when its process returned 0) or a test
    part has finished (the fit ended before the tests began): a sweep killed during its tests does not
    start the fit's process again. `launch` runs each command (default: a process of its own)."""
    if run.finished:
        log(f"skip {run.model} seed {run.seed}: {run.metrics_path} exists")
        return run
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    run.fit_dir.mkdir(parents=True, exist_ok=True)
    with open(run.output / run.model / f"seed_{run.seed}.log", "a") as out:
        def call(step: str, command: list[str]) -> None:
            log(f"{step} {run.model} seed {run.seed}")
            out.flush()
            status = launch(command, out, env)
            if status != 0:
                out.flush()
                raise RunFailed.of(f"{step} of {run.model} seed {run.seed}", status, out.name)

        ended = run.fit_dir / FIT_ENDED
        if not ended.is_file() and not any(run.test_dir.glob("*/test_metrics.json")):
            call("fit", run.fit_command())
            ended.write_text("the fit's process returned 0; a rerun of the sweep does not fit again\n")
        for part in run.test_parts():
            if part.finished:
                log(f"skip test {run.model} seed {run.seed} {part.checkpoint.name}: {part.metrics_path} exists")
                continue
            call(f"test ({', '.join(part.families)} with {part.checkpoint.name})", run.test_command(part))
            if not part.finished:
                raise RuntimeError(f"test of {run.model} seed {run.seed} wrote no {part.metrics_path}")
    merged = run.merge_tests()
    metrics = {name: value for name, value in merged.items() if name != CHECKPOINTS_KEY}
    write_text(run.metrics_path.with_suffix(".md"),
        metrics_markdown(metrics, f"{run.model} seed {run.seed} test metrics") + "\n"
        + checkpoints_markdown(merged[CHECKPOINTS_KEY]))
    write_json(run.metrics_path, merged)
    return run


def prepare_datasets(runs: list[Run], log=print) -> list[str]:
    """Generate the missing split files of every dataset the runs name (`data.dataset`, `data.data_dir`, from
    their config files and arguments, `Run.setting`), once, before runs start in parallel: otherwise each run
    would generate the same files at once, and inside its fit's wall-clock budget. Returns the datasets checked."""
    checked = []

    def data_of(run: Run) -> tuple[str, str | None]:
        dataset = run.setting("data.dataset") or run.setting("data.init_args.dataset") or DEFAULT_DATASET
        data_dir = run.setting("data.data_dir") or run.setting("data.init_args.data_dir")
        return str(dataset), None if data_dir is None else str(data_dir)

    for dataset, data_dir in dict.fromkeys(data_of(r) for r in runs):
        directory = Path(data_dir if data_dir is not None else load_config(dataset)["output"])
        missing = [s for s in SPLITS if not split_path(directory, s).exists()]
        if missing:
            from ..data.module import SimulationDataModule

            module = SimulationDataModule(dataset=dataset, data_dir=data_dir)
            log(f"generate {dataset} {missing} into {module.data_dir}")
            module.prepare_data()
        checked.append(dataset)
    return checked


def run_sweep(sweep: dict, task: int | None = None, log: Callable[[str], None] = print,
              launch: Launch = launch_process) -> list[Run]:
    """All runs (`parallel` at once, after `prepare_datasets`) or only job-array task `task`, each command
    through `launch` (see `execute`).

    Args:
        sweep: a loaded sweep file (`load_sweep`).
        task: only this run (a SLURM array task's index into `runs_of(sweep)`); None: all of them.
        log: called with one line per fit, test and skip.
        launch: how each fit and test command runs (`Launch`; default `launch_process`).

    Returns:
        the runs executed (finished ones included, skipped), each with its merged test metrics written.
    """
    runs = runs_of(sweep)
    if task is not None:
        if not 0 <= task < len(runs):
            raise IndexError(f"task {task} outside the sweep's {len(runs)} runs")
        return [execute(runs[task], log=log, launch=launch)]
    prepare_datasets([r for r in runs if not r.finished], log)
    parallel = max(1, int(sweep.get("parallel", 1)))
    threads = max(1, (os.cpu_count() or 1) // parallel)
    with ThreadPoolExecutor(parallel) as pool:
        return list(pool.map(lambda r: execute(r, threads, log, launch), runs))


def slurm_script(sweep: dict, sweep_file: str | Path, partition: str | None = None, time: str = "24:00:00",
                 gpus: int = 1, cpus: int = 8) -> str:
    """A SLURM job-array script with one task per run of the sweep."""
    count = len(runs_of(sweep))
    lines = ["#!/bin/bash", "#SBATCH --job-name=ggns-sweep", f"#SBATCH --array=0-{count - 1}",
             f"#SBATCH --time={time}", f"#SBATCH --cpus-per-task={cpus}", "#SBATCH --ntasks=1",
             f"#SBATCH --output={Path(sweep['output']) / 'slurm-%A_%a.out'}",
             "#SBATCH --signal=SIGUSR1@90  # Lightning's SLURM support: checkpoint and requeue before the time limit"]
    if gpus:
        lines.append(f"#SBATCH --gres=gpu:{gpus}")
    if partition:
        lines.append(f"#SBATCH --partition={partition}")
    lines += ["", "# one run (model x seed) per array task; finished runs are skipped, so resubmitting resumes",
              f"srun .venv/bin/python -m ggns sweep --config {sweep_file} --task $SLURM_ARRAY_TASK_ID", ""]
    return "\n".join(lines)
