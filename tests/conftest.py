"""Shared fixtures: small meshes and the tiny plate configuration."""
from __future__ import annotations

import os
import shutil
import sys
import threading
from pathlib import Path

os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")  # as `python -m ggns` runs (ggns.__main__), before torch allocates
# the checkout's experiment presets by name (ggns.config.experiment_dirs), in the processes tests start too,
# whatever their working directory
os.environ.setdefault("GGNS_PRESETS", str(Path(__file__).resolve().parents[1] / "experiments"))
if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs one test process per core (pytest-xdist): one thread each, in the processes they start
    # too (set before numpy and torch read it); torch's intra-op threads on cores that other processes use
    # make small graphs many times slower
    os.environ["OMP_NUM_THREADS"] = "1"

import numpy as np
import pytest
import skfem

from ggns.config import load_config


def box_mesh(dim: int, n: int = 5, size=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Structured simplicial mesh of a box: positions [N, dim], cells [C, dim+1] (from scikit-fem)."""
    axes = [np.linspace(0.0, size[i], n) for i in range(dim)]
    mesh = skfem.MeshTri.init_tensor(*axes) if dim == 2 else skfem.MeshTet.init_tensor(*axes)
    return mesh.p.T.copy(), mesh.t.T.astype(np.int64).copy()


@pytest.fixture
def tiny_config(tmp_path) -> dict:
    """The plate_tiny preset writing into a temporary directory."""
    return load_config("plate_tiny", [f"output={tmp_path / 'data'}"])


@pytest.fixture(scope="session")
def tiny_data_dir(tmp_path_factory):
    """All splits of the plate_tiny preset (3 / 2 / 2 trajectories of T = 8 states), generated
    once per session by the real simulator into a temporary directory; returns that directory."""
    from ggns.data.generate import generate

    out = tmp_path_factory.mktemp("plate_tiny")
    generate(load_config("plate_tiny", [f"output={out}"]), progress=False)
    return out


TINY12 = "plate_tiny12.yaml"  # the data preset written by `cli_data` into its directory


@pytest.fixture(scope="session")
def cli_data(tmp_path_factory):
    """A data preset, <dir>/plate_tiny12.yaml (plate_tiny with T = 12 states, so that the m+10 metric
    is defined in validation and test), and all its splits (3 / 2 / 2 trajectories) in <dir>,
    generated once per session (or copied from the folder GGNS_TEST_DATA names, where a machine
    cannot raycast); returns <dir>."""
    import torch

    from ggns.config import CONF_DIR
    from ggns.data.generate import generate

    out = tmp_path_factory.mktemp("plate_tiny12")
    (out / TINY12).write_text(f"base: {CONF_DIR / 'data' / 'plate_tiny.yaml'}\nscene:\n  num_steps: 12\n"
                              f"output: {out}\n")
    handed_in = os.environ.get("GGNS_TEST_DATA")
    if handed_in:  # splits generated elsewhere, for a machine without open3d (scripts/gpu_check.sh)
        for split in ("train", "val", "test"):
            shutil.copy(Path(handed_in) / f"{split}.h5", out / f"{split}.h5")
        return out
    threads = torch.get_num_threads()  # in-process generation sets it to 1
    try:
        generate(load_config(out / TINY12), progress=False)
    finally:
        torch.set_num_threads(threads)
    return out


# ---- the learned simulators on plate_tiny (test_simulators, test_data_module, test_cli) -------------
T = 8  # states per plate_tiny trajectory
SMALL = dict(latent=16, blocks=2)  # model size of these tests


@pytest.fixture(scope="module")
def single_thread():
    """One torch thread for a module: on a 2-core machine torch's intra-op threads make tiny graphs
    10-100x slower as soon as anything else runs."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


_IN_PROCESS = threading.Lock()


def launch_in_process(command: list[str], out, env: dict[str, str]) -> int:
    """A `ggns.sweeps.sweep.Launch` for tests of what a sweep or `bench learning` decides (which fits
    and tests run, skip, resume, merge): `python -m ggns ...` called in this test process, one at a time,
    with the torch threads its OMP_NUM_THREADS asks for; output into `out`. Saves a process start-up
    (about 12 s of imports here) per command. What processes add (their own exit status, a kill of the
    whole group) is tested through real processes in test_faults.py and test_bad_input.py."""
    import contextlib

    import torch

    from ggns.__main__ import main

    assert command[1:3] == ["-m", "ggns"], command
    with _IN_PROCESS, pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(out), \
            contextlib.redirect_stderr(out):
        patch.setattr(sys, "argv", ["ggns"])
        threads = torch.get_num_threads()
        torch.set_num_threads(int(env.get("OMP_NUM_THREADS", threads)))
        try:
            main(command[3:])
        except SystemExit as stop:
            return stop.code if isinstance(stop.code, int) else 1
        finally:
            torch.set_num_threads(threads)
    return 0


@pytest.fixture(scope="module")
def trajs(tiny_data_dir):
    """The plate_tiny splits as Trajectory lists."""
    from ggns.data.generate import split_path
    from ggns.data.schema import read_trajectories

    return {split: read_trajectories(split_path(tiny_data_dir, split)) for split in ("train", "val", "test")}


@pytest.fixture(scope="module")
def val_batch(trajs):
    from ggns.batch import TrajectoryBatch

    return TrajectoryBatch.from_trajectories(trajs["val"])


@pytest.fixture(scope="module")
def train_windows(trajs):
    """Two training windows of one transition each (trajectory 0 from step 3, trajectory 1 from step 5)."""
    from ggns.data.module import WindowDataset

    ds = WindowDataset(trajs["train"], 1)
    return [ds[3], ds[(T - 1) + 5]]


@pytest.fixture(scope="module")
def train_batch(train_windows):
    from ggns.data.module import collate

    return collate(train_windows)


def make(cls, seed: int = 0, **kwargs):
    """A simulator of class `cls` at the tests' small size, seeded."""
    import torch

    torch.manual_seed(seed)
    return cls(**{**SMALL, **kwargs})


def eager_losses(model, optimizer, batches) -> list[float]:
    """The losses of the eager training steps (`window_loss`, backward, the optimizer) on `batches`, with the
    host's generator seeded 1 (as the static steps they are compared with)."""
    import torch

    torch.manual_seed(1)
    losses = []
    for batch in batches:
        optimizer.zero_grad()
        loss = model.window_loss(batch)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    return losses


def first_graph(model, batch, use_points=None, t: int = 0):
    """The model's input graph of step t of `batch` (points as the model uses them by default)."""
    from ggns.graphs.state import state_graph

    use_points = model.uses_points if use_points is None else use_points
    return state_graph(batch, t, batch.positions[t], use_points, model.connectivity, model.with_material)


def normalizer_buffers(state: dict) -> dict:
    return {k: v for k, v in state.items() if "normalizer" in k}


def quiet_trainer(root, **kwargs):
    """A Lightning trainer without logger, checkpoints or progress output (one batch, no validation)."""
    import pytorch_lightning as pl

    return pl.Trainer(**{**dict(max_epochs=1, limit_train_batches=1, limit_val_batches=0, logger=False,
                                enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                                default_root_dir=root, accelerator="cpu"), **kwargs})


# ---- a tiny pretrained registry (test_pretrained, test_demo) -----------------------------------------
TINY_MODELS = {"ggns": ("conf/plate/ggns.yaml", "k1"), "mgn": ("conf/plate/mgn.yaml", "never"),
               "mgn_m": ("conf/plate/mgn_m.yaml", "never")}


@pytest.fixture(scope="session")
def tiny_registry(cli_data, tmp_path_factory):
    """Three simulators (tiny/ggns, tiny/mgn, tiny/mgn_m) trained for one epoch on the cli_data preset by
    `ggns.sweeps.pretrain.train` (the real fit command, a subprocess; the second and third run its
    command in this process) and packaged by `package`
    into a temporary registry; returns (registry directory, spec)."""
    from ggns import pretrained
    from ggns.config import CONF_DIR
    from ggns.sweeps.pretrain import package, train

    root = tmp_path_factory.mktemp("registry")
    sweep = root / "tiny_sweep.yaml"
    overrides = {"data": {"dataset": str(cli_data / TINY12), "batch_size": 8, "max_eval_trajectories": 2},
                 "trainer": {"max_epochs": 1, "check_val_every_n_epoch": 1, "enable_progress_bar": False},
                 "model": {"init_args": {"latent": 8, "blocks": 1}}}
    models = {name: {"config": str(Path(__file__).resolve().parents[1] / config), "overrides": overrides}
              for name, (config, _) in TINY_MODELS.items()}
    import json
    sweep.write_text(json.dumps({"output": str(root / "runs"), "seeds": [0], "models": models}))
    spec = {"output": str(root / "runs"), "test_trajectories": 2,
            "entries": {f"tiny/{name}": {"sweep": str(sweep), "model": name, "family": family}
                        for name, (_, family) in TINY_MODELS.items()}}
    registry = root / "pretrained"
    saved = pretrained.REGISTRY
    pretrained.REGISTRY = registry
    try:
        for i, name in enumerate(spec["entries"]):
            if i == 0:  # `ggns pretrained train`'s own subprocess
                train(name, spec)
            else:  # the same fit command in this process: one process start fewer each
                from ggns.__main__ import main
                from ggns.sweeps.pretrain import train_command

                with pytest.MonkeyPatch.context() as patch:
                    patch.setattr(sys, "argv", ["ggns"])  # LightningCLI warns when it also has one
                    main(train_command(name, spec)[3:])
            package(name, spec)
    finally:
        pretrained.REGISTRY = saved
    return registry, spec


# ---- the 3D tasks through the Lightning CLI (test_tissue, test_cavity) ------------------------------
def fit_and_test_3d(task: str, model: str, data_dir, tmp_path, latent: int, blocks: int, extra=()) -> tuple:
    """`fit` one epoch (2 batches) and `test` the last checkpoint of conf/<task>/<model>.yaml on the
    <task>_tiny data in data_dir, through the real CLI; returns (checkpoint path, test_metrics.md text),
    after checking that the test reported the full rollout, the m+10 metric and the 3D volume IoU."""
    from ggns.__main__ import main

    common = ["--config", f"conf/{task}/{model}.yaml", "--data.dataset", f"{task}_tiny", "--data.data_dir", str(data_dir),
              "--data.generate_missing", "false", "--data.batch_size", "8",
              "--trainer.logger.init_args.save_dir", str(tmp_path), *extra,
              "--model.init_args.latent", str(latent), "--model.init_args.blocks", str(blocks),
              "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false"]
    main(["fit", *common, "--trainer.logger.init_args.version", "v", "--trainer.max_epochs", "1",
          "--trainer.limit_train_batches", "2", "--trainer.limit_val_batches", "1", "--trainer.check_val_every_n_epoch", "1"])
    checkpoint = tmp_path / f"{task}_{model}" / "v" / "checkpoints" / "last.ckpt"
    assert checkpoint.is_file()
    main(["test", *common, "--trainer.logger.init_args.version", "test", "--ckpt_path", str(checkpoint)])
    metrics = (tmp_path / f"{task}_{model}" / "test" / "test_metrics.md").read_text()
    assert "rollout_mse_never" in metrics and "m10_mse" in metrics and "rollout_iou_never" in metrics  # 3D volume IoU
    return checkpoint, metrics


def save_untrained(model, path):
    """`model` saved as a Lightning checkpoint without training."""
    import pytorch_lightning as pl

    trainer = pl.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False)
    trainer.strategy.connect(model)
    trainer.save_checkpoint(path)
    return path


