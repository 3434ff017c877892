"""The speed/accuracy trade: time per rollout step against rollout error, for the ground-truth
simulator at coarser time steps and for learned simulators (checkpoints), as a CSV and a Pareto
plot (`python -m ggns bench tradeoff`).

Simulator points (`simulator_points`): a preset records one state per `frame_dt` and integrates
it with `scene.substeps` solver steps (plate and tissue: 1). The time resolution is coarsened by
solving with fewer substeps per frame; since the preset's own 1 substep cannot be divided, the
REFERENCE is made finer instead: it uses `reference_substeps` (default: the smallest multiple of
the preset's substeps that every coarsening factor divides, e.g. 10 for factors 1, 2, 5 and 1
substep), and factor c uses reference_substeps / c substeps. c = 1 is the reference itself
(error 0); the factor c = reference_substeps / preset substeps reproduces the dataset's own
generator, so its error is the dataset's time-discretization error. Trajectories are those of
the preset's test split (same combination and seed as `generate`), simulated by the scene's
`make_trajectory` with the sensor replaced by a no-op, on 1 torch thread (as a generation
worker; `timing.time_trajectories`, the timer of `bench sim` too); the time is the whole call (scene set-up included, sensor excluded) divided by the
T - 1 simulated frames, median over the trajectories.

Newton tolerance (`newton_tolerances`, a second simulator axis): the simulator at the preset's
substeps with `solver.newton_tolerance` (max |dx| of the last Newton step, m) coarser than the
preset's; the rows have `axis` "newton tolerance" (the substep rows "time step"), their setting
names the tolerance, and besides the rollout MSE against the common reference (which at the
preset's substeps is dominated by the time step) the CSV gives `mse_vs_preset_tolerance`, the
error against the same substeps at the preset's tolerance (the tolerance's own error), and
`newton_iterations` (mean per solver step) for every simulator row.

Mesh resolution: a scene module that supports it defines `resolution(scene) -> int`, the
preset's own level, and `with_resolution(scene, level) -> dict`, a copy of the scene config at
another level (plate: `grid_nodes`, nodes per side; tissue: nodes along x, the other axes scaled
alike, see `scenes.tissue.with_resolution`; cavity: nodes per ring, `scenes.cavity.with_resolution`); a scene without them runs at its preset's mesh only
(asking for a level is an error naming the scene). `resolution` sets the level for the simulator
(reference and coarse runs alike; `grid_nodes` is its older, plate-only name) and the node count
and level are recorded. `tradeoff` takes several levels: at the preset's own the learned models
are evaluated on the stored test split; at any other, `resolution_tests` generates test
trajectories at that level (real point clouds, same scenes and seeds) into
`<preset output>_grid<level>`, and the models are timed and scored on them. The models were
trained at the preset's resolution, so their error at another one is out of distribution (the
column `reference` says so); their time per step is what the resolution costs. On a denser mesh
than the preset's their graph builder's guard `max_num_neighbors` is raised by the density ratio
((level - 1) / (preset level - 1))^dim (edges are unchanged: the guard raises, it never drops).
The CSV is rewritten after each level, so a failure at a later level keeps the earlier rows.

Model points (`model_points`): each checkpoint (a path or a pretrained name) is loaded with `pretrained.load_model`
(the class is stored in the checkpoint). Rollouts of whole test trajectories per
point-cloud schedule (schedules with point clouds only for models that use them): ms per step
for 1 trajectory and for `batch` trajectories at once (test trajectories repeated if fewer), the
median of `repeats` rollouts after a warm-up (`timing.time_rollout`), on the CPU (torch's
threads, or `threads`, which the device column then names; the simulator always runs on 1) and,
when present, CUDA; the rollout MSE (`metrics.rollout_mse`, all nodes, as in `evaluate_batch`) of the
first `trajectories` test trajectories against the dataset. Each model row names its size (class,
latent width, processor blocks, parameter count), so checkpoints of several sizes put model size on
the trade-off as an axis beside mesh resolution.

The plot's x axis is ms per trajectory-step (models: the batched time divided by the batch; the
simulator runs one trajectory at a time), y the rollout MSE; both are logarithmic, so zero errors
(the simulator reference) are drawn at the bottom edge; the time-step rows of a resolution are
joined by a line, its Newton-tolerance rows drawn as crosses. Note the two references: simulator
errors are against the finer simulator, model errors against the dataset.
"""
from __future__ import annotations

