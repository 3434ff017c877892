"""Generate dataset splits: trajectories are simulated and observed in worker processes, each kept
as its own file as soon as it is finished, and written in order, through `SplitWriter`, to one HDF5
file per split when all are made; a killed generator's rerun continues from the kept ones
(`resume`).

Determinism: trajectory i of a split gets the seed SeedSequence([seed, split code, i]), so its
arrays depend neither on the number of workers nor on the other trajectories, and the seed
stored with it regenerates it alone. Balanced splits cycle through the scene's shape x
material combinations (trajectory i uses combination i mod their number).

Shards (a cluster's job array, `generate --shard i/n`): shard i of n makes the trajectories j of each
split with j mod n = i, into its own file <split>.shard-<i>-of-<n>.h5 (resumable like a whole split);
the shards need nothing from each other, so n machines make a split in 1/n of the time.
The data module reads a split's shards as they are when there is no <split>.h5 (`shard_files`,
`interleave_shards`: the same trajectories in the same order), so nothing has to run on one machine;
`merge_shards` writes <split>.h5 from the n shard files, trajectory j from shard j mod n after
checking its configuration and seed, bit for bit the file one machine would have made (for the
commands that take one split file; it only copies arrays, 26 s for the cavity_cpu train split's 150
trajectories, 686 MB, beside two training runs; the shard files are kept).

Other cameras, same trajectories: a preset with `states_from: <data preset>` (same scene, solver
and seed, another sensor) does not simulate. It reads the states of that preset's split files
(generating a missing one first) and observes them with its own cameras (the scene's
`observe_trajectory`): the cavity_cpu camera presets took 38 s and 60 s for 204 trajectories,
whose simulation took 23 minutes (docs/benchmarks.md). Without sensor noise
the result is bit for bit what a full generation with this preset makes, so a file's stored
generator config and seeds still regenerate each trajectory alone (`regenerate`).
"""
from __future__ import annotations

import multiprocessing as mp
import re
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from . import split_path  # noqa: F401 (importable from here as before)
from ..scenes import SCENES
from ..sensors.camera import DepthSensor, SensorConfig
from .resume import SplitParts, remove_stale_partials
from .schema import DatasetError, SplitReader, SplitWriter, config_differences

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


def _observe(trajectory):
    """A stored trajectory observed with this worker's sensor (`states_from`)."""
    try:
        return _worker_state["scene"].observe_trajectory(trajectory, _worker_state["sensor"])
    except Exception as error:
        raise RuntimeError(f"trajectory with seed {trajectory.seed}: {error}") from error


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


def trajectory_jobs(config: dict, split: str, count: int) -> list[tuple[int, int]]:
    """The (shape x material combination, seed) of each of a split's first `count` trajectories:
    combinations cycled in order (balanced splits), seeds derived from the config's seed."""
    combos = SCENES[config["scene"]["name"]].num_combinations(config["scene"])
    return [(i % combos, trajectory_seed(config["seed"], split, i)) for i in range(count)]


def shard_path(output: str | Path, split: str, shard: int, shards: int) -> Path:
    return Path(output) / f"{split}.shard-{shard}-of-{shards}.h5"


def shard_files(output: str | Path, split: str) -> list[Path]:
    """The shard files <split>.shard-<i>-of-<n>.h5 in `output`, in shard order ([] if there are none);
    a DatasetError when some of the n are missing or shards of two counts lie side by side."""
    found = {}
    for path in Path(output).glob(f"{split}.shard-*-of-*.h5"):
        match = re.fullmatch(rf"{re.escape(split)}\.shard-(\d+)-of-(\d+)\.h5", path.name)
        if match:
            found.setdefault(int(match.group(2)), {})[int(match.group(1))] = path
    if not found:
        return []
    if len(found) > 1:
        raise DatasetError(f"{output}: {split} shards of {sorted(found)} shards lie side by side; keep one set")
    ((shards, files),) = found.items()
    missing = [i for i in range(shards) if i not in files]
    if missing:
        names = ", ".join(shard_path(output, split, i, shards).name for i in missing[:8])
        raise DatasetError(f"{output}: {split} shards {missing[:8]} of {shards} are missing ({names}; "
                           f"make them with generate --shard i/{shards})")
    return [files[i] for i in range(shards)]


def check_shard_sizes(sizes: list[int]) -> None:
    """Refuse (DatasetError) shard sizes that are not those of one split cut into len(sizes) shards
    (shard i holds the trajectories j with j mod n = i, so the sizes fall by at most one, in order)."""
    if any(a < b for a, b in zip(sizes, sizes[1:])) or (sizes and sizes[0] - sizes[-1] > 1):
        raise DatasetError(f"shard sizes {sizes} are not those of one split cut into {len(sizes)} shards")


