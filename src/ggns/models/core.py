"""The learned core shared by GGNS and MGN: Encode-Process-Decode on a heterogeneous graph.

Encoder, on the (normalized) inputs, by `type_encoding`:
- "per_type" (MGN): one linear map per node type and per edge type embeds inputs of any width
  to the same latent size.
- "one_hot" (the paper's GGNS): the inputs of the homogeneous graph. A node of type t gets
  [one-hot of t's position among the model's node types (in `NODE_TYPES` order), its features,
  zeros up to the model's widest node input], and one shared linear map embeds all nodes; edges
  likewise with the model's edge types (`EDGE_TYPES` order). The slot of a type is fixed by the
  model, not by the types a graph holds.
Processor: `blocks` GraphNetBlocks with residuals:
    e' = e + f_E([x_src, x_dst, e]),   x' = x + f_V([x, mean of incoming e']).
Decoder, on the `mesh` latents only: the processor's MLP, then Linear(latent, out_dim) (paper:
Linear(128, 128), LeakyReLU, Linear(128, d)), [N_mesh, latent] -> [N_mesh, out_dim].

`edge_partition` selects the processor:
- False (GGNS): one shared f_E and one shared f_V for all types, and all incoming edges of a
  node are pooled into one mean, i.e. the paper's homogeneous graph.
- True (MGN): one f_E per edge type; f_V per node type, on [x, one mean per incoming edge
  type] with a fixed slot per edge type (in `EDGE_TYPES` order), zeros when that type is absent.
The paper's GGNS is type_encoding="one_hot" with edge_partition=False; MGN is "per_type" with True.

The processor runs on a packed layout (`PackedGraph`, made once per forward by `pack`): the latents of
all node types as one array [N_all, L] (types in `NODE_TYPES` order, so mesh rows come first) and of all
edge types as one array [E_all, L] (edge types into mesh first, in `EDGE_TYPES` order), with global
sender and receiver indices. A shared block is then one node projection, two gathers, one edge product,
one scatter-mean and one node product for all types at once, whatever the number of types; a
partitioned block (one MLP per type) keeps per-type latents and takes one mean per incoming edge type. The last block updates only what reaches the decoder: the edges into mesh (a prefix
of the edge array) and the mesh nodes (a prefix of the node array).

Masked edges: an edge store may carry `edge_mask` [E] bool (the fixed-capacity graphs of
`graphs.build`, whose neighbour lists have a static shape); a masked edge is computed like any other
but its message goes to a sink row that no node reads, and it counts in no mean, so the output equals
that of the graph without those edges.

Inputs are read from `data[node_type].x` and `data[edge_type].edge_attr` and normalized
inside by `input_normalizer` (per type, before any one-hot or padding), so a checkpoint carries
its statistics and every caller (training, rollout) feeds raw graphs. Fill it before training with
`input_normalizer.update(graph_features(batch))` over the training set, then `.freeze()`.
Any node or edge type the model was built for may be absent from a graph; `mesh` must be there.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Mapping

import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData

from ..graphs.types import EDGE_TYPES, NODE_TYPES
from ..phases import phase
from .normalization import DEFAULT_STD_FLOOR, NodeOrEdgeType, NormalizerDict, TypeModuleDict

EdgeType = tuple[str, str, str]
TYPE_ENCODINGS = ("per_type", "one_hot")


def mlp(in_dim: int, out_dim: int, layers: int = 1, activation: type[nn.Module] = nn.LeakyReLU) -> nn.Sequential:
    """`layers` blocks of Linear + activation, all of width out_dim.

    The paper's "1-layer MLP" is layers=1: Linear(in_dim, out_dim) then LeakyReLU (slope 0.01),
    with no output layer and no normalization.
    """
    dims = [in_dim] + [out_dim] * layers
    return nn.Sequential(*(m for i in range(layers) for m in (nn.Linear(dims[i], dims[i + 1]), activation())))


def linear_encoder(in_dim: int, latent: int) -> nn.Linear:
    """Linear(in_dim, latent); for in_dim = 0 (point nodes) this is a learned constant (its bias)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Initializing zero-element tensors")
        return nn.Linear(in_dim, latent)


