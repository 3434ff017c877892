"""The package installs as a user installs it and works outside the checkout: the wheel built from this
tree goes into a fresh virtual environment that reuses the installed torch, torch-cluster and the other
dependencies (through a .pth file, without this checkout's editable ggns), with pip offline, so a
dependency range the installed versions do not satisfy fails here; then the console script and the
commands a user starts with run from a folder outside the checkout, on the package's own presets and
pretrained simulators."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(command: list[str], cwd: Path, env: dict | None = None, timeout: int = 600) -> str:
    # without PYTHONPATH: a checkout's src on it would shadow the installed wheel; without GGNS_PRESETS: a user
    # outside the checkout has none of its experiment presets
    inherited = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "GGNS_PRESETS")}
    done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env={**inherited, **(env or {})})
    assert done.returncode == 0, f"{' '.join(map(str, command))}\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
    return done.stdout + done.stderr


@pytest.fixture(scope="module")
def fresh_env(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("install")
    source = work / "source"  # what the wheel is built from, copied so that the build leaves the checkout as it was
    source.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, source / name)
    shutil.copytree(ROOT / "src", source / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(work / "dist"),
          str(source)], cwd=work)
    (wheel,) = (work / "dist").glob("ggns-*.whl")
    venv = work / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=work)
    # the installed dependencies, each linked into one folder that the fresh environment reads, ggns left out
    shared = work / "shared"
    shared.mkdir()
    site = Path(sysconfig.get_paths()["purelib"])
    for entry in site.iterdir():
        if entry.name.lower().startswith(("ggns", "__editable__", "_ggns", "__pycache__")) or entry.suffix == ".pth":
            continue
        (shared / entry.name).symlink_to(entry)
    (fresh_site,) = (venv / "lib").glob("python*/site-packages")
    (fresh_site / "shared_dependencies.pth").write_text(f"{shared}\n")
    python = venv / "bin" / "python"
    out = _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-index", str(wheel)], cwd=work)
    assert "torch" not in out.split("Successfully installed")[-1], out  # nothing but ggns installed
    return venv


def test_the_wheel_works_from_a_folder_outside_the_checkout(fresh_env, tmp_path):
    bin_ = fresh_env / "bin"
    where = _run([str(bin_ / "python"), "-c", "import ggns, ggns.config as c; print(ggns.__file__); "
                  "print(c.CONF_DIR.is_dir())"], cwd=tmp_path)
    assert str(fresh_env) in where.splitlines()[0] and where.splitlines()[1] == "True", where
    listed = _run([str(bin_ / "ggns"), "pretrained", "list"], cwd=tmp_path)
    assert "plate/ggns" in listed and "tissue/ggns" in listed
    # a new user's first commands, from tmp_path, in one process (each start-up costs seconds)
    script = r"""
import sys
from ggns.__main__ import main

def run(*args):
    try:
        main(list(args))
    except SystemExit as stop:
        if stop.code not in (0, None):
            raise

from pathlib import Path
from ggns.config import CONF_DIR

# a user's own preset over a shipped one: the tiny plate with 12 states (validation's m+10 needs more than 10)
Path("tiny12.yaml").write_text(f"base: {CONF_DIR / 'data' / 'plate_tiny.yaml'}\nscene:\n  num_steps: 12\n"
                               "output: data/plate_tiny12\n")
run("generate", "--config", "tiny12.yaml", "--split", "train,val", "--count", "2")
run("generate", "--config", "plate", "--split", "test", "--count", "1", "--output", "data/plate", "--workers", "1")
run("rollout", "--checkpoint", "plate/ggns", "--input", "data/plate/test.h5", "--output", "predictions.h5")
run("fit", "--config", "plate/mgn", "--data.dataset", "tiny12.yaml", "--data.data_dir", "data/plate_tiny12",
    "--trainer.fast_dev_run", "true", "--model.init_args.latent", "8", "--model.init_args.blocks", "1")
# a graph preset of one's own (the shipped plate MGN's with a narrower world radius): its checkpoint holds the radii
import yaml
graph = yaml.safe_load((CONF_DIR / "graphs" / "plate_mgn.yaml").read_text())
graph["world"] = 0.3
Path("my_graph.yaml").write_text(yaml.safe_dump(graph))
run("fit", "--config", "plate/mgn", "--data.dataset", "tiny12.yaml", "--data.data_dir", "data/plate_tiny12",
    "--model.init_args.connectivity", "my_graph.yaml", "--model.init_args.latent", "8", "--model.init_args.blocks", "1",
    "--trainer.max_epochs", "1", "--trainer.limit_train_batches", "1", "--trainer.limit_val_batches", "1",
    "--trainer.check_val_every_n_epoch", "1", "--trainer.logger.init_args.save_dir", "own_graph")
"""
    _run([str(bin_ / "python"), "-c", script], cwd=tmp_path, env={"OMP_NUM_THREADS": "1"})
    # the checkpoint copied to an empty folder, where neither the preset nor the checkout is, loads and rolls out
    (checkpoint,) = (tmp_path / "own_graph").rglob("last.ckpt")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.copy(checkpoint, elsewhere / "own.ckpt")
    shutil.copy(tmp_path / "data" / "plate" / "test.h5", elsewhere / "test.h5")
    _run([str(bin_ / "ggns"), "rollout", "--checkpoint", "own.ckpt", "--input", "test.h5", "--output", "own.h5"],
         cwd=elsewhere, env={"OMP_NUM_THREADS": "1"})
    assert (elsewhere / "own.h5").is_file()
    radii = _run([str(bin_ / "python"), "-c", "from ggns.models.loading import load_simulator; "
                  "print(load_simulator('own.ckpt').connectivity.world)"], cwd=elsewhere)
    assert radii.strip().splitlines()[-1] == "0.3", radii
    assert (tmp_path / "data" / "plate" / "test.h5").is_file() and (tmp_path / "data" / "plate_tiny12" / "train.h5").is_file()
    assert (tmp_path / "predictions.h5").is_file()
