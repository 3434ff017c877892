"""Import the paper authors' datasets (jlinki/GGNS: SOFA simulations stored as Python pickles) into
split files of this package's schema (`ggns.data.schema`), so that they train and evaluate here.

An authors' file (`<name>_{train,eval,test}.pkl`) is a list with one dict per trajectory, of
per-step lists of arrays ([T][N, d] mesh nodes, [T][K, d] collider nodes, [T][P_t, d] points) and
per-trajectory arrays (edges, triangles) and scalars (Poisson's ratio). `KEYS` names the keys read
for d = 2 (Deformable Plate) and d = 3 (Tissue Manipulation and Cavity Grasping share one layout);
docs/dataset_format.md ("Importing the authors' pickles") says what each becomes and what the
importer infers: the rest state is step 0 (the authors' mesh space), fixed nodes are the nodes
that never move (the files have no fixed-node key), Young's modulus comes from the preset (the
files hold only nu), and 3D meshes get no cells (the files hold no tetrahedra: `cells` is [0, 4]).

Files are data, never code: `load_pickle` unpickles with `SafeUnpickler`, which rebuilds numpy
arrays and plain containers and refuses every other global before anything of it runs.
"""
from __future__ import annotations

import importlib
import pickle
import re
from pathlib import Path

import numpy as np

from ..checkpoints import sha256
from ..geometry import boundary_facets, signed_volumes
from ..trajectory import Trajectory, pack_point_clouds
from .schema import SplitWriter

# dim -> {role: the authors' key}; all are required but 3D's collider_faces (a plotting key of the cavity files)
KEYS = {
    2: {"positions": "nodes_grid", "edges": "edge_index_grid", "collider": "nodes_collider", "points": "pcd_points",
        "poissons_ratio": "poisson_ratio", "cells": "triangles_grid", "collider_faces": "triangles_collider"},
    3: {"positions": "tissue_mesh_positions", "edges": "tissue_mesh_edges", "collider": "gripper_position",
        "points": "tissue_pcd_points", "poissons_ratio": "poisson_ratio", "collider_faces": "gripper_triangles"},
}
SPLIT_NAMES = {"train": "train", "eval": "val", "val": "val", "test": "test"}  # the authors' split names -> ours


class UnsafePickleError(pickle.UnpicklingError, ValueError):
    """A pickle asks for a global (a function or class) that a data file has no use for."""


class ReferenceFormatError(ValueError):
    """An authors' file does not hold what the importer needs (the message names the problem)."""


# (module, name) pairs a file of numpy arrays, numbers and containers needs; numpy.core is numpy 1's
# name of numpy 2's numpy._core (pickles name whichever wrote them)
_NUMPY_CORE = {("multiarray", "_reconstruct"), ("multiarray", "scalar"), ("numeric", "_frombuffer")}
_BUILTINS = {"list", "dict", "tuple", "set", "frozenset", "bytes", "bytearray"}


class SafeUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays and scalars (ndarray, dtype and their reconstructors), plain containers
    and bytes (`_codecs.encode`, protocol 2); refuses any other global with `UnsafePickleError`
    naming it, so a crafted file cannot call os.system, eval or a constructor with side effects."""

    def find_class(self, module: str, name: str):
        for prefix in ("numpy._core.", "numpy.core."):
            if module.startswith(prefix) and (module[len(prefix):], name) in _NUMPY_CORE:
                return getattr(_numpy_core(module[len(prefix):]), name)
        if (module == "numpy" and name in ("ndarray", "dtype")) or (module == "_codecs" and name == "encode"):
            return getattr(importlib.import_module(module), name)
        if module in ("builtins", "__builtin__") and name in _BUILTINS:
            return getattr(importlib.import_module("builtins"), name)
        hint = " (torch tensors: save them as numpy arrays)" if module.split(".")[0] == "torch" else ""
        raise UnsafePickleError(f"refused to load {module}.{name}: a dataset pickle may only hold numpy arrays, "
                                f"numbers, strings and lists / dicts / tuples{hint}")


def _numpy_core(submodule: str):
    try:
        return importlib.import_module(f"numpy._core.{submodule}")
    except ImportError:  # numpy 1
        return importlib.import_module(f"numpy.core.{submodule}")


def load_pickle(path: str | Path):
    """The object in a pickle file, unpickled with `SafeUnpickler`."""
    with open(path, "rb") as f:
        try:
            return SafeUnpickler(f, encoding="latin1").load()
        except UnsafePickleError as error:
            raise UnsafePickleError(f"{path}: {error}") from None
        except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, KeyError, IndexError) as error:
            raise ReferenceFormatError(f"{path}: not a readable pickle ({type(error).__name__}: {error})") from None


def split_from_name(path: str | Path) -> str:
    """The split an authors' file name ends in: <name>_train.pkl -> train, _eval -> val, _test -> test."""
    match = re.search(r"_(train|eval|val|test)$", Path(path).stem)
    if not match:
        raise ValueError(f"{Path(path).name}: the split is not in the file name (<name>_train/_eval/_test.pkl); "
                         f"give it with --split")
    return SPLIT_NAMES[match.group(1)]


