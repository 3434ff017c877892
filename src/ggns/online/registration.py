"""`Registration`: a predicted mesh pulled onto an observed point cloud, against an elastic prior relative to
the prediction; the correction a blind simulator (MGN, MGN(M), GGNS without clouds) gets in the loop, where a
grounded GGNS gets the cloud through its graph (`OnlineSimulator(..., registration=Registration())`).

The problem, for the mesh X [N, d] predicted for the observation's tick (X0) and the observed points p_m:

    min_D  sum_m w_m dist(p_m, B_m (X0 + D))^2  +  reverse * sum_b w_b |q_b - X0_b - D_b|^2
           +  smoothness * sum_(i,j) in E |D_i - D_j|^2  +  anchor * |D|^2
    with D_i = 0 for the held nodes (fixed, and grasped ones)

- the data term is the one-sided Chamfer distance from the points to the object: B_m picks the point of the
  object nearest p_m as barycentric weights of one facet (3D: a boundary triangle, the surface a camera
  sees; 2D: a cell, since the plate's camera sees its whole face, so a point inside the mesh costs nothing);
  one-sided, so a surface the camera does not see is not pulled;
- the prior is an edge term relative to the prediction (each mesh edge's vector kept as predicted: the
  displacement field is smooth, and the prediction's shape, not the rest shape, is the reference), with a
  small `anchor` to the prediction that keeps the system well posed for nodes far from any point;
- optionally (`reverse` > 0) the other direction for the object's boundary nodes: each pulled to its nearest
  point (in 2D, where a prediction that overshoots the cloud's outline is not seen by the first term);
- robust: points (and boundary nodes) farther from the object (from the cloud) than `trim` times the mesh's
  mean edge length get no weight (outliers: flying pixels, a miscalibrated frame's fringe);
- solved by Gauss-Newton on the distances to the nearest points (point-to-plane ICP): `iterations` times the
  correspondences B from the current mesh, each point's residual taken along the direction from its nearest
  point to it (the facet's normal inside a facet), then the linear least squares in D by conjugate gradients
  on the normal equations, all in torch.

Sources: the point-to-surface correspondences of ICP (Besl & McKay 1992) with a smoothness prior on the
displacement as in non-rigid ICP (Amberg, Romdhani & Vetter, CVPR 2007) and in tracking a deformable object
from point clouds against a physical prior (Schulman et al., ICRA 2013; CDCPD, Chi et al., ICRA 2019).
The weights are chosen on validation trajectories (docs/experiments/online_registration.md).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..geometry import boundary_facets, cell_edges
from ..graphs.search import knn

CANDIDATES = 8  # facets (nearest by centroid) among which each point's nearest facet is sought


@dataclass(frozen=True)
class Registration:
    """Non-rigid registration of a predicted mesh to an observed point cloud (module docstring).

    Attributes:
        smoothness: weight of the edge term (per edge) against the data term (per point).
        reverse: weight of the boundary nodes' pull to their nearest points (per node; 0: off).
        anchor: weight pulling every node towards its prediction (per node; keeps the system well posed).
        iterations: correspondence updates (Gauss-Newton steps).
        trim: points farther from the object than `trim` x the mesh's mean edge length get no weight, and so do
            boundary nodes that far from every point (None: none is dropped).
        cg_iterations: conjugate-gradient iterations per linear solve.
        feed_model: also give the cloud to the model (a GGNS corrected and grounded at once); False: the model
            steps blind and only the registration sees the clouds.
    """

    smoothness: float = 1.0
    reverse: float = 0.0
    anchor: float = 1e-3
    iterations: int = 4
    trim: float | None = 3.0
    cg_iterations: int = 25
    feed_model: bool = False

    def __post_init__(self) -> None:
        for name in ("smoothness", "reverse", "anchor"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
                raise ValueError(f"Registration.{name} must be a finite number >= 0, got {value!r}")
        if self.anchor == 0 and self.smoothness == 0:
            raise ValueError("Registration needs smoothness > 0 or anchor > 0 (else nodes far from every point are "
                             "undetermined)")
        for name in ("iterations", "cg_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"Registration.{name} must be an integer >= 1, got {value!r}")
        if self.trim is not None and (not isinstance(self.trim, (int, float)) or not (np.isfinite(self.trim) and self.trim > 0)):
            raise ValueError(f"Registration.trim must be a number > 0 or None, got {self.trim!r}")


class ObjectGeometry:
    """What the registration needs of one object, built once: its facets [F, d] (3D: boundary triangles; 2D: the
    cells, as triangles), its undirected mesh edges [E, 2] and its held nodes (bool [N])."""

    def __init__(self, cells: np.ndarray, dim: int, held: np.ndarray, device: torch.device):
        cells = np.asarray(cells, dtype=np.int64)
        facets = boundary_facets(cells) if dim == 3 else cells
        self.dim = dim
        self.facets = torch.as_tensor(facets, device=device)
        self.edges = torch.as_tensor(cell_edges(cells), device=device)
        self.held = torch.as_tensor(np.asarray(held, dtype=bool), device=device)
        self.boundary = torch.as_tensor(np.unique(boundary_facets(cells)), device=device)  # the outline's nodes
        self._laplacian = None

    def laplacian(self) -> Tensor:
        """The mesh edges' graph Laplacian [N, N] (CSR, float64): sum over edges of (e_i - e_j)(e_i - e_j)^T."""
        if self._laplacian is None:
            i, j = self.edges[:, 0], self.edges[:, 1]
            n = int(self.held.numel())
            ones = torch.ones(len(i), dtype=torch.float64, device=self.edges.device)
            coo = torch.sparse_coo_tensor(torch.stack([torch.cat([i, j, i, j]), torch.cat([i, j, j, i])]),
                                          torch.cat([ones, ones, -ones, -ones]), (n, n), check_invariants=False).coalesce()
            self._laplacian = _csr(*_csr_parts(coo), (n, n))
        return self._laplacian

    def mean_edge(self, positions: Tensor) -> float:
        """The mean length of the mesh's edges at `positions` [N, d]."""
        return float((positions[self.edges[:, 0]] - positions[self.edges[:, 1]]).norm(dim=1).mean())


