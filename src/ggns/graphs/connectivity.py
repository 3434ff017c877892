"""Connectivity settings: the radius of every radius-built edge type of the simulation graph.

Radii are in the normalized task space [-1, 1]^d; a radius of 0 means the edge type is absent.
Presets live in conf/graphs/<name>.yaml (one key per field below, nothing else).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from ..config import load_config
from .search import SEARCHES
from .types import EDGE_TYPES, MESH_EDGE, WORLD_EDGE

_RADII = ("point_point", "mesh_point", "collider_point", "collider_mesh", "collider_collider", "world")


@dataclass(frozen=True)
class Connectivity:
    """Radius per edge family; cross-type families (e.g. mesh_point) cover both directions.

    max_num_neighbors: the most neighbours one node may find in one radius query; the graph
    builder raises (never drops edges) when any node has more.
    search: the eager graph builder's neighbour search (`graphs.search`): "auto" (torch-cluster where it
    runs on the graph's device, on a GPU when built with CUDA; else the static search), "cluster" or "static". The static steps
    (`StaticStep`, `StaticTrainStep`) always use the static search. Optional in a preset.
    """

    point_point: float
    mesh_point: float
    collider_point: float
    collider_mesh: float
    collider_collider: float
    world: float  # MGN world edges: mesh pairs within this radius that are not mesh edges
    max_num_neighbors: int
    search: str = "auto"

    def __post_init__(self):
        for name in _RADII:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"connectivity radius {name} must be a finite number >= 0 (0 = no such edges), got {value!r}")
            object.__setattr__(self, name, float(value))
        cap = self.max_num_neighbors
        if isinstance(cap, bool) or not isinstance(cap, int) or cap < 1:
            raise ValueError(f"connectivity max_num_neighbors must be an integer >= 1, got {cap!r}")
        if self.search not in SEARCHES:
            raise ValueError(f"connectivity search must be one of {SEARCHES}, got {self.search!r}")

    @classmethod
    def from_dict(cls, values: dict) -> Connectivity:
        """From a mapping holding the dataclass fields (`search` may be left out: "auto")."""
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown, missing = sorted(set(values) - fields), sorted(fields - set(values) - {"search"})
        if unknown or missing:
            raise ValueError(f"connectivity settings: unknown keys {unknown}, missing keys {missing} (expected {sorted(fields)})")
        return cls(**values)

    @property
    def uses_points(self) -> bool:
        """Whether any edge type touching point nodes has a radius > 0 (else graphs get no points)."""
        return any(r > 0 and "point" in (t[0], t[2]) for t, r in self.radii().items())

    def radii(self) -> dict[tuple[str, str, str], float]:
        """Radius of every radius-built edge type (all of EDGE_TYPES but MESH_EDGE), 0 = absent."""
        out = {}
        for edge_type in EDGE_TYPES:
            if edge_type == WORLD_EDGE:
                out[edge_type] = self.world
            elif edge_type != MESH_EDGE:
                a, b = sorted((edge_type[0], edge_type[2]))  # e.g. ("point", "near", "mesh") -> mesh_point
                out[edge_type] = getattr(self, f"{a}_{b}")
        return out


def load_connectivity(name_or_path: str | Path, overrides: list[str] = ()) -> Connectivity:
    """A preset name (conf/graphs/<name>.yaml) or a YAML path, with optional key=value overrides."""
    return Connectivity.from_dict(load_config(name_or_path, overrides, kind="graphs"))