def parse_nodes(spec) -> np.ndarray:
    """Node indices from a list of ints or a text such as "0-29,35" (ranges inclusive), int64 [n]."""
    if isinstance(spec, str):
        out = []
        for part in filter(None, (p.strip() for p in spec.split(","))):
            match = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
            if not match:
                raise ValueError(f"fixed nodes {spec!r}: {part!r} is neither an index nor a range a-b")
            first, last = int(match.group(1)), int(match.group(2) or match.group(1))
            out += range(first, last + 1)
        spec = out
    nodes = np.asarray(spec)
    if nodes.ndim != 1 or not nodes.size or not np.issubdtype(nodes.dtype, np.integer):
        raise ValueError(f"fixed nodes must be a non-empty list of node indices, got {spec!r}")
    return nodes.astype(np.int64)


# ---- one trajectory ------------------------------------------------------------------------------------------
def _steps(record: dict, key: str, dim: int, equal: bool) -> list[np.ndarray]:
    """A per-step key as float64 arrays [n_t, d] (a step given as [d] is one node; in 2D a third
    coordinate that is zero everywhere is dropped). equal: every step has the same n_t."""
    value = record[key]
    sequence = isinstance(value, (list, tuple)) or isinstance(value, np.ndarray) and value.ndim > 0
    if not sequence or len(value) == 0:
        raise ReferenceFormatError(f"key {key!r}: expected a per-step list of [n, {dim}] arrays, got "
                                   f"{'an empty one' if sequence else type(value).__name__}")
    steps = []
    for t, step in enumerate(value):
        try:
            x = np.asarray(step, dtype=np.float64)
        except (TypeError, ValueError) as error:
            raise ReferenceFormatError(f"key {key!r}, step {t}: not a numeric array ({error})") from None
        x = x.reshape(0, dim) if x.size == 0 else x.reshape(1, -1) if x.ndim == 1 else x
        if dim == 2 and x.ndim == 2 and x.shape[1] == 3 and not x[:, 2].any():
            x = x[:, :2]
        if x.ndim != 2 or x.shape[1] != dim:
            raise ReferenceFormatError(f"key {key!r}, step {t}: expected [n, {dim}] ({dim}D positions), "
                                       f"got shape {list(x.shape)}")
        if not np.isfinite(x).all():
            raise ReferenceFormatError(f"key {key!r}, step {t}: contains NaN or inf")
        if equal and steps and len(x) != len(steps[0]):
            raise ReferenceFormatError(f"key {key!r}: ragged across steps: step 0 has {len(steps[0])} nodes, "
                                       f"step {t} has {len(x)}")
        steps.append(x)
    return steps


def _indices(record: dict, key: str, width: int, count: int) -> np.ndarray:
    """An index array [M, width] (also accepted as [width, M]) of `count` nodes, int64."""
    try:
        a = np.asarray(record[key])
    except (TypeError, ValueError) as error:
        raise ReferenceFormatError(f"key {key!r}: not an index array ({error})") from None
    if a.ndim == 2 and a.shape[0] == width and a.shape[1] != width:
        a = a.T
    if a.ndim != 2 or a.shape[1] != width or not a.size:
        raise ReferenceFormatError(f"key {key!r}: expected a non-empty [M, {width}] index array, "
                                   f"got shape {list(a.shape)}")
    if a.dtype.kind == "f" and np.isfinite(a).all() and (a == np.round(a)).all():
        a = a.astype(np.int64)
    if a.dtype.kind not in "iu":
        raise ReferenceFormatError(f"key {key!r}: expected integer indices, got {a.dtype}")
    if a.min() < 0 or a.max() >= count:
        raise ReferenceFormatError(f"key {key!r}: indices must lie in [0, {count}), got [{a.min()}, {a.max()}]")
    return a.astype(np.int64)


def _edges(record: dict, key: str, count: int) -> np.ndarray:
    """Directed or undirected edges, [E, 2] or [2, E] -> unique undirected rows i < j, sorted."""
    e = np.sort(_indices(record, key, 2, count), axis=1)
    if (e[:, 0] == e[:, 1]).any():
        raise ReferenceFormatError(f"key {key!r}: holds self-loops (i, i)")
    return np.unique(e, axis=0)


