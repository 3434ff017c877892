"""Tissue Manipulation scene (GGNS paper, appendix "Tissue Manipulation"): a block of tissue with
a fixed bottom, one of whose top nodes is grasped by a rigid gripper and moved on a random path
in a vertical plane; a static liver occludes part of the tissue from the cameras.

The block is a structured tetrahedral mesh (`geometry.box_tet_mesh`: every hexahedron split into
6 tetrahedra), chosen over a mesher because the paper's numbers fit it: with 12 x 10 x 3 nodes it
has 360 nodes (paper: 361), its bottom layer is a third of them (the authors fix 121), and its
vertical spacing is the reference's smallest tissue edge (0.068). docs/tissue.md has the checks.
The grasped node is prescribed to follow the gripper (a fixed node with a moving position); the
gripper is one collider node in the graphs (`collider_positions` [T, 1, 3], no faces). The
gripper's shaft and the liver are occluders of the cameras only, not simulated.

Every quantity comes from the `scene` section of a generation config (conf/data/tissue.yaml).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..geometry import box_tet_mesh, cell_edges
from ..sim.material import Material
from ..sim.run import simulate
from ..sim.solver import SolverConfig
from ..trajectory import Trajectory, pack_point_clouds


DIM = 3  # spatial dimension of the scene


@dataclass(frozen=True)
class TissueSpec:
    """One sampled tissue trajectory: material, grasped node and gripper path."""

    material: int  # index into scene.materials
    grasp_candidate: int  # index into grasp_candidates(...)
    azimuth: float  # rad, direction of the vertical plane of motion
    waypoints: tuple[tuple[float, float], ...]  # (horizontal, vertical) offsets from the grasp point


def tissue_mesh(scene: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rest positions [N, 3], tetrahedra [C, 4] and fixed mask [N] (the bottom node layer)."""
    block = scene["block"]
    nodes = [int(n) for n in block["nodes"]]
    if len(nodes) != 3 or min(nodes) < 2:
        raise ValueError(f"scene.block.nodes must be 3 counts >= 2, got {block['nodes']}")
    positions, cells = box_tet_mesh(block["lo"], block["hi"], [n - 1 for n in nodes])
    fixed = np.isclose(positions[:, 2], float(block["lo"][2]))
    return positions, cells, fixed


def grasp_candidates(scene: dict, rest: np.ndarray) -> np.ndarray:
    """The `scene.gripper.candidates` top-layer nodes nearest the top face's centre (paper: the
    gripping point is drawn from 19 top mesh points), nearest first, ties by node index."""
    top = np.flatnonzero(np.isclose(rest[:, 2], float(scene["block"]["hi"][2])))
    centre = rest[top, :2].mean(axis=0)
    distance = np.round(np.linalg.norm(rest[top, :2] - centre, axis=1), 9)
    order = np.lexsort((top, distance))
    count = int(scene["gripper"]["candidates"])
    if not 1 <= count <= len(top):
        raise ValueError(f"scene.gripper.candidates must be in 1..{len(top)} (top nodes), got {count}")
    return top[order[:count]]


def grasped_patch(scene: dict, rest: np.ndarray, grasped: int) -> np.ndarray:
    """The top-layer nodes the gripper holds rigidly: those within `gripper.grasp_radius` of the
    grasped node (itself included), indices in increasing order. A patch instead of the single
    node: a single prescribed node is a point load, whose strains grow without bound as the mesh is
    refined and under which Newton stalls for nu = 0.49 (docs/tissue.md)."""
    top = np.isclose(rest[:, 2], float(scene["block"]["hi"][2]))
    near = np.linalg.norm(rest - rest[grasped], axis=1) <= float(scene["gripper"]["grasp_radius"])
    return np.flatnonzero(top & near)


def sample_spec(scene: dict, material: int, rng: np.random.Generator) -> TissueSpec:
    """Grasp candidate ~ uniform; plane azimuth ~ U[0, 2 pi); `gripper.waypoints` waypoints with
    horizontal offset ~ U[-reach, reach] and lift ~ U[min_lift, 1] x lift (the first one lifts)."""
    gripper = scene["gripper"]
    candidate = int(rng.integers(int(gripper["candidates"])))
    azimuth = float(rng.uniform(0.0, 2.0 * math.pi))
    waypoints = tuple((float(rng.uniform(-gripper["reach"], gripper["reach"])),
                       float(rng.uniform(gripper["min_lift"], 1.0) * gripper["lift"]))
                      for _ in range(int(gripper["waypoints"])))
    return TissueSpec(material, candidate, azimuth, waypoints)


