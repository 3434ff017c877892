"""Rollout pictures of real (tiny, untrained) simulators on plate_tiny: the figure's point clouds on
the point-using model only, the animation, and the error curves of every model and schedule."""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.collections import PathCollection
from PIL import Image

from ggns.batch import TrajectoryBatch
from ggns.evaluation.pictures import error_curves, rollout_animation, rollout_picture, rollout_series, series_errors
from ggns.models.simulators import GGNS, MGN

from conftest import T


@pytest.fixture(scope="module")
def models(train_batch, single_thread):
    """Untrained GGNS and MGN (latent 8, one block) with normalizers fitted on two training windows."""
    import torch

    out = {}
    for name, cls in (("GGNS", GGNS), ("MGN", MGN)):
        torch.manual_seed(0)
        model = cls(latent=8, blocks=1)
        model.fit_normalizers([train_batch])
        out[name] = model.eval()
    return out


@pytest.fixture(scope="module")
def one(trajs):
    """The first validation trajectory and its batch."""
    traj = trajs["val"][0]
    return traj, TrajectoryBatch.from_trajectories([traj])


def test_picture_and_animation_share_one_rollout(models, one, tmp_path, monkeypatch):
    traj, batch = one
    series = rollout_series(batch, models, "every:2")
    assert set(series[0]) == {"GGNS (every:2)", "MGN (never)"}
    for model in models.values():  # given the series, nothing is rolled out again
        monkeypatch.setattr(model, "rollout", lambda *args: pytest.fail("rolled out twice"))
    fig = rollout_picture(batch, traj.collider_faces, models, "every:2", num_frames=3, series=series)
    steps = [int(ax.get_title().removeprefix("t=")) for ax in fig.axes[:3]]
    assert steps == [0, 4, T - 1]
    clouds = [sum(isinstance(c, PathCollection) for c in ax.collections) for ax in fig.axes]
    assert clouds == [1, 1, 0, 0, 0, 0]  # GGNS's row at steps 0 and 4 (every:2; the last state gives none), MGN never
    plt.close(fig)
    path = rollout_animation(batch, traj.collider_faces, models, "every:2", tmp_path / "rollout.gif", series=series)
    assert path.stat().st_size > 0
    with Image.open(path) as image:
        assert image.n_frames == T


def test_error_curves_of_every_model_and_schedule(models, val_batch):
    """Over both validation trajectories; MGN runs `never` once, whatever the schedules."""
    curves = error_curves(val_batch, models, ["every:1", "every:5", "never"])
    assert list(curves) == ["GGNS (every:1)", "GGNS (every:5)", "GGNS (never)", "MGN (never)"]
    for curve in curves.values():
        assert curve.shape == (T,) and np.isfinite(curve).all() and curve[0] == 0 and (curve[1:] > 0).all()
    # the same numbers from rollouts the caller already has
    again = series_errors(val_batch, {"MGN (never)": models["MGN"].rollout(val_batch, "never")})
    np.testing.assert_allclose(again["MGN (never)"], curves["MGN (never)"])