def register(config: Registration, geometry: ObjectGeometry, positions: Tensor, points: Tensor) -> Tensor:
    """The registered mesh [N, d] (module docstring): `positions` [N, d] the prediction, `points` [P, d] the cloud
    (none: the prediction unchanged). Computed in float64; returned in the prediction's dtype."""
    if len(points) == 0:
        return positions
    x0 = positions.to(torch.float64)
    p = points.to(torch.float64)
    n, d = x0.shape
    free = (~geometry.held).to(x0.dtype)[:, None]
    laplacian = geometry.laplacian()
    reach = None if config.trim is None else config.trim * geometry.mean_edge(x0)
    boundary = geometry.boundary
    displacement = torch.zeros_like(x0)
    for _ in range(config.iterations):
        facet, weights, distance = nearest_on_facets(x0 + displacement, geometry.facets, p)
        # Gauss-Newton on the distance to the nearest point: the residual along the direction to the point
        # (the facet's normal where the foot is inside it); none for a point on (2D: inside) the object
        keep = (distance > 0) if reach is None else (distance > 0) & (distance <= reach)
        facet, weights, distance, seen = facet[keep], weights[keep], distance[keep], p[keep]
        corners = geometry.facets[facet]  # [P', 3] the nodes of each point's facet
        foot = (weights[..., None] * (x0 + displacement)[corners]).sum(1)
        normal = (seen - foot) / distance[:, None]
        target = ((seen - (weights[..., None] * x0[corners]).sum(1)) * normal).sum(1)  # [P'] n . (p - B X0)
        pick = _csr(torch.arange(0, 3 * len(corners) + 1, 3, device=x0.device), corners.reshape(-1), weights.reshape(-1),
                    (len(corners), n))  # B: each point's foot from the nodes
        flat = corners.reshape(-1)
        spread_weights = weights.reshape(-1, 1)
        pull = x0.new_zeros(n)
        rhs = torch.zeros_like(x0).index_add_(0, flat, (weights[..., None] * (target[:, None] * normal)[:, None])
                                              .reshape(-1, d))
        if config.reverse:
            gap, index = torch.cdist(x0[boundary] + displacement[boundary], p).min(1)
            within = torch.ones_like(gap) if reach is None else (gap <= reach).to(x0.dtype)
            pull[boundary] = config.reverse * within
            rhs.index_add_(0, boundary, pull[boundary, None] * (p[index] - x0[boundary]))
        diagonal = (config.anchor + pull)[:, None]

        def apply(v: Tensor) -> Tensor:
            """The normal equations' matrix times D [N, d], held rows and columns out."""
            v = v * free
            along = ((pick @ v) * normal).sum(1, keepdim=True) * normal  # [P', d]: n n^T B D
            out = torch.zeros_like(v).index_add_(0, flat, (spread_weights * along.repeat_interleave(3, 0)))
            return (out + config.smoothness * (laplacian @ v) + diagonal * v) * free

        displacement = conjugate_gradients(apply, rhs * free, displacement, config.cg_iterations) * free
    return (x0 + displacement).to(positions.dtype)


