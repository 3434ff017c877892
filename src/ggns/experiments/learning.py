"""Learning per CPU-second (`python -m ggns bench learning`): how fast named variants of one model
config learn within the same wall-clock budget, from their TensorBoard curves.

A learning file (conf/learning/<name>.yaml or a path) holds:
    output: lightning_logs/learning/plate_ggns  # a variant logs to <output>/<variant>/seed_<seed>
    minutes: 10                                 # wall-clock budget per variant (trainer.max_time)
    val_every: 100                              # optimizer steps between validations
    seed: 0
    parallel: 2                                 # variants at once (torch threads = cores / parallel)
    base: {config: conf/plate/ggns.yaml, args: ["--data.dataset", "plate_small"]}
    variants:                                   # name -> Lightning CLI arguments (after the base's)
      paper: []
      noise_0.005: ["--model.init_args.noise_std", "0.005"]

Each variant is one `python -m ggns fit` in its own process (`sweep.Run` builds the command), with
the budget and validation arguments first, then the base's, then the variant's (later ones win),
plus a `TrainingClock` callback. A variant is finished when its fit exited cleanly
(`<run>/learning_finished.json`); finished variants are skipped, an interrupted one resumes from its
`last.ckpt`. `write_report` then reads the event files and writes <output>/learning.md,
learning.csv, curves_steps.png and curves_seconds.png.
"""
from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np
import pytorch_lightning as pl
from omegaconf import OmegaConf

from ..config import resolve_preset
from .sweep import Run

# the curves drawn, in panel order; a variant lacking one (e.g. MGN: no point clouds) leaves it out
CURVES = ("val/one_step_ratio", "val/rollout_mse_k1", "val/rollout_mse_never", "val/m10_mse", "train/loss_points",
          "train/loss_no_points", "train/lr")
CLOCK = "time/train_seconds"
RATIO_THRESHOLD = 0.2  # one-step MSE / zero-motion MSE that counts as "learned to move"
FINISHED = "learning_finished.json"
COLUMNS = ("variant", "change", "steps", "train_seconds", "steps_per_second", "steps_to_ratio",
           "seconds_to_ratio", "best_one_step_ratio", "last_one_step_ratio", "validations", "last_val_step",
           "rollout_mse_k1_last", "rollout_mse_k1_best", "rollout_mse_never_last", "rollout_mse_never_best",
           "slope_k1", "slope_never", "m10_mse_last", "m10_mse_best", "loss_points_late", "loss_no_points_late")
LATE_STEPS = 1000  # the training loss with / without point clouds is averaged over the last this many steps


class TrainingClock(pl.Callback):
    """Logs `time/train_seconds` with the training metrics (every `log_every_n_steps`) and at every
    validation: wall seconds since training started minus the seconds spent in validation loops.
    The normalization pass and the sanity check (both before training starts) are not counted;
    checkpoint writing is. The count is saved in checkpoints, so a resumed fit continues it."""

    def __init__(self):
        self.train_seconds = 0.0
        self._since: float | None = None  # None while not training
        self._paused = False  # in a validation loop that interrupted training

    def _lap(self) -> None:
        if self._since is not None:
            now = time.perf_counter()
            self.train_seconds += now - self._since
            self._since = now

    def on_train_start(self, trainer, pl_module) -> None:
        self._since = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self._lap()
        pl_module.log(CLOCK, self.train_seconds, on_step=True, on_epoch=False, batch_size=1)

    def on_validation_start(self, trainer, pl_module) -> None:
        if self._since is not None:
            self._lap()
            self._since, self._paused = None, True

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        if not trainer.sanity_checking:
            pl_module.log(CLOCK, self.train_seconds, batch_size=1)

    def on_validation_end(self, trainer, pl_module) -> None:
        if self._paused:
            self._since, self._paused = time.perf_counter(), False

    def state_dict(self) -> dict:
        return {"train_seconds": self.train_seconds}

    def load_state_dict(self, state_dict: dict) -> None:
        self.train_seconds = float(state_dict["train_seconds"])


# ---- the variants ---------------------------------------------------------------------------------
def load_learning(name_or_path: str | Path, overrides: Sequence[str] = ()) -> dict:
    """The learning file (module docstring) with `key=value` overrides, checked."""
    path = resolve_preset(name_or_path, "learning")
    spec = OmegaConf.to_container(OmegaConf.merge(OmegaConf.load(path), OmegaConf.from_dotlist(list(overrides))),
                                  resolve=True)
    missing = [k for k in ("output", "minutes", "val_every", "base", "variants") if k not in spec]
    if missing:
        raise ValueError(f"{path}: learning file lacks {missing}")
    base = spec["base"]
    if not isinstance(base, dict) or "config" not in base:
        raise ValueError(f"{path}: `base` needs a `config` (a Lightning config file)")
    if not Path(base["config"]).is_file():
        raise FileNotFoundError(f"{path}: base config {base['config']} not found")
    if not isinstance(spec["variants"], dict) or not spec["variants"]:
        raise ValueError(f"{path}: `variants` must map at least one name to a list of CLI arguments")
    for name, args in spec["variants"].items():
        if not isinstance(args, list):
            raise ValueError(f"{path}: variant {name!r} must be a list of CLI arguments, got {args!r}")
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


