"""The online simulator (`ggns.online`) and the depth path: the stepper reproduces the offline rollout engine
fed a recorded trajectory's inputs (GGNS, GGNS+LSTM, GGNSID, MGN, MGN(M); untrained models, equality needs no
training), save/restore mid-trajectory, bad input refused with the state unchanged, late observations;
the virtual cameras' depth images back-projected onto their rays, the depth path giving the sensor's point
cloud; the sensor flaws (quadratic axial noise, grazing angles, depth edges, flying pixels, calibration
error), and the default sensor unchanged. Real components (Open3D, the real models) on tiny plate data."""
from __future__ import annotations

import dataclasses
import io

import numpy as np
import open3d as o3d
import pytest
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from conftest import box_mesh, make
from ggns.batch import TrajectoryBatch
from ggns.config import load_config
from ggns.data.generate import generate
from ggns.data.schema import read_trajectories
from ggns.evaluation.schedules import EveryK, FirstM, Never
from ggns.models.simulators import GGNS, GGNSID, GGNSLSTM, MGN, MGNM
from ggns.online import DepthImage, DepthProcessing, Observation, OnlineSimulator, online_object
from ggns.sensors.camera import (DepthSensor, PinholeCamera, SensorConfig, back_project, collider_mesh, object_mesh,
                                 rotation_xyz)


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> dict:
    return load_config("plate_tiny", [f"output={tmp_path_factory.mktemp('online')}"])


@pytest.fixture(scope="module")
def trajs(config):
    """The two plate_tiny validation trajectories (T = 8), simulated and observed by the real generator."""
    (path,) = generate(config, ["val"], progress=False)
    return read_trajectories(path)


@pytest.fixture(scope="module")
def sensor(config) -> DepthSensor:
    return DepthSensor(SensorConfig.from_dict(config["sensor"]))


def feed(sim: OnlineSimulator, trajs, schedule, steps=None) -> torch.Tensor:
    """Step `sim` through the recorded inputs of `trajs` (collider positions, the clouds the schedule says);
    returns the states [steps + 1, sumN, d] it returned, the start included."""
    out = [torch.cat(list(sim.positions().values()))]
    for t in range(sim.tick, sim.tick + (steps or trajs[0].num_steps - 1 - sim.tick)):
        seen = {b: tr.point_cloud(t) for b, tr in enumerate(trajs)} if schedule.uses_points(t) else None
        sim.step(collider={b: tr.collider_positions[t + 1] for b, tr in enumerate(trajs)}, observation=seen)
        out.append(torch.cat(list(sim.positions().values())))
    return torch.stack(out)


# ---- the stepper is the offline engine ------------------------------------------------------------------------------
@pytest.mark.parametrize("cls", [GGNS, GGNSLSTM, GGNSID, MGN, MGNM])
def test_stepper_reproduces_offline_rollout(trajs, cls):
    model = make(cls)
    batch = TrajectoryBatch.from_trajectories(trajs)
    offline = model.rollout(batch, "every:2")
    online = feed(OnlineSimulator(model, trajs), trajs, EveryK(2))
    torch.testing.assert_close(online, offline, rtol=0, atol=1e-6)
    if model.uses_points:  # the clouds reach the model: without them the rollout is another
        assert (model.rollout(batch, "never") - offline).abs().max() > 1e-4


def test_collider_pose_as_rigid_transform(trajs):
    model = make(GGNS)
    by_positions = feed(OnlineSimulator(model, trajs[:1]), trajs[:1], Never())
    sim = OnlineSimulator(model, trajs[:1])
    template = trajs[0].collider_positions[0]
    for t in range(1, trajs[0].num_steps):  # the plate's collider translates
        pose = np.eye(3)
        pose[:2, 2] = (trajs[0].collider_positions[t] - template).mean(axis=0)
        sim.step(collider=pose)
    torch.testing.assert_close(sim.positions()[0], by_positions[-1], rtol=0, atol=1e-5)
    turn = np.eye(3)
    turn[:2, :2] = rotation_xyz([0, 0, 90])[:2, :2]
    sim.step(collider=turn)
    expected = template @ turn[:2, :2].T
    np.testing.assert_allclose(sim.collider_positions()[0].numpy(), expected, atol=1e-6)


