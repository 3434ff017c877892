"""Scale check: does a dataset's geometry match the radii, training noise and point count the
paper chose for its scene? Every number from the paper is tied to a geometry (points per radius,
noise against edge length and per-step motion), so `python -m ggns geometry` measures them on
the generated files and compares them with the targets in conf/geometry/<scene>.yaml.

Measured (over the chosen trajectories and every `stride`-th step):
    points_per_step        points in one step's cloud (median; min and max reported too)
    point_spacing          median distance of a point to its nearest neighbour
    point_neighbours       P-P edges per point at the graph's P-P radius (mean)
    mesh_point_neighbours  points within the M-P radius of a mesh node (mean)
    edges_per_graph        directed edges of one graph with its point cloud, all types (mean), and per type
    smallest_mesh_edge     shortest rest-state mesh edge over all trajectories (median edge too)
    world_edges_per_node   MGN world edges per mesh node in the baseline graph (mean)
    free_motion_rms        sqrt(mean over free nodes, steps and coordinates of (x_{t+1} - x_t)^2)
    collider_step          collider displacement per step (median)
    noise_over_motion      training noise std / free_motion_rms
    noise_over_edge        training noise std / smallest mesh edge
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch_cluster

from ..batch import TrajectoryBatch
from ..config import load_config
from ..reports import markdown_table
from ..trajectory import Trajectory
from .connectivity import Connectivity, load_connectivity
from .state import state_graph
from .types import MESH_EDGE, WORLD_EDGE


def _edge_lengths(traj: Trajectory) -> np.ndarray:
    return np.linalg.norm(traj.rest_positions[traj.edges[:, 0]] - traj.rest_positions[traj.edges[:, 1]], axis=1)


def measure(trajectories: list[Trajectory], graph: Connectivity, baseline_graph: Connectivity, noise_std: float,
            stride: int = 5) -> dict[str, float]:
    """The quantities of the module docstring for these trajectories (module docstring)."""
    if not trajectories:
        raise ValueError("need at least one trajectory to measure")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    counts, spacing, edges, per_type, world, m_p = [], [], [], {}, [], []
    for traj in trajectories:
        batch = TrajectoryBatch.from_trajectories([traj], dtype=torch.float64)
        for t in range(0, traj.num_steps - 1, stride):
            points = batch.points[t]
            counts.append(len(points))
            if len(points) > 1:
                pair = torch_cluster.knn(points, points, 2)  # self and the nearest other point
                other = pair[:, pair[0] != pair[1]]
                spacing.append((points[other[0]] - points[other[1]]).norm(dim=1).median().item())
            g = state_graph(batch, t, batch.positions[t], True, graph)
            sizes = {et: g[et].edge_index.size(1) for et in g.edge_types}
            edges.append(sum(sizes.values()))
            for et, size in sizes.items():
                per_type.setdefault(et, []).append(size)
            m_p.append(sizes.get(("point", "near", "mesh"), 0) / len(traj.rest_positions))
            b = state_graph(batch, t, batch.positions[t], False, baseline_graph)
            world.append((b[WORLD_EDGE].edge_index.size(1) if WORLD_EDGE in b.edge_types else 0) / len(traj.rest_positions))
    lengths = np.concatenate([_edge_lengths(t) for t in trajectories])
    motion = np.concatenate([np.diff(t.positions, axis=0)[:, ~t.fixed].ravel() for t in trajectories])
    collider = np.concatenate([np.linalg.norm(np.diff(t.collider_positions, axis=0), axis=-1).ravel()
                               for t in trajectories if t.collider_positions.shape[1]])
    pp_edges = per_type.get(("point", "near", "point"), [0] * len(counts))
    out = {
        "points_per_step": float(np.median(counts)),
        "points_per_step_min": float(np.min(counts)),
        "points_per_step_max": float(np.max(counts)),
        "point_spacing": float(np.median(spacing)) if spacing else math.nan,
        "point_neighbours": float(np.sum(pp_edges) / max(np.sum(counts), 1)),
        "mesh_point_neighbours": float(np.mean(m_p)),
        "edges_per_graph": float(np.mean(edges)),
        "smallest_mesh_edge": float(lengths.min()),
        "median_mesh_edge": float(np.median(lengths)),
        "world_edges_per_node": float(np.mean(world)),
        "free_motion_rms": float(np.sqrt(np.mean(motion**2))),
        "collider_step": float(np.median(collider)) if len(collider) else math.nan,
    }
    out["noise_over_motion"] = noise_std / out["free_motion_rms"] if out["free_motion_rms"] > 0 else math.inf
    out["noise_over_edge"] = noise_std / out["smallest_mesh_edge"]
    for et, sizes in per_type.items():
        out[f"edges/{et[0]}-{et[2]}" + ("" if et != MESH_EDGE else " (mesh)")] = float(np.mean(sizes))
    return out


def check(values: dict[str, float], targets: dict[str, list[float]]) -> dict[str, bool]:
    """Whether each targeted quantity lies in its [low, high] range."""
    unknown = sorted(set(targets) - set(values))
    if unknown:
        raise ValueError(f"targets name unknown quantities {unknown}; measured: {sorted(values)}")
    return {name: float(lo) <= values[name] <= float(hi) for name, (lo, hi) in targets.items()}


def report(values: dict[str, float], targets: dict[str, list[float]], title: str) -> str:
    """A markdown table of every measured value, with its target range and verdict where one exists."""
    verdict = check(values, targets)
    rows = []
    for name, value in values.items():
        target = targets.get(name)
        rng = f"{target[0]:g} to {float(target[1]):g}" if target else ""
        mark = ("ok" if verdict[name] else "OUT OF RANGE") if target else ""
        rows.append((name, f"{value:.4g}", rng, mark))
    return "\n".join([f"### {title}", "", markdown_table(["quantity", "value", "target", ""], rows)]) + "\n"


def geometry_report(trajectories: list[Trajectory], source: str, targets: str | Path = "plate",
                    stride: int = 5) -> tuple[str, bool]:
    """Measure trajectories (e.g. of a generated split) against a targets file
    (conf/geometry/<name>.yaml); returns (markdown, whether every target is met)."""
    spec = load_config(targets, kind="geometry")
    values = measure(trajectories, load_connectivity(spec["graph"]), load_connectivity(spec["baseline_graph"]),
                     float(spec["noise_std"]), stride)
    title = (f"{source}: {len(trajectories)} trajectories, every {stride}th step; graphs {spec['graph']} and "
             f"{spec['baseline_graph']}, training noise {spec['noise_std']}")
    return report(values, spec["targets"], title), all(check(values, spec["targets"]).values())
