"""Learning curves of a fit, read from its TensorBoard event files: the scalars by optimizer step,
training seconds (`TrainingClock`, in ggns.callbacks.clock), the step a one-step ratio is first
reached, the late slope of a rollout curve, one table row per fit, the markdown table and the curve
figure. Used by `bench learning` (one row per variant) and by a sweep's summary (one row per run).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..reports import markdown_table

# the curves drawn, in panel order; a variant lacking one (e.g. MGN: no point clouds) leaves it out
CURVES = ("val/one_step_ratio", "val/rollout_mse_k1", "val/rollout_mse_never", "val/m10_mse", "train/loss_points",
          "train/loss_no_points", "train/lr")
CLOCK = "time/train_seconds"
RATIO_THRESHOLD = 0.2  # one-step MSE / zero-motion MSE that counts as "learned to move"
COLUMNS = ("variant", "change", "steps", "train_seconds", "steps_per_second", "steps_to_ratio",
           "seconds_to_ratio", "best_one_step_ratio", "last_one_step_ratio", "validations", "last_val_step",
           "rollout_mse_k1_last", "rollout_mse_k1_best", "rollout_mse_never_last", "rollout_mse_never_best",
           "slope_k1", "slope_never", "m10_mse_last", "m10_mse_best", "slope_m10", "loss_points_late", "loss_no_points_late")
LATE_STEPS = 1000  # the training loss with / without point clouds is averaged over the last this many steps


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
    steps >= half the last step). Where those points span less than a quarter of the last step (e.g.
    validations at 4000 and at the fit's end, 4001), the last point before the half joins them, so
    that one step's change is never read as a slope per 1000. None with fewer than 2 positive points
    or a span still under a quarter. Negative: still falling."""
    steps, values = np.asarray(steps, dtype=float), np.asarray(values, dtype=float)
    valid = (values > 0) & np.isfinite(values)
    steps, values = steps[valid], values[valid]
    if steps.size < 2:
        return None
    last = steps.max()
    keep = steps >= last / 2
    if np.ptp(steps[keep]) < last / 4 and (~keep).any():
        keep |= steps == steps[~keep].max()
    if keep.sum() < 2 or np.ptp(steps[keep]) < last / 4:
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
        steps, _, mse = scalars["val/m10_mse"]
        row.update(m10_mse_last=float(mse[-1]), m10_mse_best=float(mse.min()), slope_m10=late_slope(steps, mse))
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


# the validation scalars listed step by step (`validation_rows`), in column order
VALIDATIONS = ("val/rollout_mse_k1", "val/rollout_mse_never", "val/m10_mse", "val/one_step_ratio")
VALIDATION_COLUMNS = ("variant", "step", "train_seconds", *(tag.removeprefix("val/") for tag in VALIDATIONS))


def validation_rows(name: str, scalars: dict) -> list[dict]:
    """One row per validation step of a fit (keys `VALIDATION_COLUMNS`): the `VALIDATIONS` it logged at
    that step (None where not logged, e.g. k=1 for MGN) and its training seconds by then."""
    logged = {tag: dict(zip(scalars[tag][0].tolist(), scalars[tag][2].tolist())) for tag in VALIDATIONS if tag in scalars}
    steps = sorted({step for values in logged.values() for step in values})
    seconds = training_seconds(scalars, np.array(steps, dtype=float))[0] if steps else []
    return [{"variant": name, "step": int(step), "train_seconds": float(second),
             **{tag.removeprefix("val/"): logged.get(tag, {}).get(step) for tag in VALIDATIONS}}
            for step, second in zip(steps, seconds)]


def validation_markdown(rows: list[dict]) -> str:
    """The markdown table of `validation_rows` of one or more fits: one line per step, one column per fit
    and scalar that some row has."""
    names = list(dict.fromkeys(r["variant"] for r in rows))
    columns = [(n, k) for n in names for k in VALIDATION_COLUMNS[3:]
               if any(r[k] is not None for r in rows if r["variant"] == n)]
    by_step = {}
    for r in rows:
        by_step.setdefault(r["step"], {})[r["variant"]] = r
    lines = [[str(step)] + [_cell(by_step[step].get(n, {}).get(k)) for n, k in columns] for step in sorted(by_step)]
    return markdown_table(["step", *(f"{n}: {k}" for n, k in columns)], lines)


