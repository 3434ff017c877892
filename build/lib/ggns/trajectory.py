"""The in-memory form of one simulated trajectory: what the generator produces, what the
dataset files store (see `ggns.data.schema`) and what the graph builders read.

Shapes use T = number of recorded steps (initial state included), N = mesh nodes,
K = collider surface vertices, d = spatial dimension (2 or 3), P = points over all steps.
All coordinates are in the normalized task space [-1, 1]^d.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

# `params` keys a trajectory built from a user's arrays sets (`ggns.data.observations`); absent means True.
GROUND_TRUTH = "ground_truth"  # False: positions[1:] are not known (filled with the initial state, fixed nodes stay)
MATERIAL_KNOWN = "poissons_ratio_known"  # False: poissons_ratio is a placeholder (0.0), not the material's


def pack_point_clouds(clouds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per-step point clouds [P_t, d] -> (`points` [P, d] float32, `point_offsets` [T+1] int64) as a
    `Trajectory` stores them."""
    points = np.concatenate(clouds).astype(np.float32)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in clouds])]).astype(np.int64)
    return points, offsets


@dataclass
class Trajectory:
    rest_positions: np.ndarray  # [N, d] float64, mesh nodes in the rest (mesh-space) state
    cells: np.ndarray  # [C, d+1] int64, triangles (2D) or tetrahedra (3D)
    edges: np.ndarray  # [E, 2] int64, undirected mesh edges with i < j, sorted
    positions: np.ndarray  # [T, N, d] float64, mesh node positions per step
    fixed: np.ndarray  # [N] bool, Dirichlet (fixed) mesh nodes
    collider_faces: np.ndarray  # [F, d] int64, collider surface: segments (2D) / triangles (3D)
    collider_positions: np.ndarray  # [T, K, d] float64, collider surface vertices per step
    points: np.ndarray  # [P, d] float32, point clouds of all steps, concatenated
    point_offsets: np.ndarray  # [T+1] int64, step t owns points[offsets[t]:offsets[t+1]]
    youngs_modulus: float  # E in Pa
    poissons_ratio: float  # nu, -1 < nu < 0.5
    seed: int  # the seed this trajectory was generated from
    params: dict = field(default_factory=dict)  # scene parameters (scalars or strings)
    diagnostics: dict = field(default_factory=dict)  # per-step simulator diagnostics, name -> [T]

    @property
    def num_steps(self) -> int:
        return int(self.positions.shape[0])

    @property
    def dim(self) -> int:
        return int(self.rest_positions.shape[1])

    @property
    def has_ground_truth(self) -> bool:
        """Whether `positions` are the true states (False: only step 0 and the fixed nodes are known)."""
        return bool(self.params.get(GROUND_TRUTH, True))

    @property
    def material_known(self) -> bool:
        """Whether `poissons_ratio` is the material's (False: a placeholder; only models told the material need it)."""
        return bool(self.params.get(MATERIAL_KNOWN, True))

    def point_cloud(self, t: int) -> np.ndarray:
        """The point cloud at step t, [P_t, d]."""
        return self.points[self.point_offsets[t] : self.point_offsets[t + 1]]

    def steps(self, start: int, stop: int) -> Trajectory:
        """The trajectory restricted to states start..stop-1 (a window for training samples)."""
        if not 0 <= start < stop <= self.num_steps:
            raise IndexError(f"steps [{start}, {stop}) outside the {self.num_steps} states of this trajectory")
        offsets = self.point_offsets[start : stop + 1]
        return dataclasses.replace(
            self,
            positions=self.positions[start:stop],
            collider_positions=self.collider_positions[start:stop],
            points=self.points[offsets[0] : offsets[-1]],
            point_offsets=offsets - offsets[0],
            diagnostics={k: v[start:stop] for k, v in self.diagnostics.items()},
        )
