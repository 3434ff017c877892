"""Corotational linear elasticity on linear simplices (triangles in 2D, plane strain or plane
stress: `Material.plane`; tetrahedra in 3D), vectorized over elements in float64.

Energy density (McAdams et al. 2011 "corotated" model), with F = R S the polar decomposition:
    psi(F) = mu ||F - R||^2 + lambda / 2 (tr(R^T F) - d)^2,
which is linear elasticity in the rotated frame: zero for any rigid motion and exactly the
small-strain energy mu eps:eps + lambda/2 tr(eps)^2 to first order. It is positive definite
in the stretch S - I for the whole range -1 < nu < 0.5.

The first Piola stress P = 2 mu (F - R) + lambda (tr(R^T F) - d) R is the exact gradient of
psi. The tangent used by the solver is the warped stiffness R K0 R^T (K0: the rest linear
stiffness), which is symmetric positive semi-definite for every deformation: Newton steps
with it are descent directions for the incremental potential, so the solver converges with a
line search even through large rotations, where the exact (indefinite) tangent would not.
"""
from __future__ import annotations

import math

import torch

from ..geometry import check_cells
from .material import Material


def polar_rotation(F: torch.Tensor) -> torch.Tensor:
    """Rotation R of the polar decomposition F = R S, [C, d, d] -> [C, d, d] (det R = +1)."""
    d = F.shape[-1]
    if d == 2:
        theta = torch.atan2(F[:, 1, 0] - F[:, 0, 1], F[:, 0, 0] + F[:, 1, 1])
        c, s = torch.cos(theta), torch.sin(theta)
        return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    U, _, Vh = torch.linalg.svd(F)
    # rotation-variant SVD: flip the last singular direction of reflections
    sign = torch.sign(torch.linalg.det(U @ Vh))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    U = torch.cat([U[..., :-1], U[..., -1:] * sign[:, None, None]], dim=-1)
    return U @ Vh


class ElasticBody:
    """Rest-state precomputation of a simplicial mesh: shape gradients, volumes, lumped
    masses and the rest stiffness of every element.

    rest_positions: [N, d] float64; cells: [C, d+1] int64 (any orientation).
    """

    def __init__(self, rest_positions: torch.Tensor, cells: torch.Tensor, material: Material):
        self.X = rest_positions.to(torch.float64)
        self.material = material
        n, d = self.X.shape
        cells = torch.as_tensor(cells)
        self.cells = torch.as_tensor(check_cells(cells.cpu().numpy(), n, corners=d + 1), dtype=torch.long,
                                     device=cells.device)
        self.num_nodes, self.dim = n, d
        Xe = self.X[self.cells]  # [C, d+1, d]
        Dm = (Xe[:, 1:] - Xe[:, :1]).transpose(1, 2)  # columns X_a - X_0
        det = torch.linalg.det(Dm)
        bad = (det.abs() <= 1e-14 * Dm.abs().amax(dim=(1, 2)) ** d).nonzero().flatten()
        if len(bad):
            raise ValueError(f"degenerate (zero-volume) cells at rest: {bad[:10].tolist()}")
        self.volume = det.abs() / math.factorial(d)  # [C]
        Dm_inv = torch.linalg.inv(Dm)
        # shape-function gradients B[c, a, :] so that F = sum_a x_a (outer) B_a
        self.B = torch.cat([-Dm_inv.sum(dim=1, keepdim=True), Dm_inv], dim=1)
        lam, mu = material.lame_parameters(d)
        self.lam, self.mu = lam, mu
        eye = torch.eye(d, dtype=torch.float64)
        BB = torch.einsum("cak,cbk->cab", self.B, self.B)
        K0 = lam * torch.einsum("cai,cbj->caibj", self.B, self.B)
        K0 = K0 + mu * (torch.einsum("cab,ij->caibj", BB, eye) + torch.einsum("caj,cbi->caibj", self.B, self.B))
        self.K0 = K0 * self.volume[:, None, None, None, None]  # [C, d+1, d, d+1, d]
        mass = torch.zeros(n, dtype=torch.float64)
        mass.index_add_(0, self.cells.flatten(), (material.density * self.volume / (d + 1)).repeat_interleave(d + 1))
        self.node_mass = mass  # [N] lumped mass in kg
        dofs = (self.cells[:, :, None] * d + torch.arange(d)).reshape(len(self.cells), -1)  # [C, (d+1)d]
        m = dofs.shape[1]
        self.hess_rows = dofs[:, :, None].expand(-1, m, m).reshape(-1)
        self.hess_cols = dofs[:, None, :].expand(-1, m, m).reshape(-1)

    def deformation_gradient(self, x: torch.Tensor) -> torch.Tensor:
        """F per element, [C, d, d], from node positions x [N, d]."""
        return torch.einsum("cai,caj->cij", x[self.cells], self.B)

    def energy(self, x: torch.Tensor, R: torch.Tensor | None = None) -> torch.Tensor:
        """Total elastic energy in J (2D: J per metre of thickness), scalar."""
        F = self.deformation_gradient(x)
        R = polar_rotation(F) if R is None else R
        tr = torch.einsum("cij,cij->c", R, F) - self.dim
        psi = self.mu * ((F - R) ** 2).sum(dim=(1, 2)) + 0.5 * self.lam * tr**2
        return (self.volume * psi).sum()

    def gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy gradient dE/dx [N, d] (= minus the elastic forces) and the rotations [C, d, d]."""
        F = self.deformation_gradient(x)
        R = polar_rotation(F)
        tr = torch.einsum("cij,cij->c", R, F) - self.dim
        P = 2 * self.mu * (F - R) + self.lam * tr[:, None, None] * R
        ge = torch.einsum("cij,caj->cai", P, self.B) * self.volume[:, None, None]
        g = torch.zeros_like(x)
        g.index_add_(0, self.cells.flatten(), ge.reshape(-1, self.dim))
        return g, R

    def warped_stiffness(self, R: torch.Tensor) -> torch.Tensor:
        """Element stiffness blocks R K0 R^T flattened to match (hess_rows, hess_cols)."""
        K = torch.einsum("cip,capbq,cjq->caibj", R, self.K0, R)
        return K.reshape(-1)
