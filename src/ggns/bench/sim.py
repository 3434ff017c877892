"""`python -m ggns bench sim`: the ground-truth simulator and the depth sensor, timed trajectory by
trajectory on one thread (as a generation worker runs), and optionally the generation of all of a
preset's splits with its worker count."""
from __future__ import annotations

import platform
import statistics
import tempfile
import time

import numpy as np

from ..config import load_config
from ..data.generate import generate, trajectory_seed
from ..scenes import SCENES
from ..sensors.camera import DepthSensor, SensorConfig
from .timing import median_ms, time_trajectories


def bench_sim(preset: str = "plate", trajectories: int = 9, generate_splits: bool = False) -> dict:
    """Time the ground-truth simulator and the depth sensor trajectory by trajectory on one thread
    (as a generation worker runs), over `trajectories` of the preset's training jobs spread over its
    shape x material combinations; with `generate_splits`, also the generation of all the preset's
    splits with its worker count. Prints and returns the medians."""
    config = load_config(preset)
    scene_module = SCENES[config["scene"]["name"]]
    sensor = DepthSensor(SensorConfig.from_dict(config["sensor"]))
    combos = scene_module.num_combinations(config["scene"])
    jobs = [((i * 7) % combos, trajectory_seed(config["seed"], "train", i)) for i in range(trajectories)]
    sim_step, sensor_step, whole, newton = [], [], [], []
    for seconds, traj in time_trajectories(scene_module, config, jobs, sensor):
        whole.append(seconds)
        # observe the recorded states again to split the time between sensor and simulator
        start = time.perf_counter()
        for t in range(traj.num_steps):
            sensor.observe(traj.positions[t], traj.cells, traj.collider_positions[t], traj.collider_faces)
        observe = time.perf_counter() - start
        sensor_step.append(observe / traj.num_steps)
        sim_step.append((seconds - observe) / (traj.num_steps - 1))
        newton.append(traj.diagnostics["newton_iterations"][1:].mean())
    result = {
        "machine": f"{platform.processor() or platform.machine()}, 1 torch thread",
        "simulator ms/step (median, incl. scene set-up)": median_ms(sim_step),
        "sensor ms/step (median)": median_ms(sensor_step),
        "trajectory s (median, simulate + observe)": statistics.median(whole),
        "Newton iterations/step (mean)": float(np.mean(newton)),
        "trajectories timed": trajectories,
    }
    if generate_splits:
        total = sum(config["splits"].values())
        with tempfile.TemporaryDirectory() as out:
            start = time.perf_counter()
            generate(dict(config, output=out), progress=True)
            elapsed = time.perf_counter() - start
        result[f"generate all splits ({total} trajectories, {config['workers']} workers) s"] = elapsed
    print(f"bench sim: preset {preset!r}, {config['scene']['num_steps']} steps per trajectory")
    for key, value in result.items():
        print(f"  {key:58s} {value:.3f}" if isinstance(value, float) else f"  {key:58s} {value}")
    return result
