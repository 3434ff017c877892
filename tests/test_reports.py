"""The report writers (`ggns.reports`): markdown tables, and text / JSON / CSV files that an
interrupted or failed write never leaves truncated."""
from __future__ import annotations

import csv
import json

import pytest

from ggns.reports import markdown_table, write_csv, write_json, write_text


def test_markdown_table():
    assert markdown_table(["a", 1], [[1, "x"], [2.5, None]]) == "| a | 1 |\n|---|---|\n| 1 | x |\n| 2.5 | None |"


def test_json_round_trip_and_parents_created(tmp_path):
    path = write_json(tmp_path / "deep" / "dir" / "m.json", {"k": [1, 2.5], "n": None})
    assert json.loads(path.read_text()) == {"k": [1, 2.5], "n": None}
    assert [p.name for p in path.parent.iterdir()] == ["m.json"]  # no temporary file left


def test_a_failed_write_keeps_the_previous_file(tmp_path):
    path = write_json(tmp_path / "m.json", {"old": 1})
    with pytest.raises(TypeError):
        write_json(path, {"new": object()})  # not serializable: fails before anything is written
    assert json.loads(path.read_text()) == {"old": 1}
    with pytest.raises(TypeError):
        write_text(path, None)  # fails while writing the temporary file
    assert json.loads(path.read_text()) == {"old": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["m.json"]


def test_csv_columns_order_missing_and_extra_keys(tmp_path):
    path = write_csv(tmp_path / "t.csv", [{"b": 2, "a": 1, "extra": 9}, {"a": None}], ["a", "b"])
    with open(path, newline="") as f:
        assert list(csv.reader(f)) == [["a", "b"], ["1", "2"], ["", ""]]
