"""Static-shape graphs: a built graph copied into buffers whose shapes stay the same from step to step.

A radius graph's edge counts change with every state, and a point cloud's size with every step, so the
tensors of consecutive graphs have different shapes, which a captured CUDA graph (or a compiled step
with static shapes) cannot take. `StaticGraph` holds, for every node and edge type a model accepts,
buffers of a fixed capacity: a graph is copied into their first rows and the rest is padding that
changes nothing: padded edges carry `edge_mask` False (the core sends their messages to a sink row and
counts them in no mean, `models.core`), padded nodes have no unmasked edge. So the model's output on
the static graph equals its output on the graph itself (up to float rounding of larger products). A
type absent from a graph (no point cloud at this step) is present with every edge masked.

Capacities start at what the first graph needs times `margin` (rounded up to a multiple of
`multiple`); a later graph that needs more grows them, which the caller learns from `fill`'s return
value (a captured step is then captured anew). Node counts of mesh and collider are fixed for a batch;
points (whose counts change) are padded like edges.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

EdgeType = tuple[str, str, str]


def _capacity(need: int, margin: float, multiple: int) -> int:
    return max(multiple, int(math.ceil(need * margin / multiple)) * multiple)


class StaticGraph:
    """Fixed-capacity buffers for graphs of the node types `node_dims` {type: feature width} and edge
    types `edge_dims` {type: feature width} (a model's input widths) on `device`."""

    def __init__(self, node_dims: dict[str, int], edge_dims: dict[EdgeType, int], device,
                 margin: float = 1.25, multiple: int = 64):
        if margin < 1 or multiple < 1:
            raise ValueError(f"need margin >= 1 and multiple >= 1, got {margin}, {multiple}")
        self.node_dims, self.edge_dims = dict(node_dims), dict(edge_dims)
        self.device, self.margin, self.multiple = torch.device(device), margin, multiple
        self.graph: HeteroData | None = None

    def capacities(self) -> dict:
        """{node or edge type: rows} of the current buffers ({} before the first `fill`)."""
        if self.graph is None:
            return {}
        return {**{t: self.graph[t].num_nodes for t in self.node_dims},
                **{t: self.graph[t].edge_index.size(1) for t in self.edge_dims}}

    def _needs(self, graph: HeteroData) -> dict:
        unknown = [t for t in (*graph.node_types, *graph.edge_types) if t not in self.node_dims and
                   t not in self.edge_dims]
        if unknown:
            raise KeyError(f"types {unknown} of the graph are not among the model's {list(self.node_dims)} + "
                           f"{list(self.edge_dims)}")
        nodes = {t: graph[t].num_nodes if t in graph.node_types else 0 for t in self.node_dims}
        edges = {t: graph[t].edge_index.size(1) if t in graph.edge_types else 0 for t in self.edge_dims}
        return {**nodes, **edges}

    def _allocate(self, needs: dict, fixed_nodes: dict) -> None:
        old = self.capacities()
        data = HeteroData()
        for t, width in self.node_dims.items():
            rows = fixed_nodes[t] if t in fixed_nodes else max(old.get(t, 0), _capacity(needs[t], self.margin,
                                                                                         self.multiple))
            data[t].x = torch.zeros(rows, width, device=self.device)
        for t, width in self.edge_dims.items():
            rows = max(old.get(t, 0), _capacity(needs[t], self.margin, self.multiple))
            data[t].edge_index = torch.zeros(2, rows, dtype=torch.long, device=self.device)
            data[t].edge_attr = torch.zeros(rows, width, device=self.device)
            data[t].edge_mask = torch.zeros(rows, dtype=torch.bool, device=self.device)
        self.graph = data

    def fill(self, graph: HeteroData) -> tuple[HeteroData, bool]:
        """Copy `graph` into the buffers: (the static graph, True when the buffers were (re)allocated: a
        first graph, other mesh or collider counts, or more rows than a capacity holds)."""
        needs = self._needs(graph)
        # mesh and collider counts are the batch's: a change means another batch, not growth
        fixed = {t: needs[t] for t in ("mesh", "collider") if t in self.node_dims}
        caps = self.capacities()
        fresh = (not caps or any(caps[t] != n for t, n in fixed.items())
                 or any(needs[t] > caps[t] for t in needs if t not in fixed))
        if fresh:
            self._allocate(needs, fixed)
        static = self.graph
        for t in self.node_dims:
            if t in graph.node_types and static[t].x.shape[1]:
                static[t].x[:needs[t]].copy_(graph[t].x)
        for t in self.edge_dims:
            n, store = needs[t], static[t]
            if n:
                store.edge_index[:, :n].copy_(graph[t].edge_index)
                store.edge_attr[:n].copy_(graph[t].edge_attr)
            store.edge_mask[:n].fill_(True)
            store.edge_mask[n:].fill_(False)
        static.num_graphs = graph.num_graphs
        return static, fresh


def unmasked(store) -> Tensor:
    """The edge_index [2, E] of an edge store without its masked edges (all of them without a mask)."""
    if "edge_mask" not in store:
        return store.edge_index
    return store.edge_index[:, store.edge_mask]