@pytest.mark.parametrize("cls", [GGNSLSTM, GGNSID])
def test_state_saved_and_restored_mid_trajectory_continues_identically(trajs, cls):
    model = make(cls)
    sim = OnlineSimulator(model, trajs, history=2)
    feed(sim, trajs, EveryK(1), steps=3)
    buffer = io.BytesIO()
    torch.save(sim.state_dict(), buffer)
    through = feed(sim, trajs, EveryK(2))

    restored = OnlineSimulator(model, trajs, history=2)
    restored.load_state_dict(torch.load(io.BytesIO(buffer.getvalue())))
    assert restored.tick == 3
    torch.testing.assert_close(feed(restored, trajs, EveryK(2)), through, rtol=0, atol=0)

    forgetful = OnlineSimulator(model, trajs, history=2)  # the model state is part of what continues
    state = torch.load(io.BytesIO(buffer.getvalue()))
    forgetful.load_state_dict({**state, "model_state": None})
    assert (feed(forgetful, trajs, EveryK(2)) - through).abs().max() > 1e-5
    if cls is GGNSID:  # the fused estimate moved from the prior with the clouds seen
        prior = OnlineSimulator(model, trajs).material_estimate()
        assert restored.material_estimate() != prior


def snapshot(sim: OnlineSimulator):
    """The simulator's state, as plain values compared with ==."""
    def plain(value):
        if isinstance(value, torch.Tensor):
            return ("tensor", tuple(value.shape), value.tolist())
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    return plain(sim.state_dict())


def bad_inputs(trajs, sensor):
    """(what the error names, step keyword arguments) for each bad input; the objects are named "a" and "b"."""
    c = trajs[0].collider_positions[3]
    masked = sensor.render(trajs[0].positions[2], trajs[0].cells)
    cloud = trajs[0].point_cloud(2)
    scaled = np.diag([2.0, 2.0, 1.0])
    return [
        ("must be its vertices", dict(collider={"a": c[:-1]})),
        ("not finite", dict(collider={"a": np.where(np.arange(len(c))[:, None] == 3, np.nan, c)})),
        ("non-finite", dict(collider={"a": np.full((3, 3), np.inf)})),
        ("not a rigid transform", dict(collider={"a": scaled})),
        ("unknown object", dict(collider={"c": c})),
        ("as a mapping", dict(collider=c)),
        (r"must be \[P, 2\]", dict(observation={"a": np.zeros((5, 3))})),
        ("NaN or inf", dict(observation={"a": np.full((5, 2), np.nan)})),
        ("in the future", dict(observation={"a": Observation(points=cloud, tick=3)})),
        ("older than the kept history", dict(observation={"a": Observation(points=cloud, tick=0)})),
        ("unknown object", dict(observation={"plate": cloud})),
        ("as a mapping", dict(observation=cloud)),
        ("fixed node positions", dict(fixed={"b": np.zeros((2, 2))})),
        ("with a mask show one object", dict(observation=masked)),
    ]


def test_bad_input_is_refused_and_leaves_the_state_unchanged(trajs, sensor):
    model = make(GGNSLSTM)
    objects = {"a": trajs[0], "b": trajs[1]}
    processing = DepthProcessing.from_sensor_config(sensor.config)
    sim, twin = (OnlineSimulator(model, objects, depth=processing, history=1) for _ in range(2))
    for s in (sim, twin):
        for t in range(2):
            s.step(collider={"a": trajs[0].collider_positions[t + 1], "b": trajs[1].collider_positions[t + 1]},
                   observation={"a": trajs[0].point_cloud(t)})
    before = snapshot(sim)
    for match, kwargs in bad_inputs(trajs, sensor):
        with pytest.raises(ValueError, match=match):
            sim.step(**kwargs)
        assert snapshot(sim) == before, match
    with pytest.raises(ValueError, match="fx, fy"):
        DepthImage(np.ones((4, 4)), (0.0, 1.0, 2.0, 2.0), np.eye(4))
    with pytest.raises(ValueError, match="not a rigid transform"):
        DepthImage(np.ones((4, 4)), (4.0, 4.0, 2.0, 2.0), np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="objects"):
        sim.load_state_dict({**sim.state_dict(), "names": ["a"]})
    assert snapshot(sim) == before
    step = dict(collider={"a": trajs[0].collider_positions[3], "b": trajs[1].collider_positions[3]},
                observation={"b": trajs[1].point_cloud(2)})
    torch.testing.assert_close(sim.step(**step), twin.step(**step), rtol=0, atol=0)  # nothing half-done stayed


