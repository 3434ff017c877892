"""Aggregate per-seed test results into per-model tables, as the paper reports them.

Each run (one model config, one seed; a Lightning fit + test) writes `test_metrics.json`
into its log dir: {metric name: {"mean", "std", "count"}} over test trajectories (see
`ggns.evaluation.evaluate` and `GraphSimulator.on_test_epoch_end` in ggns.models.simulators), plus the tested checkpoint(s)
(`ggns.evaluation.selection`: "checkpoint" for one `test`, "checkpoints" per metric family for a
sweep run's merged tests). A run's value of a metric is
that "mean". The paper reports, per model and metric, the mean and standard deviation of
those values over seeds; `aggregate` computes them, `to_markdown`/`to_csv` write them out
and `normalized_benefit` gives the "normalized benefit of point clouds" against k.

Table layout: {model: {metric: {"mean": float, "std": float, "seeds": int}}}.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

from ..evaluation.selection import CHECKPOINT_KEY, CHECKPOINTS_KEY
from ..reports import markdown_table, write_csv

Table = dict[str, dict[str, dict[str, float]]]


@dataclass
class RunResult:
    """The test metrics of one run: {metric name: mean over test trajectories}, and the checkpoint
    each metric family was tested with ({family: `checkpoint_info` + note, metrics}; {} if not recorded)."""
    model: str
    seed: int
    metrics: dict[str, float]
    checkpoints: dict[str, dict] = field(default_factory=dict)


def load_run(path: str | Path, model: str, seed: int) -> RunResult:
    """Read a run's `test_metrics.json`, keeping the "mean" of each metric and the recorded checkpoints."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no test metrics file at {path}")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"malformed JSON in {path}: {e}") from e
    if not isinstance(data, dict):
        raise ValueError(f"malformed test metrics in {path}: expected an object of metrics")
    metrics = {}
    for name, entry in data.items():
        if name in (CHECKPOINT_KEY, CHECKPOINTS_KEY):
            continue
        if not isinstance(entry, dict) or "mean" not in entry:
            raise ValueError(f"malformed test metrics in {path}: metric {name!r} has no 'mean'")
        try:
            metrics[name] = float(entry["mean"])
        except (TypeError, ValueError) as e:
            raise ValueError(f"malformed test metrics in {path}: metric {name!r} mean "
                             f"{entry['mean']!r} is not a number") from e
    return RunResult(model=model, seed=seed, metrics=metrics, checkpoints=data.get(CHECKPOINTS_KEY) or {})


def aggregate(runs: Iterable[RunResult]) -> Table:
    """Mean and sample std (ddof=1) of each metric over the seeds of each model.

    "seeds" is the number of runs that reported the metric. With one seed the std is NaN
    (the sample std is undefined), never 0. A non-finite metric value raises ValueError
    naming model, seed and metric (it is never averaged silently); so does a repeated
    (model, seed) pair.
    """
    values: dict[str, dict[str, list[float]]] = {}
    seen: set[tuple[str, int]] = set()
    for run in runs:
        if (run.model, run.seed) in seen:
            raise ValueError(f"duplicate run: model {run.model!r}, seed {run.seed}")
        seen.add((run.model, run.seed))
        per_model = values.setdefault(run.model, {})
        for metric, value in run.metrics.items():
            value = float(value)
            if not math.isfinite(value):
                raise ValueError(f"non-finite metric: model {run.model!r}, seed {run.seed}, "
                                 f"metric {metric!r} = {value}")
            per_model.setdefault(metric, []).append(value)
    table: Table = {}
    for model, per_metric in values.items():
        table[model] = {}
        for metric, xs in per_metric.items():
            n = len(xs)
            mean = math.fsum(xs) / n
            std = math.sqrt(math.fsum((x - mean) ** 2 for x in xs) / (n - 1)) if n > 1 else math.nan
            table[model][metric] = {"mean": mean, "std": std, "seeds": n}
    return table


def _mean(table: Table, model: str, metric: str) -> float:
    if model not in table:
        raise ValueError(f"model {model!r} not in the table (have {sorted(table)})")
    if metric not in table[model]:
        raise ValueError(f"metric {metric!r} missing for model {model!r}")
    return table[model][metric]["mean"]


class NoBenefitError(ValueError):
    """GGNS with a point cloud every step is not below MGN: there is no benefit to normalize."""


def normalized_benefit(table: Table, ggns_model: str = "ggns", mgn_model: str = "mgn",
                       ks: Sequence[int] = (1, 2, 5, 10)) -> dict[int, float]:
    """Normalized benefit of point clouds every k steps (our reading of the paper):

        benefit(k) = (MSE_MGN - MSE_GGNS(k)) / (MSE_MGN - MSE_GGNS(1))

    with MSE_MGN the seed-mean `rollout_mse_never` of `mgn_model` and MSE_GGNS(k) the
    seed-mean `rollout_mse_k<k>` of `ggns_model`. So benefit(1) = 1 and a GGNS no better
    than MGN scores 0 (negative if worse). ValueError when a model or metric is missing;
    NoBenefitError (a ValueError) when MSE_GGNS(1) is not below MSE_MGN, where the
    denominator is zero or negative and the ratios would mean nothing (a "benefit" above 1
    that rises with k).
    """
    mgn = _mean(table, mgn_model, "rollout_mse_never")
    k1 = _mean(table, ggns_model, "rollout_mse_k1")
    if not k1 < mgn:
        raise NoBenefitError(f"no benefit to normalize: {ggns_model} "
                             f"rollout_mse_k1 {k1:.3g} is not below {mgn_model} rollout_mse_never {mgn:.3g}")
    return {k: (mgn - _mean(table, ggns_model, f"rollout_mse_k{k}")) / (mgn - k1) for k in ks}


def _metric_order(table: Table) -> list[str]:
    order: list[str] = []
    for per_metric in table.values():
        order.extend(m for m in per_metric if m not in order)
    return order


def to_markdown(table: Table, metrics: Sequence[str] | None = None, fmt: str = ".4g") -> str:
    """Rows: models; columns: metrics (default: all, in first-seen order); cells "mean ± std"
    (the mean alone where the std is NaN: one seed), "-" where a model lacks the metric (e.g. MGN has only the `_never` rollouts)."""
    metrics = list(metrics) if metrics is not None else _metric_order(table)
    rows = []
    for model, per_metric in table.items():
        cells = []
        for metric in metrics:
            s = per_metric.get(metric)
            if s is None:
                cells.append("-")
            elif math.isnan(s["std"]):  # one seed (or a deterministic baseline): no spread to report
                cells.append(format(s["mean"], fmt))
            else:
                cells.append(f"{format(s['mean'], fmt)} ± {format(s['std'], fmt)}")
        rows.append([model, *cells])
    return markdown_table(["model", *metrics], rows) + "\n"


def to_csv(table: Table, path: str | Path) -> None:
    """Long format: one row per (model, metric) with columns model, metric, mean, std, seeds
    (floats written with repr, so they read back exactly; NaN std as "nan")."""
    rows = [{"model": model, "metric": metric, "mean": repr(float(s["mean"])), "std": repr(float(s["std"])),
             "seeds": int(s["seeds"])} for model, per_metric in table.items() for metric, s in per_metric.items()]
    write_csv(path, rows, ["model", "metric", "mean", "std", "seeds"])
