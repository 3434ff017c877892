"""Stability at the extremes (`python -m ggns bench stability`): trained simulators rolled
out far beyond their training horizon, at and beyond their training materials, with the smallest
and the largest collider, with and without point clouds, in float32 and in float64.

Scenes (`scenes`): the data preset's scene with `steps` recorded states. The plate pushes its
collider down over the preset's T - 1 steps and then holds it (`collider.push_steps`), so a long
rollout is the training push followed by a long rest under load; the tissue's and the cavity's
gripper paths are defined per step and held after their end in every preset. One ground-truth
trajectory per (Poisson's ratio, collider) is made by the scene's own generator with its cameras
(`data.generate.regenerate`: real simulation, real point clouds). The plate's colliders are the
smallest and the largest radius of the preset's range (the plate's middle shape); the 3D scenes
keep their preset's gripper (one `collider` setting, "preset").

Quantities per step and trajectory (`rollout_quantities`): the rollout MSE against the ground truth,
the largest node speed (m/s) and the ground truth's, the mesh's bounding-box diagonal over the
ground truth's at that step (1 = the right size), and the share of inverted cells (signed area or
volume of the other sign than at rest) and the ground truth's. A rollout that diverges (non-finite,
or a node that left the scene: `evaluation.rollout.RolloutError`) is kept up to the step before and
recorded with that step and the error's message. float32 against float64: the same model in double
precision on the same trajectory (float64 data); `drift` is the mean node distance between the two
rollouts at each step.

Outputs in `output_dir`: stability.csv (every `stride`-th step of every rollout), stability.md (one
row per rollout: divergence, final and largest MSE, largest speed and the truth's, size range,
largest inverted share, final float32-float64 drift) and stability.png (MSE over the steps, one
panel per model and schedule).
"""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import torch

from ..batch import TrajectoryBatch
from ..config import load_config
from ..data.generate import regenerate, trajectory_seed
from ..evaluation.predict import check_model_fits
from ..evaluation.rollout import RolloutError, rollout
from ..evaluation.schedules import effective_schedules, parse_schedule
from ..geometry import signed_volumes
from ..pretrained import load_model, names
from ..reports import markdown_table, write_csv, write_text
from ..viz import plt, save_figure

COLUMNS = ("model", "schedule", "dtype", "poissons_ratio", "material", "collider", "step", "mse", "max_speed",
           "true_max_speed", "size_ratio", "inverted_share", "true_inverted_share", "drift")
PLATE_SHAPE = 4  # the plate's middle trapezoid (top width 1.6, no offset)


def training_materials(config: dict) -> list[float]:
    """The Poisson's ratios the preset's training data cover."""
    scene = config["scene"]
    if "poissons_ratios" in scene:
        return [float(nu) for nu in scene["poissons_ratios"]]
    return sorted({float(m["poissons_ratio"]) for m in scene["materials"]})


def scenes(config: dict, steps: int, materials: list[float]) -> list[tuple[dict, str, int, int]]:
    """(config of one trajectory, collider label, combination, seed) per (material, collider), with
    `steps` recorded states (module docstring)."""
    base = copy.deepcopy(config)
    scene = base["scene"]
    preset_steps = int(scene["num_steps"])
    scene["num_steps"] = int(steps)
    out = []
    if scene["name"] == "plate":
        scene["collider"]["push_steps"] = preset_steps - 1
        lo, _, hi = scene["collider"]["radius_fraction"]
        colliders = [("smallest", lo), ("largest", hi)]
    else:
        colliders = [("preset", None)]
    for i, nu in enumerate(materials):
        for j, (label, fraction) in enumerate(colliders):
            one = copy.deepcopy(base)
            if scene["name"] == "plate":
                one["scene"]["poissons_ratios"] = [float(nu)]
                one["scene"]["collider"]["radius_fraction"] = [fraction, fraction, fraction]
                combination = PLATE_SHAPE
            else:  # the preset's first material's stiffness, this Poisson's ratio
                first = dict(one["scene"]["materials"][0])
                one["scene"]["materials"] = [{**first, "poissons_ratio": float(nu)}]
                combination = 0
            out.append((one, label, combination, trajectory_seed(config["seed"], "test", i * len(colliders) + j)))
    return out


