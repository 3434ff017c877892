"""The README's and docs/results.md's results tables are what `python -m ggns paper --compact` makes of the committed sweep summaries
(each table follows a comment naming its command's arguments), and the README stays short."""
from __future__ import annotations

import re
import shlex

import pytest

from pathlib import Path
from ggns.sweeps.paper import paper_table

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MARKER = re.compile(r"<!-- python -m ggns paper (.+?) -->\n\n(.*?)\n\n(Ours: [^\n]*)", re.S)


RESULTS = ROOT / "docs" / "results.md"


def tables(path: Path = README) -> list[tuple[str, str, str]]:
    return MARKER.findall(path.read_text(encoding="utf-8"))


def test_the_readme_is_short_and_has_one_generated_table_per_task():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 160
    tasks = [dict(arg.split(" ", 1) for arg in re.findall(r"--\w+ [^-\s][^\s]*", args))["--task"]
             for args, _, _ in tables()]
    assert tasks == ["plate", "tissue", "cavity"]


def test_the_results_index_has_one_generated_table_per_task():
    assert [shlex.split(args)[1] for args, _, _ in tables(RESULTS)] == ["plate", "tissue", "cavity"]


@pytest.mark.parametrize("args, table, source", tables() + tables(RESULTS),
                         ids=lambda v: v[:40] if isinstance(v, str) else None)
def test_each_readme_table_is_generated_from_committed_summaries(args, table, source):
    words = shlex.split(args)
    assert "--compact" in words
    task = words[words.index("--task") + 1]
    summaries = dict(words[i + 1].split("=", 1) for i, w in enumerate(words) if w == "--summary")
    for paths in summaries.values():
        for path in paths.split(","):
            assert (ROOT / path).is_file(), path
    import os
    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        expected = paper_table(task, summaries, compact=True).strip()
    finally:
        os.chdir(cwd)
    assert f"{table}\n\n{source}" == expected


def test_every_relative_link_of_the_readme_exists():
    text = README.read_text(encoding="utf-8")
    targets = {t.split("#")[0] for t in re.findall(r"\]\(([^)]+)\)", text) if not t.startswith(("http", "#"))}
    assert targets and not [t for t in sorted(targets) if not (ROOT / t).exists()]
