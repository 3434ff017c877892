"""The Cavity Grasping scene (`ggns.scenes.cavity`) on its tiny preset: real simulation with real
contact, real Open3D raycasting and real HDF5 files, the scale targets, and a fit + test + export
through the CLI."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from ggns.__main__ import main
from ggns.config import load_config
from ggns.data.generate import generate
from ggns.data.schema import read_trajectories
from ggns.geometry import boundary_facets, min_volume_ratio
from ggns.scenes import cavity
from ggns.sensors.camera import DepthSensor, SensorConfig
from ggns.sim.contact import signed_distance

from conftest import fit_and_test_3d


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny preset's splits (3/2/2 trajectories of 12 steps: the gripper starts at its grasp pose
    and closes fast) and its config; the train split's trajectories (one per material)."""
    out = tmp_path_factory.mktemp("cavity_tiny")
    config = load_config("cavity_tiny", [f"output={out}"])
    train, _, _ = generate(config, ["train", "val", "test"], progress=False)
    return config, read_trajectories(train)


def _finger_boxes(config, traj) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Both fingers' contact boxes per step, rebuilt from the trajectory's parameters."""
    scene = config["scene"]
    rng = np.random.default_rng(traj.seed)
    spec = cavity.sample_spec(scene, 0, rng)
    centres, gaps, _ = cavity.gripper_schedule(scene, spec)
    box, faces = cavity.finger_mesh(scene, coarse=True)
    return [(torch.as_tensor(cavity.gripper_vertices(box, centres[t], spec.azimuth, gaps[t])), torch.as_tensor(faces))
            for t in range(traj.num_steps)]


@pytest.mark.parametrize("preset, around, along", [("cavity", 25, 15), ("cavity_tall", 15, 25)])
def test_tube_mesh_counts_and_its_surface_graph(preset, around, along):
    """750 nodes, every one on the wall's boundary; the graph is that boundary's triangulation, a
    closed genus-1 surface with exactly 3 V undirected edges (the paper's 4,500 directed); the fixed nodes
    are the bottom ring of both walls, numbered first (the tall cavity's 0-29: the reference's)."""
    config = load_config(preset)
    scene = config["scene"]
    spec = cavity.CavitySpec(0, 0.5, 0.6, 0.0, 0.5, (0.0, 0.0, 0.0), 0.3)
    rest, cells, fixed = cavity.cavity_mesh(scene, spec)
    facets = boundary_facets(cells, rest)
    edges = cavity.surface_edges(facets)
    assert (scene["cavity"]["ring_nodes"], scene["cavity"]["levels"]) == (around, along)
    assert rest.shape == (750, 3) and cells.shape == (6 * around * (along - 1), 4)
    assert len(np.unique(facets)) == 750  # no interior node
    assert 2 * len(edges) == 4500 and len(rest) - len(edges) + len(facets) == 0  # Euler characteristic 0: a torus
    assert np.flatnonzero(fixed).tolist() == list(range(2 * around))  # the bottom rim, numbered first
    assert np.allclose(rest[fixed, 2], scene["cavity"]["bottom_z"])
    outer = np.linalg.norm(rest[around:2 * around, :2], axis=1)  # level 0, outer wall: the bottom diameter
    np.testing.assert_allclose(outer, 0.25)
    inner = np.linalg.norm(rest[:around, :2], axis=1)
    np.testing.assert_allclose(outer - inner, scene["cavity"]["thickness"])
    top = rest[-around:]  # the last level's outer wall: the top diameter, `height` above the bottom
    np.testing.assert_allclose(np.linalg.norm(top[:, :2], axis=1), 0.3)
    np.testing.assert_allclose(top[:, 2], scene["cavity"]["bottom_z"] + scene["cavity"]["height"])
    finger, faces = cavity.finger_mesh(scene)
    assert 2 * len(finger) == 636 and faces.max() == len(finger) - 1


def test_fingers_close_and_squeeze_without_penetration(tiny):
    config, trajectories = tiny
    tolerance = config["solver"]["contact_tolerance"]
    assert sorted(t.poissons_ratio for t in trajectories) == [-0.9, 0.0, 0.49]
    for traj in trajectories:
        assert np.isfinite(traj.positions).all() and np.isfinite(traj.points).all()
        assert traj.collider_positions.shape == (traj.num_steps, 636, 3)
        # the fingers closed: the two fingers' mean positions came closer
        V = 318
        gap = np.linalg.norm(traj.collider_positions[:, :V].mean(1) - traj.collider_positions[:, V:].mean(1), axis=1)
        assert gap[-1] < gap[0] - 0.2
        # the cavity deformed, the fixed rim stayed exactly
        free = ~traj.fixed
        assert np.linalg.norm(traj.positions[-1, free] - traj.rest_positions[free], axis=1).max() > 0.03
        np.testing.assert_array_equal(traj.positions[:, traj.fixed],
                                      np.broadcast_to(traj.rest_positions[traj.fixed], (traj.num_steps, 50, 3)))
        # no free cavity node inside a finger beyond the contact tolerance, checked independently of the solver
        for t, fingers in enumerate(_finger_boxes(config, traj)):
            x = torch.as_tensor(traj.positions[t][free])
            for k in range(2):
                vertices = fingers[0][8 * k: 8 * (k + 1)]
                phi, _ = signed_distance(x, vertices, fingers[1])
                assert -phi.min().item() <= tolerance * (1 + 1e-6)
        assert traj.diagnostics["max_penetration"].max() <= tolerance
        assert traj.diagnostics["max_penetration"][-1] >= 0 and traj.diagnostics["contact_work"].sum() > 0
        assert min_volume_ratio(traj.positions, traj.rest_positions, traj.cells) > 0.3
        # the fingers' own corners may pass between nodes: measured, bounded by the wall's thickness
        assert 0 <= traj.diagnostics["finger_penetration"].max() < config["scene"]["cavity"]["thickness"]


@pytest.mark.parametrize("nu", [-0.95, 0.499])
def test_extreme_poissons_ratios_stay_finite_and_uninverted(nu):
    """Seed 5's fingers reach the wall at step 4 and squeeze it by 22 % of its diameter by step 8."""
    config = load_config("cavity_tiny", ["scene.num_steps=9"])
    config["scene"]["materials"] = [{"poissons_ratio": nu, "youngs_modulus": 20000.0}]
    sensor = DepthSensor(SensorConfig.from_dict(config["sensor"]))
    traj = cavity.make_trajectory(config, 0, 5, sensor)
    assert all(np.isfinite(v).all() for v in traj.diagnostics.values()) and np.isfinite(traj.positions).all()
    assert min_volume_ratio(traj.positions, traj.rest_positions, traj.cells) > 0.2
    assert traj.diagnostics["contact_work"].sum() > 0  # it was squeezed


def test_banded_and_sparse_solvers_give_the_same_squeeze():
    """The preset's banded Cholesky against SuperLU's LDL^T on a squeeze (seed 5: contact from step 4):
    the same Newton iterations per step, positions equal to round-off."""
    from ggns.bench.timing import NoSensor

    out = {}
    for solver in ("banded", "sparse"):
        config = load_config("cavity_tiny", ["scene.num_steps=9", f"solver.linear_solver={solver}"])
        out[solver] = cavity.make_trajectory(config, 1, 5, NoSensor(3))
    assert out["banded"].diagnostics["contact_work"].sum() > 0
    np.testing.assert_array_equal(out["banded"].diagnostics["newton_iterations"],
                                  out["sparse"].diagnostics["newton_iterations"])
    np.testing.assert_allclose(out["banded"].positions, out["sparse"].positions, rtol=0, atol=1e-10)


def test_fewer_cameras_never_see_what_more_cameras_would_not(tiny):
    """The same deformed state seen by the first, the first two and all five cameras, each with a
    voxel far below the ray spacing (so the cloud is the raw hits): every hit of a camera subset is a
    hit of the larger set; and the default sensors' point counts grow with the cameras."""
    config, trajectories = tiny
    traj = trajectories[0]
    t = traj.num_steps - 1
    surface = boundary_facets(traj.cells, traj.rest_positions)
    clouds = {}
    for n in (1, 2, 5):
        sensor = dict(config["sensor"], cameras=config["sensor"]["cameras"][:n], voxel_size=1e-5)
        clouds[n] = DepthSensor(SensorConfig.from_dict(sensor)).observe(
            traj.positions[t], traj.cells, traj.collider_positions[t], traj.collider_faces, surface=surface)
    assert 0 < len(clouds[1]) < len(clouds[2]) < len(clouds[5])
    for small, large in ((1, 2), (2, 5), (1, 5)):
        distance, _ = cKDTree(clouds[large]).query(clouds[small])
        assert distance.max() < 1e-4
    counts = [len(DepthSensor(SensorConfig.from_dict(load_config(name)["sensor"])).observe(
        traj.positions[t], traj.cells, traj.collider_positions[t], traj.collider_faces, surface=surface))
        for name in ("cavity_cpu_cam1", "cavity_cpu_cam2", "cavity_cpu")]
    assert counts[0] < counts[1] < counts[2]
    # the fingers occlude: without them the cameras see more of the squeezed wall
    bare = DepthSensor(SensorConfig.from_dict(config["sensor"])).observe(traj.positions[t], traj.cells, None, None)
    assert len(bare) > counts[2]


def test_other_cameras_on_stored_states_equal_a_full_generation(tiny, tmp_path):
    """`states_from`: the tiny trajectories observed again with one camera are bit for bit what a full
    generation with one camera makes (states, point clouds, seeds); a source preset of another seed,
    a noisy sensor or too short a source file are refused with the reason."""
    from ggns.config import CONF_DIR
    from ggns.data.schema import SplitReader

    config, trajectories = tiny
    source = tmp_path / "source.yaml"
    source.write_text(f"base: {CONF_DIR / 'data' / 'cavity_tiny.yaml'}\noutput: {config['output']}\n")
    one_camera = dict(config, sensor=dict(config["sensor"], cameras=config["sensor"]["cameras"][:1]),
                      splits=dict(config["splits"], train=2))
    reobserved, = generate(dict(one_camera, states_from=str(source), output=str(tmp_path / "re")), ["train"], progress=False)
    full, = generate(dict(one_camera, output=str(tmp_path / "full")), ["train"], progress=False)
    again, direct = read_trajectories(reobserved), read_trajectories(full)
    assert len(again) == len(direct) == 2
    for a, b, five in zip(again, direct, trajectories):
        assert a.seed == b.seed == five.seed
        for name in ("positions", "collider_positions", "points", "point_offsets", "cells", "edges"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert len(a.points) < len(five.points)  # one camera sees less than five
    with SplitReader(reobserved) as reader:  # the file names its source; its sensor is its own
        assert reader.generator_config["states_from"] == str(source)
        assert len(reader.generator_config["sensor"]["cameras"]) == 1
    with pytest.raises(ValueError, match="seed"):
        generate(dict(one_camera, states_from=str(source), seed=1, output=str(tmp_path / "x")), ["train"], progress=False)
    with pytest.raises(ValueError, match="noise"):
        noisy = dict(one_camera, sensor=dict(one_camera["sensor"], noise_std=0.001))
        generate(dict(noisy, states_from=str(source), output=str(tmp_path / "y")), ["train"], progress=False)
    with pytest.raises(ValueError, match="holds 3 trajectories"):
        generate(dict(one_camera, states_from=str(source), splits=dict(config["splits"], train=4),
                      output=str(tmp_path / "z")), ["train"], progress=False)
    assert not (tmp_path / "z" / "train.h5").exists()


def test_scale_within_the_targets(tiny):
    """The tiny preset's counts against conf/geometry/cavity.yaml (points, edges, world edges) and the
    paper's (nodes, directed mesh edges, collider nodes)."""
    from ggns.graphs.connectivity import load_connectivity
    from ggns.graphs.scale import measure

    config, trajectories = tiny
    geometry = load_config("cavity", kind="geometry")
    values = measure(trajectories, load_connectivity(geometry["graph"]), load_connectivity(geometry["baseline_graph"]),
                     geometry["noise_std"], stride=4)
    for name in ("points_per_step", "edges_per_graph", "world_edges_per_node", "smallest_mesh_edge",
                 "mesh_point_neighbours"):
        lo, hi = geometry["targets"][name]
        assert lo <= values[name] <= hi, (name, values[name])
    for traj in trajectories:
        assert traj.rest_positions.shape == (750, 3) and 2 * len(traj.edges) == 4500
        assert traj.collider_positions.shape[1] == 636


@pytest.mark.parametrize("model", ["ggns", "mgn"])
def test_fit_test_and_export_through_the_cli_on_tiny_cavity(tiny, tmp_path, model):
    config, _ = tiny
    data_dir = config["output"]
    schedules = ["--evaluation.schedules", '["every:1", "every:2", "never"]'] if model == "ggns" else []
    checkpoint, metrics = fit_and_test_3d("cavity", model, data_dir, tmp_path, latent=8, blocks=1, extra=schedules)
    schedule = "every:2" if model == "ggns" else "never"
    main(["export", "--checkpoint", str(checkpoint), "--dataset", "cavity_tiny", "--data-dir", str(data_dir), "--split", "test",
          "--schedule", schedule, "--output", str(tmp_path / "export")])
    truth = sorted((tmp_path / "export" / "truth").glob("*.vtu"))
    assert len(truth) == 12
    if model == "ggns":
        assert "rollout_mse_k1" in metrics
        assert len(list((tmp_path / "export" / "points").glob("*.vtu"))) == 6  # steps 0, 2, .., 10


def diagnosis_script():
    """experiments/cavity_diagnosis/cavity_diagnosis.py as a module (it is a script, not part of the package)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "experiments" / "cavity_diagnosis" / "cavity_diagnosis.py"
    spec = importlib.util.spec_from_file_location("cavity_diagnosis", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def test_shape_tangential_recovers_motion_that_keeps_edge_lengths_and_not_motion_that_stretches(tiny):
    """The diagnosis's `shape_tangential` on the tiny cavity's mesh: given a small rotation's motion across
    the surface, it returns the rotation's motion along it (a rotation keeps every edge's length); a random
    motion along the surface stretches the edges, and what it returns leaves most of it unexplained; fixed
    nodes stay put."""
    from ggns.evaluation.observability import vertex_normals
    from ggns.geometry import boundary_facets, cell_edges

    script = diagnosis_script()
    traj = tiny[1][0]
    before = traj.rest_positions.astype(np.float64)
    facets, edges = boundary_facets(traj.cells, before), cell_edges(traj.cells)
    spin = np.array([2e-4, -1e-4, 0.0])  # about a horizontal axis through the mesh's centre
    rotated = before + np.cross(spin, before - before.mean(axis=0))
    free = np.zeros(len(before), dtype=bool)
    along = script.shape_tangential(before, rotated, edges, facets, free)
    normals = vertex_normals(rotated, facets)
    true_along = script.tangential_part(rotated - before, normals)
    assert ((along - true_along) ** 2).sum() < 1e-3 * (true_along ** 2).sum()
    assert (true_along ** 2).sum() > 0.1 * ((rotated - before) ** 2).sum()  # the test has motion along to recover

    rng = np.random.default_rng(0)
    sliding = script.tangential_part(rng.normal(scale=1e-3, size=before.shape), vertex_normals(before, facets))
    along = script.shape_tangential(before, before + sliding, edges, facets, traj.fixed)
    true_along = script.tangential_part(sliding, vertex_normals(before + sliding, facets))
    assert ((along - true_along)[~traj.fixed] ** 2).sum() > 0.5 * (true_along[~traj.fixed] ** 2).sum()
    assert traj.fixed.any() and not along[traj.fixed].any()


def test_the_cavity_diagnosis_script_splits_by_wall_and_reports_finite_numbers(tiny, tmp_path):
    """experiments/cavity_diagnosis/cavity_diagnosis.py (docs/experiments/cavity_diagnosis.md) on an untrained GGNS: the inner
    wall it finds from the geometry is the mesh's own numbering's (level j, wall k: ring 2 j + k, k = 0
    inner), predicting no motion costs the true motion's mean square, and every reported number is finite."""
    import json
    import sys

    from conftest import make, save_untrained
    from ggns.models.simulators import GGNS

    config, trajectories = tiny
    script = diagnosis_script()
    rest = trajectories[0].rest_positions
    ring = len(rest) // (2 * len(np.unique(np.round(rest[:, 2], 6))))
    inner, outer = script.wall_sides(rest)
    np.testing.assert_array_equal(inner, (np.arange(len(rest)) // ring) % 2 == 0)
    assert not (inner & outer).any() and (inner | outer).all()

    checkpoint = save_untrained(make(GGNS, latent=8, blocks=1, connectivity="cavity_reduced_graph", dim=3),
                                tmp_path / "ggns.ckpt")
    argv = sys.argv
    sys.argv = ["cavity_diagnosis.py", "--dataset", "cavity_tiny", "--data-dir", str(config["output"]),
                "--checkpoint", str(checkpoint), "--trajectories", "2", "--output", str(tmp_path / "out")]
    try:
        script.main()
    finally:
        sys.argv = argv
    report = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    assert (tmp_path / "out" / "diagnosis.md").is_file()
    val = read_trajectories(f"{config['output']}/val.h5")[:2]
    motion = np.concatenate([np.diff(t.positions, axis=0)[:, ~t.fixed].ravel() for t in val])
    assert report["model"]["one_step_mse"]["no_motion"] == pytest.approx(float(np.mean(motion ** 2)), rel=1e-5)
    # the data part's split of the true displacement is the model part's static row
    for group, parts in report["data"][0]["displacement"].items():
        assert parts == pytest.approx(report["model"]["rollout"]["static"][group], rel=1e-9), group

    def numbers(x):
        if isinstance(x, dict):
            return [v for value in x.values() for v in numbers(value)]
        if isinstance(x, list):
            return [v for value in x for v in numbers(value)]
        return [x] if isinstance(x, float) else []
    values = numbers(report["model"]) + numbers(report["data"])
    assert values and all(np.isfinite(values))
    assert 0 <= report["data"][0]["coverage"]["seen"] <= 1
    assert set(report["data"][0]["shape_tangential_left"]) == {"all"} | {f"{t.poissons_ratio:g}" for t in val}
    assert set(report["model"]["by_material_split"]["static"]) == set(report["model"]["by_material"]["k1"])


def test_grounding_ratios_pairs_each_seed_and_tells_the_mean_of_ratios_from_the_ratio_of_means(tmp_path, monkeypatch):
    """experiments/cavity_mesh/scripts/grounding_ratios.py on test metrics written as a sweep writes them:
    each seed's MGN over the same seed's GGNS k=1; a seed that only GGNS finished is left out; the mean of the
    per-seed ratios differs from the ratio of the seed means, and both are reported; no finished seed is an error."""
    import importlib.util
    import json
    import sys
    from pathlib import Path

    def write(model, seed, **metrics):
        folder = tmp_path / "sweep" / model / f"seed_{seed}_test"
        folder.mkdir(parents=True)
        (folder / "test_metrics.json").write_text(json.dumps(
            {k: {"mean": v, "std": 0.0, "trajectories": 27} for k, v in metrics.items()} | {"checkpoints": {}}))
    write("ggns_partition", 0, rollout_mse_k1=1e-4, rollout_mse_never=3e-4)
    write("ggns_partition", 1, rollout_mse_k1=2e-4, rollout_mse_never=3e-4)
    write("ggns_partition", 2, rollout_mse_k1=5e-5, rollout_mse_never=3e-4)  # no MGN for seed 2
    write("mgn", 0, rollout_mse_never=2e-4)
    write("mgn", 1, rollout_mse_never=8e-4)
    write("mgn_m", 0, rollout_mse_never=1e-4)
    path = Path(__file__).resolve().parents[1] / "experiments" / "cavity_mesh" / "scripts" / "grounding_ratios.py"
    spec = importlib.util.spec_from_file_location("grounding_ratios", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = tmp_path / "ratios.md"
    monkeypatch.setattr(sys, "argv", ["grounding_ratios.py", "--sweep", str(tmp_path / "sweep"), "--output", str(out)])
    script.main()
    text = out.read_text()
    assert "| 0 | 1.000e-04 | 3.000e-04 | 2.000e-04 | 1.000e-04 | 2.00 | 1.00 |" in text
    assert "| 1 | 2.000e-04 | 3.000e-04 | 8.000e-04 | - | 4.00 | - |" in text
    assert "| 2 |" not in text
    # per seed 2 and 4: mean 3.00; seed means 5e-4 / 1.5e-4 = 3.33
    assert "MGN / GGNS k=1 3.00 (2 seeds, range 2.00-4.00); MGN(M) / GGNS k=1 1.00 (1 seeds" in text
    assert "Ratio of the seed means: MGN / GGNS k=1 3.33; MGN(M) / GGNS k=1 1.00." in text
    monkeypatch.setattr(sys, "argv", ["grounding_ratios.py", "--sweep", str(tmp_path / "empty")])
    with pytest.raises(SystemExit, match="no seed"):
        script.main()
