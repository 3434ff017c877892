"""`python -m ggns bench online-study`: how well the shipped GGNS tracks a trajectory when fed the virtual
cameras' depth frames online, against the frames' latency and the sensor's noise, with the blind shipped
baselines (MGN, MGN(M)) beside it.

For each of the first K test trajectories of the task's data preset (plate: `plate_small`, tissue:
`tissue_cpu`) the trajectory stands in for the world: an `OnlineSimulator` is stepped through its ticks with
the recorded collider poses (and the held nodes' positions, the tissue's gripper), and fed the depth images
its virtual cameras (`DepthSensor.render`, the data's cameras, occluders and object mask) took of the true
state of every r-th tick, each arriving `latency` ticks after the tick it shows (`Observation(tick=...)`):
at tick t the frame of tick t - latency, when t - latency is a multiple of r. The sensor's noise is the
axial model of `SensorConfig.axial_noise` at 0, 1 and 3 times the Kinect's coefficient scaled to the scene
(`KINECT_AXIAL_NOISE` times the metres per scene unit: both scenes are in metres), drawn per frame from a
generator seeded by (seed, trajectory, noise level). The masks crop the frames (a segmentation is assumed).

The tracking error of a run is the mean over its predicted ticks 1..T-1 of the mesh's MSE against the true
state (squared error averaged over nodes and coordinates: the library's rollout MSE). The blind runs (no
frames: GGNS, and the shipped MGN and MGN(M), which take no point cloud) are the library's rollouts of the
test metrics, stepped online. Writes online_study_raw.csv (a row per trajectory and run, the checkpoints'
sha256) and online_study.md (means over the trajectories and their ratios to the blind baselines).
"""
from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..reports import write_csv, write_text
from .online import DATA_PRESETS, camera_frames, first_test_trajectories, machine, moving_fixed, tick_inputs

NOISE_SCALES = {"none": 0.0, "realistic": 1.0, "3x": 3.0}  # times the Kinect's axial coefficient in scene units
METRES_PER_UNIT = {"plate": 1.0, "tissue": 1.0}  # conf/data/plate.yaml, tissue.yaml: lengths are metres
COLUMNS = ["task", "preset", "model", "sha256", "trajectory", "poissons ratio", "every", "latency", "noise",
           "axial noise", "frames fed", "tracking mse", "last tick mse", "manifest mse", "manifest metric", "seconds"]


def track(model, world, frames: Sequence | None, every: int, latency: int, depth) -> tuple[np.ndarray, int]:
    """(the mesh MSE against the true state at ticks 1..T-1 [T-1], the frames fed) of `model` stepped online
    through `world`, fed the frames of every `every`-th tick `latency` ticks late (None: no frames)."""
    import torch

    from ..online import Observation, OnlineSimulator

    sim = OnlineSimulator(model, {"object": world}, depth=depth, history=world.num_steps)  # any latency up to T
    fixed = moving_fixed(world)
    errors, fed = [], 0
    for t in range(world.num_steps - 1):
        shown = t - latency
        seen = None
        if frames is not None and shown >= 0 and shown % every == 0:
            seen = {"object": Observation(images=frames[shown], tick=shown)}
            fed += 1
        state = sim.step(**tick_inputs(world, t, fixed), observation=seen)["object"]
        errors.append(float(((state.to(torch.float64).numpy() - world.positions[t + 1]) ** 2).mean()))
    return np.asarray(errors), fed


def manifest_reference(manifest: dict, trajectory: int, every: int | None, latency: int, noise: str) -> tuple:
    """(value, metric) of the shipped model's test metrics for the run that is the offline rollout (no noise,
    no latency; every r ticks: rollout_mse_k<r>, blind: rollout_mse_never), or (None, None)."""
    if noise not in ("none", "-") or latency:
        return None, None
    metric = "rollout_mse_never" if every is None else f"rollout_mse_k{every}"
    values = ((manifest.get("test") or {}).get("per_trajectory") or {}).get(metric) or []
    return (values[trajectory], metric) if trajectory < len(values) else (None, None)


