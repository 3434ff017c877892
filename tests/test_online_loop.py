"""The online loop as a robot meets it, and the registration baseline: the first frame warmed up when the
simulator is built, integer depth images in their unit, lists of observations of several ticks, frames of
one tick joined (in one call and across calls), rounded poses, the grasped patch following the gripper, a
cloud denser than the training data's thinned, the model's identity in the saved state, an online
divergence naming its object; a mesh registered back onto the cloud it was displaced from, and a blind
simulator corrected by registration tracking closer than it does blind. Real data (plate_tiny and a short
tissue trajectory from the generator), real Open3D depth processing."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import box_mesh, make
from ggns.batch import TrajectoryBatch
from ggns.config import load_config
from ggns.data.generate import generate
from ggns.data.module import WindowDataset, collate
from ggns.data.schema import read_trajectories
from ggns.errors import RolloutError
from ggns.evaluation.schedules import EveryK
from ggns.geometry import boundary_facets
from ggns.models.simulators import GGNS, GGNSLSTM, MGN
from ggns.online import (DepthImage, DepthProcessing, Observation, OnlineDivergence, OnlineSimulator, Registration,
                         online_object)
from ggns.online.objects import grasped_nodes, rigid_motion
from ggns.online.registration import ObjectGeometry, register
from ggns.sensors.camera import DepthSensor, SensorConfig, back_project

TESTS = Path(__file__).resolve().parent


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> dict:
    return load_config("plate_tiny", [f"output={tmp_path_factory.mktemp('loop')}"])


@pytest.fixture(scope="module")
def trajs(config):
    """The two plate_tiny validation trajectories (T = 8)."""
    (path,) = generate(config, ["val"], progress=False)
    return read_trajectories(path)


@pytest.fixture(scope="module")
def sensor(config) -> DepthSensor:
    return DepthSensor(SensorConfig.from_dict(config["sensor"]))


def fitted(cls, trajs, **kwargs):
    """A small simulator with its normalizers fitted on the trajectories' windows (untrained: its predictions move
    the mesh at the data's scale, wrongly)."""
    model = make(cls, **kwargs)
    windows = WindowDataset(trajs, model.window)
    model.fit_normalizers([collate([windows[i] for i in range(min(8, len(windows)))])])
    return model.eval()


def colliders(trajs, t):
    return {b: tr.collider_positions[t + 1] for b, tr in enumerate(trajs)}