@pytest.mark.parametrize("delay, history", [(2, 2), (5, None)])
def test_late_observations_correct_the_past_and_predict_forward(trajs, delay, history):
    """Clouds arriving `delay` ticks late, stamped with their tick: after each tick the state is the offline
    rollout's that saw the clouds of the ticks up to t - delay (FirstM), the LSTM's state replayed too; the
    default history (8 ticks) keeps what a frame 5 ticks late needs."""
    model = make(GGNSLSTM)
    batch = TrajectoryBatch.from_trajectories(trajs)
    sim = OnlineSimulator(model, trajs, **({} if history is None else {"history": history}))
    for t in range(batch.num_steps - 1):
        seen = t - delay
        late = {b: Observation(points=tr.point_cloud(seen), tick=seen) for b, tr in enumerate(trajs)} \
            if seen >= 0 else None
        state = sim.step(collider={b: tr.collider_positions[t + 1] for b, tr in enumerate(trajs)}, observation=late)
        offline = model.rollout(batch, FirstM(max(seen + 1, 0)))[t + 1]
        torch.testing.assert_close(torch.cat(list(state.values())), offline, rtol=0, atol=1e-6)
    assert (model.rollout(batch, Never())[-1] - offline).abs().max() > 1e-4  # the late clouds mattered


# ---- depth images ------------------------------------------------------------------------------------------------
CAMERAS = [PinholeCamera((0.1, 0.2, 3.0), (0, 0, 0), (0, 1, 0), 45.0, 40, 30),
           PinholeCamera((2.0, 1.5, 1.0), (0, 0, 0), (0.2, 0.1, 1.0), 60.0, 24, 32)]


@pytest.mark.parametrize("camera", CAMERAS)
def test_camera_intrinsics_and_pose_give_its_rays(camera):
    fx, fy, cx, cy = camera.intrinsics()
    pose = camera.camera_to_world()
    v, u = np.divmod(np.arange(camera.width_px * camera.height_px), camera.width_px)
    directions = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones(len(u))], axis=1) @ pose[:3, :3].T
    rays = camera.rays()
    np.testing.assert_allclose(rays[:, 3:], directions, atol=1e-6)
    np.testing.assert_allclose(rays[:, :3], np.broadcast_to(pose[:3, 3], (len(u), 3)), atol=1e-6)


def cube_scene():
    """A tet box [-0.5, 0.5]^3 seen by three cameras, a box collider in front of one side."""
    pos, cells = box_mesh(3, 4)
    collider, collider_cells = box_mesh(3, 2, (0.3, 0.3, 0.3))
    faces = object_mesh(collider, collider_cells, 0.0)[1]
    cams = (PinholeCamera((3.0, 0.4, 0.3), (0, 0, 0), (0, 1, 0), 45.0, 60, 60),
            PinholeCamera((0.3, 3.0, 0.4), (0, 0, 0), (0, 0, 1), 45.0, 60, 60),
            PinholeCamera((0.4, 0.3, 3.0), (0, 0, 0), (0, 1, 0), 45.0, 60, 60))
    return pos - 0.5, cells, collider + [0.6, -0.1, 0.0], faces, cams


def raycast(camera, meshes):
    """(hit points [H*W, 3], depth t [H*W], geometry id [H*W]) of the camera's rays on the meshes (Open3D)."""
    scene = o3d.t.geometry.RaycastingScene()
    for v, f in meshes:
        scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    rays = camera.rays().astype(np.float64)
    hits = scene.cast_rays(o3d.core.Tensor(camera.rays()))
    t = hits["t_hit"].numpy().astype(np.float64)
    return rays[:, :3] + t[:, None] * rays[:, 3:], t, hits["geometry_ids"].numpy()


