"""Pictures of trajectories and rollouts: people would rather look at them than read tables.

`plot_trajectories` draws generated 2D data. `rollout_figure` compares predicted rollouts with the
ground truth at a few steps: one row per prediction with the truth drawn in grey beneath it (2D:
the triangle meshes; 3D: the boundary surfaces' edges, one row per prediction and view), the row's
label on its left and the step above the top row only. `rollout_animation` writes the same
comparison as a GIF, one frame per step, one panel per series (the truth, then each prediction).
`plot_error_over_time` draws per-step error curves of several rollouts on a log axis.
`save_figure` writes a figure to a PNG and `figure_to_image` renders it to an RGB array (e.g. for
`SummaryWriter.add_image(tag, img, step, dataformats="HWC")`).

Point clouds are drawn only on the panels of the predictions named in `points_on` (default: every
prediction) at the steps where `points` holds one, never on the ground truth: a model without point
clouds never saw them, so none are drawn over it.
"""
from __future__ import annotations

import re
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from itertools import cycle
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import animation  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Line3DCollection  # noqa: E402

from .geometry import boundary_facets, cell_edges, check_cells  # noqa: E402
from .trajectory import Trajectory  # noqa: E402

SAVE_DPI = 110
PANEL_INCHES = 3.0  # side of one mesh panel
LIMITS_2D = (-1.05, 1.05)  # the 2D task space [-1, 1]^2 (the plate) and a margin: its border edges stay visible
TRUTH_COLOR, COLLIDER_COLOR, POINT_COLOR = "0.35", "tab:gray", "tab:green"
_PRED_COLORS = ("tab:blue", "tab:red", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:cyan", "tab:olive")


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
            ax.fill(loop[:, 0], loop[:, 1], color=COLLIDER_COLOR, alpha=0.6)
            cloud = traj.point_cloud(t)
            ax.scatter(cloud[:, 0], cloud[:, 1], s=1.5, color=POINT_COLOR)
            ax.set(xlim=LIMITS_2D, ylim=LIMITS_2D, aspect="equal", xticks=[], yticks=[])
            ax.set_title(f"nu={traj.poissons_ratio:g}  t={t}", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


# ---- rollouts: checked once, drawn by the figure and the animation alike ------------------------
@dataclass(frozen=True)
class _Rollout:
    """A checked comparison of rollouts with the ground truth (float64 numpy), ready to draw.

    true [T, N, d]; preds {label: [T, N, d]} with their colours; clouds: T entries [P_t, d] or None;
    points_on: the labels whose panels show the clouds; collider: 2D closed loops [T, F+1, 2], 3D
    nodes [T, K, 3], or None; edges: 3D boundary-surface edges [E, 2] (2D: the triangles `cells`);
    limits [d, 2], the same for every step and panel."""

    cells: np.ndarray
    true: np.ndarray
    preds: dict[str, np.ndarray]
    colors: dict[str, str]
    clouds: list | None
    points_on: frozenset[str]
    collider: np.ndarray | None
    edges: np.ndarray | None
    limits: np.ndarray

    @property
    def dim(self) -> int:
        return self.true.shape[-1]


def _check_rollout(cells, true, preds, points, collider, collider_faces, points_on) -> _Rollout:
    """The arguments of `rollout_figure` / `rollout_animation` checked and converted; ValueError
    naming the argument otherwise."""
    true = _to_numpy(true).astype(np.float64)
    if true.ndim != 3 or true.shape[-1] not in (2, 3):
        raise ValueError(f"rollouts are drawn for 2D and 3D scenes: true must be [T, N, 2|3], got {true.shape}")
    num_steps, num_nodes, dim = true.shape
    if num_steps < 1:
        raise ValueError("true has no steps")
    cells = check_cells(_to_numpy(cells).astype(np.int64), num_nodes, corners=dim + 1)
    if not preds:
        raise ValueError("no predictions to plot")
    arrays: dict[str, np.ndarray] = {}
    for label, pred in preds.items():
        pred = _to_numpy(pred).astype(np.float64)
        if pred.ndim != 3 or pred.shape[-1] != dim:
            raise ValueError(f"prediction {label!r} must be [T, N, {dim}] like the ground truth, got {pred.shape}")
        if pred.shape != true.shape:
            raise ValueError(f"prediction {label!r} has shape {pred.shape}, ground truth has {true.shape}")
        arrays[str(label)] = pred
    points_on = frozenset(arrays if points_on is None else map(str, points_on))
    if not points_on <= arrays.keys():
        raise ValueError(f"points_on names {sorted(points_on - arrays.keys())}, "
                         f"not among the predictions {list(arrays)}")

    clouds = None
    if points is not None:
        if len(points) != num_steps:
            raise ValueError(f"points has {len(points)} entries, expected one per step ({num_steps})")
        clouds = [None if p is None else _to_numpy(p) for p in points]
        clouds = [None if p is None or p.size == 0 else p for p in clouds]
        for t, p in enumerate(clouds):
            if p is not None and (p.ndim != 2 or p.shape[1] != dim):
                raise ValueError(f"points[{t}] must be [P, {dim}], got {p.shape}")

    if collider is not None:
        collider = _to_numpy(collider).astype(np.float64)
        if collider.ndim != 3 or collider.shape[-1] != dim or collider.shape[0] != num_steps:
            raise ValueError(f"collider must be [T={num_steps}, K, {dim}], got {collider.shape}")
    if dim == 3:  # the collider's nodes are drawn as markers (collider_faces unused)
        every = np.concatenate([true.reshape(-1, 3), *(p.reshape(-1, 3) for p in arrays.values())])
        lo, hi = every.min(axis=0), every.max(axis=0)
        half = max(float((hi - lo).max()) / 2, 1e-6) * 1.05
        limits = (lo + hi)[:, None] / 2 + [-half, half]
        edges = cell_edges(boundary_facets(cells))
    else:
        limits, edges = np.array([LIMITS_2D, LIMITS_2D]), None
        if collider is not None:
            if collider_faces is None:
                ring = np.arange(collider.shape[1])
                faces = np.stack([ring, np.roll(ring, -1)], axis=1)
            else:
                faces = _to_numpy(collider_faces).astype(np.int64)
                if faces.ndim != 2 or faces.shape[1] != 2 or len(faces) == 0:
                    raise ValueError(f"collider_faces must be segments [F, 2], got {faces.shape}")
            collider = np.stack([_collider_loop(c, faces) for c in collider])
    colors = dict(zip(arrays, cycle(_PRED_COLORS)))
    return _Rollout(cells, true, arrays, colors, clouds, points_on, collider, edges, limits)


def _draw_step(ax, r: _Rollout, t: int, label: str | None, view: tuple[float, float] | None = None) -> None:
    """Step t on `ax`: the collider, the ground truth (grey; beneath the prediction when `label`
    names one), the prediction `label` in its colour and the point cloud where `label` shows it.
    3D axes look from `view` (elevation, azimuth in degrees)."""
    pred = None if label is None else r.preds[label]
    cloud = r.clouds[t] if r.clouds is not None and label in r.points_on else None
    if r.dim == 2:
        if r.collider is not None:
            ax.fill(*r.collider[t].T, color=COLLIDER_COLOR, alpha=0.6, zorder=1)
        ax.triplot(*r.true[t].T, r.cells, color=TRUTH_COLOR, lw=0.5 if pred is not None else 0.7,
                   alpha=0.7 if pred is not None else 1.0, zorder=2)
        if pred is not None:
            ax.triplot(*pred[t].T, r.cells, color=r.colors[label], lw=0.7, zorder=3)
        if cloud is not None:
            ax.scatter(*cloud.T, s=1.5, color=POINT_COLOR, zorder=4)
        ax.set(xlim=r.limits[0], ylim=r.limits[1], aspect="equal", xticks=[], yticks=[])
        return
    ax.add_collection3d(Line3DCollection(r.true[t][r.edges], colors=TRUTH_COLOR,  # edges [E, 2, 3]
                                         linewidths=0.4 if pred is not None else 0.6,
                                         alpha=0.7 if pred is not None else 1.0))
    if pred is not None:
        ax.add_collection3d(Line3DCollection(pred[t][r.edges], colors=r.colors[label], linewidths=0.6))
    if cloud is not None:
        ax.scatter(*cloud.T, s=1.0, color=POINT_COLOR, depthshade=False)
    if r.collider is not None:
        ax.scatter(*r.collider[t].T, s=25, color="black", marker="v", depthshade=False)
    ax.set(xlim=r.limits[0], ylim=r.limits[1], zlim=r.limits[2], xticks=[], yticks=[], zticks=[])
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=view[0], azim=view[1])


def _legend(fig: Figure, r: _Rollout) -> None:
    """Which colour is which series, below the panels."""
    handles = [Line2D([], [], color=TRUTH_COLOR, lw=1.0, label="ground truth")]
    handles += [Line2D([], [], color=r.colors[label], lw=1.0, label=f"prediction: {label}") for label in r.preds]
    if r.collider is not None:
        handles.append(Line2D([], [], color=COLLIDER_COLOR, lw=6, alpha=0.6, label="collider") if r.dim == 2
                       else Line2D([], [], color="black", marker="v", ls="", label="collider"))
    if r.clouds is not None and r.points_on:
        handles.append(Line2D([], [], color=POINT_COLOR, marker=".", ls="", label="point cloud given"))
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 4), fontsize=8, frameon=False)


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
    points_on: Collection[str] | None = None,
) -> Figure:
    """Predicted rollouts against the ground truth for a 2D or 3D scene (d = 2 or 3).

    cells [C, d+1] triangles / tetrahedra; true [T, N, d] ground-truth positions; preds {label:
    [T, N, d]}; frames: steps to draw (default `num_frames` evenly spaced over 0..T-1); points:
    optional list of T point clouds [P_t, d] (None / empty = none that step), drawn on the rows of
    the labels in `points_on` (default: every row); collider [T, K, d] with collider_faces [F, 2]
    (2D: segments of a closed polyline; 3D: unused, the collider nodes are drawn as markers).
    2D: one row per label; 3D: one row per label and view (elevation, azimuth in degrees,
    matplotlib's), drawing the boundary surfaces' edges. One column per frame; each row's label
    (and 3D view) on its left, the step above the top row. Returns the figure (not closed: pass it
    to `save_figure` or `figure_to_image`).
    """
    r = _check_rollout(cells, true, preds, points, collider, collider_faces, points_on)
    num_steps = r.true.shape[0]
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
    if r.dim == 3 and not views:
        raise ValueError("views must name at least one (elevation, azimuth)")
    rows = [(label, view) for label in r.preds for view in (views if r.dim == 3 else [None])]
    fig = plt.figure(figsize=(PANEL_INCHES * len(frames) + 0.4, PANEL_INCHES * len(rows) + 0.8), layout="constrained")
    for i, (label, view) in enumerate(rows):
        for j, t in enumerate(frames):
            ax = fig.add_subplot(len(rows), len(frames), i * len(frames) + j + 1,
                                 projection="3d" if r.dim == 3 else None)
            _draw_step(ax, r, t, label, view)
            if i == 0:
                ax.set_title(f"t={t}", fontsize=9)
            if j == 0:  # the row's label left of its first panel, where the layout leaves room for it
                ax.annotate(label if view is None else f"{label}\nview {view[0]:g}/{view[1]:g}", xy=(0, 0.5),
                            xycoords="axes fraction", xytext=(-4, 0), textcoords="offset points", rotation=90,
                            ha="right", va="center", fontsize=9)
    _legend(fig, r)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def _movie_writer(path: Path, fps: int) -> animation.AbstractMovieWriter:
    """PillowWriter for .gif; FFMpegWriter for .mp4 when ffmpeg is installed (RuntimeError if not)."""
    suffix = path.suffix.lower()
    if suffix == ".gif":
        return animation.PillowWriter(fps=fps)
    if suffix == ".mp4":
        if not animation.writers.is_available("ffmpeg"):
            raise RuntimeError(f"cannot write {path}: an .mp4 needs ffmpeg, which is not installed (not on PATH); "
                               "write a .gif instead (Pillow)")
        return animation.FFMpegWriter(fps=fps)
    raise ValueError(f"an animation is written as .gif (or .mp4 with ffmpeg), got {path.name!r}")


