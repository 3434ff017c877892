"""Multi-seed sweeps: a grid of model configs x seeds, each run a Lightning `fit` then `test`
through the CLI in its own process, several at once, resumable.

A sweep file (conf/sweeps/<name>.yaml or a path) holds:
    output: lightning_logs/sweeps/plate     # runs go to <output>/<model>/seed_<s>[_test]
    seeds: [0, 1, 2]
    parallel: 2                             # runs at once on this machine
    args: ["--data.dataset", "plate_small"] # CLI arguments for every run
    models:                                 # name -> Lightning config (+ its own arguments)
      ggns: {config: conf/plate/ggns.yaml, args: []}
      mgn:  {config: conf/plate/mgn.yaml}

A run is finished when `<output>/<model>/seed_<s>_test/test_metrics.json` exists; finished runs
are skipped, and a fit that left `last.ckpt` behind is resumed from it, so an interrupted sweep
continues where it stopped. `summarize` aggregates the finished runs into <output>/summary.{md,csv}. On a cluster, `slurm_script` renders a job array with one task
per run (`python -m ggns sweep --config ... --task $SLURM_ARRAY_TASK_ID`).
"""
from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from omegaconf import OmegaConf

from ..config import resolve_preset
from .aggregate import RunResult, aggregate, load_run, normalized_benefit, to_csv, to_markdown
from .baselines import GENERATED_MESH_FILE
from .baselines import ROWS as BASELINE_ROWS
from .findings import check_findings, findings_markdown
from .figures import write_figures


@dataclass(frozen=True)
class Run:
    model: str
    seed: int
    config: str
    args: tuple[str, ...]
    output: Path

    @property
    def fit_dir(self) -> Path:
        return self.output / self.model / f"seed_{self.seed}"

    @property
    def test_dir(self) -> Path:
        return self.output / self.model / f"seed_{self.seed}_test"

    @property
    def metrics_path(self) -> Path:
        return self.test_dir / "test_metrics.json"

    @property
    def finished(self) -> bool:
        return self.metrics_path.is_file()

    def _cli(self, subcommand: str, version: str) -> list[str]:
        return [sys.executable, "-m", "ggns", subcommand, "--config", self.config, "--seed_everything", str(self.seed),
                "--trainer.logger.init_args.save_dir", str(self.output),
                "--trainer.logger.init_args.name", self.model,
                "--trainer.logger.init_args.version", version, *self.args]

    def fit_command(self) -> list[str]:
        cmd = self._cli("fit", f"seed_{self.seed}")
        last = self.fit_dir / "checkpoints" / "last.ckpt"
        return cmd + (["--ckpt_path", str(last)] if last.is_file() else [])

    def test_command(self) -> list[str]:
        return self._cli("test", f"seed_{self.seed}_test") + ["--ckpt_path", str(self.checkpoint())]

    def checkpoint(self) -> Path:
        """The fit's selected checkpoint (best on the validation rollout), else its last one."""
        directory = self.fit_dir / "checkpoints"
        best = sorted(directory.glob("best-*.ckpt"), key=lambda p: p.stat().st_mtime)
        if best:
            return best[-1]
        last = directory / "last.ckpt"
        if last.is_file():
            return last
        raise FileNotFoundError(f"{directory}: the fit of {self.model} seed {self.seed} left no checkpoint")


def load_sweep(name_or_path: str | Path, overrides: list[str] = ()) -> dict:
    path = resolve_preset(name_or_path, "sweeps")
    cfg = OmegaConf.merge(OmegaConf.load(path), OmegaConf.from_dotlist(list(overrides)))
    sweep = OmegaConf.to_container(cfg, resolve=True)
    missing = [k for k in ("output", "seeds", "models") if k not in sweep]
    if missing:
        raise ValueError(f"{path}: sweep lacks {missing}")
    if not sweep["models"] or not sweep["seeds"]:
        raise ValueError(f"{path}: a sweep needs at least one model and one seed")
    for name, spec in sweep["models"].items():
        if not isinstance(spec, dict) or "config" not in spec:
            raise ValueError(f"{path}: model {name!r} needs a `config` (a Lightning config file)")
        if not Path(spec["config"]).is_file():
            raise FileNotFoundError(f"{path}: model {name!r}: config {spec['config']} not found")
    if len(set(sweep["seeds"])) != len(sweep["seeds"]):
        raise ValueError(f"{path}: repeated seeds {sweep['seeds']}")
    return sweep


def runs_of(sweep: dict) -> list[Run]:
    """The grid in a fixed order (models as listed, then seeds): task i of a job array is runs[i]."""
    output, common = Path(sweep["output"]), tuple(str(a) for a in sweep.get("args", []))
    return [Run(name, int(seed), str(spec["config"]), common + tuple(str(a) for a in spec.get("args", [])), output)
            for name, spec in sweep["models"].items() for seed in sweep["seeds"]]


def execute(run: Run, threads: int | None = None, log=print) -> Run:
    """fit (resuming a left-over last.ckpt) then test; a finished run is skipped."""
    if run.finished:
        log(f"skip {run.model} seed {run.seed}: {run.metrics_path} exists")
        return run
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    run.fit_dir.mkdir(parents=True, exist_ok=True)
    with open(run.output / run.model / f"seed_{run.seed}.log", "a") as out:
        for step, command in (("fit", run.fit_command), ("test", run.test_command)):
            log(f"{step} {run.model} seed {run.seed}")
            result = subprocess.run(command(), stdout=out, stderr=subprocess.STDOUT, env=env)
            if result.returncode != 0:
                raise RuntimeError(f"{step} of {run.model} seed {run.seed} failed (exit {result.returncode}); "
                                   f"see {out.name}")
    if not run.finished:
        raise RuntimeError(f"test of {run.model} seed {run.seed} wrote no {run.metrics_path}")
    return run


