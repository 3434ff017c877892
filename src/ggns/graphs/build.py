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
  (on either side of a cross type; for world edges, mesh-edge neighbours count too). In the hot path
  (training steps, rollouts) that verdict stays on the device (`NeighbourCheck`, a deferred check read
  at intervals), so the only synchronizations of a build are the radius queries' own (their edge
  counts are data).
"""
from __future__ import annotations

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from ..batch import check_batch_vectors
from ..checks import DeferredCheck, reads_cost
from ..phases import phase
from . import search
from .connectivity import Connectivity
from .types import MESH_EDGE, WORLD_EDGE


def relative_features(pos_src: Tensor, pos_dst: Tensor, edge_index: Tensor) -> Tensor:
    """[pos_src[i] - pos_dst[j], norm] per edge (i, j): [E, d + 1]."""
    rel = pos_src[edge_index[0]] - pos_dst[edge_index[1]]
    return torch.cat([rel, rel.norm(dim=1, keepdim=True)], dim=1)


def flipped_features(features: Tensor) -> Tensor:
    """`relative_features` of the flipped pairs: the opposite vector, the same norm."""
    return torch.cat([-features[:, :-1], features[:, -1:]], dim=1)


def mesh_edge_features(pos: Tensor, rest: Tensor, mesh_edges: Tensor) -> Tensor:
    """MESH_EDGE's features [Em, 2(d + 1)]: relative features of the current and of the rest positions."""
    return torch.cat([relative_features(pos, pos, mesh_edges), relative_features(rest, rest, mesh_edges)], dim=1)


def mesh_node_features(fixed: Tensor, dtype: torch.dtype, material: Tensor | None = None,
                       owner: Tensor | None = None) -> Tensor:
    """mesh.x [N, F]: the fixed flag, and with `material` [B] the Poisson ratio of each node's graph `owner` [N]."""
    x = fixed.to(dtype)[:, None]
    if material is None:
        return x
    return torch.cat([x, material.to(dtype)[owner, None]], dim=1)


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
    neighbours: NeighbourCheck | None = None,
    check_inputs: bool = True,
) -> HeteroData:
    """The batched graph of B = num_graphs states (module docstring for the layout): `node_graph`,
    then `add_mesh_edges`, then `add_radius_edges` for every edge type of `connectivity` (world edges
    filtered by `drop_mesh_pairs`), then the check of the neighbour caps: at once (ValueError), or
    recorded in `neighbours` (a `NeighbourCheck`, read later).

    mesh_pos, mesh_rest [N, d]; mesh_edges [2, Em] directed (both directions), global indices;
    fixed [N] bool; mesh_batch [N] long, sorted; collider_pos, collider_next [K, d] and
    collider_batch [K] (all None when there is no collider); points [P, d] and point_batch [P]
    (None: no points); material [B] Poisson ratios (MGN(M) node feature) or None. check_inputs: the
    value checks of the batch vectors and mesh edges (one sync; callers that checked the same
    batch before skip it).
    """
    with phase("graph construction"):
        if not connectivity.uses_points:
            points = point_batch = None
        data = node_graph(mesh_pos, fixed, mesh_batch, num_graphs, material, collider_pos, collider_next,
                          collider_batch, points, point_batch)
        _check_shapes(data, mesh_rest, mesh_edges, fixed, num_graphs)
        if check_inputs:
            check_values(data, mesh_edges, num_graphs)
        add_mesh_edges(data, mesh_edges, mesh_rest)
        most = {}  # edge type -> [largest neighbour count of a node in its radius query, its side, the node]
        for edge_type, radius in connectivity.radii().items():
            if radius > 0 and edge_type[0] in data.node_types and edge_type[2] in data.node_types \
                    and edge_type not in data.edge_types:
                most[edge_type] = add_radius_edges(data, edge_type, radius, connectivity.max_num_neighbors,
                                                   connectivity.search)
    with phase("checks"):
        checker = neighbours if neighbours is not None else NeighbourCheck(connectivity)
        checker.record(most)
        if neighbours is None:
            checker.raise_if_failed()
    return data


