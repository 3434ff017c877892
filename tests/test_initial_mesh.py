"""Initial mesh generation from the first point cloud (`ggns.baselines.initial_mesh`)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ggns.baselines.alpha_shapes import voxel_size_for
from ggns.baselines.initial_mesh import generated_trajectory, initial_mesh_rollout_iou, mesh_from_point_cloud
from ggns.evaluation.metrics import mesh_iou
from ggns.data.generate import split_path
from ggns.data.schema import read_trajectories
from ggns.geometry import cell_edges, signed_volumes
from ggns.batch import TrajectoryBatch
from ggns.models.simulators import GGNS
from conftest import box_mesh


def test_square_grid():
    g = np.linspace(0.0, 1.0, 41)
    points = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    # voxel centroids sit inside the square, so the IoU is < 1 (0.90 with 100 nodes, more with 400)
    nodes, cells, edges = mesh_from_point_cloud(points, 400)
    assert 280 <= len(nodes) <= 520
    assert cells.dtype == np.int64 and cells.min() == 0 and cells.max() == len(nodes) - 1
    assert np.array_equal(np.unique(cells), np.arange(len(nodes)))  # no unused node
    assert (signed_volumes(nodes, cells) > 0).all()  # counter-clockwise
    assert np.array_equal(edges, cell_edges(cells))
    sq_nodes, sq_cells = box_mesh(2, 2)
    assert mesh_iou(nodes, cells, sq_nodes, sq_cells) > 0.9


def test_mesh_iou_of_different_meshes():
    a_nodes, a_cells = box_mesh(2, 3)  # unit square
    b_nodes, b_cells = box_mesh(2, 5, size=(0.5, 1.0))  # its left half, other nodes
    assert mesh_iou(a_nodes, a_cells, a_nodes, a_cells) == pytest.approx(1.0)
    assert mesh_iou(a_nodes, a_cells, b_nodes, b_cells) == pytest.approx(0.5)
    assert mesh_iou(b_nodes + [2.0, 0.0], b_cells, a_nodes, a_cells) == pytest.approx(0.0)


def test_bad_input():
    with pytest.raises(ValueError):
        mesh_from_point_cloud(np.zeros((10, 3)), 5)
    with pytest.raises(ValueError):
        mesh_from_point_cloud(np.zeros((0, 2)), 5)
    with pytest.raises(ValueError):
        mesh_from_point_cloud(np.random.default_rng(0).random((50, 2)), 2)
    with pytest.raises(ValueError):  # collinear: no triangle
        mesh_from_point_cloud(np.stack([np.linspace(0, 1, 50), np.zeros(50)], axis=1), 20)
    with pytest.raises(ValueError):  # alpha so large that every triangle is rejected
        mesh_from_point_cloud(np.random.default_rng(0).random((200, 2)), 50, alpha=1e6)
    nodes, cells = box_mesh(2, 3)
    with pytest.raises(ValueError):
        mesh_iou(nodes, cells + 100, nodes, cells)
    with pytest.raises(ValueError):
        mesh_iou(nodes, cells.astype(float), nodes, cells)


@pytest.fixture(scope="module")
def tiny(tiny_data_dir):
    return {split: read_trajectories(split_path(tiny_data_dir, split)) for split in ("train", "test")}


def test_generated_trajectory(tiny):
    traj = tiny["test"][0]
    gen = generated_trajectory(traj, target_nodes=80)
    n = len(gen.rest_positions)
    assert 0.7 * 80 <= n <= 1.3 * 80
    assert gen.positions.shape == (traj.num_steps, n, 2)
    assert np.array_equal(gen.positions[0], gen.rest_positions)
    assert (signed_volumes(gen.rest_positions, gen.cells) > 0).all()
    assert np.array_equal(gen.edges, cell_edges(gen.cells))
    assert gen.fixed.shape == (n,) and 0 < gen.fixed.sum() < n
    y = gen.rest_positions[:, 1]
    bottom = traj.point_cloud(0)[:, 1].min()
    voxel = voxel_size_for(traj.point_cloud(0), 80)  # the fixed nodes are the bottom voxel row
    assert (y[gen.fixed] <= bottom + voxel).all() and y[gen.fixed].max() < y[~gen.fixed].min()
    assert y[gen.fixed].max() < bottom + 0.15 * np.ptp(y)  # ... which is near the plate's bottom
    assert np.array_equal(gen.points, traj.points) and np.array_equal(gen.collider_positions, traj.collider_positions)
    iou = mesh_iou(gen.rest_positions, gen.cells, traj.positions[0], traj.cells)
    assert iou > 0.8, iou
    with pytest.raises(ValueError):
        generated_trajectory(traj, fixed_tolerance=-1.0)


def test_initial_mesh_rollout_iou(tiny):
    torch.manual_seed(0)
    model = GGNS(latent=8, blocks=1)
    model.fit_normalizers([TrajectoryBatch.from_trajectories(tiny["train"])])
    model.eval()
    traj = tiny["test"][0]
    iou = initial_mesh_rollout_iou(model, traj, "every:2")
    assert iou.shape == (traj.num_steps,)
    assert np.isfinite(iou).all() and ((iou >= 0) & (iou <= 1)).all(), iou
    gen = generated_trajectory(traj)
    assert iou[0] == pytest.approx(mesh_iou(gen.rest_positions, gen.cells, traj.positions[0], traj.cells), abs=1e-5)
