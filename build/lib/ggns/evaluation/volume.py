"""Volumes covered by tetrahedral meshes and their overlap: the geometry behind the 3D mesh IoU
(`metrics.tet_mesh_iou`, the one public IoU; this module holds no input checks of its own).

Two ways to the volumes of two meshes and of their intersection:

* exact: each mesh's boundary surface (facets of exactly one tetrahedron, oriented outward) is a
  manifold3d solid (`exact_solid`, built once per mesh), and the intersection is a manifold3d
  Boolean in float64 (`exact_volumes`). Valid only where the mesh bounds the region it covers: no
  inverted or degenerate tetrahedron, no facet shared by more than two tetrahedra, a closed
  2-manifold boundary that does not meet itself, no cavity, no boundary components whose solids
  overlap (`exact_solid` lists what fails instead of returning a solid).
* sampled: membership of a fixed, seeded set of scrambled Sobol points in the bounding box of
  both meshes, tested by barycentric coordinates against every tetrahedron (either orientation:
  an inverted tetrahedron still covers its volume, as a folded triangle does in 2D); volumes are
  the box volume times the fraction of points inside. Works for any input.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..geometry import boundary_facets, signed_volumes


def _manifold3d():
    """manifold3d, imported where the exact 3D IoU needs it (the rest of the evaluation runs without it)."""
    try:
        import manifold3d
    except ImportError as error:
        raise ImportError("the exact 3D volume IoU needs manifold3d (pip install manifold3d); "
                          "method='sampled' does without it") from error
    return manifold3d

# a tetrahedron with 6|V| <= _DEGENERATE * (|e1|^2 + |e2|^2 + |e3|^2)^(3/2) covers no volume
_DEGENERATE = 1e-12
# sampled membership: at most this many point-tetrahedron pairs at once (~150 MB of temporaries)
_PAIRS_PER_CHUNK = 1 << 20
# self-intersection test: at most this many candidate facet pairs at once
_FACET_PAIRS_PER_CHUNK = 1 << 16


def _degenerate_or_inverted(x: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Tetrahedra with non-positive (or negligible) signed volume, bool [C]."""
    edges = x[cells[:, 1:]] - x[cells[:, :1]]  # [C, 3, 3]
    scale = np.square(edges).sum(axis=(1, 2)) ** 1.5
    return 6.0 * signed_volumes(x, cells) <= _DEGENERATE * scale


def _segments_cross_triangles(p: np.ndarray, q: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Whether segment p-q [K, 3] meets triangle tri [K, 3, 3] while crossing its plane: endpoints
    strictly on opposite sides of the plane, the crossing point inside the triangle or on its
    edges. A segment that merely ends on the plane (e.g. at a shared vertex) does not count."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]

    def orient(u, v, w, scale):  # sign of the triple product u . (v x w), 0 within rounding
        det = np.einsum("ij,ij->i", u, np.cross(v, w))
        return np.where(np.abs(det) <= 1e-10 * scale, 0.0, np.sign(det))

    def size(*vs):
        return np.prod([np.linalg.norm(v, axis=1) for v in vs], axis=0)

    ab, ac = b - a, c - a
    sp = orient(p - a, ab, ac, size(p - a, ab, ac))
    sq = orient(q - a, ab, ac, size(q - a, ab, ac))
    d = q - p
    s = [orient(d, u - p, v - p, size(d, u - p, v - p)) for u, v in ((a, b), (b, c), (c, a))]
    s = np.stack(s)
    return (sp * sq < 0) & ((s >= 0).all(axis=0) | (s <= 0).all(axis=0))


def surface_self_intersects(positions: np.ndarray, faces: np.ndarray) -> bool:
    """Whether the surface meets itself away from shared vertices and edges (is not embedded).

    Candidate pairs are triangles with overlapping bounding boxes (found with a k-d tree over
    their centres) that share at most one vertex; a pair meets where an edge of one crosses the
    plane of the other inside or on the boundary of that triangle, so crossings and most
    touching count. Contacts made only within a common plane (coplanar triangles, an edge lying
    in the other's plane) are not seen; `exact_solid` catches the overlaps these hide between
    separate boundary components by a Boolean union of the components.

    Args:
        positions: float64 [N, 3] node positions.
        faces: int [F, 3] triangles.

    Returns:
        True if some pair of triangles crosses.
    """
    x = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) < 2:
        return False
    tri = x[faces]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    reach = np.linalg.norm(hi - lo, axis=1).max()  # boxes that overlap have centres within this
    pairs = cKDTree((lo + hi) / 2).query_pairs(reach * (1 + 1e-9), output_type="ndarray")
    for start in range(0, len(pairs), _FACET_PAIRS_PER_CHUNK):
        i, j = pairs[start : start + _FACET_PAIRS_PER_CHUNK].T
        keep = (lo[i] <= hi[j]).all(axis=1) & (lo[j] <= hi[i]).all(axis=1)
        keep &= (faces[i][:, :, None] == faces[j][:, None, :]).sum(axis=(1, 2)) < 2
        i, j = i[keep], j[keep]
        for one, other in ((i, j), (j, i)):
            for e0, e1 in ((0, 1), (1, 2), (2, 0)):
                if _segments_cross_triangles(tri[one, e0], tri[one, e1], tri[other]).any():
                    return True
    return False