class NeighbourCheck:
    """The neighbour caps of many graph builds as a deferred check (`ggns.checks`): `record` keeps, on
    the device, the first build (at `step`, set by the caller) where a node had more than
    `max_num_neighbors` neighbours in a radius query; `raise_if_failed` reads it and raises a ValueError
    naming the step, the edge type, the node and its count."""

    def __init__(self, connectivity: Connectivity, what: str = "graph"):
        self.connectivity, self.what, self.step = connectivity, what, 0
        self.types = [t for t, r in connectivity.radii().items() if r > 0]
        self.check = DeferredCheck()

    def record(self, most: dict) -> None:
        """most: {edge type: [count, side (0: destination, 1: source), node]} of one build (long [3])."""
        if not most:
            return
        device = next(iter(most.values())).device
        table = torch.stack([most[t] if t in most else torch.zeros(3, dtype=torch.long, device=device)
                             for t in self.types])
        self.check.record((table[:, 0] > self.connectivity.max_num_neighbors).any(), self.step, table)

    def raise_if_failed(self) -> None:
        failure = self.check.failure()
        if failure is None:
            return
        self.check.reset()
        cap, radii = self.connectivity.max_num_neighbors, self.connectivity.radii()
        for edge_type, (count, side, node) in zip(self.types, failure.detail[0]):
            if count > cap:
                node_type = edge_type[2] if side == 0 else edge_type[0]
                where = f" at step {failure.step}" if self.what != "graph" else ""
                raise ValueError(
                    f"edge type {edge_type}{where}: {node_type} node {node} has more than max_num_neighbors={cap} "
                    f"neighbours within radius {radii[edge_type]} (found {count}); set a larger max_num_neighbors "
                    f"(e.g. {2 * count})")


def node_graph(mesh_pos: Tensor, fixed: Tensor, mesh_batch: Tensor, num_graphs: int, material: Tensor | None = None,
               collider_pos: Tensor | None = None, collider_next: Tensor | None = None,
               collider_batch: Tensor | None = None, points: Tensor | None = None,
               point_batch: Tensor | None = None) -> HeteroData:
    """The node stores (`pos`, `x`, `batch`) of B = num_graphs states, no edges: `mesh` always,
    `collider` and `point` when they have nodes (module docstring for the features)."""
    data = HeteroData()
    data.num_graphs = num_graphs
    if material is not None:
        _check_shape("material", material, (num_graphs,))
    x = mesh_node_features(fixed, mesh_pos.dtype, material, mesh_batch)
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
        data[MESH_EDGE].edge_index = mesh_edges
        data[MESH_EDGE].edge_attr = mesh_edge_features(data["mesh"].pos, mesh_rest, mesh_edges)
    return data


def drop_mesh_pairs(index: Tensor, mesh_edges: Tensor, num_nodes: int) -> Tensor:
    """The pairs of `index` [2, E] that are not mesh edges (the world-edge rule)."""
    return index[:, ~torch.isin(index[0] * num_nodes + index[1], mesh_edges[0] * num_nodes + mesh_edges[1])]


def drop_self_loops(index: Tensor, loops: int) -> Tensor:
    """The pairs of `index` [2, E] that are no self loops, in their order, given that it holds `loops` of
    them (each node found itself): a scatter to positions counted by a cumulative sum, where a boolean
    mask would read the device to size its output. A query that returned more pairs than its cap may have
    lost its own pair; then the neighbour check fails and the extra pair is cut."""
    keep = index[0] != index[1]
    size = max(index.size(1) - loops, 0)
    target = torch.where(keep, torch.cumsum(keep, 0) - 1, size).clamp(max=size)
    out = index.new_empty(2, size + 1)
    out.scatter_(1, target.expand(2, -1), index)
    return out[:, :size]


def neighbour_counts(index: Tensor, size: int) -> Tensor:
    """How often each of `size` nodes occurs in `index` [E] (long [size]): on a GPU a scatter, so no sync
    where `torch.bincount` would read the largest index back to size its output; on the CPU bincount."""
    if not reads_cost(index.device):
        return torch.bincount(index, minlength=size)
    return torch.zeros(size, dtype=torch.long, device=index.device).index_add_(0, index, torch.ones_like(index))


