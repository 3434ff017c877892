"""B trajectories on one device, concatenated PyG-style: what the data module's collate makes
and what the graph builders, models and metrics read (`TrajectoryBatch`).

Shapes: B trajectories, T states each (all equal), sumN / sumK / sumC mesh nodes / collider
vertices / cells over all trajectories, P_t points of all trajectories at step t, d dims.
Indices (edges, cells) are global, i.e. offset by the nodes of the trajectories before.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

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
    """B trajectories of T states concatenated PyG-style on one device: node, cell, collider and point
    arrays of all trajectories stacked, with `*_batch` vectors (and host offsets) saying whose each row is.

    Attributes:
        rest: [sumN, d] mesh rest positions.
        edges: [2, sumE] directed mesh edges (both directions), global node indices.
        fixed: [sumN] bool, the Dirichlet (fixed) nodes.
        mesh_batch: [sumN] long, the trajectory of each node.
        positions: [T, sumN, d] true mesh positions (the initial state repeated where there is no ground truth).
        collider: [T, sumK, d] collider vertices, None when no trajectory has any.
        points: T tensors [P_t, d], the point clouds of all trajectories at step t.
        material: [B] Poisson's ratios.
        cells: [sumC, d+1] long, triangles or tetrahedra, global node indices.
    """

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
    # T x (B+1) host ints: the points of trajectory b at step t are points[t][o[b]:o[b+1]], o = point_offsets[t]
    # (None: not known on the host, e.g. a batch built by hand; then computed once from point_batch)
    point_offsets: tuple[tuple[int, ...], ...] | None = None
    # B+1 host ints: trajectory b owns collider vertices o[b]:o[b+1] (None: not known on the host; computed once)
    collider_offsets: tuple[int, ...] | None = None
    # the graph-input value checks passed for this batch (`graphs.state`; one sync per batch, not per step)
    inputs_checked: bool = field(default=False, compare=False)

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

    @property
    def free_index(self) -> Tensor:
        """Indices [F] of the free (not fixed) mesh nodes, on the batch's device: selecting with it reads
        nothing back from the device, where a boolean mask would (computed once per batch)."""
        fixed, cached = self.__dict__.get("_free_index", (None, None))
        if fixed is not self.fixed:
            cached = torch.nonzero(~self.fixed.cpu())[:, 0].to(self.device)
            self.__dict__["_free_index"] = (self.fixed, cached)
        return cached

    def point_range(self, t: int) -> tuple[int, ...]:
        """The B+1 host offsets of the trajectories' points at step t (`point_offsets`)."""
        if self.point_offsets is None:
            counts = torch.bincount(self.point_batch[t].cpu(), minlength=self.num_graphs).tolist()
            return tuple(int(v) for v in np.cumsum([0] + counts))
        return self.point_offsets[t]

    @property
    def collider_range(self) -> tuple[int, ...]:
        """The B+1 host offsets of the trajectories' collider vertices (`collider_offsets`; all 0 without any)."""
        if self.collider_offsets is None:
            if self.collider_batch is None:
                return (0,) * (self.num_graphs + 1)
            counts = torch.bincount(self.collider_batch.cpu(), minlength=self.num_graphs).tolist()
            self.collider_offsets = tuple(int(v) for v in np.cumsum([0] + counts))
        return self.collider_offsets

    def to(self, device, non_blocking: bool = False) -> TrajectoryBatch:
        """A copy with every tensor on `device` (host offsets unchanged); non_blocking copies from pinned
        memory (`pin_memory`) do not wait for the device."""
        def move(value):
            if isinstance(value, Tensor):
                return value.to(device, non_blocking=non_blocking)
            if isinstance(value, list):
                return [v.to(device, non_blocking=non_blocking) for v in value]
            return value

        moved = TrajectoryBatch(**{f.name: move(getattr(self, f.name)) for f in fields(self)})
        moved.__dict__["_free_index"] = (moved.fixed, self.free_index.to(device, non_blocking=non_blocking))
        return moved

    def pin_memory(self) -> TrajectoryBatch:
        """A copy in page-locked host memory (the DataLoader's pin_memory calls it), so that the move to a GPU
        is a copy the host does not wait for."""
        def pin(value):
            if isinstance(value, Tensor):
                return value.pin_memory()
            if isinstance(value, list):
                return [v.pin_memory() for v in value]
            return value

        pinned = TrajectoryBatch(**{f.name: pin(getattr(self, f.name)) for f in fields(self)})
        pinned.__dict__["_free_index"] = (pinned.fixed, self.free_index.pin_memory())
        return pinned

    @classmethod
    def from_trajectories(cls, trajs: list[Trajectory], device: torch.device | str | None = None,
                          dtype: torch.dtype = torch.float32) -> TrajectoryBatch:
        """Concatenate trajectories with equal T and d (ValueError otherwise) on `device`.

        Args:
            trajs: B trajectories (`SplitReader` items, `trajectory_from_arrays`), all with T states in
                d dimensions; their node counts may differ.
            device: where the tensors go (default: the CPU).
            dtype: the floating-point type of positions and features.

        Returns:
            the batch: positions [T, sum_b N_b, d] with `mesh_batch` [sum_b N_b] naming each node's
            trajectory, colliders and point clouds concatenated likewise.
        """
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
        points, point_batch, point_offsets = [], [], []
        for s in range(num_steps):
            clouds = [t.point_cloud(s) for t in trajs]
            points.append(cat(clouds))
            point_batch.append(batch_of([len(p) for p in clouds]))
            point_offsets.append(tuple(int(i) for i in np.cumsum([0] + [len(p) for p in clouds])))
        batch = cls(
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
            point_offsets=tuple(point_offsets),
            collider_offsets=tuple(int(i) for i in np.cumsum([0] + k)),
        )
        batch.free_index  # noqa: B018 (computed once here; a move to a GPU carries it along)
        if batch.device.type == "cpu":  # the graph builder's value checks, here where they read no device
            vectors = {"mesh": batch.mesh_batch, **({"collider": batch.collider_batch} if sum(k) else {}),
                       **{f"point (step {s})": b for s, b in enumerate(point_batch)}}
            check_batch_vectors(vectors, batch.edges, batch.num_graphs)
            batch.inputs_checked = True
        return batch


def check_batch_vectors(batches: dict[str, Tensor], mesh_edges: Tensor, num_graphs: int) -> None:
    """Sorted batch vectors {name: [n]} in [0, num_graphs), mesh edges [2, E] in range of the `mesh` nodes
    and inside one graph: ValueError naming what failed (one read of the device for all)."""
    n = batches["mesh"].size(0)
    checks = {}
    for name, b in batches.items():
        if b.numel():
            checks[f"{name} batch sorted and in [0, {num_graphs})"] = (
                (b[1:] >= b[:-1]).all() & (b.min() >= 0) & (b.max() < num_graphs)
            )
    if mesh_edges.size(1) > 0:
        inside = (mesh_edges.min() >= 0) & (mesh_edges.max() < n)
        ends = batches["mesh"][mesh_edges.clamp(0, n - 1)]
        checks[f"mesh_edges in [0, {n}) and inside one graph"] = inside & (ends[0] == ends[1]).all()
    failed = [name for name, ok in zip(checks, torch.stack(list(checks.values())).tolist()) if not ok]
    if failed:
        raise ValueError(f"invalid graph inputs, expected: {'; '.join(failed)}")