def graph_features(data: HeteroData) -> dict[NodeOrEdgeType, Tensor]:
    """Raw model inputs of a graph: {node type: x [N, F], edge type: edge_attr [E, F]} (every type
    must have them: a missing one is an error, not a type silently left out as in `data.x_dict`)."""
    return {**{t: data[t].x for t in data.node_types}, **{t: data[t].edge_attr for t in data.edge_types}}


@dataclass
class PackedGraph:
    """A graph's types laid out as one node array and one edge array (module docstring).

    node_types / edge_types: the types present, in packing order; node_offsets / edge_offsets
    [len + 1] host ints: type i owns rows offsets[i]:offsets[i + 1]. src / dst [E_all]: global node
    indices of each edge's sender and receiver; receiver [E_all]: dst, or `num_nodes` (the sink row)
    for a masked edge; local_index: each edge type's own edge_index [2, E_t] (indices within its types). into_mesh: edges [0, into_mesh) end at mesh nodes, and num_mesh nodes are mesh.
    inv_degree [num_nodes + 1, 1]: 1 / max(1, unmasked incoming edges) (the pooled mean);
    local_receiver / inv_local_degree (the partitioned processor's per-type means): per edge type its
    receivers within their node type, n_dst (a sink row) for a masked edge, and [n_dst + 1, 1] 1 / max(1,
    unmasked incoming edges of that type).
    """

    node_types: list[str]
    node_offsets: list[int]
    edge_types: list[EdgeType]
    edge_offsets: list[int]
    src: Tensor
    dst: Tensor
    receiver: Tensor
    local_index: list[Tensor]
    into_mesh: int
    num_mesh: int
    inv_degree: Tensor
    local_receiver: list[Tensor]
    inv_local_degree: list[Tensor]

    @property
    def num_nodes(self) -> int:
        return self.node_offsets[-1]

    def node_rows(self, node_type: str) -> slice:
        i = self.node_types.index(node_type)
        return slice(self.node_offsets[i], self.node_offsets[i + 1])

    def edge_rows(self, edge_type: EdgeType) -> slice:
        i = self.edge_types.index(edge_type)
        return slice(self.edge_offsets[i], self.edge_offsets[i + 1])


def edge_packing_order(edge_types) -> list[EdgeType]:
    """Edge types into mesh first, then the others, each group in `EDGE_TYPES` order."""
    known = [t for t in EDGE_TYPES if t in edge_types]
    return [t for t in known if t[2] == "mesh"] + [t for t in known if t[2] != "mesh"]


def inverse_counts(receivers: Tensor, size: int, like: Tensor) -> Tensor:
    """1 / max(1, number of occurrences of each index in [0, size)) as [size, 1] in `like`'s dtype (no host sync).
    Counted in int32, not in `like`'s dtype: bfloat16 holds integers exactly only up to 256 (257 rounds to 256),
    and a node can receive more edges than that (the tissue's gripper)."""
    count = torch.zeros(size, 1, dtype=torch.int32, device=like.device).index_add_(
        0, receivers, torch.ones(len(receivers), 1, dtype=torch.int32, device=like.device))
    return count.clamp(min=1).to(torch.float32).reciprocal().to(like.dtype)


def pack(data: HeteroData, like: Tensor, per_type_means: bool = False) -> PackedGraph:
    """The packed layout of `data` (module docstring). like: a float tensor giving the degrees' dtype and
    device; per_type_means: also the per-type receivers and degrees of the partitioned processor."""
    node_types = [t for t in NODE_TYPES if t in data.node_types]
    if node_types[:1] != ["mesh"]:
        raise ValueError(f"a graph needs mesh nodes, got node types {data.node_types}")
    node_offsets = [0]
    for t in node_types:
        node_offsets.append(node_offsets[-1] + data[t].num_nodes)
    start = dict(zip(node_types, node_offsets))
    edge_types = edge_packing_order(data.edge_types)
    edge_offsets, src, dst, receiver, local_receiver, inv_local = [0], [], [], [], [], []
    sink = node_offsets[-1]
    for t in edge_types:
        index, store = data[t].edge_index, data[t]
        mask = store.edge_mask if "edge_mask" in store else None
        s, d = index[0] + start[t[0]], index[1] + start[t[2]]
        src.append(s)
        dst.append(d)
        receiver.append(d if mask is None else torch.where(mask, d, sink))
        if per_type_means:
            size = data[t[2]].num_nodes
            local = index[1] if mask is None else torch.where(mask, index[1], size)
            local_receiver.append(local)
            inv_local.append(inverse_counts(local, size + 1, like))
        edge_offsets.append(edge_offsets[-1] + index.size(1))
    empty = like.new_zeros(0, dtype=torch.long)
    cat = (lambda parts: torch.cat(parts) if parts else empty)
    receiver_all = cat(receiver)
    into_mesh = edge_offsets[sum(t[2] == "mesh" for t in edge_types)]
    return PackedGraph(node_types, node_offsets, edge_types, edge_offsets, cat(src), cat(dst), receiver_all,
                       [data[t].edge_index for t in edge_types], into_mesh, node_offsets[1],
                       inverse_counts(receiver_all, sink + 1, like), local_receiver, inv_local)