def variant_runs(spec: dict) -> list[Run]:
    """One fit per variant, in the file's order."""
    budget = ["--trainer.max_time", max_time(spec["minutes"]), "--trainer.max_epochs", "-1",
              "--trainer.val_check_interval", str(int(spec["val_every"])),
              "--trainer.check_val_every_n_epoch", "null",
              f"--trainer.callbacks+={TrainingClock.__module__}.{TrainingClock.__name__}"]
    base = [str(a) for a in spec["base"].get("args", [])]
    return [Run(name, int(spec.get("seed", 0)), str(spec["base"]["config"]),
                tuple(budget + base + [str(a) for a in args]), Path(spec["output"]))
            for name, args in spec["variants"].items()]


def fit_variant(run: Run, threads: int | None = None, log=print) -> Run:
    """The variant's fit in its own process (resuming a left-over last.ckpt); skipped when finished
    with the same arguments, an error when finished with others."""
    marker = run.fit_dir / FINISHED
    if marker.is_file():
        done = json.loads(marker.read_text())
        if list(done["args"]) != list(run.args):
            raise ValueError(f"variant {run.model!r} finished with other arguments than now ({marker}); "
                             f"delete {run.fit_dir} or rename the variant")
        log(f"skip {run.model}: {marker} exists")
        return run
    run.fit_dir.mkdir(parents=True, exist_ok=True)
    log(f"fit {run.model}")
    start = time.perf_counter()
    with open(run.output / run.model / f"seed_{run.seed}.log", "a") as out:
        result = subprocess.run(run.fit_command(), stdout=out, stderr=subprocess.STDOUT,
                                env={**os.environ, **({"OMP_NUM_THREADS": str(threads)} if threads else {})})
    if result.returncode != 0:
        raise RuntimeError(f"fit of variant {run.model} failed (exit {result.returncode}); see {out.name}")
    marker.write_text(json.dumps({"args": list(run.args), "process_seconds": time.perf_counter() - start}, indent=2))
    return run


def run_learning(spec: dict, only: Sequence[str] | None = None, log=print) -> Path:
    """Fit the variants (`only` these names, else all; `parallel` at once), then `write_report`."""
    runs = variant_runs(spec)
    if only:
        unknown = sorted(set(only) - {r.model for r in runs})
        if unknown:
            raise ValueError(f"unknown variants {unknown} (known: {[r.model for r in runs]})")
        runs = [r for r in runs if r.model in only]
    parallel = max(1, int(spec.get("parallel", 1)))
    threads = max(1, (os.cpu_count() or 1) // parallel)
    with ThreadPoolExecutor(parallel) as pool:
        list(pool.map(lambda r: fit_variant(r, threads, log), runs))
    return write_report(spec, log=log)


# ---- reading the curves -------------------------------------------------------------------------
def read_scalars(directory: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every scalar of a run's event files: tag -> (steps, wall times in s, values), by step; where a
    step was logged twice (a resumed fit), the later value. Steps are the optimizer steps completed
    when the value was logged: Lightning logs a training batch's metrics, and a validation that follows
    it, at that batch's 0-based index, i.e. at TensorBoard step n - 1 after n optimizer steps (the lr
    at that step is the lr of the n-th step)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(directory), size_guidance={"scalars": 0, "images": 1, "tensors": 1})
    events.Reload()
    scalars = {}
    for tag in events.Tags()["scalars"]:
        by_step = {e.step: (e.wall_time, e.value) for e in sorted(events.Scalars(tag), key=lambda e: e.wall_time)}
        steps = sorted(by_step)
        scalars[tag] = (np.array(steps, dtype=float) + 1, np.array([by_step[s][0] for s in steps]),
                        np.array([by_step[s][1] for s in steps]))
    return scalars


def training_seconds(scalars: dict, steps: np.ndarray) -> tuple[np.ndarray, bool]:
    """Seconds of training at `steps`: interpolated from the TrainingClock's readings (validation
    excluded; True), else wall seconds since the first event (validation included; False)."""
    if CLOCK in scalars:
        clock_steps, _, seconds = scalars[CLOCK]
        return np.interp(steps, np.concatenate([[0.0], clock_steps]), np.concatenate([[0.0], seconds])), True
    first = min(float(wall.min()) for _, wall, _ in scalars.values())
    walls = {s: w for curve_steps, wall, _ in scalars.values() for s, w in zip(curve_steps, wall)}
    return np.array([walls.get(s, math.nan) - first for s in steps]), False


