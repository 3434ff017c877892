"""`python -m ggns bench online`: the online simulator's (`ggns.online.OnlineSimulator`) time per tick.

A shipped simulator (or any) is stepped through the first test trajectory of its data preset (plate:
`plate_small`, tissue: `tissue_cpu`) as a control loop steps it: each tick the collider's next pose (and, where
they move, the held nodes' next positions) and either nothing, the trajectory's stored point cloud, or the
depth images of the scene's virtual cameras (rendered beforehand: the camera's input, not the stepper's
work; with the object's mask, so the crop is the mask's) through the stepper's depth path (observations
"none", "points", "depth"). Each is timed
with 1 and 2 torch threads: `warmup` ticks of a first simulator, then every tick of a fresh one (median
and quartiles of the times of `sim.step`). Writes online_bench.csv and online_bench.md.

The pieces the tracking study (`bench.online_study`) shares: the first test trajectories of a preset
(`first_test_trajectories`), a tick's inputs (`tick_inputs`) and the scene's camera frames (`camera_frames`).
"""
from __future__ import annotations

import os
import platform
import subprocess
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..config import load_config
from ..reports import write_csv, write_text
from ..trajectory import Trajectory

DATA_PRESETS = {"plate": "plate_small", "tissue": "tissue_cpu"}  # a shipped simulator's task -> its test data
OBSERVATIONS = ("none", "points", "depth")  # nothing seen, the stored point cloud, the cameras' depth images
GOAL_HZ = 100.0  # the tissue's ticks per second on 2 cores, without an observation
COLUMNS = ["simulator", "preset", "trajectory", "nodes", "observation", "mean points", "threads", "ticks",
           "median ms", "q1 ms", "q3 ms", "ticks per s"]


def data_preset(simulator: str, model: Any) -> str:
    """The data preset a simulator is measured on: its task's (`DATA_PRESETS`), else its manifest's preset.
    ValueError for a simulator without a manifest (give the preset)."""
    manifest = getattr(model, "manifest", None) or {}
    task = manifest.get("task")
    if task in DATA_PRESETS:
        return DATA_PRESETS[task]
    preset = (manifest.get("data") or {}).get("preset")
    if preset is None:
        raise ValueError(f"{simulator}: not a shipped simulator; give its data preset (--dataset)")
    return preset


def first_test_trajectories(preset: str, count: int, data_dir: str | os.PathLike | None = None,
                            simulator: str | None = None, split: str = "test") -> tuple[dict, list[Trajectory]]:
    """(the preset's config, its first `count` trajectories of `split`, test by default), read from
    <data_dir>/<split>.h5 (default: the preset's output) and refused (DatasetError) when the file was made with
    another scene, solver or sensor config; `simulator`, a shipped name: also refused when the data are not its
    training data's scene. FileNotFoundError naming the command that makes the file."""
    from ..data import split_path
    from ..data.schema import SplitReader, check_config
    from ..pretrained import check_data

    config = load_config(preset)
    directory = Path(data_dir if data_dir is not None else config["output"])
    path = split_path(directory, split)
    if not path.exists():
        raise FileNotFoundError(f"{path}: missing; make it with `python -m ggns generate --config {preset} --split "
                                f"{split} --count {count} --output {directory}` (or give its folder with --data-dir)")
    with SplitReader(path) as reader:
        check_config(reader, config)
        if simulator is not None:
            check_data(simulator, reader.generator_config, source=str(path))
        if len(reader) < count:
            raise ValueError(f"{path} holds {len(reader)} trajectories, {count} are asked for")
        return config, [reader[i] for i in range(count)]


def moving_fixed(world: Trajectory) -> np.ndarray | None:
    """Indices of the fixed nodes that move during the trajectory (the tissue's held patch; they are given to
    the stepper each tick), or None when none moves (the plate: its clamped nodes stay)."""
    index = np.flatnonzero(world.fixed)
    if not len(index) or np.array_equal(world.positions[:, index], np.broadcast_to(world.positions[:1, index],
                                                                                  world.positions[:, index].shape)):
        return None
    return index


def tick_inputs(world: Trajectory, t: int, fixed: np.ndarray | None) -> dict:
    """`OnlineSimulator.step`'s collider pose and fixed-node positions of tick t -> t + 1 (the recorded ones)."""
    inputs = {"collider": world.collider_positions[t + 1] if world.collider_positions.shape[1] else None}
    if fixed is not None:
        inputs["fixed"] = world.positions[t + 1][fixed]
    return inputs


