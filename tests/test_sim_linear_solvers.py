"""The Newton core's linear-algebra back ends (dense Cholesky, sparse LDL^T, banded Cholesky) give
the same matrices, solutions and trajectories; `auto` keeps the plate on the dense path; a bad choice
is refused; the banded one runs LAPACK on one BLAS thread."""
import numpy as np
import pytest
import threadpoolctl
import torch

from ggns.config import load_config
from ggns.geometry import boundary_facets, box_tet_mesh
from ggns.scenes.plate import collider_path, plate_material, plate_mesh, sample_spec
from ggns.sim.fem import ElasticBody
from ggns.sim.linalg import (SPARSE_MIN_FREE_DOFS, BandedLinearAlgebra, DenseLinearAlgebra, SparseLinearAlgebra,
                             one_blas_thread)
from ggns.sim.contact import signed_distance
from ggns.sim.material import Material
from ggns.sim.run import simulate
from ggns.sim.solver import Collider, Simulator, SolverConfig


def block(nodes=(5, 4, 4)):
    """A tet block with its bottom third clamped and its top centre node prescribed."""
    X, cells = box_tet_mesh((0, 0, 0), (1.0, 0.6, 0.6), [n - 1 for n in nodes])
    fixed = X[:, 2] < 0.2 + 1e-9
    pulled = int(np.argmin(((X - [0.5, 0.3, 0.6]) ** 2).sum(1)))
    fixed[pulled] = True
    body = ElasticBody(torch.tensor(X), torch.tensor(cells), Material(5000.0, 0.45, rayleigh_mass=0.5,
                                                                      rayleigh_stiffness=0.01))
    return body, torch.tensor(fixed), pulled


def test_sparse_matrices_equal_the_dense_ones():
    body, fixed, _ = block()
    free = ~fixed[:, None].expand(-1, 3).reshape(-1)
    dense, sparse = DenseLinearAlgebra(body, free), SparseLinearAlgebra(body, free)
    rng = torch.Generator().manual_seed(0)
    x = body.X + 0.05 * torch.randn(body.X.shape, generator=rng, dtype=torch.float64)
    _, R = body.gradient(x)
    diag = torch.rand(body.num_nodes * 3, generator=rng, dtype=torch.float64) + 1.0
    blocks = torch.randn(body.num_nodes, 3, 3, generator=rng, dtype=torch.float64)
    blocks = blocks @ blocks.transpose(1, 2)
    Hd = dense.add_node_blocks(0.3 * dense.stiffness(R) + dense.diag(diag), blocks)
    Hs = sparse.add_node_blocks(0.3 * sparse.stiffness(R) + sparse.diag(diag), blocks)
    torch.testing.assert_close(sparse.to_dense(Hs), Hd, rtol=1e-13, atol=1e-12)
    v = torch.randn(body.num_nodes * 3, generator=rng, dtype=torch.float64)
    torch.testing.assert_close(sparse.matvec(Hs, v), dense.matvec(Hd, v), rtol=1e-12, atol=1e-12)
    g = torch.randn(int(free.sum()), generator=rng, dtype=torch.float64)
    torch.testing.assert_close(sparse.solve(Hs, g), dense.solve(Hd, g), rtol=1e-10, atol=1e-14)
    # the banded back end: the sparse format, its own ordering and factorization
    banded = BandedLinearAlgebra(body, free)
    Hb = banded.add_node_blocks(0.3 * banded.stiffness(R) + banded.diag(diag), blocks)
    torch.testing.assert_close(Hb, Hs, rtol=0, atol=0)
    assert 0 < banded.bandwidth < banded.num_free - 1
    assert sorted(banded.order.tolist()) == list(range(banded.num_free))
    torch.testing.assert_close(banded.solve(Hb, g), dense.solve(Hd, g), rtol=1e-10, atol=1e-14)
    # an indefinite matrix is refused by all three (the Newton loop then raises SimulationError)
    shift = 2 * torch.linalg.eigvalsh(Hd[free][:, free])[0]
    assert dense.solve(Hd - dense.diag(shift.expand(len(diag))), g) is None
    assert sparse.solve(Hs - sparse.diag(shift.expand(len(diag))), g) is None
    assert banded.solve(Hb - banded.diag(shift.expand(len(diag))), g) is None


def test_banded_solves_run_on_one_blas_thread():
    with one_blas_thread():
        assert all(lib["num_threads"] == 1 for lib in threadpoolctl.threadpool_info() if lib["user_api"] == "blas")


