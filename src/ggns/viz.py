"""Pictures of trajectories and rollouts: mesh, collider and point cloud at a few steps.

`plot_trajectories` draws generated 2D data, `rollout_figure` compares predicted rollouts with the
ground truth (2D: the triangle meshes; 3D: the boundary surfaces' edges in several views); `save_figure` writes a figure to a PNG and `figure_to_image` renders it to an RGB
array (e.g. for `SummaryWriter.add_image(tag, img, step, dataformats="HWC")`).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from itertools import cycle
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from mpl_toolkits.mplot3d.art3d import Line3DCollection  # noqa: E402

from .geometry import boundary_facets, check_cells  # noqa: E402
from .trajectory import Trajectory  # noqa: E402

SAVE_DPI = 110


def _to_numpy(x) -> np.ndarray:
    """numpy or torch (any device, with or without grad) -> numpy array."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _evenly_spaced(num_steps: int, num_frames: int) -> np.ndarray:
    return np.unique(np.linspace(0, num_steps - 1, num_frames).round().astype(int))


def _collider_loop(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The collider vertices in the loop order of its segments, closed (first vertex repeated)."""
    return vertices[np.append(faces[:, 0], faces[0, 0])]


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Write `fig` as a PNG (dpi 110) to `path`, creating parent directories; closes the figure."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(path, dpi=SAVE_DPI, format="png")
    finally:
        plt.close(fig)
    return path


def figure_to_image(fig: Figure) -> np.ndarray:
    """Render `fig` on its Agg canvas to an RGB uint8 array [H, W, 3]; closes the figure."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    try:
        canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
        canvas.draw()
        rgba = np.asarray(canvas.buffer_rgba())
        image = np.ascontiguousarray(rgba[..., :3], dtype=np.uint8)
    finally:
        plt.close(fig)
    return image


def plot_trajectories(trajectories: list[Trajectory], path: str | Path, num_frames: int = 4) -> Path:
    """One row per trajectory, `num_frames` evenly spaced steps per row; writes a PNG."""
    if not trajectories:
        raise ValueError("no trajectories to plot")
    if any(t.dim != 2 for t in trajectories):
        raise ValueError("plot_trajectories draws 2D scenes only")
    rows = len(trajectories)
    fig, axes = plt.subplots(rows, num_frames, figsize=(3 * num_frames, 3 * rows), squeeze=False)
    for row, traj in zip(axes, trajectories):
        steps = np.linspace(0, traj.num_steps - 1, num_frames).round().astype(int)
        for ax, t in zip(row, steps):
            x = traj.positions[t]
            ax.triplot(x[:, 0], x[:, 1], traj.cells, color="tab:blue", lw=0.6)
            loop = _collider_loop(traj.collider_positions[t], traj.collider_faces)
            ax.fill(loop[:, 0], loop[:, 1], color="tab:gray", alpha=0.6)
            cloud = traj.point_cloud(t)
            ax.scatter(cloud[:, 0], cloud[:, 1], s=1.5, color="tab:green")
            ax.set(xlim=(-1, 1), ylim=(-1, 1), aspect="equal", xticks=[], yticks=[])
            ax.set_title(f"nu={traj.poissons_ratio:g}  t={t}", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


_PRED_COLORS = ("tab:blue", "tab:red", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:cyan", "tab:olive")


def rollout_figure(
    cells,
    true,
    preds: Mapping[str, object],
    frames: Sequence[int] | None = None,
    points: Sequence | None = None,
    collider=None,
    collider_faces=None,
    num_frames: int = 4,
    title: str | None = None,
    views: Sequence[tuple[float, float]] = ((30.0, -60.0), (90.0, -90.0)),
) -> Figure:
    """Predicted rollouts against the ground truth for a 2D or 3D scene (d = 2 or 3).

    cells [C, d+1] triangles / tetrahedra; true [T, N, d] ground-truth positions; preds {label:
    [T, N, d]}; frames: steps to draw (default `num_frames` evenly spaced over 0..T-1); points:
    optional list of T point clouds [P_t, d] (None / empty = none that step); collider [T, K, d]
    with collider_faces [F, d] (2D: segments of a closed polyline; 3D: triangles, or none for
    collider nodes drawn as markers). 2D: one row per label; 3D: one row per label and view
    (elevation, azimuth in degrees, matplotlib's), drawing the boundary surfaces' edges. One column
    per frame. Returns the figure (not closed: pass it to `save_figure` or `figure_to_image`).
    """
    cells = _to_numpy(cells).astype(np.int64)
    true = _to_numpy(true).astype(np.float64)
    if true.ndim != 3 or true.shape[-1] not in (2, 3):
        raise ValueError(f"rollout_figure draws 2D and 3D scenes: true must be [T, N, 2|3], got {true.shape}")
    dim = true.shape[-1]
    num_steps, num_nodes = true.shape[:2]
    if num_steps < 1:
        raise ValueError("true has no steps")
    cells = check_cells(cells, num_nodes, corners=dim + 1)
    if not preds:
        raise ValueError("no predictions to plot")
    pred_arrays: dict[str, np.ndarray] = {}
    for label, pred in preds.items():
        pred = _to_numpy(pred).astype(np.float64)
        if pred.ndim != 3 or pred.shape[-1] != dim:
            raise ValueError(f"prediction {label!r} must be [T, N, {dim}] like the ground truth, got {pred.shape}")
        if pred.shape != true.shape:
            raise ValueError(f"prediction {label!r} has shape {pred.shape}, ground truth has {true.shape}")
        pred_arrays[str(label)] = pred

    if frames is None:
        if num_frames < 1:
            raise ValueError(f"num_frames must be >= 1, got {num_frames}")
        frames = _evenly_spaced(num_steps, num_frames)
    frames = [int(t) for t in np.asarray(frames).reshape(-1)]
    if not frames:
        raise ValueError("no frames to draw")
    bad = [t for t in frames if not 0 <= t < num_steps]
    if bad:
        raise ValueError(f"frames {bad} outside [0, {num_steps - 1}]")

    clouds = None
    if points is not None:
        if len(points) != num_steps:
            raise ValueError(f"points has {len(points)} entries, expected one per step ({num_steps})")
        clouds = []
        for t, p in enumerate(points):
            if p is None:
                clouds.append(None)
                continue
            p = _to_numpy(p)
            if p.size == 0:
                clouds.append(None)
                continue
            if p.ndim != 2 or p.shape[1] != dim:
                raise ValueError(f"points[{t}] must be [P, {dim}], got {p.shape}")
            clouds.append(p)

    if dim == 3:
        if collider is not None:
            collider = _to_numpy(collider).astype(np.float64)
            if collider.ndim != 3 or collider.shape[-1] != 3 or collider.shape[0] != num_steps:
                raise ValueError(f"collider must be [T={num_steps}, K, 3], got {collider.shape}")
        return _rollout_figure_3d(cells, true, pred_arrays, frames, clouds, collider, views, title)
    loops = None
    if collider is not None:
        collider = _to_numpy(collider).astype(np.float64)
        if collider.ndim != 3 or collider.shape[-1] != 2 or collider.shape[0] != num_steps:
            raise ValueError(f"collider must be [T={num_steps}, K, 2], got {collider.shape}")
        if collider_faces is None:
            faces = np.stack([np.arange(collider.shape[1]), np.roll(np.arange(collider.shape[1]), -1)], axis=1)
        else:
            faces = _to_numpy(collider_faces).astype(np.int64)
            if faces.ndim != 2 or faces.shape[1] != 2 or len(faces) == 0:
                raise ValueError(f"collider_faces must be segments [F, 2], got {faces.shape}")
        loops = [_collider_loop(collider[t], faces) for t in range(num_steps)]

    rows, cols = len(pred_arrays), len(frames)
    fig, axes = plt.subplots(rows, cols, figsize=(3 * cols, 3 * rows + 0.6), squeeze=False)
    for row, (color, (label, pred)) in zip(axes, zip(cycle(_PRED_COLORS), pred_arrays.items())):
        for ax, t in zip(row, frames):
            if loops is not None:
                ax.fill(loops[t][:, 0], loops[t][:, 1], color="tab:gray", alpha=0.6, zorder=1)
            ax.triplot(true[t, :, 0], true[t, :, 1], cells, color="0.35", lw=0.5, alpha=0.7, zorder=2)
            ax.triplot(pred[t, :, 0], pred[t, :, 1], cells, color=color, lw=0.7, zorder=3)
            if clouds is not None and clouds[t] is not None:
                ax.scatter(clouds[t][:, 0], clouds[t][:, 1], s=1.5, color="tab:green", zorder=4)
            ax.set(xlim=(-1, 1), ylim=(-1, 1), aspect="equal", xticks=[], yticks=[])
            ax.set_title(f"{label}  t={t}", fontsize=9)
    handles = [Line2D([], [], color="0.35", lw=1.0, label="ground truth")]
    handles += [
        Line2D([], [], color=c, lw=1.0, label=f"prediction: {label}") for c, label in zip(cycle(_PRED_COLORS), pred_arrays)
    ]
    if loops is not None:
        handles.append(Line2D([], [], color="tab:gray", lw=6, alpha=0.6, label="collider"))
    if clouds is not None:
        handles.append(Line2D([], [], color="tab:green", marker=".", ls="", label="point cloud"))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 4), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.6 / (3 * rows + 0.6) + 0.02, 1, 0.95 if title else 1))
    return fig