def mean_aggregate(messages: Tensor, receivers: Tensor, inv_count: Tensor) -> Tensor:
    """Mean of messages [E, L] at their receivers [E] -> [len(inv_count), L], given 1 / count per row
    (`inverse_counts`); 0 where none arrive."""
    total = messages.new_zeros(len(inv_count), messages.shape[1]).index_add_(0, receivers, messages)
    return total * inv_count


class OneHotEncoder(nn.Module):
    """One Linear(len(types) + width, latent) shared by several node (or edge) types: the rows
    [M, F_t] of type t enter as [one-hot of t's position in `types`, features, zeros to `width`].
    Computed without building those rows: type t's rows are x_t W_t^T + (b + W[:, slot_t]), with W_t
    the columns of its features (the one-hot's product is a per-type bias, the zeros' nothing)."""

    def __init__(self, types: list[NodeOrEdgeType], width: int, latent: int):
        super().__init__()
        self.types, self.width = list(types), width
        self.linear = linear_encoder(len(self.types) + width, latent)

    def inputs(self, features: Mapping[NodeOrEdgeType, Tensor]) -> dict[NodeOrEdgeType, Tensor]:
        """{type: [M, F_t]} -> {type: [M, len(types) + width]}, the rows the shared Linear sees."""
        out = {}
        for t, x in features.items():
            row = x.new_zeros(len(x), len(self.types) + self.width)
            row[:, self.types.index(t)] = 1
            row[:, len(self.types):len(self.types) + x.shape[1]] = x
            out[t] = row
        return out

    def forward(self, features: Mapping[NodeOrEdgeType, Tensor]) -> dict[NodeOrEdgeType, Tensor]:
        """{type: [M, F_t]} -> {type: [M, latent]}."""
        weight, slots = self.linear.weight, len(self.types)
        biases = self.linear.bias + weight[:, :slots].T  # [types, latent]: row i is type i's bias
        out = {}
        for t, x in features.items():
            bias = biases[self.types.index(t)]
            out[t] = (torch.addmm(bias, x, weight[:, slots:slots + x.shape[1]].T) if x.shape[1]
                      else bias.expand(len(x), -1))
        return out


