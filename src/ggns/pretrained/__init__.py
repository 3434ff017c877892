"""Pretrained simulators shipped with the library, loaded by name: `ggns.pretrained.load("plate/ggns")`.

Each entry is two files in this folder, `<task>/<model>.ckpt` and its manifest `<task>/<model>.json`:
the checkpoint holds the weights, normalizer statistics and hyperparameters only (a Lightning
checkpoint without optimizer state, readable by `python -m ggns test --ckpt_path ...`), and the
manifest says how it was made and what it scores (written by `ggns.sweeps.pretrain`):

    name, task, model, class          "plate/ggns", "plate", "ggns", "GGNS"
    file, sha256, bytes               the checkpoint file and its hash (checked on every load)
    format                            the ggns checkpoint format (`ggns.checkpoints.CHECKPOINT_FORMAT`)
    trained_by                        the exact command, commit and times of the training run
    source                            the training run's checkpoint it was cut from (step, selection metric)
    data                              the data preset, schema version, its scene/solver/sensor config and a
                                      content hash of the training split
    validation                        the validation curves of the training run (step, value)
    test                              the command that evaluated the shipped file, the test trajectories
                                      and the metrics (mean, std and per trajectory)

Loading refuses, with the reason: a file whose sha256 differs from its manifest (tampered or
corrupted), a checkpoint format other than this code's, a checkpoint that is not data-only
(`ggns.checkpoints`), and (`check_data`) a dataset whose scene, solver or sensor configuration
differs from the training data's, since the model's normalizers and radii only mean something there.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from ..checkpoints import CHECKPOINT_FORMAT, CheckpointError, sha256
from ..data.schema import SCHEMA_VERSION, config_differences

if TYPE_CHECKING:
    import torch
from ..models.graph_simulator import GraphSimulator
from ..models.loading import load_simulator

REGISTRY = Path(__file__).resolve().parent
PREFIX = "pretrained:"  # `--ckpt_path pretrained:plate/ggns` in the Lightning CLI


class PretrainedError(CheckpointError):
    """A pretrained simulator that is missing, tampered with or does not fit the data or the code."""


def names() -> list[str]:
    """Every shipped simulator, "<task>/<model>", sorted."""
    return sorted(f"{p.parent.name}/{p.stem}" for p in REGISTRY.glob("*/*.json"))


def manifest_path(name: str) -> Path:
    name = name.removeprefix(PREFIX)
    path = REGISTRY / f"{name}.json"
    if name.count("/") != 1 or not path.is_file():
        raise PretrainedError(f"no pretrained simulator {name!r}; shipped: {', '.join(names()) or 'none'}")
    return path


def manifest(name: str) -> dict:
    """The manifest of a shipped simulator (module docstring)."""
    return json.loads(manifest_path(name).read_text())


def training_budget(manifest: dict) -> dict:
    """What a shipped simulator's training run was given and used, from its manifest: `optimizer_steps` (the
    optimizer steps its fit ran: the manifest's `trained_by.optimizer_steps`, the run's last checkpoint's step,
    where packaging wrote it, else `last_validation_step`: a fit stopped by its wall-clock budget validates at its
    last step, as those of the files packaged before the steps were recorded did; one stopped by `max_steps` need
    not, so packaging records them),
    `max_time_minutes` (the fit's wall-clock budget, its command's last `--trainer.max_time`; None without
    one), `max_steps` (its command's last `--trainer.max_steps`; None without one), `fit_minutes` (its
    first to last logged event), `last_validation_step` (the newest step of its validation curves) and
    `selected_step` (the step of the checkpoint shipped)."""
    import re
    from datetime import datetime

    trained = manifest.get("trained_by") or {}
    command = trained.get("command") or ""
    given = re.findall(r"--trainer\.max_time[ =](\S+)", command)  # the last one wins, as on the command line
    parts = re.fullmatch(r"(\d+):(\d+):(\d+):(\d+)", given[-1]) if given else None
    budget = None
    if parts:
        days, hours, minutes, seconds = (int(v) for v in parts.groups())
        budget = days * 1440 + hours * 60 + minutes + seconds / 60
    fit = None
    if trained.get("fit_started") and trained.get("fit_finished"):
        fit = (datetime.fromisoformat(trained["fit_finished"]) -
               datetime.fromisoformat(trained["fit_started"])).total_seconds() / 60
    max_steps = re.findall(r"--trainer\.max_steps[ =](\d+)", command)
    steps = [int(step) for curve in (manifest.get("validation") or {}).values() for step, _ in curve]
    last_validation = int(max(steps)) if steps else None
    optimizer_steps = trained.get("optimizer_steps", last_validation)
    return {"optimizer_steps": optimizer_steps, "max_time_minutes": budget,
            "max_steps": int(max_steps[-1]) if max_steps else None, "fit_minutes": fit,
            "last_validation_step": last_validation, "selected_step": (manifest.get("source") or {}).get("global_step")}


def budget_text(manifest: dict) -> str:
    """A shipped simulator's training budget in words: the optimizer steps its fit ran, with the wall-clock
    budget it was given when it had one ("28,111 steps (40 min budget)"), or "-" when the manifest tells neither."""
    budget = training_budget(manifest)
    steps = budget["optimizer_steps"]
    minutes = budget["max_time_minutes"]
    if steps is None:
        return f"{minutes:.0f} min budget" if minutes is not None else "-"
    return f"{steps:,} steps" + (f" ({minutes:.0f} min budget)" if minutes is not None else "")


def checkpoint_path(name: str) -> Path:
    """The checkpoint file of a shipped simulator, checked against its manifest (`verify`)."""
    return verify(name)[1]


def verify(name: str) -> tuple[dict, Path]:
    """(manifest, checkpoint path) after checking the file's sha256 and the checkpoint format."""
    entry = manifest(name)
    path = manifest_path(name).parent / entry["file"]
    if not path.is_file():
        raise PretrainedError(f"pretrained {name}: its checkpoint {path} is missing")
    digest = sha256(path)
    if digest != entry["sha256"]:
        raise PretrainedError(f"pretrained {name}: {path} has sha256 {digest[:12]}..., its manifest says "
                              f"{entry['sha256'][:12]}...: the file was changed or corrupted; refusing to use it")
    if entry.get("format") != CHECKPOINT_FORMAT:
        raise PretrainedError(f"pretrained {name} is checkpoint format {entry.get('format')!r}, this code reads "
                              f"format {CHECKPOINT_FORMAT}: it was made by another version of ggns")
    return entry, path