def add_radius_edges(data: HeteroData, edge_type: tuple[str, str, str], radius: float, max_num_neighbors: int,
                     neighbour_search: str = "auto") -> Tensor:
    """Adds the radius edges of `edge_type` (src, relation, dst) within each graph, with their
    features: for src == dst the symmetric pairs without self loops (WORLD_EDGE without the mesh
    edges already in `data`), else the pairs and their flipped copy as (dst, relation, src). Returns
    long [3]: the largest neighbour count of a node in the query (more than `max_num_neighbors` means
    edges were dropped: `NeighbourCheck` raises), the side of that node (0: dst, 1: src) and its index,
    without syncing the device. neighbour_search: `graphs.search.radius`'s choice of search."""
    src, _, dst = edge_type
    pos = {t: data[t].pos for t in (src, dst)}
    batch = {t: data[t].batch for t in (src, dst)}
    cap = max_num_neighbors + 1
    if src == dst:  # symmetric: (neighbour, query) pairs, self loops removed
        n = pos[src].size(0)
        # torch_cluster.radius_graph with its self-loop filter done here without a sync: each node finds itself
        # (so a query returns up to cap + 1 pairs, and its neighbours are one fewer)
        index = search.radius(pos[src], pos[src], radius, batch[src], batch[src], cap + 1, data.num_graphs,
                              neighbour_search).flip(0)
        counts = [neighbour_counts(index[1], n) - 1]
        index = drop_self_loops(index, n)
        if edge_type == WORLD_EDGE and MESH_EDGE in data.edge_types:
            index = drop_mesh_pairs(index, data[MESH_EDGE].edge_index, pos[src].size(0))
        edge_sets = {edge_type: index}
    else:  # one query (row 0 indexes dst, row 1 src), flipped for the reverse type
        pairs = search.radius(pos[src], pos[dst], radius, batch[src], batch[dst], cap, data.num_graphs,
                              neighbour_search)
        counts = [neighbour_counts(pairs[0], pos[dst].size(0)), neighbour_counts(pairs[1], pos[src].size(0))]
        edge_sets = {edge_type: pairs.flip(0), (dst, edge_type[1], src): pairs}
    features = None
    for et, index in edge_sets.items():
        if index.size(1) > 0:
            data[et].edge_index = index
            if features is None:
                features = relative_features(data[et[0]].pos, data[et[2]].pos, index)
            else:
                features = flipped_features(features)
            data[et].edge_attr = features
    most, at = torch.cat(counts).max(dim=0)  # no indexing by a device scalar: that would read it back
    side = (at >= counts[0].size(0)).long()
    return torch.stack([most, side, at - side * counts[0].size(0)])


def _check_shape(name: str, tensor: Tensor, shape: tuple) -> None:
    if tuple(tensor.shape) != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {tuple(tensor.shape)}")


def _check_shapes(data: HeteroData, mesh_rest: Tensor, mesh_edges: Tensor, fixed: Tensor, num_graphs: int) -> None:
    """The shapes of the inputs (host values, no sync)."""
    pos = {t: data[t].pos for t in data.node_types}
    n, d = pos["mesh"].shape
    if num_graphs < 1 or n < 1:
        raise ValueError(f"need num_graphs >= 1 and at least one mesh node, got {num_graphs} graphs and {n} nodes")
    _check_shape("mesh_rest", mesh_rest, (n, d))
    _check_shape("fixed", fixed, (n,))
    if mesh_edges.dim() != 2 or mesh_edges.size(0) != 2:
        raise ValueError(f"mesh_edges must have shape [2, E], got {tuple(mesh_edges.shape)}")
    for node_type, p in pos.items():
        if p.dim() != 2 or p.size(1) != d:
            raise ValueError(f"{node_type} positions must have shape [*, {d}], got {tuple(p.shape)}")
        _check_shape(f"{node_type} batch", data[node_type].batch, (p.size(0),))


def check_values(data: HeteroData, mesh_edges: Tensor, num_graphs: int) -> None:
    """One device sync for the value checks of a graph's inputs (`check_batch_vectors`)."""
    check_batch_vectors({t: data[t].batch for t in data.node_types}, mesh_edges, num_graphs)