@pytest.mark.parametrize("dim", [2, 3])
def test_depth_images_back_project_onto_the_raycast_points(trajs, sensor, dim):
    if dim == 2:
        tr = trajs[0]
        state = (tr.positions[5], tr.cells, tr.collider_positions[5], tr.collider_faces)
        cams, h = sensor.config.cameras, sensor.config.slab_half_thickness
    else:
        pos, cells, collider, faces, cams = cube_scene()
        state, h = (pos, cells, collider, faces), 0.05
        sensor = DepthSensor(SensorConfig(cams, 0.05))
    images = sensor.render(*state)
    meshes = [object_mesh(state[0], state[1], h), collider_mesh(state[2], state[3], dim, h)]
    for camera, image in zip(cams, images):
        hits, t, ids = raycast(camera, meshes)
        assert image.depth.shape == (camera.height_px, camera.width_px)
        np.testing.assert_array_equal(image.mask.ravel(), ids == 0)
        assert image.mask.sum() > 100 and (ids == 1).sum() > 10  # the object and the collider are in view
        np.testing.assert_array_equal(image.depth.ravel() > 0, np.isfinite(t))  # the collider's pixels too
        points = back_project(image)
        footprint = t[ids == 0] / camera.intrinsics()[0]  # a pixel's size at its depth
        assert (np.linalg.norm(points - hits[ids == 0], axis=1) <= footprint).all()
        unmasked = back_project(dataclasses.replace(image, mask=None))
        assert len(unmasked) == np.isfinite(t).sum()


@pytest.mark.parametrize("dim", [2, 3])
def test_depth_path_gives_the_sensors_point_cloud(trajs, sensor, dim):
    """Masked depth images through `DepthProcessing` (fuse, 2D: onto the plane, voxel grid) are the sensor's
    point cloud up to float rounding; the random down-sampling keeps as many measured points."""
    if dim == 2:
        tr = trajs[1]
        state = (tr.positions[7], tr.cells, tr.collider_positions[7], tr.collider_faces)
    else:
        pos, cells, collider, faces, cams = cube_scene()
        state, sensor = (pos, cells, collider, faces), DepthSensor(SensorConfig(cams, 0.05))
    processing = DepthProcessing.from_sensor_config(sensor.config)
    images = sensor.render(*state)
    cloud, expected = processing.cloud(images, dim, state[0], state[1]), sensor.observe(*state)
    assert cloud.dtype == np.float32 and cloud.shape == expected.shape and len(cloud) > 100
    assert cKDTree(expected).query(cloud)[0].max() < 1e-5
    random = dataclasses.replace(processing, downsample="random").cloud(images, dim, state[0], state[1])
    measured = np.concatenate([back_project(i) for i in images])[:, :dim]
    assert abs(len(random) - len(expected)) <= 0.02 * len(expected)
    assert cKDTree(measured).query(random)[0].max() < 1e-5


def test_unmasked_depth_is_cropped_around_the_object_and_off_the_collider(trajs, sensor):
    tr, t = trajs[1], 7  # the collider presses into the plate
    state = (tr.positions[t], tr.cells, tr.collider_positions[t], tr.collider_faces)
    images = [dataclasses.replace(i, mask=None) for i in sensor.render(*state)]
    expected = sensor.observe(*state)
    raw = np.concatenate([back_project(i) for i in images])[:, :2]
    voxel = sensor.config.voxel_size
    assert (cKDTree(expected).query(raw)[0] > 2 * voxel).sum() > 100  # the collider's pixels are in the images
    cloud = DepthProcessing.from_sensor_config(sensor.config).cloud(images, 2, tr.positions[t], tr.cells,
                                                                    (tr.collider_positions[t], tr.collider_faces))
    assert cKDTree(expected).query(cloud)[0].max() < voxel  # none of them passed
    assert (cKDTree(cloud).query(expected)[0] < voxel / 2).mean() > 0.95  # the object's did


