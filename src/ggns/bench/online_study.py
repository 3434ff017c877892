"""`python -m ggns bench online-study`: how well the shipped GGNS tracks a trajectory when fed the virtual
cameras' depth frames online, against the frames' latency and the sensor's noise, with the blind shipped
baselines (MGN, MGN(M)) beside it.

For each of the first K test trajectories of the task's data preset (plate: `plate_small`, tissue:
`tissue_cpu`) the trajectory stands in for the world: an `OnlineSimulator` is stepped through its ticks with
the recorded collider poses (and the held nodes' positions, the tissue's gripper), and fed the depth images
its virtual cameras (`DepthSensor.render`, the data's cameras, occluders and object mask) took of the true
state of every r-th tick, each arriving `latency` ticks after the tick it shows (`Observation(tick=...)`):
at tick t the frame of tick t - latency, when t - latency is a multiple of r. The sensor is one of
`SENSORS`: flawless; the axial noise alone at 1 and 3 times the Kinect's coefficient; the realistic preset
(`ggns.sensors.camera.SENSOR_FLAWS`: that axial noise, no return at grazing angles beyond 70 degrees, depth
edges dropped, 0.5 % flying pixels), alone, with a calibration error of millimetres or of a centimetre
(`CALIBRATION_ERRORS`), or with only the first 2 or 1 of the scene's cameras; scaled to the scene (both are
in metres), drawn per frame from a generator seeded by (seed, trajectory, the sensor's place in `SENSORS`:
a new sensor goes at its end, so that the others keep their draws; each sensor draws its own noise). The
masks crop the frames
(a segmentation is assumed).

The tracking error of a run is the mean over its predicted ticks 1..T-1 of the mesh's MSE against the true
state (squared error averaged over nodes and coordinates: the library's rollout MSE). The blind runs (no
frames: GGNS, and the shipped MGN and MGN(M), which take no point cloud) are the library's rollouts of the
test metrics, stepped online. Writes online_study_raw.csv (a row per trajectory and run, the checkpoints'
sha256) and online_study.md (means over the trajectories and their ratios to the blind baselines).
"""
from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..reports import write_csv, write_text
from .online import DATA_PRESETS, camera_frames, first_test_trajectories, machine, moving_fixed, tick_inputs

# the study's sensors: (a preset of SENSOR_FLAWS, times its axial noise, a calibration error, cameras: the
# scene's first n, None: all)
SENSORS = {
    "none": ("flawless", 1.0, "none", None),
    "axial": ("axial", 1.0, "none", None),
    "axial_3x": ("axial", 3.0, "none", None),
    "realistic": ("realistic", 1.0, "none", None),
    "realistic_calibration_mm": ("realistic", 1.0, "mm", None),
    "realistic_calibration_cm": ("realistic", 1.0, "cm", None),
    "realistic_2_cameras": ("realistic", 1.0, "none", 2),
    "realistic_1_camera": ("realistic", 1.0, "none", 1),
}
METRES_PER_UNIT = {"plate": 1.0, "tissue": 1.0}  # conf/data/plate.yaml, tissue.yaml: lengths are metres
COLUMNS = ["task", "preset", "model", "sha256", "trajectory", "poissons ratio", "every", "latency", "sensor",
           "cameras", "frames fed", "tracking mse", "last tick mse", "manifest mse", "manifest metric", "seconds"]


def sensor_overrides(name: str, config: dict, task: str) -> dict:
    """The data preset's sensor fields that study sensor `name` (`SENSORS`) replaces."""
    from ..sensors.camera import sensor_flaws

    preset, scale, calibration, cameras = SENSORS[name]
    out = sensor_flaws(preset, METRES_PER_UNIT[task], scale, calibration)
    if cameras is not None:
        out["cameras"] = list(config["sensor"]["cameras"])[:cameras]
    return out


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


def manifest_reference(manifest: dict, trajectory: int, every: int | None, latency: int, sensor: str) -> tuple:
    """(value, metric) of the shipped model's test metrics for the run that is the offline rollout (flawless
    sensor, no latency; every r ticks: rollout_mse_k<r>, blind: rollout_mse_never), or (None, None)."""
    if sensor not in ("none", "-") or latency:
        return None, None
    metric = "rollout_mse_never" if every is None else f"rollout_mse_k{every}"
    values = ((manifest.get("test") or {}).get("per_trajectory") or {}).get(metric) or []
    return (values[trajectory], metric) if trajectory < len(values) else (None, None)