def _surface_segments(positions: np.ndarray, edges: np.ndarray) -> np.ndarray:
    return np.stack([positions[edges[:, 0]], positions[edges[:, 1]]], axis=1)


def _rollout_figure_3d(cells, true, preds: dict, frames: list[int], clouds, collider, views, title) -> Figure:
    """`rollout_figure` for tetrahedral meshes: the edges of the boundary surface, truth in grey and
    each prediction in its colour, point clouds in green, collider nodes as black markers; one row
    per (label, view), one column per frame."""
    if not views:
        raise ValueError("views must name at least one (elevation, azimuth)")
    facets = boundary_facets(cells)
    edges = np.unique(np.sort(np.concatenate([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [0, 2]]]), axis=1), axis=0)
    every = np.concatenate([true.reshape(-1, 3), *(p.reshape(-1, 3) for p in preds.values())])
    lo, hi = every.min(axis=0), every.max(axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6) * 1.05
    rows, cols = len(preds) * len(views), len(frames)
    fig = plt.figure(figsize=(3 * cols, 3 * rows + 0.6))
    index = 0
    for color, (label, pred) in zip(cycle(_PRED_COLORS), preds.items()):
        for elevation, azimuth in views:
            for t in frames:
                index += 1
                ax = fig.add_subplot(rows, cols, index, projection="3d")
                ax.add_collection3d(Line3DCollection(_surface_segments(true[t], edges), colors="0.35", linewidths=0.4,
                                                     alpha=0.7))
                ax.add_collection3d(Line3DCollection(_surface_segments(pred[t], edges), colors=color, linewidths=0.6))
                if clouds is not None and clouds[t] is not None:
                    ax.scatter(*clouds[t].T, s=1.0, color="tab:green", depthshade=False)
                if collider is not None:
                    ax.scatter(*collider[t].T, s=25, color="black", marker="v", depthshade=False)
                ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
                       zlim=(centre[2] - half, centre[2] + half), xticks=[], yticks=[], zticks=[])
                ax.set_box_aspect((1, 1, 1))
                ax.view_init(elev=elevation, azim=azimuth)
                ax.set_title(f"{label}  t={t}  view {elevation:g}/{azimuth:g}", fontsize=8)
    handles = [Line2D([], [], color="0.35", lw=1.0, label="ground truth")]
    handles += [Line2D([], [], color=c, lw=1.0, label=f"prediction: {label}") for c, label in zip(cycle(_PRED_COLORS), preds)]
    if collider is not None:
        handles.append(Line2D([], [], color="black", marker="v", ls="", label="collider"))
    if clouds is not None:
        handles.append(Line2D([], [], color="tab:green", marker=".", ls="", label="point cloud"))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 4), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.6 / (3 * rows + 0.6) + 0.02, top=0.93 if title else 0.98,
                        wspace=0.02, hspace=0.15)
    return fig