def camera_frames(config: dict, world: Trajectory, sensor_overrides: Mapping[str, Any] | None = None,
                  rng: np.random.Generator | None = None, ticks: int | None = None) -> list[list]:
    """The depth images (`DepthSensor.render`, one per camera, the object's pixels masked) of the first `ticks`
    states of a trajectory, seen by the preset's virtual cameras as its data were (plate: with the collider;
    tissue: behind its occluders, the liver and the gripper's shaft), with the sensor config's fields in
    `sensor_overrides` replaced (the flaws of `SensorConfig`; random ones draw from `rng`)."""
    from ..sensors.camera import DepthSensor, SensorConfig

    sensor = DepthSensor(SensorConfig.from_dict({**dict(config["sensor"]), **dict(sensor_overrides or {})}))
    scene = config["scene"]
    ticks = world.num_steps if ticks is None else ticks
    frames = []
    if scene["name"] == "tissue":
        from ..scenes.tissue import gripper_shaft, liver_mesh

        liver = liver_mesh(scene)
        shaft, shaft_faces = gripper_shaft(scene, np.zeros(3))
        for t in range(ticks):
            frames.append(sensor.render(world.positions[t], world.cells, None, None, rng,
                                        occluders=[liver, (shaft + world.collider_positions[t][0], shaft_faces)]))
    else:
        for t in range(ticks):
            frames.append(sensor.render(world.positions[t], world.cells, world.collider_positions[t],
                                        world.collider_faces, rng))
    return frames


def step_times(model: Any, world: Trajectory, observe: Callable[[int], Any], ticks: int, depth: Any) -> list[float]:
    """Seconds of each `OnlineSimulator.step` over ticks 0 .. ticks - 1 of a fresh simulator of `world` (its
    state 0), fed the recorded collider poses (and moving fixed nodes) and `observe(t)`."""
    from ..online import OnlineSimulator

    sim = OnlineSimulator(model, {"object": world}, depth=depth, history=0)
    fixed = moving_fixed(world)
    times = []
    for t in range(ticks):
        inputs = tick_inputs(world, t, fixed)
        seen = observe(t)
        start = time.perf_counter()
        sim.step(**inputs, observation=None if seen is None else {"object": seen})
        times.append(time.perf_counter() - start)
    return times