# ---- 1. warmed up when built ----------------------------------------------------------------------------------------
def test_building_the_simulator_imports_and_runs_the_depth_path_and_a_prediction():
    """In a fresh process: warm=False leaves Open3D unimported (lazy), the default imports it when the simulator is
    built, and the state stays at tick 0, unchanged."""
    script = f"""
import sys
sys.path.insert(0, {str(TESTS)!r})
import torch
from conftest import box_mesh, make
from ggns.models.simulators import GGNS
from ggns.online import DepthProcessing, OnlineSimulator, online_object
rest, cells = box_mesh(2, 4)
obj = online_object(rest, cells, [0, 1], fix_orientation=True)
model = make(GGNS).eval()
lazy = OnlineSimulator(model, obj, depth=DepthProcessing(0.05), warm=False)
print("lazy", "open3d" in sys.modules)
sim = OnlineSimulator(model, obj, depth=DepthProcessing(0.05))
print("warm", "open3d" in sys.modules, sim.tick, bool(torch.equal(sim.positions()[0], torch.as_tensor(rest).float())))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split("\n")[:2] == ["lazy False", "warm True 0 True"], done.stdout


# ---- 2. integer depth in its unit -------------------------------------------------------------------------------------
def test_an_integer_depth_image_needs_its_unit_and_is_read_in_it():
    pose, intrinsics = np.eye(4), (40.0, 40.0, 8.0, 6.0)
    metres = np.random.default_rng(0).uniform(0.5, 2.5, (12, 16)).round(3).astype(np.float32)
    millimetres = (metres * 1000).round().astype(np.uint16)
    with pytest.raises(ValueError, match="uint16 .*give depth_scale"):
        DepthImage(millimetres, intrinsics, pose)
    with pytest.raises(ValueError, match="depth_scale must be"):
        DepthImage(millimetres, intrinsics, pose, depth_scale=0.0)
    scaled = DepthImage(millimetres, intrinsics, pose, depth_scale=0.001)
    assert scaled.depth.dtype == np.float32 and scaled.depth.max() < 3
    np.testing.assert_allclose(back_project(scaled), back_project(DepthImage(metres, intrinsics, pose)), atol=1e-5)


# ---- 3 and 4. observations of several ticks; one tick's frames joined -----------------------------------------------
def test_observations_of_several_ticks_in_one_call_are_ordered_and_replayed(trajs):
    """Ticks 0-2 stepped blind, then at tick 3 the clouds of ticks 2, 0, 3 and 1 in one call (out of order): the
    state is that of a twin fed each cloud on time (the LSTM's state replayed too)."""
    model = make(GGNSLSTM)
    late, on_time = OnlineSimulator(model, trajs[0]), OnlineSimulator(model, trajs[0])
    for t in range(3):
        late.step(collider=trajs[0].collider_positions[t + 1])
        on_time.step(collider=trajs[0].collider_positions[t + 1], observation=trajs[0].point_cloud(t))
    every = [Observation(points=trajs[0].point_cloud(s), tick=s) for s in (2, 0, 3, 1)]
    state = late.step(collider=trajs[0].collider_positions[4], observation=every)
    torch.testing.assert_close(state[0], on_time.step(collider=trajs[0].collider_positions[4],
                                                     observation=trajs[0].point_cloud(3))[0], rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="a list must hold Observations or DepthImages"):
        late.step(observation=[every[0], trajs[0].point_cloud(4)])


def test_frames_of_one_tick_are_joined_in_one_call_and_across_calls(trajs, sensor):
    """One camera's frame split in two masks (two cameras seeing halves): given together, or the second half a
    tick later stamped with its tick, the simulator sees the cloud of the whole frame; so with point clouds."""
    model = make(GGNS)
    processing = DepthProcessing.from_sensor_config(sensor.config)
    tr = trajs[0]
    (frame,) = sensor.render(tr.positions[1], tr.cells, tr.collider_positions[1], tr.collider_faces)
    columns = np.arange(frame.mask.shape[1]) < frame.mask.shape[1] // 2
    halves = [dataclasses.replace(frame, mask=frame.mask & columns), dataclasses.replace(frame, mask=frame.mask & ~columns)]
    assert all(h.mask.any() for h in halves)

    def run(feeds):
        sim = OnlineSimulator(model, tr, depth=processing)
        for t, seen in enumerate(feeds):
            sim.step(collider=tr.collider_positions[t + 1], observation=seen)
        return sim.positions()[0]

    whole = run([None, [frame], None])
    torch.testing.assert_close(run([None, halves, None]), whole, rtol=0, atol=1e-6)
    torch.testing.assert_close(run([None, [halves[0]], Observation(images=[halves[1]], tick=1)]), whole, rtol=0, atol=1e-6)
    assert (run([None, [halves[0]], None]) - whole).abs().max() > 1e-6  # half a frame is another cloud
    cloud = tr.point_cloud(1)
    parts = [Observation(points=cloud[::2]), Observation(points=cloud[1::2])]
    points_whole = run([None, cloud, None])
    torch.testing.assert_close(run([None, parts, None]), points_whole, rtol=0, atol=1e-5)
    torch.testing.assert_close(run([None, parts[0], Observation(points=cloud[1::2], tick=1)]), points_whole,
                               rtol=0, atol=1e-5)


# ---- 5. rounded poses -------------------------------------------------------------------------------------------------
def test_a_rounded_pose_is_accepted_and_a_scaled_one_is_refused_naming_its_residual(trajs):
    angle = np.radians(30)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    pose[:3, 3] = [0.1, 0.2, 3.0]
    depth = np.full((6, 8), 1.5, np.float32)
    exact = DepthImage(depth, (10.0, 10.0, 4.0, 3.0), pose)
    rounded = DepthImage(depth, (10.0, 10.0, 4.0, 3.0), pose.round(5))
    np.testing.assert_allclose(back_project(rounded), back_project(exact), atol=1e-4)
    rotation = rounded.camera_to_world[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)  # the nearest rotation is used
    scaled = pose.copy()
    scaled[:3, :3] *= 1.01
    with pytest.raises(ValueError, match=r"reaches 0\.02 > tolerance 0\.0001"):
        DepthImage(depth, (10.0, 10.0, 4.0, 3.0), scaled)
    DepthImage(depth, (10.0, 10.0, 4.0, 3.0), scaled, rigid_tolerance=0.05)  # a tolerance of one's own
    sim = OnlineSimulator(make(GGNS), trajs[0], warm=False)
    move = np.eye(3)
    move[:2, 2] = [0.01, 0.0]
    rounded_move = move.copy()
    rounded_move[0, 0] = 1.000004
    sim.step(collider=rounded_move)  # a collider pose rounded alike


# ---- 6. the grasped patch follows the gripper -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def tissue(tmp_path_factory):
    """One tissue_tiny trajectory of 6 states from the generator."""
    config = load_config("tissue_tiny", [f"output={tmp_path_factory.mktemp('tissue')}", "scene.num_steps=6",
                                         "splits.val=1"])
    (path,) = generate(config, ["val"], progress=False)
    return read_trajectories(path)[0]


def test_the_grasped_patch_follows_the_gripper_from_the_collider_pose_alone(tissue):
    """On a tissue trajectory (its grasped patch: the fixed nodes that move) the gripper's pose alone moves the
    patch as the recording did: a stepper given only the poses equals one given every fixed node's position."""
    held = grasped_nodes(tissue)
    fixed = np.flatnonzero(tissue.fixed)
    assert 0 < len(held) < len(fixed)
    model = make(MGN, dim=3, connectivity="tissue_mgn")
    alone, told = OnlineSimulator(model, tissue, warm=False), OnlineSimulator(model, tissue, warm=False)
    for t in range(tissue.num_steps - 1):
        a = alone.step(collider=tissue.collider_positions[t + 1])[0]
        b = told.step(collider=tissue.collider_positions[t + 1], fixed=tissue.positions[t + 1][fixed])[0]
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
        np.testing.assert_allclose(a[held].numpy(), tissue.positions[t + 1][held], atol=1e-5)
    # an object of one's own: the grasped nodes given, moved with the collider's rigid pose
    rest, cells = box_mesh(3, 3)
    top = np.flatnonzero(rest[:, 2] == rest[:, 2].max())[:2]
    bottom = np.flatnonzero(rest[:, 2] == 0)
    gripper = rest[top].mean(0, keepdims=True) + [0.0, 0.0, 0.1]
    obj = online_object(rest, cells, np.concatenate([bottom, top]), collider_vertices=gripper,
                        collider_faces=np.zeros((0, 3), np.int64), grasped=top, fix_orientation=True)
    sim = OnlineSimulator(model, obj, warm=False)
    lift = np.eye(4)
    lift[:3, 3] = [0.05, 0.0, 0.2]
    out = sim.step(collider=lift)[0]
    np.testing.assert_allclose(out[top].numpy(), rest[top] + [0.05, 0.0, 0.2], atol=1e-6)
    np.testing.assert_allclose(out[bottom].numpy(), rest[bottom], atol=1e-6)
    with pytest.raises(ValueError, match="grasped must be indices of fixed nodes"):
        online_object(rest, cells, bottom, collider_vertices=gripper, collider_faces=np.zeros((0, 3), np.int64),
                      grasped=top, fix_orientation=True)
    turn = np.array([[0.0, -1.0], [1.0, 0.0]])
    template = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0]])
    np.testing.assert_allclose(rigid_motion(template, template @ turn.T + [3.0, 1.0])[:2], [[0, -1, 3], [1, 0, 1]],
                               atol=1e-12)


