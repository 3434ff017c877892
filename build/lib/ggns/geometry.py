"""Mesh topology helpers shared by scenes, simulator, sensors and graph builders.

Cells are simplices: triangles [C, 3] in 2D, tetrahedra [C, 4] in 3D.
"""
from __future__ import annotations

import itertools

import numpy as np


def cell_edges(cells: np.ndarray) -> np.ndarray:
    """Unique undirected edges of simplicial cells, [E, 2] int64 with i < j, sorted."""
    cells = np.asarray(cells, dtype=np.int64)
    pairs = [cells[:, [a, b]] for a, b in itertools.combinations(range(cells.shape[1]), 2)]
    edges = np.sort(np.concatenate(pairs, axis=0), axis=1)
    return np.unique(edges, axis=0)


def boundary_facets(cells: np.ndarray, positions: np.ndarray | None = None) -> np.ndarray:
    """Facets that belong to exactly one cell: segments [F, 2] (2D) or triangles [F, 3] (3D).

    With `positions`, facets are oriented so that their normal points out of the cell
    (counter-clockwise boundary in 2D, outward right-hand normal in 3D).
    """
    cells = np.asarray(cells, dtype=np.int64)
    k = cells.shape[1]
    # facet j of a cell omits vertex j; `opposite` remembers it for orientation
    facets = np.concatenate([np.delete(cells, j, axis=1) for j in range(k)], axis=0)
    opposite = np.concatenate([cells[:, j] for j in range(k)], axis=0)
    key = np.sort(facets, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.reshape(-1)] == 1
    facets, opposite = facets[once], opposite[once]
    if positions is None:
        return facets
    x = np.asarray(positions, dtype=np.float64)
    if k == 3:  # segment (a, b): outward normal is the side away from the opposite vertex
        a, b, c = x[facets[:, 0]], x[facets[:, 1]], x[opposite]
        t = b - a
        normal = np.stack([t[:, 1], -t[:, 0]], axis=1)
        flip = np.einsum("ij,ij->i", normal, c - a) > 0
    else:
        a, b, c, o = (x[facets[:, 0]], x[facets[:, 1]], x[facets[:, 2]], x[opposite])
        normal = np.cross(b - a, c - a)
        flip = np.einsum("ij,ij->i", normal, o - a) > 0
    facets[flip] = facets[flip][:, ::-1]
    return facets


def signed_volumes(positions: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Signed area (2D) or volume (3D) of each cell, [C]."""
    x = np.asarray(positions, dtype=np.float64)[np.asarray(cells)]
    dm = (x[:, 1:] - x[:, :1]).transpose(0, 2, 1)
    d = x.shape[-1]
    return np.linalg.det(dm) / (1.0 if d == 1 else (2.0 if d == 2 else 6.0))


def check_cells(cells, num_nodes: int | None = None, name: str = "cells", corners: int = 3) -> np.ndarray:
    """`cells` as an integer array [C, corners] (triangles by default) indexing `num_nodes` nodes;
    ValueError naming `name` otherwise. The one check of a cell array."""
    cells = np.asarray(cells)
    if cells.ndim != 2 or cells.shape[1] != corners or not np.issubdtype(cells.dtype, np.integer):
        kind = "triangles" if corners == 3 else "tetrahedra" if corners == 4 else "cells"
        raise ValueError(f"{name} must be integer [C, {corners}] {kind}, got {cells.dtype} {cells.shape}")
    if num_nodes is not None and cells.size and (cells.min() < 0 or cells.max() >= num_nodes):
        raise ValueError(f"{name} index outside the {num_nodes} mesh nodes")
    return cells


def min_volume_ratio(positions: np.ndarray, rest: np.ndarray, cells: np.ndarray) -> float:
    """The smallest det F (deformed over rest signed area / volume) of any cell at any frame of
    positions [T, N, d] (or one frame [N, d]): <= 0 once a cell is flat or inverted."""
    frames = np.asarray(positions, dtype=np.float64).reshape((-1,) + np.shape(rest))
    rest_volumes = signed_volumes(rest, cells)
    return float(min((signed_volumes(x, cells) / rest_volumes).min() for x in frames))


def box_tet_mesh(lo, hi, divisions) -> tuple[np.ndarray, np.ndarray]:
    """Structured tetrahedral mesh of the axis-aligned box [lo, hi].

    The box is cut into divisions[0] x divisions[1] x divisions[2] hexahedral cells, each split
    into the 6 tetrahedra of its Kuhn (Freudenthal) subdivision: every tetrahedron runs from the
    cell's low corner to its high corner along one permutation of the axes. All cells share the
    main diagonal direction, so neighbouring cells' tetrahedra meet face to face (the mesh is
    conforming), and every tetrahedron is oriented to positive signed volume.

    Args:
        lo: Low corner, 3 numbers.
        hi: High corner, 3 numbers, each strictly greater than lo's.
        divisions: Cells per axis, one positive int for all axes or 3 of them.

    Returns:
        positions: float64 [N, 3] with N = prod(divisions + 1); node (i, j, k) has index
            (i * (ny + 1) + j) * (nz + 1) + k.
        cells: int64 [6 * prod(divisions), 4] tetrahedra.

    Raises:
        ValueError: lo/hi not 3 finite numbers with lo < hi, or divisions not positive integers.
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ValueError(f"box corners must be 3 finite numbers each, got lo={lo.tolist()} hi={hi.tolist()}")
    if not (lo < hi).all():
        raise ValueError(f"box is empty: lo={lo.tolist()} must be below hi={hi.tolist()} on every axis")
    n = np.broadcast_to(np.asarray(divisions), (3,))
    if not np.issubdtype(n.dtype, np.integer) or (n < 1).any():
        raise ValueError(f"divisions must be positive integers (one or 3), got {divisions!r}")
    n = n.astype(np.int64)
    axes = [np.linspace(lo[a], hi[a], n[a] + 1) for a in range(3)]
    positions = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    stride = np.array([(n[1] + 1) * (n[2] + 1), n[2] + 1, 1])
    corner = np.stack(np.meshgrid(*(np.arange(m) for m in n), indexing="ij"), axis=-1).reshape(-1, 3) @ stride
    tets = []
    for perm in itertools.permutations(range(3)):
        steps = np.cumsum(stride[list(perm)])  # walk from the low corner along the permuted axes
        tets.append(np.stack([corner, *(corner + s for s in steps)], axis=1))
    cells = np.concatenate(tets, axis=0)
    negative = signed_volumes(positions, cells) < 0
    cells[negative] = cells[negative][:, [1, 0, 2, 3]]
    return positions, cells
