"""Restrict an unpacked torch-cluster source tree to some of its C++ extensions (used by setup.sh).

torch-cluster 1.6.3 is nine extensions (version, grid, graclus, fps, rw, sampler, nearest, knn,
radius) of one or two C++ files each; every file takes about 40 s to compile, most of it torch's
headers. ggns calls `radius`, `radius_graph` and `knn` only, so by default the set-up builds the
extensions `version`, `radius` and `knn` (5 files instead of 18). This script edits the source
tree in place: setup.py compiles only those, the package's `__init__` loads only those (it
refuses to import when any of the nine is missing), and the version gets a local label naming
them (`1.6.3+ops.knn.radius.version`), so pip and `pip list` say what was built. Calling one of
the left-out operators (e.g. `torch_cluster.fps`) then fails with torch's "No such operator
torch_cluster::fps". Exits non-zero, changing nothing, if the sources do not look as expected.

With `--units N` (CPU builds only: setup.sh passes the number of cores), the chosen extensions'
C++ files are compiled as N translation units instead of one or two per extension, so that torch's
headers are parsed N times, not 5: each unit is one extension that registers the operators of
several (`_knn_cpu` holds knn and version, `_radius_cpu` radius, for N = 2), and `__init__` loads
those. The operators and their code are torch-cluster's own; only their static registrar is renamed
per operator, so that two can share a file. Without it each extension stays as torch-cluster builds
it (the CUDA build of scripts/gpu_check.sh).

Usage: python torch_cluster_subset.py SOURCE_DIR OP [OP ...] [--units N]
"""
from __future__ import annotations

import sys
from pathlib import Path

KNOWN = ("version", "grid", "graclus", "fps", "rw", "sampler", "nearest", "knn", "radius")
SETUP_LIST = "main_files = [path for path in main_files if 'hip' not in path]\n"
INIT_LIST = """for library in [
        '_version', '_grid', '_graclus', '_fps', '_rw', '_sampler', '_nearest',
        '_knn', '_radius'
]:"""


REGISTRAR = "static auto registry ="


def main(source: str, ops: list[str], units: int | None = None) -> None:
    unknown = sorted(set(ops) - set(KNOWN))
    if unknown or "version" not in ops:
        raise SystemExit(f"torch-cluster extensions must come from {KNOWN} and include 'version' (the package "
                         f"calls it at import); got unknown {unknown}")
    root = Path(source)
    setup, init = root / "setup.py", root / "torch_cluster" / "__init__.py"
    setup_text, init_text = setup.read_text(), init.read_text()
    version = "__version__ = '1.6.3'"
    if SETUP_LIST not in setup_text or version not in setup_text or INIT_LIST not in init_text:
        raise SystemExit(f"{root}: not the torch-cluster 1.6.3 sources this script knows; build the full package")
    label = ".".join(sorted(ops))
    built = sorted(ops) if units is None else _merge(root, sorted(ops), units)
    keep = ", ".join(repr(op) for op in built)
    setup.write_text(setup_text.replace(version, f"__version__ = '1.6.3+ops.{label}'").replace(
        SETUP_LIST, SETUP_LIST + f"    main_files = [p for p in main_files if osp.basename(p)[:-4] in ({keep},)]\n"))
    init.write_text(init_text.replace(INIT_LIST, f"for library in [{', '.join(repr('_' + op) for op in built)}]:"))


def _merge(root: Path, ops: list[str], units: int) -> list[str]:
    """The C++ files of `ops` dealt into `units` translation units; returns the extensions left to build (the
    first operator of each unit, whose csrc/<op>.cpp becomes the unit: it includes its operators' files, moved
    to <name>_src.cpp, so that setup.py finds one source per extension)."""
    if units < 1:
        raise SystemExit(f"--units must be at least 1, got {units}")
    csrc = root / "csrc"
    files = {}
    for op in ops:
        main, cpu = csrc / f"{op}.cpp", csrc / "cpu" / f"{op}_cpu.cpp"
        text = main.read_text()
        if text.count(REGISTRAR) != 1:
            raise SystemExit(f"{main}: expected one '{REGISTRAR}' to rename; build without --units")
        files[op] = (main, text.replace(REGISTRAR, f"static auto registry_{op} ="), cpu if cpu.is_file() else None)
    groups = [ops[i::units] for i in range(min(units, len(ops)))]
    for op, (main, text, cpu) in files.items():  # nothing is written before every file has been checked
        main.with_name(f"{op}_src.cpp").write_text(text)
        main.unlink()
        if cpu is not None:
            cpu.rename(cpu.with_name(f"{op}_cpu_src.cpp"))
    for group in groups:
        lines = [f"// {', '.join(group)}: one translation unit (ggns scripts/torch_cluster_subset.py --units)"]
        for op in group:
            lines.append(f'#include "{op}_src.cpp"')
            if files[op][2] is not None:
                lines.append(f'#include "cpu/{op}_cpu_src.cpp"')
        (csrc / f"{group[0]}.cpp").write_text("\n".join(lines) + "\n")
    return [group[0] for group in groups]


if __name__ == "__main__":
    args = sys.argv[1:]
    units = None
    if "--units" in args:
        at = args.index("--units")
        if at + 1 >= len(args) or not args[at + 1].isdigit():
            raise SystemExit("--units takes a number of translation units")
        units = int(args[at + 1])
        del args[at:at + 2]
    if len(args) < 2:
        raise SystemExit(__doc__)
    main(args[0], args[1:], units)
