"""Batched graph construction: B simulation states (mesh, collider, optional point cloud) as one
heterogeneous graph, built with tensor operations on the inputs' device (CPU or CUDA).

Conventions (see `ggns.graphs.types` for the vocabulary):
- A node store `mesh` always exists; `collider` and `point` exist only when they have nodes.
  Every store has `.pos` [n, d] (current positions), `.x` [n, F] and `.batch` [n] (graph of each
  node, sorted). mesh.x = [fixed flag] (+ [Poisson ratio of its graph] for MGN(M)), F = 1 or 2;
  collider.x = velocity (next - current position), F = d; point.x has F = 0.
- An edge type exists only when its radius is > 0, both node types exist and it has edges.
  Points are left out altogether when no point edge type has a radius > 0 (e.g. MGN).
  `.edge_index` [2, E]: row 0 indexes the source node type, row 1 the destination node type;
  messages flow source -> destination. Radius edges never cross graphs and have no self loops.
- `.edge_attr` columns: [pos[src] - pos[dst] (d), its norm (1)] on every edge type; MESH_EDGE
  appends [rest[src] - rest[dst] (d), its norm (1)] from the rest (mesh-space) state: 2(d+1).
- Cross-type edge sets are exactly symmetric: (B, near, A) holds the flipped pairs of (A, near, B).
- World edges (WORLD_EDGE): mesh pairs within `world` radius that are not mesh edges.
- Radius queries return at most `max_num_neighbors` neighbours per node; the builder raises
  instead of dropping edges when any node has more within the radius of any radius edge type
  (on either side of a cross type; for world edges, mesh-edge neighbours count too).
"""
from __future__ import annotations

import torch
import torch_cluster
from torch import Tensor
from torch_geometric.data import HeteroData

from .connectivity import Connectivity
from .types import MESH_EDGE, WORLD_EDGE


def relative_features(pos_src: Tensor, pos_dst: Tensor, edge_index: Tensor) -> Tensor:
    """[pos_src[i] - pos_dst[j], norm] per edge (i, j): [E, d + 1]."""
    rel = pos_src[edge_index[0]] - pos_dst[edge_index[1]]
    return torch.cat([rel, rel.norm(dim=1, keepdim=True)], dim=1)


def build_graph(
    mesh_pos: Tensor,
    mesh_rest: Tensor,
    mesh_edges: Tensor,
    fixed: Tensor,
    mesh_batch: Tensor,
    collider_pos: Tensor | None,
    collider_next: Tensor | None,
    collider_batch: Tensor | None,
    points: Tensor | None,
    point_batch: Tensor | None,
    connectivity: Connectivity,
    num_graphs: int,
    material: Tensor | None = None,
) -> HeteroData:
    """The batched graph of B = num_graphs states (module docstring for the layout): `node_graph`,
    then `add_mesh_edges`, then `add_radius_edges` for every edge type of `connectivity` (world edges
    filtered by `drop_mesh_pairs`), then one check of the neighbour caps (`check_neighbour_caps`).

    mesh_pos, mesh_rest [N, d]; mesh_edges [2, Em] directed (both directions), global indices;
    fixed [N] bool; mesh_batch [N] long, sorted; collider_pos, collider_next [K, d] and
    collider_batch [K] (all None when there is no collider); points [P, d] and point_batch [P]
    (None: no points); material [B] Poisson ratios (MGN(M) node feature) or None.
    """
    if not connectivity.uses_points:
        points = point_batch = None
    data = node_graph(mesh_pos, fixed, mesh_batch, num_graphs, material, collider_pos, collider_next, collider_batch,
                      points, point_batch)
    _check_inputs(data, mesh_rest, mesh_edges, fixed, num_graphs)
    add_mesh_edges(data, mesh_edges, mesh_rest)
    most = {}  # edge type -> largest neighbour count of a node in its radius query (0-d tensor)
    for edge_type, radius in connectivity.radii().items():
        if radius > 0 and edge_type[0] in data.node_types and edge_type[2] in data.node_types \
                and edge_type not in data.edge_types:
            most[edge_type] = add_radius_edges(data, edge_type, radius, connectivity.max_num_neighbors)
    check_neighbour_caps(most, connectivity)
    return data