# ---- 7. a dense cloud thinned ---------------------------------------------------------------------------------------
def test_a_cloud_denser_than_the_training_sensors_is_thinned_to_its_density(trajs, config):
    processing = DepthProcessing.from_sensor_config(config["sensor"])
    tr = trajs[0]
    cloud = tr.point_cloud(1)
    np.testing.assert_array_equal(processing.thin(cloud, 2), cloud)  # the sensor's own density: as it is
    rng = np.random.default_rng(0)
    dense = (np.repeat(cloud, 200, axis=0) + rng.uniform(-0.2, 0.2, (200 * len(cloud), 2)) * processing.voxel_size)
    thinned = processing.thin(dense, 2)
    assert len(thinned) <= 2 * len(cloud) and len(thinned) >= len(cloud) // 2
    model = make(GGNS)
    thinning = OnlineSimulator(model, tr, depth=processing, warm=False)
    thinning.step(collider=tr.collider_positions[1])
    state = thinning.step(collider=tr.collider_positions[2], observation=dense)[0]
    assert torch.isfinite(state).all()
    raw = OnlineSimulator(model, tr, warm=False)  # no depth processing known: the dense cloud reaches the graph
    raw.step(collider=tr.collider_positions[1])
    with pytest.raises(ValueError, match="denser than the model's graph allows .*DepthProcessing"):
        raw.step(collider=tr.collider_positions[2], observation=dense)
    assert raw.tick == 1


