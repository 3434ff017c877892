"""Where a rollout's error lives, against what a depth camera can see of it (3D, and the 2D plate).

A point cloud samples the object's surface, so it shows a surface node's displacement along the
surface normal directly; its displacement along a flat surface (tangential) and the interior
nodes' displacements it shows only through what they do to the surface's shape. `error_shares`
splits the squared position error of the free mesh nodes of a prediction into three parts:

    surface_normal      boundary nodes, along the true state's vertex normal (area-weighted mean
                        of the outward normals of the boundary triangles at the node)
    surface_tangential  boundary nodes, the rest of their error
    interior            nodes on no boundary triangle

A grounded model whose full-rollout error with a point cloud every step stays mostly tangential
and interior has learned to read the normal part only. In 2D the "surface" is the outline (boundary
segments, the vertex normal the length-weighted mean of the outward segment normals at the node):
the plate's camera sees its whole face, but voxel centroids inside it sit on a fixed grid whatever the
mesh does, so only the outline's position is in its points, and the interior part is the error the
points can correct only through the mesh.

Not every boundary node is in view: a mesh whose wall is one element thick (the cavity) has no
interior nodes at all, yet its inner wall faces away from the cameras. Given the trajectory's point
clouds, `error_shares` also splits the same error by what the cameras saw (`VISIBILITY`). A free
node is seen at a step when some point of that step's cloud lies within `radius` of the node's
true position there (`seen_fraction`, over all T recorded steps; the data's clouds, whatever
schedule the model was rolled out under), and it is

    seen            at >= `SEEN_AT_LEAST` (half) of the steps
    sometimes_seen  at some step, but fewer
    never_seen      at no step

The default radius is `RADIUS_EDGES` (0.75) x the median over the nodes of each node's shortest
mesh edge at rest (`default_visibility_radius`; the dataset's mesh-point graph radius is not known
here): a node one element behind the surface the points lie on (the cavity's inner wall, the
tissue's first interior layer) is about its shortest edge away from it, and the points are denser
than the nodes. 0.75 x the median of all edges, diagonals included, is too wide: it counts most of
the tissue's interior nodes and nearly all the cavity's inner-wall nodes as seen (measured in
docs/sweeps.md, "Where a rollout's error lives"). Used by `python -m ggns diagnose`.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import boundary_facets, cell_edges

PARTS = ("surface_normal", "surface_tangential", "interior")
VISIBILITY = ("seen", "sometimes_seen", "never_seen")
SEEN_AT_LEAST = 0.5  # fraction of the steps a "seen" node is seen at
RADIUS_EDGES = 0.75  # the default radius in medians of the nodes' shortest rest edges


def vertex_normals(positions: np.ndarray, facets: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals [N, 3] of the triangles `facets` [F, 3] (oriented outward),
    or length-weighted ones [N, 2] of the segments `facets` [F, 2] in 2D (oriented counter-clockwise,
    `geometry.boundary_facets`); zero for nodes on no facet."""
    x = np.asarray(positions, dtype=np.float64)
    if x.shape[1] == 2:
        t = x[facets[:, 1]] - x[facets[:, 0]]
        face = np.stack([t[:, 1], -t[:, 0]], axis=1)  # length x outward normal
    else:
        face = np.cross(x[facets[:, 1]] - x[facets[:, 0]], x[facets[:, 2]] - x[facets[:, 0]])  # 2 x area x normal
    normals = np.zeros_like(x)
    for k in range(facets.shape[1]):
        np.add.at(normals, facets[:, k], face)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def default_visibility_radius(rest, cells) -> float:
    """`RADIUS_EDGES` x the median over the nodes of `cells` [C, d + 1] of each node's shortest mesh
    edge at `rest` [N, d] (module docstring)."""
    edges = cell_edges(cells)
    if not len(edges):
        raise ValueError("the default visibility radius is found from the mesh edges and this mesh has none")
    rest = np.asarray(rest, dtype=np.float64)
    length = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    shortest = np.full(len(rest), np.inf)
    for end in (0, 1):
        np.minimum.at(shortest, edges[:, end], length)
    return RADIUS_EDGES * float(np.median(shortest[np.isfinite(shortest)]))


def seen_fraction(true, points, point_offsets, radius: float) -> np.ndarray:
    """[N]: for each node, the fraction of the T steps at which some point of that step's cloud lies
    within `radius` (inclusive) of the node's true position. true [T, N, 3]; points [P, 3] and
    point_offsets [T+1] as a `Trajectory` stores them (step t owns points[offsets[t]:offsets[t+1]]);
    a step without points sees no node."""
    true = np.asarray(true, dtype=np.float64)
    points, offsets = np.asarray(points, dtype=np.float64), np.asarray(point_offsets, dtype=np.int64)
    if offsets.shape != (len(true) + 1,):
        raise ValueError(f"point_offsets must be [T+1] = [{len(true) + 1}] for {len(true)} states, got {offsets.shape}")
    if points.ndim != 2 or points.shape[1] != true.shape[-1] or offsets[0] != 0 or offsets[-1] != len(points) \
            or np.any(np.diff(offsets) < 0):
        raise ValueError(f"points {points.shape} and point_offsets (from {offsets[0]} to {offsets[-1]}) do not "
                         f"describe per-step clouds of {true.shape[-1]}D points")
    if not radius > 0:
        raise ValueError(f"the visibility radius must be positive, got {radius}")
    seen = np.zeros(true.shape[1], dtype=np.int64)
    for t in range(len(true)):
        cloud = points[offsets[t] : offsets[t + 1]]
        if len(cloud):
            distance, _ = cKDTree(cloud).query(true[t], k=1, distance_upper_bound=np.nextafter(radius, np.inf))
            seen += distance <= radius
    return seen / len(true)


