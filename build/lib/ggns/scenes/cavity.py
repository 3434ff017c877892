"""Cavity Grasping scene (GGNS paper, appendix "Cavity Grasping"): a hollow truncated cone with its
bottom rim fixed is squeezed by a parallel two-finger gripper modelled on the Panda hand. The
gripper starts open at a random collision-free position in a box around the cavity's centre,
moves as fast as allowed (a speed limit per step) to the grasp pose and then closes its fingers
at constant velocity until the last step.

Mesh (docs/cavity.md has the arithmetic): a structured tetrahedral wall ONE element thick, with
`ring_nodes` nodes per ring, `levels` rings up the height and two walls (inner, outer): with
25 x 15 x 2 = 750 nodes (paper: 750). Every node lies on the wall's boundary, so the models' graph
is the boundary triangulation (`Trajectory.edges`: the edges of the boundary triangles, a closed
surface of genus 1 with exactly E = 3 V undirected edges, 4,500 directed for 750 nodes: the
paper's count), while the physics runs on the tetrahedra (`Trajectory.cells`; volume IoU and the
cameras use them too). Nodes are numbered ring by ring from the bottom: level j, wall k (0 inner,
1 outer), angle i has index (2 j + k) ring_nodes + i, so the fixed bottom rim is nodes
0 .. 2 ring_nodes - 1 (the reference fixes its first ring, nodes 0-29).

Gripper: two fingers, each a box (`gripper.finger`: width across, height, thickness) whose
surface is a structured triangle mesh (the boundary of `geometry.box_tet_mesh` with
`finger.nodes` nodes per axis): 2 x 318 = 636 collider nodes (paper: 636). The fingers are the
simulator's rigid contact surfaces (node-to-surface, frictionless: the fixed bottom rim holds the
cavity, so no friction is needed to squeeze it) and occlude the cameras. In the trajectory both
fingers form one collider ([T, 636, 3] vertices, their triangles).

Cameras: `observe_trajectory` (the fingers occlude; the wall's boundary is found once). The
generator calls it after the simulation, and again on stored states to give the same trajectories
other cameras (`states_from` in a data preset, `ggns.data.generate`).

"Radii" (paper: "between 87.5 % and 50 % of the maximum possible gripping width") are read as the
cavity's outer DIAMETER at its bottom and at its top, each drawn from U[0.5, 0.875] x the
gripper's maximum opening, so that the open gripper straddles every cavity.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..geometry import boundary_facets, box_tet_mesh, signed_volumes
from ..sim.material import Material
from ..sim.run import simulate
from ..sim.solver import SolverConfig
from ..trajectory import Trajectory, pack_point_clouds

DIM = 3  # spatial dimension of the scene


@dataclass(frozen=True)
class CavitySpec:
    """One sampled cavity trajectory."""

    material: int  # index into scene.materials
    bottom_diameter: float  # outer diameter at the bottom rim
    top_diameter: float  # outer diameter at the top rim
    azimuth: float  # rad, direction of the closing axis in the horizontal plane
    grasp_height: float  # fraction of the cavity's height at the fingers' centre
    start: tuple[float, float, float]  # gripper centre at t = 0
    squeeze: float  # final gap = (1 - squeeze) x the outer diameter at the grasp height


def surface_edges(facets: np.ndarray) -> np.ndarray:
    """Unique undirected edges [E, 2] (i < j, sorted) of triangles [F, 3]."""
    pairs = np.concatenate([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def tube_mesh(ring_nodes: int, levels: int, bottom_radius: float, top_radius: float, thickness: float,
              bottom_z: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """A truncated-cone wall one tetrahedron thick: positions [2 L n, 3] (numbered as the module
    docstring says) and right-handed tetrahedra [6 n (L - 1), 4]. Radii are the OUTER wall's; the
    inner wall lies `thickness` inside it (measured horizontally)."""
    n, L = int(ring_nodes), int(levels)
    if n < 3 or L < 2:
        raise ValueError(f"a tube needs ring_nodes >= 3 and levels >= 2, got {n} and {L}")
    if not 0 < thickness < min(bottom_radius, top_radius):
        raise ValueError(f"wall thickness {thickness} must be in (0, the smallest outer radius "
                         f"{min(bottom_radius, top_radius)})")
    # the structured box in (angle index, level, wall) coordinates; column i = n is wrapped onto i = 0.
    # The Kuhn split is the same in every hexahedron, so the wrapped mesh stays conforming.
    grid, cells = box_tet_mesh([0, 0, 0], [n, L - 1, 1], [n, L - 1, 1])
    i, j, k = np.rint(grid).astype(np.int64).T
    new_index = (2 * j + k) * n + i % n
    cells = new_index[cells]
    angle = 2 * math.pi * np.arange(n) / n
    jj, kk, ii = np.meshgrid(np.arange(L), np.arange(2), np.arange(n), indexing="ij")
    jj, kk, ii = jj.reshape(-1), kk.reshape(-1), ii.reshape(-1)
    s = jj / (L - 1)
    radius = bottom_radius + (top_radius - bottom_radius) * s - (1 - kk) * thickness
    positions = np.stack([radius * np.cos(angle[ii]), radius * np.sin(angle[ii]), bottom_z + height * s], axis=1)
    negative = signed_volumes(positions, cells) < 0
    cells[negative] = cells[negative][:, [1, 0, 2, 3]]
    return positions, cells


def finger_mesh(scene: dict, coarse: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """One finger's surface in the gripper frame with the finger's inner face at a = 0 and the finger
    on the a > 0 side: vertices [V, 3] in (closing axis a, across b, up z) and outward triangles [F, 3].
    coarse=True: the same box as 8 vertices and 12 triangles (the simulator's contact surface: the
    same geometry, 50x fewer triangles to test each node against)."""
    finger = scene["gripper"]["finger"]
    width, height, thickness = (float(finger[k]) for k in ("width", "height", "thickness"))
    nodes = [2, 2, 2] if coarse else [int(v) for v in finger["nodes"]]  # along a (thickness), b (width), z (height)
    positions, cells = box_tet_mesh([0.0, -width / 2, -height / 2], [thickness, width / 2, height / 2],
                                    [m - 1 for m in nodes])
    facets = boundary_facets(cells, positions)
    used = np.unique(facets)
    renumber = np.full(len(positions), -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    return positions[used], renumber[facets]


def gripper_vertices(finger: np.ndarray, centre: np.ndarray, azimuth: float, gap: float) -> np.ndarray:
    """Both fingers' vertices [2 V, 3] in the world: inner faces at +-gap/2 along the closing axis
    (horizontal, direction `azimuth`) from `centre`; the second finger is the first one turned by pi
    about the vertical."""
    a = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    b = np.array([-math.sin(azimuth), math.cos(azimuth), 0.0])
    z = np.array([0.0, 0.0, 1.0])
    local = finger + np.array([gap / 2, 0.0, 0.0])
    plus = local[:, :1] * a + local[:, 1:2] * b + local[:, 2:] * z
    minus = -local[:, :1] * a - local[:, 1:2] * b + local[:, 2:] * z
    return np.concatenate([plus, minus]) + centre


def cavity_mesh(scene: dict, spec: CavitySpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rest positions [N, 3], tetrahedra [C, 4] and fixed mask [N] (the bottom rim: both walls' lowest ring)."""
    cav = scene["cavity"]
    positions, cells = tube_mesh(cav["ring_nodes"], cav["levels"], spec.bottom_diameter / 2, spec.top_diameter / 2,
                                 float(cav["thickness"]), float(cav["bottom_z"]), float(cav["height"]))
    fixed = np.zeros(len(positions), dtype=bool)
    fixed[: 2 * int(cav["ring_nodes"])] = True
    return positions, cells, fixed


