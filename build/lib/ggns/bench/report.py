"""The one table printer of the benchmarks."""
from __future__ import annotations

from typing import Sequence


def format_value(key: str, value) -> str:
    """A table cell: shares as percentages, floats to 3 significant digits (whole numbers from 100)."""
    if isinstance(value, float):
        if "share" in key:
            return f"{value:.0%}"
        return f"{value:.3g}" if abs(value) < 100 else f"{value:.0f}"
    return str(value)


def print_table(rows: list[dict], columns: Sequence[str] | None = None, transpose: bool = False,
                label_keys: Sequence[str] = ()) -> None:
    """Rows as an aligned text table: one line per row and one column per key (`columns`, default
    every key in first-seen order); transpose=True prints one line per key and one column per row,
    headed by the row's `label_keys` values (for long quantity names and short values)."""
    keys = list(columns) if columns is not None else list(dict.fromkeys(k for row in rows for k in row))
    keys = [k for k in keys if any(k in row for row in rows)]
    if transpose:
        header = ["quantity"] + [" ".join(str(row[k]) for k in label_keys if k in row) for row in rows]
        table = [[k] + [format_value(k, row.get(k, "")) for row in rows] for k in keys if k not in label_keys]
    else:
        header = keys
        table = [[format_value(k, row.get(k, "")) for k in keys] for row in rows]
    widths = [max(len(line[j]) for line in [header] + table) for j in range(len(header))]
    for line in [header] + table:
        if transpose:
            print("  " + "  ".join(v.ljust(w) if j == 0 else v.rjust(w) for j, (v, w) in enumerate(zip(line, widths))))
        else:
            print("  ".join(v.rjust(w) for v, w in zip(line, widths)))