def test_stepper_takes_depth_images(trajs, sensor):
    """Depth images in a step are the processed cloud in the same step; unmasked shared images are cropped
    per object; a shipped simulator reads its training sensor's voxel from its manifest."""
    model = make(GGNS)
    processing = DepthProcessing.from_sensor_config(sensor.config)
    by_images = OnlineSimulator(model, trajs, depth=processing)
    by_points = OnlineSimulator(model, trajs)
    for t in range(3):
        images = {b: sensor.render(tr.positions[t], tr.cells, tr.collider_positions[t], tr.collider_faces)
                  for b, tr in enumerate(trajs)}
        clouds = {b: processing.cloud(images[b], 2, by_points.positions()[b].double().numpy(), tr.cells)
                  for b, tr in enumerate(trajs)}
        collider = {b: tr.collider_positions[t + 1] for b, tr in enumerate(trajs)}
        torch.testing.assert_close(by_images.step(collider, images), by_points.step(collider, clouds), rtol=0, atol=0)
    one = OnlineSimulator(model, trajs[:1], depth=processing)
    shared = [dataclasses.replace(i, mask=None) for i in sensor.render(trajs[0].positions[0], trajs[0].cells)]
    assert len(one.step(observation=shared)[0]) == len(trajs[0].rest_positions)
    from ggns import pretrained

    assert DepthProcessing.for_model(pretrained.load("plate/ggns")).voxel_size == 0.075
    with pytest.raises(ValueError, match="point density"):
        DepthProcessing.for_model(model)


def test_online_object_from_arrays_in_3d():
    """A 3D object built from arrays, stepped by a 3D GGNS with a rigidly moved collider and depth images of
    three cameras."""
    pos, cells, collider, faces, cams = cube_scene()
    model = make(GGNS, dim=3, connectivity="tissue_reduced_graph")
    fixed = pos[:, 2] < -0.49
    obj = online_object(pos, cells, fixed, collider, faces, initial_positions=pos * 1.01, fix_orientation=True)
    sensor = DepthSensor(SensorConfig(cams, 0.05))
    sim = OnlineSimulator(model, {"box": obj}, depth=DepthProcessing(voxel_size=0.05))
    np.testing.assert_allclose(sim.positions()["box"].numpy(), pos * 1.01, rtol=1e-6)
    shift = np.eye(4)
    shift[0, 3] = -0.02
    out = sim.step(collider=shift, observation=sensor.render(pos, cells, collider, faces))["box"]
    assert out.shape == (len(pos), 3) and torch.isfinite(out).all()
    np.testing.assert_allclose(sim.collider_positions()["box"].numpy(), collider + [-0.02, 0, 0], atol=1e-6)
    assert torch.equal(out[torch.as_tensor(fixed)], torch.as_tensor(pos * 1.01, dtype=out.dtype)[fixed])
    lifted = pos[fixed] * 1.01 + [0.0, 0.0, 0.05]  # the clamped nodes moved (a grasped patch)
    out = sim.step(fixed={"box": lifted})["box"]
    torch.testing.assert_close(out[torch.as_tensor(fixed)], torch.as_tensor(lifted, dtype=out.dtype), rtol=0, atol=0)
    with pytest.raises(ValueError, match="3D"):
        OnlineSimulator(make(GGNS), [obj])


# ---- sensor flaws -------------------------------------------------------------------------------------------------
def facing_plate(distance: float, tilt_deg: float = 0.0, fov_deg: float = 30.0):
    """A thin 3D plate 2 x 2 x 0.02 (its top face at z = 0, filling the view up to a distance of 3.7 with the
    default field of view) tilted about the x axis, and a 100 x 100 pixel camera looking down at it from
    `distance`."""
    pos, cells = box_mesh(3, 3, (2.0, 2.0, 0.02))
    pos = (pos - [1.0, 1.0, 0.02]) @ rotation_xyz([tilt_deg, 0, 0]).T
    camera = PinholeCamera((0.0, 0.0, distance), (0, 0, 0), (0, 1, 0), fov_deg, 100, 100)
    return pos, cells, camera


def render(camera, pos, cells, rng=None, **flaws):
    return DepthSensor(SensorConfig((camera,), 0.05, **flaws)).render(pos, cells, rng=rng)[0]


def test_axial_noise_grows_with_the_square_of_the_distance():
    c, stds = 0.01, []
    for distance in (1.0, 2.0):
        pos, cells, camera = facing_plate(distance)
        clean = render(camera, pos, cells)
        noisy = render(camera, pos, cells, np.random.default_rng(0), axial_noise=c)
        seen = clean.depth > 0
        assert seen.sum() > 2000
        stds.append(float(np.std(noisy.depth[seen].astype(np.float64) - clean.depth[seen])))
        assert stds[-1] == pytest.approx(c * distance**2, rel=0.05)
    assert stds[1] / stds[0] == pytest.approx(4.0, rel=0.08)
    with pytest.raises(ValueError, match="rng"):
        render(camera, pos, cells, axial_noise=c)