def exact_solid(positions: np.ndarray, cells: np.ndarray) -> tuple["manifold3d.Manifold | None", list[str]]:
    """The manifold3d solid bounded by a tetrahedral mesh's boundary, or why the exact
    (boundary-surface Boolean) volumes would be wrong for it.

    Args:
        positions: float64 [N, 3] node positions, finite.
        cells: int [C, 4] tetrahedra.

    Returns:
        (solid, []) when the exact path is valid, else (None, problems): one phrase per problem
        found: inverted or
        degenerate tetrahedra, facets shared by more than two tetrahedra, a boundary that is not a
        closed 2-manifold, a boundary that meets itself, an inward-facing boundary component (a
        cavity; not handled, to keep the overlap check simple), boundary components whose solids
        overlap (the union of the components is smaller than the sum of their volumes). Later
        checks are skipped once one fails.

    Known gap: a single connected boundary folded so that it overlaps itself with every contact
    exactly coplanar (measure zero for computed positions, possible for hand-made ones) passes.
    """
    x = np.asarray(positions, dtype=np.float64)
    cells = np.asarray(cells, dtype=np.int64)
    bad = int(_degenerate_or_inverted(x, cells).sum())
    if bad:
        return None, [f"{bad} inverted or degenerate tetrahedra"]
    keys = np.sort(np.concatenate([np.delete(cells, j, axis=1) for j in range(4)]), axis=1)
    crowded = int((np.unique(keys, axis=0, return_counts=True)[1] > 2).sum())
    if crowded:
        return None, [f"{crowded} facets shared by more than two tetrahedra"]
    faces = boundary_facets(cells, x)
    solid = _solid(x, faces)
    status = solid.status()
    if status != _manifold3d().Error.NoError:
        return None, [f"boundary surface is not a closed 2-manifold ({status.name})"]
    if surface_self_intersects(x, faces):
        return None, ["boundary surface intersects itself"]
    parts = solid.decompose()
    if len(parts) > 1:
        volumes = np.array([part.volume() for part in parts])
        if (volumes <= 0).any():
            return None, [f"{int((volumes <= 0).sum())} inward-facing boundary components (cavities)"]
        union = _manifold3d().Manifold.batch_boolean(parts, _manifold3d().OpType.Add).volume()
        if union < volumes.sum() * (1 - 1e-9):
            return None, [f"its {len(parts)} boundary components overlap (union {union:.6g} < sum "
                          f"{volumes.sum():.6g})"]
    return solid, []


