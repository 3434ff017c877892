"""Figures: rollout comparison (its layout), rollout animation, error over time, saving, rendering to an
image, and the trajectory plot."""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch
from matplotlib.collections import PathCollection
from matplotlib.figure import Figure
from PIL import Image

from ggns.trajectory import Trajectory
from ggns.geometry import box_tet_mesh
from ggns.viz import (LIMITS_2D, figure_to_image, plot_error_over_time, plot_trajectories, rollout_animation,
                      rollout_figure, save_figure)

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
    """One row per prediction, one column per frame: the step above the top row only, each row's
    label left of its first panel, the same limits on every panel; a legend says which is which."""
    verts, faces = collider()
    points = [np.random.default_rng(t).uniform(-1, 1, (10, 2)) for t in range(T)]
    fig = small_figure(num_frames=3, points=points, collider=verts, collider_faces=faces, title="rollout")
    assert isinstance(fig, Figure)
    axes = [ax for ax in fig.axes]
    assert len(axes) == 2 * 3
    assert [ax.get_title() for ax in axes] == ["t=0", "t=2", f"t={T - 1}", "", "", ""]
    assert [[t.get_text() for t in ax.texts] for ax in axes] == [["GGNS k=5"], [], [], ["MGN"], [], []]
    assert all(ax.get_xlim() == LIMITS_2D and ax.get_ylim() == LIMITS_2D for ax in axes)
    assert fig.legends, "a legend should say which mesh is truth and which is prediction"
    texts = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "ground truth" in texts and any("MGN" in t for t in texts)
    plt.close(fig)


def overlapping_texts(fig: Figure) -> list[tuple[str, str]]:
    """Pairs of drawn texts (suptitle, panel titles, row labels, legend entries) whose boxes overlap
    each other, or a text and a panel it does not belong to, after the layout of a real render."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    texts = [(fig._suptitle, None)] if fig._suptitle is not None else []
    texts += [(t, ax) for ax in fig.axes for t in (ax.title, *ax.texts) if t.get_text()]
    texts += [(t, None) for legend in fig.legends for t in legend.get_texts()]
    boxes = [(t.get_text(), t.get_window_extent(renderer), owner) for t, owner in texts]
    found = [(a, b) for i, (a, box_a, _) in enumerate(boxes) for b, box_b, _ in boxes[i + 1:]
             if box_a.overlaps(box_b)]
    panels = [(ax, ax.get_window_extent(renderer)) for ax in fig.axes]
    found += [(text, f"panel {fig.axes.index(ax)}") for text, box, owner in boxes for ax, panel in panels
              if ax is not owner and box.overlaps(panel)]
    plt.close(fig)
    return found


@pytest.mark.parametrize("rows", [1, 3, 6])
def test_rollout_figure_2d_texts_do_not_overlap(rows):
    _, cells, true = square()
    verts, faces = collider()
    preds = {f"GGNS+LSTM (every:{k + 1})": true + 0.01 * k for k in range(rows)}
    fig = rollout_figure(cells, true, preds, num_frames=4, collider=verts, collider_faces=faces,
                         points=[np.zeros((3, 2))] * T, title="test trajectory, nu=0.3 (green: point clouds)")
    assert overlapping_texts(fig) == []


def tet_rollout():
    positions, cells = box_tet_mesh((0, 0, 0), (1, 1, 0.5), (2, 2, 1))
    true = np.stack([positions + [0.0, 0.0, 0.05 * t] for t in range(T)])
    return positions, cells, true


@pytest.mark.parametrize("models", [1, 3])
def test_rollout_figure_3d_texts_do_not_overlap(models):
    """3D: one row per label and view (2 and 6 rows), the view named in the row's label."""
    positions, cells, true = tet_rollout()
    preds = {f"GGNS{'+LSTM' * k} (every:2)": true + 0.02 * k for k in range(models)}
    fig = rollout_figure(cells, true, preds, num_frames=3, points=[positions[:4]] * T, collider=true[:, :1],
                         title="tissue")
    labels = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert labels == [f"{label}\nview {view}" for label in preds for view in ("30/-60", "90/-90")]
    assert overlapping_texts(fig) == []


