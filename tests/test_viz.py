"""Figures: rollout comparison, saving, rendering to an image, and the trajectory plot."""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch
from matplotlib.figure import Figure

from ggns.trajectory import Trajectory
from ggns.geometry import box_tet_mesh
from ggns.viz import figure_to_image, plot_trajectories, rollout_figure, save_figure

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
T = 5


def square():
    """A 2x2 square of two triangles, moving right over T steps."""
    rest = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    cells = np.array([[0, 1, 2], [0, 2, 3]])
    shift = np.linspace(0.0, 0.3, T)[:, None, None] * np.array([1.0, 0.0])
    true = rest[None] + shift
    return rest, cells, true


def collider():
    base = np.array([[-0.9, 0.6], [-0.6, 0.6], [-0.6, 0.9], [-0.9, 0.9]])
    verts = np.repeat(base[None], T, axis=0)
    faces = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    return verts, faces


def small_figure(**kwargs):
    _, cells, true = square()
    preds = {"GGNS k=5": true + 0.02, "MGN": torch.as_tensor(true - 0.03)}
    return rollout_figure(cells, true, preds, **kwargs)


def test_rollout_figure_layout():
    verts, faces = collider()
    points = [np.random.default_rng(t).uniform(-1, 1, (10, 2)) for t in range(T)]
    fig = small_figure(num_frames=3, points=points, collider=verts, collider_faces=faces, title="rollout")
    assert isinstance(fig, Figure)
    axes = [ax for ax in fig.axes]
    assert len(axes) == 2 * 3
    titles = [ax.get_title() for ax in axes]
    assert titles[0].startswith("GGNS k=5") and titles[0].endswith("t=0")
    assert titles[3].startswith("MGN") and titles[-1].endswith(f"t={T - 1}")
    assert all(ax.get_xlim() == (-1, 1) and ax.get_ylim() == (-1, 1) for ax in axes)
    assert fig.legends, "a legend should say which mesh is truth and which is prediction"
    texts = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "ground truth" in texts and any("MGN" in t for t in texts)
    plt.close(fig)


def test_rollout_figure_explicit_frames_and_torch_inputs():
    _, cells, true = square()
    fig = rollout_figure(torch.as_tensor(cells), torch.as_tensor(true), {"a": torch.as_tensor(true)}, frames=[0, 4])
    assert len(fig.axes) == 2
    plt.close(fig)


def test_rollout_figure_points_with_none_entries():
    points = [None, np.zeros((0, 2)), np.array([[0.0, 0.0], [0.1, 0.2]]), None, torch.zeros(3, 2)]
    fig = small_figure(points=points)
    image = figure_to_image(fig)
    assert image.shape[-1] == 3


def test_save_figure_writes_png(tmp_path):
    path = save_figure(small_figure(), tmp_path / "a" / "b" / "rollout.png")
    assert path.exists() and path.stat().st_size > 0
    assert path.read_bytes()[:8] == PNG_MAGIC


def test_figure_to_image():
    fig = small_figure()
    image = figure_to_image(fig)
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    assert image.shape[0] > 0 and image.shape[1] > 0
    assert image.min() < image.max(), "the rendered image is uniform: nothing was drawn"
    assert not plt.fignum_exists(fig.number)


def test_rollout_figure_shape_mismatch():
    _, cells, true = square()
    with pytest.raises(ValueError, match="shape"):
        rollout_figure(cells, true, {"short": true[:-1]})
    with pytest.raises(ValueError, match="shape"):
        rollout_figure(cells, true, {"ok": true, "few nodes": true[:, :3]})


def test_rollout_figure_3d_views_and_dimension_checks():
    """Tetrahedral meshes: one row per (prediction, view), one column per frame; 2D and 3D arrays
    cannot be mixed."""
    positions, cells = box_tet_mesh((0, 0, 0), (1, 1, 0.5), (2, 2, 1))
    true = np.stack([positions + [0.0, 0.0, 0.05 * t] for t in range(T)])
    points = [positions[:5] + 0.01 if t % 2 == 0 else None for t in range(T)]
    collider = true[:, :1] + [0.0, 0.0, 0.1]
    fig = rollout_figure(cells, true, {"a": true, "b": true + 0.02}, points=points, collider=collider, num_frames=3,
                         views=((30, -60), (90, -90), (0, 0)))
    assert len(fig.axes) == 2 * 3 * 3 and fig.axes[0].name == "3d"
    assert figure_to_image(fig).shape[2] == 3
    _, cells2, true2 = square()
    true3 = np.concatenate([true2, np.zeros_like(true2[..., :1])], axis=-1)
    with pytest.raises(ValueError, match=r"\[T, N, 2\]"):
        rollout_figure(cells2, true2, {"p": true3})
    with pytest.raises(ValueError, match="views"):
        rollout_figure(cells, true, {"a": true}, views=())


def test_rollout_figure_frames_out_of_range():
    _, cells, true = square()
    for frames in ([0, T], [-1, 2]):
        with pytest.raises(ValueError, match="outside"):
            rollout_figure(cells, true, {"p": true}, frames=frames)


def test_plot_trajectories_writes_png(tmp_path):
    rest, cells, true = square()
    verts, faces = collider()
    counts = np.array([0, 4, 4, 0, 2])
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    traj = Trajectory(
        rest_positions=rest,
        cells=cells,
        edges=np.array([[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]),
        positions=true,
        fixed=np.array([True, False, False, True]),
        collider_faces=faces,
        collider_positions=verts,
        points=np.random.default_rng(0).uniform(-1, 1, (offsets[-1], 2)).astype(np.float32),
        point_offsets=offsets,
        youngs_modulus=1e4,
        poissons_ratio=0.3,
        seed=0,
    )
    path = plot_trajectories([traj], tmp_path / "plots" / "data.png", num_frames=3)
    assert path.exists() and path.read_bytes()[:8] == PNG_MAGIC