def _outer_radius(spec: CavitySpec, s: float) -> float:
    return (spec.bottom_diameter + (spec.top_diameter - spec.bottom_diameter) * s) / 2


def grasp_centre(scene: dict, spec: CavitySpec) -> np.ndarray:
    cav = scene["cavity"]
    return np.array([0.0, 0.0, float(cav["bottom_z"]) + spec.grasp_height * float(cav["height"])])


def _fingers_clear(scene: dict, spec: CavitySpec, rest: np.ndarray, centre: np.ndarray, gap: float) -> bool:
    """Whether both fingers (boxes, with `gripper.clearance` around them) are free of every rest node."""
    finger = scene["gripper"]["finger"]
    margin = float(scene["gripper"]["clearance"])
    a = np.array([math.cos(spec.azimuth), math.sin(spec.azimuth), 0.0])
    b = np.array([-math.sin(spec.azimuth), math.cos(spec.azimuth), 0.0])
    rel = rest - centre
    u, v, w = rel @ a, rel @ b, rel[:, 2]
    across = np.abs(v) <= float(finger["width"]) / 2 + margin
    up = np.abs(w) <= float(finger["height"]) / 2 + margin
    thick = float(finger["thickness"])
    inside = (np.abs(u) >= gap / 2 - margin) & (np.abs(u) <= gap / 2 + thick + margin)
    return not (across & up & inside).any()


