"""Learning per CPU-second (`python -m ggns bench learning`): how fast named variants of one model
config learn within the same wall-clock budget, from their TensorBoard curves.

A learning file (conf/learning/<name>.yaml, a checkout's experiments/<experiment>/learning/<name>.yaml, or a path) holds:
    output: lightning_logs/learning/plate_ggns  # a variant logs to <output>/<variant>/seed_<seed>
    minutes: 10                                 # wall-clock budget per variant (trainer.max_time)
    val_every: 100                              # optimizer steps between validations
    seed: 0
    parallel: 2                                 # variants at once (torch threads = cores / parallel)
    run:                                        # what every variant fits
      config: conf/plate/ggns.yaml              # its Lightning config
      configs: [conf/profiles/eval_9.yaml]      # optional: config files stacked after it
      overrides: {data: {dataset: plate_small}} # optional: Lightning settings, a mapping of their keys
    variants:                                   # name -> what it changes, in one of two forms:
      paper: {}                                 # a mapping of Lightning settings (over the run's), or
      noise_0.005: {model: {init_args: {noise: {std: 0.005}}}}
      mgn: {config: conf/plate/mgn.yaml, configs: [], overrides: {}}  # {config, configs, overrides}

A variant's mapping either holds Lightning keys (seed_everything, trainer, model, data, evaluation) or
only `config`, `configs` and `overrides` (its own model config instead of the run's, config files after
the run's, settings over the run's), never both; a list of command-line strings (the former form) is
refused naming the mapping that says the same. `{config: ...}` fits another model config with the run's
files and settings and then its own, so different models (GGNS beside MGN) learn side by side within one
budget.

A file may start from another with `base: <learning file>` (`ggns.config.base_chain`): the base's keys,
then the file's own on top, except `variants`, which the file replaces whole when it has them (so a
companion run names only what differs: another seed, one more variant beside the base's).

Each variant is one `python -m ggns fit` in its own process (`sweep.Run` builds the command): its config,
the run's and its own config files, then the budget and validation arguments, then the run's and the
variant's settings merged (the variant's win; `ggns.config.command_line`), plus a `TrainingClock` callback
(`ggns.callbacks.clock`). A variant is finished when its fit exited cleanly
(`<run>/learning_finished.json`, which records the settings it ran with); finished variants are skipped
(an error if their settings differ from the file's now), an interrupted one resumes from its
`last.ckpt`. `write_report` then reads the event files and writes <output>/learning.md,
learning.csv, curves_steps.png and curves_seconds.png.
"""
from __future__ import annotations

import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Sequence

from omegaconf import OmegaConf

from ..config import LIGHTNING_KEYS, command_line, config_file, load_layered, merge_overrides, old_form_error, resolve_preset
from ..config import settings as settings_of
from ..reports import write_csv, write_json
from .curves import (CLOCK, COLUMNS, LATE_STEPS, RATIO_THRESHOLD, VALIDATION_COLUMNS, markdown_rows, plot_curves,
                     read_scalars, validation_markdown, validation_rows, variant_row)
from .sweep import Launch, Run, RunFailed, check_stack, launch_process

FINISHED = "learning_finished.json"


# ---- the variants ---------------------------------------------------------------------------------
STRUCTURED = ("config", "configs", "overrides")  # the keys of a variant that is not a mapping of settings


def variant_spec(spec: dict, name: str, source: str = "learning file") -> dict:
    """Variant `name` as {config (None: the run's), configs, overrides}, from either of its forms (module
    docstring); anything else is a ValueError naming `source` and the variant."""
    variant = spec["variants"][name]
    where = f"{source}: variant {name!r}"
    if variant is None:
        variant = {}
    if isinstance(variant, list):
        raise old_form_error(where, variant, example=name)
    if not isinstance(variant, dict):
        raise ValueError(f"{where} must be a mapping of Lightning settings or {{config, configs, overrides}}, "
                         f"got {variant!r}")
    if "args" in variant:
        raise old_form_error(f"{where}: `args`", variant["args"] or [], example="overrides")
    keys = {str(k) for k in variant}
    structured = keys & set(STRUCTURED)
    settings = {k for k in keys if k.split(".")[0] in LIGHTNING_KEYS}
    unknown = sorted(keys - structured - settings)
    if unknown or (structured and settings):
        raise ValueError(f"{where} has keys {sorted(keys)}: a variant is either a mapping of Lightning settings "
                         f"(keys among {list(LIGHTNING_KEYS)}) or one of {{config, configs, overrides}}"
                         + (f" (unknown keys: {unknown})" if unknown else " (not both)"))
    if not structured:
        return {"config": None, "configs": [], "overrides": variant}
    check_stack(where, variant)
    if "config" in variant and not config_file(str(variant["config"])).is_file():
        raise FileNotFoundError(f"{where}: its config {variant['config']} not found")
    return {"config": variant.get("config"), "configs": list(variant.get("configs") or []),
            "overrides": variant.get("overrides") or {}}


