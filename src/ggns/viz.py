"""Pictures of trajectories: mesh, collider and point cloud at a few steps (2D scenes)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .data.trajectory import Trajectory  # noqa: E402


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
            loop = traj.collider_positions[t][np.append(traj.collider_faces[:, 0], traj.collider_faces[0, 0])]
            ax.fill(loop[:, 0], loop[:, 1], color="tab:gray", alpha=0.6)
            cloud = traj.point_cloud(t)
            ax.scatter(cloud[:, 0], cloud[:, 1], s=1.5, color="tab:green")
            ax.set(xlim=(-1, 1), ylim=(-1, 1), aspect="equal", xticks=[], yticks=[])
            ax.set_title(f"nu={traj.poissons_ratio:g}  t={t}", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
