"""The `bench` commands of `python -m ggns` (`bench sim`, `bench models`, `bench tradeoff`, `bench learning`,
...): one typed, documented function each, as the other commands (`ggns.cli.commands`); each imports what it
runs when it runs, so building the parser loads neither torch nor Lightning."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal


def bench_sim(*overrides: str, config: str = "plate", trajectories: int = 9, generate: bool = False) -> dict:
    """Time the ground-truth simulator and the depth sensor (and dataset generation).

    Args:
        overrides: preset overrides as key=value, e.g. solver.linear_solver=sparse (a key the preset lacks is an error)
        config: data preset
        trajectories: trajectories timed one by one
        generate: also time generating all splits of the config with its workers
    """
    from ..bench import sim as sim_bench

    return sim_bench.bench_sim(config, trajectories=trajectories, generate_splits=generate, overrides=list(overrides))


def bench_solvers(nodes: Sequence[int] = (10, 6, 6), frames: int = 12,
                  solvers: Sequence[Literal["dense", "sparse", "banded"]] = ("dense", "sparse")) -> dict:
    """The simulator's linear solvers (dense, sparse, banded) timed on a tetrahedral block with a pulled node.

    Args:
        nodes: nodes per axis of the block (1 x 0.6 x 0.6 m)
        frames: frames simulated per solver (medians reported)
        solvers: the linear solvers timed
    """
    from ..bench import sim as sim_bench

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
    from ..bench import models as model_bench


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
    from ..bench.timing import resolve_device
    from ..bench.tradeoff import tradeoff


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
    from ..bench.stability import stability

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
    from ..sweeps.learning import load_learning, run_learning, variant_runs, write_report


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
    from ..bench.step_profile import profile

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
    from ..bench.precision import bench_precision as run

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
    from ..bench.ab import DEFAULT_PROBES, ROOT, raw_from_log, report
    from ..bench.ab import bench_ab as run

    if from_log is not None:
        raw = raw_from_log(Path(from_log).read_text(encoding="utf-8"))
        return report(raw, baseline, candidate or str(ROOT), output_dir, device, dict(baseline_env or {}),
                      dict(candidate_env or {}), note=f"Summarized from the run's log ({from_log}), complete rounds only.")

    return run(baseline, tuple(probe) if probe else DEFAULT_PROBES, rounds=rounds,
               candidate=candidate or str(ROOT), output=output_dir, threads=threads, device=device,
               baseline_env=dict(baseline_env or {}), candidate_env=dict(candidate_env or {}))


def bench_online(simulator: Sequence[str] = ("plate/ggns", "tissue/ggns"), dataset: str | None = None,
                 data_dir: dict[str, str] | None = None, ticks: int | None = None, warmup: int = 5,
                 threads: Sequence[int] = (1, 2), observation: Sequence[Literal["none", "points", "depth"]] = (
                     "none", "points", "depth"), output_dir: str = "lightning_logs/online_bench") -> list[dict]:
    """The online simulator's time per tick (`ggns.online.OnlineSimulator.step`) on the first test trajectory.

    Each simulator is stepped tick by tick through the first test trajectory of its data preset (plate:
    plate_small, tissue: tissue_cpu), fed the collider's poses and nothing, the stored point cloud or the
    depth images of the scene's virtual cameras; median and quartiles per tick after a warm-up, with each
    torch thread count. Writes online_bench.csv and online_bench.md, and says whether the tissue's ticks
    without an observation on 2 threads reach 100 per second.

    Args:
        simulator: shipped simulators (e.g. tissue/mgn_m) or checkpoint paths (these need --dataset)
        dataset: the data preset of every simulator (default: each shipped simulator's: plate_small, tissue_cpu)
        data_dir: the folder of a preset's test.h5, as PRESET=DIR (default: the preset's output)
        ticks: timed ticks (default: every tick of the trajectory)
        warmup: ticks stepped before each timed run
        threads: torch thread counts
        observation: what each tick is fed: none, points (the stored cloud), depth (the virtual cameras' images)
        output_dir: where online_bench.csv and online_bench.md go
    """
    from ..bench.online import bench_online as run

    return run({name: name for name in simulator}, dataset=dataset, data_dirs=dict(data_dir or {}), ticks=ticks,
               warmup=warmup, threads=tuple(threads), observations=tuple(observation), output_dir=output_dir)


def bench_online_study(task: Literal["plate", "tissue"] = "tissue", trajectories: int = 3,
                       latency: Sequence[int] = (0, 1, 2, 5),
                       sensor: Sequence[Literal["none", "axial", "axial_3x", "realistic", "realistic_calibration_mm",
                                                "realistic_calibration_cm", "realistic_2_cameras",
                                                "realistic_1_camera"]] = ("none", "axial", "axial_3x"),
                       every: Sequence[int] = (1,), baseline: Sequence[str] = ("mgn", "mgn_m"),
                       checkpoint: dict[str, str] | None = None,
                       data_dir: str | None = None, output_dir: str = "lightning_logs/online_study",
                       seed: int = 0,
                       registered: Sequence[Literal["ggns", "ggns_blind", "mgn", "mgn_m", "static"]] = (),
                       registration: dict[str, float] | None = None, split: Literal["test", "val"] = "test",
                       grounded: bool = True) -> list[dict]:
    """The shipped GGNS tracking test trajectories online, fed the virtual cameras' depth frames late and flawed.

    The task's shipped GGNS is stepped through its first test trajectories (plate: plate_small, tissue:
    tissue_cpu) with the recorded collider poses and the masked depth images of every r-th tick, each
    arriving `latency` ticks late, seen by a flawless or a flawed sensor (`ggns.bench.online_study.SENSORS`);
    the blind shipped baselines beside it. Writes online_study_raw.csv (per trajectory) and online_study.md
    (means and ratios to the blind models) after every trajectory.

    Args:
        task: the scene whose shipped simulators are run
        trajectories: the first K test trajectories
        latency: ticks between a frame's tick and its arrival
        sensor: none, axial, axial_3x, realistic, realistic_calibration_mm, realistic_calibration_cm,
            realistic_2_cameras, realistic_1_camera (ggns.bench.online_study.SENSORS)
        every: frames of every r-th tick
        baseline: blind shipped models of the task beside GGNS (e.g. mgn, mgn_m)
        checkpoint: more GGNS fed the same frames, name=path (e.g. one trained on the flaws it is fed)
        data_dir: the folder of the preset's test.h5 (default: the preset's output)
        output_dir: where online_study_raw.csv and online_study.md go
        seed: of the sensor's random flaws
        registered: models also run blind with a registration to each frame (ggns: GGNS fed the frames and
            registered; ggns_blind: GGNS blind; mgn, mgn_m: the baselines; static: the registration alone)
        registration: Registration fields replacing the task's settings (conf/online/registration.yaml),
            e.g. smoothness=0.3
        split: the trajectories tracked (val: to choose the registration's settings)
        grounded: run the GGNS fed the frames (false: only the blind and the registered runs)
    """
    from ..bench.online_study import online_study

    return online_study(task, trajectories, latencies=tuple(latency), sensors=tuple(sensor), every=tuple(every),
                        baselines=tuple(baseline), data_dir=data_dir, output_dir=output_dir, seed=seed,
                        checkpoints=dict(checkpoint or {}), registered=tuple(registered),
                        registration=dict(registration or {}), split=split, grounded=grounded)


BENCH_COMMANDS = {"sim": bench_sim, "solvers": bench_solvers, "models": bench_models, "tradeoff": bench_tradeoff,
                  "stability": bench_stability, "learning": bench_learning, "ab": bench_ab, "profile": bench_profile,
                  "precision": bench_precision, "online": bench_online,
                  "online-study": bench_online_study}
