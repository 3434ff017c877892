"""Shared fixtures: small meshes and the tiny plate configuration."""
from __future__ import annotations

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
    generated once per session; returns <dir>."""
    import torch

    from ggns.config import CONF_DIR
    from ggns.data.generate import generate

    out = tmp_path_factory.mktemp("plate_tiny12")
    (out / TINY12).write_text(f"base: {CONF_DIR / 'data' / 'plate_tiny.yaml'}\nscene:\n  num_steps: 12\n"
                              f"output: {out}\n")
    threads = torch.get_num_threads()  # in-process generation sets it to 1
    try:
        generate(load_config(out / TINY12), progress=False)
    finally:
        torch.set_num_threads(threads)
    return out
