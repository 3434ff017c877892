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
test metrics, stepped online.

Registration variants (`registered`): a model stepped blind whose state is corrected at each frame by
registering its mesh to the frame's cloud (`ggns.online.Registration`, settings per task in
conf/online/registration.yaml unless given): the blind baselines ("mgn", "mgn_m"), GGNS stepped blind
("ggns_blind"), GGNS fed the clouds and registered as well ("ggns"), and the registration alone on a mesh
that does not move but for its held nodes ("static", `Stationary`). Writes online_study_raw.csv (a row per
trajectory and run, the checkpoints' sha256, the milliseconds per tick) and online_study.md (means over the
trajectories and their ratios to the blind baselines).
"""
from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

import torch

from ..config import CONF_DIR
from ..reports import write_csv, write_text
from .online import DATA_PRESETS, camera_frames, first_test_trajectories, machine, moving_fixed, tick_inputs

REGISTRATION_FILE = CONF_DIR / "online" / "registration.yaml"  # the registration's settings per task
REGISTERED = ("ggns", "ggns_blind", "mgn", "mgn_m", "static")  # what the study can run with a registration

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
COLUMNS = ["task", "preset", "split", "model", "sha256", "registration", "trajectory", "poissons ratio", "every",
           "latency", "sensor", "cameras", "frames fed", "tracking mse", "last tick mse", "manifest mse",
           "manifest metric", "seconds", "ms per tick"]


class Stationary(torch.nn.Module):
    """A simulator that predicts no motion: each tick the mesh stays where it is but for its held nodes (fixed,
    grasped), which move as given; the registration alone corrects it (the "static" variant). Its graphs are
    built as `like`'s (the shipped model whose connectivity and dimension it borrows)."""

    uses_points = False

    def __init__(self, like):
        super().__init__()
        self.hparams = like.hparams
        self.connectivity, self.with_material = like.connectivity, False
        self.anchor = torch.nn.Parameter(torch.zeros(1), requires_grad=False)  # gives the simulator its device and dtype

    def rollout_step(self):
        return lambda graph, state: (self.anchor.new_zeros(graph["mesh"].num_nodes, int(self.hparams.dim)), state)


def registration_settings(task: str, overrides: Mapping | None = None):
    """The task's `Registration` (conf/online/registration.yaml), with `overrides` of its fields."""
    import yaml

    from ..online import Registration

    settings = (yaml.safe_load(REGISTRATION_FILE.read_text()) or {}).get(task)
    if settings is None:
        raise ValueError(f"{REGISTRATION_FILE} has no registration settings for {task!r}")
    types = {f.name: f.type for f in dataclasses.fields(Registration)}
    unknown = sorted(set(overrides or {}) - set(types))
    if unknown:
        raise ValueError(f"unknown registration settings {unknown}; Registration has {sorted(types)}")

    def value(name: str, given):  # a command line's text as the field's type
        if types[name] == "bool":
            return given if isinstance(given, bool) else str(given).lower() in ("1", "true", "yes")
        if str(given).lower() in ("none", "null"):
            return None
        return int(float(given)) if types[name] == "int" else float(given)
    return Registration(**{**settings, **{k: value(k, v) for k, v in (overrides or {}).items()}})


def sensor_overrides(name: str, config: dict, task: str) -> dict:
    """The data preset's sensor fields that study sensor `name` (`SENSORS`) replaces."""
    from ..sensors.camera import sensor_flaws

    preset, scale, calibration, cameras = SENSORS[name]
    out = sensor_flaws(preset, METRES_PER_UNIT[task], scale, calibration)
    if cameras is not None:
        out["cameras"] = list(config["sensor"]["cameras"])[:cameras]
    return out