def online_study(task: str = "tissue", trajectories: int = 3, latencies: Sequence[int] = (0, 1, 2, 5),
                 sensors: Sequence[str] = ("none", "axial", "axial_3x"), every: Sequence[int] = (1,),
                 baselines: Sequence[str] = ("mgn", "mgn_m"), data_dir: str | os.PathLike | None = None,
                 output_dir: str | os.PathLike | None = None, seed: int = 0,
                 checkpoints: Mapping[str, str] | None = None) -> list[dict]:
    """Run the study (module docstring) on `task`'s shipped `<task>/ggns` and the blind `<task>/<baseline>`s.

    Args:
        task: plate or tissue.
        trajectories: the first K test trajectories of the task's data preset.
        latencies: ticks between a frame's tick and its arrival.
        sensors: the sensors, keys of `SENSORS`.
        every: frames of every r-th tick.
        baselines: blind shipped models of the task beside GGNS.
        data_dir: the folder of the preset's test.h5 (default: the preset's output).
        output_dir: online_study_raw.csv and online_study.md are written here after every trajectory.
        seed: of the sensor noise.
        checkpoints: more GGNS fed the same frames: a name -> a checkpoint file (e.g. one trained on the
            flaws it is fed), loaded by `ggns.models.loading.load_simulator`.
    """
    from ..checkpoints import sha256
    from ..models.loading import load_simulator
    from ..online import DepthProcessing
    from ..pretrained import load

    if task not in DATA_PRESETS:
        raise ValueError(f"task must be one of {sorted(DATA_PRESETS)}, got {task!r}")
    unknown = [n for n in sensors if n not in SENSORS]
    if unknown or any(d < 0 for d in latencies) or any(r < 1 for r in every):
        raise ValueError(f"sensors must be among {list(SENSORS)} (got {unknown}), latencies >= 0, every >= 1")
    import torch

    torch.set_num_threads(1)
    preset = DATA_PRESETS[task]
    names = [f"{task}/ggns"] + [f"{task}/{b}" for b in baselines]
    taken = sorted(set(checkpoints or {}) & set(names))
    if taken:
        raise ValueError(f"checkpoint names {taken} are the shipped models' names: name them otherwise")
    models = {name: load(name).eval() for name in names}  # sha256 checked against the manifest on loading
    digests = {name: model.manifest["sha256"] for name, model in models.items()}
    for name, path in (checkpoints or {}).items():
        models[name], digests[name] = load_simulator(path).eval(), sha256(path)
    grounded = [names[0], *(checkpoints or {})]
    config, worlds = first_test_trajectories(preset, trajectories, data_dir, names[0])
    depth = DepthProcessing.from_sensor_config(config["sensor"])
    rows: list[dict] = []

    def run(name: str, i: int, world, frames, r: int | None, d: int, sensor: str) -> None:
        model = models[name]
        start = time.perf_counter()
        errors, fed = track(model, world, frames, r or 1, d, depth)
        manifest = getattr(model, "manifest", None) or {}
        reference, metric = manifest_reference(manifest, i, r, d, sensor)
        cameras = len(sensor_overrides(sensor, config, task).get("cameras", config["sensor"]["cameras"])) \
            if sensor in SENSORS else None
        rows.append({"task": task, "preset": preset, "model": name, "sha256": digests[name],
                     "trajectory": i, "poissons ratio": world.poissons_ratio, "every": r if r else "never",
                     "latency": d if r else "-", "sensor": sensor,
                     "cameras": "-" if cameras is None else cameras,
                     "frames fed": fed, "tracking mse": float(errors.mean()), "last tick mse": float(errors[-1]),
                     "manifest mse": reference, "manifest metric": metric,
                     "seconds": round(time.perf_counter() - start, 2)})
        print(f"online study: {task} trajectory {i} {name} every={r or 'never'} latency={d if r else '-'} "
              f"sensor={sensor}: tracking mse {errors.mean():.3g}"
              + (f" (manifest {metric} {reference:.3g})" if reference is not None else "")
              + f", {rows[-1]['seconds']:.0f} s", flush=True)

    for i, world in enumerate(worlds):
        for name in names:  # blind
            run(name, i, world, None, None, 0, "-")
        for sensor in sensors:
            rng = np.random.default_rng([seed, i, list(SENSORS).index(sensor)])
            frames = camera_frames(config, world, sensor_overrides(sensor, config, task), rng)
            for name in grounded:
                for r in every:
                    for d in latencies:
                        run(name, i, world, frames, r, d, sensor)
        if output_dir is not None:
            write_outputs(rows, output_dir, task, preset, i + 1)
    return rows


def summary_rows(rows: list[dict]) -> list[dict]:
    """Mean tracking error over the trajectories per run kind, and its ratio to each blind model's mean (on the
    same trajectories)."""
    keys = list(dict.fromkeys((r["model"], r["every"], r["latency"], r["sensor"]) for r in rows))
    blind = {r["model"] for r in rows if r["every"] == "never"}
    out = []
    for key in keys:
        chosen = [r for r in rows if (r["model"], r["every"], r["latency"], r["sensor"]) == key]
        done = {r["trajectory"] for r in chosen}
        mean = float(np.mean([r["tracking mse"] for r in chosen]))
        row = {"model": key[0], "every": key[1], "latency": key[2], "sensor": key[3], "trajectories": len(chosen),
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
             "ticks late; sensor: a key of ggns.bench.online_study.SENSORS (none: flawless; axial: the Kinect's "
             "axial noise, _3x: 3 times it; realistic: axial noise, grazing angles, depth edges, flying pixels; "
             "_calibration_mm / _cm: with that extrinsic error; _2_cameras / _1_camera: with the first of the "
             "scene's cameras only).", "",
             "| model | every r | latency | sensor | trajectories | tracking MSE | " + " | ".join(ratio_keys) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(ratio_keys)]
    for r in summary:
        ratios = " | ".join("" if r[k] is None else f"{r[k]:.3f}" for k in ratio_keys)
        lines.append(f"| {r['model']} | {r['every']} | {r['latency']} | {r['sensor']} | {r['trajectories']} | "
                     f"{r['tracking mse']:.3g} | {ratios} |")
    lines += ["", "Checkpoints (sha256):", ""] + [f"- {name}: `{digest}`" for name, digest in models.items()]
    write_text(output / "online_study.md", "\n".join(lines) + "\n")
