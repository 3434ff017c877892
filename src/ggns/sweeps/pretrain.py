"""Making the shipped pretrained simulators (`ggns.pretrained`) from CPU-preset training runs.

`conf/pretrained.yaml` names each entry's sweep preset, model and checkpoint family. `train` runs
seed 0 of that preset's model with the preset's own command (`python -m ggns sweep --config <sweep>
seeds=[0] output=<output>/<task> --task <i>`); `package` cuts the run's best checkpoint of the
family down to what a simulator needs (weights, normalizer statistics, hyperparameters: no
optimizer state), evaluates the cut file on the first test trajectories of the run's data, and
writes the manifest that `ggns.pretrained` checks on every load.
"""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import torch
from omegaconf import OmegaConf

from ..batch import TrajectoryBatch
from ..checkpoints import CHECKPOINT_FORMAT, FORMAT_KEY, read_checkpoint, sha256
from ..config import CONF_DIR, command_line
from ..data.module import SimulationDataModule
from ..data.schema import SCHEMA_VERSION, SplitReader, content_hash
from ..evaluation.evaluate import MetricTable, evaluate_model
from ..evaluation.selection import checkpoint_glob, checkpoint_info
from ..models.loading import load_simulator
from .. import pretrained
from ..reports import write_json
from .curves import read_scalars
from .sweep import Run, load_sweep, runs_of

SPEC = CONF_DIR / "pretrained.yaml"
# what a shipped checkpoint keeps of a Lightning checkpoint (`python -m ggns test --ckpt_path` needs no more)
KEPT = ("epoch", "global_step", "pytorch-lightning_version", "state_dict", "hparams_name", "hyper_parameters",
        "connectivity", "simulator_class", "scene")


def load_spec(path: str | Path = SPEC) -> dict:
    return OmegaConf.to_container(OmegaConf.load(path), resolve=True)


def entry_run(name: str, spec: dict) -> tuple[Run, int, list[str]]:
    """(the sweep run, its task index, the sweep overrides) that trains entry `name`; the entry's
    `overrides` (a mapping of Lightning settings, nested or with dotted keys such as `trainer.max_time`)
    go after the sweep's (`ggns.config.command_line`)."""
    if name not in spec["entries"]:
        raise ValueError(f"no pretrained entry {name!r} in {SPEC}; entries: {', '.join(spec['entries'])}")
    entry, task = spec["entries"][name], name.split("/")[0]
    overrides = ["seeds=[0]", f"output={spec['output']}/{task}"]
    runs = runs_of(load_sweep(entry["sweep"], overrides))
    index = next((i for i, r in enumerate(runs) if r.model == entry["model"]), None)
    if index is None:
        raise ValueError(f"sweep {entry['sweep']!r} has no model {entry['model']!r}")
    run = runs[index]
    extra = tuple(command_line(entry.get("overrides") or {}))
    return dataclasses.replace(run, args=run.args + extra), index, overrides


def train_command(name: str, spec: dict, resume: bool = False) -> list[str]:
    """The fit of entry `name`: the sweep run's own fit command (`Run.fit_command`; with `resume`, from
    the run's last.ckpt when there is one)."""
    command = entry_run(name, spec)[0].fit_command()
    if not resume and "--ckpt_path" in command:
        command = command[:command.index("--ckpt_path")]
    return ["python", *command[1:]]


def train(name: str, spec: dict | None = None) -> Run:
    """Fit (or resume) the training run of entry `name` with one torch thread, as the CPU presets run
    two fits at once on 2 cores (the sweep's tests of the run are not needed: `package` evaluates)."""
    spec = spec or load_spec()
    run = entry_run(name, spec)[0]
    command = train_command(name, spec, resume=True)
    print(" ".join(command))
    run.fit_dir.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, *command[1:]], check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return run


def _git_commit(directory: Path) -> str | None:
    result = subprocess.run(["git", "-C", str(directory), "rev-parse", "HEAD"], capture_output=True, text=True)
    return result.stdout.strip() or None if result.returncode == 0 else None


def _source_checkpoint(run: Run, family: str) -> Path:
    found = sorted((run.fit_dir / "checkpoints").glob(checkpoint_glob(family)), key=os.path.getmtime)
    if not found:
        raise FileNotFoundError(f"{run.fit_dir}/checkpoints holds no {checkpoint_glob(family)}: train it first "
                                f"(python -m ggns pretrained train)")
    return found[-1]


