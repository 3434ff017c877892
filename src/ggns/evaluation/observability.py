"""Where a 3D rollout's error lives, against what a depth camera can see of it.

A point cloud samples the object's surface, so it shows a surface node's displacement along the
surface normal directly; its displacement along a flat surface (tangential) and the interior
nodes' displacements it shows only through what they do to the surface's shape. `error_shares`
splits the squared position error of the free mesh nodes of a prediction into three parts:

    surface_normal      boundary nodes, along the true state's vertex normal (area-weighted mean
                        of the outward normals of the boundary triangles at the node)
    surface_tangential  boundary nodes, the rest of their error
    interior            nodes on no boundary triangle

A grounded model whose full-rollout error with a point cloud every step stays mostly tangential
and interior has learned to read the normal part only. Used by `python -m ggns diagnose`.
"""
from __future__ import annotations

import numpy as np

from ..geometry import boundary_facets

PARTS = ("surface_normal", "surface_tangential", "interior")


def vertex_normals(positions: np.ndarray, facets: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals [N, 3] of the triangles `facets` [F, 3] (oriented outward);
    zero for nodes on no facet."""
    x = np.asarray(positions, dtype=np.float64)
    face = np.cross(x[facets[:, 1]] - x[facets[:, 0]], x[facets[:, 2]] - x[facets[:, 0]])  # 2 x area x normal
    normals = np.zeros_like(x)
    for k in range(3):
        np.add.at(normals, facets[:, k], face)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def error_shares(pred, true, rest, cells, fixed) -> dict[str, float]:
    """Squared error of the free nodes over the states 1..T-1 of a 3D prediction, split into
    `PARTS` (module docstring): {part: mean squared error per free node and coordinate, part +
    "_share": its fraction of the total}. pred, true [T, N, 3]; rest [N, 3]; cells [C, 4];
    fixed [N] bool."""
    pred, true = np.asarray(pred, dtype=np.float64), np.asarray(true, dtype=np.float64)
    if pred.shape != true.shape or pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"pred {pred.shape} and true {true.shape} must both be [T, N, 3]")
    if len(pred) < 2:
        raise ValueError("need at least two states (the first one is not predicted)")
    cells, fixed = np.asarray(cells, dtype=np.int64), np.asarray(fixed, dtype=bool)
    if cells.ndim != 2 or cells.shape[1] != 4:
        raise ValueError(f"cells must be tetrahedra [C, 4], got {cells.shape}")
    if not len(cells):
        raise ValueError("the surface is found from the tetrahedra and this mesh has none (the authors' 3D "
                         "datasets hold no volume cells, docs/dataset_format.md)")
    if fixed.shape != (pred.shape[1],):
        raise ValueError(f"fixed must be [{pred.shape[1]}], got {fixed.shape}")
    facets = boundary_facets(cells, rest)
    surface = np.zeros(len(fixed), dtype=bool)
    surface[np.unique(facets)] = True
    free = ~fixed
    if not free.any():
        raise ValueError("every node is fixed: there is no error to split")
    sums = dict.fromkeys(PARTS, 0.0)
    for t in range(1, len(pred)):
        error = pred[t] - true[t]
        normal = (error * vertex_normals(true[t], facets)).sum(axis=1)
        on, inside = surface & free, ~surface & free
        sums["surface_normal"] += float((normal[on] ** 2).sum())
        sums["surface_tangential"] += float(((error[on] ** 2).sum(axis=1) - normal[on] ** 2).sum())
        sums["interior"] += float((error[inside] ** 2).sum())
    count = (len(pred) - 1) * int(free.sum()) * 3
    total = sum(sums.values())
    out = {part: value / count for part, value in sums.items()}
    out.update({f"{part}_share": (value / total if total > 0 else 0.0) for part, value in sums.items()})
    return out
