"""Timing shared by the benchmarks: one device synchronization, medians in ms, the device choice,
the timed ground-truth trajectories (`time_trajectories`) and the timed rollouts of a learned
simulator (`time_rollout`)."""
from __future__ import annotations

import statistics
import time

import numpy as np
import torch

from ..evaluation.rollout import rollout
from ..graphs.state import ConstructionTimer
from ..trajectory import Trajectory


def sync(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA), so that a wall-clock time is the work's own."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def median_ms(values: list[float]) -> float:
    """The median of times in seconds, in ms."""
    return 1e3 * statistics.median(values)


def resolve_device(device: str) -> torch.device:
    """`device` ("cpu" or "cuda[:i]") checked: ValueError if CUDA is asked for and missing."""
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {device} requested but CUDA is not available "
                         f"(torch {torch.__version__}, built with CUDA: {torch.version.cuda or 'no'})")
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be cpu or cuda, got {device}")
    return device


def default_devices() -> list[str]:
    """The CPU, and CUDA when present."""
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


class NoSensor:
    """Stands in for the depth sensor: an empty point cloud per state (the simulator alone is timed)."""

    def __init__(self, dim: int = 2):
        self.dim = dim

    def observe(self, *args, **kwargs) -> np.ndarray:
        return np.zeros((0, self.dim), dtype=np.float32)


def time_trajectories(scene_module, config: dict, jobs: list[tuple[int, int]], sensor) -> list[tuple[float, Trajectory]]:
    """(seconds, trajectory) of `scene_module.make_trajectory(config, combination, seed, sensor)` for
    each (combination, seed) job, on one torch thread as a generation worker runs (the caller's
    thread count is restored); the time is the whole call, scene set-up included."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        timed = []
        for combination, seed in jobs:
            start = time.perf_counter()
            trajectory = scene_module.make_trajectory(config, combination, seed, sensor)
            timed.append((time.perf_counter() - start, trajectory))
        return timed
    finally:
        torch.set_num_threads(threads)


def time_rollout(model, batch, schedule, steps: int, repeats: int, device: torch.device) -> dict:
    """Median ms per rollout step of `model` on `batch` under `schedule` (after one warm-up step,
    `repeats` rollouts of `steps` steps) and the median share of it spent building graphs."""
    model.eval()
    with torch.no_grad(), ConstructionTimer(device) as timer:
        rollout(model.step, batch, schedule, model.connectivity, model.with_material, steps=1)  # warm-up
        times, shares = [], []
        for _ in range(repeats):
            timer.reset()
            sync(device)
            start = time.perf_counter()
            rollout(model.step, batch, schedule, model.connectivity, model.with_material, steps=steps)
            sync(device)
            elapsed = time.perf_counter() - start
            times.append(elapsed / steps)
            shares.append(timer.seconds / elapsed)
    return {"ms per step": median_ms(times), "graph construction share": statistics.median(shares)}