def gripper_path(scene: dict, spec: TissueSpec, start: np.ndarray) -> np.ndarray:
    """Gripper positions per recorded step [T, 3]: from `start` through the waypoints, one every
    `gripper.segment_steps` steps, linearly, in the vertical plane of direction `spec.azimuth`,
    then held (the speed does not depend on T: a shorter preset sees the path's beginning)."""
    T = int(scene["num_steps"])
    horizontal = np.array([math.cos(spec.azimuth), math.sin(spec.azimuth), 0.0])
    offsets = np.array([[0.0, 0.0], *spec.waypoints])  # [W + 1, 2]
    knots = float(scene["gripper"]["segment_steps"]) * np.arange(len(offsets))
    s = np.arange(T, dtype=np.float64)
    u, w = np.interp(s, knots, offsets[:, 0]), np.interp(s, knots, offsets[:, 1])
    return start[None] + u[:, None] * horizontal[None] + w[:, None] * np.array([0.0, 0.0, 1.0])[None]


def liver_mesh(scene: dict) -> tuple[np.ndarray, np.ndarray]:
    """The static occluding liver: an ellipsoid (`scene.liver.centre`, `radii`), vertices [V, 3] and
    outward triangles [F, 3]."""
    import trimesh  # here, not at the top: with networkx and shapely 0.4 s of every process's start, for two shapes

    liver = scene["liver"]
    sphere = trimesh.creation.icosphere(subdivisions=int(liver.get("subdivisions", 2)))
    vertices = np.asarray(sphere.vertices) * np.asarray(liver["radii"], dtype=np.float64) + np.asarray(
        liver["centre"], dtype=np.float64)
    return vertices, np.asarray(sphere.faces, dtype=np.int64)