def load(name: str, map_location: str | torch.device = "cpu") -> GraphSimulator:
    """A shipped simulator in eval mode, verified (`verify`); its manifest is `model.manifest`.

    Args:
        name: "<task>/<model>", one of `names()` (e.g. "plate/ggns", "tissue/mgn_m").
        map_location: where the weights go ("cpu", "cuda", a torch.device).

    Returns:
        the simulator (a `GraphSimulator` subclass, e.g. `GGNS`), its sha256 and class checked against
        the manifest (`PretrainedError` otherwise).
    """
    entry, path = verify(name)
    model = load_simulator(path, map_location=map_location)
    if type(model).__name__ != entry["class"]:
        raise PretrainedError(f"pretrained {name}: the checkpoint holds a {type(model).__name__}, "
                              f"its manifest says {entry['class']}")
    model.manifest = entry
    return model


def load_model(spec: str | Path, map_location: str | torch.device = "cpu") -> GraphSimulator:
    """A simulator from a pretrained name ("plate/ggns", "pretrained:plate/ggns") or a .ckpt path.

    Args:
        spec: a shipped simulator's name, with or without the "pretrained:" prefix, or the path of a
            checkpoint this library wrote (read as data only, `ggns.checkpoints`).
        map_location: where the weights go.

    Returns:
        the simulator in eval mode.
    """
    text = str(spec)
    if text.startswith(PREFIX) or (not Path(text).exists() and text.count("/") == 1 and not text.endswith(".ckpt")):
        return load(text, map_location)
    name = shipped_name(text)
    return load(name, map_location) if name else load_simulator(text, map_location=map_location)


def shipped_name(path: str | Path) -> str | None:
    """"<task>/<model>" if `path` is a shipped checkpoint file of this registry, else None."""
    path = Path(path).resolve()
    if path.suffix == ".ckpt" and path.parent.parent == REGISTRY:
        return f"{path.parent.name}/{path.stem}"
    return None


def check_data(name: str, generator_config: dict | None, dim: int | None = None, source: str = "the data") -> None:
    """Refuse data a shipped simulator was not trained for: another dimension, another schema
    version, or (for data made by ggns' generator) a scene, solver or sensor configuration that
    differs from the training data's, naming the differing keys. Data without a generator config
    (imported or a user's own) is checked for its dimension only."""
    entry = manifest(name)
    data = entry["data"]
    if dim is not None and dim != data["dim"]:
        raise PretrainedError(f"pretrained {name} simulates {data['dim']}D scenes, {source} is {dim}D")
    if generator_config is None:
        return
    if data["schema_version"] != SCHEMA_VERSION:
        raise PretrainedError(f"pretrained {name} was trained on dataset schema {data['schema_version']}, "
                              f"this code reads schema {SCHEMA_VERSION}")
    differences = config_differences(generator_config, data["config"])
    if differences:
        raise PretrainedError(f"pretrained {name} was trained on the {data['preset']!r} scene, {source} differs: "
                              + "; ".join(differences[:6]) + (" ..." if len(differences) > 6 else ""))