def test_sparse_and_dense_trajectories_agree_on_a_tet_block():
    """Pulled node, gravity, damping and a cube collider pressing on the top: same states, same
    Newton iteration counts."""
    body, fixed, pulled = block()
    cube, cube_cells = box_tet_mesh((0, 0, 0), (0.3, 0.3, 0.3), 1)
    faces = torch.tensor(boundary_facets(cube_cells, cube))
    cube = torch.tensor(cube) + torch.tensor([0.05, 0.15, 0.62])  # just above the top, off the pulled node
    states, iterations = {}, {}
    for solver in ("dense", "sparse", "banded"):
        sim = Simulator(body, fixed, SolverConfig(dt=0.01, gravity=(0.0, 0.0, -9.81), linear_solver=solver))
        assert sim.linalg.name == solver
        x, v = body.X.clone(), torch.zeros_like(body.X)
        states[solver], iterations[solver] = [], []
        for t in range(1, 7):
            target = body.X.clone()
            target[pulled] += t * torch.tensor([0.003, 0.0, 0.004], dtype=torch.float64)
            collider = Collider(cube - torch.tensor([0.0, 0.0, 0.01 * t], dtype=torch.float64), faces)
            x, v, info = sim.step(x, v, [collider], fixed_positions=target)
            states[solver].append(x)
            iterations[solver].append((info.newton_iterations, info.contact_iterations))
        assert info.contact_work > 0  # the collider did push
    assert iterations["dense"] == iterations["sparse"] == iterations["banded"]
    for xd, xs, xb in zip(states["dense"], states["sparse"], states["banded"]):
        assert (xd - xs).abs().max() < 1e-9
        assert (xd - xb).abs().max() < 1e-9


def test_sparse_and_dense_plate_trajectories_agree_and_auto_keeps_the_plate_dense():
    cfg = load_config("plate", ["scene.num_steps=8"])
    scene = cfg["scene"]
    spec = sample_spec(scene, 2, -0.9, np.random.default_rng(1))
    rest, cells, fixed = plate_mesh(scene, spec.shape_id)
    path, faces = collider_path(scene, spec)
    material = plate_material(scene, -0.9)
    out = {}
    for solver in ("auto", "dense", "sparse"):
        config = SolverConfig(dt=scene["frame_dt"], linear_solver=solver, **cfg["solver"])
        out[solver] = simulate(rest, cells, fixed, material, config, [(path, faces)])
    np.testing.assert_array_equal(out["auto"][0], out["dense"][0])  # the plate stays dense: bit-identical
    np.testing.assert_allclose(out["sparse"][0], out["dense"][0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(out["sparse"][1]["newton_iterations"], out["dense"][1]["newton_iterations"])
    assert out["dense"][1]["contact_work"].sum() > 0


def test_auto_picks_by_the_number_of_free_dofs():
    body, fixed, _ = block((10, 6, 6))  # the tissue-size block: 717 free dofs
    assert Simulator(body, fixed, SolverConfig(dt=0.01)).linalg.name == "sparse"
    small, small_fixed, _ = block((3, 3, 3))
    assert 3 * int((~small_fixed).sum()) < SPARSE_MIN_FREE_DOFS
    assert Simulator(small, small_fixed, SolverConfig(dt=0.01)).linalg.name == "dense"


def test_unknown_linear_solver_is_refused():
    with pytest.raises(ValueError, match=r"linear_solver must be one of \('auto', 'dense', 'sparse', 'banded'\).*'cholmod'"):
        SolverConfig(dt=0.01, linear_solver="cholmod")


def test_signed_distance_to_a_3d_cube():
    """3D colliders (triangle meshes): distance, sign and normal against the analytic unit cube."""
    cube, cube_cells = box_tet_mesh((0, 0, 0), (1, 1, 1), 2)
    faces = torch.tensor(boundary_facets(cube_cells, cube))
    p = torch.tensor([[0.5, 0.5, 1.2], [0.5, 0.4, 0.9], [1.3, 1.4, 0.5], [0.2, 0.5, 0.5]], dtype=torch.float64)
    phi, normal = signed_distance(p, torch.tensor(cube), faces)
    torch.testing.assert_close(phi, torch.tensor([0.2, -0.1, 0.5, -0.2], dtype=torch.float64))
    torch.testing.assert_close(normal[0], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(normal[1], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(normal[2], torch.tensor([0.6, 0.8, 0.0], dtype=torch.float64))
    torch.testing.assert_close(normal[3], torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64))
