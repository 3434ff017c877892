"""Hand-computed cases for the evaluation metrics and point-cloud schedules."""
from __future__ import annotations

import math

import pytest
import torch

from ggns.evaluation import (
    EveryK,
    FirstM,
    Never,
    batch_iou,
    m_plus_10_mse,
    m_plus_10_pooled_mse,
    m_plus_10_starts,
    mesh_iou,
    one_step_mse,
    parse_schedule,
    per_step_curve,
    rollout_mse,
    step_mse,
)

SQUARE = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
SQUARE_CELLS = torch.tensor([[0, 1, 2], [0, 2, 3]])


def test_step_mse_known_values():
    true = torch.zeros(1, 2, 2, 2)
    pred = torch.tensor([[[[1.0, 0.0], [0.0, 0.0]], [[2.0, 2.0], [0.0, 2.0]]]])
    # t=0: (1+0+0+0)/4; t=1: (4+4+0+4)/4
    assert torch.allclose(step_mse(pred, true), torch.tensor([[0.25, 3.0]], dtype=torch.float64))


def test_masked_nodes_excluded():
    true = torch.zeros(2, 1, 3, 1)
    pred = torch.tensor([1.0, 2.0, 100.0]).reshape(1, 1, 3, 1).repeat(2, 1, 1, 1)
    shared = step_mse(pred, true, torch.tensor([True, True, False]))
    assert torch.allclose(shared, torch.tensor([[2.5], [2.5]], dtype=torch.float64))
    per_traj = step_mse(pred, true, torch.tensor([[True, False, False], [False, True, False]]))
    assert torch.allclose(per_traj, torch.tensor([[1.0], [4.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="no node"):
        step_mse(pred, true, torch.tensor([False, False, False]))


def test_rollout_mse_excludes_initial_state_and_averages_trajectories():
    true = torch.zeros(2, 3, 1, 1)
    pred = torch.tensor([[50.0, 1.0, 3.0], [50.0, 2.0, 2.0]]).reshape(2, 3, 1, 1)
    mean, per_traj = rollout_mse(pred, true)
    # trajectory 0: (1 + 9) / 2 = 5; trajectory 1: (4 + 4) / 2 = 4; the 50s at t=0 are ignored
    assert torch.allclose(per_traj, torch.tensor([5.0, 4.0], dtype=torch.float64))
    assert mean == pytest.approx(4.5)
    assert torch.allclose(per_step_curve(pred, true), torch.tensor([2500.0, 2.5, 6.5], dtype=torch.float64))


def test_one_step_mse_counts_every_entry():
    mean, per_traj = one_step_mse(torch.tensor([1.0, 3.0]).reshape(1, 2, 1, 1), torch.zeros(1, 2, 1, 1))
    assert mean == pytest.approx(5.0) and per_traj.tolist() == [5.0]


def test_m_plus_10_scores_only_state_m_plus_horizon():
    T, horizon = 6, 2
    true = torch.zeros(2, T, 1, 1)
    assert m_plus_10_starts(T, horizon) == [0, 1, 2, 3]
    preds = {}
    for m in m_plus_10_starts(T, horizon):
        p = torch.full((2, T, 1, 1), 100.0)  # every other state is wrong but unscored
        p[0, m + horizon] = m
        p[1, m + horizon] = 2 * m
        preds[m] = p
    mean, per_m = m_plus_10_mse(preds, true, horizon=horizon)
    # per m: mean over trajectories of (m^2, 4 m^2) = 2.5 m^2
    assert torch.allclose(per_m, torch.tensor([0.0, 2.5, 10.0, 22.5], dtype=torch.float64))
    assert mean == pytest.approx(35.0 / 4)
    short = {0: torch.zeros(2, horizon + 1, 1, 1)}  # a rollout that stops exactly at S_{m+horizon}
    assert m_plus_10_mse(short, true, horizon=horizon)[0] == 0.0
    with pytest.raises(ValueError, match="outside"):
        m_plus_10_mse({4: torch.zeros(2, T, 1, 1)}, true, horizon=horizon)
    with pytest.raises(ValueError):
        m_plus_10_mse({}, true)


def test_m_plus_10_pooled_counts_every_step_of_every_rollout_as_the_authors_code():
    """States 1..m+horizon of each rollout, summed over m, over sum of (m + horizon): with T = 6,
    horizon 2 and a squared error of 1 at point-cloud steps and 9 at blind ones (one node, one
    coordinate): m = 0..3 give 0 + 2 * 9, 1 + 18, 2 + 18, 3 + 18 over 2 + 3 + 4 + 5."""
    T, horizon = 6, 2
    true = torch.zeros(2, T, 1, 1)
    preds = {}
    for m in m_plus_10_starts(T, horizon):
        p = torch.full((2, T, 1, 1), 100.0)  # states after m + horizon are not counted
        p[:, 0] = 0.0
        p[:, 1 : m + 1] = 1.0
        p[:, m + 1 : m + horizon + 1] = 3.0
        preds[m] = p
    assert m_plus_10_pooled_mse(preds, true, horizon=horizon) == pytest.approx((0 + 1 + 2 + 3 + 4 * 18) / 14)
    blind_only = {m: torch.where(torch.arange(T)[None, :, None, None] > m, 3.0, 0.0).expand(2, T, 1, 1) for m in preds}
    # all steps equally wrong: the pooled value is that error, the paper's m+10 too
    assert m_plus_10_pooled_mse({m: torch.full((2, T, 1, 1), 3.0) for m in preds}, true, horizon=horizon) == 9.0
    assert m_plus_10_pooled_mse(blind_only, true, horizon=horizon) < m_plus_10_mse(blind_only, true, horizon=horizon)[0]
    with pytest.raises(ValueError, match="do not hold states"):
        m_plus_10_pooled_mse({4: torch.zeros(2, T, 1, 1)}, true, horizon=horizon)


def test_schedules():
    assert EveryK(1).mask(5).all()
    assert EveryK(2).mask(5).tolist() == [True, False, True, False, True]
    assert not Never().mask(4).any()
    assert FirstM(3).mask(5).tolist() == [True, True, True, False, False]
    assert FirstM(0).mask(2).tolist() == [False, False]
    assert EveryK(3).uses_points(6) and not EveryK(3).uses_points(7)
    with pytest.raises(ValueError):
        EveryK(1).uses_points(-1)


@pytest.mark.parametrize("text", ["every:1", "every:2", "never", "first:5", "first:0"])
def test_parse_round_trip(text):
    assert str(parse_schedule(text)) == text
    assert parse_schedule(text) == parse_schedule(str(parse_schedule(text)))


@pytest.mark.parametrize("text", ["every:0", "every:x", "every", "first:-1", "first:1.5", "never:2", "often", ""])
def test_parse_rejects_bad_text(text):
    with pytest.raises(ValueError):
        parse_schedule(text)


def test_iou_identical_and_shifted_squares():
    assert mesh_iou(SQUARE, SQUARE_CELLS, SQUARE, SQUARE_CELLS) == pytest.approx(1.0)
    shift = torch.tensor([0.5, 0.0])
    assert mesh_iou(SQUARE + shift, SQUARE_CELLS, SQUARE, SQUARE_CELLS) == pytest.approx(1.0 / 3.0)
    assert mesh_iou(SQUARE + 4 * shift, SQUARE_CELLS, SQUARE, SQUARE_CELLS) == 0.0


def test_iou_folded_and_degenerate_triangles():
    folded = SQUARE.clone()
    folded[3] = torch.tensor([1.0, 0.0])  # triangle (0, 2, 3) flips onto triangle (0, 1, 2)
    assert mesh_iou(folded, SQUARE_CELLS, SQUARE, SQUARE_CELLS) == pytest.approx(0.5)
    collapsed = SQUARE.clone()
    collapsed[3] = torch.tensor([0.5, 0.5])  # triangle (0, 2, 3) becomes a segment
    assert mesh_iou(collapsed, SQUARE_CELLS, SQUARE, SQUARE_CELLS) == pytest.approx(0.5)


def test_batch_iou_shape_and_values():
    true = SQUARE.expand(2, 3, 4, 2)
    pred = true + torch.tensor([0.0, 0.5, 2.0]).reshape(1, 3, 1, 1) * torch.tensor([1.0, 0.0])
    iou = batch_iou(pred, true, SQUARE_CELLS)
    assert iou.shape == (2, 3)
    assert torch.allclose(iou, torch.tensor([[1.0, 1 / 3, 0.0]] * 2, dtype=torch.float64))


def test_nan_is_rejected_everywhere():
    true = torch.zeros(1, 12, 4, 2)
    bad = true.clone()
    bad[0, 5, 1, 0] = math.nan
    for call in (
        lambda: step_mse(bad, true),
        lambda: one_step_mse(bad, true),
        lambda: rollout_mse(bad, true),
        lambda: per_step_curve(bad, true),
        lambda: m_plus_10_mse({0: bad}, true),
        lambda: batch_iou(bad, true, SQUARE_CELLS),
        lambda: mesh_iou(bad[0, 5], SQUARE_CELLS, true[0, 5], SQUARE_CELLS),
    ):
        with pytest.raises(ValueError, match="non-finite"):
            call()
