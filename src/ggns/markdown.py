"""The markdown table writer of every report the library writes (test metrics, the scale check, sweep
summaries, findings, learning tables, the demo's report)."""
from __future__ import annotations

from collections.abc import Iterable, Sequence


def table(header: Sequence, rows: Iterable[Sequence]) -> str:
    """A markdown table: the header row, the separator, then one line per row (cells as `str`);
    lines joined by newlines, no trailing newline."""
    header = [str(h) for h in header]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)