def steps_to_threshold(steps: Sequence[float], values: Sequence[float], threshold: float) -> float | None:
    """The first step whose value is <= threshold (None if none is)."""
    for step, value in zip(steps, values):
        if value <= threshold:
            return step
    return None


def late_slope(steps: Sequence[float], values: Sequence[float]) -> float | None:
    """Least-squares slope of log10(value) per 1000 steps over the last half of the curve (points at
    steps >= half the last step); None with fewer than 2 such positive points. Negative: still falling."""
    steps, values = np.asarray(steps, dtype=float), np.asarray(values, dtype=float)
    if steps.size == 0:
        return None
    keep = (steps >= steps.max() / 2) & (values > 0) & np.isfinite(values)
    if keep.sum() < 2 or np.ptp(steps[keep]) == 0:
        return None
    return float(np.polyfit(steps[keep] / 1000.0, np.log10(values[keep]), 1)[0])


def variant_row(name: str, args: Sequence[str], scalars: dict, threshold: float = RATIO_THRESHOLD) -> dict:
    """One table row (keys `COLUMNS`; None where the curves lack what a column needs)."""
    row = dict.fromkeys(COLUMNS)
    row.update(variant=name, change=" ".join(args) or "(base)")
    if not scalars:
        return row
    last_step = max(float(steps.max()) for steps, _, _ in scalars.values())
    seconds, clocked = training_seconds(scalars, np.array([last_step]))
    row.update(steps=int(last_step), train_seconds=float(seconds[0]))
    if clocked and seconds[0] > 0:
        row["steps_per_second"] = last_step / float(seconds[0])
    if "val/one_step_ratio" in scalars:
        steps, _, ratios = scalars["val/one_step_ratio"]
        reached = steps_to_threshold(steps, ratios, threshold)
        row.update(best_one_step_ratio=float(ratios.min()), last_one_step_ratio=float(ratios[-1]),
                   validations=len(steps), last_val_step=int(steps[-1]))
        if reached is not None:
            seconds_then = training_seconds(scalars, np.array([reached]))[0]
            row.update(steps_to_ratio=int(reached), seconds_to_ratio=float(seconds_then[0]))
    for key in ("k1", "never"):
        if f"val/rollout_mse_{key}" in scalars:
            steps, _, mse = scalars[f"val/rollout_mse_{key}"]
            row.update({f"rollout_mse_{key}_last": float(mse[-1]), f"rollout_mse_{key}_best": float(mse.min()),
                        f"slope_{key}": late_slope(steps, mse)})
            row["validations"] = row["validations"] or len(steps)
            row["last_val_step"] = row["last_val_step"] or int(steps[-1])
    if "val/m10_mse" in scalars:
        mse = scalars["val/m10_mse"][2]
        row.update(m10_mse_last=float(mse[-1]), m10_mse_best=float(mse.min()))
    for key in ("points", "no_points"):
        if f"train/loss_{key}" in scalars:
            steps, _, loss = scalars[f"train/loss_{key}"]
            row[f"loss_{key}_late"] = float(loss[steps > steps.max() - LATE_STEPS].mean())
    return row


# ---- the report ----------------------------------------------------------------------------------
def _cell(value, fmt: str = ".3g") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if fmt == "seconds":
        fmt = ".0f" if value >= 10 else ".2g"
    return format(value, fmt) if isinstance(value, float) else str(value)