# ---- 8. the model's identity in the state ---------------------------------------------------------------------------
def test_a_state_is_refused_by_a_simulator_of_another_model(trajs):
    ggns = make(GGNS)
    sim = OnlineSimulator(ggns, trajs[0], warm=False)
    sim.step(collider=trajs[0].collider_positions[1], observation=trajs[0].point_cloud(0))
    state = sim.state_dict()
    assert state["model"]["class"] == "GGNS" and len(state["model"]["weights_sha256"]) == 64
    for other in (make(MGN), make(GGNS, seed=1)):
        with pytest.raises(ValueError, match="another model's state"):
            OnlineSimulator(other, trajs[0], warm=False).load_state_dict(state)
    again = OnlineSimulator(ggns, trajs[0], warm=False)
    again.load_state_dict(state)
    torch.testing.assert_close(again.positions()[0], sim.positions()[0], rtol=0, atol=0)


# ---- 9. an online divergence names its object -----------------------------------------------------------------------
def test_a_divergence_names_the_object_and_leaves_the_state_unchanged(trajs):
    sim = OnlineSimulator(make(MGN), {"left": trajs[0], "right": trajs[1]}, warm=False)
    far = trajs[1].positions[1][trajs[1].fixed] + 1e4
    with pytest.raises(OnlineDivergence, match="object 'right' diverged predicting tick 1 from tick 0") as error:
        sim.step(fixed={"right": far})
    assert isinstance(error.value, RolloutError) and error.value.object == "right" and error.value.step == 0
    assert sim.tick == 0


# ---- the registration -------------------------------------------------------------------------------------------------
def test_a_mesh_displaced_rigidly_from_its_surface_is_registered_back():
    rest, cells = box_mesh(3, 5, (1.0, 0.8, 0.4))
    rng = np.random.default_rng(0)
    facets = boundary_facets(cells)
    weights = rng.dirichlet([1, 1, 1], 3000)
    points = torch.as_tensor((weights[:, :, None] * rest[facets[rng.integers(0, len(facets), 3000)]]).sum(1))
    angle = np.radians(3)
    turn = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    moved = torch.as_tensor((rest - rest.mean(0)) @ turn.T + rest.mean(0) + [0.04, -0.03, 0.05])
    geometry = ObjectGeometry(cells, 3, np.zeros(len(rest), bool), torch.device("cpu"))
    out = register(Registration(iterations=6), geometry, moved, points)
    before, after = float(((moved - torch.as_tensor(rest)) ** 2).mean()), float(((out - torch.as_tensor(rest)) ** 2).mean())
    assert after < 0.05 * before, (before, after)
    held = np.zeros(len(rest), bool)
    held[:3] = True  # held nodes stay where the prediction put them
    kept = register(Registration(), ObjectGeometry(cells, 3, held, torch.device("cpu")), moved, points)
    torch.testing.assert_close(kept[:3], moved[:3], rtol=0, atol=0)
    assert register(Registration(), geometry, moved, points[:0]) is moved
    for bad in (dict(smoothness=-1.0), dict(iterations=0), dict(trim=0.0), dict(smoothness=0.0, anchor=0.0)):
        with pytest.raises(ValueError, match="Registration"):
            Registration(**bad)


def test_a_blind_simulator_corrected_by_registration_tracks_closer_than_blind(trajs):
    """An MGN that moves the plate wrongly, fed the flawless clouds of every tick (and, one tick late, of every
    second): registered, its tracking error is below its blind one; the clouds do not reach the model."""
    model = fitted(MGN, trajs)
    tr = trajs[0]

    def track(registration, every=1, latency=0):
        sim = OnlineSimulator(model, tr, registration=registration, warm=False)
        errors = []
        for t in range(tr.num_steps - 1):
            shown = t - latency
            seen = Observation(points=tr.point_cloud(shown), tick=shown) if shown >= 0 and shown % every == 0 else None
            state = sim.step(collider=tr.collider_positions[t + 1], observation=seen)[0]
            errors.append(float(((state.double().numpy() - tr.positions[t + 1]) ** 2).mean()))
        return np.mean(errors)

    blind = track(None)
    registered = Registration(reverse=1.0)
    assert track(registered) < 0.75 * blind
    assert track(registered, every=2, latency=1) < blind
    # blind MGN fed clouds without a registration: exactly blind (it takes no point cloud)
    assert track(None) == blind


