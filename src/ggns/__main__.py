"""Command line: `python -m ggns <command>` (or the `ggns` console script).

    fit, validate, test, predict
              the Lightning CLI for the simulators (`python -m ggns fit --help`; see ggns.cli)
    generate  simulate and observe dataset splits into HDF5 files
    import-reference
              one split of the paper authors' datasets (their pickles) as an HDF5 split file
    geometry  measure a generated dataset's scale against the paper's radii, noise and point count
    rollout   roll out a checkpoint (pretrained name or .ckpt) on a split file into a predictions file
    sweep     multi-seed sweeps of model configs
    bench     benchmarks (`bench sim`: simulator and dataset generation speed;
              `bench solvers`: the simulator's dense and sparse linear solvers on a 3D block;
              `bench models`: training and rollout throughput of the learned simulators;
              `bench tradeoff`: time per rollout step against rollout error, CSV + Pareto plot;
              `bench learning`: learning curves of model variants per CPU-second, table + plots)
    demo      the README's main job on a small embedded default
"""
from __future__ import annotations

import sys

from .command_line import build_parser, call
from .commands import COMMANDS

LIGHTNING_COMMANDS = ("fit", "validate", "test", "predict")  # LightningCLI (ggns.cli); the rest: ggns.commands


def main(argv: list[str] | None = None) -> None:
    given = sys.argv[1:] if argv is None else list(argv)
    if given and given[0] in LIGHTNING_COMMANDS:
        # imported here: Lightning takes seconds to import, and the other commands do not need it
        from pytorch_lightning.utilities.exceptions import SIGTERMException

        from .checkpoints import CheckpointError
        from .cli import CheckpointMismatchError, build_cli

        try:
            build_cli(argv)  # None: LightningCLI reads sys.argv itself
        except (CheckpointMismatchError, CheckpointError) as error:
            print(f"error: {error}", file=sys.stderr)
            raise SystemExit(2) from None
        except SIGTERMException:
            # Lightning stops a SIGTERM'd run with a bare SystemExit, i.e. exit status 0; a sweep or a
            # learning file would then test a partial fit or mark it finished.
            print(f"error: {given[0]} stopped by SIGTERM before it finished (rerun it to resume from "
                  "last.ckpt)", file=sys.stderr)
            raise SystemExit(143) from None
        return
    parser = build_parser(COMMANDS, prog="ggns", description=__doc__)
    args = parser.parse_args(argv)
    try:
        call(args)
    except (FileNotFoundError, FileExistsError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
