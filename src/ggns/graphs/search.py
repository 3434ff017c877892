"""Neighbour search with static shapes and no host read: for each query node, at most `cap` neighbours
within a radius (or its k nearest), as a fixed-size index with a validity mask.

torch-cluster's `radius` returns a list of pairs whose length is data: on a GPU its wrapper reads that
length back (two synchronizations per call), and a step built on it cannot be captured as a CUDA graph
or compiled with static shapes. The search here computes, for every query node, the distances to every
node of its own graph (the batch vectors are sorted, so a graph's nodes are one contiguous run) on the
device, `span` candidates per query where `span` is a capacity: at least the node count of the largest
graph of the batch, a host number the caller knows (`TrajectoryBatch.node_offsets`, `point_offsets`).
The result has shape [queries, min(cap, span)]: each row the neighbours of one query, nearest first
when it has more than `cap` within the radius (then the farther ones are dropped, and `count` says
how many there were, so the caller can report the overflow later), its own graph only. Queries are
processed in tiles of at most `TILE` candidate pairs, so memory stays bounded for large graphs.

`compact` turns such rows into an edge list of fixed capacity (its valid prefix and a mask), again
without a read: the number of edges is a device value that the caller checks against the capacity
later (`needed`).

Radius semantics follow torch-cluster's: a neighbour lies strictly within the radius (d < r). Padding
rows (a batch value of `num_graphs` or more: the static builder's padded point slots) neither find nor
are found.

`radius` and `knn` at the bottom are the dynamic searches of the eager graph builder: torch-cluster
wherever it can run on the tensors' device (the reference; on a GPU only when it was built with CUDA),
else the static search with its output compacted to the exact edge count (one read).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor

try:  # optional: the CPU default of the eager builder; PyG 2.8 no longer uses it
    import torch_cluster
except ImportError:  # pragma: no cover - exercised where torch-cluster is not installed
    torch_cluster = None

TILE = 1 << 22  # candidate pairs per tile (4M: 48 MiB of float32 distances in 3D)


@dataclass
class Neighbours:
    """The static result of a search: index [M, w] (source node of each slot; 0 in an invalid slot),
    mask [M, w] bool (the slot holds a neighbour), count [M] long (neighbours within the radius before
    the cap; for knn, the candidates that exist, at most k)."""

    index: Tensor
    mask: Tensor
    count: Tensor


def graph_starts(batch: Tensor, num_graphs: int) -> Tensor:
    """[num_graphs + 2] long: where each graph's rows start in the sorted batch vector `batch`; entry
    num_graphs is the end of the last graph (padding rows with batch >= num_graphs follow it), entry
    num_graphs + 1 the end of the padding."""
    return torch.searchsorted(batch, torch.arange(num_graphs + 2, device=batch.device, dtype=batch.dtype))


def candidates(starts: Tensor, batch_y: Tensor, num_graphs: int, span: int, rows_x: int) -> tuple[Tensor, Tensor]:
    """(candidate source rows [M, span], valid [M, span]): for each query row of `batch_y`, the rows of x of
    its graph (a contiguous run, from x's `graph_starts`), padded to `span`; a padding query has none.
    rows_x: x's row count."""
    graph = batch_y.clamp(max=num_graphs)  # padding queries look at the empty run [end, end)
    first, last = starts[graph], starts[graph + 1]
    last = torch.where(batch_y < num_graphs, last, first)
    cand = first[:, None] + torch.arange(span, device=batch_y.device)
    valid = cand < last[:, None]
    return cand.clamp(max=max(rows_x - 1, 0)), valid


def _tiles(rows: int, span: int) -> list[slice]:
    step = max(1, TILE // max(span, 1))
    return [slice(i, min(i + step, rows)) for i in range(0, rows, step)] or [slice(0, 0)]


def static_radius(x: Tensor, y: Tensor, r: float, batch_x: Tensor, batch_y: Tensor, num_graphs: int, cap: int,
                  span: int, exclude_self: bool = False, exclude: Tensor | None = None) -> Neighbours:
    """Neighbours in x [Nx, d] of every query in y [Ny, d] within radius r, inside their graph (batch_x
    [Nx] sorted, batch_y [Ny]; rows with a batch value >= num_graphs are padding), at most `cap` per query,
    nearest first when more are within r. span: a capacity >= the row count of the largest graph of x.
    exclude_self: x is y and a node is not its own neighbour. exclude: pairs [2, E] (source row in x,
    query row in y) that are not neighbours whatever their distance (MGN's world edges leave the mesh
    edges out); within the radius they still count toward `count`, as the eager builder counts them."""
    if span < 1 or cap < 1:
        raise ValueError(f"need span >= 1 and cap >= 1, got {span}, {cap}")
    ny = y.size(0)
    width = min(cap, span)
    if x.size(0) == 0 or ny == 0:
        empty = torch.zeros(ny, width, dtype=torch.long, device=y.device)
        return Neighbours(empty, empty.bool(), torch.zeros(ny, dtype=torch.long, device=y.device))
    starts = graph_starts(batch_x, num_graphs)
    index, mask, count = [], [], []
    for rows in _tiles(ny, span):
        cand, valid = candidates(starts, batch_y[rows], num_graphs, span, x.size(0))
        d2 = (x[cand] - y[rows, None]).square().sum(-1)
        within = valid & (d2 < r * r)
        if exclude_self:
            within &= cand != torch.arange(rows.start, rows.stop, device=y.device)[:, None]
        count.append(within.sum(1))  # excluded pairs count, as in the eager builder (`graphs.build`)
        if exclude is not None and exclude.size(1):
            within &= ~_excluded(exclude, rows, starts, batch_y, num_graphs, span, within.shape)
        if span <= cap:  # every candidate fits: keep them in their order
            index.append(torch.where(within, cand, 0))
            mask.append(within)
        else:
            key = torch.where(within, d2, torch.full_like(d2, float("inf")))
            order = key.topk(width, dim=1, largest=False, sorted=True).indices
            kept = within.gather(1, order)
            index.append(torch.where(kept, cand.gather(1, order), 0))
            mask.append(kept)
    return Neighbours(torch.cat(index), torch.cat(mask), torch.cat(count))


def _excluded(pairs: Tensor, rows: slice, starts: Tensor, batch_y: Tensor, num_graphs: int, span: int,
              shape: torch.Size) -> Tensor:
    """[rows, span] bool: the candidate slots of queries `rows` that `pairs` [2, E] (source, query) name. A
    pair's slot is its source's position within the query's graph; pairs of other rows go to a spare slot."""
    src, dst = pairs[0], pairs[1]
    graph = batch_y[dst].clamp(max=num_graphs)
    slot = src - starts[graph]
    inside = (dst >= rows.start) & (dst < rows.stop) & (slot >= 0) & (slot < span)
    flat = torch.where(inside, (dst - rows.start) * span + slot, shape[0] * span)
    out = torch.zeros(shape[0] * span + 1, dtype=torch.bool, device=pairs.device)
    out.index_fill_(0, flat, True)
    return out[:-1].view(shape)


def static_knn(x: Tensor, y: Tensor, k: int, batch_x: Tensor, batch_y: Tensor, num_graphs: int,
               span: int) -> Neighbours:
    """The k nearest nodes of x in the graph of every query of y (nearest first; fewer when its graph has
    fewer than k nodes: `mask`), static shapes [Ny, min(k, span)] (`static_radius` for the arguments)."""
    return static_radius(x, y, float("inf"), batch_x, batch_y, num_graphs, k, span)


def compact(neighbours: Neighbours, capacity: int) -> tuple[Tensor, Tensor, Tensor]:
    """The pairs of `neighbours` as an edge list of fixed `capacity`: (edge_index [2, capacity] with row 0
    the source and row 1 the query, row-major order of the valid slots, zeros after them; edge_mask
    [capacity] bool; needed, a 0-d long tensor: the number of valid pairs, which may exceed the capacity
    (then the pairs past it are dropped and the caller must grow it))."""
    flat = neighbours.mask.reshape(-1)
    position = torch.cumsum(flat, 0) - 1
    needed = flat.sum()
    target = torch.where(flat & (position < capacity), position, capacity)
    queries = torch.arange(neighbours.mask.size(0), device=flat.device)[:, None].expand_as(neighbours.mask)
    pairs = torch.stack([neighbours.index.reshape(-1), queries.reshape(-1)])
    out = torch.zeros(2, capacity + 1, dtype=torch.long, device=flat.device)
    out.scatter_(1, target.expand(2, -1), pairs)
    edge_mask = torch.arange(capacity, device=flat.device) < needed
    return out[:, :capacity], edge_mask, needed


# ---- the dynamic searches of the eager builder ------------------------------------------------------------
def largest_graph(batch: Tensor, num_graphs: int) -> int:
    """The row count of the largest graph in a sorted batch vector (one read)."""
    if batch.numel() == 0:
        return 1
    starts = graph_starts(batch, num_graphs)
    return max(1, int((starts[1:num_graphs + 1] - starts[:num_graphs]).max()))


def radius(x: Tensor, y: Tensor, r: float, batch_x: Tensor, batch_y: Tensor, max_num_neighbors: int,
           num_graphs: int, search: str = "auto") -> Tensor:
    """Pairs [2, E] (row 0: query row in y, row 1: source row in x), as `torch_cluster.radius` returns
    them, at most `max_num_neighbors` per query. search: "cluster" (torch-cluster), "static" (the
    static search, compacted to its exact size with one read), "auto" (torch-cluster where it runs on
    the tensors' device, `cluster_runs_on`, else the static search)."""
    if _use_cluster(search, y.device):
        return torch_cluster.radius(x, y, r, batch_x, batch_y, max_num_neighbors=max_num_neighbors,
                                    batch_size=num_graphs)
    return _pairs(static_radius(x, y, r, batch_x, batch_y, num_graphs, max_num_neighbors,
                                largest_graph(batch_x, num_graphs)))


def knn(x: Tensor, y: Tensor, k: int, batch_x: Tensor | None = None, batch_y: Tensor | None = None,
        search: str = "auto") -> Tensor:
    """Pairs [2, E] (row 0: query row in y, row 1: source row in x) of the k nearest, as `torch_cluster.knn`
    (`radius` for `search`)."""
    if _use_cluster(search, y.device):
        return torch_cluster.knn(x, y, k, batch_x, batch_y)
    bx = torch.zeros(x.size(0), dtype=torch.long, device=x.device) if batch_x is None else batch_x
    by = torch.zeros(y.size(0), dtype=torch.long, device=y.device) if batch_y is None else batch_y
    graphs = int(torch.maximum(bx.max(), by.max())) + 1 if bx.numel() and by.numel() else 1
    return _pairs(static_knn(x, y, k, bx, by, graphs, largest_graph(bx, graphs)))


def _pairs(found: Neighbours) -> Tensor:
    """The found pairs as torch-cluster gives them, [2, E] (row 0: query, row 1: source), E read once."""
    return compact(found, int(found.mask.sum()))[0].flip(0)


SEARCHES = ("auto", "cluster", "static")


def cluster_runs_on(device: torch.device) -> bool:
    """Whether torch-cluster is installed and runs on `device`: any CPU build on the CPU, on a GPU a build
    with CUDA (`torch_cluster`'s `cuda_version()` is -1 in a CPU-only build). Under `checks.gpu_code_paths`
    the CPU takes torch-cluster as a GPU with a CUDA build does, so the CPU's count of host reads is that GPU's."""
    if torch_cluster is None:
        return False
    if device.type == "cpu":
        return True
    return device.type == "cuda" and _cluster_has_cuda()


@functools.cache
def _cluster_has_cuda() -> bool:
    return int(torch.ops.torch_cluster.cuda_version()) != -1


def _use_cluster(search: str, device: torch.device) -> bool:
    if search not in SEARCHES:
        raise ValueError(f"neighbour search must be one of {SEARCHES}, got {search!r}")
    if search == "cluster":
        if torch_cluster is None:
            raise ImportError("neighbour search 'cluster' needs torch-cluster, which is not installed; use 'static'")
        if not cluster_runs_on(device):
            raise RuntimeError(f"neighbour search 'cluster' on {device}: the installed torch-cluster was built without "
                               f"CUDA (scripts/gpu_check.sh builds it with FORCE_ONLY_CUDA=1); use 'auto' or 'static'")
        return True
    return search == "auto" and cluster_runs_on(device)
