"""Command line: `python -m ggns <command>` (or the `ggns` console script).

    fit, validate, test, predict
              the Lightning CLI for the simulators (`python -m ggns fit --help`; see ggns.cli)
    generate  simulate and observe dataset splits into HDF5 files
    geometry  measure a generated dataset's scale against the paper's radii, noise and point count
    sweep     multi-seed sweeps of model configs
    bench     benchmarks (`bench sim`: simulator and dataset generation speed;
              `bench models`: training and rollout throughput of the learned simulators;
              `bench tradeoff`: time per rollout step against rollout error, CSV + Pareto plot;
              `bench learning`: learning curves of model variants per CPU-second, table + plots)
    demo      the README's main job on a small embedded default
"""
from __future__ import annotations

import argparse
import sys


def _generate(args: argparse.Namespace) -> None:
    from .config import load_config
    from .data.generate import generate

    overrides = list(args.overrides)
    for key in ("seed", "output", "workers"):
        if getattr(args, key) is not None:
            overrides.append(f"{key}={getattr(args, key)}")
    if args.count is not None:
        if not args.split:
            raise SystemExit("--count needs --split (which split gets that many trajectories)")
        overrides += [f"splits.{s}={args.count}" for s in args.split]
    config = load_config(args.config, overrides)
    for path in generate(config, args.split, overwrite=args.overwrite):
        print(path)


def _geometry(args: argparse.Namespace) -> None:
    from .data.module import SimulationDataModule
    from .graphs.scale import geometry_report

    data = SimulationDataModule(args.dataset, generate_missing=False)
    trajectories = data.trajectories(args.split)[: args.trajectories]
    table, ok = geometry_report(trajectories, f"{args.dataset} {data.path(args.split)}", args.targets, args.stride)
    print(table)
    print("all targets met" if ok else "some targets are not met (OUT OF RANGE above)")


def _bench(args: argparse.Namespace) -> None:
    from .bench.models import bench_models
    from .bench.sim import bench_sim

    if args.overrides and args.what != "learning":
        raise ValueError(f"--set {args.overrides} is for `bench learning` only")
    if args.what == "learning":
        from .experiments.learning import load_learning, run_learning, write_report

        overrides = list(args.overrides)
        for key in ("minutes", "parallel", "output_dir"):
            if getattr(args, key) is not None:
                overrides.append(f"{'output' if key == 'output_dir' else key}={getattr(args, key)}")
        spec = load_learning(args.config or "plate_ggns", overrides)
        if args.report_only:
            write_report(spec)
        else:
            run_learning(spec, args.variant)
        return
    if args.what == "tradeoff":
        from .bench.tradeoff import tradeoff

        checkpoints = {}
        for item in args.checkpoint or []:
            name, sep, path = item.partition("=")
            if not sep or not name or not path:
                raise ValueError(f"--checkpoint takes name=path, got {item!r}")
            checkpoints[name] = path
        tradeoff(args.dataset, checkpoints, trajectories=args.trajectories or 4,
                 coarsen=tuple(int(c) for c in args.coarsen.split(",") if c.strip()),
                 output_dir=args.output_dir or "lightning_logs/tradeoff",
                 schedules=tuple(s.strip() for s in args.schedules.split(",") if s.strip()),
                 batch=args.rollout_trajectories, repeats=args.repeats,
                 grid_nodes=[int(n) for n in args.grid_nodes.split(",") if n.strip()] if args.grid_nodes else None)
        return
    if args.what == "models":
        models = tuple(m.strip() for m in args.models.split(",") if m.strip())
        bench_models(args.dataset, models, train_batches=args.train_batches, rollout_steps=args.rollout_steps,
                     device=args.device, output=args.output, batch_size=args.batch_size,
                     rollout_trajectories=args.rollout_trajectories, repeats=args.repeats)
        return
    bench_sim(args.config or "plate", trajectories=args.trajectories or 9, generate_splits=args.generate)


def _demo(args: argparse.Namespace) -> None:
    from .demo import run_demo

    run_demo(args.output, preset=args.preset, minutes=args.minutes, models=tuple(args.models.split(",")),
             test_trajectories=args.test_trajectories)


def _sweep(args: argparse.Namespace) -> None:
    from .experiments.sweep import load_sweep, run_baselines, run_sweep, slurm_script, summarize

    sweep = load_sweep(args.config, args.overrides)
    if args.slurm:
        from pathlib import Path

        Path(args.slurm).write_text(slurm_script(sweep, args.config))
        print(f"wrote {args.slurm} (submit with sbatch)")
        return
    if not args.aggregate_only:
        run_sweep(sweep, args.task)
    if args.task is None:
        run_baselines(sweep)
        summarize(sweep)


