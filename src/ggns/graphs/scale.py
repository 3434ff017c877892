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
    mesh_hops_diameter     most mesh-edge hops between two mesh nodes (rest mesh; max over trajectories)
    fixed_hops_max         mesh-edge hops from the farthest free node to a fixed node (max)
    collider_hops_max      mesh-edge hops from the farthest mesh node to one a collider-mesh edge reaches,
                           in the model graph (max over measured steps with such edges)
    *_world                the same three over mesh and world edges of the baseline graph
A model passes messages one hop per processor block: fewer blocks than these hops leave nodes that
cannot see the fixed nodes or the collider within one step (the receptive field).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import scipy.sparse as sparse
import torch
from scipy.sparse.csgraph import shortest_path

from ..batch import TrajectoryBatch
from ..config import load_config
from ..reports import markdown_table
from ..trajectory import Trajectory
from . import search
from .connectivity import Connectivity, load_connectivity
from .state import state_graph
from .types import MESH_EDGE, WORLD_EDGE


def _edge_lengths(traj: Trajectory) -> np.ndarray:
    return np.linalg.norm(traj.rest_positions[traj.edges[:, 0]] - traj.rest_positions[traj.edges[:, 1]], axis=1)


def graph_hops(num_nodes: int, edge_index: np.ndarray, sources: np.ndarray | None = None) -> np.ndarray:
    """Fewest hops over the undirected edges `edge_index` [2, E] between nodes: [num_nodes, num_nodes] if
    sources is None, else [num_nodes] from every node to the nearest node of `sources` (a bool mask or
    indices); inf where unreachable."""
    edge_index = np.asarray(edge_index)
    adjacency = sparse.coo_matrix((np.ones(edge_index.shape[1]), (edge_index[0], edge_index[1])),
                                  shape=(num_nodes, num_nodes)).tocsr()
    if sources is None:
        return shortest_path(adjacency, directed=False, unweighted=True)
    sources = np.flatnonzero(sources) if np.asarray(sources).dtype == bool else np.asarray(sources)
    if len(sources) == 0:
        return np.full(num_nodes, np.inf)
    return shortest_path(adjacency, directed=False, unweighted=True, indices=sources).min(axis=0)


def _hops(g, fixed: np.ndarray, with_world: bool) -> tuple[float, float, float]:
    """(diameter, hops to the nearest fixed node, hops to the nearest collider-reached node) of one mesh graph."""
    types = [MESH_EDGE] + ([WORLD_EDGE] if with_world and WORLD_EDGE in g.edge_types else [])
    index = np.concatenate([g[et].edge_index.numpy() for et in types], axis=1)
    n = g["mesh"].num_nodes
    diameter = graph_hops(n, index).max()
    to_fixed = graph_hops(n, index, fixed)[~fixed].max() if fixed.any() and (~fixed).any() else math.nan
    c_m = ("collider", "near", "mesh")
    reached = np.unique(g[c_m].edge_index[1].numpy()) if c_m in g.edge_types else np.zeros(0, dtype=int)
    to_collider = graph_hops(n, index, reached).max() if len(reached) else math.nan
    return float(diameter), float(to_fixed), float(to_collider)


def measure(trajectories: list[Trajectory], graph: Connectivity, baseline_graph: Connectivity, noise_std: float,
            stride: int = 5) -> dict[str, float]:
    """The quantities of the module docstring for these trajectories (module docstring)."""
    if not trajectories:
        raise ValueError("need at least one trajectory to measure")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    counts, spacing, edges, per_type, world, m_p = [], [], [], {}, [], []
    hops = {False: [], True: []}  # (diameter, to fixed, to collider) per step: model graph, baseline graph
    for traj in trajectories:
        batch = TrajectoryBatch.from_trajectories([traj], dtype=torch.float64)
        for t in range(0, traj.num_steps - 1, stride):
            points = batch.points[t]
            counts.append(len(points))
            if len(points) > 1:
                pair = search.knn(points, points, 2)  # self and the nearest other point
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
            hops[False].append(_hops(state_graph(batch, t, batch.positions[t], False, graph), traj.fixed, False))
            hops[True].append(_hops(b, traj.fixed, True))
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
    for with_world, suffix in ((False, ""), (True, "_world")):
        diameter, to_fixed, to_collider = np.array(hops[with_world]).T
        for name, values in (("mesh_hops_diameter", diameter), ("fixed_hops_max", to_fixed),
                             ("collider_hops_max", to_collider)):
            out[name + suffix] = math.nan if np.isnan(values).all() else float(np.nanmax(values))
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
