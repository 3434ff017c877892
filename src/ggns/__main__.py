"""Command line: `python -m ggns <command>` (or the `ggns` console script).

    fit, validate, test, predict
              the Lightning CLI for the simulators (`python -m ggns fit --help`; see ggns.cli)
    generate  simulate and observe dataset splits into HDF5 files
    bench     benchmarks (`bench sim`: simulator and dataset generation speed)
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


def _bench(args: argparse.Namespace) -> None:
    from .bench import bench_sim

    bench_sim(args.config, trajectories=args.trajectories, generate_splits=args.generate)


def _demo(args: argparse.Namespace) -> None:
    from .demo import run_demo

    run_demo(args.output)


def main(argv: list[str] | None = None) -> None:
    given = sys.argv[1:] if argv is None else list(argv)
    if given and given[0] in ("fit", "validate", "test", "predict"):
        from .cli import build_cli

        build_cli(argv)  # None: LightningCLI reads sys.argv itself
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

    bench = sub.add_parser("bench", help="benchmarks")
    bench.add_argument("what", choices=["sim"])
    bench.add_argument("--config", default="plate")
    bench.add_argument("--trajectories", type=int, default=9, help="trajectories timed one by one")
    bench.add_argument("--generate", action="store_true", help="also time generating all splits of the config with its workers")
    bench.set_defaults(run=_bench)

    demo = sub.add_parser("demo", help="the README's main job on a small default")
    demo.add_argument("--output", default="lightning_logs/demo")
    demo.set_defaults(run=_demo)

    args = parser.parse_args(argv)
    try:
        args.run(args)
    except (FileNotFoundError, FileExistsError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