def scatters(ax) -> int:
    return sum(isinstance(c, PathCollection) for c in ax.collections)


def test_rollout_figure_points_only_on_the_rows_that_use_them():
    """points_on: the clouds are drawn on those rows at the steps that have one, not on the others."""
    verts, faces = collider()
    points = [np.zeros((3, 2)) if t % 2 == 0 else None for t in range(T)]
    fig = small_figure(frames=[0, 1, 2], points=points, collider=verts, collider_faces=faces, points_on=["GGNS k=5"])
    assert [scatters(ax) for ax in fig.axes] == [1, 0, 1, 0, 0, 0]
    plt.close(fig)
    positions, cells, true = tet_rollout()
    fig = rollout_figure(cells, true, {"a": true, "b": true}, frames=[0, 1], points=[positions[:4]] + [None] * (T - 1),
                         points_on={"b"}, views=((30, -60),))
    assert [scatters(ax) for ax in fig.axes] == [0, 0, 1, 0]
    plt.close(fig)
    with pytest.raises(ValueError, match="points_on"):
        small_figure(points=points, points_on=["GGNS"])


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
    positions, cells, true = tet_rollout()
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


def gif_frames(path) -> int:
    assert path.read_bytes()[:6] in (b"GIF87a", b"GIF89a") and path.stat().st_size > 0
    with Image.open(path) as image:
        return image.n_frames


def test_rollout_animation_writes_one_frame_per_step(tmp_path):
    _, cells, true = square()
    verts, faces = collider()
    points = [np.zeros((3, 2)) if t % 2 == 0 else None for t in range(T)]
    path = rollout_animation(cells, true, {"GGNS (every:2)": true + 0.02, "MGN (never)": true - 0.03},
                             tmp_path / "a" / "rollout.gif", points=points, collider=verts, collider_faces=faces,
                             points_on=["GGNS (every:2)"], fps=5, title="plate")
    assert path == tmp_path / "a" / "rollout.gif" and gif_frames(path) == T


def test_rollout_animation_3d(tmp_path):
    positions, cells, true = tet_rollout()
    path = rollout_animation(cells, true, {"GGNS (every:1)": true + 0.01}, tmp_path / "tissue.gif",
                             points=[positions[:4]] * T, collider=true[:, :1], view=(20, 30))
    assert gif_frames(path) == T


def test_rollout_animation_formats(tmp_path, monkeypatch):
    """An .mp4 needs ffmpeg: a clear error when it is missing; other suffixes are refused."""
    from matplotlib import animation

    _, cells, true = square()
    monkeypatch.setattr(animation.writers, "is_available", lambda name: False)
    with pytest.raises(RuntimeError, match="ffmpeg"):
        rollout_animation(cells, true, {"p": true}, tmp_path / "rollout.mp4")
    with pytest.raises(ValueError, match=".gif"):
        rollout_animation(cells, true, {"p": true}, tmp_path / "rollout.avi")
    assert not list(tmp_path.iterdir())


def test_plot_error_over_time_writes_png(tmp_path):
    steps = np.arange(T)
    curves = {"GGNS (every:1)": 1e-4 * steps, "GGNS (never)": 1e-3 * steps**2,
              "MGN (never)": torch.tensor(2e-3 * steps)}
    path = plot_error_over_time(curves, tmp_path / "errors.png", title="error over time")
    assert path.read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(ValueError, match="non-finite"):
        plot_error_over_time({"a": np.array([0.0, np.nan])}, tmp_path / "bad.png")
    with pytest.raises(ValueError, match="no error curves"):
        plot_error_over_time({}, tmp_path / "none.png")