def rollout_animation(
    cells,
    true,
    preds: Mapping[str, object],
    path: str | Path,
    points: Sequence | None = None,
    collider=None,
    collider_faces=None,
    fps: int = 10,
    view: tuple[float, float] = (30.0, -60.0),
    points_on: Collection[str] | None = None,
    title: str | None = None,
) -> Path:
    """The rollouts of `rollout_figure` as an animation, every step t = 0..T-1 one frame; writes
    `path` (.gif with Pillow; .mp4 needs ffmpeg) and returns it.

    One panel per series side by side: the ground truth, then each prediction (truth in grey
    beneath it), with the same axis limits at every step; point clouds [P_t, d] on the panels of
    `points_on` (default: every prediction) at the steps where `points` holds one. 3D: the
    boundary surfaces' edges from one `view` (elevation, azimuth in degrees). Arguments and shapes
    as in `rollout_figure`; the frame's step (and "point cloud given") is written above the panels.
    """
    path = Path(path)
    writer = _movie_writer(path, fps)
    r = _check_rollout(cells, true, preds, points, collider, collider_faces, points_on)
    labels = [None, *r.preds]
    fig = plt.figure(figsize=(PANEL_INCHES * len(labels), PANEL_INCHES + 1.0), layout="constrained")
    axes = [fig.add_subplot(1, len(labels), i + 1, projection="3d" if r.dim == 3 else None) for i in range(len(labels))]
    _legend(fig, r)
    head = f"{title}   " if title else ""

    def draw(t: int) -> None:
        for ax, label in zip(axes, labels):
            ax.clear()
            _draw_step(ax, r, t, label, view)
            ax.set_title("ground truth" if label is None else label, fontsize=9)
        given = r.clouds is not None and r.clouds[t] is not None and bool(r.points_on)
        fig.suptitle(f"{head}t={t}" + ("   point cloud given" if given else ""), fontsize=10)

    draw(0)
    fig.canvas.draw()
    fig.set_layout_engine("none")  # the layout of the first frame, kept: the panels do not move
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        animation.FuncAnimation(fig, draw, frames=r.true.shape[0], repeat=False).save(path, writer=writer)
    finally:
        plt.close(fig)
    return path