def node_graph(mesh_pos: Tensor, fixed: Tensor, mesh_batch: Tensor, num_graphs: int, material: Tensor | None = None,
               collider_pos: Tensor | None = None, collider_next: Tensor | None = None,
               collider_batch: Tensor | None = None, points: Tensor | None = None,
               point_batch: Tensor | None = None) -> HeteroData:
    """The node stores (`pos`, `x`, `batch`) of B = num_graphs states, no edges: `mesh` always,
    `collider` and `point` when they have nodes (module docstring for the features)."""
    data = HeteroData()
    data.num_graphs = num_graphs
    x = fixed.to(mesh_pos.dtype)[:, None]
    if material is not None:
        _check_shape("material", material, (num_graphs,))
        x = torch.cat([x, material.to(mesh_pos.dtype)[mesh_batch, None]], dim=1)
    data["mesh"].pos, data["mesh"].x, data["mesh"].batch = mesh_pos, x, mesh_batch
    if collider_pos is not None and collider_pos.size(0) > 0:
        if collider_next is None or collider_batch is None:
            raise ValueError("collider_pos needs collider_next and collider_batch")
        _check_shape("collider_next", collider_next, collider_pos.shape)
        data["collider"].pos, data["collider"].batch = collider_pos, collider_batch
        data["collider"].x = collider_next - collider_pos
    if points is not None and points.size(0) > 0:
        if point_batch is None:
            raise ValueError("points need point_batch")
        data["point"].pos, data["point"].batch = points, point_batch
        data["point"].x = points.new_zeros(points.size(0), 0)
    return data


def add_mesh_edges(data: HeteroData, mesh_edges: Tensor, mesh_rest: Tensor) -> HeteroData:
    """Adds MESH_EDGE (directed mesh edges [2, Em]) with its features from the current and the rest
    positions [N, d], when there are any."""
    if mesh_edges.size(1) > 0:
        pos = data["mesh"].pos
        data[MESH_EDGE].edge_index = mesh_edges
        data[MESH_EDGE].edge_attr = torch.cat(
            [relative_features(pos, pos, mesh_edges), relative_features(mesh_rest, mesh_rest, mesh_edges)], dim=1
        )
    return data


def drop_mesh_pairs(index: Tensor, mesh_edges: Tensor, num_nodes: int) -> Tensor:
    """The pairs of `index` [2, E] that are not mesh edges (the world-edge rule)."""
    return index[:, ~torch.isin(index[0] * num_nodes + index[1], mesh_edges[0] * num_nodes + mesh_edges[1])]


