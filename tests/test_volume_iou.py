"""Hand-computed cases for the 3D (tetrahedral) mesh IoU and the box tetrahedral mesh."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ggns.evaluation import tet_mesh_iou
from ggns.evaluation.metrics import rollout_volume_iou
from ggns.evaluation.volume import surface_self_intersects
from ggns.geometry import boundary_facets, box_tet_mesh, signed_volumes

CUBE, CUBE_CELLS = box_tet_mesh([0, 0, 0], [1, 1, 1], 2)  # 27 nodes, 48 tetrahedra
SAMPLED_TOL = 2e-2  # stated tolerance of the sampled IoU at the default 2^15 points (observed ~1e-4)


def test_box_tet_mesh_fills_the_box_with_positive_conforming_tetrahedra():
    positions, cells = box_tet_mesh([-1.0, 0.0, 2.0], [1.0, 3.0, 2.5], (2, 3, 4))
    assert positions.shape == (3 * 4 * 5, 3) and cells.shape == (6 * 2 * 3 * 4, 4)
    volumes = signed_volumes(positions, cells)
    assert (volumes > 0).all()
    assert volumes.sum() == pytest.approx(2.0 * 3.0 * 0.5, rel=1e-12)
    # conforming: the boundary is exactly two triangles per boundary quad (no hanging facets inside)
    assert len(boundary_facets(cells)) == 2 * 2 * (2 * 3 + 2 * 4 + 3 * 4)
    with pytest.raises(ValueError, match="empty"):
        box_tet_mesh([0, 0, 0], [1, 0, 1], 1)
    with pytest.raises(ValueError, match="divisions"):
        box_tet_mesh([0, 0, 0], [1, 1, 1], 0)


def test_identical_meshes_have_iou_exactly_one():
    result = tet_mesh_iou(torch.as_tensor(CUBE), torch.as_tensor(CUBE), torch.as_tensor(CUBE_CELLS))
    assert result.method == "exact" and result.reason == "" and result.samples == 0
    assert result.iou == 1.0 and result.union == pytest.approx(1.0, abs=1e-12)


def test_half_shifted_cube_gives_one_third_exact_and_sampled():
    shifted = CUBE + np.array([0.5, 0.0, 0.0])
    exact = tet_mesh_iou(shifted, CUBE, CUBE_CELLS, method="exact")
    assert exact.method == "exact"
    assert exact.intersection == pytest.approx(0.5, abs=1e-9) and exact.union == pytest.approx(1.5, abs=1e-9)
    assert exact.iou == pytest.approx(1 / 3, abs=1e-9)
    assert tet_mesh_iou(shifted, CUBE, CUBE_CELLS).method == "exact"  # "auto" on a valid pair
    sampled = tet_mesh_iou(shifted, CUBE, CUBE_CELLS, method="sampled")
    assert sampled.method == "sampled" and sampled.reason == "requested" and sampled.samples == 1 << 15
    assert sampled.iou == pytest.approx(1 / 3, abs=SAMPLED_TOL)
    assert tet_mesh_iou(shifted, CUBE, CUBE_CELLS, method="sampled") == sampled  # seeded: reproducible


def test_disjoint_cubes_have_iou_zero():
    far = CUBE + np.array([3.0, 0.0, 0.0])
    assert tet_mesh_iou(far, CUBE, CUBE_CELLS).iou == 0.0
    assert tet_mesh_iou(far, CUBE, CUBE_CELLS, method="sampled", samples=1 << 12).iou == 0.0


def test_inverted_tetrahedron_falls_back_to_sampling():
    true = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    cells = np.array([[0, 1, 2, 3]])
    pred = true.copy()
    pred[3] = [0.0, 0.0, -1.0]  # the tetrahedron turns inside out into its mirror image below z = 0
    result = tet_mesh_iou(pred, true, cells)
    assert result.method == "sampled" and "pred_nodes: 1 inverted or degenerate" in result.reason
    assert result.pred_volume == pytest.approx(1 / 6, abs=SAMPLED_TOL)  # inverted, it still covers its volume
    assert result.iou == 0.0  # the mirror images share only the face z = 0
    with pytest.raises(ValueError, match="exact volume IoU is invalid here: pred_nodes: 1 inverted"):
        tet_mesh_iou(pred, true, cells, method="exact")


ONE, ONE_CELLS = box_tet_mesh([0, 0, 0], [1, 1, 1], 1)


@pytest.mark.parametrize("second, reason, covered", [
    (ONE + [0.5, 0.2, 0.1], "pred_nodes: boundary surface intersects itself", 2 - 0.5 * 0.8 * 0.9),
    (ONE + [0.5, 0.0, 0.0], "pred_nodes: boundary surface intersects itself", 1.5),  # faces touch in-plane
    (3 * ONE - 1, "pred_nodes: its 2 boundary components overlap", 27.0),  # nested: the surfaces never meet
])
def test_self_overlapping_prediction_falls_back_to_sampling(second, reason, covered):
    cells = np.concatenate([ONE_CELLS, ONE_CELLS + len(ONE)])
    true = np.concatenate([ONE, ONE + [2.0, 0.0, 0.0]])  # two separate unit cubes: volume 2
    pred = np.concatenate([ONE, second])  # the second cube pushed into (or around) the first
    result = tet_mesh_iou(pred, true, cells)
    assert result.method == "sampled" and result.reason.startswith(reason)
    assert result.pred_volume == pytest.approx(covered, rel=SAMPLED_TOL)  # not the sum of the tetrahedra
    assert result.iou == pytest.approx(1.0 / (covered + 2.0 - 1.0), abs=SAMPLED_TOL)
    with pytest.raises(ValueError, match=reason.split(": ")[1]):
        tet_mesh_iou(pred, true, cells, method="exact")


def test_surface_self_intersection_test():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, -1], [0.2, 0.2, 1], [1, 1, 1]], dtype=float)
    assert surface_self_intersects(x, np.array([[0, 1, 2], [3, 4, 5]]))  # an edge pierces the other
    assert not surface_self_intersects(x, np.array([[0, 1, 2], [1, 2, 5]]))  # sharing an edge
    assert not surface_self_intersects(x, np.array([[0, 1, 2], [0, 4, 5]]))  # sharing a vertex
    touching = x.copy()
    touching[3:] = [[1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [2.0, 1.0, 0.0]]  # an edge passes through node 1's point
    assert surface_self_intersects(touching, np.array([[0, 1, 2], [3, 4, 5]]))  # touching also counts
    apart = x.copy()
    apart[3:] += [0.0, 0.0, 2.0]  # the second triangle lifted clear of the first
    assert not surface_self_intersects(apart, np.array([[0, 1, 2], [3, 4, 5]]))
    assert not surface_self_intersects(CUBE, boundary_facets(CUBE_CELLS, CUBE))  # a closed surface


def test_bad_input_is_rejected_with_the_problem_named():
    with pytest.raises(ValueError, match=r"cells must be integer \[C, 4\] tetrahedra"):
        tet_mesh_iou(CUBE, CUBE, CUBE_CELLS[:, :3])
    with pytest.raises(ValueError, match="outside the 27 mesh nodes"):
        tet_mesh_iou(CUBE, CUBE, CUBE_CELLS + 1)
    bad = CUBE.copy()
    bad[4, 1] = math.nan
    for method in ("auto", "exact", "sampled"):
        with pytest.raises(ValueError, match="pred_nodes has 1 non-finite"):
            tet_mesh_iou(bad, CUBE, CUBE_CELLS, method=method)
    with pytest.raises(ValueError, match=r"must be \[N, 3\]"):
        tet_mesh_iou(CUBE[:, :2], CUBE[:, :2], CUBE_CELLS)
    with pytest.raises(ValueError, match="same N"):
        tet_mesh_iou(CUBE, CUBE[:-1], CUBE_CELLS[:1])
    with pytest.raises(ValueError, match="method"):
        tet_mesh_iou(CUBE, CUBE, CUBE_CELLS, method="voxels")
    with pytest.raises(ValueError, match="samples"):
        tet_mesh_iou(CUBE, CUBE, CUBE_CELLS, method="sampled", samples=0)
    flat = CUBE * [1.0, 1.0, 0.0]  # every tetrahedron squashed flat
    with pytest.raises(ValueError, match="zero volume"):
        tet_mesh_iou(flat, flat, CUBE_CELLS)


def test_rollout_volume_iou_averages_every_stride_th_state():
    positions, cells = box_tet_mesh((0, 0, 0), (1, 1, 1), 1)
    true = np.stack([positions] * 5)
    pred = true.copy()
    pred[2] += [0.5, 0.0, 0.0]  # IoU 1/3 at state 2, 1 elsewhere
    assert rollout_volume_iou(pred, true, cells, stride=2) == pytest.approx((1 / 3 + 1) / 2, abs=1e-9)  # states 2, 4
    assert rollout_volume_iou(pred[None], true[None], cells, stride=10) == pytest.approx(1.0)  # the last state
    with pytest.raises(ValueError, match=r"\[T, N, 3\]"):
        rollout_volume_iou(pred[..., :2], true[..., :2], cells)
