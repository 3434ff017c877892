"""The experiments' scripts (experiments/*/*.py) run end to end on tiny data, as their pages' commands do."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from ggns.models.simulators import GGNSID
from conftest import make, save_untrained

ROOT = Path(__file__).resolve().parents[1]


def test_material_trace_prints_the_estimate_along_rollouts(tiny_data_dir, tmp_path):
    """experiments/material_estimator/material_trace.py (docs/experiments/material_estimator.md) on an untrained GGNSID: one row
    per k and 5th step with finite errors (the estimate starts at the prior: never nan for GGNSID), and
    the oracle table with both rollouts."""
    model = make(GGNSID, latent=8, blocks=1, estimator_latent=8, estimator_blocks=1)
    checkpoint = save_untrained(model, tmp_path / "ggns_id.ckpt")
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, str(ROOT / "experiments" / "material_estimator" / "material_trace.py"), str(checkpoint),
                          "--dataset", "plate_tiny", "--data-dir", str(tiny_data_dir), "--trajectories", "2",
                          "--schedules", "1,5", "--oracle"], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [line.split("|")[1:-1] for line in out.stdout.splitlines() if line.startswith("| 1 |") or line.startswith("| 5 |")]
    assert [(r[0].strip(), r[1].strip()) for r in rows] == [("1", "5"), ("5", "5")]  # T = 8: step 5 only
    for row in rows:
        assert all(cell.strip() not in ("nan", "inf") for cell in row[2:]), row
    assert "| k=1 |" in out.stdout and "| never |" in out.stdout
