"""Deformable Plate scene (GGNS paper, appendix "Deformable Plate"): a 2D trapezoid with a
fixed bottom edge, pushed down by a rigid circular collider moving at constant velocity.

Every quantity comes from the `scene` section of a generation config (conf/data/plate.yaml).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..trajectory import Trajectory, pack_point_clouds
from ..geometry import cell_edges
from ..sim.material import Material
from ..sim.run import simulate
from ..sim.solver import SolverConfig


DIM = 2  # spatial dimension of the scene


@dataclass(frozen=True)
class PlateSpec:
    """One sampled plate trajectory: shape, material and collider path."""

    shape_id: int  # 0..8, index into top_widths x top_offsets
    poissons_ratio: float
    collider_radius: float  # m
    collider_start_x: float  # m, centre x at t = 0


def trapezoid(scene: dict, shape_id: int) -> tuple[float, float, float, float]:
    """(bottom_left_x, bottom_right_x, top_left_x, top_right_x) of the nine trapezoids."""
    widths, offsets = scene["top_widths"], scene["top_offsets"]
    if not 0 <= shape_id < len(widths) * len(offsets):
        raise ValueError(f"shape_id must be in 0..{len(widths) * len(offsets) - 1}, got {shape_id}")
    top_w, off = widths[shape_id // len(offsets)], offsets[shape_id % len(offsets)]
    half = scene["bottom_width"] / 2
    return -half, half, off - top_w / 2, off + top_w / 2


def plate_mesh(scene: dict, shape_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Structured triangle mesh of a trapezoid: rest positions [n*n, 2], cells [2(n-1)^2, 3]
    (counter-clockwise), fixed mask [n*n] (the bottom row). Every quad is split along the same
    diagonal, bottom-right to top-left (scene.diagonals "uniform", as the paper's plate), or
    along alternating diagonals ("alternating", the earlier scene)."""
    n = int(scene["grid_nodes"])
    bl, br, tl, tr = trapezoid(scene, shape_id)
    s, r = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="xy")  # s along x, r along y
    left, right = bl + (tl - bl) * r, br + (tr - br) * r
    x = left + (right - left) * s
    y = scene["bottom_y"] + scene["height"] * r
    positions = np.stack([x.ravel(), y.ravel()], axis=1)
    j, i = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")  # j row, i column
    a, b = j * n + i, j * n + i + 1
    c, d = a + n + 1, a + n  # c above b, d above a
    diagonals = scene.get("diagonals", "alternating")
    if diagonals == "uniform":
        even = np.zeros(a.size, dtype=bool)  # split b-d everywhere
    elif diagonals == "alternating":
        even = ((i + j) % 2 == 0).ravel()
    else:
        raise ValueError(f"scene.diagonals must be 'uniform' or 'alternating', got {diagonals!r}")
    a, b, c, d = a.ravel(), b.ravel(), c.ravel(), d.ravel()
    first = np.where(even[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
    second = np.where(even[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
    cells = np.concatenate([first, second]).astype(np.int64)
    fixed = np.zeros(n * n, dtype=bool)
    fixed[:n] = True
    return positions, cells, fixed


def plate_material(scene: dict, poissons_ratio: float) -> Material:
    """The plate's material for one Poisson's ratio (2D idealization: scene.plane)."""
    return Material.of_scene(scene, scene["youngs_modulus"], poissons_ratio)


def circle(radius: float, centre: tuple[float, float], count: int) -> tuple[np.ndarray, np.ndarray]:
    """Closed counter-clockwise polygon: vertices [count, 2], segments [count, 2]."""
    angle = 2 * math.pi * np.arange(count) / count
    vertices = np.stack([centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle)], axis=1)
    segments = np.stack([np.arange(count), (np.arange(count) + 1) % count], axis=1).astype(np.int64)
    return vertices, segments


def sample_spec(scene: dict, shape_id: int, poissons_ratio: float, rng: np.random.Generator) -> PlateSpec:
    """Collider radius ~ triangular(radius_fraction) x top edge length; start x ~ U(top corners)."""
    _, _, tl, tr = trapezoid(scene, shape_id)
    lo, mode, hi = scene["collider"]["radius_fraction"]
    radius = (lo if lo == hi else rng.triangular(lo, mode, hi)) * (tr - tl)  # numpy refuses lo == hi
    return PlateSpec(shape_id, float(poissons_ratio), float(radius), float(rng.uniform(tl, tr)))


def collider_path(scene: dict, spec: PlateSpec) -> tuple[np.ndarray, np.ndarray]:
    """Collider vertices per recorded step [T, K, 2] and segments [K, 2]: `collider.travel` down at a
    constant velocity over `collider.push_steps` steps (default: all T - 1), then held (a long
    rollout of the same push: the stability study, docs/experiments/stability.md)."""
    T, col = int(scene["num_steps"]), scene["collider"]
    push = int(col.get("push_steps") or T - 1)
    top_y = scene["bottom_y"] + scene["height"]
    centre_y0 = top_y + col["start_gap"] + spec.collider_radius
    vertices, segments = circle(spec.collider_radius, (spec.collider_start_x, centre_y0), int(col["vertices"]))
    drop = col["travel"] * np.minimum(np.arange(T), push) / max(push, 1)
    path = vertices[None] - np.stack([np.zeros_like(drop), drop], axis=1)[:, None, :]
    return path, segments


def check_config(config: dict) -> None:
    """Refuse a configuration before any work starts: invalid materials or solver settings, or a
    plate that leaves the task space [-1, 1]^2. The collider starts above the plate's top edge
    and may start outside the task space (the paper's plate fills it; radii and features are
    relative, so only the deformable object has to lie inside)."""
    scene = config["scene"]
    for nu in scene["poissons_ratios"]:
        plate_material(scene, nu)
    SolverConfig(dt=scene["frame_dt"] / int(scene["substeps"]), **config["solver"])
    if int(scene["num_steps"]) < 2:
        raise ValueError(f"scene.num_steps must be >= 2, got {scene['num_steps']}")
    push = scene["collider"].get("push_steps")
    if push is not None and not 1 <= int(push) <= int(scene["num_steps"]) - 1:
        raise ValueError(f"collider.push_steps must be in 1..num_steps - 1 = {int(scene['num_steps']) - 1}, got {push}")
    lo, mode, hi = scene["collider"]["radius_fraction"]
    if not 0 < lo <= mode <= hi:
        raise ValueError(f"collider.radius_fraction must be 0 < min <= mode <= max, got {[lo, mode, hi]}")
    if not scene["collider"]["start_gap"] > 0:
        raise ValueError(f"collider.start_gap must be > 0 (the collider starts above the plate), got {scene['collider']['start_gap']}")
    top = scene["bottom_y"] + scene["height"]
    for shape in range(len(scene["top_widths"]) * len(scene["top_offsets"])):
        bl, br, tl, tr = trapezoid(scene, shape)
        extent = max(abs(bl), abs(br), abs(tl), abs(tr), abs(scene["bottom_y"]), abs(top))
        if extent > 1.0 + 1e-9:
            raise ValueError(f"plate shape {shape} reaches {extent:.3f} > 1: the plate must fit in [-1, 1]^2")


def num_combinations(scene: dict) -> int:
    """Shape x material combinations that balanced splits cycle through."""
    return len(scene["top_widths"]) * len(scene["top_offsets"]) * len(scene["poissons_ratios"])


@dataclass(frozen=True)
class SimulationInputs:
    """What `simulate` takes for one plate trajectory (`simulation_inputs`), and the sampled spec."""

    spec: PlateSpec
    rest: np.ndarray  # [N, 2]
    cells: np.ndarray  # [C, 3]
    fixed: np.ndarray  # [N] bool
    path: np.ndarray  # collider vertices per frame [T, K, 2]
    faces: np.ndarray  # collider segments [F, 2]
    material: Material
    solver: SolverConfig
    substeps: int

    def simulate(self):
        """(positions [T, N, 2], diagnostics): the trajectory's simulation (`sim.run.simulate`)."""
        return simulate(self.rest, self.cells, self.fixed, self.material, self.solver, [(self.path, self.faces)],
                        self.substeps)


def simulation_inputs(config: dict, combination: int, rng: np.random.Generator) -> SimulationInputs:
    """Sample combination's trajectory (0..num_combinations-1, shape-major) with rng and build its mesh,
    collider path, material and solver settings (the preset's substeps per frame)."""
    scene = config["scene"]
    n_nu = len(scene["poissons_ratios"])
    spec = sample_spec(scene, combination // n_nu, scene["poissons_ratios"][combination % n_nu], rng)
    rest, cells, fixed = plate_mesh(scene, spec.shape_id)
    path, faces = collider_path(scene, spec)
    substeps = int(scene["substeps"])
    return SimulationInputs(spec, rest, cells, fixed, path, faces, plate_material(scene, spec.poissons_ratio),
                            SolverConfig(dt=scene["frame_dt"] / substeps, **config["solver"]), substeps)


def make_trajectory(config: dict, combination: int, seed: int, sensor) -> Trajectory:
    """Simulate and observe one plate trajectory. combination: 0..num_combinations-1
    (shape-major); seed: drives collider sampling and sensor noise."""
    scene = config["scene"]
    rng = np.random.default_rng(seed)
    inputs = simulation_inputs(config, combination, rng)
    spec, rest, cells, fixed = inputs.spec, inputs.rest, inputs.cells, inputs.fixed
    path, faces, material = inputs.path, inputs.faces, inputs.material
    positions, diagnostics = inputs.simulate()
    points, offsets = pack_point_clouds([sensor.observe(positions[t], cells, path[t], faces, rng)
                                         for t in range(len(positions))])
    return Trajectory(
        rest_positions=rest,
        cells=cells,
        edges=cell_edges(cells),
        positions=positions,
        fixed=fixed,
        collider_faces=faces,
        collider_positions=path,
        points=points,
        point_offsets=offsets,
        youngs_modulus=float(scene["youngs_modulus"]),
        poissons_ratio=spec.poissons_ratio,
        seed=int(seed),
        params={
            "shape_id": spec.shape_id,
            "collider_radius": spec.collider_radius,
            "collider_start_x": spec.collider_start_x,
            "collider_travel": float(scene["collider"]["travel"]),
            "frame_dt": float(scene["frame_dt"]),
            "plane": material.plane,
        },
        diagnostics=diagnostics,
    )


def resolution(scene: dict) -> int:
    """The mesh resolution level of a plate scene config (`bench tradeoff`): nodes per side."""
    return int(scene["grid_nodes"])


def with_resolution(scene: dict, level: int) -> dict:
    """A copy of the scene config at mesh resolution `level` = nodes per side (level^2 nodes)."""
    if int(level) < 2:
        raise ValueError(f"plate mesh resolution must be >= 2 nodes per side, got {level}")
    return {**scene, "grid_nodes": int(level)}
