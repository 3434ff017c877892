"""ParaView files of rollouts (`ggns.paraview`): the .vtu grids read back (XML) to exactly what was
written, the .pvd collections name existing files at the right times, bad input is refused."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from ggns.geometry import box_tet_mesh
from ggns.paraview import VTK_TETRA, VTK_TRIANGLE, VTK_VERTEX, write_rollout, write_vtu


def read_vtu(path):
    piece = ET.parse(path).getroot().find("UnstructuredGrid/Piece")
    arrays = {a.get("Name"): np.array(a.text.split(), dtype=float) for a in piece.iter("DataArray")}
    points = np.array(piece.find("Points/DataArray").text.split(), dtype=float).reshape(-1, 3)
    return int(piece.get("NumberOfPoints")), int(piece.get("NumberOfCells")), points, arrays


def test_tetrahedra_round_trip_with_point_data(tmp_path):
    positions, cells = box_tet_mesh((0, 0, 0), (1, 1, 1), 1)
    positions = positions + np.random.default_rng(0).normal(0, 1e-3, positions.shape)
    error = np.linspace(0, 1, len(positions))
    n, c, points, arrays = read_vtu(write_vtu(tmp_path / "a.vtu", positions, cells, {"error": error}))
    assert (n, c) == (8, 6)
    np.testing.assert_array_equal(points, positions)  # repr floats: exact
    np.testing.assert_array_equal(arrays["connectivity"].reshape(-1, 4), cells)
    np.testing.assert_array_equal(arrays["offsets"], 4 * np.arange(1, 7))
    assert set(arrays["types"]) == {VTK_TETRA}
    np.testing.assert_array_equal(arrays["error"], error)


def test_2d_meshes_lie_in_z_0(tmp_path):
    positions = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    _, _, points, arrays = read_vtu(write_vtu(tmp_path / "t.vtu", positions, [[0, 1, 2]]))
    np.testing.assert_array_equal(points, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert set(arrays["types"]) == {VTK_TRIANGLE}


def test_rollout_series_and_collections(tmp_path):
    positions, cells = box_tet_mesh((0, 0, 0), (1, 1, 1), 1)
    truth = np.stack([positions + [0, 0, 0.1 * t] for t in range(3)])
    pred = truth + 0.01
    clouds = [positions[:3], None, positions[:2]]
    written = write_rollout(tmp_path, cells, truth, {"GGNS_every_1": pred}, clouds, frame_dt=0.02)
    assert [p.name for p in written] == ["truth.pvd", "GGNS_every_1.pvd", "points.pvd"]
    for pvd in written:
        for entry in ET.parse(pvd).getroot().iter("DataSet"):
            assert (tmp_path / entry.get("file")).is_file()
    times = [float(e.get("timestep")) for e in ET.parse(tmp_path / "points.pvd").getroot().iter("DataSet")]
    assert times == [0.0, 0.04]  # no cloud at step 1
    _, _, points, arrays = read_vtu(tmp_path / "GGNS_every_1" / "0002.vtu")
    np.testing.assert_allclose(points, pred[2])
    np.testing.assert_allclose(arrays["error"], np.sqrt(3) * 0.01)
    n, c, _, arrays = read_vtu(tmp_path / "points" / "0002.vtu")
    assert (n, c) == (2, 2) and set(arrays["types"]) == {VTK_VERTEX}


def test_rollout_without_ground_truth_writes_the_predictions_alone(tmp_path):
    """A trajectory built from a user's arrays without true positions: no truth series, no error."""
    positions, cells = box_tet_mesh((0, 0, 0), (1, 1, 1), 1)
    pred = np.stack([positions + [0, 0, 0.1 * t] for t in range(3)])
    assert [p.name for p in write_rollout(tmp_path, cells, None, {"GGNS": pred})] == ["GGNS.pvd"]
    _, _, points, arrays = read_vtu(tmp_path / "GGNS" / "0001.vtu")
    np.testing.assert_allclose(points, pred[1])
    assert "error" not in arrays and not (tmp_path / "truth").exists()


def test_bad_input_is_refused_and_leaves_no_file(tmp_path):
    positions, cells = box_tet_mesh((0, 0, 0), (1, 1, 1), 1)
    bad = positions.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_vtu(tmp_path / "nan.vtu", bad, cells)
    with pytest.raises(ValueError, match="index outside"):
        write_vtu(tmp_path / "idx.vtu", positions, cells + 100)
    with pytest.raises(ValueError, match="shape"):
        write_rollout(tmp_path / "r", cells, positions[None], {"p": positions[None, :4]})
    with pytest.raises(ValueError, match="series name"):
        write_rollout(tmp_path / "r", cells, positions[None], {"a/b": positions[None]})
    assert not (tmp_path / "nan.vtu").exists() and not (tmp_path / "idx.vtu").exists()