def markdown_rows(rows: list[dict], threshold: float = RATIO_THRESHOLD, label: str = "variant",
                  change: bool = True) -> str:
    """The markdown table of `variant_row`s; the first column headed `label`, the `change` column
    (the variant's arguments) left out when change=False."""
    head = [label] + (["change"] if change else []) + ["steps", "train s", "steps/s", f"one-step ratio <= {threshold}: step (s)",
            "one-step ratio best / last", "rollout MSE k=1 last / best", "rollout MSE never last / best",
            "m+10 MSE last / best", "slope k=1", "slope never", "slope m+10", f"train loss with / without points (last {LATE_STEPS} steps)",
            "validations (last at step)"]
    lines = []
    for r in rows:
        if r["steps_to_ratio"] is not None:
            reached = f"{r['steps_to_ratio']} ({_cell(r['seconds_to_ratio'], 'seconds')} s)"
        elif r["best_one_step_ratio"] is not None:
            reached = f"not reached (best {_cell(r['best_one_step_ratio'])})"
        else:
            reached = "n/a"
        cells = [r["variant"]] + ([f"`{r['change']}`"] if change else []) + [_cell(r["steps"]), _cell(r["train_seconds"], "seconds"),
                 _cell(r["steps_per_second"]), reached,
                 f"{_cell(r['best_one_step_ratio'])} / {_cell(r['last_one_step_ratio'])}",
                 f"{_cell(r['rollout_mse_k1_last'])} / {_cell(r['rollout_mse_k1_best'])}",
                 f"{_cell(r['rollout_mse_never_last'])} / {_cell(r['rollout_mse_never_best'])}",
                 f"{_cell(r['m10_mse_last'])} / {_cell(r['m10_mse_best'])}",
                 _cell(r["slope_k1"], "+.2f"), _cell(r["slope_never"], "+.2f"), _cell(r["slope_m10"], "+.2f"),
                 f"{_cell(r['loss_points_late'])} / {_cell(r['loss_no_points_late'])}",
                 f"{_cell(r['validations'])} ({_cell(r['last_val_step'])})"]
        lines.append(cells)
    return markdown_table(head, lines) + "\n"


def plot_curves(curves: dict[str, dict], path: Path, against: str, title: str = "variant",
                groups: dict[str, tuple[str, int]] | None = None) -> Path:
    """One panel per `CURVES` tag, one line per variant (or run); x: optimizer steps (against="steps")
    or training seconds ("seconds"). curves: name -> its `read_scalars`; title: the legend's title;
    groups: name -> (group, member), drawn with one colour per group and one line style per member
    (e.g. a sweep's runs: model and seed)."""
    from ..viz import plt, save_figure

    styles = {}
    if groups:
        colours = {g: f"C{i % 10}" for i, g in enumerate(dict.fromkeys(g for g, _ in groups.values()))}
        dashes = ("-", "--", ":", "-.")
        styles = {name: {"color": colours[g], "ls": dashes[m % len(dashes)]} for name, (g, m) in groups.items()}
    fig, axes = plt.subplots(2, 4, figsize=(18, 8), constrained_layout=True)
    for ax, tag in zip(axes.flat, CURVES):
        for variant, scalars in curves.items():
            if tag not in scalars:
                continue
            steps, _, values = scalars[tag]
            x = steps if against == "steps" else training_seconds(scalars, steps)[0]
            ax.plot(x, values, marker="o" if tag.startswith("val/") else None, ms=3, lw=1, label=variant,
                    **styles.get(variant, {"ls": "-"}))
        ax.set_title(tag)
        ax.set_xlabel("optimizer steps" if against == "steps" else "training seconds")
        if tag != "train/lr" and ax.has_data():
            ax.set_yscale("log")
        if tag == "val/one_step_ratio":
            ax.axhline(RATIO_THRESHOLD, color="gray", ls="--", lw=1)
    handles = {}
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    axes.flat[-1].axis("off")
    if handles:
        axes.flat[-1].legend(list(handles.values()), list(handles), loc="center", title=title)
    return save_figure(fig, path)


