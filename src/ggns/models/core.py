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

Inputs are read from `data[node_type].x` and `data[edge_type].edge_attr` and normalized
inside by `input_normalizer` (per type, before any one-hot or padding), so a checkpoint carries
its statistics and every caller (training, rollout) feeds raw graphs. Fill it before training with
`input_normalizer.update(graph_features(batch))` over the training set, then `.freeze()`.
Any node or edge type the model was built for may be absent from a graph; `mesh` must be there.
"""
from __future__ import annotations

import warnings
from typing import Mapping

import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData

from ..graphs.types import EDGE_TYPES, NODE_TYPES
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


def apply_shared(f: nn.Module, inputs: dict) -> dict:
    """One module f on the inputs {type: [M_t, F]} of all types at once -> {type: [M_t, F']}."""
    if not inputs:
        return {}
    out = f(torch.cat(list(inputs.values())))
    return dict(zip(inputs, out.split([len(v) for v in inputs.values()])))


class OneHotEncoder(nn.Module):
    """One Linear(len(types) + width, latent) shared by several node (or edge) types: the rows
    [M, F_t] of type t enter as [one-hot of t's position in `types`, features, zeros to `width`]."""

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
        return apply_shared(self.linear, self.inputs(features))


def mean_aggregate(messages: list[tuple[Tensor, Tensor]], num_nodes: int, like: Tensor) -> Tensor:
    """Mean of messages [E_i, L] at their receivers [E_i] -> [num_nodes, L]; 0 where none arrive."""
    total = like.new_zeros(num_nodes, like.shape[1])
    count = like.new_zeros(num_nodes, 1)
    for message, receivers in messages:
        total.index_add_(0, receivers, message)
        count.index_add_(0, receivers, message.new_ones(len(receivers), 1))
    return total / count.clamp(min=1)


class GraphNetBlock(nn.Module):
    """One message-passing step with residuals, updating the edges of `edge_types` and the nodes
    of `node_types` (a graph may lack any of them); other types are dropped from the output."""

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

    def _run_mlp(self, f: nn.Module, inputs: dict) -> dict:
        """f per type (a TypeModuleDict) or one shared f on all types at once."""
        if isinstance(f, TypeModuleDict):
            return {t: f[t](v) for t, v in inputs.items()}
        return apply_shared(f, inputs)

    def _edge_updates(self, x_dict: dict[str, Tensor], edge_attr_dict: dict[EdgeType, Tensor],
                      edge_index_dict: dict[EdgeType, Tensor]) -> dict[EdgeType, Tensor]:
        """f_E([x_src, x_dst, e]) per edge type, with f_E's first Linear split by input block: the
        node blocks are applied once per node and gathered per edge, so the per-edge work is one
        [L, L] product instead of a [3L, L] product on a concatenation (same function and weights)."""
        shared_projection: dict[str, Tensor] = {}  # node type -> [N, 2L]: [x W_src^T, x W_dst^T] (shared f_E)
        updates = {}
        for t, index in edge_index_dict.items():
            if t not in self.edge_types:
                continue
            f = self.edge_mlp[t] if self.edge_partition else self.edge_mlp
            first, latent = f[0], edge_attr_dict[t].shape[1]
            w_node, w_edge = first.weight[:, : 2 * latent], first.weight[:, 2 * latent:]
            if self.edge_partition:
                src = x_dict[t[0]] @ w_node[:, :latent].T
                dst = x_dict[t[2]] @ w_node[:, latent:].T
            else:
                for n in (t[0], t[2]):
                    if n not in shared_projection:
                        shared_projection[n] = x_dict[n] @ torch.cat([w_node[:, :latent], w_node[:, latent:]]).T
                src, dst = shared_projection[t[0]][:, :latent], shared_projection[t[2]][:, latent:]
            h = (src.index_select(0, index[0]) + dst.index_select(0, index[1])
                 + nn.functional.linear(edge_attr_dict[t], w_edge, first.bias))
            updates[t] = f[1:](h)
        return updates

    def _aggregates(self, node_type: str, x: Tensor, edge_attr_dict: dict[EdgeType, Tensor],
                    edge_index_dict: dict[EdgeType, Tensor]) -> list[Tensor]:
        """The means of the incoming edge latents of the nodes `x` [N, L] of `node_type`."""
        if self.edge_partition:  # one mean per incoming edge type
            return [mean_aggregate([(edge_attr_dict[t], edge_index_dict[t][1])] if t in edge_attr_dict else [],
                                   len(x), x)
                    for t in self.slots[node_type]]
        return [mean_aggregate([(edge_attr_dict[t], edge_index_dict[t][1]) for t in edge_attr_dict
                                if t[2] == node_type], len(x), x)]

    def forward(self, x_dict: dict[str, Tensor], edge_attr_dict: dict[EdgeType, Tensor],
                edge_index_dict: dict[EdgeType, Tensor]) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor]]:
        """Latents x_dict {node type: [N, L]}, edge_attr_dict {edge type: [E, L]} and edge_index_dict
        {edge type: [2, E]} -> (x_dict', edge_attr_dict')."""
        edge_attr_dict = {t: edge_attr_dict[t] + update
                          for t, update in self._edge_updates(x_dict, edge_attr_dict, edge_index_dict).items()}
        node_inputs = {n: torch.cat([x, *self._aggregates(n, x, edge_attr_dict, edge_index_dict)], dim=1)
                       for n, x in x_dict.items() if n in self.node_types}
        x_dict = {n: x_dict[n] + update for n, update in self._run_mlp(self.node_mlp, node_inputs).items()}
        return x_dict, edge_attr_dict


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
        self.type_encoding = type_encoding
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

    def encode(self, data: HeteroData) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor]]:
        """Graph -> encoded latents ({node type: [N, latent]}, {edge type: [E, latent]})."""
        features = self.input_normalizer(graph_features(data))  # KeyError for a type the model lacks
        x_dict = {t: features[t] for t in data.node_types}
        edge_attr_dict = {t: features[t] for t in data.edge_types}
        if self.type_encoding == "one_hot":
            return self.node_encoder(x_dict), self.edge_encoder(edge_attr_dict)
        return ({t: self.node_encoder[t](x) for t, x in x_dict.items()},
                {t: self.edge_encoder[t](e) for t, e in edge_attr_dict.items()})

    def encode_process(self, data: HeteroData) -> Tensor:
        """Graph -> mesh node latents [N_mesh, latent] after the processor."""
        x_dict, edge_attr_dict = self.encode(data)
        edge_index_dict = {t: data[t].edge_index for t in data.edge_types}  # data.edge_index_dict fails without edges
        for block in self.processor:
            x_dict, edge_attr_dict = block(x_dict, edge_attr_dict, edge_index_dict)
        return x_dict["mesh"]

    def decode(self, latents: Tensor) -> Tensor:
        """Mesh latents [N_mesh, latent] -> [N_mesh, out_dim]."""
        return self.decoder(latents)

    def forward(self, data: HeteroData) -> Tensor:
        """Graph -> [N_mesh, out_dim], in the units of the (normalized) training target."""
        return self.decode(self.encode_process(data))
