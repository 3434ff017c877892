"""Oracle: at small strain the corotational simulator's static equilibrium equals linear
elasticity as assembled by scikit-fem on the same mesh (plane strain in 2D)."""
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


def skfem_displacement(X, cells, fixed, force, material):
    """Linear-elastic displacement [N, d] for nodal forces `force` [N, d], fixed nodes clamped."""
    d = X.shape[1]
    mesh = skfem.MeshTri(X.T, cells.T) if d == 2 else skfem.MeshTet(X.T, cells.T)
    element = skfem.ElementVector(skfem.ElementTriP1() if d == 2 else skfem.ElementTetP1())
    basis = skfem.Basis(mesh, element)
    K = skfem.asm(linear_elasticity(*material.lame), basis)
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


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("nu", [-0.9, 0.0, 0.49])
def test_static_equilibrium_matches_scikit_fem(dim, nu):
    X, cells, fixed = MESHES[dim]
    material = Material(5000.0, nu)
    rng = np.random.default_rng(dim)
    force = rng.normal(size=X.shape)
    force[fixed] = 0.0
    u_ref = skfem_displacement(X, cells, fixed, force, material)
    scale = 1e-7 * np.ptp(X, axis=0).max() / np.abs(u_ref).max()  # strain ~ 1e-7: linear regime
    u_ref, force = u_ref * scale, force * scale
    sim = Simulator(ElasticBody(torch.tensor(X), torch.tensor(cells), material), torch.tensor(fixed), SolverConfig(dt=1.0))
    x = sim.static_equilibrium(torch.tensor(X), torch.tensor(force))
    u = (x - torch.tensor(X)).numpy()
    assert np.linalg.norm(u - u_ref) / np.linalg.norm(u_ref) < 1e-6