def test_grazing_angles_and_depth_edges_return_nothing():
    kept = {}
    for tilt in (50.0, 70.0):  # a narrow view (rays within 5 degrees of its axis) the tilted plate fills
        pos, cells, camera = facing_plate(3.0, tilt, fov_deg=10.0)
        seen = render(camera, pos, cells).depth > 0
        assert seen.all()
        kept[tilt] = (render(camera, pos, cells, grazing_angle_deg=60.0).depth > 0).mean()
    assert kept[50.0] == 1.0 and kept[70.0] == 0.0
    pos, cells, camera = facing_plate(5.0)  # the plate's silhouette inside the image is a depth edge
    seen = render(camera, pos, cells).depth > 0
    assert not seen.all()
    silhouette = seen & ~ndimage.binary_erosion(seen, border_value=1)
    edged = render(camera, pos, cells, edge_threshold=0.05).depth > 0
    assert silhouette.sum() > 50
    np.testing.assert_array_equal(edged, seen & ~silhouette)


def test_flying_pixels():
    pos, cells, camera = facing_plate(2.0)
    clean = render(camera, pos, cells)
    flawed = render(camera, pos, cells, np.random.default_rng(1), outlier_fraction=0.2, outlier_range=0.3)
    seen = clean.depth > 0
    moved = np.abs(flawed.depth - clean.depth)[seen]
    assert (moved > 1e-4).mean() == pytest.approx(0.2, abs=0.03) and moved.max() <= 0.3 + 1e-5


def test_extrinsic_calibration_error():
    """The images report the configured pose while the camera sits elsewhere: a 0.1 shift along the view
    moves the plate's points 0.1 towards the camera, a 5 degree turn tilts them 5 degrees; in 2D `observe`
    (fusing the flawed images) shifts the plate's cloud by the error in the plane."""
    pos, cells, camera = facing_plate(2.0)
    shifted = back_project(render(camera, pos, cells, extrinsic_error=(0, 0, 0, 0, 0, 0.1)))
    np.testing.assert_allclose(shifted[:, 2], 0.1, atol=1e-5)
    turned = back_project(render(camera, pos, cells, extrinsic_error=(5.0, 0, 0, 0, 0, 0)))
    centred = turned - turned.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    assert np.degrees(np.arccos(abs(normal[2]))) == pytest.approx(5.0, abs=0.05)

    pos2, cells2 = box_mesh(2, 5)
    front = PinholeCamera((0.5, 0.5, 3.0), (0.5, 0.5, 0.0), (0, 1, 0), 45.0, 120, 120)
    fine = 0.01  # a voxel below the pixels' spacing (0.02 here): the points are the pixels' hits
    clean = DepthSensor(SensorConfig((front,), fine)).observe(pos2, cells2, None, None)
    error = (0, 0, 0, 0.05, 0.0, 0.0)  # along the camera's x: world -x for this camera (`camera_to_world`)
    flawed = DepthSensor(SensorConfig((front,), fine, extrinsic_error=error)).observe(pos2, cells2, None, None)
    shift = -(front.camera_to_world()[:3, :3] @ np.array(error[3:]))[:2]
    np.testing.assert_allclose(flawed.mean(axis=0) - clean.mean(axis=0), shift, atol=0.003)
    assert np.abs(shift).max() == pytest.approx(0.05)


