"""The commands of `python -m ggns` besides the Lightning CLI's fit/validate/test/predict (ggns.cli).

One typed, documented function per command; `COMMANDS` maps the command line's words to them
and `ggns.command_line` builds the parser from their signatures and docstrings (an option per
parameter: `train_batches` is `--train-batches`). They are also the Python API of the commands:
`commands.generate(config="plate_tiny", split=["train"], count=3)`. Each command imports what it
runs when it runs, so building the parser (or `--help`) loads neither torch nor Lightning
(importing pytorch_lightning alone takes about 5 s here).
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

Split = Literal["train", "val", "test"]


def generate(*overrides: str, config: str = "plate", split: Sequence[Split] | None = None, count: int | None = None,
             seed: int | None = None, output: str | None = None, workers: int | None = None,
             overwrite: bool = False, shard: str | None = None, merge_shards: int | None = None) -> list[Path]:
    """Generate dataset splits (simulate, observe, write HDF5).

    On a cluster, one job per shard (scripts/slurm_generate.sh): `--shard i/n` makes every n-th
    trajectory of each split from the i-th into <split>.shard-<i>-of-<n>.h5, and `--merge-shards n`
    then writes <split>.h5 from them, bit for bit what one machine would make.

    Args:
        overrides: config overrides as key=value, e.g. scene.num_steps=20 (a key the preset lacks is an error)
        config: preset name in conf/data/ or a YAML path
        split: split(s) to generate (default: all in the config)
        count: trajectories per chosen split (default: the config's split sizes; needs --split)
        seed: the config's seed (trajectory i of a split has a seed derived from it)
        output: output directory, one <split>.h5 per split (default: the config's)
        workers: parallel worker processes (default: the config's)
        overwrite: replace existing split files
        shard: i/n, make shard i (from 0) of n of each chosen split (its own file)
        merge_shards: n, write the split files from their n shard files (simulates nothing)
    """
    from .config import load_config

    overrides = list(overrides)
    for key, value in (("seed", seed), ("output", output), ("workers", workers)):
        if value is not None:
            overrides.append(f"{key}={value}")
    if count is not None:
        if not split:
            raise ValueError("--count needs --split (which split gets that many trajectories)")
        overrides += [f"splits.{s}={count}" for s in split]
    if shard is not None and merge_shards is not None:
        raise ValueError("--shard makes one shard, --merge-shards merges them all: give one of them")
    chosen = list(split) if split else None
    settings = load_config(config, overrides)  # a typo is refused here, before torch is imported
    from .data.generate import generate as generate_splits, merge_shards as merge_split_shards, parse_shard

    if merge_shards is not None:
        paths = merge_split_shards(settings, merge_shards, chosen, overwrite=overwrite)
    else:
        paths = generate_splits(settings, chosen, overwrite=overwrite,
                                shard=parse_shard(shard) if shard is not None else None)
    for path in paths:
        print(path)
    return paths


def import_reference(*overrides: str, input: str, config: str = "reference_plate", split: Split | None = None,
                     output: str | None = None, fixed: str | None = None, youngs_modulus: float | None = None,
                     steps: int | None = None, overwrite: bool = False) -> Path:
    """Import one split of the paper authors' datasets (jlinki/GGNS pickles) as an HDF5 split file.

    The pickle is read as data only (numpy arrays and containers; anything else is refused). See
    docs/dataset_format.md, "Importing the authors' pickles", for what each key becomes.

    Args:
        overrides: preset overrides as key=value, e.g. importer.fixed_tolerance=1e-5 (a key the preset lacks is an error)
        input: the authors' pickle, e.g. deformable_plate_dataset_train.pkl (a list with one dict per trajectory)
        config: data preset of the imported dataset, reference_plate, reference_tissue, reference_cavity or a YAML path
        split: the split the file becomes (default: from the file name, _train, _eval as val, _test)
        output: output directory, gets <split>.h5 (default: the preset's)
        fixed: fixed mesh nodes, e.g. 0-29 (default: inferred as the nodes that never move)
        youngs_modulus: E in Pa of every trajectory (default: the preset's, by Poisson's ratio; the cavity needs it)
        steps: keep the first n states of every trajectory (default: all)
        overwrite: replace an existing split file
    """
    from .config import load_config
    from .data.reference import import_reference as convert, split_from_name

    preset = load_config(config, list(overrides))
    if "importer" not in preset:
        raise ValueError(f"--config {config}: not a preset of imported data (it has no importer section; "
                         "see conf/data/reference_plate.yaml)")
    for key, value in (("fixed", fixed), ("youngs_modulus", youngs_modulus), ("steps", steps)):
        if value is not None:
            preset["importer"][key] = value
    summary = convert(input, preset, split or split_from_name(input), output, overwrite=overwrite)
    ranges = (f"{name} {lo:g}" + (f"-{hi:g}" if hi != lo else "") for name, (lo, hi) in summary["sizes"].items())
    print(f"{summary['path']}: {summary['trajectories']} trajectories; {', '.join(ranges)}")
    return summary["path"]


def geometry(dataset: str = "plate_small", split: Split = "train", trajectories: int = 27, stride: int = 5,
             targets: str = "plate") -> bool:
    """Measure a generated dataset's scale (points, neighbours, edges, motion) against the targets.

    Args:
        dataset: data preset whose generated split is measured
        split: the split measured
        trajectories: the split's first n trajectories
        stride: measure every n-th step
        targets: targets file, conf/geometry/<name>.yaml or a YAML path
    """
    from .data.module import SimulationDataModule
    from .graphs.scale import geometry_report


    data = SimulationDataModule(dataset, generate_missing=False)
    table, ok = geometry_report(data.trajectories(split)[:trajectories], f"{dataset} {data.path(split)}", targets,
                                stride)
    print(table)
    print("all targets met" if ok else "some targets are not met (OUT OF RANGE above)")
    return ok


def bench_sim(*overrides: str, config: str = "plate", trajectories: int = 9, generate: bool = False) -> dict:
    """Time the ground-truth simulator and the depth sensor (and dataset generation).

    Args:
        overrides: preset overrides as key=value, e.g. solver.linear_solver=sparse (a key the preset lacks is an error)
        config: data preset
        trajectories: trajectories timed one by one
        generate: also time generating all splits of the config with its workers
    """
    from .bench import sim as sim_bench

    return sim_bench.bench_sim(config, trajectories=trajectories, generate_splits=generate, overrides=list(overrides))


def bench_solvers(nodes: Sequence[int] = (10, 6, 6), frames: int = 12,
                  solvers: Sequence[Literal["dense", "sparse", "banded"]] = ("dense", "sparse")) -> dict:
    """The simulator's linear solvers (dense, sparse, banded) timed on a tetrahedral block with a pulled node.

    Args:
        nodes: nodes per axis of the block (1 x 0.6 x 0.6 m)
        frames: frames simulated per solver (medians reported)
        solvers: the linear solvers timed
    """
    from .bench import sim as sim_bench

    return sim_bench.bench_linear_solvers(tuple(nodes), frames=frames, solvers=tuple(solvers))


def bench_models(dataset: str = "plate_small", models: Sequence[str] = ("ggns", "ggns_lstm", "mgn", "mgn_m"),
                 train_batches: int = 10, rollout_steps: int | None = None,
                 device: Literal["cpu", "cuda"] = "cpu", output: str | None = None, batch_size: int = 32,
                 rollout_trajectories: int = 32, repeats: int = 3) -> list[dict]:
    """Training and rollout throughput of the learned simulators.

    Args:
        dataset: data preset (train and test splits; generated if missing)
        models: model configs of conf/plate/
        train_batches: timed training iterations per model
        rollout_steps: steps per timed rollout (default: whole test trajectories)
        device: where the models run
        output: write the measurements to this CSV
        batch_size: training windows per batch (paper: 32)
        rollout_trajectories: trajectories in the batched rollout
        repeats: timed rollouts per measurement (the median is reported)
    """
    from .bench import models as model_bench


    return model_bench.bench_models(dataset, tuple(models), train_batches=train_batches, rollout_steps=rollout_steps,
                                    device=device, output=output, batch_size=batch_size,
                                    rollout_trajectories=rollout_trajectories, repeats=repeats)


def bench_tradeoff(dataset: str = "plate_small", checkpoint: dict[str, str] | None = None, trajectories: int = 4,
                   coarsen: Sequence[int] = (1, 2, 5), schedules: Sequence[str] = ("every:1", "never"),
                   grid_nodes: Sequence[int] | None = None, rollout_trajectories: int = 32, repeats: int = 3,
                   output_dir: str = "lightning_logs/tradeoff", resolution: Sequence[int] | None = None,
                   newton_tolerance: Sequence[float] | None = None, data_dir: str | None = None,
                   threads: int | None = None, simulator: bool = True,
                   devices: Sequence[str] | None = None) -> list[dict]:
    """Time per rollout step against rollout error: the simulator and model checkpoints (CSV + Pareto plot).

    Args:
        dataset: data preset whose test trajectories are scored
        checkpoint: a model checkpoint to place on the trade-off, as name=path
        trajectories: test trajectories scored
        coarsen: simulator time-step coarsening factors
        schedules: point-cloud schedules of the model rollouts
        grid_nodes: the plate's mesh nodes per side (older name of --resolution)
        rollout_trajectories: trajectories in the batched rollout
        repeats: timed rollouts per measurement (the median is reported)
        output_dir: where tradeoff.csv and tradeoff.png go
        resolution: mesh resolution levels for the simulator and the models (plate: nodes per side, tissue: nodes along x, cavity: nodes per ring; default: the preset's)
        newton_tolerance: also the simulator at these Newton tolerances (m, coarser than the preset's), at the preset's substeps
        data_dir: the dataset's directory (default: the preset's output)
        threads: torch threads of the model rollouts on the CPU (default: torch's; the simulator always runs on 1)
        simulator: also the simulator's points (--no-simulator: the checkpoints only)
        devices: where the model rollouts run, cpu and/or cuda (default: cpu, and cuda where torch sees a GPU)
    """
    from .bench.timing import resolve_device
    from .bench.tradeoff import tradeoff


    if grid_nodes and resolution:
        raise ValueError("give --resolution or --grid-nodes (its older name), not both")
    levels = resolution or grid_nodes
    return tradeoff(dataset, dict(checkpoint or {}), trajectories=trajectories, coarsen=tuple(coarsen),
                    output_dir=output_dir, schedules=tuple(schedules), batch=rollout_trajectories, repeats=repeats,
                    resolution=list(levels) if levels else None, newton_tolerances=tuple(newton_tolerance or ()),
                    data_dir=data_dir, threads=threads, simulator=simulator,
                    devices=[str(resolve_device(d)) for d in devices] if devices else None)


def bench_stability(dataset: str = "plate", checkpoint: dict[str, str] | None = None, steps: int = 1000,
                    beyond: Sequence[float] = (-0.95, 0.499), schedules: Sequence[str] = ("every:1", "never"),
                    dtypes: Sequence[str] = ("float32", "float64"), stride: int = 10,
                    output_dir: str = "lightning_logs/stability") -> list[dict]:
    """Long rollouts at and beyond the training materials, smallest and largest colliders, float32 and 64.

    Args:
        dataset: data preset whose scene is simulated (plate: the push, then held)
        checkpoint: a simulator to roll out, as name=path or name=pretrained name (default: the shipped ones of the scene)
        steps: recorded states of each trajectory (the plate preset's 50, the tissue's 100)
        beyond: Poisson's ratios beyond the training ones, also rolled out
        schedules: point-cloud schedules (with point clouds only for models that use them)
        dtypes: float32 and/or float64 (the drift between them is reported)
        stride: steps between CSV rows
        output_dir: where stability.csv, .md and .png go
    """
    from .bench.stability import stability

    return stability(dataset, dict(checkpoint) if checkpoint else None, steps=steps, beyond=tuple(beyond),
                     schedules=tuple(schedules), dtypes=tuple(dtypes), stride=stride, output_dir=output_dir)


def bench_learning(*overrides: str, config: str = "plate_ggns", minutes: float | None = None,
                   parallel: int | None = None, variant: Sequence[str] | None = None, output_dir: str | None = None,
                   report_only: bool = False, dry_run: bool = False) -> Path | None:
    """Learning curves of named model variants within a wall-clock budget each (table + plots).

    Args:
        overrides: learning-file overrides as key=value, e.g. val_every=50
        config: learning file in conf/learning/ or a checkout's experiments/*/learning/, or a YAML path
        minutes: wall-clock budget per variant (default: the file's)
        parallel: variants at once (default: the file's)
        variant: run only these variants (default: all; the report covers every variant with logs)
        output_dir: where the variants and the report go (default: the file's output)
        report_only: only write the report from the logs
        dry_run: print each variant's fit command (its config files and settings) and run nothing
    """
    from .experiments.learning import load_learning, run_learning, variant_runs, write_report


    overrides = list(overrides)
    for key, value in (("minutes", minutes), ("parallel", parallel), ("output", output_dir)):
        if value is not None:
            overrides.append(f"{key}={value}")
    spec = load_learning(config, overrides)
    if dry_run:
        print_commands([r for r in variant_runs(spec) if not variant or r.model in variant])
        return None
    return write_report(spec) if report_only else run_learning(spec, variant)


def print_commands(runs) -> None:
    """Each run's fit command as a shell line (`python -m ggns fit --config ... --key value ...`)."""
    import shlex

    for run in runs:
        print(f"# {run.model} seed {run.seed}")
        print(shlex.join(["python", *run.fit_command()[1:]]))


def export(checkpoint: str, dataset: str = "plate_small", data_dir: str | None = None,
           split: Literal["train", "val", "test"] = "test", trajectory: int = 0, schedule: str = "every:1",
           output: str = "lightning_logs/export") -> list[Path]:
    """Write one trajectory's truth (when known), a checkpoint's rollout and the point clouds as ParaView files.

    Args:
        checkpoint: the model checkpoint (.ckpt) whose rollout is written, or a pretrained name (plate/ggns)
        dataset: data preset whose split holds the trajectory
        data_dir: folder of the split files (default: the preset's output)
        split: the split
        trajectory: index of the trajectory in the split
        schedule: point-cloud schedule of the rollout (a model without point clouds uses never)
        output: folder of the .pvd collections (truth, the model, points) and their .vtu steps
    """
    from .batch import TrajectoryBatch
    from .data.module import SimulationDataModule
    from .evaluation.pictures import rollout_series
    from .evaluation.predict import check_model_fits
    from .evaluation.schedules import parse_schedule
    from .pretrained import load_model
    from .paraview import write_rollout

    model = load_model(checkpoint, map_location="cpu")
    data = SimulationDataModule(dataset, data_dir=data_dir, generate_missing=False)
    trajectories = data.trajectories(split)
    if not 0 <= trajectory < len(trajectories):
        raise ValueError(f"--trajectory {trajectory} is not among the {len(trajectories)} {split} trajectories")
    chosen = trajectories[trajectory]
    check_model_fits(model, chosen.dim, data.config["scene"]["name"])
    preds, points = rollout_series(TrajectoryBatch.from_trajectories([chosen]), {type(model).__name__: model},
                                   parse_schedule(schedule))
    names = {re.sub(r"[^\w.+-]+", "_", label).strip("_"): x for label, x in preds.items()}
    truth = chosen.positions if chosen.has_ground_truth else None  # a trajectory of your own may have none
    paths = write_rollout(output, chosen.cells, truth, names, points,
                          frame_dt=float(chosen.params.get("frame_dt", 1.0)))
    for path in paths:
        print(path)
    return paths


def diagnose(checkpoint: str, dataset: str = "tissue_cpu", data_dir: str | None = None,
             split: Literal["train", "val", "test"] = "val", trajectories: int = 9,
             schedule: Sequence[str] = ("every:1", "never"), output: str | None = None,
             visibility_radius: float | None = None, m_plus_10_stride: int = 0) -> str:
    """Where a checkpoint's rollout error lives: surface normal, surface tangential, interior (in 2D
    the surface is the outline), and by what the cameras saw (seen, sometimes seen, never seen).

    Args:
        checkpoint: the model checkpoint (.ckpt) to roll out, or a pretrained name (tissue/ggns)
        dataset: data preset whose split holds the trajectories
        data_dir: folder of the split files (default: the preset's output)
        split: the split
        trajectories: the first n trajectories of the split, rolled out as one batch
        schedule: point-cloud schedules to roll out (a model without point clouds uses never)
        output: also write the table to this markdown file
        visibility_radius: a node is seen at a step with a point this close (default: 0.75 x the nodes' median shortest rest edge)
        m_plus_10_stride: also the m+10 error per start m, every this many m (0: not); for GGNSID also its material estimate's error after m point clouds
    """
    from .batch import TrajectoryBatch
    from .data.module import SimulationDataModule
    from .evaluation.evaluate import split_trajectories
    from .evaluation.observability import PARTS, SEEN_AT_LEAST, VISIBILITY, error_shares
    from .evaluation.predict import check_model_fits
    from .evaluation.schedules import effective_schedule, parse_schedule
    from .pretrained import load_model
    from .reports import markdown_table, write_text

    model = load_model(checkpoint, map_location="cpu")
    data = SimulationDataModule(dataset, data_dir=data_dir, generate_missing=False)
    chosen = data.trajectories(split)[:trajectories]
    if not chosen:
        raise ValueError(f"diagnose needs trajectories; {dataset}/{split} has none")
    check_model_fits(model, chosen[0].dim, data.config["scene"]["name"])
    batch = TrajectoryBatch.from_trajectories(chosen)
    rows, done, parts = [], set(), []
    for text in schedule:
        plan = effective_schedule(parse_schedule(text), model.uses_points)
        if plan.key in done:
            continue
        done.add(plan.key)
        preds = split_trajectories(model.rollout(batch, plan), batch)
        parts = [error_shares(p[0].numpy(), traj.positions, traj.rest_positions, traj.cells, traj.fixed,
                              points=traj.points, point_offsets=traj.point_offsets, radius=visibility_radius)
                 for p, traj in zip(preds, chosen)]
        mean = {p: sum(part[p] for part in parts) / len(parts) for p in (*PARTS, *VISIBILITY)}
        total = sum(mean[p] for p in PARTS)
        rows.append([plan.key, f"{total:.3g}",
                     *(f"{mean[p]:.3g} ({mean[p] / total if total > 0 else 0.0:.2f})" for p in (*PARTS, *VISIBILITY))])
    table = (f"{type(model).__name__} from {checkpoint}, {len(chosen)} {split} trajectories of {dataset}: mean squared "
             f"error per free node and coordinate over states 1..T-1, mean over trajectories (share of that total)\n\n"
             + markdown_table(["schedule", "free nodes", *PARTS, *VISIBILITY], rows) + "\n")
    if parts:  # the groups depend on the data only (true positions and point clouds), not on the schedule
        nodes = {g: sum(part[f"{g}_nodes"] for part in parts) for g in VISIBILITY}
        radii = sorted({part["visibility_radius"] for part in parts})
        radius = f"{radii[0]:.3g}" if len(radii) == 1 else f"{radii[0]:.3g} to {radii[-1]:.3g}"
        table += (f"\nVisibility groups of the free nodes, from the data's point clouds whatever the schedule: a node is "
                  f"seen at a step when a point of that step's cloud lies within {radius} of its true position; seen "
                  f"at >= {SEEN_AT_LEAST:.0%} of the steps: seen, at none: never_seen. Free nodes over the "
                  f"{len(chosen)} trajectories: "
                  + ", ".join(f"{g} {nodes[g]} ({nodes[g] / max(sum(nodes.values()), 1):.2f})" for g in VISIBILITY)
                  + "\n")
    if m_plus_10_stride < 0:
        raise ValueError(f"m_plus_10_stride must be >= 0, got {m_plus_10_stride}")
    if m_plus_10_stride and batch.num_steps > 10:
        from .evaluation.evaluate import m_plus_10_profile, pooled_over
        from .evaluation.metrics import m_plus_10_starts

        profile = m_plus_10_profile(model, batch, m_plus_10_starts(batch.num_steps)[::m_plus_10_stride])
        columns = ["m", "m10_mse", "m10_pooled_mse"] + (["material_error"] if "material_error" in profile[0] else [])
        table += ("\nm+10 per start m: the error at S_{m+10} after m point clouds and 10 blind steps (m10_mse), the "
                  "same rollout's steps 1..m+10 pooled as the authors' code did (m10_pooled_mse)"
                  + (", and the mean |estimate - Poisson's ratio| of the material carried after the m point clouds "
                     "(material_error; none before the first)" if "material_error" in columns else "")
                  + f"; over these m: m10_mse {sum(r['m10_mse'] for r in profile) / len(profile):.3g} (mean), "
                  f"m10_pooled_mse {pooled_over(profile):.3g} (every step of these rollouts pooled)\n\n"
                  + markdown_table(columns, [[str(r["m"])] + [f"{r[c]:.3g}" for c in columns[1:]] for r in profile])
                  + "\n")
    print(table)
    if output:
        write_text(output, table)
    return table


def rollout(checkpoint: str, input: str, output: str = "predictions.h5", trajectories: Sequence[int] | None = None,
            schedule: str = "every:1", batch_size: int = 8, device: Literal["cpu", "cuda"] = "cpu",
            overwrite: bool = False) -> Path:
    """Roll out a checkpoint on the trajectories of a split file and write the predictions file.

    Args:
        checkpoint: a pretrained model's name (e.g. plate/ggns) or a .ckpt path
        input: split file (docs/dataset_format.md), generated or written from your own arrays
        output: the predictions file written (docs/dataset_format.md, "Predictions files")
        trajectories: indices of the input's trajectories rolled out (default: all)
        schedule: point-cloud schedule, every:K, first:M or never (a model without point clouds runs never)
        batch_size: trajectories rolled out at once
        device: where the model runs
        overwrite: replace an existing output file
    """
    from .checkpoints import sha256
    from .data.predictions import Predictions, write_predictions
    from .data.schema import SplitReader
    from .evaluation.predict import check_model_fits, rollout_trajectories
    from .evaluation.schedules import effective_schedule, parse_schedule
    from .pretrained import check_data, load_model

    if Path(output).exists() and not overwrite:
        raise FileExistsError(f"{output}: already exists (--overwrite replaces it)")
    plan = parse_schedule(schedule)
    with SplitReader(input) as split:
        chosen = list(range(len(split))) if trajectories is None else list(trajectories)
        outside = [i for i in chosen if not 0 <= i < len(split)]
        if outside or not chosen:
            raise ValueError(f"--trajectories {outside or chosen}: {input} holds trajectories 0..{len(split) - 1}")
        model = load_model(checkpoint, map_location=device)
        manifest = getattr(model, "manifest", None)  # set on shipped (pretrained) simulators
        check_model_fits(model, split.dim, split.scene, task=manifest["task"] if manifest else None)
        if manifest:
            check_data(manifest["name"], split.generator_config or None, split.dim, source=str(input))
        inputs = [split[i] for i in chosen]
        scene = split.scene
    plan = effective_schedule(plan, model.uses_points)
    positions = rollout_trajectories(model, inputs, plan, batch_size)
    path = write_predictions(output, Predictions(
        positions=positions, inputs=inputs, model_class=type(model).__name__, schedule=str(plan),
        checkpoint=checkpoint, checkpoint_sha256=manifest["sha256"] if manifest else sha256(checkpoint),
        input_file=str(Path(input).resolve()), input_indices=chosen, scene=scene), overwrite=overwrite)
    print(f"{path}: {len(inputs)} rollouts of {type(model).__name__} ({checkpoint}) under {plan}")
    return path


def sweep(*overrides: str, config: str = "plate", task: int | None = None, slurm: str | None = None,
          aggregate_only: bool = False, dry_run: bool = False) -> None:
    """Multi-seed sweep of model configs (fit + test per run, resumable), then baselines and summary.

    Args:
        overrides: sweep overrides as key=value, e.g. seeds=[0,1] parallel=2
        config: sweep preset in conf/sweeps/ or a checkout's experiments/*/sweeps/, or a YAML path
        task: run only this run of the grid (a SLURM array task; no summary)
        slurm: write a SLURM job-array script for the sweep to this file instead of running
        aggregate_only: only aggregate the finished runs (e.g. after a SLURM array)
        dry_run: print each run's fit command (its config files and settings; with --task, that run's) and run nothing
    """
    from .experiments.sweep import load_sweep, run_baselines, run_sweep, runs_of, slurm_script, summarize


    spec = load_sweep(config, list(overrides))
    if dry_run:
        runs = runs_of(spec)
        print_commands(runs if task is None else [runs[task]])
        return
    if slurm:
        Path(slurm).write_text(slurm_script(spec, config))
        print(f"wrote {slurm} (submit with sbatch)")
        return
    if not aggregate_only:
        run_sweep(spec, task)
    if task is None:
        run_baselines(spec)
        summarize(spec)


def pretrained_list() -> list[str]:
    """The shipped pretrained simulators, their training data, budget, steps and test metric."""
    from .pretrained import manifest, names, training_budget

    shipped = names()
    for name in shipped:
        m = manifest(name)
        family = m["source"]["family"]
        metric = m["test"]["metrics"].get(f"rollout_mse_{family}", {}).get("mean")
        budget = training_budget(m)["max_time_minutes"]
        budget = f"{budget:3.0f} min" if budget is not None else "   -   "
        print(f"{name:14s} {m['class']:6s} {m['bytes'] / 1024:5.0f} KB  data {m['data']['preset']:10s} budget {budget} "
              f"{m['source']['global_step']:6d} steps  test rollout_mse_{family} {metric:.3e} "
              f"({m['test']['trajectories']} trajectories)")
    return shipped


def pretrained_train(name: str, output: str | None = None) -> None:
    """Train (or resume) the CPU-preset run a shipped simulator is cut from (conf/pretrained.yaml).

    Args:
        name: the entry, e.g. plate/ggns
        output: folder of the sweep runs (default: the spec's)
    """
    from .experiments.pretrain import load_spec, train

    spec = load_spec()
    train(name, {**spec, "output": output or spec["output"]})


def pretrained_package(name: str, output: str | None = None) -> Path:
    """Cut a finished run's checkpoint into src/ggns/pretrained/, evaluate it and write its manifest.

    Args:
        name: the entry, e.g. plate/ggns
        output: folder of the sweep runs (default: the spec's)
    """
    from .experiments.pretrain import load_spec, package

    spec = load_spec()
    return package(name, {**spec, "output": output or spec["output"]})


def demo(task: Literal["plate", "tissue"] = "plate", output: str = "lightning_logs/demo", minutes: float | None = None,
         test_trajectories: int | None = None, data: str | None = None, train: bool = True) -> Path:
    """The README's main job (conf/demo/<task>.yaml): the pretrained GGNS, MGN and MGN(M) on test
    trajectories generated here, pictures, and GGNS trained from scratch for a few minutes.

    Args:
        task: plate (the default, about 5 minutes on 2 cores) or tissue
        output: the report, pictures and logs go to <output>/<task>/
        minutes: from-scratch training budget (default: the task's; 0 skips the training)
        test_trajectories: test trajectories evaluated (default: the task's)
        data: another data preset of the same scene (default: the task's)
        train: train GGNS from scratch after the evaluation
    """
    from .demo import run_demo

    return run_demo(task, output, minutes=minutes, test_trajectories=test_trajectories, data=data, train=train)


def paper(task: Literal["plate", "tissue", "cavity"] = "plate", summary: dict[str, str] | None = None,
          output: str | None = None, compact: bool = False) -> str:
    """Our sweep results in the paper's layout, the paper's figures (conf/paper/ggns_iclr2023.yaml) beside them.

    Args:
        task: the paper's task the sweeps ran
        summary: a sweep's summary.csv, as label=path (repeatable; rows labelled when several); label=a.csv,b.csv pools runs of one sweep on disjoint seeds
        output: also write the markdown to this file
        compact: the paper's four models and four columns only (the README's tables)
    """
    from .experiments.paper import paper_table
    from .reports import write_text

    text = paper_table(task, dict(summary or {}), compact=compact)
    print(text)
    if output:
        write_text(output, text + "\n")
    return text


def bench_profile(model: str = "ggns", dataset: str = "plate_small", latent: int = 128, blocks: int = 5,
                  batch_size: int = 32, rollout_trajectories: int = 1, schedule: str = "every:1",
                  device: Literal["cpu", "cuda"] = "cpu", steps: int = 10, warmup: int = 3, fit_steps: int = 0,
                  output_dir: str | None = None, compile: bool = False, static: bool = False) -> dict:
    """Where the time of a training step and a rollout step goes: phases, operators or kernels, host reads, matrix share.

    Args:
        model: model config of conf/plate/ (random weights: speed does not depend on them)
        dataset: data preset (train and test splits)
        latent: latent width (paper: 128)
        blocks: message-passing blocks (paper: 5)
        batch_size: training windows per batch (paper: 32)
        rollout_trajectories: trajectories rolled out at once
        schedule: point-cloud schedule of the rollout
        device: where the model runs
        steps: profiled steps of each kind
        warmup: steps before the timing
        fit_steps: also a Lightning fit of this many steps, against the bare loop (0: none)
        output_dir: write profile.json and profile.md here
        compile: compile the message-passing blocks (torch.compile, dynamic shapes)
        static: the whole training and rollout steps on static shapes, no host read (CUDA-graph replays on a GPU)
    """
    from .bench.step_profile import profile

    return profile(model, dataset, latent=latent, blocks=blocks, batch_size=batch_size,
                   rollout_trajectories=rollout_trajectories, schedule=schedule, device=device, steps=steps,
                   warmup=warmup, fit_steps=fit_steps, output=output_dir, compile=compile, static=static)


def bench_precision(checkpoint: dict[str, str] | None = None, dataset: str = "plate_small", trajectories: int = 9,
                    schedules: Sequence[str] = ("every:1", "every:5", "never"),
                    modes: Sequence[str] = ("float32", "bf16", "tf32"), device: Literal["cpu", "cuda"] = "cpu",
                    output_dir: str | None = None) -> list[dict]:
    """The shipped (or any) simulators' test metrics in float32, bf16 autocast and, on a GPU, TF32.

    Args:
        checkpoint: name=path or name=pretrained name (default: plate/ggns, plate/mgn and plate/mgn_m)
        dataset: data preset whose test trajectories are scored
        trajectories: test trajectories scored
        schedules: point-cloud schedules of the rollouts
        modes: float32 (always run, the reference), bf16, tf32 (GPU only)
        device: where the models run
        output_dir: write precision.csv and precision.md here
    """
    from .bench.precision import bench_precision as run

    checkpoints = dict(checkpoint or {name: name for name in ("plate/ggns", "plate/mgn", "plate/mgn_m")})
    return run(checkpoints, dataset, trajectories=trajectories, schedules=tuple(schedules), modes=tuple(modes),
               device=device, output_dir=output_dir)


def bench_ab(baseline: str, probe: Sequence[str] | None = None, rounds: int = 5, candidate: str | None = None,
             output_dir: str | None = None, threads: int | None = None,
             device: Literal["cpu", "cuda"] = "cpu", baseline_env: dict[str, str] | None = None,
             candidate_env: dict[str, str] | None = None, from_log: str | None = None) -> list[dict]:
    """This checkout against a baseline commit, in one run on this machine (probes alternate between them).

    Args:
        baseline: a commit of this repository (checked out into a temporary worktree) or a checkout's path
        probe: probes as "train MODEL LATENT BLOCKS BATCH", "rollout MODEL LATENT BLOCKS TRAJECTORIES SCHEDULE
            [static]", "fit MODEL LATENT BLOCKS BATCH", "ops train|rollout MODEL LATENT BLOCKS SIZE" (operators
            per step) or "import MODULE" (ms to import it in a fresh process; default: the demo's and the
            paper-size models' times)
        rounds: rounds of every probe on both trees (medians over rounds are reported)
        candidate: the tree measured against the baseline (default: this checkout)
        output_dir: write ab_raw.csv and ab_summary.md here
        threads: OMP_NUM_THREADS of the probes (default: torch's own choice)
        device: where the probes run
        baseline_env: environment variables of the baseline's probes, as NAME=VALUE
        candidate_env: environment variables of the candidate's probes, as NAME=VALUE (the same tree on both
            sides with another setting on one measures that setting)
        from_log: summarize the printed log of an earlier run instead of running (its complete rounds:
            what an interrupted run leaves); baseline, candidate and the environments label the summary
    """
    from .bench.ab import DEFAULT_PROBES, ROOT, raw_from_log, report
    from .bench.ab import bench_ab as run

    if from_log is not None:
        raw = raw_from_log(Path(from_log).read_text(encoding="utf-8"))
        return report(raw, baseline, candidate or str(ROOT), output_dir, device, dict(baseline_env or {}),
                      dict(candidate_env or {}), note=f"Summarized from the run's log ({from_log}), complete rounds only.")

    return run(baseline, tuple(probe) if probe else DEFAULT_PROBES, rounds=rounds,
               candidate=candidate or str(ROOT), output=output_dir, threads=threads, device=device,
               baseline_env=dict(baseline_env or {}), candidate_env=dict(candidate_env or {}))


COMMANDS = {
    "generate": generate,
    "import-reference": import_reference,
    "geometry": geometry,
    "bench": {"sim": bench_sim, "solvers": bench_solvers, "models": bench_models, "tradeoff": bench_tradeoff,
              "stability": bench_stability,
              "learning": bench_learning, "ab": bench_ab,
              "profile": bench_profile, "precision": bench_precision},
    "export": export,
    "rollout": rollout,
    "diagnose": diagnose,
    "sweep": sweep,
    "pretrained": {"list": pretrained_list, "train": pretrained_train, "package": pretrained_package},
    "demo": demo,
    "paper": paper,
}
