"""Implicit (backward Euler) time stepping of an `ElasticBody` with Dirichlet nodes and
kinematic rigid colliders, plus a static equilibrium solver that shares the same Newton core.

One time step minimizes the incremental potential over the free degrees of freedom
    Phi(x) = |x - x_pred|^2_M / (2 h^2) + E(x) - f_ext . x + |x - x_n|^2_D / (2 h) + C(x),
x_pred = x_n + h v_n, D = alpha M + beta K(x_n) (Rayleigh damping, stiffness lagged to the
step's start), whose stationary point is backward Euler. C(x) is the augmented-Lagrangian
term of the non-penetration constraints phi_i(x) >= 0 (signed distance of node i to each
collider at the step's end). Newton uses an elastic tangent chosen by `SolverConfig.tangent`
(fem.py): the positive semi-definite warped stiffness, or the exact Hessian (falling back to its
positive semi-definite projection in an iteration where the Newton matrix is not positive
definite), and an Armijo line search on Phi, so with a positive definite matrix every step
decreases the potential: unconditionally stable, no oscillation. The damping matrix D is the
warped stiffness whatever the tangent (it is part of the model, not of the solver).
Multiplier updates repeat until no node is inside a collider by more than the tolerance.
Contact is node-to-surface, frictionless by default. With `SolverConfig.friction` mu > 0 the potential
gains a lagged, smoothed Coulomb term (as in incremental-potential contact): for each node the previous
step ended in contact with a collider, with that step's normal force N and normal n,
    F(x) = sum_i mu N_i f(|T_i u_i|),  u_i = (x_i - x_n,i) - (collider displacement at node i),
T_i = I - n_i n_i^T and f(y) = y^2 / (2 eps) for y < eps, y - eps / 2 beyond, eps = friction_velocity h:
sticking below a slip of eps per step, sliding with force mu N beyond. The collider's displacement at
a node is that of its nearest collider vertex (exact for a translating collider).

The linear algebra (matrix format, factorization) is a back end from `linalg` chosen by
`SolverConfig.linear_solver`: dense Cholesky, sparse LDL^T or banded Cholesky; the Newton loop, line search,
contact and error reporting are the same for both.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..errors import SimulationError  # noqa: F401 (raised here; importable from here as before)
from .contact import signed_distance
from .fem import TANGENTS, ElasticBody
from .linalg import LINEAR_SOLVERS, SPARSE_MIN_FREE_DOFS, linear_algebra


@dataclass(frozen=True)
class SolverConfig:
    """dt: solver time step in s. Tolerances are in metres (the task space's length unit)."""

    dt: float
    gravity: tuple[float, ...] | None = None  # m/s^2, None: no gravity
    newton_tolerance: float = 1e-9  # max |dx| of the last full Newton step, m
    max_newton_iterations: int = 100
    contact_tolerance: float = 1e-4  # max penetration at the end of a step, m
    contact_stiffness: float = 100.0  # penalty per node, relative to its own mass+stiffness diagonal
    max_contact_iterations: int = 40
    # "dense" (torch Cholesky), "sparse" (scipy SuperLU), "banded" (LAPACK banded Cholesky after a
    # reverse Cuthill-McKee ordering: thin meshes such as the cavity's tube) or "auto": sparse from
    # SPARSE_MIN_FREE_DOFS free unknowns on, dense below (docs/simulator.md, "Linear solver")
    linear_solver: str = "auto"
    # Newton's elastic tangent (fem.py, docs/simulator.md "Tangent"): "warped" (R K0 R^T, the
    # rotation's derivative omitted), "exact" (the exact Hessian; an iteration whose Newton matrix
    # is then not positive definite retries with "projected") or "projected" (the exact Hessian
    # clamped to positive semi-definite)
    tangent: str = "warped"
    # True: a step that starts at rest (zero velocity, prescribed nodes not moving, no contact
    # force) at a state whose potential gradient g satisfies |g|_2 h^2 / min node mass <=
    # newton_tolerance keeps the state without a Newton solve (Simulator.step). That bounds the
    # Newton step below the tolerance whenever the elastic tangent there is positive
    # semi-definite, as at the rest shape. For scenes that wait at rest until a collider arrives
    # (the cavity); off by default so that existing presets regenerate bit for bit.
    skip_at_rest: bool = False
    # Coulomb friction coefficient between the body and every collider (0: frictionless, as every shipped
    # preset), and the slip speed below which contact sticks (m/s; the smoothing of the Coulomb cone)
    friction: float = 0.0
    friction_velocity: float = 1e-3

    def __post_init__(self) -> None:
        if not self.dt > 0:
            raise ValueError(f"dt must be > 0 s, got {self.dt}")
        for name in ("newton_tolerance", "contact_tolerance", "contact_stiffness"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(f"linear_solver must be one of {LINEAR_SOLVERS} (\"auto\": sparse from "
                             f"{SPARSE_MIN_FREE_DOFS} free unknowns on), got {self.linear_solver!r}")
        if self.tangent not in TANGENTS:
            raise ValueError(f"tangent must be one of {TANGENTS}, got {self.tangent!r}")
        if not self.friction >= 0 or not self.friction_velocity > 0:
            raise ValueError(f"friction must be >= 0 and friction_velocity > 0 m/s, got {self.friction} and "
                             f"{self.friction_velocity}")


@dataclass
class StepInfo:
    newton_iterations: int  # summed over contact iterations
    contact_iterations: int
    max_penetration: float  # m, >= 0
    contact_work: float  # J, work of the contact forces on the body during the step


@dataclass
class Collider:
    """A rigid collider surface at one instant: vertices [K, d], faces [F, d] (segments or triangles)."""

    vertices: torch.Tensor
    faces: torch.Tensor


class Simulator:
    """Backward Euler simulator of one body. `fixed` is [N] or [N, d] bool (per-dof Dirichlet)."""

    def __init__(self, body: ElasticBody, fixed: torch.Tensor, config: SolverConfig):
        self.body, self.config = body, config
        n, d = body.num_nodes, body.dim
        fixed = torch.as_tensor(fixed, dtype=torch.bool)
        fixed = fixed[:, None].expand(n, d) if fixed.ndim == 1 else fixed
        if fixed.shape != (n, d):
            raise ValueError(f"fixed must be [N] or [N, d] = [{n}, {d}], got {tuple(fixed.shape)}")
        self.free = ~fixed.reshape(-1)  # [N d]
        self.linalg = linear_algebra(config.linear_solver, body, self.free)
        gravity = (0.0,) * d if config.gravity is None else tuple(config.gravity)
        if len(gravity) != d:
            raise ValueError(f"gravity must have {d} components, got {gravity}")
        self.gravity_force = body.node_mass[:, None] * torch.tensor(gravity, dtype=torch.float64)
        self.mass_dofs = body.node_mass.repeat_interleave(d)  # [N d]
        rest_diag = torch.zeros(n * d, dtype=torch.float64)
        diag = body.hess_rows == body.hess_cols
        rest_diag.index_add_(0, body.hess_rows[diag], body.K0.reshape(-1)[diag])
        node_scale = (self.mass_dofs / config.dt**2 + rest_diag).reshape(n, d).mean(1)
        self.contact_kappa = config.contact_stiffness * node_scale  # [N] N/m
        extent = (body.X.amax(0) - body.X.amin(0)).norm().item()
        self.line_search_threshold = 1e-6 * extent  # smaller Newton steps are taken in full
        self.multipliers: list[torch.Tensor] = []  # per collider [N], warm-started over steps
        # friction (config.friction > 0): per collider, the last step's (normal force [N], normal [N, d],
        # collider vertices [K, d]) at its end
        self.friction_lag: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
        self.projected_fallbacks = 0  # Newton iterations of tangent "exact" that took "projected"
        self.steps_taken = 0

    # ---- assembly -------------------------------------------------------------------
    def _contact(self, x: torch.Tensor, colliders: list[Collider], want_hessian: bool):
        """AL contact term: value, gradient [N, d], Gauss-Newton Hessian blocks, and per collider phi [N]
        and the normals [N, d] (inf and zero at nodes outside its bounding box without a multiplier)."""
        value = x.new_zeros(())
        grad = torch.zeros_like(x)
        hess = [] if want_hessian else None
        phis, normals = [], []
        kappa = self.contact_kappa
        for lam, col in zip(self.multipliers, colliders):
            # nodes outside the collider's bounding box are outside the collider (phi > 0):
            # without a multiplier their term is exactly zero, so only the rest is evaluated
            lo, hi = col.vertices.amin(0), col.vertices.amax(0)
            near = (((x >= lo) & (x <= hi)).all(1) | (lam > 0)).nonzero().flatten()
            phi = torch.full_like(lam, torch.inf)
            normal = torch.zeros_like(x)
            if len(near):
                phi[near], normal[near] = signed_distance(x[near], col.vertices, col.faces)
            force = (lam - kappa * phi).clamp_min(0.0)  # [N] normal force magnitude
            value = value + ((force**2 - lam**2) / (2 * kappa)).sum()
            grad -= force[:, None] * normal
            if want_hessian:
                active = (force > 0).to(x.dtype) * kappa
                hess.append(active[:, None, None] * normal[:, :, None] * normal[:, None, :])
            phis.append(phi)
            normals.append(normal)
        return value, grad, hess, phis, normals

    def _friction_terms(self, x: torch.Tensor, colliders) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
        """Per collider in contact at the last step's end: (nodes [M], mu N [M], tangent projector [M, d, d],
        the collider's displacement at those nodes over this step [M, d])."""
        if not self.config.friction > 0 or len(self.friction_lag) != len(colliders):
            return []
        terms = []
        for (normal_force, normal, before), col in zip(self.friction_lag, colliders):
            nodes = (normal_force > 0).nonzero().flatten()
            if not len(nodes) or before.shape != col.vertices.shape:
                continue
            nearest = torch.cdist(x[nodes], before).argmin(1)
            moved = col.vertices[nearest] - before[nearest]
            n = normal[nodes]
            project = torch.eye(x.shape[1], dtype=x.dtype) - n[:, :, None] * n[:, None, :]
            terms.append((nodes, self.config.friction * normal_force[nodes], project, moved))
        return terms

    def _friction(self, y: torch.Tensor, x: torch.Tensor, terms, want_hessian: bool):
        """The lagged friction potential F(y) of the step from x (module docstring): value, gradient [N, d],
        Hessian blocks [N, d, d] (positive semi-definite) or None."""
        eps = self.config.friction_velocity * self.config.dt
        value, grad = y.new_zeros(()), torch.zeros_like(y)
        hess = torch.zeros(y.shape + (y.shape[1],), dtype=y.dtype) if want_hessian else None
        for nodes, mu_n, project, moved in terms:
            u = torch.einsum("mij,mj->mi", project, y[nodes] - x[nodes] - moved)  # tangential slip
            slip = u.norm(dim=1)
            stick = slip < eps
            value = value + (mu_n * torch.where(stick, slip**2 / (2 * eps), slip - eps / 2)).sum()
            scale = mu_n / torch.where(stick, torch.full_like(slip, eps), slip)
            grad.index_add_(0, nodes, scale[:, None] * u)
            if want_hessian:
                t = u / slip.clamp_min(1e-300)[:, None]
                sliding = (~stick).to(y.dtype)[:, None, None] * t[:, :, None] * t[:, None, :]
                hess.index_add_(0, nodes, scale[:, None, None] * (project - sliding))
        return value, grad, hess

    def _lag_friction(self, phis, normals, colliders) -> None:
        """Keep this step's normal forces and normals at its end (`_contact` at the accepted positions)
        for the next step's friction."""
        self.friction_lag = [((lam - self.contact_kappa * phi).clamp_min(0.0), normal, col.vertices.clone())
                             for lam, phi, normal, col in zip(self.multipliers, phis, normals, colliders)]

    # ---- Newton core ------------------------------------------------------------------
    def _minimize(self, x: torch.Tensor, potential, gradient_hessian, what: str) -> tuple[torch.Tensor, int]:
        """Minimize `potential` over the free dofs from x by Newton with Armijo line search.
        gradient_hessian(x, tangent) -> gradient [N, d], Newton matrix."""
        free, tangent = self.free, self.config.tangent
        known = None  # potential(x) when the last line search computed it (the accepted trial): not again
        for it in range(1, self.config.max_newton_iterations + 1):
            g, H = gradient_hessian(x, tangent)
            g = g.reshape(-1)[free]
            dx_free = self.linalg.solve(H, g)
            if dx_free is None and tangent == "exact":
                # the exact Hessian is indefinite here (compressed and twisted elements outweigh
                # the inertia): this iteration takes its positive semi-definite projection
                self.projected_fallbacks += 1
                g, H = gradient_hessian(x, "projected")
                g = g.reshape(-1)[free]
                dx_free = self.linalg.solve(H, g)
            if dx_free is None:
                raise SimulationError(f"{what}: Newton matrix not positive definite at iteration {it} "
                                      f"({self.linalg.name} solver; Dirichlet nodes missing?)")
            dx_free = -dx_free
            dx = torch.zeros_like(x).reshape(-1)
            dx[free] = dx_free
            dx = dx.view_as(x)
            alpha = 1.0
            if dx_free.abs().max() > self.line_search_threshold:
                phi0 = potential(x) if known is None else known
                slope = (g * dx_free).sum()
                while (known := potential(x + alpha * dx)) > phi0 + 1e-4 * alpha * slope:
                    alpha *= 0.5
                    if alpha < 1e-10:
                        raise SimulationError(f"{what}: line search failed at Newton iteration {it}")
            else:
                known = None
            x = x + alpha * dx
            if not torch.isfinite(x).all():
                raise SimulationError(f"{what}: non-finite positions at Newton iteration {it}")
            # converged when the full Newton step is below the tolerance: a step the line search
            # shrank (alpha < 1) can be tiny at a kink of the energy (an inverted element) far from
            # a stationary point, so a small accepted step alone does not end the iteration
            if dx_free.abs().max() < self.config.newton_tolerance:
                return x, it
        raise SimulationError(
            f"{what}: Newton did not converge in {self.config.max_newton_iterations} iterations "
            f"(last Newton step {dx_free.abs().max():.3e} m, taken with line-search factor {alpha:.3g})"
        )

    # ---- public API -------------------------------------------------------------------
    def step(
        self,
        x: torch.Tensor,
        v: torch.Tensor,
        colliders: list[Collider] = (),
        fixed_positions: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, StepInfo]:
        """Advance by dt. x, v: [N, d] at the step's start; colliders: at the step's end;
        fixed_positions: [N, d] prescribed positions of the fixed dofs at the step's end
        (default: unchanged). Returns x, v at the end and diagnostics."""
        cfg, body = self.config, self.body
        h, what = cfg.dt, f"time step {self.steps_taken}"
        if len(self.multipliers) != len(colliders):
            self.multipliers = [x.new_zeros(body.num_nodes) for _ in colliders]
        if cfg.skip_at_rest and self._at_rest(x, v, colliders, fixed_positions):
            self.steps_taken += 1
            return x.clone(), torch.zeros_like(v), StepInfo(0, 0, 0.0, 0.0)
        x_pred = x + h * v
        fixed = ~self.free.view_as(x)
        if fixed_positions is not None:
            x_pred = torch.where(fixed, fixed_positions, x_pred)
        else:
            x_pred = torch.where(fixed, x, x_pred)
        M = self.mass_dofs.view_as(x)
        la = self.linalg
        _, R_start = body.gradient(x)
        D = body.material.rayleigh_stiffness * la.stiffness(R_start)
        D = D + la.diag(body.material.rayleigh_mass * self.mass_dofs)
        Hconst = D / h + la.diag(self.mass_dofs / h**2)
        friction = self._friction_terms(x, colliders)

        def potential(y):
            dy, dn = (y - x_pred).reshape(-1), (y - x).reshape(-1)
            value = 0.5 * (self.mass_dofs * dy * dy).sum() / h**2 + dn @ la.matvec(D, dn) / (2 * h)
            value = value + body.energy(y) - (self.gravity_force * y).sum()
            if friction:
                value = value + self._friction(y, x, friction, False)[0]
            return value + self._contact(y, colliders, False)[0]

        def gradient_hessian(y, tangent):
            ge, K = body.gradient_hessian(y, tangent)
            dn = (y - x).reshape(-1)
            g = M * (y - x_pred) / h**2 + ge - self.gravity_force + la.matvec(D, dn).view_as(y) / h
            _, gc, hc, _, _ = self._contact(y, colliders, True)
            H = Hconst + la.assemble(K)
            for blocks in hc:
                H = la.add_node_blocks(H, blocks)
            if friction:
                _, gf, hf = self._friction(y, x, friction, True)
                g, H = g + gf, la.add_node_blocks(H, hf)
            return g + gc, H

        newton_total, y = 0, x_pred
        for contact_it in range(1, cfg.max_contact_iterations + 1):
            y, its = self._minimize(y, potential, gradient_hessian, what)
            newton_total += its
            _, gc, _, phis, normals = self._contact(y, colliders, False)
            penetration = max([0.0] + [(-phi[self.free.view_as(x)[:, 0]]).max().item() for phi in phis])
            if penetration <= cfg.contact_tolerance:
                break
            self.multipliers = [(lam - self.contact_kappa * phi).clamp_min(0.0) for lam, phi in zip(self.multipliers, phis)]
        else:
            raise SimulationError(
                f"{what}: penetration {penetration:.3e} m still above the tolerance "
                f"{cfg.contact_tolerance:.1e} m after {cfg.max_contact_iterations} contact iterations"
            )
        work = -(gc * (y - x)).sum().item()  # contact force = -gradient of C
        if self.config.friction > 0:
            self._lag_friction(phis, normals, colliders)
        v_new = (y - x) / h
        if not (torch.isfinite(y).all() and torch.isfinite(v_new).all()):
            raise SimulationError(f"{what}: non-finite state")
        self.steps_taken += 1
        return y, v_new, StepInfo(newton_total, contact_it, penetration, work)

    def _at_rest(self, x, v, colliders, fixed_positions) -> bool:
        """Whether a step from (x, v) may keep x (SolverConfig.skip_at_rest)."""
        if v.abs().max() > 0:
            return False
        fixed = ~self.free.view_as(x)
        if fixed_positions is not None and (fixed_positions[fixed] != x[fixed]).any():
            return False
        if len(self.multipliers) and any((lam > 0).any() for lam in self.multipliers):
            return False
        ge, _ = self.body.gradient(x)
        _, gc, _, _, _ = self._contact(x, colliders, False)
        if gc.abs().max() > 0:
            return False
        g = (ge - self.gravity_force).reshape(-1)[self.free]
        bound = g.norm() * self.config.dt**2 / self.body.node_mass.min()
        return bool(bound <= self.config.newton_tolerance)

    def static_equilibrium(
        self, x0: torch.Tensor, external_force: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Positions [N, d] minimizing E(x) - f . x with the fixed dofs held at their values in x0
        (no inertia, no colliders). The fixed dofs must remove all rigid motions."""
        f = torch.zeros_like(x0) if external_force is None else external_force.to(torch.float64)
        body = self.body

        def potential(y):
            return body.energy(y) - (f * y).sum()

        def gradient_hessian(y, tangent):
            g, K = body.gradient_hessian(y, tangent)
            return g - f, self.linalg.assemble(K)

        return self._minimize(x0.to(torch.float64), potential, gradient_hessian, "static equilibrium")[0]

    def kinetic_energy(self, v: torch.Tensor) -> float:
        return 0.5 * (self.mass_dofs * v.reshape(-1) ** 2).sum().item()