def sample_spec(scene: dict, material: int, rng: np.random.Generator) -> CavitySpec:
    """Diameters ~ U[min, max] x opening (bottom and top independently), closing azimuth ~ U[0, pi),
    grasp height ~ U[grasp_height], squeeze ~ U[squeeze], and a start centre ~ uniform in the box
    `gripper.start_box` around the grasp centre, redrawn until the open fingers are clear of the
    cavity at every point of the straight approach (checked at `gripper.path_checks` points)."""
    cav, grip = scene["cavity"], scene["gripper"]
    opening = float(grip["max_opening"])
    lo, hi = (float(v) for v in cav["diameter_fraction"])
    bottom, top = (float(rng.uniform(lo, hi) * opening) for _ in range(2))
    azimuth = float(rng.uniform(0.0, math.pi))
    height = float(rng.uniform(*grip["grasp_height"]))
    squeeze = float(rng.uniform(*grip["squeeze"]))
    spec = CavitySpec(material, bottom, top, azimuth, height, (0.0, 0.0, 0.0), squeeze)
    rest, _, _ = cavity_mesh(scene, spec)
    goal = grasp_centre(scene, spec)
    box = np.asarray(grip["start_box"], dtype=np.float64)
    for _ in range(int(grip["max_start_draws"])):
        start = goal + rng.uniform(-box, box)
        checks = np.linspace(0.0, 1.0, int(grip["path_checks"]))
        if all(_fingers_clear(scene, spec, rest, start + c * (goal - start), opening) for c in checks):
            return CavitySpec(material, bottom, top, azimuth, height, tuple(float(v) for v in start), squeeze)
    raise ValueError(f"no collision-free gripper start found in {grip['max_start_draws']} draws from "
                     f"scene.gripper.start_box {box.tolist()} (diameters {bottom:.3f}, {top:.3f}): enlarge "
                     "max_opening or shrink the cavity")


def gripper_schedule(scene: dict, spec: CavitySpec) -> tuple[np.ndarray, np.ndarray, int]:
    """Gripper centre per step [T, 3], gap between the fingers' inner faces per step [T] and the
    step at which closing starts: the centre moves in a straight line at `gripper.speed` per step
    (the last move shorter) to the grasp centre; then the gap closes at the constant
    `gripper.closing_speed` per step from the maximum opening to (1 - squeeze) x the cavity's outer
    diameter at the grasp height, and the fingers hold still (the cavity settles) until the end."""
    grip = scene["gripper"]
    T = int(scene["num_steps"])
    start, goal = np.asarray(spec.start), grasp_centre(scene, spec)
    distance = float(np.linalg.norm(goal - start))
    arrive = int(math.ceil(distance / float(grip["speed"]) - 1e-9))
    t = np.arange(T, dtype=np.float64)
    fraction = np.clip(t * float(grip["speed"]) / max(distance, 1e-12), 0.0, 1.0)
    centres = start + fraction[:, None] * (goal - start)
    opening = float(grip["max_opening"])
    final_gap = (1 - spec.squeeze) * 2 * _outer_radius(spec, spec.grasp_height)
    gaps = np.maximum(opening - float(grip["closing_speed"]) * np.clip(t - arrive, 0.0, None), final_gap)
    return centres, gaps, arrive