def cut_checkpoint(source: Path, target: Path) -> None:
    """Write `source` without optimizer, loop and callback state (`KEPT`), atomically."""
    checkpoint = read_checkpoint(source)
    cut = {key: checkpoint[key] for key in KEPT if key in checkpoint}
    cut[FORMAT_KEY] = CHECKPOINT_FORMAT
    target.parent.mkdir(parents=True, exist_ok=True)
    temporary = target.with_name(f".{target.name}.partial-{os.getpid()}")
    torch.save(cut, temporary)
    os.replace(temporary, target)


def test_metrics(model, data: SimulationDataModule, count: int) -> dict:
    """The paper's metrics of `model` on the first `count` test trajectories, all at once:
    {"trajectories", "seconds", "metrics": {name: {mean, std, count}}, "per_trajectory": {name: [..]}}."""
    trajectories = data.trajectories("test")[:count]
    start = time.perf_counter()
    per_trajectory = evaluate_model(model, TrajectoryBatch.from_trajectories(trajectories), m_plus_10=True, iou=True)
    table = MetricTable()
    table.add(per_trajectory)
    return {"trajectories": len(trajectories), "seconds": round(time.perf_counter() - start, 1),
            "metrics": table.summary(), "per_trajectory": {k: v.tolist() for k, v in per_trajectory.items()}}


def validation_curves(scalars: dict) -> dict[str, list[list[float]]]:
    """Every val/ scalar of a run's TensorBoard logs (`read_scalars`): tag -> [[step, value], ...]."""
    return {tag: [[float(s), float(v)] for s, v in zip(steps, values)]
            for tag, (steps, _, values) in scalars.items() if tag.startswith("val/")}


def package(name: str, spec: dict | None = None) -> Path:
    """Cut entry `name`'s checkpoint into the registry, evaluate it and write its manifest."""
    spec = spec or load_spec()
    run, index, overrides = entry_run(name, spec)
    entry = spec["entries"][name]
    source = _source_checkpoint(run, entry["family"])
    target = pretrained.REGISTRY / f"{name}.ckpt"
    cut_checkpoint(source, target)
    model = load_simulator(target, map_location="cpu")
    hparams = read_checkpoint(source)["datamodule_hyper_parameters"]
    data = SimulationDataModule(hparams["dataset"], data_dir=hparams.get("data_dir"), generate_missing=False)
    with SplitReader(data.path("train")) as train_split:
        generator_config, train_count = train_split.generator_config, len(train_split)
    info = checkpoint_info(source)
    last = run.fit_dir / "checkpoints" / "last.ckpt"  # the fit's newest state: the optimizer steps it ran
    fit_steps = max(int(checkpoint_info(last)["global_step"]) if last.is_file() else 0, int(info["global_step"]))
    scalars = read_scalars(run.fit_dir)
    walls = [wall for _, w, _ in scalars.values() for wall in w]
    manifest = {
        "name": name, "task": name.split("/")[0], "model": name.split("/")[1], "class": type(model).__name__,
        "file": target.name, "sha256": sha256(target), "bytes": target.stat().st_size, "format": CHECKPOINT_FORMAT,
        "parameters": sum(p.numel() for p in model.parameters()),
        "trained_by": {"command": " ".join(train_command(name, spec)), "sweep": f"{entry['sweep']}: {entry['model']} seed 0",
                       "commit": _git_commit(run.output), "optimizer_steps": fit_steps,
                       "fit_started": _utc(min(walls)) if walls else None,
                       "fit_finished": _utc(max(walls)) if walls else None,
                       "machine": f"{os.cpu_count()} CPU cores (the packaging machine's count)"},
        "source": {"checkpoint": info["name"], "family": entry["family"], "selected_on": info["selected_on"],
                   "score": info["score"], "global_step": info["global_step"], "epoch": info["epoch"]},
        "data": {"preset": hparams["dataset"], "dim": data.dim, "schema_version": SCHEMA_VERSION,
                 "config": {k: generator_config.get(k) for k in ("scene", "solver", "sensor", "seed")},
                 "train_trajectories": train_count, "train_content_sha256": content_hash(data.path("train"))},
        "hyper_parameters": {k: v for k, v in model.hparams.items() if not k.startswith("_")},
        "validation": validation_curves(scalars),
        "test": {"command": f"python -m ggns pretrained package --name {name}",
                 "packaged_with_commit": _git_commit(Path(__file__).parent), "split": "test",
                 **test_metrics(model, data, entry.get("test_trajectories", spec["test_trajectories"]))},
    }
    path = write_json(pretrained.REGISTRY / f"{name}.json", manifest)
    print(f"wrote {target} ({manifest['bytes'] / 1024:.0f} KB) and {path}")
    return path


def _utc(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, timezone.utc).isoformat(timespec="seconds")
