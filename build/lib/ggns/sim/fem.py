"""Corotational linear elasticity on linear simplices (triangles in 2D, plane strain or plane
stress: `Material.plane`; tetrahedra in 3D), vectorized over elements in float64.

Energy density (McAdams et al. 2011 "corotated" model), with F = R S the polar decomposition:
    psi(F) = mu ||F - R||^2 + lambda / 2 (tr(R^T F) - d)^2,
which is linear elasticity in the rotated frame: zero for any rigid motion and exactly the
small-strain energy mu eps:eps + lambda/2 tr(eps)^2 to first order. It is positive definite
in the stretch S - I for the whole range -1 < nu < 0.5.

The first Piola stress P = 2 mu (F - R) + lambda (tr(R^T F) - d) R is the exact gradient of
psi (R^T dR is skew and S symmetric, so the rotation's variation drops out of dpsi). Its
derivative, the exact Hessian, is
    dP = 2 mu dF + lambda (R : dF) R + (lambda (tr S - d) - 2 mu) dR,
with dR = U Omega V^T, Omega_kl = (M_kl - M_lk) / (sigma_k + sigma_l), M = U^T dF V, from the
(rotation-variant) SVD F = U Sigma V^T. In the singular-value frame its eigen-system is analytic
(McAdams et al. 2011; Smith et al. 2019, "Analytic eigensystems for isotropic distortion
energies"): per pair k < l a "flip" mode (M_kl + M_lk)/sqrt 2 with eigenvalue 2 mu and a
"twist" mode (M_kl - M_lk)/sqrt 2 with eigenvalue
    lambda_kl = 2 mu + (2 lambda (tr S - d) - 4 mu) / (sigma_k + sigma_l),
and on the diagonal M_kk the constant 2 mu I + lambda 1 1^T. Three tangents are built from it
(`SolverConfig.tangent`, `ElasticBody.gradient_hessian`):
- "warped": R K0 R^T (K0: the rest linear stiffness), which is this eigen-system with every
  twist eigenvalue set to 0: symmetric positive semi-definite for every deformation, but it
  omits the coupling of stress and rotation, so Newton converges only linearly.
- "exact": the exact Hessian. Its twist eigenvalues are negative in compressed elements, so it
  can be indefinite; the solver adds inertia (M / h^2) and retries an iteration whose Newton
  matrix is not positive definite with "projected".
- "projected": the eigen-system with its eigenvalues clamped at 0, the positive semi-definite
  projection of the exact Hessian: exact where that is positive semi-definite (stretched or
  dilated elements), equal to "warped" where every twist eigenvalue is <= 0.
All three coincide at a rigid rotation of the rest state (lambda_kl = 0 there). A pair with
sigma_k + sigma_l <= `TWIST_MIN_SUM` (nearly or truly inverted, where dR is unbounded) gets
twist eigenvalue 0 in every tangent, as in "warped".
"""
from __future__ import annotations

import math

import torch

from ..geometry import check_cells
from .material import Material


TANGENTS = ("warped", "exact", "projected")
TWIST_MIN_SUM = 1e-6  # sigma_k + sigma_l at or below which a pair's twist eigenvalue is taken as 0


