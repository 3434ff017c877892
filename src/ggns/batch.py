"""B trajectories on one device, concatenated PyG-style: what the data module's collate makes
and what the graph builders, models and metrics read (`TrajectoryBatch`).

Shapes: B trajectories, T states each (all equal), sumN / sumK / sumC mesh nodes / collider
vertices / cells over all trajectories, P_t points of all trajectories at step t, d dims.
Indices (edges, cells) are global, i.e. offset by the nodes of the trajectories before.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from .trajectory import Trajectory


def directed_mesh_edges(edges: Tensor) -> Tensor:
    """Undirected edges [E, 2] -> directed edge_index [2, 2E] (each edge in both directions)."""
    edges = torch.as_tensor(edges, dtype=torch.long)
    return torch.cat([edges.T, edges.T.flip(0)], dim=1)


@dataclass
class TrajectoryBatch:
    rest: Tensor  # [sumN, d] mesh rest positions
    edges: Tensor  # [2, sumE] directed mesh edges (both directions), global indices
    fixed: Tensor  # [sumN] bool, Dirichlet nodes
    mesh_batch: Tensor  # [sumN] long, trajectory of each node
    positions: Tensor  # [T, sumN, d] true mesh positions (initial state repeated where ground_truth is False)
    collider: Tensor | None  # [T, sumK, d] collider vertices, None when no trajectory has any
    collider_batch: Tensor | None  # [sumK] long
    points: list[Tensor]  # T x [P_t, d], point clouds of all trajectories at step t
    point_batch: list[Tensor]  # T x [P_t] long, trajectory of each point
    material: Tensor  # [B] Poisson ratios
    cells: Tensor  # [sumC, d+1] long, global node indices
    node_offsets: tuple[int, ...]  # B+1 host ints: trajectory b owns nodes node_offsets[b]:node_offsets[b+1]
    cell_offsets: tuple[int, ...]  # B+1 host ints, likewise for cells
    ground_truth: tuple[bool, ...]  # B host flags: positions[1:] of trajectory b are true (`has_ground_truth`)
    material_known: tuple[bool, ...]  # B host flags: material[b] is the material's (`Trajectory.material_known`)

    @property
    def num_graphs(self) -> int:
        return len(self.node_offsets) - 1

    @property
    def num_steps(self) -> int:
        return int(self.positions.shape[0])

    def require_ground_truth(self, what: str) -> None:
        """ValueError naming the trajectories without true positions: `what` (metrics, teacher forcing) needs them."""
        missing = [b for b, known in enumerate(self.ground_truth) if not known]
        if missing:
            raise ValueError(f"{what} needs the true positions, but trajectory(ies) {missing} of the batch have none "
                             f"(built without true_positions: only the initial state and the fixed nodes are known)")

    def require_material(self, what: str) -> None:
        """ValueError naming the trajectories whose Poisson's ratio is a placeholder: `what` needs the material."""
        missing = [b for b, known in enumerate(self.material_known) if not known]
        if missing:
            raise ValueError(f"{what} is told the material (Poisson's ratio), but trajectory(ies) {missing} of the "
                             f"batch were built without poissons_ratio; give it, or use a model that infers it (GGNS)")

    @property
    def device(self) -> torch.device:
        return self.positions.device

    def to(self, device) -> TrajectoryBatch:
        """A copy with every tensor on `device` (host offsets unchanged)."""
        def move(value):
            if isinstance(value, Tensor):
                return value.to(device)
            if isinstance(value, list):
                return [v.to(device) for v in value]
            return value

        return TrajectoryBatch(**{f.name: move(getattr(self, f.name)) for f in fields(self)})

    @classmethod
    def from_trajectories(cls, trajs: list[Trajectory], device=None, dtype=torch.float32) -> TrajectoryBatch:
        """Concatenate trajectories with equal T and d (ValueError otherwise) on `device`."""
        if not trajs:
            raise ValueError("TrajectoryBatch needs at least one trajectory")
        shapes = [(t.num_steps, t.dim) for t in trajs]
        if len(set(shapes)) > 1:
            raise ValueError(f"trajectories in one batch need equal step counts T and dimensions d, got (T, d) = {shapes}")
        num_steps = shapes[0][0]
        n = np.cumsum([0] + [len(t.rest_positions) for t in trajs])
        c = np.cumsum([0] + [len(t.cells) for t in trajs])

        def cat(arrays, kind=dtype, axis=0):
            return torch.as_tensor(np.concatenate(arrays, axis=axis)).to(device=device, dtype=kind)

        def batch_of(sizes):
            return torch.repeat_interleave(torch.arange(len(trajs)), torch.as_tensor(sizes)).to(device)

        k = [t.collider_positions.shape[1] for t in trajs]
        points, point_batch = [], []
        for s in range(num_steps):
            clouds = [t.point_cloud(s) for t in trajs]
            points.append(cat(clouds))
            point_batch.append(batch_of([len(p) for p in clouds]))
        return cls(
            rest=cat([t.rest_positions for t in trajs]),
            edges=directed_mesh_edges(cat([t.edges + o for t, o in zip(trajs, n)], torch.long)),
            fixed=cat([t.fixed for t in trajs], torch.bool),
            mesh_batch=batch_of(np.diff(n)),
            positions=cat([t.positions for t in trajs], axis=1),
            collider=cat([t.collider_positions for t in trajs], axis=1) if sum(k) else None,
            collider_batch=batch_of(k) if sum(k) else None,
            points=points,
            point_batch=point_batch,
            material=torch.tensor([float(t.poissons_ratio) for t in trajs], dtype=dtype, device=device),
            cells=cat([t.cells + o for t, o in zip(trajs, n)], torch.long),
            node_offsets=tuple(int(i) for i in n),
            cell_offsets=tuple(int(i) for i in c),
            ground_truth=tuple(t.has_ground_truth for t in trajs),
            material_known=tuple(t.material_known for t in trajs),
        )
