"""Stability at the extremes (`ggns.bench.stability`): long rollouts at and beyond the
training materials with the smallest and largest colliders, float32 against float64, on plate_tiny
(T = 8 pushed, then held) with small untrained simulators: every rollout is recorded, and one that
diverges is kept up to the step before and reported, not returned as garbage."""
from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from ggns.bench.stability import rollout_quantities, scenes, stability
from ggns.config import load_config
from ggns.models.simulators import GGNS, MGN
from ggns.scenes.plate import PlateSpec, collider_path
from conftest import make, save_untrained

pytestmark = pytest.mark.usefixtures("single_thread")
STEPS = 20


def test_the_plate_push_is_the_presets_then_held():
    scene = load_config("plate_tiny")["scene"]
    spec = PlateSpec(4, 0.0, 0.2, 0.0)
    pushed, _ = collider_path(scene, spec)
    longer = {**scene, "num_steps": STEPS, "collider": {**scene["collider"], "push_steps": scene["num_steps"] - 1}}
    held, _ = collider_path(longer, spec)
    assert held.shape[0] == STEPS and np.array_equal(held[: len(pushed)], pushed)
    assert np.array_equal(held[len(pushed):], np.repeat(pushed[-1:], STEPS - len(pushed), axis=0))
    configs = scenes(load_config("plate_tiny"), STEPS, [-0.9, 0.499])
    assert [(c["scene"]["poissons_ratios"], label) for c, label, _, _ in configs] == [
        ([-0.9], "smallest"), ([-0.9], "largest"), ([0.499], "smallest"), ([0.499], "largest")]
    assert len({seed for *_, seed in configs}) == 4


def test_quantities_of_a_rollout_against_its_truth():
    rest = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    cells = np.array([[0, 1, 2]])
    truth = np.stack([rest, rest + [0.0, 0.1]])
    flipped = np.stack([rest, rest * [1.0, -1.0]])  # the triangle mirrored: inverted
    q = rollout_quantities(flipped, truth, rest, cells, frame_dt=0.1)
    assert q["inverted_share"].tolist() == [0.0, 1.0] and q["true_inverted_share"].tolist() == [0.0, 0.0]
    assert q["mse"][0] == 0 and q["mse"][1] == pytest.approx(((flipped[1] - truth[1]) ** 2).mean())
    assert q["max_speed"][1] == pytest.approx(20.0) and q["true_max_speed"][1] == pytest.approx(1.0)
    assert q["size_ratio"][1] == pytest.approx(1.0)


def test_long_rollouts_are_recorded_and_a_divergence_is_reported(tmp_path):
    ggns = save_untrained(make(GGNS), tmp_path / "ggns.ckpt")
    blowing_up = make(MGN)
    blowing_up.target_normalizer.std.fill_(1e4)  # every step moves nodes by ~1e4 m: escapes at once
    mgn = save_untrained(blowing_up, tmp_path / "mgn.ckpt")
    summary = stability("plate_tiny", {"ggns": str(ggns), "mgn": str(mgn)}, steps=STEPS, stride=5,
                        output_dir=tmp_path / "out", log=lambda *_: None)
    # 5 materials (3 training, 2 beyond) x 2 colliders; GGNS 2 schedules, MGN 1; 2 dtypes
    assert len(summary) == 10 * (2 + 1) * 2
    assert {(r["poissons_ratio"], r["material"]) for r in summary} == {
        (-0.95, "beyond"), (-0.9, "training"), (0.0, "training"), (0.49, "training"), (0.499, "beyond")}
    for row in summary:
        if row["model"] == "mgn":
            assert row["diverged"].startswith("state 1: rollout diverged at prediction step 0") and row["states"] == 1
            assert "from its start, more than 100 x" in row["diverged"]
        else:
            assert row["diverged"] == "" and row["states"] == STEPS and np.isfinite(row["mse_last"])
            assert 0.0 <= row["true_inverted_max"] <= 1.0  # the simulator inverts a few cells here (fast push)
            if row["dtype"] == "float64":
                assert row["drift_last"] is not None and 0 <= row["drift_last"] < 1e-3
    with open(tmp_path / "out" / "stability.csv") as f:
        rows = list(csv.DictReader(f))
    assert sorted({int(r["step"]) for r in rows if r["model"] == "ggns"}) == [0, 5, 10, 15]
    assert {r["schedule"] for r in rows if r["model"] == "ggns"} == {"every:1", "never"}
    text = (tmp_path / "out" / "stability.md").read_text()
    assert "| mgn | never | float32 | +0.499 | beyond | largest | state 1 |" in text
    assert (tmp_path / "out" / "stability.png").stat().st_size > 10_000