def interleave_shards(shards: list[list]) -> list:
    """The split's items in order from its shards' (trajectory j is item j // n of shard j mod n)."""
    sizes = [len(s) for s in shards]
    check_shard_sizes(sizes)
    return [shards[j % len(shards)][j // len(shards)] for j in range(sum(sizes))]


def read_shards(files: list[Path], config: dict, split: str) -> list:
    """The trajectories of a split from its shard files (`shard_files`), in the split's order, each
    shard checked against `config` (read_trajectories) and each trajectory against its seed."""
    from .schema import read_trajectories

    trajectories = interleave_shards([read_trajectories(f, expected_config=config) for f in files])
    for j, trajectory in enumerate(trajectories):
        check_shard_seed(files, config, split, j, trajectory.seed)
    return trajectories


def check_shard_seed(files: list[Path], config: dict, split: str, j: int, seed: int) -> None:
    """Refuse (DatasetError naming the shard file) trajectory j of a split read from its shard files
    when its stored seed is not that of trajectory j of `config`'s split (another seed or shard set)."""
    if seed != trajectory_seed(config["seed"], split, j):
        raise DatasetError(f"{files[j % len(files)]}: trajectory {j // len(files)} has seed {seed}, "
                           f"not that of trajectory {j} of this preset's {split} split (another seed or shard set)")


def parse_shard(text: str) -> tuple[int, int]:
    """"i/n" -> (i, n), with 0 <= i < n."""
    try:
        shard, shards = (int(x) for x in str(text).split("/"))
    except ValueError:
        raise ValueError(f"--shard must be i/n (shard i of n, from 0), got {text!r}") from None
    if not 0 <= shard < shards:
        raise ValueError(f"--shard {text}: need 0 <= i < n")
    return shard, shards


def generate(config: dict, splits: list[str] | None = None, *, overwrite: bool = False, progress: bool = True,
             shard: tuple[int, int] | None = None) -> list[Path]:
    """Generate the splits named in config['splits'] (or the given subset) into
    <output>/<split>.h5, with config['workers'] processes; returns the file paths. shard (i, n):
    only the trajectories j with j mod n = i, into <split>.shard-<i>-of-<n>.h5 (module docstring)."""
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
    source = check_states_from(config) if config.get("states_from") else None
    paths = [split_path(config["output"], s) if shard is None else shard_path(config["output"], s, *shard)
             for s in chosen]
    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{existing} already exist; pass --overwrite (overwrite=True) to replace them")
    workers = max(1, int(config["workers"]))
    dim = SCENES[name].DIM
    pool, threads = None, torch.get_num_threads()
    if workers > 1:
        # the sensor first built here: a missing open3d or a bad sensor fails in this process with its own
        # error, not in a worker initializer, which multiprocessing.Pool would restart without end
        DepthSensor(SensorConfig.from_dict(config["sensor"]))
        pool = mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(config,))
    else:
        _init_worker(config)  # in this process: its thread setting is restored below
    log = print if progress else (lambda *_: None)
    try:
        for split, path in zip(chosen, paths):
            jobs = trajectory_jobs(config, split, int(sizes[split]))
            mine = list(range(len(jobs))) if shard is None else list(range(shard[0], len(jobs), shard[1]))
            if not mine:
                raise ValueError(f"shard {shard[0]}/{shard[1]} of the {split} split's {len(jobs)} trajectories is empty")
            remove_stale_partials(path.parent, log)
            parts = SplitParts(path, config, scene=name, split=split, dim=dim, log=log)
            done = parts.done(jobs)
            todo = [i for i in mine if i not in done]
            if source is not None:
                stored = stored_states(config, source, split, len(jobs), progress=progress, indices=todo)
                results = pool.imap(_observe, stored) if pool else map(_observe, stored)
            else:
                todo_jobs = [jobs[i] for i in todo]
                results = pool.imap(_make, todo_jobs) if pool else map(_make, todo_jobs)
            with tqdm(total=len(mine), initial=len(mine) - len(todo), desc=f"{name}/{split}", unit="traj",
                      disable=not progress) as bar:
                for index, trajectory in zip(todo, results):
                    parts.write(index, trajectory)
                    bar.update()
            parts.merge(len(jobs), overwrite=overwrite, indices=mine)
    finally:
        if pool is not None:
            pool.terminate()
        torch.set_num_threads(threads)
    return paths


def merge_shards(config: dict, shards: int, splits: list[str] | None = None, *, overwrite: bool = False,
                 progress: bool = True) -> list[Path]:
    """<split>.h5 from the `shards` files <split>.shard-<i>-of-<shards>.h5 of `generate(shard=...)`:
    trajectory j from shard j mod shards, each shard checked to hold this config's trajectories
    (configuration, count, seeds), written atomically; returns the split files. The shards are kept."""
    if shards < 1:
        raise ValueError(f"--merge-shards needs the number of shards (>= 1), got {shards}")
    name, sizes = config["scene"]["name"], config["splits"]
    chosen = list(sizes) if splits is None else list(splits)
    paths = []
    for split in chosen:
        path = split_path(config["output"], split)
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} already exists; pass --overwrite (overwrite=True) to replace it")
        jobs = trajectory_jobs(config, split, int(sizes[split]))
        files = [shard_path(config["output"], split, i, shards) for i in range(shards)]
        missing = [str(f) for f in files if not f.exists()]
        if missing:
            raise FileNotFoundError(f"shards {missing[:4]} are missing: generate them (generate --shard i/{shards})")
        readers = []
        try:
            for i, file in enumerate(files):
                reader = SplitReader(file)
                readers.append(reader)
                differ = config_differences(reader.generator_config, config)
                if reader.generator_config.get("seed") != config["seed"]:
                    differ.append(f"seed {reader.generator_config.get('seed')} there, {config['seed']} here")
                if differ:
                    raise DatasetError(f"{file}: made with another configuration ({', '.join(differ[:4])})")
                expected = len(range(i, len(jobs), shards))
                if len(reader) != expected:
                    raise DatasetError(f"{file}: holds {len(reader)} trajectories, shard {i}/{shards} of {len(jobs)} "
                                       f"has {expected}")
            with SplitWriter(path, scene=name, split=split, dim=SCENES[name].DIM, generator_config=config,
                             overwrite=overwrite) as writer:
                for j in tqdm(range(len(jobs)), desc=f"merge {split}", unit="traj", disable=not progress):
                    reader, k = readers[j % shards], j // shards
                    if reader.seed(k) != jobs[j][1]:
                        raise DatasetError(f"{files[j % shards]}: trajectory {k} has seed {reader.seed(k)}, "
                                           f"trajectory {j} of the split has {jobs[j][1]}")
                    writer.append(reader[k])
        finally:
            for reader in readers:
                reader.close()
        paths.append(path)
    return paths