def add_radius_edges(data: HeteroData, edge_type: tuple[str, str, str], radius: float, max_num_neighbors: int) -> Tensor:
    """Adds the radius edges of `edge_type` (src, relation, dst) within each graph, with their
    features: for src == dst the symmetric pairs without self loops (WORLD_EDGE without the mesh
    edges already in `data`), else the pairs and their flipped copy as (dst, relation, src). Returns
    the largest neighbour count of a node in the query (0-d tensor; more than `max_num_neighbors`
    means edges were dropped: `check_neighbour_caps` raises), without syncing the device."""
    src, _, dst = edge_type
    pos = {t: data[t].pos for t in (src, dst)}
    batch = {t: data[t].batch for t in (src, dst)}
    cap = max_num_neighbors + 1
    if src == dst:  # symmetric: (neighbour, query) pairs, self loops removed
        index = torch_cluster.radius_graph(pos[src], radius, batch[src], max_num_neighbors=cap, batch_size=data.num_graphs)
        counts = [torch.bincount(index[1], minlength=pos[src].size(0))]
        if edge_type == WORLD_EDGE and MESH_EDGE in data.edge_types:
            index = drop_mesh_pairs(index, data[MESH_EDGE].edge_index, pos[src].size(0))
        edge_sets = {edge_type: index}
    else:  # one query (row 0 indexes dst, row 1 src), flipped for the reverse type
        pairs = torch_cluster.radius(pos[src], pos[dst], radius, batch[src], batch[dst], max_num_neighbors=cap,
                                     batch_size=data.num_graphs)
        counts = [torch.bincount(pairs[0], minlength=pos[dst].size(0)), torch.bincount(pairs[1], minlength=pos[src].size(0))]
        edge_sets = {edge_type: pairs.flip(0), (dst, edge_type[1], src): pairs}
    for et, index in edge_sets.items():
        if index.size(1) > 0:
            data[et].edge_index = index
            data[et].edge_attr = relative_features(data[et[0]].pos, data[et[2]].pos, index)
    return torch.cat(counts).max()


def _check_shape(name: str, tensor: Tensor, shape: tuple) -> None:
    if tuple(tensor.shape) != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {tuple(tensor.shape)}")


def _check_inputs(data: HeteroData, mesh_rest: Tensor, mesh_edges: Tensor, fixed: Tensor, num_graphs: int) -> None:
    """Shapes on the host, then one device sync for the value checks (sorted batch vectors in
    [0, num_graphs), mesh edges in range and inside one graph)."""
    pos = {t: data[t].pos for t in data.node_types}
    batch = {t: data[t].batch for t in data.node_types}
    n, d = pos["mesh"].shape
    if num_graphs < 1 or n < 1:
        raise ValueError(f"need num_graphs >= 1 and at least one mesh node, got {num_graphs} graphs and {n} nodes")
    _check_shape("mesh_rest", mesh_rest, (n, d))
    _check_shape("fixed", fixed, (n,))
    if mesh_edges.dim() != 2 or mesh_edges.size(0) != 2:
        raise ValueError(f"mesh_edges must have shape [2, E], got {tuple(mesh_edges.shape)}")
    checks = {}
    for node_type, p in pos.items():
        if p.dim() != 2 or p.size(1) != d:
            raise ValueError(f"{node_type} positions must have shape [*, {d}], got {tuple(p.shape)}")
        b = batch[node_type]
        _check_shape(f"{node_type} batch", b, (p.size(0),))
        checks[f"{node_type} batch sorted and in [0, {num_graphs})"] = (
            (b[1:] >= b[:-1]).all() & (b.min() >= 0) & (b.max() < num_graphs)
        )
    if mesh_edges.size(1) > 0:
        inside = (mesh_edges.min() >= 0) & (mesh_edges.max() < n)
        ends = batch["mesh"][mesh_edges.clamp(0, n - 1)]
        checks[f"mesh_edges in [0, {n}) and inside one graph"] = inside & (ends[0] == ends[1]).all()
    failed = [name for name, ok in zip(checks, torch.stack(list(checks.values())).tolist()) if not ok]
    if failed:
        raise ValueError(f"invalid graph inputs, expected: {'; '.join(failed)}")


def check_neighbour_caps(most: dict, connectivity: Connectivity) -> None:
    """Raise when a radius query may have dropped neighbours: `most` maps edge types to the largest
    neighbour count `add_radius_edges` returned (one device sync for all)."""
    if not most:
        return
    cap, radii = connectivity.max_num_neighbors, connectivity.radii()
    for edge_type, count in zip(most, torch.stack(list(most.values())).tolist()):
        if count > cap:
            raise ValueError(
                f"edge type {edge_type}: a node has more than max_num_neighbors={cap} neighbours within radius "
                f"{radii[edge_type]} (found {count}); set a larger max_num_neighbors (e.g. {2 * count})"
            )
