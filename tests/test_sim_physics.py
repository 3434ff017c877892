"""Physics of the ground-truth simulator: Poisson effect, rigid-motion invariance,
convergence in the time step, and refusal of invalid materials."""
import math

import numpy as np
import pytest
import torch

from ggns.config import load_config
from ggns.scenes.plate import collider_path, make_trajectory, plate_material, plate_mesh, sample_spec
from ggns.sim.fem import ElasticBody
from ggns.sim.material import Material
from ggns.sim.run import simulate
from ggns.sim.solver import SolverConfig, Simulator

from conftest import box_mesh


@pytest.mark.parametrize("dim, plane", [(2, "strain"), (2, "stress"), (3, "strain")])
@pytest.mark.parametrize("nu", [-0.9, 0.0, 0.49])
def test_uniaxial_compression_gives_the_linear_elastic_strain_ratio(dim, plane, nu):
    """A free block compressed by 1 % between frictionless plates (roller conditions): the
    lateral strain is -nu/(1-nu) x the axial one in plane strain, -nu in plane stress and 3D."""
    X, cells = box_mesh(dim, n=5)
    axial = dim - 1  # compress along the last axis
    bottom, top = X[:, axial] == 0.0, X[:, axial] == 1.0
    fixed = np.zeros_like(X, dtype=bool)
    fixed[bottom | top, axial] = True  # rollers: normal displacement prescribed
    fixed[np.all(X[:, :axial] == 0.0, axis=1) & bottom, :] = True  # pin one corner against rigid motion
    if dim == 3:  # and the rotation about the axial axis
        fixed[(X[:, 0] == 1.0) & (X[:, 1] == 0.0) & bottom, 1] = True
    x0 = X.copy()
    x0[top, axial] -= 0.01
    material = Material(5000.0, nu, plane=plane)
    sim = Simulator(ElasticBody(torch.tensor(X), torch.tensor(cells), material), torch.tensor(fixed), SolverConfig(dt=1.0))
    x = sim.static_equilibrium(torch.tensor(x0)).numpy()
    eps_axial = -0.01
    eps_lateral = (x[X[:, 0] == 1.0, 0] - x[X[:, 0] == 0.0, 0]).mean() - 1.0
    expected = -nu / (1 - nu) if (dim, plane) == (2, "strain") else -nu
    ratio = eps_lateral / eps_axial
    assert ratio == pytest.approx(expected, rel=0.02, abs=1e-3)
    if nu < 0:
        assert eps_lateral < 0  # the auxetic block contracts sideways under compression
    else:
        assert eps_lateral > -1e-6


@pytest.mark.parametrize("dim", [2, 3])
def test_rigid_motion_creates_no_elastic_force(dim):
    X, cells = box_mesh(dim, n=4)
    body = ElasticBody(torch.tensor(X), torch.tensor(cells), Material(5000.0, 0.3))
    a = 1.1
    R2 = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=torch.float64)
    R = R2 if dim == 2 else torch.block_diag(R2, torch.ones(1, 1, dtype=torch.float64)) @ torch.linalg.matrix_exp(
        torch.tensor([[0, 0, 0.7], [0, 0, -0.4], [-0.7, 0.4, 0]], dtype=torch.float64))
    moved = torch.tensor(X) @ R.T + 0.37
    strained = torch.tensor(X) * 1.01
    g_rigid, g_strain = body.gradient(moved)[0], body.gradient(strained)[0]
    assert g_rigid.abs().max() < 1e-9 * g_strain.abs().max()
    assert body.energy(moved).abs() < 1e-12 * body.energy(strained)


def _plate_final_state(substeps: int) -> np.ndarray:
    cfg = load_config("plate", ["scene.num_steps=11", "scene.collider.travel=0.12"])
    scene = cfg["scene"]
    spec = sample_spec(scene, 4, 0.0, np.random.default_rng(0))
    rest, cells, fixed = plate_mesh(scene, 4)
    path, faces = collider_path(scene, spec)
    material = plate_material(scene, 0.0)
    solver = SolverConfig(dt=scene["frame_dt"] / substeps, newton_tolerance=1e-10, contact_tolerance=1e-6)
    positions, _ = simulate(rest, cells, fixed, material, solver, [(path, faces)], substeps)
    return positions[-1]


