"""Signed distance from points to a closed rigid collider surface, in torch float64.

The surface is a closed polyline (2D, faces [F, 2] segments) or a closed triangle mesh
(3D, faces [F, 3]). Inside/outside comes from the generalized winding number, so the face
orientation may be either way round but must be consistent. Costs O(M F) for M points.
"""
from __future__ import annotations

import math

import torch


def _closest_on_segments(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Closest points on segments (a, b) to points p: p [M, 1, d], a/b [.., F, d] -> [M, F, d]."""
    ab = b - a
    t = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-300)
    return a + t.clamp(0.0, 1.0)[..., None] * ab


def _closest_on_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Closest points on triangles to points p: p [M, 1, 3], a/b/c [F, 3] -> [M, F, 3]."""
    n = torch.linalg.cross(b - a, c - a)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    q = p - ((p - a) * n).sum(-1, keepdim=True) * n  # projection onto the plane
    # inside test: q on the inner side of all three edges
    inside = torch.ones(q.shape[:-1], dtype=torch.bool)
    for u, v in ((a, b), (b, c), (c, a)):  # (torch.linalg.cross broadcasts only equal numbers of dimensions)
        inside &= (torch.linalg.cross((v - u).expand_as(q), q - u) * n).sum(-1) >= 0
    best = q
    dist = torch.where(inside, ((p - q) ** 2).sum(-1), torch.full(q.shape[:-1], math.inf, dtype=p.dtype))
    for u, v in ((a, b), (b, c), (c, a)):
        e = _closest_on_segments(p, u, v)
        de = ((p - e) ** 2).sum(-1)
        closer = de < dist
        best = torch.where(closer[..., None], e, best)
        dist = torch.where(closer, de, dist)
    return best


def winding_number(p: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Generalized winding number of a closed surface around points p [M, d] -> [M] (+-1 inside, 0 outside)."""
    corners = vertices[faces] - p[:, None, None, :]  # [M, F, d, d]
    if p.shape[1] == 2:
        a, b = corners[..., 0, :], corners[..., 1, :]
        cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
        angle = torch.atan2(cross, (a * b).sum(-1))
        return angle.sum(-1) / (2 * math.pi)
    a, b, c = corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
    num = (a * torch.linalg.cross(b, c)).sum(-1)
    den = la * lb * lc + (a * b).sum(-1) * lc + (a * c).sum(-1) * lb + (b * c).sum(-1) * la
    return (2 * torch.atan2(num, den)).sum(-1) / (4 * math.pi)


def signed_distance(p: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance phi [M] (negative inside) and outward unit normal [M, d] at the
    closest surface point, for points p [M, d] and a closed surface (vertices [K, d], faces [F, d])."""
    corners = vertices[faces]  # [F, d, d]
    q = p[:, None, :]
    if p.shape[1] == 2:
        closest = _closest_on_segments(q, corners[:, 0], corners[:, 1])
    else:
        closest = _closest_on_triangles(q, corners[:, 0], corners[:, 1], corners[:, 2])
    d2 = ((q - closest) ** 2).sum(-1)  # [M, F]
    idx = d2.argmin(dim=1)
    nearest = closest[torch.arange(len(p)), idx]
    dist = d2[torch.arange(len(p)), idx].sqrt()
    inside = winding_number(p, vertices, faces).abs() > 0.5
    sign = torch.where(inside, -1.0, 1.0).to(p.dtype)
    diff = p - nearest
    normal = sign[:, None] * diff / dist[:, None].clamp_min(1e-300)
    # exactly on the surface: fall back to the direction away from the collider's centroid
    on_surface = dist < 1e-12
    if on_surface.any():
        away = p[on_surface] - vertices.mean(0)
        normal[on_surface] = away / away.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return sign * dist, normal
