"""The command line, in one package: `python -m ggns <command>` (or the `ggns` console script) runs `main`.

    lightning.py  fit, validate, test, predict: the Lightning CLI for the simulators (`SimulatorCLI`)
    parser.py     argparse parsers built from typed, documented functions
    commands.py   generate, import-reference, geometry, export, rollout, diagnose, sweep, pretrained, demo, paper
    bench.py      the `bench` commands
    demo.py       the demo (`demo`)

`build_cli`, `config_bases`, `shipped_configs` and the CLI's other names are importable from here; they
are loaded when first asked for, so that `python -m ggns sweep ...` and `--help` start without Lightning.
"""
from __future__ import annotations

import os
import sys

from .commands import COMMANDS
from .parser import build_parser, call

USAGE = """Command line: `python -m ggns <command>` (or the `ggns` console script).

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
    demo      the README's demo on a small embedded default
    paper     sweep summaries in the paper's layout, the paper's figures beside them

A bad input (missing file or preset, out-of-range value, unreadable dataset or checkpoint) or a
reported numerical failure ends with one line on stderr, `error: ...`, and exit status 2;
`python -m ggns --traceback <command> ...` (or GGNS_TRACEBACK=1) shows the traceback instead.
"""

_LIGHTNING_NAMES = ("build_cli", "config_bases", "shipped_configs", "SimulatorCLI", "CheckpointMismatchError",
                    "refuse_renamed_args", "command_line_model_args")


def __getattr__(name: str):
    if name in _LIGHTNING_NAMES:
        from . import lightning

        return getattr(lightning, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


LIGHTNING_COMMANDS = ("fit", "validate", "test", "predict")  # LightningCLI (`lightning.py`); the rest: `commands.py`


# Errors that name a problem with the user's input or a reported numerical failure: one line on
# stderr and exit status 2, no traceback (GGNS_TRACEBACK=1 or a leading --traceback shows it).
# ValueError covers DatasetError, CheckpointError, CheckpointMismatchError, UnknownKeyError and the
# configs' range checks; SimulationError and RolloutError are the simulator's and the rollout's
# numerical reports (they name the step and where); RunFailed, a sweep's or `bench learning`'s
# subprocess that failed, carries that subprocess's own error line.
def _user_errors() -> tuple[type[BaseException], ...]:
    from ..errors import RolloutError, SimulationError

    errors = (FileNotFoundError, FileExistsError, IsADirectoryError, PermissionError, ValueError, SimulationError,
              RolloutError)
    if "ggns.sweeps.sweep" in sys.modules:  # a sweep's fit or test that failed, with its own error line
        from ..sweeps.sweep import RunFailed

        errors += (RunFailed,)
    if "pytorch_lightning" in sys.modules:  # Lightning's own refusal of a configuration
        from pytorch_lightning.utilities.exceptions import MisconfigurationException

        errors += (MisconfigurationException,)
    return errors


def main(argv: list[str] | None = None) -> None:
    given = sys.argv[1:] if argv is None else list(argv)
    traceback = os.environ.get("GGNS_TRACEBACK", "") not in ("", "0")
    if given[:1] == ["--traceback"]:
        traceback, given = True, given[1:]
        argv = given
    try:
        _run(given, argv)
    except _user_errors() as error:
        if traceback:
            raise
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None


def _run(given: list[str], argv: list[str] | None) -> None:
    if given and given[0] in LIGHTNING_COMMANDS:
        # imported here: Lightning takes seconds to import, and the other commands do not need it
        from pytorch_lightning.utilities.exceptions import SIGTERMException

        from .lightning import build_cli

        try:
            build_cli(argv)  # None: LightningCLI reads sys.argv itself
        except SIGTERMException:
            # Lightning stops a SIGTERM'd run with a bare SystemExit, i.e. exit status 0; a sweep or a
            # learning file would then test a partial fit or mark it finished.
            print(f"error: {given[0]} stopped by SIGTERM before it finished (rerun it to resume from "
                  "last.ckpt)", file=sys.stderr)
            raise SystemExit(143) from None
        return
    parser = build_parser(COMMANDS, prog="ggns", description=USAGE)
    call(parser.parse_args(argv))

