"""Numerical stability at the extremes of the material range and of the collider speed."""
import numpy as np
import pytest

from ggns.config import load_config
from ggns.scenes.plate import make_trajectory
from ggns.sensors.camera import DepthSensor, SensorConfig


@pytest.mark.parametrize("nu", [-0.95, 0.499])
@pytest.mark.parametrize("speed", [1.0, 2.0])
def test_plate_stays_finite_passive_and_unpenetrated(nu, speed):
    cfg = load_config("plate", [f"scene.poissons_ratios=[{nu}]"])
    cfg["scene"]["collider"]["travel"] *= speed  # same duration, `speed` x the default velocity
    sensor = DepthSensor(SensorConfig.from_dict(cfg["sensor"]))
    # the widest trapezoid with the largest collider centred on it: the hardest push
    cfg["scene"]["collider"]["radius_fraction"] = [0.59, 0.6, 0.6]
    traj = make_trajectory(cfg, combination=6, seed=1, sensor=sensor)
    d = traj.diagnostics
    assert np.isfinite(traj.positions).all()
    # penetration within the stated tolerance at every frame
    assert d["max_penetration"].max() <= cfg["solver"]["contact_tolerance"]
    # passivity: the body never holds more energy than the collider has put into it
    energy = d["kinetic_energy"] + d["elastic_energy"]
    work = np.cumsum(d["contact_work"])
    assert np.all(energy <= work * 1.001 + 1e-9), (energy - work).max()
    assert energy[-1] > 0  # the collider did push
    # the fixed bottom edge never moved
    assert np.array_equal(traj.positions[:, traj.fixed], np.broadcast_to(traj.rest_positions[traj.fixed], traj.positions[:, traj.fixed].shape))