# ---- error over time ------------------------------------------------------------------------------
_SERIES_LABEL = re.compile(r"^(?P<model>.*) \((?P<schedule>[^()]*)\)$")
_LINE_STYLES = ("-", "--", "-.", ":", (0, (5, 1)), (0, (1, 1)), (0, (3, 1, 1, 1, 1, 1)))


def plot_error_over_time(curves: Mapping[str, object], path: str | Path, title: str | None = None,
                         ylabel: str = "mesh position MSE") -> Path:
    """Per-step error curves {label: [T]} (e.g. `evaluation.pictures.error_curves`) in one plot,
    x = step t, log y axis; writes a PNG to `path` and returns it.

    The curves start at t = 1: S_0 is given (error 0, not drawable on a log axis). Labels of the form
    "<model> (<schedule>)" share one colour per model and one line style per schedule; the legend
    stands right of the axes, over no line."""
    if not curves:
        raise ValueError("no error curves to plot")
    colors, styles = {}, {}
    fig, ax = plt.subplots(figsize=(7.5, 4.0), layout="constrained")
    for label, curve in curves.items():
        curve = _to_numpy(curve).astype(np.float64)
        if curve.ndim != 1 or len(curve) < 2:
            raise ValueError(f"curve {label!r} must be [T] with T >= 2 steps, got {curve.shape}")
        if not np.isfinite(curve).all():
            raise ValueError(f"curve {label!r} has non-finite values (diverged rollout?)")
        match = _SERIES_LABEL.match(label)
        model, schedule = (match["model"], match["schedule"]) if match else (label, "")
        color = colors.setdefault(model, _PRED_COLORS[len(colors) % len(_PRED_COLORS)])
        style = styles.setdefault(schedule, _LINE_STYLES[len(styles) % len(_LINE_STYLES)])
        ax.plot(np.arange(1, len(curve)), curve[1:], color=color, ls=style, lw=1.4, label=label)
    ax.set_yscale("log", nonpositive="mask")
    ax.set(xlabel="step t (S_0 given)", ylabel=ylabel)
    ax.grid(True, which="major", alpha=0.35)
    ax.grid(True, which="minor", alpha=0.12)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    if title:
        ax.set_title(title, fontsize=10)
    return save_figure(fig, path)