def legacy_observe(config: SensorConfig, positions, cells, collider_vertices, collider_faces, rng=None):
    """`DepthSensor.observe` as it was before depth images and the sensor flaws, written out: the datasets'
    points."""
    d = positions.shape[1]
    scene = o3d.t.geometry.RaycastingScene()
    meshes = [object_mesh(positions, cells, config.slab_half_thickness)]
    if collider_vertices is not None:
        meshes.append(collider_mesh(collider_vertices, collider_faces, d, config.slab_half_thickness))
    ids = [scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
           for v, f in meshes]
    rays = np.concatenate([c.rays() for c in config.cameras])
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    mask = hits["geometry_ids"].numpy() == ids[0]
    rays, t = rays.astype(np.float64)[mask], hits["t_hit"].numpy()[mask].astype(np.float64)
    points = rays[:, :3] + t[:, None] * rays[:, 3:]
    if d == 2:
        points[:, 2] = 0.0
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    points = np.asarray(cloud.voxel_down_sample(config.voxel_size).points)[:, :d]
    points = points[np.lexsort(points.T[::-1])]
    if config.noise_std > 0:
        points = points + rng.normal(0.0, config.noise_std, size=points.shape)
    return points.astype(np.float32)


def test_default_sensor_is_unchanged_bit_for_bit(trajs, config):
    """Without flaws `observe` is the cast the datasets were made with: equal, bit for bit, to it written out
    and to the stored points of the generated trajectories."""
    sensor_config = SensorConfig.from_dict(config["sensor"])
    assert not sensor_config.has_flaws
    sensor = DepthSensor(sensor_config)
    for tr in trajs:
        for t in (0, tr.num_steps - 1):
            state = (tr.positions[t], tr.cells, tr.collider_positions[t], tr.collider_faces)
            np.testing.assert_array_equal(sensor.observe(*state), tr.point_cloud(t))
            np.testing.assert_array_equal(sensor.observe(*state), legacy_observe(sensor_config, *state))
    noisy = dataclasses.replace(sensor_config, noise_std=0.01)
    state = (trajs[0].positions[4], trajs[0].cells, trajs[0].collider_positions[4], trajs[0].collider_faces)
    np.testing.assert_array_equal(DepthSensor(noisy).observe(*state, np.random.default_rng(5)),
                                  legacy_observe(noisy, *state, np.random.default_rng(5)))
    pos, cells, _, _, cams = cube_scene()
    cube = SensorConfig(cams, 0.05)
    np.testing.assert_array_equal(DepthSensor(cube).observe(pos, cells, None, None),
                                  legacy_observe(cube, pos, cells, None, None))


@pytest.mark.parametrize("field, value", [("axial_noise", -1.0), ("grazing_angle_deg", 0.0),
                                          ("outlier_fraction", 1.5), ("extrinsic_error", (0, 0, 0)),
                                          ("edge_threshold", float("nan"))])
def test_bad_flaw_settings_name_their_field(field, value):
    with pytest.raises(ValueError, match=field):
        SensorConfig(CAMERAS[:1], 0.05, **{field: value})


# ---- the benchmark of the stepper's time per tick (`python -m ggns bench online`) --------------------------------
def test_bench_online_times_each_observation_and_writes_its_files(tiny_data_dir, tmp_path):
    import csv

    from ggns.bench.online import COLUMNS, bench_online
    from ggns.cli.bench import BENCH_COMMANDS

    assert "online" in BENCH_COMMANDS
    rows = bench_online({"untrained": make(GGNS)}, dataset="plate_tiny", data_dirs={"plate_tiny": str(tiny_data_dir)},
                        ticks=3, warmup=1, threads=(1,), output_dir=tmp_path)
    assert [(r["observation"], r["threads"], r["ticks"]) for r in rows] == [("none", 1, 3), ("points", 1, 3),
                                                                            ("depth", 1, 3)]
    for row in rows:
        assert np.isfinite([row["median ms"], row["q1 ms"], row["q3 ms"]]).all()
        assert 0 < row["q1 ms"] <= row["median ms"] <= row["q3 ms"] and row["ticks per s"] > 0
    assert rows[0]["mean points"] == 0 and rows[1]["mean points"] > 0 and rows[2]["mean points"] > 0
    with open(tmp_path / "online_bench.csv", newline="") as file:
        written = list(csv.DictReader(file))
    assert list(written[0]) == COLUMNS and [r["observation"] for r in written] == ["none", "points", "depth"]
    assert all(np.isfinite(float(r["median ms"])) for r in written)
    assert "| untrained | plate_tiny | 81 | depth |" in (tmp_path / "online_bench.md").read_text()


