"""Our sweep results in the paper's layout, with the paper's figures beside them (`python -m ggns paper`).

One table per task, as the paper reports it: full-rollout MSE per point-cloud schedule (k = 1, 2, 5,
10; MGN and MGN(M) without point clouds, our `never`), the m+10-step MSE (pooled over each rollout's
steps, as the paper's is, and at S_{m+10} alone: conf/paper/ggns_iclr2023.yaml says why), the one-step MSE against
predicting no motion (the paper reports none) and the rollout IoU (the paper's: the plate only). Ours
come from sweep summaries (`summary.csv`: seed mean and std per model and metric, `ggns.sweeps.
aggregate`); the paper's from conf/paper/ggns_iclr2023.yaml (read from its LaTeX source). Below the
table, the ratios the paper's claims rest on, ours beside the paper's.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import yaml

from ..config import CONF_DIR
from ..reports import markdown_table

PAPER_FIGURES = CONF_DIR / "paper" / "ggns_iclr2023.yaml"
TASKS = ("plate", "tissue", "cavity")
COLUMNS = {"rollout_mse_k1": "rollout MSE k=1", "rollout_mse_k2": "k=2", "rollout_mse_k5": "k=5",
           "rollout_mse_k10": "k=10", "rollout_mse_never": "never", "m10_mse": "m+10 at S_m+10",
           "m10_pooled_mse": "m+10 pooled (the paper's)",
           "one_step_ratio": "one-step MSE / no motion", "rollout_iou_k1": "IoU k=1", "rollout_iou_k2": "IoU k=2",
           "rollout_iou_k5": "IoU k=5", "rollout_iou_never": "IoU never"}
LABELS = {"ggns": "GGNS", "ggns_lstm": "GGNS+LSTM", "ggns_id": "GGNSID", "ggns_m": "GGNS(M)", "mgn": "MGN",
          "mgn_m": "MGN(M)", "mgn_shared": "MGN, the authors' variant", "static": "static (mesh held at S_0)",
          "ggns_partition": "GGNS, per-type processor", "ggns_id_partition": "GGNSID, per-type processor",
          "ggns_id_points_field": "GGNSID, field on point-cloud samples"}
PAPER_MODELS = ("ggns", "ggns_lstm", "mgn_m", "mgn")
NOT_ROWS = ("alpha_shapes",)  # baselines with generated-mesh metrics only
NOT_POOLED = ("static", "alpha_shapes")  # deterministic baselines: one value, whatever the seeds


def paper_figures(task: str, path: str | Path = PAPER_FIGURES) -> dict[str, dict[str, float]]:
    """{metric: {model: mean}} of the paper for `task` (plate, tissue or cavity)."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; the paper has {', '.join(TASKS)}")
    with open(path, encoding="utf-8") as f:
        figures = yaml.safe_load(f)[task]
    return {metric: {model: float(value["mean"]) for model, value in models.items()}
            for metric, models in figures.items() if metric in COLUMNS}


def _read_one(path: Path) -> dict[str, dict[str, tuple[float, float, int]]]:
    if not path.is_file():
        raise FileNotFoundError(f"no sweep summary {path} (`python -m ggns sweep --config ... --aggregate-only` writes it)")
    out: dict[str, dict[str, tuple[float, float, int]]] = {}
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = {"model", "metric", "mean", "std", "seeds"} - set(reader.fieldnames or ())
        if missing:
            raise ValueError(f"{path}: not a sweep summary (columns {sorted(missing)} missing)")
        for row in reader:
            std = float(row["std"]) if row["std"] not in ("", "nan") else math.nan
            out.setdefault(row["model"], {})[row["metric"]] = (float(row["mean"]), std, int(row["seeds"]))
    return out


def _pool(parts: list[tuple[float, float, int]]) -> tuple[float, float, int]:
    """Seed means and stds of disjoint seed sets pooled into the mean and sample std over all seeds."""
    total = sum(n for _, _, n in parts)
    mean = sum(m * n for m, _, n in parts) / total
    if total < 2:
        return mean, math.nan, total
    within = sum((n - 1) * s * s for _, s, n in parts if n > 1 and not math.isnan(s))
    between = sum(n * (m - mean) ** 2 for m, _, n in parts)
    return mean, math.sqrt((within + between) / (total - 1)), total


def read_summary(paths: str | Path | list) -> dict[str, dict[str, tuple[float, float, int]]]:
    """{model: {metric: (mean, std, seeds)}} of a sweep's summary.csv; several summaries (a list, or one
    string of comma-separated paths) of the same sweep run on disjoint seeds are pooled over all their
    seeds (a deterministic baseline, `static`, is taken from the first). Adds `one_step_ratio`, the
    one-step MSE over that of predicting no motion, where the summary has the `static` row."""
    if isinstance(paths, (str, Path)):
        paths = str(paths).split(",")
    parts = [_read_one(Path(p)) for p in paths]
    out: dict[str, dict[str, tuple[float, float, int]]] = {}
    for model in dict.fromkeys(m for part in parts for m in part):
        metrics = dict.fromkeys(k for part in parts for k in part.get(model, {}))
        values = {k: [part[model][k] for part in parts if k in part.get(model, {})] for k in metrics}
        out[model] = {k: (v[0] if model in NOT_POOLED else _pool(v)) for k, v in values.items()}
    no_motion = out.get("static", {}).get("one_step_mse")
    if no_motion:  # the one-step MSE of predicting no motion on the same test trajectories
        for model, metrics in out.items():
            if "one_step_mse" in metrics:
                mean, std, seeds = metrics["one_step_mse"]
                metrics["one_step_ratio"] = (mean / no_motion[0], std / no_motion[0], seeds)
    return out


