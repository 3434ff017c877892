"""The speed/accuracy trade: time per rollout step against rollout error, for the ground-truth
simulator at coarser time steps and for learned simulators (checkpoints), as a CSV and a Pareto
plot (`python -m ggns bench tradeoff`).

Simulator points (`simulator_points`): the plate preset records one state per `frame_dt` and
integrates it with `scene.substeps` solver steps (plate: 1). The time resolution is coarsened by
solving with fewer substeps per frame; since the preset's own 1 substep cannot be divided, the
REFERENCE is made finer instead: it uses `reference_substeps` (default: the smallest multiple of
the preset's substeps that every coarsening factor divides, e.g. 10 for factors 1, 2, 5 and 1
substep), and factor c uses reference_substeps / c substeps. c = 1 is the reference itself
(error 0); the factor c = reference_substeps / preset substeps reproduces the dataset's own
generator, so its error is the dataset's time-discretization error. Trajectories are those of
the preset's test split (same combination and seed as `generate`), simulated by the scene's
`make_trajectory` with the sensor replaced by a no-op, on 1 torch thread (as a generation
worker; `timing.time_trajectories`, the timer of `bench sim` too); the time is the whole call (scene set-up included, sensor excluded) divided by the
T - 1 simulated frames, median over the trajectories. Mesh resolution: the plate scene exposes
`scene.grid_nodes` (nodes per side); `grid_nodes` overrides it for the simulator (reference and
coarse runs alike) and the node count is recorded. `tradeoff` takes several resolutions: at the
preset's own the learned models are evaluated on the stored test split; at any other,
`resolution_tests` generates test trajectories at that resolution (real point clouds, same scenes
and seeds) into `<preset output>_grid<N>`, and the models are timed and scored on them. The models
were trained at the preset's resolution, so their error at another one is out of distribution
(the column `reference` says so); their time per step is what the resolution costs.

Model points (`model_points`): each checkpoint (a path or a pretrained name) is loaded with `pretrained.load_model`
(the class is stored in the checkpoint). Rollouts of whole test trajectories per
point-cloud schedule (schedules with point clouds only for models that use them): ms per step
for 1 trajectory and for `batch` trajectories at once (test trajectories repeated if fewer), the
median of `repeats` rollouts after a warm-up (`timing.time_rollout`), on the CPU and, when
present, CUDA; the rollout MSE (`metrics.rollout_mse`, all nodes, as in `evaluate_batch`) of the
first `trajectories` test trajectories against the dataset.

The plot's x axis is ms per trajectory-step (models: the batched time divided by the batch; the
simulator runs one trajectory at a time), y the rollout MSE; both are logarithmic, so zero errors
(the simulator reference) are drawn at the bottom edge. Note the two references: simulator
errors are against the finer simulator, model errors against the dataset.
"""
from __future__ import annotations

import math
import statistics
from pathlib import Path

import numpy as np
import torch

from ..batch import TrajectoryBatch
from ..config import load_config
from ..data.generate import generate, split_path, trajectory_jobs
from ..data.module import SimulationDataModule
from ..data.schema import read_trajectories
from ..evaluation.evaluate import split_trajectories
from ..evaluation.metrics import rollout_mse
from ..evaluation.schedules import effective_schedules
from ..pretrained import load_model
from ..reports import write_csv
from ..scenes import SCENES
from ..viz import plt, save_figure
from .report import print_table
from .timing import NoSensor, default_devices, time_rollout, time_trajectories

COLUMNS = ("kind", "name", "setting", "device", "nodes", "steps", "trajectories", "ms_per_step_1",
           "batch", "ms_per_step_batched", "ms_per_trajectory_step", "rollout_mse", "reference", "pareto")


def reference_substeps_for(preset_substeps: int, coarsen) -> int:
    """Smallest multiple of the preset's substeps that every coarsening factor divides."""
    return math.lcm(int(preset_substeps), *(int(c) for c in coarsen))