def online_study(task: str = "tissue", trajectories: int = 3, latencies: Sequence[int] = (0, 1, 2, 5),
                 noises: Sequence[str] = ("none", "realistic", "3x"), every: Sequence[int] = (1,),
                 baselines: Sequence[str] = ("mgn", "mgn_m"), data_dir: str | os.PathLike | None = None,
                 output_dir: str | os.PathLike | None = None, seed: int = 0) -> list[dict]:
    """Run the study (module docstring) on `task`'s shipped `<task>/ggns` and the blind `<task>/<baseline>`s.

    Args:
        task: plate or tissue.
        trajectories: the first K test trajectories of the task's data preset.
        latencies: ticks between a frame's tick and its arrival.
        noises: sensor noise levels, keys of `NOISE_SCALES`.
        every: frames of every r-th tick.
        baselines: blind shipped models of the task beside GGNS.
        data_dir: the folder of the preset's test.h5 (default: the preset's output).
        output_dir: online_study_raw.csv and online_study.md are written here after every trajectory.
        seed: of the sensor noise.
    """
    from ..online import DepthProcessing
    from ..pretrained import load
    from ..sensors.camera import KINECT_AXIAL_NOISE

    if task not in DATA_PRESETS:
        raise ValueError(f"task must be one of {sorted(DATA_PRESETS)}, got {task!r}")
    unknown = [n for n in noises if n not in NOISE_SCALES]
    if unknown or any(d < 0 for d in latencies) or any(r < 1 for r in every):
        raise ValueError(f"noises must be among {list(NOISE_SCALES)} (got {unknown}), latencies >= 0, every >= 1")
    import torch

    torch.set_num_threads(1)
    preset = DATA_PRESETS[task]
    names = [f"{task}/ggns"] + [f"{task}/{b}" for b in baselines]
    models = {name: load(name).eval() for name in names}  # sha256 checked against the manifest on loading
    config, worlds = first_test_trajectories(preset, trajectories, data_dir, names[0])
    depth = DepthProcessing.from_sensor_config(config["sensor"])
    axial = {n: NOISE_SCALES[n] * KINECT_AXIAL_NOISE * METRES_PER_UNIT[task] for n in noises}
    rows: list[dict] = []

    def run(name: str, i: int, world, frames, r: int | None, d: int, noise: str) -> None:
        model = models[name]
        start = time.perf_counter()
        errors, fed = track(model, world, frames, r or 1, d, depth)
        reference, metric = manifest_reference(model.manifest, i, r, d, noise)
        rows.append({"task": task, "preset": preset, "model": name, "sha256": model.manifest["sha256"],
                     "trajectory": i, "poissons ratio": world.poissons_ratio, "every": r if r else "never",
                     "latency": d if r else "-", "noise": noise, "axial noise": axial.get(noise, "-"),
                     "frames fed": fed, "tracking mse": float(errors.mean()), "last tick mse": float(errors[-1]),
                     "manifest mse": reference, "manifest metric": metric,
                     "seconds": round(time.perf_counter() - start, 2)})
        print(f"online study: {task} trajectory {i} {name} every={r or 'never'} latency={d if r else '-'} "
              f"noise={noise}: tracking mse {errors.mean():.3g}"
              + (f" (manifest {metric} {reference:.3g})" if reference is not None else "")
              + f", {rows[-1]['seconds']:.0f} s", flush=True)

    for i, world in enumerate(worlds):
        for name in names:  # blind
            run(name, i, world, None, None, 0, "-")
        for level, noise in enumerate(noises):
            rng = np.random.default_rng([seed, i, level])
            frames = camera_frames(config, world, {"axial_noise": axial[noise]}, rng)
            for r in every:
                for d in latencies:
                    run(names[0], i, world, frames, r, d, noise)
        if output_dir is not None:
            write_outputs(rows, output_dir, task, preset, i + 1)
    return rows


def summary_rows(rows: list[dict]) -> list[dict]:
    """Mean tracking error over the trajectories per run kind, and its ratio to each blind model's mean (on the
    same trajectories)."""
    keys = list(dict.fromkeys((r["model"], r["every"], r["latency"], r["noise"]) for r in rows))
    blind = {r["model"] for r in rows if r["every"] == "never"}
    out = []
    for key in keys:
        chosen = [r for r in rows if (r["model"], r["every"], r["latency"], r["noise"]) == key]
        done = {r["trajectory"] for r in chosen}
        mean = float(np.mean([r["tracking mse"] for r in chosen]))
        row = {"model": key[0], "every": key[1], "latency": key[2], "noise": key[3], "trajectories": len(chosen),
               "tracking mse": mean}
        for other in sorted(blind):
            base = [r["tracking mse"] for r in rows if r["model"] == other and r["every"] == "never"
                    and r["trajectory"] in done]
            row[f"ratio to blind {other}"] = mean / float(np.mean(base)) if len(base) == len(chosen) else None
        out.append(row)
    return out


def write_outputs(rows: list[dict], output_dir: str | os.PathLike, task: str, preset: str, done: int) -> None:
    """online_study_raw.csv (every row) and online_study.md (the summary) in `output_dir`."""
    output = Path(output_dir)
    write_csv(output / "online_study_raw.csv", rows, COLUMNS)
    summary = summary_rows(rows)
    ratio_keys = [k for k in summary[0] if k.startswith("ratio to")]
    models = {r["model"]: r["sha256"] for r in rows}
    lines = [f"Online tracking study, {task} ({preset}), the first {done} test trajectories; {machine()}.", "",
             "Tracking error: the mean over ticks 1..T-1 of the mesh MSE against the true state, averaged over the "
             "trajectories. Frames: the virtual cameras' masked depth images of every r-th tick, arriving `latency` "
             "ticks late; noise: the axial model, none, the Kinect's coefficient (realistic) and 3 times it.", "",
             "| model | every r | latency | noise | trajectories | tracking MSE | " + " | ".join(ratio_keys) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(ratio_keys)]
    for r in summary:
        ratios = " | ".join("" if r[k] is None else f"{r[k]:.3f}" for k in ratio_keys)
        lines.append(f"| {r['model']} | {r['every']} | {r['latency']} | {r['noise']} | {r['trajectories']} | "
                     f"{r['tracking mse']:.3g} | {ratios} |")
    lines += ["", "Checkpoints (sha256):", ""] + [f"- {name}: `{digest}`" for name, digest in models.items()]
    write_text(output / "online_study.md", "\n".join(lines) + "\n")
