"""The Tissue Manipulation scene (`ggns.scenes.tissue`) on its tiny preset: real simulation, real
Open3D raycasting and real HDF5 files, and a fit + test of each model family through the CLI."""
from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from ggns.__main__ import main
from ggns.config import load_config
from ggns.data.generate import generate
from ggns.data.schema import read_trajectories
from ggns.geometry import boundary_facets, min_volume_ratio
from ggns.scenes import tissue
from ggns.sensors.camera import DepthSensor, PinholeCamera, SensorConfig

from conftest import fit_and_test_3d


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny preset's splits (3/2/2 trajectories) and its config; the train split's trajectories
    (one per material)."""
    out = tmp_path_factory.mktemp("tissue_tiny")
    config = load_config("tissue_tiny", [f"output={out}"])
    train, _, _ = generate(config, ["train", "val", "test"], progress=False)
    return config, read_trajectories(train)


def test_mesh_fixed_layer_and_grasp_candidates():
    scene = load_config("tissue")["scene"]
    rest, cells, fixed = tissue.tissue_mesh(scene)
    assert rest.shape == (360, 3) and cells.shape == (6 * 9 * 8 * 3, 4)
    assert fixed.sum() == 90 and np.allclose(rest[fixed, 2], -0.6)
    candidates = tissue.grasp_candidates(scene, rest)
    assert len(candidates) == 19 == len(set(candidates.tolist()))
    assert np.allclose(rest[candidates, 2], -0.3)


def test_grasped_patch_follows_the_gripper_and_the_bottom_stays(tiny):
    config, trajectories = tiny
    scene = config["scene"]
    assert sorted(t.poissons_ratio for t in trajectories) == [-0.9, 0.0, 0.49]
    for traj in trajectories:
        assert np.isfinite(traj.positions).all() and np.isfinite(traj.points).all()
        path = traj.collider_positions[:, 0]  # the gripper: one collider node
        assert traj.collider_positions.shape == (traj.num_steps, 1, 3) and traj.collider_faces.shape == (0, 3)
        held = tissue.grasped_patch(scene, traj.rest_positions, traj.params["grasped_node"])
        assert len(held) == traj.params["grasped_nodes"] == 5 and traj.fixed[held].all()
        np.testing.assert_allclose(traj.positions[:, held] - traj.rest_positions[held],
                                   np.broadcast_to((path - path[0])[:, None], (traj.num_steps, len(held), 3)), atol=1e-9)
        assert np.linalg.norm(path[-1] - path[0]) > 0.01  # it moved (11 steps of the first segment)
        bottom = np.isclose(traj.rest_positions[:, 2], -0.6)
        np.testing.assert_array_equal(traj.positions[:, bottom], np.broadcast_to(traj.rest_positions[bottom],
                                                                                 (traj.num_steps, bottom.sum(), 3)))
        free = ~traj.fixed
        assert np.abs(traj.positions[:, free] - traj.rest_positions[free]).max() < 0.2  # bounded response
        assert min_volume_ratio(traj.positions, traj.rest_positions, traj.cells) > 0.3  # none inverted or crushed


@pytest.mark.parametrize("nu", [-0.95, 0.499])
def test_extreme_poissons_ratios_stay_bounded(nu):
    """30 steps of the default path at nu = -0.95 and 0.499: finite, no inverted element, the motion
    quasi-static (kinetic energy far below elastic), Newton converged in a few iterations."""
    config = load_config("tissue_tiny", ["scene.num_steps=30"])
    config["scene"]["materials"] = [{"poissons_ratio": nu, "youngs_modulus": 30000.0}]
    sensor = DepthSensor(SensorConfig.from_dict(config["sensor"]))
    traj = tissue.make_trajectory(config, 0, 7, sensor)
    d = traj.diagnostics
    assert all(np.isfinite(v).all() for v in d.values()) and np.isfinite(traj.positions).all()
    assert min_volume_ratio(traj.positions, traj.rest_positions, traj.cells) > 0.2
    assert d["elastic_energy"][-1] > 0 and d["kinetic_energy"].max() < 0.05 * d["elastic_energy"].max()
    assert d["newton_iterations"].max() <= 10


def test_points_lie_on_the_deformed_surface(tiny):
    config, trajectories = tiny
    voxel = config["sensor"]["voxel_size"]
    for traj in trajectories:
        counts = np.diff(traj.point_offsets)
        assert 700 <= counts.min() and counts.max() <= 1100
        for t in (0, traj.num_steps - 1):
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(traj.positions[t].astype(np.float32),
                                boundary_facets(traj.cells, traj.positions[t]).astype(np.uint32))
            distance = scene.compute_distance(traj.point_cloud(t).astype(np.float32)).numpy()
            assert distance.max() < voxel  # a voxel's centroid of surface hits lies within a voxel of the surface


def test_a_known_occluder_hides_what_is_behind_it():
    """One camera above the rest block; a plate above its x < 0 half: no point of that half is seen."""
    scene = load_config("tissue")["scene"]
    rest, cells, _ = tissue.tissue_mesh(scene)
    camera = PinholeCamera(eye=(0.0, 0.0, 2.0), look_at=(0.0, 0.0, -0.5), up=(0.0, 1.0, 0.0), fov_deg=50.0,
                           width_px=120, height_px=120)
    sensor = DepthSensor(SensorConfig(cameras=(camera,), voxel_size=0.03))
    plate = np.array([[-2.0, -2.0, 0.0], [0.0, -2.0, 0.0], [0.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    occluder = (plate, np.array([[0, 1, 2], [0, 2, 3]]))
    seen = sensor.observe(rest, cells, None, None)
    hidden = sensor.observe(rest, cells, None, None, occluders=[occluder])
    assert (seen[:, 0] < -0.1).sum() > 50  # without it the camera sees that half
    # rays reaching x < 0 on the top (z = -0.3) pass the plane z = 0 at x < 0: all blocked
    assert (hidden[:, 0] < -1e-6).sum() == 0
    assert len(hidden) > 0.4 * len(seen)
    with pytest.raises(ValueError, match="occluder 0"):
        sensor.observe(rest, cells, None, None, occluders=[(plate[:, :2], occluder[1])])


@pytest.mark.parametrize("model", ["ggns", "mgn_m"])
def test_fit_and_test_through_the_cli_on_tiny_tissue(tiny, tmp_path, model):
    config, _ = tiny
    data_dir = config["output"]
    checkpoint, metrics = fit_and_test_3d("tissue", model, data_dir, tmp_path, latent=16, blocks=2)
    if model == "ggns":
        assert "rollout_mse_k1" in metrics
        # the same rollout as ParaView files: truth, the model, the point clouds
        main(["export", "--checkpoint", str(checkpoint), "--dataset", "tissue_tiny", "--data-dir", str(data_dir), "--split", "test",
              "--schedule", "every:2", "--output", str(tmp_path / "export")])
        pvds = sorted(p.name for p in (tmp_path / "export").glob("*.pvd"))
        assert pvds == ["GGNS_every_2.pvd", "points.pvd", "truth.pvd"]
        assert len(list((tmp_path / "export" / "truth").glob("*.vtu"))) == 12
        assert len(list((tmp_path / "export" / "points").glob("*.vtu"))) == 6  # steps 0, 2, .., 10


def test_per_type_ggnsid_fits_and_tests_on_tiny_tissue(tiny, tmp_path):
    """experiments/tissue_cpu/learning/tissue_cpu_m10.yaml's GGNSID on the tissue: the per-type processor and the material
    estimator train and roll out in 3D through the CLI, and the checkpoint loads back as GGNSID."""
    from ggns.models.simulators import GGNSID
    from ggns.models.loading import load_simulator

    config, _ = tiny
    extra = ["--model.class_path", "ggns.models.simulators.GGNSID", "--model.init_args.processor", "per_type"]
    checkpoint, metrics = fit_and_test_3d("tissue", "ggns", config["output"], tmp_path, latent=16, blocks=2, extra=extra)
    assert "rollout_mse_k1" in metrics
    model = load_simulator(checkpoint)
    assert isinstance(model, GGNSID) and model.edge_partition and model.hparams.dim == 3


def test_static_reference_row_scores_volumes_in_3d(tiny):
    """The sweep's static row (mesh held at S_0) on tissue: MSE and the volume IoU, which is 1 at
    rest and below 1 once the gripper has deformed the block."""
    import torch

    from ggns.baselines.scores import static_metrics
    from ggns.evaluation.metrics import rollout_volume_iou

    _, trajectories = tiny
    row = static_metrics(trajectories)
    assert row["rollout_iou_never"]["count"] == len(trajectories)
    held = [np.broadcast_to(t.positions[:1], t.positions.shape) for t in trajectories]
    ious = [rollout_volume_iou(h, t.positions, t.cells) for h, t in zip(held, trajectories)]
    assert row["rollout_iou_never"]["mean"] == pytest.approx(np.mean(ious))
    assert all(0.5 < iou < 1.0 for iou in ious)
    assert rollout_volume_iou(trajectories[0].positions, trajectories[0].positions, trajectories[0].cells) == pytest.approx(1.0)
    assert row["rollout_mse_never"]["mean"] > 0 and torch.isfinite(torch.tensor(row["one_step_mse"]["mean"]))
