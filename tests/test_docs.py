"""The documentation site builds with `mkdocs build --strict`: a link to a page or file that does not
exist, a page missing from the API reference's imports or a docstring mkdocstrings cannot read fails it."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_documentation_site_builds_strictly(tmp_path):
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    warnings = [line for line in done.stderr.splitlines() if line.startswith(("WARNING", "ERROR"))]
    assert done.returncode == 0, "\n".join(warnings) or done.stderr[-3000:]
    api = (tmp_path / "site" / "api" / "index.html").read_text(encoding="utf-8")
    for name in ("ggns.pretrained.load", "trajectory_from_arrays", "TrajectoryBatch", "GGNS", "SimulationDataModule"):
        assert name in api, name