def rollout_quantities(positions: np.ndarray, truth: np.ndarray, rest: np.ndarray, cells: np.ndarray,
                       frame_dt: float) -> dict[str, np.ndarray]:
    """Per-step quantities of a rollout positions [S, N, d] against the truth [>= S, N, d] (module docstring)."""
    truth = truth[: len(positions)]
    rest_sign = np.sign(signed_volumes(rest, cells))

    def speed(x):
        return np.concatenate([[0.0], np.linalg.norm(np.diff(x, axis=0), axis=-1).max(axis=1) / frame_dt])

    def diagonal(x):
        return np.linalg.norm(x.max(axis=1) - x.min(axis=1), axis=-1)

    def inverted(x):
        return np.array([(np.sign(signed_volumes(frame, cells)) != rest_sign).mean() for frame in x])

    return {"mse": ((positions - truth) ** 2).mean(axis=(1, 2)), "max_speed": speed(positions),
            "true_max_speed": speed(truth), "size_ratio": diagonal(positions) / diagonal(truth),
            "inverted_share": inverted(positions), "true_inverted_share": inverted(truth)}


def _rollout(model, trajectory, schedule, dtype) -> tuple[np.ndarray, str | None]:
    """Positions [S, N, d] of a rollout (S = T, or fewer: the states before a divergence) and the
    divergence message (None). The model is copied to `dtype` (float64: every parameter and buffer)."""
    batch = TrajectoryBatch.from_trajectories([trajectory], dtype=dtype)
    model = copy.deepcopy(model).to(dtype) if dtype != torch.float32 else model
    try:
        positions, _ = rollout(model.step, batch, schedule, model.connectivity, model.with_material)
        return positions.double().numpy(), None
    except RolloutError as error:
        # the states before the divergence: roll out again up to the step before
        step = error.step
        positions, _ = rollout(model.step, batch, schedule, model.connectivity, model.with_material, steps=step)
        return positions.double().numpy(), f"state {step + 1}: {error}"


def stability(dataset: str = "plate", checkpoints: dict[str, str] | None = None, steps: int = 1000,
              beyond: tuple[float, ...] = (-0.95, 0.499), schedules=("every:1", "never"),
              dtypes=("float32", "float64"), stride: int = 10, output_dir: str | Path = "lightning_logs/stability",
              log=print) -> list[dict]:
    """Run the study (module docstring); returns the summary rows. checkpoints: name -> checkpoint path
    or pretrained name (default: the shipped simulators of the preset's scene)."""
    config = load_config(dataset)
    scene_name = config["scene"]["name"]
    if checkpoints is None:
        checkpoints = {n.split("/")[1]: n for n in names() if n.split("/")[0] == scene_name}
        if not checkpoints:
            raise ValueError(f"no shipped simulators of the {scene_name} scene: pass --checkpoint name=path")
    if steps < 2 or stride < 1:
        raise ValueError(f"need steps >= 2 and stride >= 1, got {steps} and {stride}")
    unknown = [d for d in dtypes if d not in ("float32", "float64")]
    if unknown:
        raise ValueError(f"dtypes must be float32 and/or float64, got {unknown}")
    output = Path(output_dir)
    trained = training_materials(config)
    materials = sorted(set(trained) | {float(nu) for nu in beyond})
    log(f"ground truth: {len(materials)} materials x colliders, {steps} states each")
    truths = []
    for one, collider, combination, seed in scenes(config, steps, materials):
        trajectory = regenerate(one, combination, seed)
        truths.append((trajectory, collider))
        log(f"  nu {trajectory.poissons_ratio:+.3f}, {collider} collider: simulated")
    models = {name: load_model(path, map_location="cpu") for name, path in checkpoints.items()}
    for model in models.values():
        check_model_fits(model, truths[0][0].dim, scene_name)
    rows, summary = [], []
    for name, model in models.items():
        for schedule in effective_schedules([parse_schedule(s) for s in schedules], model.uses_points):
            for trajectory, collider in truths:
                runs = {}
                for dtype in dtypes:
                    runs[dtype] = _rollout(model, trajectory, schedule, getattr(torch, dtype))
                for dtype, (positions, diverged) in runs.items():
                    q = rollout_quantities(positions, trajectory.positions, trajectory.rest_positions,
                                           trajectory.cells, float(trajectory.params["frame_dt"]))
                    drift = np.full(len(positions), np.nan)
                    if dtype == "float64" and "float32" in runs:
                        other = runs["float32"][0]
                        n = min(len(other), len(positions))
                        drift[:n] = np.linalg.norm(positions[:n] - other[:n], axis=-1).mean(axis=1)
                    material = "training" if trajectory.poissons_ratio in trained else "beyond"
                    common = dict(model=name, schedule=str(schedule), dtype=dtype,
                                  poissons_ratio=trajectory.poissons_ratio, material=material, collider=collider)
                    for step in range(0, len(positions), stride):
                        rows.append({**common, "step": step, **{k: float(v[step]) for k, v in q.items()},
                                     "drift": None if math.isnan(drift[step]) else float(drift[step])})
                    summary.append({**common, "diverged": diverged or "", "states": len(positions),
                                    "mse_last": float(q["mse"][-1]), "mse_max": float(q["mse"].max()),
                                    "speed_max": float(q["max_speed"].max()),
                                    "true_speed_max": float(q["true_max_speed"].max()),
                                    "size_min": float(q["size_ratio"].min()), "size_max": float(q["size_ratio"].max()),
                                    "inverted_max": float(q["inverted_share"].max()),
                                    "true_inverted_max": float(q["true_inverted_share"].max()),
                                    "drift_last": None if math.isnan(drift[-1]) else float(drift[-1])})
                log(f"  {name} {schedule} nu {trajectory.poissons_ratio:+.3f} {collider}: "
                    + ", ".join(f"{r['dtype']} mse_last {r['mse_last']:.3g}{' DIVERGED ' + r['diverged'][:60] if r['diverged'] else ''}"
                                for r in summary[-len(runs):]))
    output.mkdir(parents=True, exist_ok=True)
    write_csv(output / "stability.csv", rows, COLUMNS)
    write_text(output / "stability.md", summary_markdown(summary, dataset, steps))
    plot(rows, output / "stability.png")
    log(f"wrote {output / 'stability.csv'}, {output / 'stability.md'}, {output / 'stability.png'}")
    return summary