def test_online_study_feeds_late_frames_and_scores_every_tick(trajs, config):
    from ggns.bench.online import camera_frames
    from ggns.bench.online_study import track

    world, model = trajs[0], make(GGNS)
    depth = DepthProcessing.from_sensor_config(config["sensor"])
    errors, fed = track(model, world, camera_frames(config, world), every=2, latency=1, depth=depth)
    assert errors.shape == (world.num_steps - 1,) and np.isfinite(errors).all()
    assert fed == len(range(0, world.num_steps - 2, 2))  # the frames of ticks 0, 2, .. arrive at 1, 3, .. <= T - 2
    frames = camera_frames(config, world)
    late, fed = track(model, world, frames, every=1, latency=5, depth=depth)  # 5 ticks late: kept that long
    assert fed == world.num_steps - 1 - 5 and np.isfinite(late).all()
    blind, none = track(model, world, None, 1, 0, depth)  # blind: the offline rollout, scored per tick
    offline = model.rollout(TrajectoryBatch.from_trajectories([world]), "never")
    np.testing.assert_allclose(blind, ((offline[1:].double().numpy() - world.positions[1:]) ** 2).mean(axis=(1, 2)),
                               rtol=1e-5)
    assert none == 0


def test_sensor_presets_scale_to_the_scene_and_every_study_sensor_builds(config):
    """The named flaws: lengths in metres divided by the scene's metres per unit, the axial coefficient per
    metre multiplied by it; calibration errors added; unknown names refused naming the known ones. Each of the
    study's sensors gives a valid SensorConfig of the scene (its cameras: all, or the first n)."""
    from ggns.bench.online_study import SENSORS, sensor_overrides
    from ggns.sensors.camera import KINECT_AXIAL_NOISE, SensorConfig, sensor_flaws

    assert sensor_flaws("flawless") == {}
    real = sensor_flaws("realistic", metres_per_unit=0.1, noise_scale=3.0, calibration="cm")
    assert real["axial_noise"] == pytest.approx(3 * 0.1 * KINECT_AXIAL_NOISE)
    assert real["edge_threshold"] == pytest.approx(0.3) and real["outlier_range"] == pytest.approx(1.0)
    assert real["extrinsic_error"] == pytest.approx((1.0, 1.0, 1.0, 0.1, 0.1, 0.1))
    assert real["grazing_angle_deg"] == 70.0 and real["outlier_fraction"] == 0.005
    for bad in ({"preset": "kinect"}, {"calibration": "m"}):
        with pytest.raises(ValueError, match="known"):
            sensor_flaws(**bad)
    tissue = load_config("tissue_tiny")
    for scene, task in ((config, "plate"), (tissue, "tissue")):  # 1 and 5 cameras
        cameras = len(scene["sensor"]["cameras"])
        for name, (_, _, _, first) in SENSORS.items():
            sensor = SensorConfig.from_dict({**scene["sensor"], **sensor_overrides(name, scene, task)})
            assert len(sensor.cameras) == min(first or cameras, cameras)
            assert sensor.cameras[0] == SensorConfig.from_dict(scene["sensor"]).cameras[0]  # the first ones kept
            assert sensor.has_flaws == (name != "none")
    # the fine-tuning's flawed data preset holds the realistic preset's values for its scene in metres
    flawed = load_config("tissue_cpu_60_realistic")["sensor"]
    assert {k: flawed[k] for k in sensor_flaws("realistic")} == pytest.approx(sensor_flaws("realistic"))


def test_the_online_study_command_offers_every_study_sensor_and_refuses_a_checkpoint_named_as_a_shipped_model(tmp_path):
    """`bench online-study --sensor` lists its choices for the command line; they are the study's SENSORS, no
    more and no fewer. A checkpoint given the name of a shipped model it is compared with is refused before
    any model loads (it would replace that model's rows)."""
    import typing

    from ggns.bench.online_study import SENSORS, online_study
    from ggns.cli.bench import bench_online_study

    (choices,) = typing.get_args(typing.get_type_hints(bench_online_study)["sensor"])
    assert set(typing.get_args(choices)) == set(SENSORS)
    with pytest.raises(ValueError, match=r"checkpoint names \['tissue/mgn'\] are the shipped models' names"):
        online_study("tissue", checkpoints={"tissue/mgn": str(tmp_path / "absent.ckpt")}, output_dir=tmp_path)
    assert not list(tmp_path.iterdir())
