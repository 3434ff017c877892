"""The rollout engine and TrajectoryBatch on real tiny plate data (2 trajectories, T = 8):
ground truth replay, point-cloud schedules, fixed nodes, divergence errors, model state,
m+horizon rollouts and batching."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch_geometric.utils import scatter

from ggns.config import load_config
from ggns.data.generate import generate
from ggns.data.schema import SplitReader
from ggns.evaluation.evaluate import evaluate_batch, zero_motion_one_step_mse
from ggns.evaluation.metrics import m_plus_10_mse
from ggns.evaluation.rollout import RolloutError, m_plus_10_rollouts, rollout
from ggns.evaluation.schedules import EveryK, FirstM, Never
from ggns.batch import TrajectoryBatch
from ggns.graphs.connectivity import load_connectivity
from ggns.graphs.state import state_graph

CONN = load_connectivity("plate_full_graph")
T = 8


@pytest.fixture(scope="module")
def trajs(tmp_path_factory):
    cfg = load_config("plate_tiny", [f"output={tmp_path_factory.mktemp('data')}"])
    (path,) = generate(cfg, ["val"], progress=False)
    reader = SplitReader(path)
    return [reader[i] for i in range(len(reader))]


@pytest.fixture(scope="module")
def batch(trajs):
    return TrajectoryBatch.from_trajectories(trajs, dtype=torch.float64)


def step_of(graph, batch) -> int:
    """The step t of a graph, found from its collider positions (the collider moves every step)."""
    (t,) = [t for t in range(batch.num_steps) if torch.equal(graph["collider"].pos, batch.collider[t])]
    return t


def true_step(batch, points_only: bool = False):
    """step_fn returning the true displacement x_{t+1} - x_t of the current step; with points_only,
    zero displacement for graphs without point nodes."""
    def step_fn(graph, state):
        t = step_of(graph, batch)
        if points_only and "point" not in graph.node_types:
            return torch.zeros_like(graph["mesh"].pos), state
        return batch.positions[t + 1] - graph["mesh"].pos, state

    return step_fn


def test_batch_layout(trajs, batch):
    n = [len(t.rest_positions) for t in trajs]
    assert batch.num_graphs == 2 and batch.num_steps == T
    assert batch.node_offsets == (0, n[0], n[0] + n[1])
    assert batch.positions.shape == (T, sum(n), 2) and batch.collider.shape[0] == T
    assert batch.edges.shape == (2, 2 * sum(len(t.edges) for t in trajs))
    assert (batch.mesh_batch[batch.edges[0]] == batch.mesh_batch[batch.edges[1]]).all()
    assert torch.equal(batch.cells[batch.cell_offsets[1]:], torch.as_tensor(trajs[1].cells) + n[0])
    for t in range(T):
        assert torch.equal(batch.point_batch[t].bincount(minlength=2),
                           torch.tensor([len(tr.point_cloud(t)) for tr in trajs]))
    assert batch.material.tolist() == [tr.poissons_ratio for tr in trajs]
    assert batch.to("cpu").positions.device.type == "cpu"


def test_true_displacement_reproduces_ground_truth(batch):
    calls = []

    def step_fn(graph, state):  # a step counter, as the step-function contract prescribes
        t = len(calls)
        calls.append(t)
        return batch.positions[t + 1] - batch.positions[t], state

    positions, _ = rollout(step_fn, batch, EveryK(1), CONN)
    assert positions.shape == batch.positions.shape and len(calls) == T - 1
    torch.testing.assert_close(positions, batch.positions, rtol=0, atol=1e-12)


@pytest.mark.parametrize("schedule", [EveryK(1), EveryK(2), EveryK(5), Never(), FirstM(3)], ids=str)
def test_schedule_uses_points_exactly_at_scheduled_steps(batch, schedule):
    seen = []

    def step_fn(graph, state):
        seen.append("point" in graph.node_types)
        return torch.zeros_like(graph["mesh"].pos), state

    rollout(step_fn, batch, schedule, CONN)
    assert seen == schedule.mask(T - 1).tolist()


def test_per_trajectory_point_mask(batch):
    pos = batch.positions[3]
    graph = state_graph(batch, 3, pos, torch.tensor([False, True]), CONN)
    assert (graph["point"].batch == 1).all() and len(graph["point"].pos) == (batch.point_batch[3] == 1).sum()
    assert torch.equal(graph["point"].pos, batch.points[3][batch.point_batch[3] == 1])
    assert "point" not in state_graph(batch, 3, pos, torch.tensor([False, False]), CONN).node_types
    assert "point" not in state_graph(batch, 3, pos, False, CONN).node_types
    assert len(state_graph(batch, 3, pos, True, CONN)["point"].pos) == len(batch.points[3])
    assert state_graph(batch, 3, pos, True, CONN, with_material=True)["mesh"].x.shape[1] == 2
    with pytest.raises(IndexError, match="t=7"):
        state_graph(batch, T - 1, pos, True, CONN)


def test_fixed_nodes_stay_at_true_positions(batch):
    assert batch.fixed.any()

    def step_fn(graph, state):
        return torch.where(graph["mesh"].x[:, :1] > 0, 1e3, 0.0).expand_as(graph["mesh"].pos), state

    positions, _ = rollout(step_fn, batch, EveryK(2), CONN)
    assert torch.equal(positions[:, batch.fixed], batch.positions[:, batch.fixed])
    assert torch.equal(positions[:, ~batch.fixed], batch.positions[:1, ~batch.fixed].expand(T, -1, -1))


def test_zero_motion_baseline_by_hand_and_through_the_engine(batch):
    """`zero_motion_one_step_mse` (the validation's no-motion reference): per trajectory, the mean over
    t = 1..T-1 of the squared step x_t - x_{t-1} over all nodes and coordinates, fixed nodes at their
    known positions adding zero (here they move, so that this is checked); and the same numbers as
    the one-step MSE of a zero-displacement step function through the engine."""
    moved = dataclasses.replace(batch, positions=batch.positions.clone())
    moved.positions[:, moved.fixed] += torch.arange(T, dtype=torch.float64)[:, None, None]
    got = zero_motion_one_step_mse(moved)
    o = moved.node_offsets
    for b in range(moved.num_graphs):
        x, free = moved.positions[:, o[b]:o[b + 1]].numpy(), (~moved.fixed[o[b]:o[b + 1]]).numpy()
        by_hand = np.mean([((x[t] - x[t - 1]) ** 2 * free[:, None]).sum() / x[t].size for t in range(1, T)])
        assert by_hand > 0 and got[b].item() == pytest.approx(by_hand, rel=1e-12)

    def zero(graph, state):
        return torch.zeros_like(graph["mesh"].pos), state

    engine = evaluate_batch(zero, moved, CONN, schedules=[], m_plus_10=False, iou=False)
    torch.testing.assert_close(got, engine["one_step_mse"], rtol=1e-12, atol=0)


def test_non_finite_step_raises_naming_step_and_trajectory(batch):
    node = int(torch.nonzero(~batch.fixed & (batch.mesh_batch == 1))[0])

    def step_fn(graph, state):
        state = 0 if state is None else state + 1
        displacement = torch.zeros_like(graph["mesh"].pos)
        if state == 2:
            displacement[node, 0] = float("nan")
        return displacement, state

    local = node - batch.node_offsets[1]
    with pytest.raises(RolloutError, match=rf"step 2 .*\[1\] of the batch; the first: mesh node {local} of "
                                           rf"trajectory 1, predicted position \[nan, "):
        rollout(step_fn, batch, EveryK(1), CONN)


def test_a_node_that_escapes_the_scene_stops_the_rollout_naming_it(batch):
    """Finite but garbage: a free node pushed 1e3 x the start extent away at step 3 is reported
    (step, node within its trajectory, distance) instead of returned."""
    node = int(torch.nonzero(~batch.fixed & (batch.mesh_batch == 1))[0])
    extent = float((batch.positions[0].amax(0) - batch.positions[0].amin(0)).norm())

    def step_fn(graph, state):
        state = 0 if state is None else state + 1
        displacement = torch.zeros_like(graph["mesh"].pos)
        if state == 3:
            displacement[node, 1] = 1e3 * extent
        return displacement, state

    local = node - batch.node_offsets[1]
    with pytest.raises(RolloutError, match=rf"step 3 .*mesh node {local} of trajectory 1 is .* from its start, more "
                                           rf"than 100 x the start state's extent"):
        rollout(step_fn, batch, EveryK(1), CONN)


def test_state_is_carried_within_and_reset_between_rollouts(batch):
    seen = []

    def step_fn(graph, state):
        seen.append(state)
        return torch.zeros_like(graph["mesh"].pos), (0 if state is None else state) + 1

    for _ in range(2):
        _, final = rollout(step_fn, batch, EveryK(1), CONN)
        assert final == T - 1
    assert seen == [None, *range(1, T - 1)] * 2
    seen.clear()
    _, final = rollout(step_fn, batch, Never(), CONN, start=2, steps=3, state=10)
    assert seen == [10, 11, 12] and final == 13


def test_m_plus_horizon_rollouts_track_then_freeze(batch):
    horizon = 3
    preds = m_plus_10_rollouts(true_step(batch, points_only=True), batch, CONN, horizon=horizon)
    assert sorted(preds) == list(range(T - horizon))
    for m, pred in preds.items():
        assert pred.shape == (m + horizon + 1, *batch.positions.shape[1:])
        torch.testing.assert_close(pred[: m + 1], batch.positions[: m + 1], rtol=0, atol=1e-12)
        free = pred[:, ~batch.fixed]
        assert torch.equal(free[m + 1 :], free[m : m + 1].expand(horizon, -1, -1))
    stacked = {m: p[None] for m, p in preds.items()}  # one "trajectory" of all nodes, for the metric
    m_plus_10_mse(stacked, batch.positions[None], horizon=horizon)


def test_m_plus_horizon_stride_averages_every_strided_start(batch):
    """`evaluate_batch(m_plus_10_stride=s)`: the m+horizon error averaged over the starts 0, s, 2s, ...
    only (the validation's cheaper estimate); stride 1 is every start."""
    step_fn, horizon = true_step(batch, points_only=True), 3
    starts = list(range(T - horizon))
    preds = m_plus_10_rollouts(step_fn, batch, CONN, horizon=horizon)
    o = batch.node_offsets
    per_m = [m_plus_10_mse({m: preds[m][None, :, o[0]:o[1]]}, batch.positions[None, :, o[0]:o[1]], horizon=horizon)[0]
             for m in starts]  # trajectory 0
    for stride in (1, 2):
        got = evaluate_batch(step_fn, batch, CONN, schedules=[], iou=False, horizon=horizon, m_plus_10_stride=stride)
        assert got["m10_mse"][0].item() == pytest.approx(np.mean(per_m[::stride]), rel=1e-12)
    assert np.mean(per_m[::2]) != pytest.approx(np.mean(per_m), rel=1e-3)  # the stride changes the value here
    with pytest.raises(ValueError, match="m_plus_10_stride must be >= 1"):
        evaluate_batch(step_fn, batch, CONN, m_plus_10_stride=0)


def test_m_plus_horizon_model_state_is_copied(batch):
    """Blind branches start from a copy of the chain's model state: in-place updates inside a
    branch never reach the chain or other branches."""
    seen = []

    def step_fn(graph, state):
        state = state if state is not None else {"count": torch.zeros(())}
        seen.append(("point" in graph.node_types, int(state["count"])))
        state["count"] += 1  # in place
        return torch.zeros_like(graph["mesh"].pos), state

    m_plus_10_rollouts(step_fn, batch, CONN, horizon=3, starts=[1, 2])
    # chain step 0; branch m=1 (counts 1..3); chain step 1 still sees 1; branch m=2 (2..4)
    assert seen == [(True, 0), (False, 1), (False, 2), (False, 3), (True, 1), (False, 2), (False, 3), (False, 4)]


def test_mismatched_step_counts_raise(trajs):
    short = dataclasses.replace(trajs[1], positions=trajs[1].positions[:5], collider_positions=trajs[1].collider_positions[:5],
                                point_offsets=trajs[1].point_offsets[:6])
    with pytest.raises(ValueError, match="equal step counts"):
        TrajectoryBatch.from_trajectories([trajs[0], short])


def test_batched_rollout_equals_one_at_a_time(trajs):
    def step_fn(graph, state):
        b = graph["mesh"].batch
        velocity = scatter(graph["collider"].x, graph["collider"].batch, dim=0, dim_size=graph.num_graphs, reduce="mean")
        out = velocity[b] * (1 + graph["mesh"].pos.square().sum(1, keepdim=True))
        if "point" in graph.node_types:
            centre = scatter(graph["point"].pos, graph["point"].batch, dim=0, dim_size=graph.num_graphs, reduce="mean")
            out = out + 0.01 * (centre[b] - graph["mesh"].pos)
        return out, state

    batched, _ = rollout(step_fn, TrajectoryBatch.from_trajectories(trajs), EveryK(2), CONN)
    single = [rollout(step_fn, TrajectoryBatch.from_trajectories([t]), EveryK(2), CONN)[0] for t in trajs]
    torch.testing.assert_close(batched, torch.cat(single, dim=1), rtol=1e-6, atol=1e-6)
