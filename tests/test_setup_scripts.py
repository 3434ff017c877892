"""scripts/torch_cluster_subset.py, which restricts torch-cluster's sources to the extensions ggns
calls, on the two files it edits (copied from the 1.6.3 sources' relevant lines)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "torch_cluster_subset.py"
SETUP = """import glob
import os.path as osp
__version__ = '1.6.3'
def get_extensions():
    main_files = glob.glob(osp.join('csrc', '*.cpp'))
    # remove generated 'hip' files, in case of rebuilds
    main_files = [path for path in main_files if 'hip' not in path]
    return main_files
"""
INIT = """for library in [
        '_version', '_grid', '_graclus', '_fps', '_rw', '_sampler', '_nearest',
        '_knn', '_radius'
]:
    loaded.append(library)
"""


def source_tree(tmp_path: Path) -> Path:
    (tmp_path / "torch_cluster").mkdir()
    (tmp_path / "setup.py").write_text(SETUP)
    (tmp_path / "torch_cluster" / "__init__.py").write_text(INIT)
    (tmp_path / "csrc").mkdir()
    for name in ("version", "grid", "graclus", "fps", "rw", "sampler", "nearest", "knn", "radius"):
        (tmp_path / "csrc" / f"{name}.cpp").write_text("")
    return tmp_path


def run(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True)


def test_only_the_chosen_extensions_are_built_and_loaded(tmp_path):
    root = source_tree(tmp_path)
    assert run(root, "version", "radius", "knn").returncode == 0
    scope = {"__file__": str(root / "setup.py")}
    exec(compile((root / "setup.py").read_text(), "setup.py", "exec"), scope)
    cwd = os.getcwd()
    try:
        os.chdir(root)
        built = sorted(Path(p).stem for p in scope["get_extensions"]())
    finally:
        os.chdir(cwd)
    assert built == ["knn", "radius", "version"]
    assert scope["__version__"] == "1.6.3+ops.knn.radius.version"
    loaded: list[str] = []
    exec((root / "torch_cluster" / "__init__.py").read_text(), {"loaded": loaded})
    assert loaded == ["_knn", "_radius", "_version"]


def test_units_put_several_extensions_in_one_file_each_registrar_renamed(tmp_path):
    root = source_tree(tmp_path)
    for op in ("version", "radius", "knn"):
        (root / "csrc" / f"{op}.cpp").write_text(f"// {op}\nstatic auto registry =\n    op({op!r});\n")
    (root / "csrc" / "cpu").mkdir()
    for op in ("radius", "knn"):
        (root / "csrc" / "cpu" / f"{op}_cpu.cpp").write_text(f"// {op} on the CPU\n")
    assert run(root, "version", "radius", "knn", "--units", "2").returncode == 0
    csrc = root / "csrc"
    assert (csrc / "knn.cpp").read_text().splitlines()[1:] == [
        '#include "knn_src.cpp"', '#include "cpu/knn_cpu_src.cpp"', '#include "version_src.cpp"']
    assert (csrc / "radius.cpp").read_text().splitlines()[1:] == [
        '#include "radius_src.cpp"', '#include "cpu/radius_cpu_src.cpp"']
    assert not (csrc / "version.cpp").exists() and not (csrc / "cpu" / "knn_cpu.cpp").exists()
    assert "static auto registry_version =" in (csrc / "version_src.cpp").read_text()
    assert (csrc / "cpu" / "radius_cpu_src.cpp").read_text() == "// radius on the CPU\n"
    loaded: list[str] = []
    exec((root / "torch_cluster" / "__init__.py").read_text(), {"loaded": loaded})
    assert loaded == ["_knn", "_radius"]  # version's operator is registered by _knn
    assert "1.6.3+ops.knn.radius.version" in (root / "setup.py").read_text()


def test_units_refuse_sources_they_cannot_rename_and_change_nothing(tmp_path):
    root = source_tree(tmp_path)  # empty C++ files: no registrar to rename
    result = run(root, "version", "radius", "--units", "2")
    assert result.returncode != 0 and "expected one 'static auto registry ='" in result.stderr
    assert sorted(p.name for p in (root / "csrc").iterdir()) == sorted(
        f"{name}.cpp" for name in ("version", "grid", "graclus", "fps", "rw", "sampler", "nearest", "knn", "radius"))


def test_unknown_sources_or_operators_change_nothing(tmp_path):
    root = source_tree(tmp_path)
    for args, message in ((["version", "radius", "voronoi"], "unknown ['voronoi']"), (["radius"], "include 'version'")):
        result = run(root, *args)
        assert result.returncode != 0 and message in result.stderr
    (root / "setup.py").write_text(SETUP.replace("1.6.3", "1.7.0"))
    result = run(root, "version", "radius")
    assert result.returncode != 0 and "not the torch-cluster 1.6.3 sources" in result.stderr
    assert (root / "torch_cluster" / "__init__.py").read_text() == INIT
