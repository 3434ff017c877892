"""The exact (consistent) tangent of the corotated model (`SolverConfig.tangent = "exact"`, and its
positive semi-definite projection "projected"): it is the derivative of the elastic forces,
equals the warped stiffness at a rigid rotation of the rest state, stays finite (and positive
semi-definite when projected) for inverted and collapsed elements, and Newton with it converges
in fewer iterations to the same states as with the warped one, on both linear-algebra back ends."""
import numpy as np
import pytest
import torch

from ggns.geometry import box_tet_mesh
from ggns.sim.fem import ElasticBody
from ggns.sim.material import Material
from ggns.sim.solver import Simulator, SolverConfig


def random_rotation(d: int, rng: torch.Generator) -> torch.Tensor:
    Q, _ = torch.linalg.qr(torch.randn(d, d, generator=rng, dtype=torch.float64))
    if torch.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def small_body(d: int, plane: str = "strain", nu: float = 0.3) -> ElasticBody:
    """A few random elements (two in 2D, a 2 x 1 x 1 tet box in 3D) with shared nodes."""
    if d == 2:
        X = torch.tensor([[0.0, 0.0], [1.0, 0.1], [0.2, 0.9], [1.1, 1.2]], dtype=torch.float64)
        cells = torch.tensor([[0, 1, 2], [1, 3, 2]])
    else:
        X, cells = box_tet_mesh((0, 0, 0), (1.0, 0.5, 0.5), [2, 1, 1])
        X, cells = torch.tensor(X), torch.tensor(cells)
    return ElasticBody(X, cells, Material(1000.0, nu, plane=plane))


def assembled(body: ElasticBody, blocks: torch.Tensor) -> torch.Tensor:
    n = body.X.numel()
    K = torch.zeros(n * n, dtype=torch.float64)
    K.index_add_(0, body.hess_rows * n + body.hess_cols, blocks)
    return K.view(n, n)


@pytest.mark.parametrize("d,plane,nu", [(2, "strain", 0.3), (2, "stress", -0.9), (2, "stress", 0.49),
                                        (3, "strain", 0.3), (3, "strain", -0.9), (3, "strain", 0.49)])
def test_exact_hessian_is_the_derivative_of_the_forces(d, plane, nu):
    body = small_body(d, plane, nu)
    rng = torch.Generator().manual_seed(d)
    for trial in range(3):  # a random stretch and shear, node noise, then a random rotation
        A = torch.eye(d, dtype=torch.float64) + 0.3 * torch.randn(d, d, generator=rng, dtype=torch.float64)
        x = body.X @ A.T + 0.03 * torch.randn(body.X.shape, generator=rng, dtype=torch.float64)
        x = x @ random_rotation(d, rng).T
        F = body.deformation_gradient(x)
        assert (torch.linalg.det(F) > 0.05).all()  # well away from inversion
        H = assembled(body, body.exact_hessian(x))
        n, eps = x.numel(), 1e-6
        H_fd = torch.zeros(n, n, dtype=torch.float64)
        for j in range(n):
            e = torch.zeros(n, dtype=torch.float64)
            e[j] = eps
            e = e.view_as(x)
            H_fd[:, j] = ((body.gradient(x + e)[0] - body.gradient(x - e)[0]) / (2 * eps)).reshape(-1)
        scale = H.abs().max()
        assert (H - H_fd).abs().max() < 1e-7 * scale
        assert (H - H.T).abs().max() < 1e-12 * scale
        # the projection only removes negative curvature: PSD, and H_proj - H is PSD too
        Hp = assembled(body, body.exact_hessian(x, project=True))
        assert torch.linalg.eigvalsh(Hp).min() > -1e-10 * scale
        assert torch.linalg.eigvalsh(Hp - H).min() > -1e-10 * scale
        # the solver's entry point: the same gradient as `gradient`, and these blocks
        for tangent, project in (("exact", False), ("projected", True)):
            g, K = body.gradient_hessian(x, tangent)
            torch.testing.assert_close(g, body.gradient(x)[0], rtol=0, atol=0)
            torch.testing.assert_close(K, body.exact_hessian(x, project), rtol=0, atol=0)


@pytest.mark.parametrize("d", [2, 3])
def test_exact_tangent_equals_warped_at_a_rigid_rotation(d):
    body = small_body(d)
    rng = torch.Generator().manual_seed(10 + d)
    Q = random_rotation(d, rng)
    x = body.X @ Q.T + torch.randn(d, generator=rng, dtype=torch.float64)
    _, R = body.gradient(x)
    warped = body.warped_stiffness(R)
    scale = warped.abs().max()
    # the twist eigenvalues are exactly 0 there, so projected and unprojected agree with warped
    assert (body.exact_hessian(x) - warped).abs().max() < 1e-12 * scale
    assert (body.exact_hessian(x, project=True) - warped).abs().max() < 1e-12 * scale
    # under uniform compression every twist eigenvalue is negative: the projection is the warped
    # stiffness, the exact Hessian is not
    x = 0.9 * body.X @ Q.T
    _, R = body.gradient(x)
    assert (body.exact_hessian(x, project=True) - body.warped_stiffness(R)).abs().max() < 1e-12 * scale
    assert (body.exact_hessian(x) - body.warped_stiffness(R)).abs().max() > 1e-3 * scale


