"""What the point clouds give GGNS on a 3D task, and what it does with them (the cavity's grounding gain):
python experiments/cavity_diagnosis/cavity_diagnosis.py --dataset cavity_cpu [--cameras cavity_cpu_cam2,cavity_cpu_cam1]
    [--checkpoint CKPT] [--split val --trajectories 9] [--output docs/results/cavity_diagnosis]

Data (no model): per camera preset, points per step, the share of free mesh nodes with a point within a
voxel (`--near`, default the preset's voxel size) per step, split into the inner and outer wall (nodes
nearer to / farther from the vertical axis than the mean of their height) and the nodes near a finger
(within `--finger` of a collider vertex at that step), the mean number of points within the graph's
mesh-point radius per free node, the RMS per-step motion of the free nodes (all, near a finger, the 10 %
that move most) against the training noise and the points' spacing (median nearest-neighbour distance),
and the true displacement from S_0 split along the true surface normal / tangential by the same groups.

Motion along the surface from the shape (no model): how much of the true tangential motion the true
shape determines if the wall does not stretch. Each step's motion across the surface (along the vertex
normal at S_t) is taken as known, the motion along it (two tangent coordinates per free node) is the
least-squares solution that keeps every tetrahedron edge's length (linearized at S_{t-1}; fixed nodes
held), and the steps' solutions are summed from S_0: `shape_tangential`. Reported for --dataset (not
again for the --cameras presets, which observe the same states) by material and group, as the share of
the true tangential displacement from S_0 (and of each step's) left unexplained (0: the shape and no
stretch give it all, 1: no better than none, above 1: worse), beside how much the true motion stretches
the edges (RMS edge-length change over RMS relative motion of the edge's ends).

With a checkpoint, on the first n trajectories of the split:
- rollouts from S_0 with a point cloud every step and without: the squared error per free node split by
  direction (along the true vertex normal / tangential) and group (seen at >= half the steps within the
  voxel, never seen; inner, outer wall; near a finger at that step, far), by material, and over time;
  the same split of the mesh held at S_0 (static: the true displacement);
- the truth handed in: one step from the true state S_t, with and without the point cloud, against
  predicting no motion (the one-step ratio), for every t;
- a perturbed truth: one step from S_t + delta (delta per free node and coordinate ~ N(0, sigma^2), or a
  smooth field of that std, `ggns.models.training_noise.smooth_field`, wavelength `--field-wavelength`;
  sigma = `--sigma`, default the model's training noise), with and without the point cloud; the share
  of delta's squared size left in the prediction's error (normal and tangential, seen and never seen)
  after the true step's own motion is taken out: 1.0 keeps the perturbation, 0.0 removes it. A model
  that reads the points removes the normal part of the seen nodes' perturbation with them and not
  without them.

Writes <output>/diagnosis.md and diagnosis.json (with the command and the git commit). A diagnostic for
docs/experiments/cavity_diagnosis.md, not a library command."""
from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from scipy.spatial import cKDTree

from ggns.batch import TrajectoryBatch
from ggns.data.module import SimulationDataModule
from ggns.evaluation.evaluate import split_trajectories
from ggns.evaluation.observability import SEEN_AT_LEAST, normal_tangential, vertex_normals
from ggns.evaluation.rollout import rollout
from ggns.evaluation.schedules import EveryK, Never, effective_schedule
from ggns.geometry import boundary_facets, cell_edges
from ggns.models.training_noise import smooth_field
from ggns.pretrained import load_model
from ggns.reports import markdown_table, write_json, write_text

ROOT = Path(__file__).resolve().parents[2]  # the checkout
GROUPS = ("all", "seen", "never_seen", "inner", "outer", "near_finger", "far")
PERTURBATIONS = ("node", "field")  # per node and coordinate; a smooth field (`smooth_field`)


