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

Usage: python torch_cluster_subset.py SOURCE_DIR OP [OP ...]
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


def main(source: str, ops: list[str]) -> None:
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
    keep = ", ".join(repr(op) for op in sorted(ops))
    setup.write_text(setup_text.replace(version, f"__version__ = '1.6.3+ops.{label}'").replace(
        SETUP_LIST, SETUP_LIST + f"    main_files = [p for p in main_files if osp.basename(p)[:-4] in ({keep},)]\n"))
    init.write_text(init_text.replace(INIT_LIST, f"for library in [{', '.join(repr('_' + op) for op in sorted(ops))}]:"))


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    main(sys.argv[1], sys.argv[2:])