def track(model, world, frames: Sequence | None, every: int, latency: int, depth,
          registration=None) -> tuple[np.ndarray, int]:
    """(the mesh MSE against the true state at ticks 1..T-1 [T-1], the frames fed) of `model` stepped online
    through `world`, fed the frames of every `every`-th tick `latency` ticks late (None: no frames), each
    registered to when `registration` (a `Registration`) is given."""
    from ..online import Observation, OnlineSimulator

    sim = OnlineSimulator(model, {"object": world}, depth=depth, history=world.num_steps,  # any latency up to T
                          registration=registration)
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
                 checkpoints: Mapping[str, str] | None = None, registered: Sequence[str] = (),
                 registration: Mapping | None = None, split: str = "test", grounded: bool = True) -> list[dict]:
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
        registered: the models also run with a registration to each frame (`REGISTERED`; module docstring).
        registration: `Registration` fields replacing the task's settings of conf/online/registration.yaml.
        split: the data's split whose first trajectories are tracked (val: to choose the registration's settings).
        grounded: run the GGNS fed the frames (False: only the blind and registered runs).
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
    strange = [n for n in registered if n not in REGISTERED]
    if strange:
        raise ValueError(f"registered models must be among {list(REGISTERED)}, got {strange}")
    correction = registration_settings(task, registration) if registered else None
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
    fed_models = [names[0], *(checkpoints or {})] if grounded else []
    config, worlds = first_test_trajectories(preset, trajectories, data_dir, names[0], split)
    depth = DepthProcessing.from_sensor_config(config["sensor"])
    rows: list[dict] = []
    corrected = {}  # run name -> (model, Registration)
    for kind in registered:
        if kind == "static":
            corrected["static + registration"] = (Stationary(models[names[0]]), correction, "-")
        elif kind == "ggns_blind":
            corrected[f"{names[0]} blind + registration"] = (models[names[0]], correction, names[0])
        elif kind == "ggns":
            corrected[f"{names[0]} + registration"] = (models[names[0]], dataclasses.replace(correction, feed_model=True),
                                                       names[0])
        else:
            shipped = f"{task}/{kind}"
            if shipped not in models:
                models[shipped] = load(shipped).eval()
                digests[shipped] = models[shipped].manifest["sha256"]
            corrected[f"{shipped} + registration"] = (models[shipped], correction, shipped)

    def run(name: str, i: int, world, frames, r: int | None, d: int, sensor: str) -> None:
        model, registration, digest = (models[name], None, name) if name in models else corrected[name]
        start = time.perf_counter()
        errors, fed = track(model, world, frames, r or 1, d, depth, registration)
        manifest = getattr(model, "manifest", None) or {}
        reference, metric = manifest_reference(manifest, i, r, d, sensor) if split == "test" else (None, None)
        cameras = len(sensor_overrides(sensor, config, task).get("cameras", config["sensor"]["cameras"])) \
            if sensor in SENSORS else None
        seconds = time.perf_counter() - start
        rows.append({"task": task, "preset": preset, "split": split, "model": name, "sha256": digests.get(digest, "-"),
                     "registration": "-" if registration is None else registration_text(registration),
                     "trajectory": i, "poissons ratio": world.poissons_ratio, "every": r if r else "never",
                     "latency": d if r else "-", "sensor": sensor,
                     "cameras": "-" if cameras is None else cameras,
                     "frames fed": fed, "tracking mse": float(errors.mean()), "last tick mse": float(errors[-1]),
                     "manifest mse": reference, "manifest metric": metric,
                     "seconds": round(seconds, 2), "ms per tick": round(1000 * seconds / len(errors), 2)})
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
            for name in [*fed_models, *corrected]:
                for r in every:
                    for d in latencies:
                        run(name, i, world, frames, r, d, sensor)
        if output_dir is not None:
            write_outputs(rows, output_dir, task, preset, i + 1)
    return rows


def registration_text(registration) -> str:
    """A registration's settings as text (the raw file's column)."""
    return ", ".join(f"{f.name}={getattr(registration, f.name)}" for f in dataclasses.fields(registration))


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
               "tracking mse": mean, "ms per tick": float(np.mean([r.get("ms per tick") or np.nan for r in chosen]))}
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
    settings = sorted({r["registration"] for r in rows if r.get("registration") not in (None, "-")})
    lines = [f"Online tracking study, {task} ({preset}), the first {done} test trajectories; {machine()}.", "",
             "Tracking error: the mean over ticks 1..T-1 of the mesh MSE against the true state, averaged over the "
             "trajectories. Frames: the virtual cameras' masked depth images of every r-th tick, arriving `latency` "
             "ticks late; sensor: a key of ggns.bench.online_study.SENSORS (none: flawless; axial: the Kinect's "
             "axial noise, _3x: 3 times it; realistic: axial noise, grazing angles, depth edges, flying pixels; "
             "_calibration_mm / _cm: with that extrinsic error; _2_cameras / _1_camera: with the first of the "
             "scene's cameras only).", "",
             "| model | every r | latency | sensor | trajectories | tracking MSE | ms per tick | " + " | ".join(ratio_keys)
             + " |", "|---|---|---|---|---|---|---|" + "---|" * len(ratio_keys)]
    for r in summary:
        ratios = " | ".join("" if r[k] is None else f"{r[k]:.3f}" for k in ratio_keys)
        lines.append(f"| {r['model']} | {r['every']} | {r['latency']} | {r['sensor']} | {r['trajectories']} | "
                     f"{r['tracking mse']:.3g} | {r['ms per tick']:.1f} | {ratios} |")
    lines += ["", "Checkpoints (sha256):", ""] + [f"- {name}: `{digest}`" for name, digest in models.items()]
    if settings:
        lines += ["", "Registration settings:", ""] + [f"- {s}" for s in settings]
    write_text(output / "online_study.md", "\n".join(lines) + "\n")