def check_config(config: dict) -> None:
    """Refuse a configuration before any work starts."""
    scene = config["scene"]
    if not scene["materials"]:
        raise ValueError("scene.materials must list at least one {poissons_ratio, youngs_modulus}")
    for index in range(len(scene["materials"])):
        Material.listed(scene, index)
    SolverConfig(dt=scene["frame_dt"] / int(scene["substeps"]), **config["solver"])
    T = int(scene["num_steps"])
    if T < 2:
        raise ValueError(f"scene.num_steps must be >= 2, got {scene['num_steps']}")
    cav, grip = scene["cavity"], scene["gripper"]
    lo, hi = (float(v) for v in cav["diameter_fraction"])
    if not 0 < lo <= hi < 1:
        raise ValueError(f"scene.cavity.diameter_fraction must be 0 < min <= max < 1 of the gripper's opening "
                         f"(the open gripper must straddle the cavity), got {[lo, hi]}")
    opening = float(grip["max_opening"])
    thickness = float(cav["thickness"])
    if not 0 < thickness < lo * opening / 2:
        raise ValueError(f"scene.cavity.thickness {thickness} must be in (0, the smallest outer radius {lo * opening / 2})")
    for name in ("grasp_height", "squeeze"):
        a, b = (float(v) for v in grip[name])
        if not 0 <= a <= b <= 1:
            raise ValueError(f"scene.gripper.{name} must be a range within [0, 1], got {[a, b]}")
    if (1 - float(grip["squeeze"][1])) * lo * opening <= 2 * thickness:
        raise ValueError("scene.gripper.squeeze: the largest squeeze of the narrowest cavity would press its inner "
                         "walls together (self-contact is not simulated)")
    for name in ("speed", "closing_speed"):
        if not float(grip[name]) > 0:
            raise ValueError(f"scene.gripper.{name} must be > 0 (per step), got {grip[name]}")
    finger = grip["finger"]
    if len(finger["nodes"]) != 3 or min(int(v) for v in finger["nodes"]) < 2:
        raise ValueError(f"scene.gripper.finger.nodes must be 3 counts >= 2, got {finger['nodes']}")
    reach = opening / 2 + float(finger["thickness"]) + float(np.abs(grip["start_box"]).max())
    top = float(cav["bottom_z"]) + float(cav["height"])
    if reach > 1.0 or float(cav["bottom_z"]) < -1.0 or top + float(finger["height"]) / 2 + float(grip["start_box"][2]) > 1.0:
        raise ValueError("the cavity or the gripper's start box leaves the task space [-1, 1]^3")
    tube_mesh(cav["ring_nodes"], cav["levels"], lo * opening / 2, lo * opening / 2, thickness, 0.0, 1.0)


def num_combinations(scene: dict) -> int:
    """Materials that balanced splits cycle through (shape and gripper are drawn per trajectory)."""
    return len(scene["materials"])