def normal_tangential(error: np.ndarray, positions: np.ndarray, facets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A state's error per node split along the surface: (normal, tangential) squared errors [N], the
    error's square along the node's vertex normal (`vertex_normals` of `positions` [N, d] and the boundary
    `facets`) and the rest of |error|^2 [N, d]. Meaningful on surface nodes."""
    normal = (error * vertex_normals(positions, facets)).sum(axis=1) ** 2
    return normal, (error ** 2).sum(axis=1) - normal


def error_shares(pred, true, rest, cells, fixed, points=None, point_offsets=None,
                 radius: float | None = None) -> dict[str, float]:
    """Squared error of the free nodes over the states 1..T-1 of a prediction, split into `PARTS`
    (module docstring): {part: mean squared error per free node and coordinate, part + "_share": its
    fraction of the total}. pred, true [T, N, d] (d = 2 or 3); rest [N, d]; cells [C, d + 1]
    (triangles in 2D, tetrahedra in 3D); fixed [N] bool.

    With the trajectory's `points` and `point_offsets` (`seen_fraction`), also split into the
    `VISIBILITY` groups of the free nodes: group and group + "_share" as for a part (the groups,
    like the parts, add up to the total), group + "_nodes": its free node count, group +
    "_node_mse": mean squared error per node of the group and coordinate (nan for an empty group),
    and "visibility_radius": the radius used (default: `default_visibility_radius`)."""
    pred, true = np.asarray(pred, dtype=np.float64), np.asarray(true, dtype=np.float64)
    if pred.shape != true.shape or pred.ndim != 3 or pred.shape[-1] not in (2, 3):
        raise ValueError(f"pred {pred.shape} and true {true.shape} must both be [T, N, 2] or [T, N, 3]")
    if len(pred) < 2:
        raise ValueError("need at least two states (the first one is not predicted)")
    dim = pred.shape[-1]
    kind = "tetrahedra" if dim == 3 else "triangles"
    cells, fixed = np.asarray(cells, dtype=np.int64), np.asarray(fixed, dtype=bool)
    if cells.ndim != 2 or cells.shape[1] != dim + 1:
        raise ValueError(f"cells of a {dim}D mesh must be {kind} [C, {dim + 1}], got {cells.shape}")
    if not len(cells):
        raise ValueError(f"the surface is found from the {kind} and this mesh has none (the authors' 3D "
                         "datasets hold no volume cells, docs/dataset_format.md)")
    if fixed.shape != (pred.shape[1],):
        raise ValueError(f"fixed must be [{pred.shape[1]}], got {fixed.shape}")
    if (points is None) != (point_offsets is None):
        raise ValueError("the visibility split needs both points and point_offsets")
    facets = boundary_facets(cells, rest)
    surface = np.zeros(len(fixed), dtype=bool)
    surface[np.unique(facets)] = True
    free = ~fixed
    if not free.any():
        raise ValueError("every node is fixed: there is no error to split")
    sums = dict.fromkeys(PARTS, 0.0)
    for t in range(1, len(pred)):
        error = pred[t] - true[t]
        normal, tangential = normal_tangential(error, true[t], facets)
        on, inside = surface & free, ~surface & free
        sums["surface_normal"] += float(normal[on].sum())
        sums["surface_tangential"] += float(tangential[on].sum())
        sums["interior"] += float((error[inside] ** 2).sum())
    steps = len(pred) - 1
    count = steps * int(free.sum()) * dim
    total = sum(sums.values())
    out = {part: value / count for part, value in sums.items()}
    out.update({f"{part}_share": (value / total if total > 0 else 0.0) for part, value in sums.items()})
    if points is None:
        return out

    radius = default_visibility_radius(rest, cells) if radius is None else float(radius)
    fraction = seen_fraction(true, points, point_offsets, radius)
    groups = {"seen": fraction >= SEEN_AT_LEAST, "never_seen": fraction == 0}
    groups["sometimes_seen"] = ~groups["seen"] & ~groups["never_seen"]
    per_node = ((pred[1:] - true[1:]) ** 2).sum(axis=(0, 2))  # [N], over the predicted states and coordinates
    group_sums = {g: float(per_node[groups[g] & free].sum()) for g in VISIBILITY}
    group_total = sum(group_sums.values())
    for g in VISIBILITY:
        nodes = int((groups[g] & free).sum())
        out[g] = group_sums[g] / count
        out[f"{g}_share"] = group_sums[g] / group_total if group_total > 0 else 0.0
        out[f"{g}_nodes"] = nodes
        out[f"{g}_node_mse"] = group_sums[g] / (steps * nodes * dim) if nodes else float("nan")
    out["visibility_radius"] = radius
    return out
