"""Figures of an aggregated sweep table, as in the GGNS paper.

Each `draw_*` function draws on a given matplotlib Axes (so tests can inspect the artists);
the matching public function makes a figure, draws and writes a PNG via `ggns.viz.save_figure`
and returns its path. `write_figures` writes all figures the table supports.

Table layout (see `aggregate`): {model: {metric: {"mean", "std", "seeds"}}}. Error bars are the
std over seeds; a NaN std (one seed) draws no error bar.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

from ..viz import plt, save_figure
from .aggregate import Table, normalized_benefit

SCHEDULES = ("k1", "k2", "k5", "k10", "never")
BENEFIT_KS = (1, 2, 5, 10)
_SCHEDULE_LABELS = {"k1": "k = 1", "k2": "k = 2", "k5": "k = 5", "k10": "k = 10", "never": "never"}
_COLORS = dict(zip(SCHEDULES, ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:gray")))


def _has(table: Table, prefix: str) -> bool:
    return any(f"{prefix}{s}" in per_metric for per_metric in table.values() for s in SCHEDULES)


def _errorbar(ax, x: float, stats: dict) -> None:
    std = float(stats.get("std", math.nan))
    if math.isfinite(std):
        ax.errorbar([x], [stats["mean"]], yerr=[std], fmt="none", ecolor="black", capsize=3, lw=1)


def draw_schedule_bars(ax, table: Table, prefix: str) -> None:
    """Grouped bars of `<prefix><schedule>` per model (groups: the models that have any) and
    schedule (bars it has)."""
    if not _has(table, prefix):
        raise ValueError(f"no {prefix}<schedule> metric in the table")
    width = 0.8 / len(SCHEDULES)
    labelled: set[str] = set()
    models = {m: per_metric for m, per_metric in table.items() if any(f"{prefix}{s}" in per_metric for s in SCHEDULES)}
    for i, (model, per_metric) in enumerate(models.items()):
        present = [s for s in SCHEDULES if f"{prefix}{s}" in per_metric]
        for j, schedule in enumerate(present):
            stats = per_metric[f"{prefix}{schedule}"]
            x = i + (j - (len(present) - 1) / 2) * width
            label = None if schedule in labelled else _SCHEDULE_LABELS[schedule]
            labelled.add(schedule)
            ax.bar([x], [stats["mean"]], width=width, color=_COLORS[schedule], label=label)
            _errorbar(ax, x, stats)
    ax.set_xticks(range(len(models)), list(models))
    ax.legend(title="point cloud every")


def draw_m_plus_10_bars(ax, table: Table, metric: str = "m10_mse") -> None:
    models = [m for m, per_metric in table.items() if metric in per_metric]
    if not models:
        raise ValueError(f"no {metric} in the table")
    for i, model in enumerate(models):
        stats = table[model][metric]
        ax.bar([i], [stats["mean"]], width=0.6, color="tab:blue")
        _errorbar(ax, i, stats)
    ax.set_xticks(range(len(models)), models)


def draw_benefit_curve(ax, table: Table, ggns_model: str = "ggns", mgn_model: str = "mgn",
                       ks: Sequence[int] = BENEFIT_KS) -> dict[int, float]:
    """The normalized benefit against k (the line labelled `<ggns> vs <mgn>`) and a line at 0."""
    benefit = normalized_benefit(table, ggns_model, mgn_model, ks)
    ax.axhline(0.0, color="gray", ls="--", lw=1, label=f"{mgn_model} (no point cloud)")
    ax.plot(list(benefit), list(benefit.values()), "o-", label=f"{ggns_model} vs {mgn_model}")
    ax.set_xscale("log")
    ax.set_xticks(list(benefit), [str(k) for k in benefit])
    ax.minorticks_off()
    ax.set_xlabel("point cloud every k steps")
    ax.set_ylabel("normalized benefit of point clouds")
    ax.legend()
    return benefit


def _figure(draw, path, ylabel=None, title=None, yscale=None, ylim=None, **kwargs) -> Path:
    fig, ax = plt.subplots(figsize=(7, 4))
    try:
        draw(ax, **kwargs)
    except BaseException:
        plt.close(fig)
        raise
    if yscale:
        ax.set_yscale(yscale)
    if ylim:
        ax.set_ylim(*ylim)
    if ylabel:
        ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, path)


def rollout_mse_bars(table: Table, path: str | Path) -> Path:
    return _figure(draw_schedule_bars, path, table=table, prefix="rollout_mse_", yscale="log",
                   ylabel="full-rollout MSE", title="Full-rollout MSE (mean ± std over seeds)")


def iou_bars(table: Table, path: str | Path) -> Path:
    return _figure(draw_schedule_bars, path, table=table, prefix="rollout_iou_", ylim=(0.0, 1.0),
                   ylabel="rollout IoU", title="Rollout IoU (mean ± std over seeds)")


def generated_mesh_iou_bars(table: Table, path: str | Path) -> Path:
    return _figure(draw_schedule_bars, path, table=table, prefix="generated_mesh_iou_", ylim=(0.0, 1.0),
                   ylabel="rollout IoU", title="IoU without the initial mesh (generated from the first point cloud)")


def m_plus_10_bars(table: Table, path: str | Path) -> Path:
    return _figure(draw_m_plus_10_bars, path, table=table, yscale="log", ylabel="M+10 MSE",
                   title="M+10 MSE (mean ± std over seeds)")


def benefit_curve(table: Table, path: str | Path, ggns_model: str = "ggns", mgn_model: str = "mgn") -> Path:
    return _figure(draw_benefit_curve, path, table=table, ggns_model=ggns_model, mgn_model=mgn_model,
                   title="Normalized benefit of point clouds (1 at k = 1, 0 at MGN)")


FIGURES = ("rollout_mse.png", "m_plus_10.png", "rollout_iou.png", "generated_mesh_iou.png", "normalized_benefit.png")


def write_figures(table: Table, directory: str | Path) -> list[Path]:
    """All figures the table supports, into `directory`: rollout_mse.png, m_plus_10.png,
    rollout_iou.png, generated_mesh_iou.png, normalized_benefit.png (each skipped when its metrics are missing;
    a skipped figure left there by an earlier call is removed, so the directory never shows a stale one)."""
    directory = Path(directory)
    paths = []
    if _has(table, "rollout_mse_"):
        paths.append(rollout_mse_bars(table, directory / "rollout_mse.png"))
    if any("m10_mse" in per_metric for per_metric in table.values()):
        paths.append(m_plus_10_bars(table, directory / "m_plus_10.png"))
    if _has(table, "rollout_iou_"):
        paths.append(iou_bars(table, directory / "rollout_iou.png"))
    if _has(table, "generated_mesh_iou_"):
        paths.append(generated_mesh_iou_bars(table, directory / "generated_mesh_iou.png"))
    if "ggns" in table and "mgn" in table:
        try:
            normalized_benefit(table)
        except ValueError:
            pass  # a k metric missing, or GGNS k=1 not below MGN (nothing to normalize): no curve
        else:
            paths.append(benefit_curve(table, directory / "normalized_benefit.png"))
    for name in FIGURES:
        if directory / name not in paths:
            (directory / name).unlink(missing_ok=True)
    return paths