def make_trajectory(config: dict, combination: int, seed: int, sensor) -> Trajectory:
    """Simulate and observe one cavity trajectory. combination: the material index; seed: drives the
    cavity's shape, the gripper's start, grasp pose and squeeze, and the sensor noise."""
    scene = config["scene"]
    rng = np.random.default_rng(seed)
    spec = sample_spec(scene, combination, rng)
    rest, cells, fixed = cavity_mesh(scene, spec)
    finger, finger_faces = finger_mesh(scene)
    centres, gaps, arrive = gripper_schedule(scene, spec)
    T = len(centres)
    vertices = np.stack([gripper_vertices(finger, centres[t], spec.azimuth, gaps[t]) for t in range(T)])
    V = len(finger)
    faces = np.concatenate([finger_faces, finger_faces + V])
    box, box_faces = finger_mesh(scene, coarse=True)
    boxes = np.stack([gripper_vertices(box, centres[t], spec.azimuth, gaps[t]) for t in range(T)])
    material = Material.listed(scene, spec.material)
    substeps = int(scene["substeps"])
    solver = SolverConfig(dt=scene["frame_dt"] / substeps, **config["solver"])
    positions, diagnostics = simulate(rest, cells, fixed, material, solver,
                                      [(boxes[:, :8], box_faces), (boxes[:, 8:], box_faces)], substeps)
    diagnostics["finger_penetration"] = finger_penetration(positions, cells, vertices)
    unobserved = Trajectory(
        rest_positions=rest,
        cells=cells,
        edges=surface_edges(boundary_facets(cells)),
        positions=positions,
        fixed=fixed,
        collider_faces=faces,
        collider_positions=vertices,
        points=np.zeros((0, 3), dtype=np.float32),
        point_offsets=np.zeros(T + 1, dtype=np.int64),
        youngs_modulus=material.youngs_modulus,
        poissons_ratio=material.poissons_ratio,
        seed=int(seed),
        params={
            "bottom_diameter": spec.bottom_diameter,
            "top_diameter": spec.top_diameter,
            "gripper_azimuth": spec.azimuth,
            "grasp_height": spec.grasp_height,
            "squeeze": spec.squeeze,
            "closing_step": int(arrive),
            "frame_dt": float(scene["frame_dt"]),
        },
        diagnostics=diagnostics,
    )
    return observe_trajectory(unobserved, sensor, rng)


def observe_trajectory(trajectory: Trajectory, sensor, rng: np.random.Generator | None = None) -> Trajectory:
    """The trajectory with the point clouds `sensor` takes of its states (any it had are replaced):
    the fingers (its collider) occlude and give no points, the wall's boundary is found once. rng:
    the sensor's noise draws (needed when its noise_std > 0)."""
    surface = boundary_facets(trajectory.cells, trajectory.rest_positions)
    points, offsets = pack_point_clouds([
        sensor.observe(trajectory.positions[t], trajectory.cells, trajectory.collider_positions[t],
                       trajectory.collider_faces, rng, surface=surface)
        for t in range(trajectory.num_steps)])
    return dataclasses.replace(trajectory, points=points, point_offsets=offsets)


def finger_penetration(positions: np.ndarray, cells: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Per step [T]: the deepest finger vertex inside the cavity's wall (m, >= 0; Open3D's signed
    distance to the wall's closed boundary surface). The simulator's contact keeps cavity NODES out
    of the fingers; a finger's edges and corners can still pass between nodes of a coarse mesh,
    which this measures."""
    import open3d as o3d

    facets = boundary_facets(cells, positions[0]).astype(np.uint32)
    depth = np.zeros(len(positions))
    for t in range(len(positions)):
        lo, hi = positions[t].min(0), positions[t].max(0)
        near = ((vertices[t] >= lo) & (vertices[t] <= hi)).all(1)
        if not near.any():
            continue
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(positions[t].astype(np.float32)), o3d.core.Tensor(facets))
        phi = scene.compute_signed_distance(o3d.core.Tensor(vertices[t][near].astype(np.float32))).numpy()
        depth[t] = float(max(0.0, -phi.min()))
    return depth


def resolution(scene: dict) -> int:
    """The mesh resolution level of a cavity scene config (`bench tradeoff`): nodes per ring."""
    return int(scene["cavity"]["ring_nodes"])


def with_resolution(scene: dict, level: int) -> dict:
    """A copy of the scene config at mesh resolution `level` = nodes per ring (`bench tradeoff`). The
    rings up the height are the preset's scaled by the same factor, level / ring_nodes, rounded (at
    least 2), so the wall's elements keep their shape; the wall stays one element thick (25 -> 15
    levels, the preset; 16 -> 10 levels, 320 nodes; 40 -> 23 levels, 1,840 nodes)."""
    cav = scene["cavity"]
    level = int(level)
    if level < 3:
        raise ValueError(f"cavity mesh resolution must be >= 3 nodes per ring, got {level}")
    levels = max(2, round((int(cav["levels"]) - 1) * level / int(cav["ring_nodes"])) + 1)
    return {**scene, "cavity": {**cav, "ring_nodes": level, "levels": levels}}