def main(argv: list[str] | None = None) -> None:
    given = sys.argv[1:] if argv is None else list(argv)
    if given and given[0] in ("fit", "validate", "test", "predict"):
        from pytorch_lightning.utilities.exceptions import SIGTERMException

        from .cli import CheckpointMismatchError, build_cli

        try:
            build_cli(argv)  # None: LightningCLI reads sys.argv itself
        except CheckpointMismatchError as error:
            print(f"error: {error}", file=sys.stderr)
            raise SystemExit(2) from None
        except SIGTERMException:
            # Lightning stops a SIGTERM'd run with a bare SystemExit, i.e. exit status 0; a sweep or a
            # learning file would then test a partial fit or mark it finished.
            print(f"error: {given[0]} stopped by SIGTERM before it finished (rerun it to resume from "
                  "last.ckpt)", file=sys.stderr)
            raise SystemExit(143) from None
        return
    parser = argparse.ArgumentParser(prog="ggns", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    gen = sub.add_parser("generate", help="generate dataset splits (HDF5)")
    gen.add_argument("--config", default="plate", help="preset name in conf/data/ or a YAML path (default: plate)")
    gen.add_argument("--split", action="append", choices=["train", "val", "test"], help="split(s) to generate (default: all in the config)")
    gen.add_argument("--count", type=int, help="trajectories per chosen split (default: the config's split sizes)")
    gen.add_argument("--seed", type=int)
    gen.add_argument("--output", help="output directory (one <split>.h5 per split)")
    gen.add_argument("--workers", type=int, help="parallel worker processes")
    gen.add_argument("--overwrite", action="store_true", help="replace existing split files")
    gen.add_argument("overrides", nargs="*", help="config overrides as key=value, e.g. scene.num_steps=20")
    gen.set_defaults(run=_generate)

    geo = sub.add_parser("geometry", help="measure a dataset's scale (points, neighbours, edges, motion) against targets")
    geo.add_argument("--dataset", default="plate_small", help="data preset whose generated split is measured")
    geo.add_argument("--split", default="train", choices=["train", "val", "test"])
    geo.add_argument("--trajectories", type=int, default=27, help="first n trajectories of the split")
    geo.add_argument("--stride", type=int, default=5, help="measure every n-th step")
    geo.add_argument("--targets", default="plate", help="targets file: conf/geometry/<name>.yaml or a YAML path")
    geo.set_defaults(run=_geometry)

    bench = sub.add_parser("bench", help="benchmarks")
    bench.add_argument("what", choices=["sim", "models", "tradeoff", "learning"],
                       help="sim: simulator and generation; models: learned simulators; tradeoff: speed vs error; "
                       "learning: learning curves of model variants within a wall-clock budget")
    bench.add_argument("--set", action="append", dest="overrides", default=[], metavar="KEY=VALUE",
                       help="learning: a learning-file override (repeatable), e.g. --set val_every=50")
    bench.add_argument("--config", help="sim: data preset (default plate); learning: learning file in conf/learning/ "
                       "or a YAML path (default plate_ggns)")
    bench.add_argument("--trajectories", type=int, help="sim: trajectories timed one by one (default 9); "
                       "tradeoff: test trajectories scored (default 4)")
    bench.add_argument("--generate", action="store_true", help="sim: also time generating all splits of the config with its workers")
    bench.add_argument("--dataset", default="plate_small", help="models: data preset (train and test splits; generated if missing)")
    bench.add_argument("--models", default="ggns,ggns_lstm,mgn,mgn_m", help="models: comma-separated (default: all four)")
    bench.add_argument("--train-batches", type=int, default=10, help="models: timed training iterations per model")
    bench.add_argument("--rollout-steps", type=int, help="models: steps per timed rollout (default: whole test trajectories)")
    bench.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="models: device")
    bench.add_argument("--output", help="models: write the measurements to this CSV")
    bench.add_argument("--batch-size", type=int, default=32, help="models: training windows per batch (paper: 32)")
    bench.add_argument("--rollout-trajectories", type=int, default=32, help="models, tradeoff: trajectories in the batched rollout")
    bench.add_argument("--repeats", type=int, default=3, help="models, tradeoff: timed rollouts per measurement (median)")
    bench.add_argument("--checkpoint", action="append", metavar="NAME=PATH", help="tradeoff: a model checkpoint (repeatable)")
    bench.add_argument("--coarsen", default="1,2,5", help="tradeoff: simulator time-step coarsening factors")
    bench.add_argument("--schedules", default="every:1,never", help="tradeoff: point-cloud schedules of the model rollouts")
    bench.add_argument("--grid-nodes", help="tradeoff: mesh nodes per side, comma-separated resolutions for the simulator "
                       "and the models (default: the preset's)")
    bench.add_argument("--output-dir", help="tradeoff: where tradeoff.csv/.png go (default lightning_logs/tradeoff); "
                       "learning: where the variants and the report go (default: the file's output)")
    bench.add_argument("--minutes", type=float, help="learning: wall-clock budget per variant (default: the file's)")
    bench.add_argument("--parallel", type=int, help="learning: variants at once (default: the file's)")
    bench.add_argument("--variant", action="append", help="learning: run only this variant (repeatable)")
    bench.add_argument("--report-only", action="store_true", help="learning: only write the report from the logs")
    bench.set_defaults(run=_bench)

    sweep = sub.add_parser("sweep", help="multi-seed sweep of model configs (fit + test per run, resumable)")
    sweep.add_argument("--config", default="plate", help="sweep preset in conf/sweeps/ or a YAML path")
    sweep.add_argument("--task", type=int, help="run only this run of the grid (a SLURM array task)")
    sweep.add_argument("--slurm", help="write a SLURM job-array script for the sweep to this file instead of running")
    sweep.add_argument("--aggregate-only", action="store_true", help="only aggregate the finished runs (e.g. after a SLURM array)")
    sweep.add_argument("overrides", nargs="*", help="sweep overrides as key=value, e.g. seeds=[0,1] parallel=2")
    sweep.set_defaults(run=_sweep)

    demo = sub.add_parser("demo", help="the README's main job on a small default")
    demo.add_argument("--output", default="lightning_logs/demo")
    demo.add_argument("--preset", default="plate_small", help="data preset (conf/data/)")
    demo.add_argument("--minutes", type=float, default=4.0, help="wall-clock training budget per model")
    demo.add_argument("--test-trajectories", type=int, default=9, help="test trajectories evaluated per model")
    demo.add_argument("--models", default="ggns,mgn", help="comma-separated configs from conf/plate/")
    demo.set_defaults(run=_demo)

    args = parser.parse_args(argv)
    try:
        args.run(args)
    except (FileNotFoundError, FileExistsError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