def run_sweep(sweep: dict, task: int | None = None, log=print) -> list[Run]:
    """All runs (`parallel` at once) or only job-array task `task`. Returns the runs executed."""
    runs = runs_of(sweep)
    if task is not None:
        if not 0 <= task < len(runs):
            raise IndexError(f"task {task} outside the sweep's {len(runs)} runs")
        return [execute(runs[task], log=log)]
    parallel = max(1, int(sweep.get("parallel", 1)))
    threads = max(1, (os.cpu_count() or 1) // parallel)
    with ThreadPoolExecutor(parallel) as pool:
        return list(pool.map(lambda r: execute(r, threads, log), runs))


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


def _run_result(run: Run) -> RunResult:
    """A finished run's test metrics, with its generated-mesh baseline metrics when computed."""
    result = load_run(run.metrics_path, run.model, run.seed)
    extra = run.test_dir / GENERATED_MESH_FILE
    if extra.is_file():
        result.metrics.update(load_run(extra, run.model, run.seed).metrics)
    return result


# summary sections: (title, metric-name prefixes), in this order; other metrics go last
SECTIONS = (("Full-rollout MSE (point cloud every k steps)", ("rollout_mse_",)),
            ("One-step and m+10-step MSE", ("one_step_mse", "m10_mse")),
            ("Rollout IoU (true initial mesh)", ("rollout_iou_",)),
            ("Rollout IoU from a mesh generated from the first point cloud", ("generated_mesh_iou_",)))


def _sections(table) -> list[str]:
    metrics = list(dict.fromkeys(m for per_metric in table.values() for m in per_metric))
    lines, used = [], set()
    for title, prefixes in SECTIONS + (("Other metrics", None),):
        chosen = [m for m in metrics if m not in used and (prefixes is None or m.startswith(prefixes))]
        rows = {model: per_metric for model, per_metric in table.items() if any(m in per_metric for m in chosen)}
        if chosen and rows:
            used.update(chosen)
            lines += [f"## {title}", "", to_markdown(rows, chosen)]
    return lines


def _steps_logged(directory: Path) -> int | None:
    """The largest step of any scalar in the TensorBoard event files of a fit (its training length,
    to within `log_every_n_steps`; validation is logged at the step it ran), or None."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    steps = []
    for path in directory.glob("events.out.tfevents.*"):
        events = EventAccumulator(str(path), size_guidance={"scalars": 0, "images": 1})
        events.Reload()
        steps += [e.step for tag in events.Tags()["scalars"] for e in events.Scalars(tag)]
    return max(steps) if steps else None


def _training_markdown(runs: list[Run]) -> str:
    """Per run: optimizer steps and epoch of the tested checkpoint, and the steps the fit logged."""
    import torch

    lines = ["| model | seed | tested checkpoint | its steps / epoch | largest logged step of the fit |", "|---|---|---|---|---|"]
    for run in runs:
        logged = _steps_logged(run.fit_dir)
        logged = "-" if logged is None else str(logged)
        try:
            tested = run.checkpoint()
        except FileNotFoundError:  # checkpoints removed after testing
            lines.append(f"| {run.model} | {run.seed} | (removed) | - | {logged} |")
            continue
        checkpoint = torch.load(tested, map_location="cpu", weights_only=False)
        lines.append(f"| {run.model} | {run.seed} | {tested.name} | {checkpoint.get('global_step', '?')} / "
                     f"{checkpoint.get('epoch', '?')} | {logged} |")
    return "\n".join(lines) + "\n"


def summarize(sweep: dict, log=print) -> Path:
    """Aggregate the finished runs (and the baselines computed by `run_baselines`) into
    <output>/summary.md and summary.csv (mean +- std over seeds; the normalized benefit of
    point clouds when the sweep has `ggns` and `mgn`) plus figures."""
    finished = [r for r in runs_of(sweep) if r.finished]
    if not finished:
        raise FileNotFoundError(f"{sweep['output']}: no finished run to aggregate")
    output = Path(sweep["output"])
    results = [_run_result(r) for r in finished]
    for row in BASELINE_ROWS:
        path = output / row / "test_metrics.json"
        if path.is_file():
            results.append(load_run(path, row, 0))
    table = aggregate(results)
    to_csv(table, output / "summary.csv")
    lines = ["# Sweep summary", "", f"{len(finished)} of {len(runs_of(sweep))} runs finished; mean ± std over seeds "
             "(a single value where there is one seed or a deterministic baseline).", ""] + _sections(table)
    if "ggns" in table and "mgn" in table:
        try:
            benefit = normalized_benefit(table)
            lines += ["## Normalized benefit of point clouds (1 at k = 1, 0 at MGN)", "",
                      "| k | " + " | ".join(map(str, benefit)) + " |", "|---|" + "---|" * len(benefit),
                      "| benefit | " + " | ".join(f"{v:.3f}" for v in benefit.values()) + " |"]
        except ValueError as error:
            lines += ["", f"Normalized benefit not computed: {error}"]
    lines += ["", "## The paper's findings on this sweep", "", findings_markdown(check_findings(table))]
    lines += ["## Training of each run", "", _training_markdown(finished)]
    lines += [f"![{figure.stem}]({figure.name})" for figure in write_figures(table, output)]
    path = output / "summary.md"
    path.write_text("\n".join(lines) + "\n")
    log(f"wrote {path} and {output / 'summary.csv'}")
    return path