def wall_sides(rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inner, outer) [N] bool: a node nearer to the vertical axis through the rest mesh's centre than
    the mean of the nodes at its height is on the inner wall (every height level of the cavity's tube
    holds one inner and one outer ring)."""
    centre = rest[:, :2].mean(axis=0)
    radial = np.linalg.norm(rest[:, :2] - centre, axis=1)
    level = np.round(rest[:, 2], 6)
    inner = np.zeros(len(rest), dtype=bool)
    for z in np.unique(level):
        at = level == z
        inner[at] = radial[at] < radial[at].mean()
    return inner, ~inner


def nearest_distance(queries: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    if not len(cloud):
        return np.full(len(queries), np.inf)
    return cKDTree(cloud).query(queries, k=1)[0]


def per_step_groups(traj, near: float, finger: float) -> dict[str, np.ndarray]:
    """{group: [T, N] bool} for the free nodes (module docstring); seen / never_seen over the whole
    trajectory (seen at >= half the steps, never at none), the others per step."""
    steps, nodes = traj.positions.shape[:2]
    free = ~traj.fixed
    hit = np.stack([nearest_distance(traj.positions[t], traj.point_cloud(t)) <= near for t in range(steps)])
    fraction = hit.mean(axis=0)
    at_finger = np.stack([nearest_distance(traj.positions[t], traj.collider_positions[t]) <= finger
                          for t in range(steps)])
    inner, outer = wall_sides(traj.rest_positions)
    every = np.ones((steps, nodes), dtype=bool)
    groups = {"all": every, "seen": every & (fraction >= SEEN_AT_LEAST), "never_seen": every & (fraction == 0),
              "inner": every & inner, "outer": every & outer, "near_finger": at_finger, "far": ~at_finger}
    return {g: m & free for g, m in groups.items()} | {"_hit": hit & free}


def tangent_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents [N, 3] orthogonal to each other and to the unit `normals` [N, 3]."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    first = np.cross(normals, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return first, np.cross(normals, first)


def shape_tangential(before: np.ndarray, after: np.ndarray, edges: np.ndarray, facets: np.ndarray,
                     fixed: np.ndarray, regularization: float = 1e-9) -> np.ndarray:
    """The motion along the surface [N, 3] that the shape at `after` [N, 3] determines if the wall does
    not stretch: with each free node's motion across the surface (along its vertex normal at `after`)
    taken from the truth, its two tangent coordinates minimize the squared length change of `edges`
    [E, 2] linearized at `before` (edge directions there), fixed nodes held (a tiny Tikhonov term picks
    the least motion where the edges leave it open, e.g. a rotation about an axis of symmetry)."""
    motion = after - before
    normals = vertex_normals(after, facets)
    tangents = tangent_basis(normals)
    across = (motion * normals).sum(axis=1)
    free = ~np.asarray(fixed, dtype=bool)
    column = np.full(len(motion), -1, dtype=np.int64)
    column[free] = np.arange(int(free.sum()))
    i, j = edges[:, 0], edges[:, 1]
    direction = before[j] - before[i]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    normal_motion = across[:, None] * normals * free[:, None]
    known = (direction * (normal_motion[j] - normal_motion[i])).sum(axis=1)  # each edge's stretch from it
    rows, columns, values = [], [], []
    for node, sign in ((j, 1.0), (i, -1.0)):
        ok = free[node]
        for k, tangent in enumerate(tangents):
            rows.append(np.flatnonzero(ok))
            columns.append(2 * column[node[ok]] + k)
            values.append(sign * (direction[ok] * tangent[node[ok]]).sum(axis=1))
    a = sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(columns))),
                          shape=(len(edges), 2 * int(free.sum())))
    coefficients = sparse_linalg.spsolve((a.T @ a + regularization * sparse.eye(a.shape[1])).tocsc(), -(a.T @ known))
    along = np.zeros_like(motion)
    along[free] = coefficients[0::2, None] * tangents[0][free] + coefficients[1::2, None] * tangents[1][free]
    return along


def tangential_part(vectors: np.ndarray, normals: np.ndarray) -> np.ndarray:
    return vectors - (vectors * normals).sum(axis=1, keepdims=True) * normals


SHAPE_GROUPS = ("all", "near_finger", "far")


def shape_report(trajs: list, groups: list[dict]) -> dict:
    """`shape_tangential` over the trajectories (module docstring): {material or "all": {group: share of the
    true tangential displacement left, "per_step_<group>": the same of each step's, "stretch_ratio"}}."""
    sums: dict = {}
    for traj, group in zip(trajs, groups):
        x = traj.positions.astype(np.float64)
        facets, edges = boundary_facets(traj.cells, traj.rest_positions), cell_edges(traj.cells)
        total = np.zeros_like(x[0])
        lengths = np.linalg.norm(x[:, edges[:, 1]] - x[:, edges[:, 0]], axis=2)  # [T, E]
        for key in ("all", f"{traj.poissons_ratio:g}"):
            sums.setdefault(key, {g: np.zeros(4) for g in SHAPE_GROUPS} | {"stretch": np.zeros(2)})
        for t in range(1, traj.num_steps):
            step = shape_tangential(x[t - 1], x[t], edges, facets, traj.fixed)
            total += step
            normals = vertex_normals(x[t], facets)
            true_step = tangential_part(x[t] - x[t - 1], normals)
            true_total = tangential_part(x[t] - x[0], normals)
            left_total = ((tangential_part(total, normals) - true_total) ** 2).sum(axis=1)
            left_step = ((step - true_step) ** 2).sum(axis=1)
            relative = (x[t] - x[t - 1])[edges[:, 1]] - (x[t] - x[t - 1])[edges[:, 0]]
            for key in ("all", f"{traj.poissons_ratio:g}"):
                for g in SHAPE_GROUPS:
                    mask = group[g][t]
                    sums[key][g] += (left_total[mask].sum(), (true_total[mask] ** 2).sum(),
                                     left_step[mask].sum(), (true_step[mask] ** 2).sum())
                sums[key]["stretch"] += (((lengths[t] - lengths[t - 1]) ** 2).sum(), (relative ** 2).sum())
    return {key: {g: float(s[g][0] / s[g][1]) for g in SHAPE_GROUPS}
            | {f"per_step_{g}": float(s[g][2] / s[g][3]) for g in SHAPE_GROUPS}
            | {"stretch_ratio": float(np.sqrt(s["stretch"][0] / s["stretch"][1]))} for key, s in sums.items()}


def data_report(dataset: str, data_dir: str | None, split: str, count: int, near: float | None,
                finger: float, radius: float, noise: float, shape: bool = True) -> dict:
    data = SimulationDataModule(dataset, data_dir=data_dir, generate_missing=False)
    near = float(data.config["sensor"]["voxel_size"]) if near is None else near
    trajs = data.trajectories(split)[:count]
    if not trajs:
        raise ValueError(f"{dataset}/{split} has no trajectories")
    points, cover, neighbours, spacing = [], {g: [] for g in GROUPS}, [], []
    motion = {"all": [], "near_finger": []}
    top, displacement, all_groups = [], [], []
    for traj in trajs:
        groups = per_step_groups(traj, near, finger)
        all_groups.append(groups)
        held = np.repeat(traj.positions[:1], traj.num_steps, axis=0)  # S_0 held: its error is the displacement
        displacement.append(split_error(held, traj.positions, boundary_facets(traj.cells, traj.rest_positions), groups,
                                        range(1, traj.num_steps)))
        free = ~traj.fixed
        for t in range(traj.num_steps):
            cloud = traj.point_cloud(t)
            points.append(len(cloud))
            if len(cloud) > 1:
                tree = cKDTree(cloud)
                spacing.append(float(np.median(tree.query(cloud, k=2)[0][:, 1])))
                neighbours.append(float(np.mean([len(n) for n in tree.query_ball_point(traj.positions[t][free], radius)])))
            for g in GROUPS:
                mask = groups[g][t]
                if mask.any():
                    cover[g].append(float(groups["_hit"][t][mask].mean()))
        step = np.linalg.norm(np.diff(traj.positions, axis=0), axis=2)[:, free]  # [T-1, free]
        motion["all"].append(step.ravel())
        motion["near_finger"].append(step[groups["near_finger"][1:][:, free]])
        top.append(np.sort(step.ravel())[-max(1, step.size // 10):])

    def rms(parts):  # per coordinate, as the training noise's std
        x = np.concatenate(parts) if parts else np.zeros(0)
        return float(np.sqrt(np.mean(x ** 2) / 3)) if x.size else float("nan")

    report = {"dataset": dataset, "split": split, "trajectories": len(trajs), "near": near, "finger": finger,
              "mesh_point_radius": radius, "training_noise": noise,
              "points_per_step_median": float(np.median(points)), "points_per_step_min": int(np.min(points)),
              "points_per_step_max": int(np.max(points)),
              "coverage": {g: float(np.mean(v)) if v else float("nan") for g, v in cover.items()},
              "points_within_radius_per_free_node": float(np.mean(neighbours)),
              "point_spacing_median": float(np.median(spacing)),
              "motion_rms_per_coordinate": {"all": rms(motion["all"]), "near_finger": rms(motion["near_finger"]),
                                            "top_10_percent": rms(top)},
              "displacement": {g: {k: float(np.mean([r[g][k] for r in displacement]))
                                   for k in ("normal", "tangential", "total")} for g in GROUPS}}
    if shape:  # the states' own property: once per set of states, not per camera preset
        report["shape_tangential_left"] = shape_report(trajs, all_groups)
    return report


def split_error(pred: np.ndarray, true: np.ndarray, facets: np.ndarray, groups: dict, steps: range) -> dict:
    """{group: {"normal", "tangential", "total"}: squared error per node-step and coordinate}."""
    sums = {g: np.zeros(3) for g in GROUPS}  # normal, tangential, count
    for t in steps:
        normal, tangential = normal_tangential(pred[t] - true[t], true[t], facets)
        for g in GROUPS:
            mask = groups[g][t]
            sums[g] += (normal[mask].sum(), tangential[mask].sum(), mask.sum())
    return {g: {"normal": s[0] / max(s[2], 1) / 3, "tangential": s[1] / max(s[2], 1) / 3,
                "total": (s[0] + s[1]) / max(s[2], 1) / 3, "node_steps": int(s[2])} for g, s in sums.items()}


def material_means(per: list[dict], trajs: list, parts: tuple[str, ...]) -> dict:
    """{material: {part: mean over its trajectories of `split_error`'s "all" group}} (materials by Poisson's ratio)."""
    return {f"{m:g}": {k: float(np.mean([r["all"][k] for r, tr in zip(per, trajs) if tr.poissons_ratio == m]))
                       for k in parts} for m in sorted({tr.poissons_ratio for tr in trajs})}


def model_report(checkpoint: str, dataset: str, data_dir: str | None, split: str, count: int, near: float | None,
                 finger: float, sigma: float | None, wavelength: float, seed: int, one_step: bool = True) -> dict:
    model = load_model(checkpoint, map_location="cpu").eval()
    data = SimulationDataModule(dataset, data_dir=data_dir, generate_missing=False)
    near = float(data.config["sensor"]["voxel_size"]) if near is None else near
    trajs = data.trajectories(split)[:count]
    batch = TrajectoryBatch.from_trajectories(trajs)
    sigma = float(model.noise.std) if sigma is None else sigma
    step_fn, connectivity = model.rollout_step(), model.connectivity
    groups = [per_step_groups(traj, near, finger) for traj in trajs]
    facets = [boundary_facets(traj.cells, traj.rest_positions) for traj in trajs]
    schedules = {"k1": effective_schedule(EveryK(1), model.uses_points), "never": Never()}
    out: dict = {"checkpoint": checkpoint, "model": type(model).__name__, "dataset": dataset, "split": split,
                 "trajectories": len(trajs), "sigma": sigma, "rollout": {}, "by_material": {}, "by_material_split": {},
                 "over_time": {}}
    with torch.no_grad():
        for name, schedule in schedules.items():
            preds = [p[0].numpy().astype(np.float64) for p in
                     split_trajectories(rollout(step_fn, batch, schedule, connectivity, model.with_material)[0], batch)]
            per = [split_error(p, tr.positions, f, g, range(1, tr.num_steps))
                   for p, tr, f, g in zip(preds, trajs, facets, groups)]
            out["rollout"][name] = {g: {k: float(np.mean([r[g][k] for r in per])) for k in ("normal", "tangential", "total")}
                                    for g in GROUPS}
            split = material_means(per, trajs, ("normal", "tangential", "total"))
            out["by_material"][name] = {m: parts.pop("total") for m, parts in split.items()}
            out["by_material_split"][name] = split
            curve = np.mean([((p - tr.positions)[:, ~tr.fixed] ** 2).mean(axis=(1, 2)) for p, tr in zip(preds, trajs)],
                            axis=0)
            out["over_time"][name] = [float(curve[t]) for t in range(0, len(curve), 10)] + [float(curve[-1])]
        # the mesh held at S_0 (the true displacement itself, split the same way)
        static = [split_error(np.repeat(tr.positions[:1], tr.num_steps, axis=0), tr.positions, f, g, range(1, tr.num_steps))
                  for tr, f, g in zip(trajs, facets, groups)]
        out["rollout"]["static"] = {g: {k: float(np.mean([r[g][k] for r in static])) for k in ("normal", "tangential", "total")}
                                    for g in GROUPS}
        out["by_material_split"]["static"] = material_means(static, trajs, ("normal", "tangential"))
        if not one_step:
            return out
        # one step from the truth, and from the truth perturbed, with and without the point cloud
        torch.manual_seed(seed)
        steps = batch.num_steps - 1
        free = ~batch.fixed
        one = {name: np.zeros(2) for name in ("no_motion", *schedules)}
        kept = {(kind, name, g, part): np.zeros(2) for kind in PERTURBATIONS for name in schedules
                for g in ("all", "seen", "never_seen") for part in ("normal", "tangential")}
        truth, owner = batch.positions, batch.mesh_batch
        for t in range(steps):
            motion = truth[t + 1] - truth[t]
            one["no_motion"] += (float((motion[free] ** 2).sum()), int(free.sum()) * 3)
            deltas = {"node": torch.randn(truth[t].shape, dtype=truth.dtype) * sigma,
                      "field": smooth_field(batch.rest, owner, batch.num_graphs, sigma, wavelength)}
            for name, schedule in schedules.items():
                clean = rollout(step_fn, batch, schedule, connectivity, model.with_material, start=t, steps=1)[0][1]
                one[name] += (float(((clean - truth[t + 1])[free] ** 2).sum()), int(free.sum()) * 3)
                for kind, delta in deltas.items():
                    delta = torch.where(batch.fixed[:, None], torch.zeros_like(delta), delta)
                    moved = rollout(step_fn, batch, schedule, connectivity, model.with_material, start=t, steps=1,
                                    start_positions=truth[t] + delta)[0][1]
                    left = (moved - clean).numpy().astype(np.float64)  # the perturbation's part of the prediction
                    d = delta.numpy().astype(np.float64)
                    for b, traj in enumerate(trajs):
                        lo, hi = int(batch.node_offsets[b]), int(batch.node_offsets[b + 1])
                        n = vertex_normals(traj.positions[t], facets[b])
                        x_n, d_n = (left[lo:hi] * n).sum(1) ** 2, (d[lo:hi] * n).sum(1) ** 2
                        x_t, d_t = (left[lo:hi] ** 2).sum(1) - x_n, (d[lo:hi] ** 2).sum(1) - d_n
                        for g in ("all", "seen", "never_seen"):
                            mask = groups[b][g][t]
                            kept[(kind, name, g, "normal")] += (float(x_n[mask].sum()), float(d_n[mask].sum()))
                            kept[(kind, name, g, "tangential")] += (float(x_t[mask].sum()), float(d_t[mask].sum()))
        out["one_step_mse"] = {name: float(s[0] / s[1]) for name, s in one.items()}
        out["one_step_ratio"] = {name: out["one_step_mse"][name] / out["one_step_mse"]["no_motion"] for name in schedules}
        out["field_wavelength"] = wavelength
        out["perturbation_kept"] = {"/".join(key): float(s[0] / s[1]) if s[1] > 0 else float("nan")
                                    for key, s in kept.items()}
    return out


def markdown(report: dict) -> str:
    lines = [f"`{report['command']}` at commit {report['commit']}", ""]
    for data in report["data"]:
        lines += [f"## Data: {data['dataset']} ({data['split']}, {data['trajectories']} trajectories)", "",
                  f"points per step: median {data['points_per_step_median']:.0f} ({data['points_per_step_min']}-"
                  f"{data['points_per_step_max']}); point spacing (median nearest neighbour) "
                  f"{data['point_spacing_median']:.4f}; points within the mesh-point radius {data['mesh_point_radius']} "
                  f"per free node {data['points_within_radius_per_free_node']:.2f}", "",
                  "coverage: share of the free nodes with a point within "
                  f"{data['near']:.3g} per step, mean over steps", "",
                  markdown_table(list(GROUPS), [[f"{data['coverage'][g]:.3f}" for g in GROUPS]]), "",
                  "RMS per-step motion per coordinate of the free nodes: "
                  + ", ".join(f"{k} {v:.5f}" for k, v in data["motion_rms_per_coordinate"].items())
                  + f"; training noise {data['training_noise']} is "
                  f"{data['training_noise'] / data['motion_rms_per_coordinate']['all']:.1f}x the first", "",
                  "true displacement from S_0 (squared, per free node-step and coordinate), normal / tangential "
                  "to the true surface", "",
                  markdown_table(list(GROUPS), [[f"{data['displacement'][g]['normal']:.3g} / "
                                                 f"{data['displacement'][g]['tangential']:.3g}" for g in GROUPS]]), ""]
        shape = data.get("shape_tangential_left")
        if shape:
            lines += ["motion along the surface from the shape if the wall does not stretch (`shape_tangential`): "
                      "share of the true tangential displacement from S_0 left unexplained (each step's in brackets), "
                      "and the true motion's RMS edge-length change over its edges' RMS relative motion", "",
                      markdown_table(["material", *SHAPE_GROUPS, "stretch ratio"],
                                     [[key] + [f"{r[g]:.3f} ({r['per_step_' + g]:.3f})" for g in SHAPE_GROUPS]
                                      + [f"{r['stretch_ratio']:.3f}"] for key, r in shape.items()]), ""]
    model = report.get("model")
    if model:
        lines += [f"## Model: {model['model']} from {model['checkpoint']} ({model['split']}, {model['trajectories']} "
                  "trajectories)", "", "Rollout from S_0: squared error per free node-step and coordinate, normal / tangential", ""]
        rows = [[name] + [f"{r[g]['normal']:.3g} / {r[g]['tangential']:.3g}" for g in GROUPS]
                for name, r in model["rollout"].items()]
        lines += [markdown_table(["schedule", *GROUPS], rows), ""]
        lines += ["By material (Poisson's ratio), all free nodes: " + "; ".join(
            f"{name}: " + ", ".join(f"nu={m} {v:.3g}" for m, v in r.items()) for name, r in model["by_material"].items()), ""]
        split = model.get("by_material_split", {})
        if split:
            materials = list(next(iter(split.values())))
            lines += ["By material, all free nodes, normal / tangential", "",
                      markdown_table(["schedule", *(f"nu={m}" for m in materials)],
                                     [[name] + [f"{r[m]['normal']:.3g} / {r[m]['tangential']:.3g}" for m in materials]
                                      for name, r in split.items()]), ""]
        lines += ["Over time (every 10th state and the last): " + "; ".join(
            f"{name}: " + " ".join(f"{v:.2g}" for v in r) for name, r in model["over_time"].items()), ""]
        if "one_step_mse" not in model:
            return "\n".join(lines) + "\n"
        lines += ["One step from the true state: MSE " + ", ".join(f"{k} {v:.3g}" for k, v in model["one_step_mse"].items())
                  + "; ratio to no motion " + ", ".join(f"{k} {v:.2f}" for k, v in model["one_step_ratio"].items()), ""]
        lines += [f"One step from the true state + a perturbation of std {model['sigma']} per free node and coordinate "
                  f"(node: independent per node; field: smooth, wavelength {model['field_wavelength']}): the share of "
                  "the perturbation's squared size left in the prediction (1: kept, 0: removed), normal / tangential", ""]
        keys = [(kind, name) for kind in PERTURBATIONS for name in model["rollout"] if name != "static"]
        kept = model["perturbation_kept"]
        rows = [[f"{kind}, {name}"] + [f"{kept[f'{kind}/{name}/{g}/normal']:.3f} / {kept[f'{kind}/{name}/{g}/tangential']:.3f}"
                                       for g in ("all", "seen", "never_seen")] for kind, name in keys]
        lines += [markdown_table(["perturbation, schedule", "all", "seen", "never_seen"], rows), ""]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="cavity_cpu")
    parser.add_argument("--cameras", default="", help="more data presets (other cameras) for the data part, comma-separated")
    parser.add_argument("--data-dir", default=None, help="folder of --dataset's split files (default: the preset's output)")
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--split", default="val")
    parser.add_argument("--trajectories", type=int, default=9)
    parser.add_argument("--near", type=float, default=None, help="a node is seen with a point this close (default: voxel size)")
    parser.add_argument("--finger", type=float, default=0.1, help="a node is near a finger within this of a collider vertex")
    parser.add_argument("--radius", type=float, default=0.05, help="the graph's mesh-point radius")
    parser.add_argument("--noise", type=float, default=0.01, help="the training noise the motion is compared with")
    parser.add_argument("--sigma", type=float, default=None, help="the perturbation's std (default: the model's training noise)")
    parser.add_argument("--field-wavelength", type=float, default=1.5,
                        help="the smooth perturbation's wavelength (rest-space units)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rollouts-only", action="store_true",
                        help="with --checkpoint: the rollouts and the static split only (no one-step or perturbation part)")
    parser.add_argument("--output", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    report = {"command": shlex.join(["python", "experiments/cavity_diagnosis/cavity_diagnosis.py", *sys.argv[1:]]), "commit": commit or "unknown",
              "data": [data_report(d, args.data_dir if d == args.dataset else None, args.split, args.trajectories,
                                   args.near, args.finger, args.radius, args.noise, shape=d == args.dataset)
                       for d in [args.dataset, *filter(None, args.cameras.split(","))]]}
    if args.checkpoint:
        report["model"] = model_report(args.checkpoint, args.dataset, args.data_dir, args.split, args.trajectories,
                                       args.near, args.finger, args.sigma, args.field_wavelength, args.seed,
                                       one_step=not args.rollouts_only)
    text = markdown(report)
    print(text)
    if args.output:
        write_text(Path(args.output) / "diagnosis.md", text)
        write_json(Path(args.output) / "diagnosis.json", report)


if __name__ == "__main__":
    main()