import dataclasses
import math
import statistics
from pathlib import Path

import numpy as np
import torch

from ..batch import TrajectoryBatch
from ..config import load_config
from ..data.generate import generate, split_path, trajectory_jobs
from ..data.module import SimulationDataModule
from ..data.schema import DatasetError, read_trajectories
from ..evaluation.evaluate import split_trajectories
from ..evaluation.metrics import rollout_mse
from ..evaluation.predict import check_model_fits
from ..evaluation.schedules import effective_schedules
from ..pretrained import load_model
from ..reports import write_csv
from ..scenes import SCENES
from ..sim.solver import SolverConfig
from ..viz import plt, save_figure
from .report import print_table
from .timing import NoSensor, default_devices, time_rollout, time_trajectories

COLUMNS = ("kind", "name", "setting", "device", "nodes", "steps", "trajectories", "ms_per_step_1",
           "batch", "ms_per_step_batched", "ms_per_trajectory_step", "rollout_mse", "reference", "pareto",
           "resolution", "axis", "substeps", "newton_tolerance", "newton_iterations", "mse_vs_preset_tolerance",
           "model_class", "latent", "blocks", "parameters")


def reference_substeps_for(preset_substeps: int, coarsen) -> int:
    """Smallest multiple of the preset's substeps that every coarsening factor divides."""
    return math.lcm(int(preset_substeps), *(int(c) for c in coarsen))


def resolution_module(scene_name: str):
    """The scene module of `scene_name`, checked to define mesh resolution levels
    (`resolution(scene) -> int` and `with_resolution(scene, level) -> dict`; module docstring)."""
    if scene_name not in SCENES:
        raise ValueError(f"unknown scene {scene_name!r}; known: {sorted(SCENES)}")
    module = SCENES[scene_name]
    missing = [f for f in ("resolution", "with_resolution") if not callable(getattr(module, f, None))]
    if missing:
        raise ValueError(f"scene {scene_name!r} has no mesh resolution levels: its module {module.__name__} lacks "
                         f"{' and '.join(missing)}(...), which bench tradeoff needs for --resolution; run it without "
                         f"--resolution (the preset's own mesh) or add them to the scene module")
    return module


def preset_resolution(scene: dict):
    """The preset's own resolution level, or "" when its scene module defines no levels."""
    module = SCENES.get(scene["name"])
    return int(module.resolution(scene)) if callable(getattr(module, "resolution", None)) else ""


def at_resolution(config: dict, level: int | None) -> dict:
    """`config` with its scene at mesh resolution `level` (None: unchanged)."""
    if level is None:
        return config
    module = resolution_module(config["scene"]["name"])
    return {**config, "scene": module.with_resolution(config["scene"], int(level))}