@pytest.mark.parametrize("d", [2, 3])
def test_tangents_are_finite_for_inverted_and_collapsed_elements(d):
    body = small_body(d)
    rng = torch.Generator().manual_seed(20 + d)
    flip = torch.eye(d, dtype=torch.float64)
    flip[0, 0] = -1.0
    collapsed = body.X.clone()
    collapsed[:, -1] = 0.0  # every element flat: a zero singular value
    for x in (body.X @ flip.T,  # every element inverted
              body.X @ torch.diag(torch.tensor([-0.5] + [1.0] * (d - 1), dtype=torch.float64)),
              collapsed,
              torch.zeros_like(body.X),  # every element collapsed to a point: sigma = 0
              body.X + torch.randn(body.X.shape, generator=rng, dtype=torch.float64)):
        assert torch.isfinite(body.exact_hessian(x)).all()
        H = assembled(body, body.exact_hessian(x, project=True))
        assert torch.isfinite(H).all()
        assert torch.linalg.eigvalsh(H).min() > -1e-10 * H.abs().max()


def pulled_block(nu: float):
    """A 5 x 3 x 3-node tet block of 1 x 0.5 x 0.5 m, bottom layer clamped, the top centre node pulled."""
    X, cells = box_tet_mesh((0, 0, 0), (1.0, 0.5, 0.5), [4, 2, 2])
    fixed = X[:, 2] < 1e-9
    pulled = int(np.argmin(((X - [0.5, 0.25, 0.5]) ** 2).sum(1)))
    fixed[pulled] = True
    body = ElasticBody(torch.tensor(X), torch.tensor(cells),
                       Material(30000.0, nu, rayleigh_mass=1.0, rayleigh_stiffness=0.005))
    return body, torch.tensor(fixed), pulled


def run_block(nu: float, tangent: str, linear_solver: str, frames: int = 6):
    body, fixed, pulled = pulled_block(nu)
    config = SolverConfig(dt=0.02, gravity=(0.0, 0.0, -9.81), newton_tolerance=1e-9, tangent=tangent,
                          linear_solver=linear_solver)
    sim = Simulator(body, fixed, config)
    x, v = body.X.clone(), torch.zeros_like(body.X)
    velocity = torch.tensor([1.5, 0.0, 2.0], dtype=torch.float64)  # m/s: large rotations of the top
    iterations = []
    for t in range(1, frames + 1):
        target = body.X.clone()
        target[pulled] += t * config.dt * velocity
        x, v, info = sim.step(x, v, fixed_positions=target)
        iterations.append(info.newton_iterations)
    return x, iterations


@pytest.mark.parametrize("nu", [-0.9, 0.49])
def test_exact_tangent_converges_faster_to_the_same_states(nu):
    x_warped, it_warped = run_block(nu, "warped", "dense")
    x_exact, it_exact = run_block(nu, "exact", "dense")
    x_sparse, it_sparse = run_block(nu, "exact", "sparse")
    x_projected, _ = run_block(nu, "projected", "dense")
    # quadratic convergence: at most 5 Newton iterations per step where "warped" needs 5 to 11
    assert max(it_exact) <= 5 and sum(it_exact) < 0.75 * sum(it_warped)
    # all converge to the stationary point of the same potential (Newton tolerance 1e-9 m)
    assert (x_exact - x_warped).abs().max() < 1e-8
    assert (x_projected - x_warped).abs().max() < 1e-8
    # the exact tangent through the sparse back end: same states, same iteration counts
    assert (x_sparse - x_exact).abs().max() < 1e-10
    assert it_sparse == it_exact


def test_static_equilibrium_with_the_exact_tangent_falls_back_where_indefinite():
    """Without inertia the exact Hessian of a compressed block is indefinite: those iterations take
    the projected tangent, and the equilibrium is the warped tangent's."""
    body, fixed, pulled = pulled_block(0.49)
    x0 = body.X.clone()
    x0[pulled] += torch.tensor([0.2, 0.0, -0.25], dtype=torch.float64)  # pushed down and sideways
    states, fallbacks = [], []
    for tangent in ("warped", "exact"):
        sim = Simulator(body, fixed, SolverConfig(dt=1.0, newton_tolerance=1e-10, tangent=tangent))
        states.append(sim.static_equilibrium(x0))
        fallbacks.append(sim.projected_fallbacks)
    assert (states[0] - states[1]).abs().max() < 1e-8
    assert fallbacks[0] == 0 and fallbacks[1] > 0


def test_unknown_tangent_is_refused():
    with pytest.raises(ValueError, match="tangent"):
        SolverConfig(dt=0.01, tangent="secant")
    with pytest.raises(ValueError, match="tangent"):
        small_body(2).gradient_hessian(small_body(2).X, "secant")