def _cell(value: tuple[float, float, int] | None, fmt: str) -> str:
    if value is None:
        return "-"
    mean, std, seeds = value
    text = format(mean, fmt)
    return text if seeds < 2 or math.isnan(std) else f"{text} ± {format(std, '.1e' if fmt.endswith('e') else fmt)}"


def _fmt(metric: str) -> str:
    return ".4f" if "iou" in metric else (".3f" if metric == "one_step_ratio" else ".2e")


def _ratios(tables: dict[str, dict], paper: dict) -> tuple[list[str], list[list[str]]]:
    """The ratios behind the paper's claims: a column per GGNS-like model of each summary (its baselines
    from the same summary, else from the first that has them) and the paper's GGNS."""
    def value(table, model, metric):
        entry = table.get(model, {}).get(metric)
        return entry[0] if entry else None

    def baseline(label, model, metric):
        for table in [tables[label], *tables.values()]:
            if value(table, model, metric) is not None:
                return value(table, model, metric)
        return None

    def ratio(a, b):
        return f"{a / b:.2f}x" if a and b else "-"

    claims = [("MGN(M) never / GGNS k=1 (paper: > 1)", "mgn_m", "rollout_mse_never", "rollout_mse_k1"),
              ("MGN never / GGNS k=1", "mgn", "rollout_mse_never", "rollout_mse_k1"),
              ("MGN(M) never / GGNS k=2", "mgn_m", "rollout_mse_never", "rollout_mse_k2"),
              ("MGN(M) m+10 pooled / GGNS m+10 pooled (paper: > 1)", "mgn_m", "m10_pooled_mse", "m10_pooled_mse"),
              ("MGN m+10 pooled / GGNS m+10 pooled", "mgn", "m10_pooled_mse", "m10_pooled_mse"),
              ("MGN(M) m+10 at S_m+10 / GGNS's", "mgn_m", "m10_mse", "m10_mse")]
    several = len(tables) > 1
    columns = [(label, model) for label, table in tables.items() for model in table
               if model.startswith("ggns") and model != "ggns_m"]
    header = ["ratio", *(f"ours: {label + ': ' if several else ''}{LABELS.get(m, m)}" for label, m in columns),
              "paper: GGNS"]
    rows = [[claim, *(ratio(baseline(label, base, top), value(tables[label], model, bottom)) for label, model in columns),
             ratio(paper.get(top, {}).get(base), paper.get(bottom, {}).get("ggns"))]
            for claim, base, top, bottom in claims]
    return header, rows


COMPACT_COLUMNS = ("rollout_mse_k1", "rollout_mse_k5", "rollout_mse_never", "m10_pooled_mse")
NOT_COMPACT = ("static", "alpha_shapes", "mgn_shared", "ggns_m")  # baselines and ablations the paper has not


def paper_table(task: str, summaries: dict[str, str | Path], compact: bool = False) -> str:
    """Markdown: our models (each summary's, labelled when there are several) and the paper's, in the
    paper's layout (module docstring), then the ratios of its claims. compact: the paper's models and ours
    (no baselines or ablations, NOT_COMPACT) and the columns COMPACT_COLUMNS (full rollouts with a point cloud every step and every 5th, without,
    and the m+10 error), no ratios: the README's tables."""
    if not summaries:
        raise ValueError("give at least one sweep summary (--summary LABEL=PATH)")
    paper = paper_figures(task)
    tables = {label: read_summary(path) for label, path in summaries.items()}
    if compact:
        tables = {label: {m: v for m, v in table.items() if m not in NOT_COMPACT} for label, table in tables.items()}
    columns = [c for c in COLUMNS if (any(c in m for t in tables.values() for m in t.values()) or c in paper)
               and (not compact or c in COMPACT_COLUMNS)]
    rows, shown = [], set()
    for label, table in tables.items():
        for model, metrics in table.items():
            if model in NOT_ROWS or not any(c in metrics for c in columns) or (model == "static" and model in shown):
                continue
            shown.add(model)
            seeds = max(v[2] for v in metrics.values())
            name = f"{LABELS.get(model, model)} ({seeds} seed{'s' if seeds > 1 else ''})"
            rows.append([f"{label}: {name}" if len(tables) > 1 else name,
                         *(_cell(metrics.get(c), _fmt(c)) for c in columns)])
    for model in PAPER_MODELS:
        if any(model in paper.get(c, {}) for c in columns):
            rows.append([f"paper: {LABELS[model]}",
                         *(format(paper[c][model], _fmt(c)) if model in paper.get(c, {}) else "-" for c in columns)])
    header = ["model", *(COLUMNS[c] for c in columns)]
    sources = ", ".join(f"{label}: `{path}`" for label, path in summaries.items())
    if compact:
        return "\n".join([markdown_table(header, rows), "",
                          f"Ours: seed mean ± std ({sources}); paper: conf/paper/ggns_iclr2023.yaml.", ""])
    ratio_header, ratio_rows = _ratios(tables, paper)
    lines = [f"### {task}: ours and the paper's", "",
             f"Ours: seed mean ± std of the test metrics ({sources}); paper: conf/paper/ggns_iclr2023.yaml "
             "(the mean of each bar or table entry; '-': not reported). MSE in squared task-space units.", "",
             markdown_table(header, rows), "",
             markdown_table(ratio_header, ratio_rows), ""]
    return "\n".join(lines)