def _csr(crow: Tensor, col: Tensor, values: Tensor, size: tuple[int, int]) -> Tensor:
    """A CSR matrix from its parts (torch's CSR support is marked beta; its warning is not ours to print)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, col, values, size, check_invariants=False)


def _csr_parts(coo: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(crow, col, values) of a coalesced COO matrix."""
    rows, columns = coo.indices()
    crow = torch.zeros(coo.size(0) + 1, dtype=torch.long, device=rows.device)
    crow[1:] = torch.bincount(rows, minlength=coo.size(0)).cumsum(0)
    return crow, columns, coo.values()


def conjugate_gradients(apply, rhs: Tensor, start: Tensor, iterations: int) -> Tensor:
    """x with apply(x) = rhs (apply: an SPD linear map on vectors), from `start`, at most `iterations` steps."""
    x = start.clone()
    r = rhs - apply(x)
    direction = r.clone()
    rr = (r * r).sum()
    stop = 1e-24 * float((rhs * rhs).sum())
    for _ in range(iterations):
        if float(rr) <= stop:
            break
        ad = apply(direction)
        alpha = rr / (direction * ad).sum().clamp_min(1e-300)
        x = x + alpha * direction
        r = r - alpha * ad
        rr_next = (r * r).sum()
        direction = r + (rr_next / rr.clamp_min(1e-300)) * direction
        rr = rr_next
    return x


def nearest_on_facets(positions: Tensor, facets: Tensor, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """For each point [P, d], the nearest point of the facets (triangles [F, 3] of `positions` [N, d]; in 2D
    a point inside a triangle is its own nearest point): (facet index [P], barycentric weights [P, 3],
    distance [P]). Sought among the `CANDIDATES` facets whose centroids are nearest."""
    corners = positions[facets]  # [F, 3, d]
    centroids = corners.mean(1)
    k = min(CANDIDATES, len(facets))
    pairs = knn(centroids, points, k)  # [2, P k]: (point, facet), k per point
    order = torch.sort(pairs[0], stable=True).indices
    candidates = pairs[1, order].view(len(points), k)
    tri = corners[candidates]  # [P, k, 3, d]
    weights = closest_on_triangles(points[:, None].expand(-1, k, -1), tri)  # [P, k, 3]
    foot = (weights[..., None] * tri).sum(2)
    distance = (foot - points[:, None]).norm(dim=-1)  # [P, k]
    best = distance.argmin(1)
    rows = torch.arange(len(points), device=points.device)
    return candidates[rows, best], weights[rows, best], distance[rows, best]


def closest_on_triangles(points: Tensor, triangles: Tensor) -> Tensor:
    """Barycentric weights [..., 3] of the point of each triangle [..., 3, d] (d = 2 or 3) nearest to each point
    [..., d]: the projection onto the triangle's plane when it falls inside, else the nearest point of its edges."""
    a, b, c = triangles.unbind(-2)
    ab, ac, ap = b - a, c - a, points - a
    d00, d01, d11 = (ab * ab).sum(-1), (ab * ac).sum(-1), (ac * ac).sum(-1)
    d20, d21 = (ap * ab).sum(-1), (ap * ac).sum(-1)
    denominator = (d00 * d11 - d01 * d01).clamp_min(1e-30)
    v = (d11 * d20 - d01 * d21) / denominator
    w = (d00 * d21 - d01 * d20) / denominator
    inside = torch.stack([1 - v - w, v, w], -1)
    inside_ok = (v >= 0) & (w >= 0) & (v + w <= 1)
    best, best_distance = inside, torch.where(inside_ok, (ap - v[..., None] * ab - w[..., None] * ac).norm(dim=-1),
                                              torch.full_like(v, float("inf")))
    for i, j in ((0, 1), (1, 2), (2, 0)):  # the nearest point of each edge (i, j)
        start, end = triangles[..., i, :], triangles[..., j, :]
        edge = end - start
        s = ((points - start) * edge).sum(-1) / (edge * edge).sum(-1).clamp_min(1e-30)
        s = s.clamp(0, 1)
        distance = (start + s[..., None] * edge - points).norm(dim=-1)
        weights = torch.zeros_like(inside)
        weights[..., i], weights[..., j] = 1 - s, s
        better = (distance < best_distance) & ~inside_ok
        best = torch.where(better[..., None], weights, best)
        best_distance = torch.where(better, distance, best_distance)
    return best
