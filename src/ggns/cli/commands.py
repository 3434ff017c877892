"""The commands of `python -m ggns` besides the Lightning CLI's fit/validate/test/predict (`ggns.cli.lightning`).

One typed, documented function per command; `COMMANDS` maps the command line's words to them
and `ggns.cli.parser` builds the parser from their signatures and docstrings (an option per
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

from .bench import BENCH_COMMANDS, print_commands

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
    from ..config import load_config

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
    from ..data.generate import generate as generate_splits, merge_shards as merge_split_shards, parse_shard

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
    from ..config import load_config
    from ..data.reference import import_reference as convert, split_from_name

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
    from ..data.module import SimulationDataModule
    from ..graphs.scale import geometry_report


    data = SimulationDataModule(dataset, generate_missing=False)
    table, ok = geometry_report(data.trajectories(split)[:trajectories], f"{dataset} {data.path(split)}", targets,
                                stride)
    print(table)
    print("all targets met" if ok else "some targets are not met (OUT OF RANGE above)")
    return ok


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
    from ..batch import TrajectoryBatch
    from ..data.module import SimulationDataModule
    from ..evaluation.pictures import rollout_series
    from ..evaluation.predict import check_model_fits
    from ..evaluation.schedules import parse_schedule
    from ..pretrained import load_model
    from ..paraview import write_rollout

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
    from ..batch import TrajectoryBatch
    from ..data.module import SimulationDataModule
    from ..evaluation.evaluate import split_trajectories
    from ..evaluation.observability import PARTS, SEEN_AT_LEAST, VISIBILITY, error_shares
    from ..evaluation.predict import check_model_fits
    from ..evaluation.schedules import effective_schedule, parse_schedule
    from ..pretrained import load_model
    from ..reports import markdown_table, write_text

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
        from ..evaluation.evaluate import m_plus_10_profile, pooled_over
        from ..evaluation.metrics import m_plus_10_starts

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
    from ..checkpoints import sha256
    from ..data.predictions import Predictions, write_predictions
    from ..data.schema import SplitReader
    from ..evaluation.predict import check_model_fits, rollout_trajectories
    from ..evaluation.schedules import effective_schedule, parse_schedule
    from ..pretrained import check_data, load_model

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
    from ..sweeps.summary import run_baselines, summarize
    from ..sweeps.sweep import load_sweep, run_sweep, runs_of, slurm_script


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
    from ..pretrained import budget_text, manifest, names

    shipped = names()
    for name in shipped:
        m = manifest(name)
        family = m["source"]["family"]
        metric = m["test"]["metrics"].get(f"rollout_mse_{family}", {}).get("mean")
        print(f"{name:14s} {m['class']:6s} {m['bytes'] / 1024:5.0f} KB  data {m['data']['preset']:10s} "
              f"trained {budget_text(m):>28s}  file from step {m['source']['global_step']:<6d} "
              f"test rollout_mse_{family} {metric:.3e} ({m['test']['trajectories']} trajectories)")
    return shipped


def pretrained_train(name: str, output: str | None = None) -> None:
    """Train (or resume) the CPU-preset run a shipped simulator is cut from (conf/pretrained.yaml).

    Args:
        name: the entry, e.g. plate/ggns
        output: folder of the sweep runs (default: the spec's)
    """
    from ..sweeps.pretrain import load_spec, train

    spec = load_spec()
    train(name, {**spec, "output": output or spec["output"]})


def pretrained_package(name: str, output: str | None = None) -> Path:
    """Cut a finished run's checkpoint into src/ggns/pretrained/, evaluate it and write its manifest.

    Args:
        name: the entry, e.g. plate/ggns
        output: folder of the sweep runs (default: the spec's)
    """
    from ..sweeps.pretrain import load_spec, package

    spec = load_spec()
    return package(name, {**spec, "output": output or spec["output"]})


def demo(task: Literal["plate", "tissue"] = "plate", output: str = "lightning_logs/demo", minutes: float | None = None,
         test_trajectories: int | None = None, data: str | None = None, train: bool = True, online: bool = False,
         trajectory: int = 0, every: int = 2, latency: int = 1, noise: float = 1.0) -> Path:
    """The README's demo (conf/demo/<task>.yaml): the pretrained GGNS, MGN and MGN(M) on test
    trajectories generated here, pictures, and GGNS trained from scratch for a few minutes; with --online,
    the shipped GGNS stepped tick by tick on one test trajectory, fed late, noisy depth frames, beside the
    blind models (docs/online.md).

    Args:
        task: plate (the default, about 5 minutes on 2 cores) or tissue
        output: the report, pictures and logs go to <output>/<task>/
        minutes: from-scratch training budget (default: the task's; 0 skips the training)
        test_trajectories: test trajectories evaluated (default: the task's)
        data: another data preset of the same scene (default: the task's)
        train: train GGNS from scratch after the evaluation
        online: instead, the online loop (online.md, online.png, online.json in <output>/<task>/)
        trajectory: the online loop's test trajectory
        every: the online loop's frames: of every n-th tick
        latency: the online loop's frames arrive this many ticks after the tick they show
        noise: the online loop's axial depth noise, times the Kinect's (0: none)
    """
    from .demo import load_demo, run_demo, run_online

    if online:
        spec = load_demo(task)
        if data is not None:
            spec["data"] = data
        return run_online(task, output, spec, trajectory=trajectory, every=every, latency=latency, noise=noise)
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
    from ..sweeps.paper import paper_table
    from ..reports import write_text

    text = paper_table(task, dict(summary or {}), compact=compact)
    print(text)
    if output:
        write_text(output, text + "\n")
    return text


COMMANDS = {
    "generate": generate,
    "import-reference": import_reference,
    "geometry": geometry,
    "bench": BENCH_COMMANDS,
    "export": export,
    "rollout": rollout,
    "diagnose": diagnose,
    "sweep": sweep,
    "pretrained": {"list": pretrained_list, "train": pretrained_train, "package": pretrained_package},
    "demo": demo,
    "paper": paper,
}
