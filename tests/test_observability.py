"""`evaluation.observability.error_shares` on a known mesh: a 2x2x2-cell box has one interior node
and a node at the middle of each face, whose vertex normal is the face's normal. Its visibility split
on two tetrahedra (every node on the boundary, like the cavity's wall) under hand-placed point clouds."""
from __future__ import annotations

import numpy as np
import pytest

from ggns.evaluation.observability import (PARTS, VISIBILITY, default_visibility_radius, error_shares, seen_fraction,
                                           vertex_normals)
from ggns.geometry import boundary_facets, box_tet_mesh
from ggns.trajectory import pack_point_clouds


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


# two tetrahedra sharing the face 1-2-3; node 0 fixed; node 4 rises 0.2 a step
TWO_TETS_REST = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=np.float64)
TWO_TETS = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
ERRORS = {1: 0.01, 2: 0.02, 3: 0.3, 4: 0.04}  # node: its x error at each predicted state


@pytest.fixture(scope="module")
def two_tets():
    rest = TWO_TETS_REST
    true = np.stack([rest + np.outer(np.arange(5) == 4, [0, 0, 0.2 * t]) for t in range(4)])  # 4 states
    pred = true.copy()
    for node, dx in ERRORS.items():
        pred[1:, node, 0] += dx
    pred[1:, 0] += 0.5  # a fixed node's error counts nowhere
    near = 0.05  # a point this far from a node sees it at radius 0.1
    at = lambda t, node: true[t, node] + [0, near, 0]  # noqa: E731
    clouds = [
        np.array([at(0, 0), at(0, 1), at(0, 2)]),
        np.array([at(1, 0), at(1, 1), rest[4]]),  # rest[4] is 0.2 from node 4's true position: not seen
        np.array([at(2, 0), at(2, 1), pred[2, 3]]),  # on node 3's prediction, 0.3 from its true position: not seen
        np.array([at(3, 0), at(3, 2), at(3, 4)]),
    ]
    points, offsets = pack_point_clouds(clouds)
    return pred, true, rest, points, offsets


def test_seen_fraction_counts_the_steps_with_a_point_near_the_true_position(two_tets):
    _, true, _, points, offsets = two_tets
    np.testing.assert_allclose(seen_fraction(true, points, offsets, 0.1), [1, 3 / 4, 2 / 4, 0, 1 / 4])
    np.testing.assert_allclose(seen_fraction(true, points, offsets, 0.25)[[3, 4]], [0, 2 / 4])  # rest[4] now counts
    empty = np.zeros((0, 3), dtype=np.float32)
    np.testing.assert_array_equal(seen_fraction(true, empty, np.zeros(5, dtype=np.int64), 0.1), 0)


def test_visibility_groups_and_their_errors_by_hand(two_tets):
    pred, true, rest, points, offsets = two_tets
    fixed = np.arange(5) == 0
    shares = error_shares(pred, true, rest, TWO_TETS, fixed, points=points, point_offsets=offsets, radius=0.1)
    # node 1 seen at 3 of 4 steps, node 2 at 2 of 4 (>= half: seen), node 4 at 1, node 3 at none
    squared = {node: 3 * dx**2 for node, dx in ERRORS.items()}  # 3 predicted states
    total = sum(squared.values())
    count = 3 * 4 * 3  # predicted states x free nodes x coordinates
    expected = {"seen": (squared[1] + squared[2], 2), "sometimes_seen": (squared[4], 1), "never_seen": (squared[3], 1)}
    for group, (error, nodes) in expected.items():
        assert shares[group] == pytest.approx(error / count)
        assert shares[f"{group}_share"] == pytest.approx(error / total)
        assert shares[f"{group}_nodes"] == nodes
        assert shares[f"{group}_node_mse"] == pytest.approx(error / (3 * nodes * 3))
    assert shares["visibility_radius"] == 0.1
    # every node is on the boundary: nothing interior, and both splits add up to the same total
    assert shares["interior"] == 0.0
    assert sum(shares[g] for g in VISIBILITY) == pytest.approx(sum(shares[p] for p in PARTS)) == pytest.approx(total / count)


