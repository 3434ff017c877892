"""Dataset generation end to end: real simulation, real Open3D raycasting, real HDF5 files."""

import numpy as np
import pytest
import shapely

from ggns.data.generate import generate, regenerate, split_path
from ggns.data.schema import SplitReader, read_trajectories

def _assert_same(a, b):
    for name in ("rest_positions", "cells", "edges", "positions", "fixed", "collider_faces", "collider_positions", "points", "point_offsets"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert (a.poissons_ratio, a.seed, a.params) == (b.poissons_ratio, b.seed, b.params)


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from ggns.config import load_config

    config = load_config("plate_tiny", [f"output={tmp_path_factory.mktemp('tiny')}"])
    generate(config, progress=False)
    return config


def test_generation_is_deterministic_and_independent_of_workers(tiny_dataset, tmp_path):
    again = dict(tiny_dataset, output=str(tmp_path), workers=2)
    generate(again, ["train"], progress=False)
    first = list(read_trajectories(split_path(tiny_dataset["output"], "train")))
    second = list(read_trajectories(split_path(tmp_path, "train")))
    assert len(first) == len(second) == tiny_dataset["splits"]["train"] > 0
    for a, b in zip(first, second):
        _assert_same(a, b)


def test_a_trajectory_regenerates_from_its_stored_seed(tiny_dataset):
    with SplitReader(split_path(tiny_dataset["output"], "val")) as reader:
        stored = reader[1]
        config = reader.generator_config
    _assert_same(regenerate(config, 1, stored.seed), stored)


def test_splits_are_balanced_and_described(tiny_dataset):
    with SplitReader(split_path(tiny_dataset["output"], "train")) as reader:
        assert (reader.scene, reader.split, reader.dim, len(reader)) == ("plate", "train", 2, 3)
        trajs = list(reader)
    assert [t.poissons_ratio for t in trajs] == [-0.9, 0.0, 0.49]  # combination i mod 27, material-minor
    assert len({t.seed for t in trajs}) == 3
    t = trajs[0]
    assert t.positions.shape == (8, 81, 2) and t.edges.shape == (208, 2)  # 416 directed mesh edges
    assert t.collider_positions.shape == (8, 57, 2)
    assert np.abs(t.rest_positions).max() <= 1  # the plate fills [-1, 1]^2 at rest; the collider starts above it
    assert t.collider_positions[0, :, 1].min() > t.rest_positions[:, 1].max()
    assert t.params["plane"] == "stress"
    assert t.fixed.sum() == 9


def test_every_point_lies_on_the_deformed_plate(tiny_dataset):
    tolerance = tiny_dataset["sensor"]["voxel_size"]  # voxel centroids of hits on the object
    trajectories = list(read_trajectories(split_path(tiny_dataset["output"], "test")))
    assert len(trajectories) == tiny_dataset["splits"]["test"] > 0
    for traj in trajectories:
        assert traj.num_steps > 1
        for t in range(traj.num_steps):
            region = shapely.union_all(shapely.polygons(traj.positions[t][traj.cells]))
            points = shapely.points(traj.point_cloud(t).astype(np.float64))
            assert len(points) > 300
            assert shapely.distance(region, points).max() <= tolerance
            assert np.mean(shapely.distance(region, points) == 0) > 0.9


def _run_cli(capsys, *args) -> tuple[int, str]:
    """`python -m ggns <args>` in this process: (exit status, what it wrote on stderr)."""
    from ggns.__main__ import main

    capsys.readouterr()
    try:
        main(list(args))
        status = 0
    except SystemExit as stop:
        status = stop.code if isinstance(stop.code, int) else 1
    return status, capsys.readouterr().err


@pytest.mark.parametrize(
    "override, message",
    [("scene.poissons_ratios=[0.5]", "Poisson's ratio"), ("scene.youngs_modulus=0", "Young's modulus"), ("sensor.voxel_size=0", "voxel_size"),
     ("scene.gird_nodes=5", "scene.gird_nodes (did you mean scene.grid_nodes?)"),  # a typo
     ("sensr.voxel_size=0.1", "sensr (did you mean sensor or")],
)
def test_cli_refuses_bad_configuration_before_writing(tmp_path, capsys, override, message):
    status, err = _run_cli(capsys, "generate", "--config", "plate_tiny", "--output", str(tmp_path / "out"), override)
    assert status == 2 and message in err
    assert not (tmp_path / "out").exists()


def test_cli_refuses_to_overwrite_and_keeps_the_file(tiny_dataset, capsys):
    path = split_path(tiny_dataset["output"], "train")
    before = path.read_bytes()
    status, err = _run_cli(capsys, "generate", "--config", "plate_tiny", "--output", tiny_dataset["output"],
                           "--split", "train")
    assert status == 2 and "already exist" in err
    assert path.read_bytes() == before
