"""The writers of every report file the library makes, one per kind (figures: `ggns.viz.save_figure`):

- `markdown_table`: the markdown tables of test metrics (`metrics_markdown`), the scale check, sweep
  summaries, findings, learning tables and the demo's report;
- `write_text`, `write_json`, `write_csv`: files written to a temporary name and renamed into place,
  so an interrupted write leaves the previous file (or none), never a truncated one.
"""
from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path


def markdown_table(header: Sequence, rows: Iterable[Sequence]) -> str:
    """A markdown table: the header row, the separator, then one line per row (cells as `str`);
    lines joined by newlines, no trailing newline."""
    header = [str(h) for h in header]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def metrics_markdown(results: dict[str, dict[str, float]], title: str | None = None) -> str:
    """Metric summaries {name: {"mean", "std", "count"}} as a markdown table (mean +- std over trajectories)."""
    lines = [f"### {title}", ""] if title else []
    rows = [(name, f"{s['mean']:.4e}", "" if math.isnan(s["std"]) else f"{s['std']:.3e}", s["count"])
            for name, s in results.items()]
    lines.append(markdown_table(["metric", "mean", "std over trajectories", "trajectories"], rows))
    return "\n".join(lines) + "\n"


def write_text(path: str | Path, text: str) -> Path:
    """Write `text` to `path` (parents created) via a temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_json(path: str | Path, data) -> Path:
    """`data` as indented JSON (`write_text`)."""
    return write_text(path, json.dumps(data, indent=2))


def write_csv(path: str | Path, rows: Iterable[Mapping], columns: Sequence[str]) -> Path:
    """Dict rows as CSV with the header `columns` (`write_text`): keys outside `columns` are dropped,
    missing keys and None are empty cells."""
    buffer = io.StringIO(newline="")
    writer = csv.DictWriter(buffer, fieldnames=list(columns), extrasaction="ignore")
    writer.writeheader()
    writer.writerows({k: ("" if v is None else v) for k, v in row.items()} for row in rows)
    return write_text(path, buffer.getvalue())