def _counter_clockwise(rest: np.ndarray, triangles: np.ndarray, key: str) -> np.ndarray:
    area = signed_volumes(rest, triangles)
    flat = np.flatnonzero(np.abs(area) <= 1e-12)
    if flat.size:
        raise ReferenceFormatError(f"key {key!r}: {flat.size} triangles have zero area at step 0 (first: {flat[0]})")
    triangles = triangles.copy()
    triangles[area < 0] = triangles[area < 0][:, [0, 2, 1]]
    return triangles


def _boundary_loops(x: np.ndarray, triangles: np.ndarray, key: str) -> np.ndarray:
    """The boundary of a 2D collider's triangles as counter-clockwise segments [F, 2], in loop order
    (each loop's segments follow each other, as a scene's collider outline)."""
    following = {}
    for a, b in boundary_facets(triangles, x):
        if a in following:
            raise ReferenceFormatError(f"key {key!r}: the boundary is not a set of closed loops (node {a})")
        following[int(a)] = int(b)
    loops, left = [], set(following)
    while left:
        start = node = min(left)
        while True:
            left.discard(node)
            loops.append((node, following[node]))
            node = following[node]
            if node == start:
                break
            if node not in left:
                raise ReferenceFormatError(f"key {key!r}: the boundary is not a set of closed loops (node {node})")
    return np.array(loops, dtype=np.int64)


def _youngs_modulus(nu: float, importer: dict) -> float:
    """E in Pa: importer.youngs_modulus, else the E that importer.materials pairs with nu."""
    value = importer["youngs_modulus"]
    if value is None:
        value = next((m["youngs_modulus"] for m in importer["materials"]
                      if abs(m["poissons_ratio"] - nu) <= 1e-6), None)
    if value is None:
        known = [m["poissons_ratio"] for m in importer["materials"]]
        raise ReferenceFormatError(f"no Young's modulus for nu = {nu:g}: the preset's importer.materials gives E for "
                                   f"nu in {known}; give E with --youngs-modulus PA")
    if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
        raise ValueError(f"Young's modulus must be a positive number of Pa, got {value!r}")
    return float(value)


def reference_trajectory(record, dim: int, importer: dict, seed: int = 0) -> Trajectory:
    """One authors' trajectory dict as a `Trajectory` (module docstring); `importer` is a preset's
    importer section. ReferenceFormatError names the key and the problem."""
    if not isinstance(record, dict):
        raise ReferenceFormatError(f"expected a dict of arrays, got {type(record).__name__}")
    keys = KEYS[dim]
    need = [k for role, k in keys.items() if not (dim == 3 and role == "collider_faces")]
    missing = [k for k in need if k not in record]
    if missing:
        other = list(KEYS[5 - dim].values())[:4]  # the other layout's per-step keys and edges
        other = "; the file holds the other dimension's keys" if all(k in record for k in other) else ""
        raise ReferenceFormatError(f"lacks key(s) {missing} of the {dim}D layout{other}; "
                                   f"keys present: {sorted(map(str, record))}")
    positions = np.stack(_steps(record, keys["positions"], dim, equal=True))
    collider = _steps(record, keys["collider"], dim, equal=True)
    clouds = _steps(record, keys["points"], dim, equal=False)
    for key, value in ((keys["collider"], collider), (keys["points"], clouds)):
        if len(value) != len(positions):
            raise ReferenceFormatError(f"key {key!r} has {len(value)} steps, "
                                       f"{keys['positions']!r} has {len(positions)}")
    if importer["steps"] is not None:
        if len(positions) < importer["steps"]:
            raise ReferenceFormatError(f"{len(positions)} steps, fewer than importer.steps = {importer['steps']}")
        positions, collider, clouds = (a[:importer["steps"]] for a in (positions, collider, clouds))
    rest, n = positions[0], positions.shape[1]
    bound = 1.0 + importer["bounds_tolerance"]
    if np.abs(rest).max() > bound:
        raise ReferenceFormatError(f"key {keys['positions']!r}: the mesh at step 0 leaves [-1, 1]^{dim} "
                                   f"(max |coordinate| {np.abs(rest).max():.4g}); the format needs normalized "
                                   f"coordinates")
    try:
        nu = float(np.asarray(record[keys["poissons_ratio"]], dtype=np.float64).reshape(()))
    except (TypeError, ValueError):
        raise ReferenceFormatError(f"key {keys['poissons_ratio']!r}: expected one number, "
                                   f"got {record[keys['poissons_ratio']]!r:.80}") from None
    if not -1.0 < nu < 0.5:
        raise ReferenceFormatError(f"key {keys['poissons_ratio']!r}: nu = {nu} is outside (-1, 0.5)")

    collider = np.stack(collider)
    faces = np.zeros((0, dim), dtype=np.int64)
    if dim == 2:
        cells = _counter_clockwise(rest, _indices(record, keys["cells"], 3, n), keys["cells"])
        faces = _boundary_loops(collider[0], _indices(record, keys["collider_faces"], 3, collider.shape[1]),
                                keys["collider_faces"])
    else:
        cells = np.zeros((0, 4), dtype=np.int64)  # the files hold no tetrahedra (module docstring)
        if importer["collider_faces"] and keys["collider_faces"] in record:
            faces = _indices(record, keys["collider_faces"], 3, collider.shape[1])

    moved = np.abs(positions - rest).max(axis=(0, 2))  # [N], the largest displacement of each node
    if importer["fixed"] is None:
        fixed = moved <= importer["fixed_tolerance"]
    else:
        nodes = parse_nodes(importer["fixed"])
        if nodes.min() < 0 or nodes.max() >= n:
            raise ReferenceFormatError(f"fixed nodes must lie in [0, {n}) (the mesh has {n} nodes), got "
                                       f"[{nodes.min()}, {nodes.max()}]")
        if moved[nodes].max() > importer["fixed_tolerance"]:
            worst = nodes[np.argmax(moved[nodes])]
            raise ReferenceFormatError(f"fixed node {worst} moves by {moved[worst]:.3g} (importer.fixed_tolerance "
                                       f"{importer['fixed_tolerance']:g}): the rollout would give it the true "
                                       f"positions")
        fixed = np.zeros(n, dtype=bool)
        fixed[nodes] = True
    points, offsets = pack_point_clouds(clouds)
    return Trajectory(rest_positions=rest.copy(), cells=cells, edges=_edges(record, keys["edges"], n),
                      positions=positions, fixed=fixed, collider_faces=faces, collider_positions=collider,
                      points=points, point_offsets=offsets, youngs_modulus=_youngs_modulus(nu, importer),
                      poissons_ratio=nu, seed=seed)