def time_simulator(name: str, model: Any, preset: str, config: dict, world: Trajectory, ticks: int | None = None,
                   warmup: int = 5, threads: Sequence[int] = (1, 2),
                   observations: Sequence[str] = OBSERVATIONS) -> list[dict]:
    """One row per (observation, threads): the times per tick of `model` stepped through `world` (module
    docstring). ticks: timed ticks (default: every tick of the trajectory)."""
    from ..online import DepthProcessing

    unknown = set(observations) - set(OBSERVATIONS)
    if unknown:
        raise ValueError(f"unknown observation(s) {sorted(unknown)}; known: {OBSERVATIONS}")
    ticks = world.num_steps - 1 if ticks is None else ticks
    if not 1 <= ticks <= world.num_steps - 1 or warmup < 0:
        raise ValueError(f"ticks must be in 1..{world.num_steps - 1} (the trajectory's) and warmup >= 0, got "
                         f"ticks={ticks}, warmup={warmup}")
    depth = DepthProcessing.from_sensor_config(config["sensor"])
    frames = camera_frames(config, world, ticks=ticks) if "depth" in observations else []
    sources = {"none": lambda t: None, "points": world.point_cloud, "depth": frames.__getitem__}
    points = {"none": 0.0, "points": float(np.mean([len(world.point_cloud(t)) for t in range(ticks)])),
              "depth": float(np.mean([len(depth.cloud(frames[t], world.dim, world.positions[t], world.cells))
                                             for t in range(0, ticks, max(1, ticks // 10))])) if frames else 0.0}
    before = torch.get_num_threads()
    rows = []
    try:
        for count in threads:
            torch.set_num_threads(int(count))
            for what in observations:
                if warmup:
                    step_times(model, world, sources[what], min(warmup, ticks), depth)
                seconds = 1e3 * np.asarray(step_times(model, world, sources[what], ticks, depth))
                q1, median, q3 = np.percentile(seconds, [25, 50, 75])
                rows.append({"simulator": name, "preset": preset, "trajectory": 0, "nodes": len(world.rest_positions),
                             "observation": what, "mean points": points[what], "threads": int(count),
                             "ticks": ticks, "median ms": float(median), "q1 ms": float(q1), "q3 ms": float(q3),
                             "ticks per s": 1e3 / float(median)})
                print(f"bench online: {name} {what}, {count} thread(s): {median:.1f} ms per tick "
                      f"({q1:.1f}-{q3:.1f}), {1e3 / median:.0f} ticks/s", flush=True)
    finally:
        torch.set_num_threads(before)
    return rows


def goal_verdict(rows: list[dict], goal_hz: float = GOAL_HZ) -> str | None:
    """Whether the tissue's ticks without an observation on 2 threads reach `goal_hz` (None: not measured)."""
    measured = [r for r in rows if r["preset"].startswith("tissue") and r["observation"] == "none" and r["threads"] == 2]
    if not measured:
        return None
    return "; ".join(f"{r['simulator']}: {r['ticks per s']:.0f} ticks/s (median {r['median ms']:.2f} ms), the "
                     f"{goal_hz:.0f} Hz goal (tissue, no observation, 2 threads) is "
                     f"{'met' if r['ticks per s'] >= goal_hz else 'not met'}" for r in measured)


def bench_online(simulators: Mapping[str, Any], dataset: str | None = None,
                 data_dirs: Mapping[str, str] | None = None, ticks: int | None = None, warmup: int = 5,
                 threads: Sequence[int] = (1, 2), observations: Sequence[str] = OBSERVATIONS,
                 output_dir: str | os.PathLike | None = None) -> list[dict]:
    """Time the online stepper of each simulator (module docstring); print the table and the 100 Hz verdict.

    Args:
        simulators: name -> a shipped name ("tissue/ggns"), a checkpoint path or a model object.
        dataset: the data preset of every simulator (default: each shipped simulator's, `data_preset`).
        data_dirs: preset -> the folder of its test.h5 (default: the preset's output).
        ticks, warmup, threads, observations: as `time_simulator`.
        output_dir: write online_bench.csv and online_bench.md here.
    """
    from ..pretrained import load_model, names

    rows = []
    for name, spec in simulators.items():
        model = load_model(spec) if isinstance(spec, (str, os.PathLike)) else spec
        model.eval()
        preset = dataset or data_preset(name, model)
        shipped = spec if isinstance(spec, str) and spec in names() else None
        config, (world,) = first_test_trajectories(preset, 1, (data_dirs or {}).get(preset), shipped)
        rows += time_simulator(name, model, preset, config, world, ticks=ticks, warmup=warmup, threads=threads,
                               observations=observations)
    text = online_markdown(rows)
    print("\n" + text)
    if output_dir is not None:
        write_csv(Path(output_dir) / "online_bench.csv", rows, COLUMNS)
        write_text(Path(output_dir) / "online_bench.md", text)
    return rows


def machine() -> str:
    """The machine in words: CPU cores, torch version, the checkout's commit (when in a git checkout) and the load
    average of the last minute (other processes share the cores)."""
    commit = subprocess.run(["git", "-C", str(Path(__file__).resolve().parent), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip() or "unknown"
    return (f"{os.cpu_count()} CPU cores ({platform.processor() or platform.machine()}), torch {torch.__version__}, "
            f"commit {commit}, load average {os.getloadavg()[0]:.1f} when written")


def online_markdown(rows: list[dict]) -> str:
    """The table of `bench_online`'s rows and the goal's verdict."""
    lines = [f"Time per tick of `OnlineSimulator.step`, {machine()}: median and quartiles (ms) over the ticks of the "
             "first test trajectory, after a warm-up.", "",
             "| simulator | preset | nodes | observation | mean points | threads | ticks | median ms | q1-q3 ms | ticks/s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['simulator']} | {r['preset']} | {r['nodes']} | {r['observation']} | {r['mean points']:.0f} | "
                     f"{r['threads']} | {r['ticks']} | {r['median ms']:.2f} | {r['q1 ms']:.2f}-{r['q3 ms']:.2f} | "
                     f"{r['ticks per s']:.0f} |")
    verdict = goal_verdict(rows)
    if verdict:
        lines += ["", verdict + "."]
    return "\n".join(lines) + "\n"
