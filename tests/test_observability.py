"""`evaluation.observability.error_shares` on a known mesh: a 2x2x2-cell box has one interior node
and a node at the middle of each face, whose vertex normal is the face's normal."""
from __future__ import annotations

import numpy as np
import pytest

from ggns.evaluation.observability import error_shares, vertex_normals
from ggns.geometry import boundary_facets, box_tet_mesh


@pytest.fixture(scope="module")
def box():
    rest, cells = box_tet_mesh([0, 0, 0], [1, 1, 1], 2)
    centre = int(np.argmin(np.linalg.norm(rest - 0.5, axis=1)))
    top = int(np.argmin(np.linalg.norm(rest - [0.5, 0.5, 1.0], axis=1)))
    corner = int(np.argmin(np.linalg.norm(rest, axis=1)))
    return rest, cells, centre, top, corner


def _shares(box, node, offset, fixed_nodes=()):
    rest, cells, *_ = box
    true = np.stack([rest, rest + 0.01, rest])  # 3 states; the error is measured against the true ones
    pred = true.copy()
    pred[1:, node] += offset
    fixed = np.zeros(len(rest), dtype=bool)
    fixed[list(fixed_nodes)] = True
    return error_shares(pred, true, rest, cells, fixed)


def test_vertex_normal_of_a_face_centre_is_the_face_normal(box):
    rest, cells, centre, top, _ = box
    normals = vertex_normals(rest, boundary_facets(cells, rest))
    np.testing.assert_allclose(normals[top], [0, 0, 1], atol=1e-12)
    np.testing.assert_array_equal(normals[centre], 0)  # on no boundary triangle


@pytest.mark.parametrize("where, offset, part", [("top", [0, 0, 0.003], "surface_normal"),
                                                 ("top", [0.003, -0.004, 0], "surface_tangential"),
                                                 ("centre", [0.002, 0.001, 0.003], "interior")])
def test_each_error_lands_in_its_part(box, where, offset, part):
    rest, _, centre, top, _ = box
    shares = _shares(box, {"top": top, "centre": centre}[where], np.array(offset))
    assert shares[f"{part}_share"] == pytest.approx(1.0)
    squared = float(np.sum(np.square(offset)))
    assert shares[part] == pytest.approx(2 * squared / (2 * len(rest) * 3))  # 2 predicted states, 27 free nodes
    assert sum(shares[f"{p}_share"] for p in ("surface_normal", "surface_tangential", "interior")) == pytest.approx(1.0)


def test_a_tilted_error_splits_by_the_normal_and_fixed_nodes_do_not_count(box):
    rest, _, _, top, corner = box
    shares = _shares(box, top, np.array([0.003, 0.0, 0.004]), fixed_nodes=[corner])
    assert shares["surface_normal_share"] == pytest.approx(16 / 25)
    assert shares["surface_tangential_share"] == pytest.approx(9 / 25)
    fixed_only = _shares(box, corner, np.array([0.01, 0.0, 0.0]), fixed_nodes=[corner])
    assert fixed_only["surface_normal"] == fixed_only["surface_tangential"] == fixed_only["interior"] == 0.0


def test_bad_inputs_name_the_problem(box):
    rest, cells, *_ = box
    fixed = np.zeros(len(rest), dtype=bool)
    with pytest.raises(ValueError, match="must both be"):
        error_shares(np.zeros((3, len(rest), 3)), np.zeros((3, len(rest) + 1, 3)), rest, cells, fixed)
    with pytest.raises(ValueError, match="tetrahedra"):
        error_shares(np.zeros((3, len(rest), 3)), np.zeros((3, len(rest), 3)), rest, cells[:, :3], fixed)
    with pytest.raises(ValueError, match="every node is fixed"):
        error_shares(np.zeros((3, len(rest), 3)), np.zeros((3, len(rest), 3)), rest, cells, ~fixed)