def test_halving_the_time_step_converges():
    """Backward Euler is first order: the error against a fine reference roughly halves with dt."""
    reference = _plate_final_state(32)
    errors = [np.abs(_plate_final_state(s) - reference).max() for s in (1, 2, 4)]
    assert errors[0] > errors[1] > errors[2]
    assert errors[0] / errors[1] > 1.5 and errors[1] / errors[2] > 1.5


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"youngs_modulus": 5000.0, "poissons_ratio": 0.5}, "Poisson"),
        ({"youngs_modulus": 5000.0, "poissons_ratio": -1.0}, "Poisson"),
        ({"youngs_modulus": 0.0, "poissons_ratio": 0.3}, "Young"),
        ({"youngs_modulus": float("nan"), "poissons_ratio": 0.3}, "Young"),
        ({"youngs_modulus": 5000.0, "poissons_ratio": 0.3, "density": -1.0}, "density"),
        ({"youngs_modulus": 5000.0, "poissons_ratio": 0.3, "plane": "plain"}, "plane"),
    ],
)
def test_invalid_material_is_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Material(**kwargs)


def test_scene_with_invalid_poissons_ratio_is_refused(tiny_config):
    tiny_config["scene"]["poissons_ratios"] = [0.5]
    with pytest.raises(ValueError, match="Poisson"):
        make_trajectory(tiny_config, 0, 0, sensor=None)


def _pressed_and_dragged(friction: float, steps: int = 10):
    """The tet block of test_sim_linear_solvers with a cube pressed 2 cm into its top over 4 steps, then
    dragged 1 cm per step along x for `steps` steps: (the top nodes' mean x displacement, the cube's)."""
    from ggns.geometry import boundary_facets, box_tet_mesh
    from ggns.sim.solver import Collider, Simulator, SolverConfig
    from test_sim_linear_solvers import block

    body, fixed, pulled = block()
    fixed[pulled] = False
    cube, cube_cells = box_tet_mesh((0, 0, 0), (0.4, 0.8, 0.3), 1)
    faces = torch.tensor(boundary_facets(cube_cells, cube))
    cube = torch.tensor(cube) + torch.tensor([0.3, -0.1, 0.6])  # touching the top, across its width
    sim = Simulator(body, fixed, SolverConfig(dt=0.01, friction=friction))
    x, v = body.X.clone(), torch.zeros_like(body.X)
    offset = torch.zeros(3, dtype=torch.float64)
    top = body.X[:, 2] > 0.6 - 1e-9
    for t in range(4 + steps):
        offset += torch.tensor([0.01 if t >= 4 else 0.0, 0.0, -0.005 if t < 4 else 0.0], dtype=torch.float64)
        x, v, info = sim.step(x, v, [Collider(cube + offset, faces)])
        assert info.max_penetration <= 1e-4
    under = top & (body.X[:, 0] > 0.3) & (body.X[:, 0] < 0.7)
    return (x - body.X)[under, 0].mean().item(), offset[0].item()


def test_friction_drags_the_surface_along_and_frictionless_contact_does_not():
    """A cube pressed into a clamped block and dragged 10 cm sideways: without friction the nodes under it
    barely move along x (only what the pressing does); with mu = 0.5 they follow a little of the drag; with
    mu = 10 they stick, and a larger mu changes nothing more (sticking is the limit: the block's shear
    stiffness then decides, up to the slip the smoothing allows, 1e-5 m per step)."""
    frictionless, dragged = _pressed_and_dragged(0.0)
    some, _ = _pressed_and_dragged(0.5)
    sticking, _ = _pressed_and_dragged(10.0)
    stuck, _ = _pressed_and_dragged(100.0)
    assert abs(frictionless) < 0.02 * dragged
    assert 0.03 * dragged < some < 0.5 * sticking
    assert sticking > 0.5 * dragged and abs(stuck - sticking) < 0.05 * sticking


def test_friction_settings_are_checked():
    from ggns.sim.solver import SolverConfig

    for kwargs in (dict(friction=-0.1), dict(friction_velocity=0.0)):
        with pytest.raises(ValueError, match="friction"):
            SolverConfig(dt=0.01, **kwargs)


def test_a_file_from_before_friction_reads_as_frictionless_and_not_as_friction():
    """A split file written before the solver had `friction` does not name it: it is the frictionless
    preset's file, and another configuration than a preset with friction."""
    import dataclasses

    from ggns.data.schema import SOLVER_DEFAULTS, config_differences
    from ggns.sim.solver import SolverConfig

    defaults = {f.name: f.default for f in dataclasses.fields(SolverConfig)}
    assert all(defaults[k] == v for k, v in SOLVER_DEFAULTS.items())
    stored = load_config("cavity_tiny")
    stored["solver"].pop("friction")
    assert config_differences(stored, load_config("cavity_tiny")) == []
    assert config_differences(stored, load_config("cavity_tiny", ["solver.friction=0.5"])) == ["solver.friction"]