class GraphNetBlock(nn.Module):
    """One message-passing step with residuals on a `PackedGraph`, updating the edges of `edge_types`
    and the nodes of `node_types` (a graph may lack any of them)."""

    def __init__(self, node_types: list[str], edge_types: list[EdgeType], latent: int, mlp_layers: int,
                 edge_partition: bool):
        super().__init__()
        self.node_types, self.edge_types, self.edge_partition = node_types, edge_types, edge_partition
        if edge_partition:
            self.slots = {n: [t for t in edge_types if t[2] == n] for n in node_types}
            self.edge_mlp = TypeModuleDict({t: mlp(3 * latent, latent, mlp_layers) for t in edge_types})
            self.node_mlp = TypeModuleDict(
                {n: mlp((1 + len(self.slots[n])) * latent, latent, mlp_layers) for n in node_types})
        else:
            self.edge_mlp = mlp(3 * latent, latent, mlp_layers)
            self.node_mlp = mlp(2 * latent, latent, mlp_layers)

    @staticmethod
    def _edge_update(f: nn.Sequential, x_src: Tensor, x_dst: Tensor, src: Tensor, dst: Tensor, e: Tensor) -> Tensor:
        """e + f([x_src[src], x_dst[dst], e]) with f's first Linear split by input block: the node blocks
        are applied once per node and gathered per edge, so the per-edge work is one [L, L] product
        instead of a [3L, L] product on a concatenation (same function and weights)."""
        first, latent = f[0], e.shape[1]
        w_src, w_dst, w_edge = first.weight.split(latent, dim=1)
        if x_src is x_dst:  # one product for both node blocks
            a, b = (x_src @ torch.cat([w_src, w_dst]).T).split(latent, dim=1)
        else:
            a, b = x_src @ w_src.T, x_dst @ w_dst.T
        h = nn.functional.linear(e, w_edge, first.bias)  # added to in place: no [E, L] temporaries
        h += a.index_select(0, src)
        h += b.index_select(0, dst)
        return e + f[1:](h)

    def forward(self, x, e, graph: PackedGraph):
        """Shared: latents x [N_all, L] and e [E_all, L] of `graph` -> (x' [N', L], e' [E', L]), all rows or,
        for a block that updates only mesh nodes, the mesh prefix of both. Partitioned: lists of per-type
        latents in, lists out (`_partitioned`)."""
        mesh_only = self.node_types == ["mesh"]
        if self.edge_partition:
            return self._partitioned(x, e, graph, mesh_only)
        edges = graph.into_mesh if mesh_only else len(e)
        nodes = graph.num_mesh if mesh_only else len(x)
        # slices only where they cut something: a slice's backward writes a zero-filled copy of the whole input
        if edges < len(e):
            e, src, dst, receiver = e[:edges], graph.src[:edges], graph.dst[:edges], graph.receiver[:edges]
        else:
            src, dst, receiver = graph.src, graph.dst, graph.receiver
        e = self._edge_update(self.edge_mlp, x, x, src, dst, e)
        aggregate = mean_aggregate(e, receiver, graph.inv_degree)
        kept = x[:nodes] if nodes < len(x) else x
        x = kept + self.node_mlp(torch.cat([kept, aggregate[:nodes]], dim=1))
        return x, e

    def _partitioned(self, x: list[Tensor], e: list[Tensor], graph: PackedGraph,
                     mesh_only: bool) -> tuple[list[Tensor], list[Tensor]]:
        """One f_E per edge type, one f_V per node type, on per-type latents ([N_t, L] per node type and
        [E_t, L] per edge type in packing order, as lists: no concatenation to cut apart again), with one
        mean per incoming edge type (a zero slot for a type the graph lacks). A block that updates only mesh
        nodes returns the mesh latents and the edges into mesh."""
        x_of = dict(zip(graph.node_types, x))
        types = len(graph.edge_types) if not mesh_only else sum(t[2] == "mesh" for t in graph.edge_types)
        means, updated = {}, []
        for i, (t, index, e_t) in enumerate(zip(graph.edge_types[:types], graph.local_index, e)):
            e_t = self._edge_update(self.edge_mlp[t], x_of[t[0]], x_of[t[2]], index[0], index[1], e_t)
            updated.append(e_t)
            means[t] = mean_aggregate(e_t, graph.local_receiver[i], graph.inv_local_degree[i])
        out = []
        for n in graph.node_types[:1] if mesh_only else graph.node_types:
            x_n = x_of[n]
            slots = [means[t][:len(x_n)] if t in means else x_n.new_zeros(x_n.shape) for t in self.slots[n]]
            out.append(x_n + self.node_mlp[n](torch.cat([x_n, *slots], dim=1)))
        return out, updated