# ---- scheduling on several test processes (`make test`: pytest-xdist, --dist loadgroup) -------------------------
# Each test file runs whole in one process, so that its module fixtures (generated data, trained models) are
# built once; the files sharing the tiny registry (a session fixture that trains three simulators) run in one
# process too. xdist hands the groups out in its own order (most tests first). Handing them out longest first
# (measured with GGNS_TEST_TIMELINE below) was not faster over four runs each, whose times varied by up to 25 %
# (docs/experiments/test_suite_time.md), so it is not done.
SHARED_GROUPS = {"test_demo.py": "tiny_registry", "test_pretrained.py": "tiny_registry",
                 "test_scripts.py": "test_simulators.py"}  # the latter: one tiny_data_dir for both


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the groups
def pytest_collection_modifyitems(config, items):
    for item in items:
        item.add_marker(pytest.mark.xdist_group(SHARED_GROUPS.get(item.path.name, item.path.name)))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """With GGNS_TEST_TIMELINE=<file>, one JSON line per test (its set-up, call and teardown): test process,
    test id, start and end (seconds since the epoch) and the test process's CPU seconds: where a run's time
    goes, per test and per test process."""
    path = os.environ.get("GGNS_TEST_TIMELINE")
    if not path:
        yield
        return
    import json
    import time

    start, cpu = time.time(), time.process_time()
    yield
    line = {"process": os.environ.get("PYTEST_XDIST_WORKER", "main"), "test": item.nodeid, "start": start,
            "end": time.time(), "cpu": time.process_time() - cpu}
    with open(path, "a") as out:
        out.write(json.dumps(line) + "\n")
