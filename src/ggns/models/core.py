"""The learned core shared by GGNS and MGN: Encode-Process-Decode on a heterogeneous graph.

Encoder: one linear map per node type and per edge type embeds the (normalized) inputs of
any width to the same latent size. Processor: `blocks` GraphNetBlocks with residuals:
    e' = e + f_E([x_src, x_dst, e]),   x' = x + f_V([x, mean of incoming e']).
Decoder, on the `mesh` latents only: the processor's MLP, then Linear(latent, out_dim) (paper:
Linear(128, 128), LeakyReLU, Linear(128, d)), [N_mesh, latent] -> [N_mesh, out_dim].

`edge_partition` selects the model family:
- False (GGNS): one shared f_E and one shared f_V for all types, and all incoming edges of a
  node are pooled into one mean, i.e. the paper's homogeneous graph. The type identity that
  GGNS feeds as one-hot features is carried by the per-type encoders: a one-hot column
  through a shared linear encoder adds a per-type bias, which each type's own encoder has
  (the paper's shared encoder also ties the weights of columns that types share; these don't).
- True (MGN): one f_E per edge type; f_V per node type, on [x, one mean per incoming edge
  type] with a fixed slot per edge type (in `EDGE_TYPES` order), zeros when that type is absent.

Inputs are read from `data[node_type].x` and `data[edge_type].edge_attr` and normalized
inside by `input_normalizer`, so a checkpoint carries its statistics and every caller
(training, rollout) feeds raw graphs. Fill it before training with
`input_normalizer.update(graph_features(batch))` over the training set, then `.freeze()`.
Any node or edge type the model was built for may be absent from a graph; `mesh` must be there.
"""
from __future__ import annotations

import warnings
from typing import Mapping

import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData

from ggns.graphs.types import EDGE_TYPES, NODE_TYPES
from ggns.models.normalization import NodeOrEdgeType, NormalizerDict, type_key

EdgeType = tuple[str, str, str]


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
    """Raw model inputs of a graph: {node type: x [N, F], edge type: edge_attr [E, F]}."""
    return {**{t: data[t].x for t in data.node_types}, **{t: data[t].edge_attr for t in data.edge_types}}


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
            self.edge_mlp = nn.ModuleDict({type_key(t): mlp(3 * latent, latent, mlp_layers) for t in edge_types})
            self.node_mlp = nn.ModuleDict(
                {n: mlp((1 + len(self.slots[n])) * latent, latent, mlp_layers) for n in node_types})
        else:
            self.edge_mlp = mlp(3 * latent, latent, mlp_layers)
            self.node_mlp = mlp(2 * latent, latent, mlp_layers)

    def _apply(self, f: nn.Module, inputs: dict) -> dict:
        """f per type (a ModuleDict) or one shared f on all types at once."""
        if isinstance(f, nn.ModuleDict):
            return {t: f[type_key(t)](v) for t, v in inputs.items()}
        if not inputs:
            return {}
        out = f(torch.cat(list(inputs.values())))
        return dict(zip(inputs, out.split([len(v) for v in inputs.values()])))

    def _aggregates(self, node_type: str, x: Tensor, e: dict[EdgeType, Tensor],
                    edge_index: dict[EdgeType, Tensor]) -> list[Tensor]:
        if self.edge_partition:  # one mean per incoming edge type
            return [mean_aggregate([(e[t], edge_index[t][1])] if t in e else [], len(x), x)
                    for t in self.slots[node_type]]
        return [mean_aggregate([(e[t], edge_index[t][1]) for t in e if t[2] == node_type], len(x), x)]

    def forward(self, x: dict[str, Tensor], e: dict[EdgeType, Tensor],
                edge_index: dict[EdgeType, Tensor]) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor]]:
        """x {node type: [N, L]}, e {edge type: [E, L]}, edge_index {edge type: [2, E]} -> (x', e')."""
        edge_inputs = {t: torch.cat([x[t[0]][i[0]], x[t[2]][i[1]], e[t]], dim=1)
                       for t, i in edge_index.items() if t in self.edge_types}
        e = {t: e[t] + update for t, update in self._apply(self.edge_mlp, edge_inputs).items()}
        node_inputs = {n: torch.cat([v, *self._aggregates(n, v, e, edge_index)], dim=1)
                       for n, v in x.items() if n in self.node_types}
        x = {n: x[n] + update for n, update in self._apply(self.node_mlp, node_inputs).items()}
        return x, e


class EncodeProcessDecode(nn.Module):
    """Graph [HeteroData] -> per-mesh-node output [N_mesh, out_dim] (see module docstring).

    node_dims / edge_dims: input width per node / edge type the model accepts (types from
    `NODE_TYPES` / `EDGE_TYPES`; `mesh` required). Paper defaults: latent 128, 5 blocks,
    1-layer MLPs.
    """

    def __init__(self, node_dims: Mapping[str, int], edge_dims: Mapping[EdgeType, int], out_dim: int,
                 latent: int = 128, blocks: int = 5, mlp_layers: int = 1, edge_partition: bool = False,
                 std_floor: float = 1e-8):
        super().__init__()
        unknown = [t for t in [*node_dims, *edge_dims] if t not in NODE_TYPES + EDGE_TYPES]
        if unknown or "mesh" not in node_dims:
            raise ValueError(f"node types must include 'mesh' and come from NODE_TYPES/EDGE_TYPES; unknown: {unknown}")
        missing = [t for t in edge_dims if t[0] not in node_dims or t[2] not in node_dims]
        if missing:
            raise ValueError(f"edge types {missing} connect node types missing from node_dims")
        node_types = [t for t in NODE_TYPES if t in node_dims]
        edge_types = [t for t in EDGE_TYPES if t in edge_dims]
        self.input_normalizer = NormalizerDict({**node_dims, **edge_dims}, std_floor)
        self.node_encoder = nn.ModuleDict({t: linear_encoder(node_dims[t], latent) for t in node_types})
        self.edge_encoder = nn.ModuleDict({type_key(t): linear_encoder(edge_dims[t], latent) for t in edge_types})
        # The last block updates only what reaches the decoder: mesh nodes and edges into mesh.
        last = (["mesh"], [t for t in edge_types if t[2] == "mesh"])
        self.processor = nn.ModuleList(
            GraphNetBlock(*(last if b == blocks - 1 else (node_types, edge_types)), latent, mlp_layers, edge_partition)
            for b in range(blocks))
        self.decoder = nn.Sequential(mlp(latent, latent, mlp_layers), nn.Linear(latent, out_dim))

    def encode_process(self, data: HeteroData) -> Tensor:
        """Graph -> mesh node latents [N_mesh, latent] after the processor."""
        features = self.input_normalizer(graph_features(data))  # KeyError for a type the model lacks
        x = {t: self.node_encoder[t](features[t]) for t in data.node_types}
        e = {t: self.edge_encoder[type_key(t)](features[t]) for t in data.edge_types}
        edge_index = {t: data[t].edge_index for t in data.edge_types}
        for block in self.processor:
            x, e = block(x, e, edge_index)
        return x["mesh"]

    def decode(self, latents: Tensor) -> Tensor:
        """Mesh latents [N_mesh, latent] -> [N_mesh, out_dim]."""
        return self.decoder(latents)

    def forward(self, data: HeteroData) -> Tensor:
        """Graph -> [N_mesh, out_dim], in the units of the (normalized) training target."""
        return self.decode(self.encode_process(data))