class EncodeProcessDecode(nn.Module):
    """Graph [HeteroData] -> per-mesh-node output [N_mesh, out_dim] (see module docstring).

    node_dims / edge_dims: input width per node / edge type the model accepts (types from
    `NODE_TYPES` / `EDGE_TYPES`; `mesh` required). type_encoding: "per_type" or "one_hot".
    Paper defaults: latent 128, 5 blocks, 1-layer MLPs.
    """

    def __init__(self, node_dims: Mapping[str, int], edge_dims: Mapping[EdgeType, int], out_dim: int,
                 latent: int = 128, blocks: int = 5, mlp_layers: int = 1, edge_partition: bool = False,
                 std_floor: float = DEFAULT_STD_FLOOR, type_encoding: str = "per_type"):
        super().__init__()
        if type_encoding not in TYPE_ENCODINGS:
            raise ValueError(f"type_encoding must be one of {TYPE_ENCODINGS}, got {type_encoding!r}")
        unknown = [t for t in [*node_dims, *edge_dims] if t not in NODE_TYPES + EDGE_TYPES]
        if unknown or "mesh" not in node_dims:
            raise ValueError(f"node types must include 'mesh' and come from NODE_TYPES/EDGE_TYPES; unknown: {unknown}")
        missing = [t for t in edge_dims if t[0] not in node_dims or t[2] not in node_dims]
        if missing:
            raise ValueError(f"edge types {missing} connect node types missing from node_dims")
        node_types = [t for t in NODE_TYPES if t in node_dims]
        edge_types = [t for t in EDGE_TYPES if t in edge_dims]
        self.input_normalizer = NormalizerDict({**node_dims, **edge_dims}, std_floor)
        self.type_encoding, self.edge_partition = type_encoding, edge_partition
        if type_encoding == "one_hot":
            self.node_encoder = OneHotEncoder(node_types, max(node_dims.values()), latent)
            self.edge_encoder = OneHotEncoder(edge_types, max(edge_dims.values(), default=0), latent)
        else:
            self.node_encoder = TypeModuleDict({t: linear_encoder(node_dims[t], latent) for t in node_types})
            self.edge_encoder = TypeModuleDict({t: linear_encoder(edge_dims[t], latent) for t in edge_types})
        # The last block updates only what reaches the decoder: mesh nodes and edges into mesh.
        last = (["mesh"], [t for t in edge_types if t[2] == "mesh"])
        self.processor = nn.ModuleList(
            GraphNetBlock(*(last if b == blocks - 1 else (node_types, edge_types)), latent, mlp_layers, edge_partition)
            for b in range(blocks))
        self.decoder = nn.Sequential(mlp(latent, latent, mlp_layers), nn.Linear(latent, out_dim))

    def _encode(self, features: Mapping[NodeOrEdgeType, Tensor], types: list) -> dict:
        encoder = self.node_encoder if isinstance(types[0], str) else self.edge_encoder
        if self.type_encoding == "one_hot":
            return encoder(features)
        return {t: encoder[t](features[t]) for t in types}

    def encode(self, data: HeteroData) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor]]:
        """Graph -> encoded latents ({node type: [N, latent]}, {edge type: [E, latent]})."""
        features = self.input_normalizer(graph_features(data))  # KeyError for a type the model lacks
        node_types, edge_types = list(data.node_types), list(data.edge_types)
        x = self._encode({t: features[t] for t in node_types}, node_types)
        e = self._encode({t: features[t] for t in edge_types}, edge_types) if edge_types else {}
        return x, e

    def encode_process(self, data: HeteroData) -> Tensor:
        """Graph -> mesh node latents [N_mesh, latent] after the processor."""
        with phase("encoder"):
            x_dict, e_dict = self.encode(data)
            like = x_dict["mesh"]
            graph = pack(data, like, per_type_means=self.edge_partition)
            if self.edge_partition:  # per-type lists (each type has its own MLPs)
                x, e = [x_dict[t] for t in graph.node_types], [e_dict[t] for t in graph.edge_types]
            else:
                x = torch.cat([x_dict[t] for t in graph.node_types])
                e = torch.cat([e_dict[t] for t in graph.edge_types]) if graph.edge_types else like[:0]
        with phase("processor"):
            for block in self.processor:
                x, e = block(x, e, graph)
        return x[0] if self.edge_partition else x[:graph.num_mesh]

    def decode(self, latents: Tensor) -> Tensor:
        """Mesh latents [N_mesh, latent] -> [N_mesh, out_dim]."""
        with phase("decoder"):
            return self.decoder(latents)

    def forward(self, data: HeteroData) -> Tensor:
        """Graph -> [N_mesh, out_dim], in the units of the (normalized) training target."""
        return self.decode(self.encode_process(data))
