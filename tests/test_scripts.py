"""The experiments' scripts (experiments/*/*.py) run end to end on tiny data, as their pages' commands do; the
GPU check's plan (scripts/gpu_check.sh --dry-run) and `bench ab`'s handling of a probe that fails."""
from __future__ import annotations

import csv
import os
import runpy
import subprocess
import sys
import tarfile
import time
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


def test_a_failing_ab_probe_is_reported_and_the_other_probes_still_run(tmp_path, capsys):
    """`bench ab` with a probe the probe script rejects: the other probe is measured on both trees and
    summarized as before, the failed runs are in ab_raw.csv and ab_summary.md with their error's last
    lines, the log's FAILED lines are read back by raw_from_log, and the run ends with ProbesFailed."""
    from ggns.bench.ab import ProbesFailed, bench_ab, raw_from_log, summarize

    with pytest.raises(ProbesFailed, match="2 of 4 probe runs failed.*'nonsense 1 2' on baseline"):
        bench_ab(str(ROOT), ("import ggns.config", "nonsense 1 2"), rounds=1, candidate=str(ROOT), output=str(tmp_path))
    raw = list(csv.DictReader((tmp_path / "ab_raw.csv").open()))
    assert [(r["probe"], r["tree"], bool(r["error"])) for r in raw] == [
        ("import ggns.config", "baseline", False), ("import ggns.config", "candidate", False),
        ("nonsense 1 2", "baseline", True), ("nonsense 1 2", "candidate", True)]
    assert all(r["error"].splitlines()[-1] == "KeyError: 'nonsense'" for r in raw[2:])
    summary = (tmp_path / "ab_summary.md").read_text()
    assert "| `import ggns.config` | ms |" in summary and "| `nonsense 1 2` |" not in summary
    assert "Failed: 2 of 4 probe runs" in summary and "- `nonsense 1 2` on candidate, round 1:" in summary
    assert summary.count("KeyError: 'nonsense'") == 2
    logged = raw_from_log(capsys.readouterr().out)
    assert [r.get("error") for r in logged] == [None, None, "KeyError: 'nonsense'", "KeyError: 'nonsense'"]
    assert [row["probe"] for row in summarize(logged)] == ["import ggns.config"]


GPU_STEPS = ["environment", "packages", "torch_cluster", "plate_small", "tests", "profile_static", "profile", "ab",
             "learning", "precision"]


def gpu_check_dry_run(tmp_path: Path, **env: str) -> tuple[subprocess.CompletedProcess, dict[str, dict], float]:
    """scripts/gpu_check.sh --dry-run with `env`: the process, steps.tsv's rows by step, its wall-clock seconds."""
    out = tmp_path / "out"
    start = time.perf_counter()
    done = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh"), "--dry-run", str(tmp_path / "kit"), str(out)],
                          env={**os.environ, **env}, capture_output=True, text=True, timeout=60)
    seconds = time.perf_counter() - start
    with open(out / "steps.tsv") as file:
        rows = {row["step"]: row for row in csv.DictReader(file, delimiter="\t")}
    return done, rows, seconds


def test_the_gpu_check_plan_fits_its_deadline_and_a_failing_step_stops_no_other(tmp_path):
    """Every step starts in the plan's order (two stubs failing), the budgets add up to at most the deadline
    less its margin, each step may use at least its budget, the exit status counts the failures, and the
    archive holds steps.tsv (with its totals) and every step's log."""
    done, rows, _ = gpu_check_dry_run(tmp_path, DRY_RUN_FAIL="tests ab")
    assert done.returncode == 2, done.stdout + done.stderr
    total = rows.pop("total")
    assert list(rows) == GPU_STEPS
    planned = [int(r["planned_s"]) for r in rows.values()]
    assert sum(planned) == int(total["planned_s"]) <= int(total["limit_s"]) == 450 - 20
    assert all(int(r["limit_s"]) >= int(r["planned_s"]) > 0 for r in rows.values())
    assert {name: r["status"] for name, r in rows.items() if r["status"] != "ok"} == {
        "tests": "failed (status 1)", "ab": "failed (status 1)"}
    assert total["status"] == "2 failed, 0 skipped"
    with tarfile.open(tmp_path / "out" / "gpu_check.tar.gz") as archive:
        names = set(archive.getnames())
        assert {"./steps.tsv", "./gpu_check.log"} | {f"./logs/{name}.log" for name in GPU_STEPS} <= names
        assert not any(name.endswith("gpu_check.tar.gz") for name in names)
        assert archive.extractfile("./steps.tsv").read().decode().splitlines()[-1].startswith("total\t")


def test_a_gpu_check_step_that_hangs_is_stopped_at_its_limit_and_the_later_steps_keep_their_budgets(tmp_path):
    """With a 20-second deadline the budgets are scaled down to fit; the second step hangs and is stopped at
    its limit (its budget and the time no step was promised), and every later step still runs."""
    done, rows, seconds = gpu_check_dry_run(tmp_path, DRY_RUN_HANG="packages", DEADLINE="20", MARGIN="0")
    assert done.returncode == 1, done.stdout + done.stderr
    total = rows.pop("total")
    later = sum(int(r["planned_s"]) for r in list(rows.values())[2:])
    limit = 20 - later  # the first step took well under a second
    assert int(total["planned_s"]) <= 20 and limit < 8  # keeps this test short
    assert rows["packages"]["status"] == f"timeout after {limit} s"
    assert all(r["status"] == "ok" and int(r["limit_s"]) >= int(r["planned_s"]) for name, r in rows.items()
               if name != "packages")
    assert total["status"] == "1 failed, 0 skipped" and (tmp_path / "out" / "gpu_check.tar.gz").is_file()
    assert limit <= seconds < limit + 5
