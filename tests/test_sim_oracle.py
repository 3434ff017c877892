"""Oracle: at small strain the corotational simulator's static equilibrium equals linear
elasticity as assembled by scikit-fem on the same mesh (2D: plane strain and plane stress), through
both linear solvers (dense and sparse)."""
import numpy as np
import pytest
import skfem
import torch
from skfem.models.elasticity import linear_elasticity

from ggns.config import load_config
from ggns.scenes.plate import plate_mesh
from ggns.sim.fem import ElasticBody
from ggns.sim.material import Material
from ggns.sim.solver import Simulator, SolverConfig

from conftest import box_mesh


def textbook_lame(E, nu, dim, plane):
    """(lambda, mu) from E and nu, written out independently of ggns.sim.material: plane stress
    has the in-plane material matrix E / (1 - nu^2) [[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]],
    i.e. lambda = E nu / (1 - nu^2); 3D and plane strain use lambda = E nu / ((1 + nu)(1 - 2 nu))."""
    mu = E / (2 * (1 + nu))
    if dim == 2 and plane == "stress":
        return E * nu / (1 - nu**2), mu
    return E * nu / ((1 + nu) * (1 - 2 * nu)), mu


def skfem_displacement(X, cells, fixed, force, lame):
    """Linear-elastic displacement [N, d] for nodal forces `force` [N, d], fixed nodes clamped."""
    d = X.shape[1]
    mesh = skfem.MeshTri(X.T, cells.T) if d == 2 else skfem.MeshTet(X.T, cells.T)
    element = skfem.ElementVector(skfem.ElementTriP1() if d == 2 else skfem.ElementTetP1())
    basis = skfem.Basis(mesh, element)
    K = skfem.asm(linear_elasticity(*lame), basis)
    f = np.zeros(basis.N)
    f[basis.nodal_dofs.T.ravel()] = force.ravel()
    u = skfem.solve(*skfem.condense(K, f, D=basis.nodal_dofs[:, fixed].ravel()))
    return u[basis.nodal_dofs.T]


def meshes():
    plate = load_config("plate")["scene"]
    X2, c2, fixed2 = plate_mesh(plate, 4)
    X3, c3 = box_mesh(3, n=4, size=(1.0, 0.6, 0.8))
    return {2: (X2, c2, fixed2), 3: (X3, c3, X3[:, 2] == 0.0)}


MESHES = meshes()


@pytest.mark.parametrize("linear_solver", ["dense", "sparse", "banded"])
@pytest.mark.parametrize("dim, plane", [(2, "strain"), (2, "stress"), (3, "strain")])
@pytest.mark.parametrize("nu", [-0.9, 0.0, 0.49])
def test_static_equilibrium_matches_scikit_fem(dim, plane, nu, linear_solver):
    X, cells, fixed = MESHES[dim]
    material = Material(5000.0, nu, plane=plane)
    rng = np.random.default_rng(dim)
    force = rng.normal(size=X.shape)
    force[fixed] = 0.0
    u_ref = skfem_displacement(X, cells, fixed, force, textbook_lame(5000.0, nu, dim, plane))
    scale = 1e-7 * np.ptp(X, axis=0).max() / np.abs(u_ref).max()  # strain ~ 1e-7: linear regime
    u_ref, force = u_ref * scale, force * scale
    sim = Simulator(ElasticBody(torch.tensor(X), torch.tensor(cells), material), torch.tensor(fixed),
                    SolverConfig(dt=1.0, linear_solver=linear_solver))
    assert sim.linalg.name == linear_solver
    x = sim.static_equilibrium(torch.tensor(X), torch.tensor(force))
    u = (x - torch.tensor(X)).numpy()
    assert np.linalg.norm(u - u_ref) / np.linalg.norm(u_ref) < 1e-6


@pytest.mark.parametrize("nu", [-0.9, 0.49])
def test_plane_stress_and_plane_strain_differ_except_at_zero_poisson(nu):
    """The switch matters: the two idealizations give different 2D responses for nu != 0 (plane
    strain is stiffer in the plane for nu = 0.49 and softer in bulk for nu = -0.9) and the same
    for nu = 0, where lambda = 0 in both."""
    X, cells, fixed = MESHES[2]
    force = np.random.default_rng(0).normal(size=X.shape) * 1e-4
    force[fixed] = 0.0
    u = {}
    for plane in ("strain", "stress"):
        for v in (nu, 0.0):
            sim = Simulator(ElasticBody(torch.tensor(X), torch.tensor(cells), Material(5000.0, v, plane=plane)),
                            torch.tensor(fixed), SolverConfig(dt=1.0))
            u[plane, v] = (sim.static_equilibrium(torch.tensor(X), torch.tensor(force)) - torch.tensor(X)).numpy()
    assert np.linalg.norm(u["strain", nu] - u["stress", nu]) > 0.05 * np.linalg.norm(u["stress", nu])
    np.testing.assert_allclose(u["strain", 0.0], u["stress", 0.0], rtol=1e-9, atol=1e-15)