def simulator_points(config: dict, trajectories: int = 4, coarsen=(1, 2, 5), grid_nodes: int | None = None,
                     reference_substeps: int | None = None, split: str = "test") -> list[dict]:
    """One row per coarsening factor (module docstring): ms per simulated frame and rollout MSE
    against the reference (substeps `reference_substeps`); the first `trajectories` of `split`."""
    coarsen = sorted({int(c) for c in coarsen})
    if not coarsen or coarsen[0] < 1 or trajectories < 1:
        raise ValueError(f"need coarsening factors >= 1 and trajectories >= 1, got {coarsen}, {trajectories}")
    scene = dict(config["scene"])
    if grid_nodes is not None:
        scene["grid_nodes"] = int(grid_nodes)
    preset_substeps = int(config["scene"]["substeps"])
    reference = reference_substeps or reference_substeps_for(preset_substeps, coarsen)
    bad = [c for c in coarsen if reference % c]
    if bad:
        raise ValueError(f"reference_substeps={reference} is not divisible by the coarsening factors {bad}")
    module = SCENES[scene["name"]]
    base = {**config, "scene": scene}
    module.check_config({**base, "scene": {**scene, "substeps": reference}})
    jobs = trajectory_jobs(base, split, trajectories)
    sensor = NoSensor(int(scene.get("dim", 2)))
    runs = {c: time_trajectories(module, {**base, "scene": {**scene, "substeps": reference // c}}, jobs, sensor)
            for c in coarsen}
    # the reference: the c = 1 runs if made, else simulated now (untimed)
    reference_runs = runs[1] if 1 in runs else \
        time_trajectories(module, {**base, "scene": {**scene, "substeps": reference}}, jobs, sensor)
    truth = np.stack([t.positions for _, t in reference_runs])
    rows = []
    for c in coarsen:
        pred = np.stack([t.positions for _, t in runs[c]])
        steps = pred.shape[1] - 1
        ms = 1e3 * statistics.median(seconds / steps for seconds, _ in runs[c])
        rows.append({
            "kind": "simulator", "name": "simulator", "setting": f"substeps={reference // c} (coarsen {c}x)",
            "device": "cpu (1 thread)", "nodes": int(pred.shape[2]), "steps": steps, "trajectories": len(jobs),
            "ms_per_step_1": ms, "batch": 1, "ms_per_step_batched": ms, "ms_per_trajectory_step": ms,
            "rollout_mse": rollout_mse(torch.from_numpy(pred), torch.from_numpy(truth))[0],
            "reference": f"simulator substeps={reference}",
        })
    return rows


def resolution_tests(config: dict, grid_nodes: int, count: int, log=print):
    """`count` test trajectories of the preset `config` at `grid_nodes` nodes per side (its scenes
    and seeds, real point clouds), generated once into `<output>_grid<grid_nodes>/test.h5` and
    regenerated when that file holds fewer. Returns (trajectories, data directory)."""
    if int(grid_nodes) < 2 or count < 1:
        raise ValueError(f"need grid_nodes >= 2 and count >= 1, got {grid_nodes}, {count}")
    output = Path(f"{config['output']}_grid{int(grid_nodes)}")
    cfg = {**config, "scene": {**config["scene"], "grid_nodes": int(grid_nodes)},
           "splits": {"test": int(count)}, "output": str(output)}
    path = split_path(output, "test")
    tests = read_trajectories(path) if path.exists() else []
    if len(tests) < count:
        log(f"generating {count} test trajectories at {grid_nodes} x {grid_nodes} nodes into {output}")
        generate(cfg, ["test"], overwrite=path.exists(), progress=False)
        tests = read_trajectories(path)
    return tests[:count], output


def model_points(checkpoints: dict, dataset: str = "plate_small", schedules=("every:1", "never"), trajectories: int = 4,
                 batch: int = 32, repeats: int = 3, devices=None, data_dir: str | None = None,
                 tests: list | None = None, reference: str | None = None) -> list[dict]:
    """One row per checkpoint x schedule x device (module docstring). `tests`: the test
    trajectories to use instead of the dataset's test split (`reference` then names them)."""
    if trajectories < 1 or batch < 1 or repeats < 1:
        raise ValueError("trajectories, batch and repeats must be >= 1")
    if tests is None:
        datamodule = SimulationDataModule(dataset=dataset, data_dir=data_dir)
        datamodule.prepare_data()
        tests = datamodule.trajectories("test")
    reference = reference or f"dataset {dataset} test"
    scored = tests[:trajectories]
    rows = []
    for name, path in checkpoints.items():
        model = load_model(path, map_location="cpu")
        chosen = effective_schedules(schedules, model.uses_points)
        for device in devices or default_devices():
            device = torch.device(device)
            model.to(device)
            one = TrajectoryBatch.from_trajectories(tests[:1], device=device)
            many = TrajectoryBatch.from_trajectories([tests[i % len(tests)] for i in range(batch)], device=device)
            error_batch = TrajectoryBatch.from_trajectories(scored, device=device)
            steps = one.num_steps - 1
            for schedule in chosen:
                ms_one = time_rollout(model, one, schedule, steps, repeats, device)["ms per step"]
                ms_many = time_rollout(model, many, schedule, steps, repeats, device)["ms per step"]
                pred = split_trajectories(model.rollout(error_batch, schedule), error_batch)
                true = split_trajectories(error_batch.positions, error_batch)
                mse = float(np.mean([rollout_mse(p, t)[0] for p, t in zip(pred, true)]))
                rows.append({
                    "kind": "model", "name": name, "setting": str(schedule), "device": str(device),
                    "nodes": int(np.mean(np.diff(one.node_offsets))), "steps": steps, "trajectories": len(scored),
                    "ms_per_step_1": ms_one, "batch": batch, "ms_per_step_batched": ms_many,
                    "ms_per_trajectory_step": ms_many / batch, "rollout_mse": mse, "reference": reference,
                })
        model.cpu()
    return rows


def pareto_mask(rows: list[dict]) -> list[bool]:
    """True for the rows no other row beats in both time per trajectory-step and error (lower is better)."""
    pts = [(r["ms_per_trajectory_step"], r["rollout_mse"]) for r in rows]
    return [not any(qx <= px and qy <= py and (qx, qy) != (px, py) for qx, qy in pts) for px, py in pts]


def tradeoff_csv(rows: list[dict], path: str | Path) -> Path:
    """Rows as CSV with the columns `COLUMNS` (missing ones empty; `pareto` filled in if absent)."""
    front = pareto_mask(rows) if rows else []
    return write_csv(path, [{**row, "pareto": row.get("pareto", on_front)} for row, on_front in zip(rows, front)],
                     COLUMNS)


def pareto_plot(rows: list[dict], path: str | Path) -> Path:
    """Log-log plot of rollout MSE against ms per trajectory-step: one labelled marker per point,
    the simulator's points joined by a line, the Pareto front as a dashed step line."""
    if not rows:
        raise ValueError("nothing to plot")
    xs = np.array([r["ms_per_trajectory_step"] for r in rows], dtype=float)
    ys = np.array([r["rollout_mse"] for r in rows], dtype=float)
    positive = ys[ys > 0]
    floor = positive.min() / 10 if len(positive) else 1e-12  # zero errors are drawn here
    shown = np.where(ys > 0, ys, floor)
    fig, ax = plt.subplots(figsize=(7, 5))
    resolutions = list(dict.fromkeys(r.get("nodes") for r in rows))
    shades = dict(zip(resolutions, ("black", "dimgray", "darkgray", "silver")))
    for nodes in resolutions:
        sim = [i for i, r in enumerate(rows) if r["kind"] == "simulator" and r.get("nodes") == nodes]
        if sim:
            order = sorted(sim, key=lambda i: xs[i])
            where = f", {nodes} nodes" if len(resolutions) > 1 else ""
            ax.plot(xs[order], shown[order], "-o", color=shades.get(nodes, "black"),
                    label=f"simulator (coarser time steps{where})")
    markers = iter("sD^vP*Xph<>")
    for key in dict.fromkeys((r["name"], r["device"]) for r in rows if r["kind"] != "simulator"):
        idx = [i for i, r in enumerate(rows) if (r["name"], r["device"]) == key and r["kind"] != "simulator"]
        ax.scatter(xs[idx], shown[idx], marker=next(markers, "o"), s=50, label=f"{key[0]} ({key[1]})")
    for i, r in enumerate(rows):
        label = r["setting"] + (" = reference (error 0)" if ys[i] == 0 else "")
        if len(resolutions) > 1:
            label += f" [{r.get('nodes')} nodes]"
        ax.annotate(label, (xs[i], shown[i]), textcoords="offset points", xytext=(5, 4), fontsize=7)
    front = sorted((i for i, ok in enumerate(pareto_mask(rows)) if ok), key=lambda i: xs[i])
    ax.step(xs[front], shown[front], where="post", ls="--", color="tab:red", lw=1, label="Pareto front")
    ax.scatter(xs[front], shown[front], s=160, facecolors="none", edgecolors="tab:red")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(xs.min() / 2, xs.max() * 8)  # room for the labels right of the points
    ax.set_xlabel("ms per trajectory-step")
    ax.set_ylabel("rollout MSE")
    ax.set_title("speed / accuracy trade")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


def tradeoff(dataset: str = "plate_small", checkpoints: dict | None = None, trajectories: int = 4, coarsen=(1, 2, 5),
             output_dir: str | Path = "lightning_logs/tradeoff", schedules=("every:1", "never"), batch: int = 32,
             repeats: int = 3, grid_nodes=None, data_dir: str | None = None) -> list[dict]:
    """Simulator and model points at each mesh resolution in `grid_nodes` (nodes per side; an int,
    a list, or None for the preset's); writes <output_dir>/tradeoff.csv and tradeoff.png and
    prints the table."""
    config = load_config(dataset)
    preset = int(config["scene"].get("grid_nodes", 0)) or None
    resolutions = [preset] if grid_nodes is None else [int(n) for n in np.atleast_1d(grid_nodes)]
    rows = []
    for nodes in resolutions:
        rows += simulator_points(config, trajectories, coarsen, grid_nodes=nodes)
        if not checkpoints:
            continue
        if nodes == preset:
            rows += model_points(checkpoints, dataset, schedules, trajectories, batch=batch, repeats=repeats,
                                 data_dir=data_dir)
        else:
            tests, directory = resolution_tests({**config, "output": data_dir or config["output"]}, nodes, trajectories)
            rows += model_points(checkpoints, dataset, schedules, trajectories, batch=batch, repeats=repeats,
                                 tests=tests, reference=f"{directory} test (models trained at {preset} per side)")
    for row, on_front in zip(rows, pareto_mask(rows)):
        row["pareto"] = on_front
    out = Path(output_dir)
    csv_path, png_path = tradeoff_csv(rows, out / "tradeoff.csv"), pareto_plot(rows, out / "tradeoff.png")
    print_table(rows, COLUMNS)
    print(f"\nwrote {csv_path} and {png_path}")
    return rows