def test_default_radius_and_the_split_without_points(two_tets):
    pred, true, rest, points, offsets = two_tets
    fixed = np.arange(5) == 0
    # shortest edges: 1 at nodes 0..3 (their edges to node 0), sqrt 2 at node 4: the median is 1
    assert default_visibility_radius(rest, TWO_TETS) == pytest.approx(0.75)
    shares = error_shares(pred, true, rest, TWO_TETS, fixed, points=points, point_offsets=offsets)
    assert shares["visibility_radius"] == pytest.approx(0.75)
    # at 0.75 node 4 is also seen at step 1 (rest[4], 0.2 away) and node 3 at step 2 (its prediction, 0.3 away)
    assert (shares["seen_nodes"], shares["sometimes_seen_nodes"], shares["never_seen_nodes"]) == (3, 1, 0)
    plain = error_shares(pred, true, rest, TWO_TETS, fixed)
    assert set(plain) == {*PARTS, *(f"{p}_share" for p in PARTS)}
    assert all(shares[key] == value for key, value in plain.items())


def test_bad_visibility_inputs_name_the_problem(two_tets):
    pred, true, rest, points, offsets = two_tets
    fixed = np.arange(5) == 0
    with pytest.raises(ValueError, match="both points and point_offsets"):
        error_shares(pred, true, rest, TWO_TETS, fixed, points=points)
    with pytest.raises(ValueError, match=r"point_offsets must be \[T\+1\] = \[5\]"):
        error_shares(pred, true, rest, TWO_TETS, fixed, points=points, point_offsets=offsets[:-1])
    with pytest.raises(ValueError, match="do not describe per-step clouds"):
        error_shares(pred, true, rest, TWO_TETS, fixed, points=points[:-1], point_offsets=offsets)
    with pytest.raises(ValueError, match="must be positive"):
        error_shares(pred, true, rest, TWO_TETS, fixed, points=points, point_offsets=offsets, radius=0.0)


# ---- 2D: the outline against the interior, on a 2x2-cell square of 8 triangles ----------------------
SQUARE_REST = np.array([[x, y] for y in (0.0, 0.5, 1.0) for x in (0.0, 0.5, 1.0)])  # node 3 * row + column
SQUARE = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [3, 4, 7], [3, 7, 6], [4, 5, 8], [4, 8, 7]])
CENTRE, BOTTOM_MIDDLE, CORNER = 4, 1, 0


def test_2d_vertex_normals_are_the_outline_normals():
    normals = vertex_normals(SQUARE_REST, boundary_facets(SQUARE, SQUARE_REST))
    np.testing.assert_allclose(normals[BOTTOM_MIDDLE], [0, -1], atol=1e-12)  # outward: below the square
    np.testing.assert_allclose(normals[CORNER], [-np.sqrt(0.5), -np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_array_equal(normals[CENTRE], 0)  # on no boundary segment


@pytest.mark.parametrize("node, offset, part", [(BOTTOM_MIDDLE, [0.0, 0.004], "surface_normal"),
                                                (BOTTOM_MIDDLE, [-0.003, 0.0], "surface_tangential"),
                                                (CENTRE, [0.002, -0.001], "interior")])
def test_2d_each_error_lands_in_its_part(node, offset, part):
    true = np.stack([SQUARE_REST, SQUARE_REST * 1.1, SQUARE_REST + 0.02])  # the error is against these
    pred = true.copy()
    pred[1:, node] += offset
    fixed = np.zeros(len(SQUARE_REST), dtype=bool)
    fixed[CORNER] = True
    shares = error_shares(pred, true, SQUARE_REST, SQUARE, fixed)
    assert shares[f"{part}_share"] == pytest.approx(1.0)
    assert shares[part] == pytest.approx(2 * float(np.sum(np.square(offset))) / (2 * 8 * 2))  # 8 free nodes, 2D
    tilted = true.copy()
    tilted[1:, BOTTOM_MIDDLE] += [0.003, 0.004]
    both = error_shares(tilted, true, SQUARE_REST, SQUARE, fixed)
    assert (both["surface_normal_share"], both["surface_tangential_share"]) == (pytest.approx(16 / 25),
                                                                                pytest.approx(9 / 25))


def test_2d_cells_must_be_triangles():
    with pytest.raises(ValueError, match=r"2D mesh must be triangles \[C, 3\]"):
        error_shares(np.zeros((3, 9, 2)), np.zeros((3, 9, 2)), SQUARE_REST, np.zeros((2, 4), dtype=int),
                     np.zeros(9, dtype=bool))