# What must agree between a preset and the preset whose states it re-observes (`states_from`)
STATES_SECTIONS = ("scene", "solver")


def check_states_from(config: dict) -> dict:
    """The generator config of the preset named by config['states_from'], after checking that its
    trajectories are this preset's: same scene, solver and seed, and no sensor noise here (noise
    draws follow the simulation's random stream, which re-observation does not replay)."""
    from ..config import load_config

    name = config["states_from"]
    if not hasattr(SCENES[config["scene"]["name"]], "observe_trajectory"):
        raise ValueError(f"states_from: the {config['scene']['name']} scene cannot re-observe stored states "
                         f"(no observe_trajectory); generate this preset in full instead")
    if float(config["sensor"].get("noise_std", 0.0)) > 0:
        raise ValueError(f"states_from: re-observation reproduces a full generation only without sensor noise "
                         f"(sensor.noise_std is {config['sensor']['noise_std']}); generate this preset in full instead")
    source = load_config(name)
    differ = config_differences(source, config, STATES_SECTIONS)
    if source["seed"] != config["seed"]:
        differ.append(f"seed ({source['seed']} there, {config['seed']} here)")
    if differ:
        raise ValueError(f"states_from: preset {name!r} makes other trajectories than this one "
                         f"(differs in {', '.join(differ[:6])}); its states cannot stand for this preset's")
    return source


def stored_states(config: dict, source: dict, split: str, count: int, progress: bool = True, indices=None):
    """The first `count` trajectories of `split` of `source`, the generator config of the preset named by
    config['states_from'] (`check_states_from`; its split file generated first when missing), checked
    one by one against this preset's seeds; only those at `indices` (in order) when given."""
    path = split_path(source["output"], split)
    if not path.exists():
        generate(source, [split], progress=progress)
    reader = SplitReader(path)
    differ = config_differences(reader.generator_config, config, STATES_SECTIONS)
    if differ:
        reader.close()
        raise ValueError(f"{path}: states_from: the file was generated with another scene or solver than this "
                         f"preset ({', '.join(differ[:6])}); regenerate it (python -m ggns generate --config "
                         f"{config['states_from']} --overwrite)")
    if len(reader) < count:
        reader.close()
        raise ValueError(f"{path}: states_from: holds {len(reader)} trajectories, this preset's {split} split needs {count}")
    jobs = trajectory_jobs(config, split, count)

    def states():
        with reader:
            for i in range(count) if indices is None else indices:
                seed = jobs[i][1]
                trajectory = reader[i]
                if trajectory.seed != seed:
                    raise ValueError(f"{path}: states_from: trajectory {i} has seed {trajectory.seed}, this preset's "
                                     f"has {seed}; the file is not this preset's trajectories")
                yield trajectory
    return states()
