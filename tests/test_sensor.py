"""Virtual depth camera: points on the deformable surface only, occlusion, voxel, noise, config."""
from __future__ import annotations

import itertools

import numpy as np
import open3d as o3d
import pytest
import shapely

from ggns.geometry import boundary_facets
from ggns.sensors.camera import DepthSensor, PinholeCamera, SensorConfig

VOXEL = 0.05


def grid_2d(n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Unit square [-0.5, 0.5]^2 with n x n nodes, two triangles per quad."""
    t = np.linspace(-0.5, 0.5, n)
    x, y = np.meshgrid(t, t, indexing="xy")
    pos = np.stack([x.ravel(), y.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="xy")
    v0 = (j * n + i).ravel()
    v1, v2, v3 = v0 + 1, v0 + n + 1, v0 + n
    cells = np.concatenate([np.stack([v0, v1, v2], 1), np.stack([v0, v2, v3], 1)])
    return pos, cells


def tet_cube(n: int = 3, lo: float = -0.5, hi: float = 0.5):
    """Cube [lo, hi]^3 with n^3 sub-cubes, each split into 6 Kuhn tetrahedra (conforming)."""
    t = np.linspace(lo, hi, n + 1)
    pos = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    corner = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    cells = []
    for perm in itertools.permutations(range(3)):
        verts, c = [corner], corner.copy()
        for axis in perm:
            c = c.copy()
            c[:, axis] += 1
            verts.append(c)
        cells.append(np.stack([idx[v[:, 0], v[:, 1], v[:, 2]] for v in verts], axis=1))
    return pos, np.concatenate(cells)


def square_polyline(x0, y0, x1, y1):
    verts = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)
    return verts, np.array([[0, 1], [1, 2], [2, 3], [3, 0]])


def cam(eye, look_at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), px=120):
    return PinholeCamera(eye=eye, look_at=look_at, up=up, fov_deg=45.0, width_px=px, height_px=px)


FRONT_2D = cam((0.1, 0.0, 3.0))
CUBE_CAMS = (cam((3.0, 0.4, 0.3)), cam((0.3, 3.0, 0.4), up=(0, 0, 1)), cam((0.4, 0.3, 3.0)))


def sheared_square():
    pos, cells = grid_2d()
    pos = pos + np.stack([0.3 * pos[:, 1], np.zeros(len(pos))], axis=1)
    return pos, cells


def surface_distance(points, pos, cells):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(pos.astype(np.float32)),
                        o3d.core.Tensor(boundary_facets(cells).astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def test_2d_points_inside_and_covering_deformed_square():
    pos, cells = sheared_square()
    points = DepthSensor(SensorConfig((FRONT_2D,), VOXEL)).observe(pos, cells, None, None)
    assert points.dtype == np.float32 and points.shape[1] == 2
    square = shapely.Polygon(pos[[0, 4, 24, 20]])  # corners of the 5 x 5 grid
    assert shapely.contains_xy(square.buffer(VOXEL), points[:, 0], points[:, 1]).all()
    assert shapely.MultiPoint(points).convex_hull.area > 0.8 * square.area
    expected = square.area / VOXEL**2
    assert 0.7 * expected < len(points) < 1.3 * expected


def test_3d_points_on_visible_boundary_faces():
    pos, cells = tet_cube()
    points = DepthSensor(SensorConfig(CUBE_CAMS, VOXEL)).observe(pos, cells, None, None)
    assert points.dtype == np.float32 and points.shape[1] == 3
    assert surface_distance(points, pos, cells).max() < VOXEL
    for axis in range(3):  # each camera sees its +axis face; nobody sees the -axis faces
        inner = (np.abs(np.delete(points, axis, axis=1)) < 0.4).all(axis=1)
        assert (inner & (np.abs(points[:, axis] - 0.5) < 0.01)).sum() > 100
        assert (inner & (np.abs(points[:, axis] + 0.5) < 0.01)).sum() == 0


def test_2d_collider_beside_object_gives_no_points():
    pos, cells = sheared_square()
    collider = square_polyline(1.0, -0.3, 1.4, 0.3)
    sensor = DepthSensor(SensorConfig((FRONT_2D,), VOXEL))
    points = sensor.observe(pos, cells, *collider)
    assert len(points) > 100
    assert points[:, 0].max() < 0.65 + VOXEL  # sheared square reaches x = 0.65
    np.testing.assert_array_equal(points, sensor.observe(pos, cells, None, None))


def test_3d_collider_beside_gives_no_points_and_in_front_occludes():
    pos, cells = tet_cube()
    top = cam((0.0, 0.0, 3.0), px=160)
    sensor = DepthSensor(SensorConfig((top,), VOXEL))
    free = sensor.observe(pos, cells, None, None)

    side_pos, side_cells = tet_cube(1, 0.7, 1.0)
    beside = sensor.observe(pos, cells, side_pos, boundary_facets(side_cells, side_pos))
    assert np.abs(beside).max() <= 0.5 + 1e-4

    plate_pos, plate_cells = tet_cube(1)
    plate_pos = plate_pos * [0.6, 1.4, 0.1] + [0.4, 0.0, 1.0]  # x in [0.1, 0.7], z ~ 1
    occluded = sensor.observe(pos, cells, plate_pos, boundary_facets(plate_cells, plate_pos))
    n_free, n_occ = (np.sum(p[:, 0] > 0.2) for p in (free, occluded))
    assert n_free > 50 and n_occ < 0.2 * n_free
    assert np.sum(occluded[:, 0] < -0.1) == np.sum(free[:, 0] < -0.1)  # open side untouched


def test_larger_voxel_gives_fewer_points():
    pos, cells = sheared_square()
    counts = [len(DepthSensor(SensorConfig((FRONT_2D,), v)).observe(pos, cells, None, None))
              for v in (0.04, 0.08)]
    assert 2.5 < counts[0] / counts[1] < 5.5  # area scaling ~ 4


def test_noise_level_seed_and_rng_requirement():
    pos, cells = sheared_square()
    clean = DepthSensor(SensorConfig((FRONT_2D,), VOXEL)).observe(pos, cells, None, None)
    noisy_sensor = DepthSensor(SensorConfig((FRONT_2D,), VOXEL, noise_std=0.01))
    noisy = noisy_sensor.observe(pos, cells, None, None, np.random.default_rng(3))
    assert noisy.shape == clean.shape
    assert 0.007 < np.std(noisy - clean) < 0.013
    again = noisy_sensor.observe(pos, cells, None, None, np.random.default_rng(3))
    np.testing.assert_array_equal(noisy, again)
    with pytest.raises(ValueError, match="rng"):
        noisy_sensor.observe(pos, cells, None, None)


def test_deterministic_and_empty():
    pos, cells = tet_cube()
    sensor = DepthSensor(SensorConfig(CUBE_CAMS, VOXEL))
    np.testing.assert_array_equal(sensor.observe(pos, cells, None, None),
                                  sensor.observe(pos, cells, None, None))
    away = DepthSensor(SensorConfig((cam((0.0, 0.0, 3.0), look_at=(0.0, 0.0, 6.0)),), VOXEL))
    assert away.observe(pos, cells, None, None).shape == (0, 3)
    pos2, cells2 = sheared_square()
    assert away.observe(pos2, cells2, None, None).shape == (0, 2)


def test_from_dict():
    d = {"cameras": [{"eye": [0, 0, 3], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 40,
                      "width_px": 64, "height_px": 48}], "voxel_size": 0.1, "noise_std": 0.01}
    cfg = SensorConfig.from_dict(d)
    assert cfg.cameras[0].eye == (0.0, 0.0, 3.0) and cfg.voxel_size == 0.1
    assert cfg.slab_half_thickness == 0.05


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: PinholeCamera((0, 0, 3), (0, 0, 0), (0, 1, 0), 0.0, 8, 8), "fov_deg"),
        (lambda: PinholeCamera((0, 0, 3), (0, 0, 0), (0, 1, 0), 45.0, 0, 8), "width_px"),
        (lambda: PinholeCamera((0, 0, 3), (0, 0, 3), (0, 1, 0), 45.0, 8, 8), "look_at"),
        (lambda: PinholeCamera((0, 0, 3), (0, 0, 0), (0, 0, 2), 45.0, 8, 8), "up"),
        (lambda: SensorConfig((FRONT_2D,), 0.0), "voxel_size"),
        (lambda: SensorConfig((), 0.1), "cameras"),
        (lambda: SensorConfig((FRONT_2D,), 0.1, noise_std=-1.0), "noise_std"),
    ],
)
def test_bad_config_names_field(make, field):
    with pytest.raises(ValueError, match=field):
        make()


def test_without_open3d_training_imports_and_generation_names_what_is_missing(tmp_path):
    """A machine without open3d (a GPU node, say) still imports everything that trains and evaluates;
    generating a dataset fails at once with an error naming open3d, also with worker processes (a
    failing worker initializer would make multiprocessing.Pool restart workers without end)."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(f"""
        import sys
        sys.modules["open3d"] = None  # import open3d now raises ImportError
        import ggns.cli.lightning, ggns.cli.commands, ggns.data.module, ggns.bench.tradeoff, ggns.callbacks
        from ggns.config import load_config
        from ggns.data.generate import generate
        for workers in (1, 2):
            try:
                generate(load_config("plate_tiny", ["output={tmp_path}/w" + str(workers), "workers=" + str(workers)]),
                         progress=False)
            except ImportError as error:
                assert "open3d is needed to raycast" in str(error), error
                print("refused", workers)
        """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["refused", "1", "refused", "2"]
    assert not list(tmp_path.rglob("*.h5"))  # nothing written