def gripper_shaft(scene: dict, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gripper's shaft as an occluder: a vertical box of `gripper.shaft_width` x width x
    `gripper.shaft_length` standing on the grasp point. Vertices [8, 3], triangles [12, 3]."""
    import trimesh

    width, length = float(scene["gripper"]["shaft_width"]), float(scene["gripper"]["shaft_length"])
    box = trimesh.creation.box(extents=(width, width, length))
    vertices = np.asarray(box.vertices) + position + np.array([0.0, 0.0, length / 2 + 1e-3])
    return vertices, np.asarray(box.faces, dtype=np.int64)


def check_config(config: dict) -> None:
    """Refuse a configuration before any work starts: bad materials, solver settings, a block that
    leaves the task space [-1, 1]^3 or gripper settings that cannot be sampled."""
    scene = config["scene"]
    if not scene["materials"]:
        raise ValueError("scene.materials must list at least one {poissons_ratio, youngs_modulus}")
    for index in range(len(scene["materials"])):
        Material.listed(scene, index)
    SolverConfig(dt=scene["frame_dt"] / int(scene["substeps"]), **config["solver"])
    if int(scene["num_steps"]) < 2:
        raise ValueError(f"scene.num_steps must be >= 2, got {scene['num_steps']}")
    lo, hi = np.asarray(scene["block"]["lo"], dtype=float), np.asarray(scene["block"]["hi"], dtype=float)
    if np.abs(np.concatenate([lo, hi])).max() > 1.0 + 1e-9:
        raise ValueError(f"scene.block {lo.tolist()} .. {hi.tolist()} must lie in [-1, 1]^3")
    rest, _, _ = tissue_mesh(scene)
    grasp_candidates(scene, rest)
    gripper = scene["gripper"]
    if int(gripper["waypoints"]) < 1 or not 0 <= float(gripper["min_lift"]) <= 1 or float(gripper["segment_steps"]) <= 0:
        raise ValueError("scene.gripper needs waypoints >= 1, 0 <= min_lift <= 1 and segment_steps > 0")
    reach = float(gripper["reach"]) + float(np.abs(rest[:, :2]).max())
    if reach > 1.0 + 1e-9 or float(hi[2] + gripper["lift"]) > 1.0 + 1e-9:
        raise ValueError("the gripper's reach and lift would take the grasped node out of [-1, 1]^3")


def num_combinations(scene: dict) -> int:
    """Materials that balanced splits cycle through (grasp point and path are drawn per trajectory)."""
    return len(scene["materials"])


def make_trajectory(config: dict, combination: int, seed: int, sensor) -> Trajectory:
    """Simulate and observe one tissue trajectory. combination: the material index; seed: drives
    the grasp point, the gripper path and the sensor noise."""
    scene = config["scene"]
    rng = np.random.default_rng(seed)
    spec = sample_spec(scene, combination, rng)
    rest, cells, fixed = tissue_mesh(scene)
    grasped = int(grasp_candidates(scene, rest)[spec.grasp_candidate])
    held = grasped_patch(scene, rest, grasped)
    fixed = fixed.copy()
    fixed[held] = True
    path = gripper_path(scene, spec, rest[grasped])
    T = len(path)
    targets = np.repeat(rest[None], T, axis=0)
    targets[:, held] += (path - path[0])[:, None, :]
    material = Material.listed(scene, spec.material)
    substeps = int(scene["substeps"])
    solver = SolverConfig(dt=scene["frame_dt"] / substeps, **config["solver"])
    collider = path[:, None, :]  # the gripper: one collider node, no contact surface
    no_faces = np.zeros((0, 3), dtype=np.int64)
    positions, diagnostics = simulate(rest, cells, fixed, material, solver, [(collider, no_faces)], substeps,
                                      fixed_paths=targets)
    liver = liver_mesh(scene)
    shaft, shaft_faces = gripper_shaft(scene, np.zeros(3))  # built once, moved with the gripper
    points, offsets = pack_point_clouds([sensor.observe(positions[t], cells, None, None, rng,
                                                        occluders=[liver, (shaft + path[t], shaft_faces)])
                                         for t in range(T)])
    return Trajectory(
        rest_positions=rest,
        cells=cells,
        edges=cell_edges(cells),
        positions=positions,
        fixed=fixed,
        collider_faces=no_faces,
        collider_positions=collider,
        points=points,
        point_offsets=offsets,
        youngs_modulus=material.youngs_modulus,
        poissons_ratio=material.poissons_ratio,
        seed=int(seed),
        params={
            "grasped_node": grasped,
            "grasped_nodes": len(held),
            "gripper_azimuth": spec.azimuth,
            "frame_dt": float(scene["frame_dt"]),
        },
        diagnostics=diagnostics,
    )


def resolution(scene: dict) -> int:
    """The mesh resolution level of a tissue scene config (`bench tradeoff`): nodes along x."""
    return int(scene["block"]["nodes"][0])


def with_resolution(scene: dict, level: int) -> dict:
    """A copy of the scene config at mesh resolution `level` = nodes along x (`bench tradeoff`).
    The block keeps its extent; the element counts along y and z are the preset's scaled by the
    same factor as along x, (level - 1) / (nodes_x - 1), rounded, at least one (2 node layers), so
    the elements keep the preset's near-cubic shape and the preset maps to itself ([10, 9, 4]:
    level 7 gives [7, 6, 3] = 126 nodes, 13 gives [13, 12, 5] = 780, 19 gives [19, 17, 7] = 2261).
    The grasp radius stays in metres (a finer mesh holds more nodes of the same patch) but is
    scaled with the coarser of the x and y spacings on a coarser mesh, so the gripper holds the
    grasped node's neighbours there too, never a single node (a point load, `grasped_patch`);
    the grasp candidates are capped at the top layer's node count."""
    nodes = [int(n) for n in scene["block"]["nodes"]]
    level = int(level)
    if level < 2:
        raise ValueError(f"tissue mesh resolution must be >= 2 nodes along x, got {level}")
    factor = (level - 1) / (nodes[0] - 1)
    scaled = [level] + [max(1, round((n - 1) * factor)) + 1 for n in nodes[1:]]
    gripper = dict(scene["gripper"])
    coarser = max((n - 1) / (m - 1) for n, m in zip(nodes[:2], scaled[:2]))  # spacing ratio, x or y
    gripper["grasp_radius"] = float(gripper["grasp_radius"]) * max(1.0, coarser)
    gripper["candidates"] = min(int(gripper["candidates"]), scaled[0] * scaled[1])
    return {**scene, "block": {**scene["block"], "nodes": scaled}, "gripper": gripper}
