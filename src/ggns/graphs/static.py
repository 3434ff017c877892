"""Graph building with static shapes: the model input of a state built by tensor operations on buffers of
fixed capacity, with no host read, so that a whole step (graph, model, integration, checks) can be
captured as one CUDA graph or compiled with `torch.compile(fullgraph=True, dynamic=False)`.

The eager builder (`graphs.build`) makes a graph whose edge counts are data (a radius query's pairs),
and a point cloud whose size changes with every step. Here every shape is a host number fixed in
advance (`StaticLayout`):
- node rows: the batch's mesh nodes and collider vertices, and `points` rows for the point cloud of
  one step (the largest cloud of the batch's steps; the rest are padding rows whose batch value is
  `num_graphs`, which neither find nor are found);
- per radius edge type an edge capacity: the static search (`graphs.search`) gives each query at most
  `max_num_neighbors` neighbours in a fixed-width row, and `compact` packs the valid pairs into the
  capacity's prefix with a mask (`edge_mask`: the core sends a masked edge's message to a sink row and
  counts it in no mean, `models.core`), so the model's output equals its output on the eager graph up to
  the rounding of sums taken in another order.
The numbers a step cannot know without reading the device are returned as tensors (`StaticChecks`):
how many pairs each edge type needed (more than its capacity: the caller grows it and repeats the step)
and the largest neighbour count of a node (more than `max_num_neighbors`: the neighbour check's error).

A type absent from a scene (no collider) is absent from the layout; the point type is present in every
step of a model that uses points, with all its edges masked where a graph has no cloud at that step.

`TensorGraph` is the part of PyG's HeteroData that the models read (`graph[type].x`, `.edge_index`,
`.edge_attr`, `.edge_mask`, `node_types`, `edge_types`, `num_graphs`) as plain attributes, which
`torch.compile` traces (HeteroData's storage machinery it does not).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from ..phases import phase
from .build import flipped_features, mesh_edge_features, mesh_node_features, relative_features
from .connectivity import Connectivity
from .search import compact, static_radius
from .types import EDGE_TYPES, MESH_EDGE, WORLD_EDGE

EdgeType = tuple[str, str, str]


class TensorStore:
    """The tensors of one node or edge type, as attributes (`"edge_mask" in store` as in PyG)."""

    def __init__(self, **tensors: Tensor):
        self.__dict__.update(tensors)

    def __contains__(self, key: str) -> bool:
        return key in self.__dict__

    @property
    def num_nodes(self) -> int:
        return self.x.size(0)


class TensorGraph:
    """A batched heterogeneous graph as the models read it (module docstring)."""

    def __init__(self, num_graphs: int):
        self.num_graphs = num_graphs
        self.stores: dict = {}

    def __getitem__(self, key) -> TensorStore:
        return self.stores[key]

    def __contains__(self, key) -> bool:
        return key in self.stores

    def add(self, key, **tensors: Tensor) -> TensorStore:
        self.stores[key] = TensorStore(**tensors)
        return self.stores[key]

    @property
    def node_types(self) -> list[str]:
        return [k for k in self.stores if isinstance(k, str)]

    @property
    def edge_types(self) -> list[EdgeType]:
        return [k for k in self.stores if isinstance(k, tuple)]


def round_up(need: int, margin: float = 1.25, multiple: int = 64) -> int:
    """A capacity for `need` rows: need x margin rounded up to a multiple of `multiple` (at least one)."""
    return max(multiple, int(math.ceil(need * margin / multiple)) * multiple)


@dataclass(frozen=True)
class StaticLayout:
    """The host numbers that fix every shape of a static graph (module docstring).

    num_graphs: B; nodes: {node type: rows} (mesh and collider exact, point a capacity); spans: {node
    type: rows of the largest graph} (the search's candidates per query); edges: {radius edge type:
    capacity} for the queried direction of each type (a cross type's flipped copy shares it)."""

    num_graphs: int
    nodes: dict = field(hash=False)
    spans: dict = field(hash=False)
    edges: dict = field(hash=False)

    def capacity_tensor(self, device=None) -> Tensor:
        """The edge capacities as a long tensor [types] (what a step compares its needed pairs with)."""
        return torch.tensor(list(self.edges.values()), dtype=torch.long, device=device)

    def grown(self, needed: dict[EdgeType, int], margin: float = 1.25) -> StaticLayout:
        """The layout with every edge capacity that `needed` exceeds grown to hold it with a margin."""
        edges = {t: max(c, round_up(needed.get(t, 0), margin)) if needed.get(t, 0) > c else c
                 for t, c in self.edges.items()}
        return replace(self, edges=edges)


def batch_layout(batch, connectivity: Connectivity, uses_points: bool, edges: dict | None = None,
                 size=lambda n: n) -> StaticLayout:
    """The static layout of `batch` (a `TrajectoryBatch`; host numbers only): node rows and the largest graph
    of each node type from its host offsets, each passed through `size` (the rollouts' exact counts, the
    training's buckets), and the edge capacities `edges` of the queried types (0 for a type not in it)."""
    def largest(offsets) -> int:
        return max(1, max(b - a for a, b in zip(offsets, offsets[1:])))

    nodes, spans = {"mesh": size(batch.rest.size(0))}, {"mesh": size(largest(batch.node_offsets))}
    if batch.collider is not None:
        nodes["collider"], spans["collider"] = size(batch.collider.size(1)), size(largest(batch.collider_range))
    if uses_points:
        clouds = [batch.point_range(t) for t in range(batch.num_steps)]
        nodes["point"] = size(max(1, max(o[-1] for o in clouds)))
        spans["point"] = size(max(largest(o) for o in clouds))
    types = queried_types(connectivity, nodes)
    return StaticLayout(batch.num_graphs, nodes, spans, {t: (edges or {}).get(t, 0) for t in types})


def queried_types(connectivity: Connectivity, node_types) -> list[EdgeType]:
    """The radius edge types that a graph with `node_types` builds by a query, in `EDGE_TYPES` order: every
    type with a radius > 0 whose ends exist, a cross type once (its flipped twin comes with it)."""
    radii, out = connectivity.radii(), []
    for t in EDGE_TYPES:
        if t == MESH_EDGE or radii[t] <= 0 or t[0] not in node_types or t[2] not in node_types:
            continue
        if t[0] != t[2] and (t[2], t[1], t[0]) in out:
            continue
        out.append(t)
    return out


@dataclass
class StaticChecks:
    """What one static build could not check without a read (tensors): needed [types] long, the pairs
    each queried type found (compare with its capacity); most [types, 3] long, per type the largest
    neighbour count of a node, its side (0: the query side, the type's destination; 1: the source) and
    its row (`graphs.build.NeighbourCheck`'s table)."""

    needed: Tensor
    most: Tensor


def static_graph(layout: StaticLayout, connectivity: Connectivity, mesh_pos: Tensor, mesh_rest: Tensor,
                 mesh_edges: Tensor, fixed: Tensor, mesh_batch: Tensor, collider_pos: Tensor | None,
                 collider_next: Tensor | None, collider_batch: Tensor | None, points: Tensor | None,
                 point_batch: Tensor | None, use_points: Tensor | None, material: Tensor | None = None,
                 mesh_edge_mask: Tensor | None = None) -> tuple[TensorGraph, StaticChecks]:
    """The static graph of B = layout.num_graphs states (module docstring): the eager builder's features
    and edge rules (`graphs.build`) on fixed-capacity buffers.

    mesh_pos, mesh_rest [N, d]; mesh_edges [2, Em]; fixed [N] bool; mesh_batch [N] (sorted; padding rows,
    if any, carry B); collider_pos, collider_next [K, d], collider_batch [K] (None: no collider); points
    [P, d] and point_batch [P] (sorted, padding B; P = layout.nodes["point"]) with use_points [B] bool
    (which graphs see their cloud in this step), None for a model without points; material [B] or None;
    mesh_edge_mask [Em] bool: which mesh edges are real (padded batches), None: all.
    """
    with phase("graph construction"):
        return _static_graph(layout, connectivity, mesh_pos, mesh_rest, mesh_edges, fixed, mesh_batch, collider_pos,
                             collider_next, collider_batch, points, point_batch, use_points, material, mesh_edge_mask)


def _static_graph(layout, connectivity, mesh_pos, mesh_rest, mesh_edges, fixed, mesh_batch, collider_pos,
                  collider_next, collider_batch, points, point_batch, use_points, material, mesh_edge_mask):
    B = layout.num_graphs
    graph = TensorGraph(B)
    x = mesh_node_features(fixed, mesh_pos.dtype, material, mesh_batch.clamp(max=B - 1))
    nodes = {"mesh": (mesh_pos, mesh_batch)}
    graph.add("mesh", x=x, pos=mesh_pos, batch=mesh_batch)
    if "collider" in layout.nodes:
        graph.add("collider", x=collider_next - collider_pos, pos=collider_pos, batch=collider_batch)
        nodes["collider"] = (collider_pos, collider_batch)
    if "point" in layout.nodes:
        graph.add("point", x=points.new_zeros(points.size(0), 0), pos=points, batch=point_batch)
        nodes["point"] = (points, point_batch)
    mesh_features = mesh_edge_features(mesh_pos, mesh_rest, mesh_edges)
    if mesh_edge_mask is None:
        graph.add(MESH_EDGE, edge_index=mesh_edges, edge_attr=mesh_features)
    else:
        graph.add(MESH_EDGE, edge_index=mesh_edges, edge_attr=mesh_features, edge_mask=mesh_edge_mask)
    radii, cap = connectivity.radii(), connectivity.max_num_neighbors
    needed, most = [], []
    for edge_type, capacity in layout.edges.items():
        src, _, dst = edge_type
        (x_pos, x_batch), (y_pos, y_batch) = nodes[src], nodes[dst]
        active = y_batch < B
        if "point" in (src, dst):  # the graphs that see their cloud in this step
            active = active & use_points[y_batch.clamp(max=B - 1)]
        found = static_radius(x_pos, y_pos, radii[edge_type], x_batch, y_batch, B, cap, layout.spans[src],
                              exclude_self=src == dst,
                              exclude=mesh_edges if edge_type == WORLD_EDGE else None)
        found.mask &= active[:, None]
        found.count = found.count * active
        index, mask, total = compact(found, capacity)
        features = relative_features(x_pos, y_pos, index)
        graph.add(edge_type, edge_index=index, edge_attr=features, edge_mask=mask)
        query_most, query_at = found.count.max(dim=0)
        if src != dst:
            graph.add((dst, edge_type[1], src), edge_index=index.flip(0),
                      edge_attr=flipped_features(features), edge_mask=mask)
            per_source = torch.zeros(x_pos.size(0), dtype=torch.long, device=x_pos.device).index_add_(
                0, index[0], mask.long())
            source_most, source_at = per_source.max(dim=0)
            side = (source_most > query_most).long()
            row = torch.stack([torch.maximum(query_most, source_most), side,
                               torch.where(side.bool(), source_at, query_at)])
        else:
            row = torch.stack([query_most, torch.zeros_like(query_most), query_at])
        needed.append(total)
        most.append(row)
    if not needed:
        empty = mesh_batch.new_zeros(0)
        return graph, StaticChecks(empty, empty.view(0, 3))
    return graph, StaticChecks(torch.stack(needed), torch.stack(most))


def measure_pairs(batch, connectivity: Connectivity, layout: StaticLayout) -> dict[EdgeType, int]:
    """{queried edge type: the most pairs one state of `batch` (a `TrajectoryBatch`) has}, over its true
    states with every point cloud, by the static search (one read): where edge capacities start."""
    radii, cap, counts = connectivity.radii(), connectivity.max_num_neighbors, []
    if not layout.edges:
        return {}
    for t in range(batch.num_steps):
        nodes = {"mesh": (batch.positions[t], batch.mesh_batch)}
        if "collider" in layout.nodes:
            nodes["collider"] = (batch.collider[t], batch.collider_batch)
        if "point" in layout.nodes:
            nodes["point"] = (batch.points[t], batch.point_batch[t])
        for edge_type in layout.edges:
            (xp, xb), (yp, yb) = nodes[edge_type[0]], nodes[edge_type[2]]
            found = static_radius(xp, yp, radii[edge_type], xb, yb, layout.num_graphs, cap, layout.spans[edge_type[0]],
                                  exclude_self=edge_type[0] == edge_type[2],
                                  exclude=batch.edges if edge_type == WORLD_EDGE else None)
            counts.append(found.mask.sum())
    most = torch.stack(counts).view(batch.num_steps, len(layout.edges)).amax(0).tolist()
    return dict(zip(layout.edges, most))


def fill_clouds(batch, points: Tensor, point_batch: Tensor) -> None:
    """Copy the point clouds of every step of `batch` (a `TrajectoryBatch`) into buffers points [T, P, d] and
    point_batch [T, P]: each step's cloud in the first rows, the rest padding rows of graph B (zeros)."""
    points.zero_()
    point_batch.fill_(batch.num_graphs)
    for t in range(batch.num_steps):
        n = batch.point_range(t)[-1]
        points[t, :n].copy_(batch.points[t])
        point_batch[t, :n].copy_(batch.point_batch[t])