def load_learning(name_or_path: str | Path, overrides: Sequence[str] = ()) -> dict:
    """The learning file (module docstring) over its bases, with `key=value` overrides, checked."""
    path = resolve_preset(name_or_path, "learning")
    spec = OmegaConf.to_container(OmegaConf.merge(load_layered(path, "learning", replace=("variants",)),
                                                  OmegaConf.from_dotlist(list(overrides))), resolve=True)
    missing = [k for k in ("output", "minutes", "val_every", "run", "variants") if k not in spec]
    if missing:
        raise ValueError(f"{path}: learning file lacks {missing}")
    run = spec["run"]
    if not isinstance(run, dict) or "config" not in run:
        raise ValueError(f"{path}: `run` needs a `config` (a Lightning config file)")
    unknown = sorted(set(run) - set(STRUCTURED) - {"args"})
    if unknown:
        raise ValueError(f"{path}: `run` has unknown keys {unknown} (it has `config` and may have `configs` and "
                         f"`overrides`)")
    check_stack(f"{path}: `run`", run)
    if not config_file(str(run["config"])).is_file():
        raise FileNotFoundError(f"{path}: the run's config {run['config']} not found")
    if not isinstance(spec["variants"], dict) or not spec["variants"]:
        raise ValueError(f"{path}: `variants` must map at least one name to what it changes")
    for name in spec["variants"]:
        variant_spec(spec, name, str(path))
        if not name or "/" in name or name.startswith("."):
            raise ValueError(f"{path}: variant name {name!r} is not a directory name")
    if not float(spec["minutes"]) > 0:
        raise ValueError(f"{path}: minutes must be > 0, got {spec['minutes']}")
    if int(spec["val_every"]) < 1:
        raise ValueError(f"{path}: val_every must be >= 1 optimizer steps, got {spec['val_every']}")
    return spec


def max_time(minutes: float) -> str:
    """Lightning's `trainer.max_time` string DD:HH:MM:SS for a budget in minutes (whole seconds, at least 1)."""
    seconds = max(1, round(float(minutes) * 60))
    return f"{seconds // 86400:02d}:{seconds // 3600 % 24:02d}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def variant_config(spec: dict, name: str) -> tuple[str, list[str], list[str]]:
    """The variant's model config (its own or the run's), its config files (the run's, then its own) and its
    arguments (the run's settings merged with its own, as `--key value`)."""
    variant, run = variant_spec(spec, name), spec["run"]
    configs = [str(c) for c in [*(run.get("configs") or []), *variant["configs"]]]
    args = command_line(merge_overrides(run.get("overrides") or {}, variant["overrides"]))
    return str(variant["config"] or run["config"]), configs, args


def variant_change(spec: dict, name: str) -> list[str]:
    """The report's `change` column: the variant's own config and files (`--config X`) and settings."""
    variant = variant_spec(spec, name)
    files = [variant["config"]] if variant["config"] else []
    return ([part for path in [*files, *variant["configs"]] for part in ("--config", str(path))]
            + command_line(variant["overrides"]))


def variant_runs(spec: dict) -> list[Run]:
    """One fit per variant, in the file's order."""
    budget = ["--trainer.max_time", max_time(spec["minutes"]), "--trainer.max_epochs", "-1",
              "--trainer.val_check_interval", str(int(spec["val_every"])),
              "--trainer.check_val_every_n_epoch", "null",
              "--trainer.callbacks+=ggns.callbacks.TrainingClock"]
    configs = {name: variant_config(spec, name) for name in spec["variants"]}
    return [Run(name, int(spec.get("seed", 0)), config, tuple(budget + args), Path(spec["output"]), tuple(files))
            for name, (config, files, args) in configs.items()]


def run_settings(run: Run) -> dict:
    """The settings a variant's fit runs with beside its model config: its config files', then its
    arguments' (`ggns.config.settings`), as JSON keeps them."""
    return json.loads(json.dumps(settings_of(run.args, run.configs)))


def fit_variant(run: Run, threads: int | None = None, log=print, launch: Launch = launch_process) -> Run:
    """The variant's fit through `launch` (default: its own process; resuming a left-over last.ckpt);
    skipped when finished with the same arguments, an error when finished with others."""
    marker = run.fit_dir / FINISHED
    if marker.is_file():
        done = json.loads(marker.read_text())
        # the settings it ran with (a marker written before config files were stacked: those its arguments made)
        ran = done["settings"] if "settings" in done else json.loads(json.dumps(settings_of(done["args"])))
        now = run_settings(run)
        if ran != now or done.get("config", run.config) != run.config:
            changed = sorted(k for k in set(ran) | set(now) if ran.get(k, "(unset)") != now.get(k, "(unset)"))
            raise ValueError(f"variant {run.model!r} finished with other arguments than now ({marker}: "
                             + (", ".join(f"{k}: {ran.get(k, '(unset)')!r} then, {now.get(k, '(unset)')!r} now"
                                          for k in changed) or f"config {done.get('config')}") +
                             f"); delete {run.fit_dir} or rename the variant")
        log(f"skip {run.model}: {marker} exists")
        return run
    run.fit_dir.mkdir(parents=True, exist_ok=True)
    log(f"fit {run.model}")
    start = time.perf_counter()
    with open(run.output / run.model / f"seed_{run.seed}.log", "a") as out:
        status = launch(run.fit_command(), out, {**os.environ, **({"OMP_NUM_THREADS": str(threads)} if threads else {})})
    if status != 0:
        raise RunFailed.of(f"fit of variant {run.model}", status, out.name)
    write_json(marker, {"config": run.config, "configs": list(run.configs), "args": list(run.args),
                        "settings": run_settings(run), "process_seconds": time.perf_counter() - start})
    return run


