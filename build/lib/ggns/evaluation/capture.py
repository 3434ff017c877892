"""A model's rollout step on static-shape graphs, captured as a CUDA graph on a GPU (`StaticStep`).

An eager rollout step on a GPU launches every operator of the encoder, processor and decoder from
Python, a few hundred launches whose host time exceeds the arithmetic of a single trajectory. Here the
graph that the rollout engine built is copied into fixed-capacity buffers (`graphs.static.StaticGraph`),
and the model's step on those buffers is recorded once as a CUDA graph and replayed at every later step
(`torch.cuda.CUDAGraph`): a handful of copies and one launch. A graph that outgrows a capacity (more
edges than ever before) grows the buffers and is recorded anew. The graph construction (the radius
queries, whose edge counts are data) stays eager.

Where no GPU is used (`capture=False`, or a CPU model), the same buffers run eagerly: the padded step,
which must give the model's own step (tests/test_static.py); on a GPU tests/test_cuda.py compares the
replayed step with the eager one.

Models whose step carries state or reads more than the graph's features (GGNS+LSTM, GGNSID) are not
supported: `StaticStep` refuses them and their rollouts stay eager.
"""
from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from ..graphs.static import StaticGraph


class StaticStep:
    """`step(graph, state) -> (displacement [N_mesh, d], state)` of `model` on static-shape graphs, a CUDA
    graph replay when `capture` (default: when the model is on a GPU). `recordings` counts captures."""

    def __init__(self, model, capture: bool | None = None, margin: float = 1.25):
        if model.recurrent or model.material_input:
            raise ValueError(f"{type(model).__name__}: a static step needs a step without state that reads only the "
                             f"graph's features (not GGNS+LSTM, not GGNSID)")
        device = next(model.parameters()).device
        self.capture = device.type == "cuda" if capture is None else capture
        if self.capture and device.type != "cuda":
            raise ValueError(f"capture needs the model on a CUDA device, it is on {device}")
        node_dims, edge_dims = model.input_dims(model.connectivity, model.hparams.dim,
                                                model.with_material or model.material_input)
        self.model, self.buffers = model, StaticGraph(node_dims, edge_dims, device, margin=margin)
        self.recordings = 0
        self._graph: torch.cuda.CUDAGraph | None = None
        self._output: Tensor | None = None

    def __call__(self, graph: HeteroData, state: Any = None) -> tuple[Tensor, Any]:
        static, fresh = self.buffers.fill(graph)
        if not self.capture:
            return self.model.step(static)[0], state
        if fresh or self._graph is None:
            self._record(static)
        self._graph.replay()
        return self._output, state

    def _record(self, static: HeteroData) -> None:
        """Warm up on a side stream (lazy initializations happen outside the capture), then capture."""
        self._graph = None
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.no_grad(), torch.cuda.stream(side):
            for _ in range(2):
                self.model.step(static)
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.no_grad(), torch.cuda.graph(graph):
            self._output = self.model.step(static)[0]
        self._graph = graph
        self.recordings += 1