def rotation_variant_svd(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """F = U diag(sigma) Vh with U Vh a rotation, [C, d, d] -> U, sigma [C, d], Vh: the SVD with
    the last (smallest) singular value negated for reflections (det F < 0)."""
    U, sigma, Vh = torch.linalg.svd(F)
    sign = torch.sign(torch.linalg.det(U @ Vh))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    U = torch.cat([U[..., :-1], U[..., -1:] * sign[:, None, None]], dim=-1)
    sigma = torch.cat([sigma[..., :-1], sigma[..., -1:] * sign[:, None]], dim=-1)
    return U, sigma, Vh


def polar_rotation(F: torch.Tensor) -> torch.Tensor:
    """Rotation R of the polar decomposition F = R S, [C, d, d] -> [C, d, d] (det R = +1)."""
    d = F.shape[-1]
    if d == 2:
        theta = torch.atan2(F[:, 1, 0] - F[:, 0, 1], F[:, 0, 0] + F[:, 1, 1])
        c, s = torch.cos(theta), torch.sin(theta)
        return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    U, _, Vh = rotation_variant_svd(F)
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
        # the 2 mu dF : dF part of the exact Hessian, in node dofs
        self.K_identity = (2 * mu) * torch.einsum("cab,ij->caibj", BB * self.volume[:, None, None], eye)
        mass = torch.zeros(n, dtype=torch.float64)
        mass.index_add_(0, self.cells.flatten(), (material.density * self.volume / (d + 1)).repeat_interleave(d + 1))
        self.node_mass = mass  # [N] lumped mass in kg
        dofs = (self.cells[:, :, None] * d + torch.arange(d)).reshape(len(self.cells), -1)  # [C, (d+1)d]
        m = dofs.shape[1]
        self.hess_rows = dofs[:, :, None].expand(-1, m, m).reshape(-1)
        self.hess_cols = dofs[:, None, :].expand(-1, m, m).reshape(-1)
        self._last_svd = None  # (F, its rotation-variant SVD) of the last 3D evaluation (`_svd`)

    def _svd(self, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`rotation_variant_svd(F)`, remembered for the last F: a Newton iteration evaluates the energy
        at the line search's accepted point and then the gradient and tangent at the same point, so
        the second needs no SVD of its own (the same numbers, bit for bit)."""
        cached = self._last_svd
        if cached is not None and cached[0].shape == F.shape and torch.equal(cached[0], F):
            return cached[1]
        result = rotation_variant_svd(F)
        self._last_svd = (F, result)
        return result

    def _rotation(self, F: torch.Tensor) -> torch.Tensor:
        """`polar_rotation(F)`, through the remembered SVD in 3D."""
        if self.dim == 2:
            return polar_rotation(F)
        U, _, Vh = self._svd(F)
        return U @ Vh

    def deformation_gradient(self, x: torch.Tensor) -> torch.Tensor:
        """F per element, [C, d, d], from node positions x [N, d]."""
        return torch.einsum("cai,caj->cij", x[self.cells], self.B)

    def energy(self, x: torch.Tensor, R: torch.Tensor | None = None) -> torch.Tensor:
        """Total elastic energy in J (2D: J per metre of thickness), scalar."""
        F = self.deformation_gradient(x)
        R = self._rotation(F) if R is None else R
        tr = torch.einsum("cij,cij->c", R, F) - self.dim
        psi = self.mu * ((F - R) ** 2).sum(dim=(1, 2)) + 0.5 * self.lam * tr**2
        return (self.volume * psi).sum()

    def gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Energy gradient dE/dx [N, d] (= minus the elastic forces) and the rotations [C, d, d]."""
        F = self.deformation_gradient(x)
        R = self._rotation(F)
        return self._gradient(x, F, R), R

    def _gradient(self, x: torch.Tensor, F: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
        tr = torch.einsum("cij,cij->c", R, F) - self.dim
        P = 2 * self.mu * (F - R) + self.lam * tr[:, None, None] * R
        ge = torch.einsum("cij,caj->cai", P, self.B) * self.volume[:, None, None]
        g = torch.zeros_like(x)
        g.index_add_(0, self.cells.flatten(), ge.reshape(-1, self.dim))
        return g

    def gradient_hessian(self, x: torch.Tensor, tangent: str = "warped") -> tuple[torch.Tensor, torch.Tensor]:
        """Energy gradient dE/dx [N, d] and the element tangent blocks flattened to match
        (hess_rows, hess_cols): `tangent` "warped" (R K0 R^T), "exact" (the exact Hessian) or
        "projected" (the exact Hessian clamped to positive semi-definite); module docstring."""
        if tangent not in TANGENTS:
            raise ValueError(f"tangent must be one of {TANGENTS}, got {tangent!r}")
        F = self.deformation_gradient(x)
        if tangent == "warped":
            R = self._rotation(F)
            return self._gradient(x, F, R), self.warped_stiffness(R)
        R, twists, sums = self._twist_modes(F)
        return self._gradient(x, F, R), self._exact_blocks(F, R, twists, sums, project=tangent == "projected")

    def exact_hessian(self, x: torch.Tensor, project: bool = False) -> torch.Tensor:
        """Element blocks of the exact Hessian of the energy, flattened to match (hess_rows,
        hess_cols), exact wherever every sigma_k + sigma_l > TWIST_MIN_SUM; project=True:
        clamped to positive semi-definite (the "projected" tangent)."""
        F = self.deformation_gradient(x)
        R, twists, sums = self._twist_modes(F)
        return self._exact_blocks(F, R, twists, sums, project)

    def _twist_modes(self, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rotations R [C, d, d], the unit twist directions T_kl = (u_k v_l^T - u_l v_k^T) / sqrt 2
        [C, P, d, d] of the P = d (d - 1) / 2 singular-value pairs k < l and sigma_k + sigma_l [C, P]."""
        if self.dim == 2:
            # F = R S: the one twist is J R / sqrt 2 (J the quarter turn) and sigma_0 + sigma_1 = tr S
            R = polar_rotation(F)
            J = torch.tensor([[0.0, -1.0], [1.0, 0.0]], dtype=F.dtype)
            return R, (J @ R)[:, None] / math.sqrt(2), torch.einsum("cij,cij->c", R, F)[:, None]
        U, sigma, Vh = self._svd(F)
        pairs = ((0, 1), (0, 2), (1, 2))
        twists = torch.stack([U[:, :, k, None] * Vh[:, None, l, :] - U[:, :, l, None] * Vh[:, None, k, :]
                              for k, l in pairs], dim=1) / math.sqrt(2)
        sums = torch.stack([sigma[:, k] + sigma[:, l] for k, l in pairs], dim=1)
        return U @ Vh, twists, sums

    def _exact_blocks(self, F, R, twists, sums, project: bool) -> torch.Tensor:
        # dF : H : dF = 2 mu |dF|^2 + lambda (R : dF)^2 + sum_kl (lambda_kl - 2 mu) (T_kl : dF)^2
        d, lam, mu = self.dim, self.lam, self.mu
        tr = torch.einsum("cij,cij->c", R, F) - d
        # a (nearly) inverted pair, where dR is unbounded, keeps the warped stiffness's twist eigenvalue 0
        regular = sums > TWIST_MIN_SUM
        twist = 2 * mu + (2 * lam * tr[:, None] - 4 * mu) / torch.where(regular, sums, torch.ones_like(sums))
        twist = torch.where(regular, twist, torch.zeros_like(twist))
        if project:
            # twist eigenvalues clamped at 0; the volumetric one, 2 mu + d lambda, too (it is > 0
            # for every valid material)
            twist = twist.clamp_min(0.0)
            lam = max(lam, -2 * mu / d)
        r = torch.einsum("cik,cak->cai", R, self.B)  # (R : dF) = r . dx over the element's dofs
        tau = torch.einsum("cpik,cak->cpai", twists, self.B)
        vol = self.volume
        K = self.K_identity + torch.einsum("c,cai,cbj->caibj", lam * vol, r, r)
        K = K + torch.einsum("cp,cpai,cpbj->caibj", (twist - 2 * mu) * vol[:, None], tau, tau)
        return K.reshape(-1)

    def warped_stiffness(self, R: torch.Tensor) -> torch.Tensor:
        """Element stiffness blocks R K0 R^T flattened to match (hess_rows, hess_cols)."""
        K = torch.einsum("cip,capbq,cjq->caibj", R, self.K0, R)
        return K.reshape(-1)