# ---- one file ----------------------------------------------------------------------------------------------
def import_reference(source: str | Path, config: dict, split: str, output: str | Path | None = None,
                     overwrite: bool = False) -> dict:
    """Convert an authors' pickle into <output>/<split>.h5 (output: default the preset's `output`).

    config: a reference data preset (conf/data/reference_*.yaml: scene name and dim, importer
    section). The file's generator_config is the preset plus `source` (file name, sha256, split).
    An existing split file is kept unless `overwrite`; a file that fails to convert leaves nothing
    behind (SplitWriter). Returns a summary: path, trajectories, and sizes: (min, max) over the
    trajectories of steps, nodes, fixed nodes and mean points per step.
    """
    source, steps = Path(source), config["importer"]["steps"]
    if split not in ("train", "val", "test"):
        raise ValueError(f"split must be train, val or test, got {split!r}")
    if steps is not None and (not isinstance(steps, int) or steps < 2):
        raise ValueError(f"steps must be an integer >= 2 (the initial state and one to predict), got {steps!r}")
    path = Path(output if output is not None else config["output"]) / f"{split}.h5"
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: already exists (--overwrite replaces it)")
    if not source.is_file():
        raise FileNotFoundError(f"{source}: no such file")
    dim = config["scene"]["dim"]
    digest, records = sha256(source), load_pickle(source)
    if not isinstance(records, (list, tuple)) or not records:
        empty = " (empty)" if isinstance(records, (list, tuple)) else ""
        raise ReferenceFormatError(f"{source}: expected a non-empty list with one dict per trajectory, got "
                                   f"{type(records).__name__}{empty}")
    stored = {**config, "output": str(path.parent),
              "source": {"file": source.name, "sha256": digest, "split": split, "trajectories": len(records)}}
    sizes = {"steps": [], "nodes": [], "fixed": [], "points per step": []}
    with SplitWriter(path, scene=config["scene"]["name"], split=split, dim=dim, generator_config=stored,
                     overwrite=overwrite) as writer:
        for i, record in enumerate(records):
            try:
                traj = reference_trajectory(record, dim, config["importer"], seed=i)
            except ReferenceFormatError as error:
                raise ReferenceFormatError(f"{source}: trajectory {i}: {error}") from None
            writer.append(traj)
            for name, value in zip(sizes, (traj.num_steps, len(traj.rest_positions), int(traj.fixed.sum()),
                                           len(traj.points) / traj.num_steps)):
                sizes[name].append(value)
    return {"path": path, "trajectories": len(records), "sizes": {k: (min(v), max(v)) for k, v in sizes.items()}}
