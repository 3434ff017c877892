"""The experiments' scripts (experiments/*/*.py) run end to end on tiny data, as their pages' commands do."""
from __future__ import annotations

import runpy
import sys
from pathlib import Path

import pytest

from ggns.models.simulators import GGNSID
from conftest import make, save_untrained

ROOT = Path(__file__).resolve().parents[1]


def test_material_trace_prints_the_estimate_along_rollouts(tiny_data_dir, tmp_path, capsys):
    """experiments/material_estimator/material_trace.py (docs/experiments/material_estimator.md) on an untrained GGNSID: one row
    per k and 5th step with finite errors (the estimate starts at the prior: never nan for GGNSID), and
    the oracle table with both rollouts."""
    model = make(GGNSID, latent=8, blocks=1, estimator_latent=8, estimator_blocks=1)
    checkpoint = save_untrained(model, tmp_path / "ggns_id.ckpt")
    script = ROOT / "experiments" / "material_estimator" / "material_trace.py"
    capsys.readouterr()
    with pytest.MonkeyPatch.context() as patch:  # run as `python <script> ...` would, in this process
        patch.setattr(sys, "argv", [str(script), str(checkpoint), "--dataset", "plate_tiny", "--data-dir",
                                    str(tiny_data_dir), "--trajectories", "2", "--schedules", "1,5", "--oracle"])
        runpy.run_path(str(script), run_name="__main__")
    stdout = capsys.readouterr().out
    rows = [line.split("|")[1:-1] for line in stdout.splitlines() if line.startswith("| 1 |") or line.startswith("| 5 |")]
    assert [(r[0].strip(), r[1].strip()) for r in rows] == [("1", "5"), ("5", "5")]  # T = 8: step 5 only
    for row in rows:
        assert all(cell.strip() not in ("nan", "inf") for cell in row[2:]), row
    assert "| k=1 |" in stdout and "| never |" in stdout