def test_a_grounded_simulator_can_be_registered_as_well(trajs):
    model = make(GGNS)
    tr = trajs[0]
    states = {}
    for name, registration in (("grounded", None), ("both", Registration(feed_model=True)),
                               ("registered", Registration())):
        sim = OnlineSimulator(model, tr, registration=registration, warm=False)
        for t in range(3):
            state = sim.step(collider=tr.collider_positions[t + 1], observation=tr.point_cloud(t))[0]
        states[name] = state
    assert (states["both"] - states["grounded"]).abs().max() > 1e-6
    assert (states["both"] - states["registered"]).abs().max() > 1e-6
    batch = TrajectoryBatch.from_trajectories([tr])
    torch.testing.assert_close(states["grounded"], model.rollout(batch, EveryK(1))[3], rtol=0, atol=1e-6)


def test_the_study_runs_a_registration_alone_on_a_mesh_that_does_not_move(trajs, config):
    """`Stationary` keeps the mesh where it is (blind: every tick's error is state 0's against the truth), and
    registered to the frames it tracks closer; the study's settings come from conf/online/registration.yaml,
    overridden by text as a command line gives them, unknown ones refused."""
    from ggns.bench.online import camera_frames
    from ggns.bench.online_study import REGISTRATION_FILE, Stationary, registration_settings, track

    world = trajs[0]
    static = Stationary(make(GGNS))
    depth = DepthProcessing.from_sensor_config(config["sensor"])
    blind, _ = track(static, world, None, 1, 0, depth)
    np.testing.assert_allclose(blind, ((world.positions[0] - world.positions[1:]) ** 2).mean(axis=(1, 2)), rtol=1e-5)
    settings = registration_settings("plate", {"smoothness": "0.5", "iterations": "3"})
    assert (settings.smoothness, settings.iterations) == (0.5, 3) and isinstance(settings.iterations, int)
    assert "plate:" in REGISTRATION_FILE.read_text()
    registered, fed = track(static, world, camera_frames(config, world), 1, 0, depth, settings)
    assert fed == world.num_steps - 1 and registered.mean() < blind.mean()
    with pytest.raises(ValueError, match="unknown registration settings"):
        registration_settings("plate", {"smoothnes": "1"})


def test_the_comparison_summary_pairs_trajectories_and_tells_the_ratio_of_means(tmp_path):
    """experiments/online_registration/scripts/summary.py on raw rows as the study writes them: the mean over
    the trajectories every run of a setting has, the lowest run, GGNS over MGN + registration as a ratio of the
    means and the trajectories where GGNS is below."""
    import csv
    import importlib.util

    path = TESTS.parent / "experiments" / "online_registration" / "scripts" / "summary.py"
    spec = importlib.util.spec_from_file_location("registration_summary", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    rows = []
    for trajectory, (ggns, registered) in enumerate([(1.0, 2.0), (4.0, 2.0)]):
        for model, mse, every in [("tissue/ggns", 9.0, "never"), ("tissue/mgn", 8.0, "never"), ("tissue/ggns", ggns, "1"),
                                  ("tissue/mgn + registration", registered, "1")]:
            rows.append({"model": model, "trajectory": trajectory, "every": every, "latency": "0" if every != "never" else "-",
                         "sensor": "none" if every != "never" else "-", "tracking mse": mse, "ms per tick": 10.0})
    raw = tmp_path / "raw.csv"
    with raw.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (row,) = module.summarize(module.read([raw]))
    assert (row["GGNS"], row["MGN + reg"], row["MGN blind"]) == (2.5, 2.0, 8.0)
    assert row["lowest"] == "MGN + reg" and row["ggns_over_registered_mgn"] == 1.25
    assert row["ggns_below_registered_mgn"] == 1 and row["trajectories"] == 2
    assert "1.25 (1 of 2)" in module.markdown([row])
