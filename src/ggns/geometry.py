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


def box_tetrahedra(nodes: tuple[int, int, int], size: tuple[float, float, float] = (1.0, 1.0, 1.0)
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Structured tetrahedral mesh of the box [0, size]: `nodes` = (nx, ny, nz) >= 2 nodes per axis,
    every hexahedron split into 6 tetrahedra along its main diagonal (Kuhn; conforming, the same
    split in every cell). Returns positions [nx ny nz, 3] float64 (x fastest) and cells [C, 4]
    int64, positively oriented."""
    nx, ny, nz = (int(n) for n in nodes)
    if min(nx, ny, nz) < 2:
        raise ValueError(f"box_tetrahedra needs >= 2 nodes per axis, got {nodes}")
    axes = [np.linspace(0.0, s, n) for s, n in zip(size, (nx, ny, nz))]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    positions = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    index = np.arange(nx * ny * nz).reshape(nz, ny, nx)
    corner = index[:-1, :-1, :-1].ravel()  # the (0, 0, 0) corner of each hexahedron
    step = np.array([1, nx, nx * ny])  # index offset of one step along x, y, z
    cells = []
    for order in itertools.permutations(range(3)):  # a path 000 -> 111 along the axes in `order`
        a = corner
        b = a + step[order[0]]
        c = b + step[order[1]]
        cells.append(np.stack([a, b, c, c + step[order[2]]], axis=1))
    cells = np.concatenate(cells).astype(np.int64)
    flip = signed_volumes(positions, cells) < 0
    cells[flip] = cells[flip][:, [0, 2, 1, 3]]
    return positions, cells