def run_learning(spec: dict, only: Sequence[str] | None = None, log: Callable[[str], None] = print,
                 launch: Launch = launch_process) -> Path:
    """Fit the variants (`only` these names, else all; `parallel` at once; each through `launch`, see
    `fit_variant`), then `write_report`.

    Args:
        spec: a loaded learning file (`load_learning`).
        only: names of the variants to fit; None: all.
        log: called with one line per fit and skip.
        launch: how each fit command runs (`ggns.sweeps.sweep.Launch`; default its own process).

    Returns:
        the report's path, <output>/learning.md.
    """
    runs = variant_runs(spec)
    if only:
        unknown = sorted(set(only) - {r.model for r in runs})
        if unknown:
            raise ValueError(f"unknown variants {unknown} (known: {[r.model for r in runs]})")
        runs = [r for r in runs if r.model in only]
    parallel = max(1, int(spec.get("parallel", 1)))
    threads = max(1, (os.cpu_count() or 1) // parallel)
    with ThreadPoolExecutor(parallel) as pool:
        list(pool.map(lambda r: fit_variant(r, threads, log, launch), runs))
    return write_report(spec, log=log)


def write_report(spec: dict, log=print) -> Path:
    """learning.md, learning.csv and the two curve figures in the spec's output, from the event
    files of every variant that logged anything (finished or not)."""
    output = Path(spec["output"])
    runs = [r for r in variant_runs(spec) if r.fit_dir.is_dir()]
    if not runs:
        raise FileNotFoundError(f"{output}: no variant has run yet")
    curves = {r.model: read_scalars(r.fit_dir) for r in runs}
    rows = [variant_row(r.model, variant_change(spec, r.model), curves[r.model]) for r in runs]
    write_csv(output / "learning.csv", rows, COLUMNS)
    validations = [row for r in runs for row in validation_rows(r.model, curves[r.model])]
    write_csv(output / "learning_validations.csv", validations, VALIDATION_COLUMNS)
    figures = [plot_curves(curves, output / f"curves_{x}.png", x) for x in ("steps", "seconds")]
    finished = [r.model for r in runs if (r.fit_dir / FINISHED).is_file()]
    clocked = [r.model for r in runs if CLOCK in curves[r.model]]
    run = spec["run"]
    files = " ".join(f"--config {path}" for path in [run["config"], *(run.get("configs") or [])])
    lines = ["# Learning per CPU-second", "",
             f"Run: `{files}` with `{' '.join(command_line(run.get('overrides') or {})) or '(no settings)'}`; "
             f"seed {spec.get('seed', 0)}; budget {spec['minutes']} min of wall-clock per variant "
             f"(`trainer.max_time`, validation included); validation every {spec['val_every']} optimizer steps; "
             f"{spec.get('parallel', 1)} variant(s) at once. Finished: {len(finished)} of {len(spec['variants'])} "
             f"variants ({', '.join(finished) or 'none'}).", "",
             "Training seconds exclude validation (`TrainingClock`)" +
             ("" if len(clocked) == len(runs) else f" except for {sorted(set(curves) - set(clocked))}, whose "
              "seconds are wall seconds since the first event, validation included, and which have no steps/s") +
             f". One-step ratio: `val/one_step_ratio`, the one-step MSE over the zero-motion MSE; the step (and "
             f"training seconds) of the first validation at or below {RATIO_THRESHOLD}. Rollout MSE at the last "
             "validation / the best one. Slope: log10 rollout (or m+10) MSE per 1000 steps, least squares over the "
             "validations in the second half of the steps (negative: still falling). m+10: `val/m10_mse`. Train loss: "
             f"the normalized training loss of graphs with / without a point cloud, mean of the values logged in "
             f"the last {LATE_STEPS} optimizer steps. n/a: not logged.", "",
             markdown_rows(rows), ""] + [f"![{p.stem}]({p.name})" for p in figures] + [
             "", "## At each validation", "",
             "The validation scalars of every variant step by step (also in learning_validations.csv, with the "
             "training seconds).", "", validation_markdown(validations) if validations else "(none yet)"]
    path = output / "learning.md"
    path.write_text("\n".join(lines) + "\n")
    log(f"wrote {path}, {output / 'learning.csv'}, learning_validations.csv and {', '.join(p.name for p in figures)}")
    return path
