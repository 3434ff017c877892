"""Generate dataset splits: trajectories are simulated and observed in worker processes and
written in order, through `SplitWriter`, to one HDF5 file per split.

Determinism: trajectory i of a split gets the seed SeedSequence([seed, split code, i]), so its
arrays depend neither on the number of workers nor on the other trajectories, and the seed
stored with it regenerates it alone. Balanced splits cycle through the scene's shape x
material combinations (trajectory i uses combination i mod their number).
"""
from __future__ import annotations

import multiprocessing as mp
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..scenes import SCENES
from ..sensors.camera import DepthSensor, SensorConfig
from .schema import SplitWriter

SPLIT_CODES = {"train": 0, "val": 1, "test": 2}

_worker_state: dict = {}


def trajectory_seed(seed: int, split: str, index: int) -> int:
    """The 63-bit seed of trajectory `index` of `split`."""
    if split not in SPLIT_CODES:
        raise ValueError(f"unknown split {split!r}; expected one of {sorted(SPLIT_CODES)}")
    state = np.random.SeedSequence([int(seed), SPLIT_CODES[split], int(index)]).generate_state(1, np.uint64)[0]
    return int(state >> np.uint64(1))


def _init_worker(config: dict) -> None:
    torch.set_num_threads(1)
    _worker_state["config"] = config
    _worker_state["scene"] = SCENES[config["scene"]["name"]]
    _worker_state["sensor"] = DepthSensor(SensorConfig.from_dict(config["sensor"]))


def _make(job: tuple[int, int]):
    combination, seed = job
    scene = _worker_state["scene"]
    try:
        return scene.make_trajectory(_worker_state["config"], combination, seed, _worker_state["sensor"])
    except Exception as error:  # name the trajectory, keep the cause
        raise RuntimeError(f"trajectory with seed {seed} (combination {combination}): {error}") from error


def regenerate(config: dict, combination: int, seed: int):
    """One trajectory exactly as `generate` made it (e.g. from a file's generator_config and a stored
    seed). Generation runs torch single-threaded, and float reductions depend on the thread
    count, so this pins torch to 1 thread while it simulates and restores the setting after."""
    threads = torch.get_num_threads()
    try:
        _init_worker(config)
        return _make((combination, seed))
    finally:
        torch.set_num_threads(threads)


def split_path(output: str | Path, split: str) -> Path:
    return Path(output) / f"{split}.h5"


def trajectory_jobs(config: dict, split: str, count: int) -> list[tuple[int, int]]:
    """The (shape x material combination, seed) of each of a split's first `count` trajectories:
    combinations cycled in order (balanced splits), seeds derived from the config's seed."""
    combos = SCENES[config["scene"]["name"]].num_combinations(config["scene"])
    return [(i % combos, trajectory_seed(config["seed"], split, i)) for i in range(count)]


def generate(config: dict, splits: list[str] | None = None, *, overwrite: bool = False, progress: bool = True) -> list[Path]:
    """Generate the splits named in config['splits'] (or the given subset) into
    <output>/<split>.h5, with config['workers'] processes; returns the file paths."""
    name, sizes = config["scene"]["name"], config["splits"]
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; known: {sorted(SCENES)}")
    SCENES[name].check_config(config)
    SensorConfig.from_dict(config["sensor"])
    chosen = list(sizes) if splits is None else list(splits)
    unknown = [s for s in chosen if s not in sizes]
    if unknown:
        raise ValueError(f"splits {unknown} have no size in the config (sizes given: {sizes})")
    bad = {s: sizes[s] for s in chosen if int(sizes[s]) < 1}
    if bad:
        raise ValueError(f"split sizes must be >= 1, got {bad}")
    paths = [split_path(config["output"], s) for s in chosen]
    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{existing} already exist; pass --overwrite (overwrite=True) to replace them")
    workers = max(1, int(config["workers"]))
    dim = SCENES[name].DIM
    pool, threads = None, torch.get_num_threads()
    if workers > 1:
        pool = mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(config,))
    else:
        _init_worker(config)  # in this process: its thread setting is restored below
    try:
        for split, path in zip(chosen, paths):
            jobs = trajectory_jobs(config, split, int(sizes[split]))
            results = pool.imap(_make, jobs) if pool else map(_make, jobs)
            with SplitWriter(path, scene=name, split=split, dim=dim, generator_config=config, overwrite=overwrite) as writer:
                with tqdm(total=len(jobs), desc=f"{name}/{split}", unit="traj", disable=not progress) as bar:
                    for trajectory in results:
                        writer.append(trajectory)
                        bar.update()
    finally:
        if pool is not None:
            pool.terminate()
        torch.set_num_threads(threads)
    return paths