def _solid(x: np.ndarray, faces: np.ndarray) -> "manifold3d.Manifold":
    """manifold3d solid bounded by `faces` (outward), on the nodes they use, in float64."""
    used, local = np.unique(faces, return_inverse=True)
    mesh = _manifold3d().Mesh64(
        vert_properties=np.ascontiguousarray(x[used]),
        tri_verts=np.ascontiguousarray(local.reshape(faces.shape).astype(np.uint64)),
    )
    return _manifold3d().Manifold(mesh)


def exact_volumes(pred: "manifold3d.Manifold", true: "manifold3d.Manifold") -> tuple[float, float, float]:
    """(pred volume, true volume, intersection volume) of two solids from `exact_solid`, the
    intersection by a manifold3d Boolean."""
    return pred.volume(), true.volume(), (pred ^ true).volume()


def _covered(points: torch.Tensor, x: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """Which points [P, 3] lie in some non-degenerate tetrahedron of the mesh, bool [P]."""
    inside = torch.zeros(len(points), dtype=torch.bool)
    corners = x[cells]  # [C, 4, 3]
    edges = (corners[:, 1:] - corners[:, :1]).transpose(1, 2)  # columns are edge vectors, [C, 3, 3]
    scale = edges.square().sum(dim=(1, 2)) ** 1.5
    keep = torch.linalg.det(edges).abs() > _DEGENERATE * scale  # degenerate ones cover no volume
    origin, inverse = corners[keep, 0], torch.linalg.inv(edges[keep])
    lo, hi = corners[keep].amin(dim=1), corners[keep].amax(dim=1)
    if not len(origin):
        return inside
    step = max(1, _PAIRS_PER_CHUNK // len(origin))
    for start in range(0, len(points), step):
        p = points[start : start + step]
        near = ((p[:, None] >= lo) & (p[:, None] <= hi)).all(dim=-1)  # [P', C]
        rows, tets = near.nonzero(as_tuple=True)
        lam = torch.einsum("kij,kj->ki", inverse[tets], p[rows] - origin[tets])
        hit = (lam >= 0).all(dim=1) & (lam.sum(dim=1) <= 1)
        inside[start + rows[hit]] = True
    return inside


def sampled_volumes(pred_positions: np.ndarray, true_positions: np.ndarray, cells: np.ndarray,
                    samples: int, seed: int = 0) -> tuple[float, float, float]:
    """Volumes of two tetrahedral meshes and of their intersection, estimated from points.

    The points are the first `samples` points of a scrambled Sobol sequence (torch's
    SobolEngine, seeded with `seed`, so the same inputs always give the same numbers), scaled
    into the bounding box of both meshes. A point is in a mesh if it lies in any of its
    non-degenerate tetrahedra, whatever their orientation. The standard error of the estimates
    falls roughly like 1 / samples (low-discrepancy points) and is largest on thin or small
    regions relative to the box.

    Args:
        pred_positions: float64 [N, 3].
        true_positions: float64 [N, 3].
        cells: int [C, 4] tetrahedra shared by both meshes.
        samples: number of points (a power of two keeps the Sobol points balanced).
        seed: scrambling seed.

    Returns:
        (pred volume, true volume, intersection volume), each box volume x fraction of points.
    """
    pred = torch.as_tensor(np.asarray(pred_positions, dtype=np.float64))
    true = torch.as_tensor(np.asarray(true_positions, dtype=np.float64))
    cells = torch.as_tensor(np.asarray(cells, dtype=np.int64))
    both = torch.cat([pred, true])
    lo, hi = both.amin(dim=0), both.amax(dim=0)
    unit = torch.quasirandom.SobolEngine(3, scramble=True, seed=seed).draw(samples, dtype=torch.float64)
    points = lo + unit * (hi - lo)
    in_pred, in_true = _covered(points, pred, cells), _covered(points, true, cells)
    cell_volume = float(torch.prod(hi - lo)) / samples
    return (cell_volume * int(in_pred.sum()), cell_volume * int(in_true.sum()),
            cell_volume * int((in_pred & in_true).sum()))