def simulator_points(config: dict, trajectories: int = 4, coarsen=(1, 2, 5), grid_nodes: int | None = None,
                     reference_substeps: int | None = None, split: str = "test", resolution: int | None = None,
                     newton_tolerances=()) -> list[dict]:
    """One row per coarsening factor, then one per Newton tolerance (module docstring): ms per
    simulated frame and rollout MSE against the reference (substeps `reference_substeps`, the
    preset's tolerance); the first `trajectories` of `split`, at mesh resolution `resolution`
    (`grid_nodes`: its older, plate-only name; None: the preset's)."""
    coarsen = sorted({int(c) for c in coarsen})
    if not coarsen or coarsen[0] < 1 or trajectories < 1:
        raise ValueError(f"need coarsening factors >= 1 and trajectories >= 1, got {coarsen}, {trajectories}")
    if grid_nodes is not None and resolution is not None:
        raise ValueError("give resolution or grid_nodes (its older name), not both")
    level = resolution if resolution is not None else grid_nodes
    base = at_resolution(config, level)
    scene, solver = dict(base["scene"]), dict(base["solver"])
    preset_substeps = int(config["scene"]["substeps"])
    preset_tolerance = float(solver.get("newton_tolerance", SolverConfig.newton_tolerance))
    tolerances = sorted({float(t) for t in newton_tolerances})
    finer = [t for t in tolerances if t <= preset_tolerance]
    if finer:
        raise ValueError(f"Newton tolerances must be coarser than the preset's {preset_tolerance:g}, got {finer}")
    reference = reference_substeps or reference_substeps_for(preset_substeps, coarsen)
    bad = [c for c in coarsen if reference % c]
    if bad:
        raise ValueError(f"reference_substeps={reference} is not divisible by the coarsening factors {bad}")
    module = SCENES[scene["name"]]

    def setting(substeps: int, tolerance: float = preset_tolerance) -> dict:
        return {**base, "scene": {**scene, "substeps": substeps}, "solver": {**solver, "newton_tolerance": tolerance}}

    module.check_config(setting(reference))
    for tolerance in tolerances:
        module.check_config(setting(preset_substeps, tolerance))
    jobs = trajectory_jobs(base, split, trajectories)
    sensor = NoSensor(int(getattr(module, "DIM", scene.get("dim", 2))))
    runs = {c: time_trajectories(module, setting(reference // c), jobs, sensor) for c in coarsen}
    # the reference: the c = 1 runs if made, else simulated now (untimed)
    reference_runs = runs[1] if 1 in runs else time_trajectories(module, setting(reference), jobs, sensor)
    truth = torch.from_numpy(np.stack([t.positions for _, t in reference_runs]))
    level = level if level is not None else preset_resolution(scene)
    points = [(f"substeps={reference // c} (coarsen {c}x)", "time step", reference // c, preset_tolerance, runs[c])
              for c in coarsen]
    points += [(f"newton_tolerance={t:g} (substeps={preset_substeps})", "newton tolerance", preset_substeps, t,
                time_trajectories(module, setting(preset_substeps, t), jobs, sensor)) for t in tolerances]
    same_steps = None  # the tolerance rows' own error: against the preset's tolerance at the same substeps
    if tolerances:
        c = reference // preset_substeps if reference % preset_substeps == 0 else None
        same_steps = runs[c] if c in runs else time_trajectories(module, setting(preset_substeps), jobs, sensor)
        same_steps = torch.from_numpy(np.stack([t.positions for _, t in same_steps]))
    rows = []
    for label, axis, substeps, tolerance, timed in points:
        pred = np.stack([t.positions for _, t in timed])
        steps = pred.shape[1] - 1
        ms = 1e3 * statistics.median(seconds / steps for seconds, _ in timed)
        iterations = [t.diagnostics["newton_iterations"][1:].mean() for _, t in timed
                      if t.diagnostics is not None and "newton_iterations" in t.diagnostics]
        rows.append({
            "kind": "simulator", "name": "simulator", "setting": label,
            "device": "cpu (1 thread)", "nodes": int(pred.shape[2]), "steps": steps, "trajectories": len(jobs),
            "ms_per_step_1": ms, "batch": 1, "ms_per_step_batched": ms, "ms_per_trajectory_step": ms,
            "rollout_mse": rollout_mse(torch.from_numpy(pred), truth)[0],
            "reference": f"simulator substeps={reference}"
            + (f", newton_tolerance={preset_tolerance:g}" if tolerances else ""),
            "resolution": level, "axis": axis, "substeps": substeps, "newton_tolerance": tolerance,
            "newton_iterations": float(np.mean(iterations)) / substeps if iterations else "",
            "mse_vs_preset_tolerance": rollout_mse(torch.from_numpy(pred), same_steps)[0]
            if axis == "newton tolerance" else "",
        })
    return rows


def resolution_tests(config: dict, grid_nodes: int, count: int, log=print):
    """`count` test trajectories of the preset `config` at mesh resolution level `grid_nodes`
    (plate: nodes per side; the scene module's `with_resolution`) with its scenes and seeds and
    real point clouds, generated once into `<output>_grid<level>/test.h5` and regenerated when
    that file holds fewer or was made with another scene, solver or sensor configuration.
    Returns (trajectories, data directory)."""
    if int(grid_nodes) < 2 or count < 1:
        raise ValueError(f"need a resolution level >= 2 and count >= 1, got {grid_nodes}, {count}")
    level = int(grid_nodes)
    output = Path(f"{config['output']}_grid{level}")
    cfg = {**at_resolution(config, level), "splits": {"test": int(count)}, "output": str(output)}
    path = split_path(output, "test")
    try:
        tests = read_trajectories(path, expected_config=cfg) if path.exists() else []
    except DatasetError:
        tests = []  # made with another configuration: regenerated
    if len(tests) < count:
        log(f"generating {count} {config['scene']['name']} test trajectories at mesh resolution {level} into {output}")
        generate(cfg, ["test"], overwrite=path.exists(), progress=False)
        tests = read_trajectories(path)
    return tests[:count], output


def model_points(checkpoints: dict, dataset: str = "plate_small", schedules=("every:1", "never"), trajectories: int = 4,
                 batch: int = 32, repeats: int = 3, devices=None, data_dir: str | None = None,
                 tests: list | None = None, reference: str | None = None, resolution: int | str = "",
                 neighbour_scale: float = 1.0, threads: int | None = None) -> list[dict]:
    """One row per checkpoint x schedule x device (module docstring). `tests`: the test
    trajectories to use instead of the dataset's test split (`reference` then names them);
    `resolution`: their mesh resolution level, for the CSV; `neighbour_scale`: the models'
    `max_num_neighbors` (a guard of the graph builder, which raises rather than drop an edge) is
    multiplied by it, for meshes denser than the models were trained on (edges are unchanged);
    `threads`: torch threads of the CPU rollouts (default: torch's; the device column then says so)."""
    if threads is not None and int(threads) < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    before = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(int(threads))
    try:
        return _model_points(checkpoints, dataset, schedules, trajectories, batch, repeats, devices, data_dir, tests,
                             reference, resolution, neighbour_scale,
                             "" if threads is None else f" ({threads} thread{'s' if threads > 1 else ''})")
    finally:
        torch.set_num_threads(before)


def _model_points(checkpoints, dataset, schedules, trajectories, batch, repeats, devices, data_dir, tests, reference,
                  resolution, neighbour_scale, cpu_note) -> list[dict]:
    if trajectories < 1 or batch < 1 or repeats < 1:
        raise ValueError("trajectories, batch and repeats must be >= 1")
    if tests is None:
        datamodule = SimulationDataModule(dataset=dataset, data_dir=data_dir)
        if not datamodule.path("test").exists():  # only the test split is used
            datamodule.prepare_data()
        tests = datamodule.trajectories("test")
    reference = reference or f"dataset {dataset} test"
    scored = tests[:trajectories]
    rows = []
    for name, path in checkpoints.items():
        model = load_model(path, map_location="cpu")
        check_model_fits(model, tests[0].dim)
        if neighbour_scale > 1:
            cap = math.ceil(model.connectivity.max_num_neighbors * neighbour_scale)
            model.connectivity = dataclasses.replace(model.connectivity, max_num_neighbors=cap)
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
                where = str(device) + (cpu_note if device.type == "cpu" else "")
                rows.append({
                    "kind": "model", "name": name, "setting": str(schedule), "device": where,
                    "nodes": int(np.mean(np.diff(one.node_offsets))), "steps": steps, "trajectories": len(scored),
                    "ms_per_step_1": ms_one, "batch": batch, "ms_per_step_batched": ms_many,
                    "ms_per_trajectory_step": ms_many / batch, "rollout_mse": mse, "reference": reference,
                    "resolution": resolution, "model_class": type(model).__name__,
                    "latent": model.hparams.latent, "blocks": model.hparams.blocks,
                    "parameters": sum(p.numel() for p in model.parameters()),
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
    fig, ax = plt.subplots(figsize=(9.5, 5))
    resolutions = list(dict.fromkeys(r.get("nodes") for r in rows))
    shades = dict(zip(resolutions, ("black", "dimgray", "darkgray", "silver")))
    for nodes in resolutions:
        sim = [i for i, r in enumerate(rows) if r["kind"] == "simulator" and r.get("nodes") == nodes]
        steps = [i for i in sim if rows[i].get("axis") != "newton tolerance"]
        tolerances = [i for i in sim if rows[i].get("axis") == "newton tolerance"]
        where = f", {nodes} nodes" if len(resolutions) > 1 else ""
        if steps:
            order = sorted(steps, key=lambda i: xs[i])
            ax.plot(xs[order], shown[order], "-o", color=shades.get(nodes, "black"),
                    label=f"simulator (coarser time steps{where})")
        if tolerances:
            ax.scatter(xs[tolerances], shown[tolerances], marker="x", color=shades.get(nodes, "black"),
                       label=f"simulator (coarser Newton tolerance{where})")
    markers = iter("sD^vP*Xph<>")
    for key in dict.fromkeys((r["name"], r["device"]) for r in rows if r["kind"] != "simulator"):
        idx = [i for i, r in enumerate(rows) if (r["name"], r["device"]) == key and r["kind"] != "simulator"]
        ax.scatter(xs[idx], shown[idx], marker=next(markers, "o"), s=50, label=f"{key[0]} ({key[1]})")
    for i, r in enumerate(rows):
        label = f"tol {r['newton_tolerance']:g}" if r.get("axis") == "newton tolerance" else r["setting"]
        label += " = reference (error 0)" if ys[i] == 0 else ""
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
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside: the points stay visible
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


def tradeoff(dataset: str = "plate_small", checkpoints: dict | None = None, trajectories: int = 4, coarsen=(1, 2, 5),
             output_dir: str | Path = "lightning_logs/tradeoff", schedules=("every:1", "never"), batch: int = 32,
             repeats: int = 3, grid_nodes=None, data_dir: str | None = None, resolution=None,
             newton_tolerances=(), threads: int | None = None, simulator: bool = True, devices=None) -> list[dict]:
    """Simulator and model points at each mesh resolution level in `resolution` (an int, a list,
    or None for the preset's; `grid_nodes`: its older, plate-only name), the simulator's time-step
    coarsenings and Newton tolerances at each (`threads`: torch threads of the model rollouts;
    `simulator` False: the models only; `devices`: where the models roll out, default the CPU and
    CUDA where present); writes <output_dir>/tradeoff.csv and tradeoff.png and
    prints the table."""
    if not simulator and not checkpoints:
        raise ValueError("nothing to measure: no checkpoints and the simulator left out")
    config = load_config(dataset)
    if grid_nodes is not None and resolution is not None:
        raise ValueError("give resolution or grid_nodes (its older name), not both")
    levels = resolution if resolution is not None else grid_nodes
    if levels is None:
        preset, resolutions = None, [None]  # the preset's own mesh: no resolution levels needed
    else:
        preset = int(resolution_module(config["scene"]["name"]).resolution(config["scene"]))
        resolutions = [int(n) for n in np.atleast_1d(levels)]
    out = Path(output_dir)
    rows = []
    for level in resolutions:
        if simulator:
            rows += simulator_points(config, trajectories, coarsen, resolution=level,
                                     newton_tolerances=newton_tolerances)
        if checkpoints and (level is None or level == preset):
            rows += model_points(checkpoints, dataset, schedules, trajectories, batch=batch, repeats=repeats,
                                 data_dir=data_dir, resolution=preset_resolution(config["scene"]), threads=threads,
                                 devices=devices)
        elif checkpoints:
            tests, directory = resolution_tests({**config, "output": data_dir or config["output"]}, level, trajectories)
            dim = int(getattr(SCENES[config["scene"]["name"]], "DIM", 2))
            rows += model_points(checkpoints, dataset, schedules, trajectories, batch=batch, repeats=repeats,
                                 tests=tests, reference=f"{directory} test (models trained at resolution {preset})",
                                 resolution=level, neighbour_scale=((level - 1) / (preset - 1)) ** dim,
                                 threads=threads, devices=devices)
        tradeoff_csv(rows, out / "tradeoff.csv")  # so far: a later level's failure keeps these rows
        print(f"resolution {'(preset)' if level is None else level}: {len(rows)} rows so far", flush=True)
    for row, on_front in zip(rows, pareto_mask(rows)):
        row["pareto"] = on_front
    csv_path, png_path = tradeoff_csv(rows, out / "tradeoff.csv"), pareto_plot(rows, out / "tradeoff.png")
    print_table(rows, COLUMNS)
    print(f"\nwrote {csv_path} and {png_path}")
    return rows
