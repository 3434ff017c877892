"""Alpha-shape baseline: voxel subsampling, alpha shapes and their IoU with the true mesh."""
from __future__ import annotations

import numpy as np
import pytest
import shapely

from ggns.baselines.alpha_shapes import (
    alpha_shape,
    alpha_shape_iou,
    default_alpha,
    trajectory_alpha_iou,
    voxel_size_for,
    voxel_subsample,
)
from ggns.data.generate import split_path
from ggns.data.schema import SplitReader
from conftest import box_mesh


def grid(n: int, lo=0.0, hi=1.0) -> np.ndarray:
    xs = np.linspace(lo, hi, n)
    return np.stack(np.meshgrid(xs, xs, indexing="ij"), axis=-1).reshape(-1, 2)


def l_shape(n: int = 41) -> np.ndarray:
    pts = grid(n)
    return pts[(pts[:, 0] <= 0.5) | (pts[:, 1] <= 0.5)]  # unit square minus its upper right quarter


def test_square_alpha_shape_matches_the_square():
    shape = alpha_shape(grid(41), alpha=10.0)
    square = shapely.box(0, 0, 1, 1)
    iou = shapely.area(shape & square) / shapely.area(shape | square)
    assert iou > 0.9


def test_l_shape_is_not_convex():
    shape = alpha_shape(l_shape(), alpha=10.0)
    assert shape.area == pytest.approx(0.75, rel=0.05)
    assert shape.area < 0.9 * shape.convex_hull.area  # hull: 0.875, shape: about 0.75
    assert not shape.contains(shapely.Point(0.8, 0.8))  # the missing quarter stays open


def test_voxel_subsample_hits_the_target():
    rng = np.random.default_rng(0)
    pts = grid(101) + rng.normal(scale=1e-3, size=(101 * 101, 2))
    for target in (30, 100, 500):
        sub = voxel_subsample(pts, target)
        assert abs(len(sub) - target) <= 0.25 * target
        assert np.array_equal(sub, voxel_subsample(pts, target))  # deterministic
    sub = voxel_subsample(pts, 100)
    assert sub.min() >= pts.min() and sub.max() <= pts.max()


def test_bad_inputs_raise():
    pts = grid(5)
    with pytest.raises(ValueError):
        voxel_subsample(np.zeros((0, 2)), 10)
    with pytest.raises(ValueError):
        voxel_subsample(pts, 2)
    with pytest.raises(ValueError):
        alpha_shape(pts, 0.0)
    with pytest.raises(ValueError):
        alpha_shape(pts, -1.0)
    with pytest.raises(ValueError):
        alpha_shape(pts[:2], 1.0)
    with pytest.raises(ValueError):
        alpha_shape(np.zeros((5, 3)), 1.0)
    with pytest.raises(ValueError):
        default_alpha(0.0)


def test_huge_alpha_gives_an_empty_shape_and_zero_iou():
    pts = grid(21)
    assert alpha_shape(pts, 1e6).is_empty
    positions, cells = box_mesh(2, n=21)
    assert alpha_shape_iou(pts, positions, cells, alpha=1e6) == 0.0
    assert alpha_shape_iou(pts, positions, cells) > 0.9  # default alpha on the same data


def test_collinear_points_give_an_empty_shape():
    assert alpha_shape(np.stack([np.linspace(0, 1, 5), np.zeros(5)], axis=1), 1.0).is_empty


def test_default_alpha_keeps_the_l_shape_concave():
    pts = l_shape(81)
    positions, cells = box_mesh(2, n=21)
    keep = np.all(positions[cells].max(axis=1) > 0.5, axis=1)  # triangles in the upper right quarter
    cells = cells[~keep]
    iou = alpha_shape_iou(pts, positions, cells)  # target = 441 nodes (some unused) -> about 441 points
    assert iou > 0.85
    voxel = voxel_size_for(pts, len(positions))
    assert alpha_shape(voxel_subsample(pts, len(positions)), default_alpha(voxel)).area < 0.85


def test_tiny_plate_trajectory_iou(tiny_data_dir):
    with SplitReader(split_path(tiny_data_dir, "test")) as reader:
        traj = reader[0]
    iou = trajectory_alpha_iou(traj)
    assert iou.shape == (traj.num_steps,)
    assert np.all((iou > 0.5) & (iou <= 1.0)), iou