def markdown_rows(rows: list[dict], threshold: float = RATIO_THRESHOLD) -> str:
    """The markdown table of `variant_row`s."""
    head = ["variant", "change", "steps", "train s", "steps/s", f"one-step ratio <= {threshold}: step (s)",
            "one-step ratio best / last", "rollout MSE k=1 last / best", "rollout MSE never last / best",
            "m+10 MSE last / best", "slope k=1", "slope never", f"train loss with / without points (last {LATE_STEPS} steps)",
            "validations (last at step)"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in rows:
        if r["steps_to_ratio"] is not None:
            reached = f"{r['steps_to_ratio']} ({_cell(r['seconds_to_ratio'], 'seconds')} s)"
        elif r["best_one_step_ratio"] is not None:
            reached = f"not reached (best {_cell(r['best_one_step_ratio'])})"
        else:
            reached = "n/a"
        cells = [r["variant"], f"`{r['change']}`", _cell(r["steps"]), _cell(r["train_seconds"], "seconds"),
                 _cell(r["steps_per_second"]), reached,
                 f"{_cell(r['best_one_step_ratio'])} / {_cell(r['last_one_step_ratio'])}",
                 f"{_cell(r['rollout_mse_k1_last'])} / {_cell(r['rollout_mse_k1_best'])}",
                 f"{_cell(r['rollout_mse_never_last'])} / {_cell(r['rollout_mse_never_best'])}",
                 f"{_cell(r['m10_mse_last'])} / {_cell(r['m10_mse_best'])}",
                 _cell(r["slope_k1"], "+.2f"), _cell(r["slope_never"], "+.2f"),
                 f"{_cell(r['loss_points_late'])} / {_cell(r['loss_no_points_late'])}",
                 f"{_cell(r['validations'])} ({_cell(r['last_val_step'])})"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_curves(curves: dict[str, dict], path: Path, against: str) -> Path:
    """One panel per `CURVES` tag, one line per variant; x: optimizer steps (against="steps") or
    training seconds ("seconds"). curves: variant -> its `read_scalars`."""
    from ..viz import plt, save_figure

    fig, axes = plt.subplots(2, 4, figsize=(18, 8), constrained_layout=True)
    for ax, tag in zip(axes.flat, CURVES):
        for variant, scalars in curves.items():
            if tag not in scalars:
                continue
            steps, _, values = scalars[tag]
            x = steps if against == "steps" else training_seconds(scalars, steps)[0]
            ax.plot(x, values, "o-" if tag.startswith("val/") else "-", ms=3, lw=1, label=variant)
        ax.set_title(tag)
        ax.set_xlabel("optimizer steps" if against == "steps" else "training seconds")
        if tag != "train/lr" and ax.has_data():
            ax.set_yscale("log")
        if tag == "val/one_step_ratio":
            ax.axhline(RATIO_THRESHOLD, color="gray", ls="--", lw=1)
    handles, labels = {}, []
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    axes.flat[-1].axis("off")
    if handles:
        axes.flat[-1].legend(list(handles.values()), list(handles), loc="center", title="variant")
    return save_figure(fig, path)


def write_report(spec: dict, log=print) -> Path:
    """learning.md, learning.csv and the two curve figures in the spec's output, from the event
    files of every variant that logged anything (finished or not)."""
    output = Path(spec["output"])
    runs = [r for r in variant_runs(spec) if r.fit_dir.is_dir()]
    if not runs:
        raise FileNotFoundError(f"{output}: no variant has run yet")
    curves = {r.model: read_scalars(r.fit_dir) for r in runs}
    rows = [variant_row(r.model, spec["variants"][r.model], curves[r.model]) for r in runs]
    output.mkdir(parents=True, exist_ok=True)
    with open(output / "learning.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(COLUMNS))
        writer.writeheader()
        writer.writerows({k: ("" if v is None else v) for k, v in row.items()} for row in rows)
    figures = [plot_curves(curves, output / f"curves_{x}.png", x) for x in ("steps", "seconds")]
    finished = [r.model for r in runs if (r.fit_dir / FINISHED).is_file()]
    clocked = [r.model for r in runs if CLOCK in curves[r.model]]
    base = spec["base"]
    lines = ["# Learning per CPU-second", "",
             f"Base: `{base['config']}` with `{' '.join(map(str, base.get('args', []))) or '(no arguments)'}`; "
             f"seed {spec.get('seed', 0)}; budget {spec['minutes']} min of wall-clock per variant "
             f"(`trainer.max_time`, validation included); validation every {spec['val_every']} optimizer steps; "
             f"{spec.get('parallel', 1)} variant(s) at once. Finished: {len(finished)} of {len(spec['variants'])} "
             f"variants ({', '.join(finished) or 'none'}).", "",
             "Training seconds exclude validation (`TrainingClock`)" +
             ("" if len(clocked) == len(runs) else f" except for {sorted(set(curves) - set(clocked))}, whose "
              "seconds are wall seconds since the first event, validation included, and which have no steps/s") +
             f". One-step ratio: `val/one_step_ratio`, the one-step MSE over the zero-motion MSE; the step (and "
             f"training seconds) of the first validation at or below {RATIO_THRESHOLD}. Rollout MSE at the last "
             "validation / the best one. Slope: log10 rollout MSE per 1000 steps, least squares over the "
             "validations in the second half of the steps (negative: still falling). m+10: `val/m10_mse`. Train loss: "
             f"the normalized training loss of graphs with / without a point cloud, mean of the values logged in "
             f"the last {LATE_STEPS} optimizer steps. n/a: not logged.", "",
             markdown_rows(rows)] + [f"![{p.stem}]({p.name})" for p in figures]
    path = output / "learning.md"
    path.write_text("\n".join(lines) + "\n")
    log(f"wrote {path}, {output / 'learning.csv'} and {', '.join(p.name for p in figures)}")
    return path