def summary_markdown(summary: list[dict], dataset: str, steps: int) -> str:
    header = ["model", "schedule", "dtype", "nu", "material", "collider", "diverged at", "MSE last", "MSE max",
              "speed max (truth)", "size ratio min-max", "inverted max (truth)", "drift f32-f64 last"]
    body = [(r["model"], r["schedule"], r["dtype"], f"{r['poissons_ratio']:+.3f}", r["material"], r["collider"],
             r["diverged"].split(":")[0] if r["diverged"] else "no", f"{r['mse_last']:.3g}", f"{r['mse_max']:.3g}",
             f"{r['speed_max']:.3g} ({r['true_speed_max']:.3g})", f"{r['size_min']:.3f}-{r['size_max']:.3f}",
             f"{r['inverted_max']:.3f} ({r['true_inverted_max']:.3f})",
             "" if r["drift_last"] is None else f"{r['drift_last']:.3g}") for r in summary]
    return (f"# Stability: {steps}-state rollouts on {dataset}\n\n" + markdown_table(header, body) + "\n"
            + "".join(f"\n- {r['model']} {r['schedule']} {r['dtype']} nu {r['poissons_ratio']:+.3f} {r['collider']}: "
                      f"{r['diverged']}" for r in summary if r["diverged"]) + "\n")


def plot(rows: list[dict], path: Path) -> None:
    """MSE over the steps (float32 rollouts), one panel per model and schedule, one line per scene."""
    panels = sorted({(r["model"], r["schedule"]) for r in rows})
    if not panels:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.6), squeeze=False, sharey=True)
    for ax, (model, schedule) in zip(axes[0], panels):
        lines = {}
        for r in rows:
            if r["model"] == model and r["schedule"] == schedule and r["dtype"] == "float32":
                lines.setdefault((r["poissons_ratio"], r["collider"]), []).append((r["step"], r["mse"]))
        for (nu, collider), points in sorted(lines.items()):
            steps, mse = zip(*points)
            ax.plot(steps, np.maximum(mse, 1e-12), linestyle="-" if collider != "smallest" else "--",
                    label=f"nu {nu:+.3f}, {collider}")
        ax.set_yscale("log")
        ax.set_title(f"{model}, {schedule}")
        ax.set_xlabel("step")
    axes[0][0].set_ylabel("rollout MSE (float32)")
    axes[0][-1].legend(fontsize=6)
    save_figure(fig, path)
