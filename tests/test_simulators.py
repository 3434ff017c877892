"""The learned simulators (ggns.models.simulators) on real tiny plate data (plate_tiny: 3 / 2 / 2
trajectories, T = 8 states, generated once per session by the real simulator): forward pass and
invariances, overfitting one batch with the real loss, LSTM state handling, the rollout schedules as
the models see them, normalizer statistics in checkpoints, divergence reports, the noise field.
Runs single-threaded (conftest `single_thread`)."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from ggns.batch import TrajectoryBatch
from ggns.data.module import SimulationDataModule, WindowDataset, collate
from ggns.evaluation.evaluate import m_plus_10_profile, pooled_over
from ggns.evaluation.metrics import m_plus_10_pooled_mse
from ggns.evaluation.rollout import RolloutError, m_plus_10_rollouts, rollout
from ggns.evaluation.schedules import PAPER_SCHEDULES, EveryK, FirstM, Never, effective_schedules
from ggns.models.lr_schedule import LRSchedule
from ggns.models.training_noise import TrainingNoise
from ggns.models.simulators import GGNS, GGNSID, GGNSLSTM, GGNSM, MGN, MGNM, MGNShared
from ggns.models.loading import load_simulator, upgrade_hparams
from conftest import T, first_graph, make, normalizer_buffers, quiet_trainer, save_untrained

pytestmark = pytest.mark.usefixtures("single_thread")

ALL_MODELS = (GGNS, GGNSLSTM, MGN, MGNM, MGNShared, GGNSM, GGNSID)


# ---- 1. forward shapes ---------------------------------------------------------------------------
@pytest.mark.parametrize("cls", ALL_MODELS)
def test_step_returns_a_finite_displacement_per_mesh_node(cls, val_batch):
    model = make(cls)
    graph = first_graph(model, val_batch)
    n = val_batch.rest.shape[0]
    with torch.no_grad():
        displacement, state = model.step(graph, None)
    assert displacement.shape == (n, 2) and torch.isfinite(displacement).all()
    assert graph["mesh"].x.shape == (n, 2 if cls in (MGNM, GGNSM, GGNSID) else 1)
    if cls is GGNSLSTM:
        h, c = state
        assert h.shape == c.shape == (n, 16)
    elif cls is GGNSID:  # (precision, precision-weighted mean) of the material per trajectory
        assert [t.shape for t in state] == [(val_batch.num_graphs,)] * 2
    else:
        assert state is None
    assert torch.equal(model(graph), displacement)  # forward = one step from a fresh state


def test_ggns_takes_graphs_with_and_without_points(val_batch):
    model = make(GGNS)
    with_points, without = first_graph(model, val_batch, True), first_graph(model, val_batch, False)
    assert "point" in with_points.node_types and ("point", "near", "mesh") in with_points.edge_types
    assert "point" not in without.node_types
    with torch.no_grad():
        a, b = model.step(with_points)[0], model.step(without)[0]
    assert a.shape == b.shape == (val_batch.rest.shape[0], 2)
    assert torch.isfinite(a).all() and torch.isfinite(b).all()
    assert not torch.allclose(a, b)  # the points reach the mesh


def test_mgn_shared_is_the_ggns_core_on_mesh_and_collider_edges(val_batch):
    """The authors' plate MGN: GGNS's one-hot shared processor, no world edges, no points."""
    model, ggns = make(MGNShared), make(GGNS)
    assert model.processor == ggns.processor == "shared" and model.core.type_encoding == ggns.core.type_encoding
    assert not model.uses_points and [str(s) for s in effective_schedules(PAPER_SCHEDULES, model.uses_points)] == ["never"]
    graph = first_graph(model, val_batch, True)
    assert set(graph.node_types) == {"mesh", "collider"}
    assert ("mesh", "world", "mesh") not in graph.edge_types and ("collider", "near", "mesh") in graph.edge_types


@pytest.mark.parametrize("cls", [MGN, MGNM])
def test_mgn_graphs_never_hold_points(cls, val_batch):
    model = make(cls)
    assert not model.uses_points and model.hparams.point_probability == 0
    for use_points in (True, torch.ones(val_batch.num_graphs, dtype=torch.bool)):
        graph = first_graph(model, val_batch, use_points)
        assert "point" not in graph.node_types
        assert not any("point" in (t[0], t[2]) for t in graph.edge_types)
        assert ("mesh", "world", "mesh") in graph.edge_types
    # the training graphs likewise, and MGN(M)'s second mesh column is the trajectory's Poisson ratio
    (graph, _), = model.training_graphs(dataclasses.replace(val_batch, positions=val_batch.positions[:2]))
    assert "point" not in graph.node_types
    if cls is MGNM:
        assert torch.equal(graph["mesh"].x[:, 1], val_batch.material[val_batch.mesh_batch])


def test_ggns_m_is_ggns_given_the_material(val_batch):
    """The ablation GGNS(M): GGNS's graphs with points, plus the Poisson ratio as a mesh feature that
    the prediction depends on."""
    model = make(GGNSM)
    assert model.uses_points and model.with_material
    graph = first_graph(model, val_batch, True)
    assert "point" in graph.node_types
    assert torch.equal(graph["mesh"].x[:, 1], val_batch.material[val_batch.mesh_batch])
    other = first_graph(model, dataclasses.replace(val_batch, material=-val_batch.material), True)
    with torch.no_grad():
        assert not torch.allclose(model.step(graph)[0], model.step(other)[0])


@pytest.mark.parametrize("cls, partition", [(GGNS, True), (MGNM, False)])
def test_the_processor_component_swaps_the_layout_and_survives_a_checkpoint(cls, partition, tiny_data_dir,
                                                                            val_batch, tmp_path):
    """`processor` chooses the layout of any class: GGNS with MGN's per-type encoders and edge MLPs, or
    MGN with GGNS's one-hot shared processor (the paper's "MGN (1H)" ablation); the graph (points, world
    edges, material) stays the class's, and a trained checkpoint rebuilds the same modules. An unknown
    layout is refused by name."""
    layout = "per_type" if partition else "shared"
    default, model = make(cls), make(cls, processor=layout, statistics_batches=1)
    assert default.processor == cls.default_processor != layout and model.processor == layout
    with pytest.raises(ValueError, match="processor must be one of"):
        make(cls, processor="per_edge")
    assert (default.edge_partition, default.core.type_encoding) == (not partition, "one_hot" if partition else "per_type")
    assert (model.edge_partition, model.core.type_encoding) == (partition, "per_type" if partition else "one_hot")
    edge_mlp = model.core.processor[0].edge_mlp
    assert isinstance(edge_mlp, torch.nn.ModuleDict) == partition  # one MLP per edge type, or one shared
    assert model.uses_points == default.uses_points and model.with_material == default.with_material
    graph = first_graph(model, val_batch, True)
    assert set(graph.edge_types) == set(first_graph(default, val_batch, True).edge_types)
    data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=4, generate_missing=False)
    trainer = quiet_trainer(tmp_path)
    trainer.fit(model, data)
    trainer.save_checkpoint(tmp_path / "model.ckpt")
    loaded = cls.load_from_checkpoint(tmp_path / "model.ckpt")
    assert loaded.edge_partition == partition and loaded.core.type_encoding == model.core.type_encoding
    model.eval()
    loaded.eval()
    with torch.no_grad():
        displacement = model.step(graph)[0]
        assert torch.isfinite(displacement).all()
        assert torch.equal(loaded.step(graph)[0], displacement)


# ---- 2. translation invariance ---------------------------------------------------------------------
def translated(batch: TrajectoryBatch, shift: torch.Tensor) -> TrajectoryBatch:
    """The same states moved by `shift` (mesh, collider and points; the rest state is mesh space)."""
    return dataclasses.replace(batch, positions=batch.positions + shift, collider=batch.collider + shift,
                               points=[p + shift for p in batch.points])


@pytest.mark.parametrize("cls", [GGNS, MGN])
def test_prediction_is_translation_invariant(cls, trajs, train_windows):
    """In float64, so that the check sees the model and not float32 rounding (which the
    normalization can amplify)."""
    model = make(cls).double()
    model.fit_normalizers([TrajectoryBatch.from_trajectories(train_windows, dtype=torch.float64)])
    batch = TrajectoryBatch.from_trajectories(trajs["val"], dtype=torch.float64)
    moved = translated(batch, torch.tensor([0.3, -0.2], dtype=torch.float64))
    for t in (0, 4):
        g, h = first_graph(model, batch, t=t), first_graph(model, moved, t=t)
        assert g.edge_types == h.edge_types
        assert all(g[e].edge_index.shape == h[e].edge_index.shape for e in g.edge_types)
        assert ("point" in g.node_types) == (cls is GGNS)
        with torch.no_grad():
            a, b = model.step(g)[0], model.step(h)[0]
        assert a.abs().max() > 1e-4  # not trivially zero
        torch.testing.assert_close(b, a, atol=1e-9, rtol=0)


@pytest.mark.parametrize("cls", [GGNS, MGN])
def test_float32_prediction_is_translation_invariant(cls, val_batch, train_batch):
    model = make(cls)
    model.fit_normalizers([train_batch])
    moved = translated(val_batch, torch.tensor([0.3, -0.2]))
    g, h = first_graph(model, val_batch), first_graph(model, moved)
    features = model.core.input_normalizer["collider"]
    # float32 resolution of positions near 1 (~1.2e-7) over the std floor (1e-5) bounds the change
    assert (features(g["collider"].x) - features(h["collider"].x)).abs().max() < 1.2e-2
    with torch.no_grad():
        torch.testing.assert_close(model.step(h)[0], model.step(g)[0], atol=1e-5, rtol=0)


# ---- 3. overfitting one batch ----------------------------------------------------------------------
@pytest.mark.parametrize("cls, window, factor", [(GGNS, 1, 5), (GGNSLSTM, 3, 5), (MGN, 1, 20), (MGNM, 1, 20)])
def test_each_model_overfits_one_window(cls, window, factor, trajs):
    """Adam (lr 3e-3, latent 32, 2 blocks) on one training window with noise_std=0 (and point
    clouds always, p = 1, for the GGNS models, so the input never changes), 100 steps of the real
    `window_loss`, must cut that window's loss by `factor`: 5 for GGNS / GGNS+LSTM (observed
    13-31x over seeds), 20 for MGN / MGN(M) (observed 59-144x)."""
    kwargs = dict(latent=32, blocks=2, noise=TrainingNoise(std=0.0), lr_schedule=LRSchedule(lr=3e-3))
    if cls in (GGNS, GGNSLSTM):
        kwargs["point_probability"] = 1.0
    if cls is GGNSLSTM:
        kwargs["window"] = window
    model = make(cls, **kwargs)
    batch = collate([WindowDataset(trajs["train"], window)[1]])
    assert batch.num_steps == window + 1
    model.fit_normalizers([batch])
    optimizer = model.configure_optimizers()["optimizer"]
    with torch.no_grad():
        initial = model.window_loss(batch, train=False).item()
    for _ in range(100):
        optimizer.zero_grad()
        model.window_loss(batch, train=True).backward()
        optimizer.step()
    with torch.no_grad():
        final = model.window_loss(batch, train=False).item()
    assert 0.3 < initial < 3  # standardized targets, untrained model
    assert final < initial / factor, (initial, final)


# ---- 5. schedules as the model sees them -----------------------------------------------------------
@pytest.mark.parametrize("schedule", [EveryK(3), FirstM(2), Never()], ids=str)
def test_rollout_gives_point_clouds_exactly_at_scheduled_steps(schedule, val_batch):
    model = make(GGNS)
    model_step = model.step
    seen = []

    def step_fn(graph, state):
        t = len(seen)
        has = "point" in graph.node_types
        seen.append(has)
        if has:  # the point cloud of the input state t, all trajectories
            assert torch.equal(graph["point"].pos, val_batch.points[t])
        return model_step(graph, state)

    rollout(step_fn, val_batch, schedule, model.connectivity)
    assert seen == schedule.mask(T - 1).tolist()
    expected = {"every:3": [True, False, False, True, False, False, True], "first:2": [True, True] + [False] * 5,
                "never": [False] * 7}
    assert seen == expected[str(schedule)]
    # the model's own rollout goes through its step with the same schedule
    seen.clear()
    model.step = step_fn  # an instance attribute shadows the method
    positions = model.rollout(val_batch, str(schedule))
    assert seen == expected[str(schedule)] and positions.shape == val_batch.positions.shape


# ---- 6. LSTM state -----------------------------------------------------------------------------------
def test_lstm_state_starts_fresh_and_carries(trajs, val_batch, train_batch):
    model = make(GGNSLSTM, window=3)
    model.fit_normalizers([train_batch])
    model.eval()
    conn = model.connectivity
    graph = first_graph(model, val_batch)
    n = val_batch.rest.shape[0]
    zeros = (torch.zeros(n, 16), torch.zeros(n, 16))
    with torch.no_grad():
        fresh, (h, c) = model.step(graph, None)
        explicit, (h0, c0) = model.step(graph, zeros)
    assert torch.equal(fresh, explicit) and torch.equal(h, h0) and torch.equal(c, c0)
    assert h.abs().max() > 0

    # reset: every rollout starts from state None, whatever ran before
    first = model.rollout(val_batch, "every:2")
    model.rollout(TrajectoryBatch.from_trajectories(trajs["test"]), "every:2")
    assert torch.equal(model.rollout(val_batch, "every:2"), first)
    # ... and per trajectory: the batched rollout equals each trajectory's own
    o = val_batch.node_offsets
    for b in range(val_batch.num_graphs):
        alone = model.rollout(TrajectoryBatch.from_trajectories([trajs["val"][b]]), "every:2")
        torch.testing.assert_close(alone, first[:, o[b]:o[b + 1]], atol=1e-5, rtol=0)

    # carry: state after steps 0-1 continues the rollout exactly; zeroing it changes step 2
    full, _ = rollout(model.step, val_batch, EveryK(1), conn, steps=3)
    head, state = rollout(model.step, val_batch, EveryK(1), conn, steps=2)
    carried, _ = rollout(model.step, val_batch, EveryK(1), conn, start_positions=head[2], start=2, steps=1, state=state)
    reset, _ = rollout(model.step, val_batch, EveryK(1), conn, start_positions=head[2], start=2, steps=1, state=zeros)
    none, _ = rollout(model.step, val_batch, EveryK(1), conn, start_positions=head[2], start=2, steps=1)
    torch.testing.assert_close(carried[1], full[3], atol=1e-6, rtol=0)
    assert torch.equal(reset[1], none[1])
    free = ~val_batch.fixed
    step_size = (full[3] - full[2])[free].abs().max()
    assert (reset[1] - carried[1])[free].abs().max() > 1e-3 * step_size


def test_lstm_window_loss_carries_state_through_the_window(trajs):
    """A 3-transition window's loss is the mean of its transitions' losses for GGNS (no state),
    but not for GGNS+LSTM, whose later transitions see the state of the earlier ones."""
    window = collate([WindowDataset(trajs["train"], 3)[0]])
    singles = [collate([WindowDataset(trajs["train"], 1)[s]]) for s in range(3)]
    for cls, carries in ((GGNS, False), (GGNSLSTM, True)):
        model = make(cls, point_probability=1.0, noise=dict(std=0.0))
        model.fit_normalizers([window])
        with torch.no_grad():
            whole = model.window_loss(window, train=False)
            parts = torch.stack([model.window_loss(s, train=False) for s in singles]).mean()
        assert torch.isclose(whole, parts, rtol=1e-5).item() != carries, (cls.__name__, whole, parts)


def test_lstm_truncated_backpropagation_trains_only_the_last_transitions(trajs, tmp_path):
    """`backprop_steps=1` on a 3-transition window: the loss is the last transition's, with the LSTM
    state that the first two carried forward (the full window's last term), and it trains the LSTM;
    `backprop_steps=window` is the paper's loss; the setting survives a checkpoint."""
    window = collate([WindowDataset(trajs["train"], 3)[0]])
    full = make(GGNSLSTM, window=3, point_probability=1.0, noise=dict(std=0.0))
    full.fit_normalizers([window])
    truncated = make(GGNSLSTM, window=3, point_probability=1.0, noise=dict(std=0.0), backprop_steps=1)
    truncated.load_state_dict(full.state_dict())
    same = make(GGNSLSTM, window=3, point_probability=1.0, noise=dict(std=0.0), backprop_steps=3)
    same.load_state_dict(full.state_dict())
    free = ~window.fixed
    with torch.no_grad():
        state, terms = None, []
        for graph, target in full.training_graphs(window, train=False):
            out, state = full.predict_normalized(graph, state)
            terms.append((out[free] - full.target_normalizer(target[free])).square().mean())
        torch.testing.assert_close(full.window_loss(window, train=False), torch.stack(terms).mean())
        torch.testing.assert_close(same.window_loss(window, train=False), torch.stack(terms).mean())
    loss = truncated.window_loss(window, train=False)
    torch.testing.assert_close(loss.detach(), terms[-1])
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in truncated.lstm.parameters())
    with pytest.raises(ValueError, match="backprop_steps must lie in"):
        make(GGNSLSTM, window=3, backprop_steps=4)
    path = tmp_path / "lstm.ckpt"
    save_untrained(truncated, path)
    assert load_simulator(path).backprop_steps == 1


def test_training_loss_by_point_clouds(trajs):
    """`window_loss(by_points=True)`: the mean per-sample loss of the graphs with and without a point
    cloud (GGNS draws one per window), each equal to the per-sample losses computed one window at a
    time; equal meshes, so the whole loss is their mean over all samples. A group absent is left out."""
    windows = [WindowDataset(trajs["train"], 1)[i] for i in range(3 * (T - 1))]
    batch = collate(windows)
    model = make(GGNS, noise=dict(std=0.0))
    model.fit_normalizers([batch])
    torch.manual_seed(3)
    drawn = torch.rand(batch.num_graphs) < 0.5  # the draw `training_graphs` makes first (no noise)
    assert 0 < drawn.sum() < batch.num_graphs
    torch.manual_seed(3)
    with torch.no_grad():
        loss, groups = model.window_loss(batch, train=True, by_points=True)
        alone = []
        for window, points in zip(windows, drawn.tolist()):
            single = collate([window])
            free = ~single.fixed
            out = model.predict_normalized(first_graph(model, single, points))[0]
            target = model.target_normalizer((single.positions[1] - single.positions[0])[free])
            alone.append((out[free] - target).square().mean())
    alone = torch.stack(alone)
    torch.testing.assert_close(groups["points"], alone[drawn].mean(), rtol=1e-5, atol=0)
    torch.testing.assert_close(groups["no_points"], alone[~drawn].mean(), rtol=1e-5, atol=0)
    torch.testing.assert_close(loss, alone.mean(), rtol=1e-5, atol=0)
    with torch.no_grad():
        assert set(model.window_loss(batch, train=False, by_points=True)[1]) == {"points"}  # evaluation: always
        mgn = make(MGN)
        mgn.fit_normalizers([batch])
        assert set(mgn.window_loss(batch, train=True, by_points=True)[1]) == {"no_points"}


# ---- 7. normalizer statistics in checkpoints ---------------------------------------------------------
def test_normalizer_statistics_travel_with_the_checkpoint(tiny_data_dir, val_batch, tmp_path):
    model = make(GGNS, statistics_batches=2)
    data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=4, generate_missing=False)
    trainer = quiet_trainer(tmp_path)
    trainer.fit(model, data)
    assert model.target_normalizer.frozen and model.core.input_normalizer["mesh"].frozen
    assert int(model.target_normalizer.count) == 8 * 72  # 2 statistics batches of 4 windows x 72 free nodes
    trainer.save_checkpoint(tmp_path / "model.ckpt")
    loaded = GGNS.load_from_checkpoint(tmp_path / "model.ckpt")
    fitted, restored, untouched = (normalizer_buffers(dict(m.named_buffers())) for m in (model, loaded, make(GGNS)))
    assert fitted.keys() == restored.keys() and len(fitted) > 10
    for name, value in fitted.items():
        assert torch.equal(restored[name], value), name
    assert not torch.equal(untouched["target_normalizer.std"], fitted["target_normalizer.std"])
    model.eval()
    loaded.eval()
    graph = first_graph(model, val_batch)
    with torch.no_grad():
        assert torch.equal(loaded.step(graph)[0], model.step(graph)[0])


# ---- 8. divergence --------------------------------------------------------------------------------------
def test_nan_rollout_names_step_and_trajectory(val_batch):
    conn = make(GGNS).connectivity

    def nan_at(step: int, trajectory: int, nodes: str = "all"):
        calls = []

        def step_fn(graph, state):
            t = len(calls)
            calls.append(t)
            out = torch.zeros_like(graph["mesh"].pos)
            if t == step:
                hit = graph["mesh"].batch == trajectory
                if nodes == "fixed":
                    hit &= val_batch.fixed
                out[hit] = float("nan")
            return out, state

        return step_fn, calls

    step_fn, calls = nan_at(3, 1)
    with pytest.raises(RolloutError, match=r"step 3 \(state 3 -> 4\).*index\(es\) \[1\] "):
        rollout(step_fn, val_batch, EveryK(2), conn)
    assert calls == [0, 1, 2, 3]  # stopped at the bad step
    # NaN only at fixed nodes is harmless: they take their known positions
    step_fn, calls = nan_at(3, 1, nodes="fixed")
    positions, _ = rollout(step_fn, val_batch, EveryK(2), conn)
    assert torch.isfinite(positions).all() and len(calls) == T - 1

    model = make(MGN)
    with torch.no_grad():
        model.core.decoder[-1].bias.fill_(float("nan"))
    with pytest.raises(RolloutError, match=r"step 0 .*\[0, 1\]"):
        model.rollout(val_batch, "never")
    with pytest.raises(RolloutError):
        model.evaluate(val_batch, m_plus_10=False, iou=False)


def test_noise_field_moves_free_nodes_smoothly_and_is_refused_when_negative(trajs):
    """`noise.field_std`: training inputs get a smooth field on the free nodes (fixed ones stay), the
    target is corrected by it (x_{t+1} - noisy x_t); evaluation inputs get none; a negative std is refused."""
    batch = collate([WindowDataset(trajs["train"], 1)[0]])
    model = make(GGNS, noise=TrainingNoise(std=0.0, field_std=0.05))
    torch.manual_seed(0)
    (graph, target), = model.training_graphs(batch, train=True)
    moved = graph["mesh"].pos - batch.positions[0]
    assert torch.equal(moved[batch.fixed], torch.zeros_like(moved[batch.fixed]))
    assert 0.005 < moved[~batch.fixed].std().item() < 0.5
    torch.testing.assert_close(target, batch.positions[1] - graph["mesh"].pos)
    (clean, _), = model.training_graphs(batch, train=False)
    assert torch.equal(clean["mesh"].pos, batch.positions[0])
    with pytest.raises(ValueError, match="field_std >= 0"):
        make(GGNS, noise=dict(field_std=-0.1))
    with pytest.raises(ValueError, match=r"unknown fields \['fieldstd'\]"):
        make(GGNS, noise=dict(fieldstd=0.1))


def test_noise_field_on_point_cloud_samples_only_and_its_linear_decay(trajs, tiny_data_dir, tmp_path):
    """`noise.field_points_only`: a window drawn without its point clouds gets no field (a blind step
    cannot see it); `noise.field_decay_steps`: the field's std falls linearly to 0 with the optimizer
    step. Both survive a checkpoint round trip as hyperparameters; bad settings are refused."""
    batch = collate([WindowDataset(trajs["train"], 1)[i] for i in range(4)])
    model = make(GGNS, noise=TrainingNoise(std=0.0, field_std=0.05, field_points_only=True), point_probability=0.5)
    for seed in range(20):  # the first seed that draws both kinds among the 4 windows
        torch.manual_seed(seed)
        (graph, _), = model.training_graphs(batch, train=True)
        with_points = torch.zeros(batch.num_graphs, dtype=torch.bool)
        with_points[graph["point"].batch] = True
        if with_points.any() and not with_points.all():
            break
    assert with_points.any() and not with_points.all()
    moved = (graph["mesh"].pos - batch.positions[0]).norm(dim=1)
    for g in range(batch.num_graphs):
        nodes = (batch.mesh_batch == g) & ~batch.fixed
        assert (moved[nodes] > 0).all() if with_points[g] else (moved[nodes] == 0).all(), g
    decaying = make(GGNS, noise=dict(field_std=0.04, field_decay_steps=100))
    assert decaying.noise.field_std_at(decaying.global_step) == 0.04  # no trainer: step 0
    assert [decaying.noise.field_std_at(step) for step in (0, 25, 100, 150)] == pytest.approx([0.04, 0.03, 0.0, 0.0])
    assert TrainingNoise(field_std=0.04).field_std_at(10**6) == 0.04
    decaying.hparams.statistics_batches = 1
    trainer = quiet_trainer(tmp_path)  # one optimizer step
    trainer.fit(decaying, SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=4,
                                               generate_missing=False))
    assert decaying.noise.field_std_at(decaying.global_step) == pytest.approx(0.04 * (1 - 1 / 100))
    trainer.save_checkpoint(tmp_path / "model.ckpt")
    loaded = GGNS.load_from_checkpoint(tmp_path / "model.ckpt", weights_only=True)
    assert loaded.noise == decaying.noise and loaded.hparams.noise["field_decay_steps"] == 100
    with pytest.raises(ValueError, match="field_points_only needs point clouds"):
        make(MGN, noise=dict(field_points_only=True))
    with pytest.raises(ValueError, match="field_decay_steps must be an integer >= 0"):
        make(GGNS, noise=dict(field_decay_steps=-1))


def test_ggns_id_reads_the_material_from_points_only_and_never_from_the_label(val_batch, tiny_data_dir, tmp_path):
    """GGNSID: the training graphs carry the label (teacher forcing) and its estimator's
    Gaussian NLL joins the loss on samples with points; a rollout's graphs carry no label, so changing the
    batch's materials changes nothing, while blind steps keep the prior (the training labels' mean) and
    point clouds move the estimate. Survives a checkpoint round trip and runs in the rollout engine."""
    model = make(GGNSID, statistics_batches=1)
    data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=4, generate_missing=False)
    trainer = quiet_trainer(tmp_path)
    trainer.fit(model, data)
    assert model.material_normalizer.frozen and model.estimator.input_normalizer["mesh"].frozen
    train = dataclasses.replace(val_batch, positions=val_batch.positions[:2])
    (graph, _), = model.training_graphs(train, train=False)
    assert torch.equal(graph["mesh"].x[:, 1], val_batch.material[val_batch.mesh_batch])
    assert model.auxiliary_loss(graph, train) is not None and torch.isfinite(model.auxiliary_loss(graph, train))
    without = first_graph(model, val_batch, False)
    assert model.auxiliary_loss(without, train) is None  # nothing to read the material from
    trainer.save_checkpoint(tmp_path / "id.ckpt")
    loaded = GGNSID.load_from_checkpoint(tmp_path / "id.ckpt", weights_only=True).eval()
    model.eval()
    other = dataclasses.replace(val_batch, material=-val_batch.material, material_known=(False,) * val_batch.num_graphs)
    prior = float(loaded.material_normalizer.mean[0])
    with torch.no_grad():
        for schedule in (EveryK(1), Never()):
            positions, state = rollout(loaded.step, val_batch, schedule, loaded.connectivity)
            again, _ = rollout(loaded.step, other, schedule, loaded.connectivity)
            assert torch.isfinite(positions).all() and torch.equal(positions, again)
            estimate = loaded.material_estimate(state)
            if isinstance(schedule, Never):
                torch.testing.assert_close(estimate, torch.full_like(estimate, prior))
            else:
                assert not torch.allclose(estimate, torch.full_like(estimate, prior))
        torch.testing.assert_close(rollout(model.step, val_batch, EveryK(1), model.connectivity)[0],
                                   rollout(loaded.step, val_batch, EveryK(1), loaded.connectivity)[0])
    # `diagnose --m-plus-10-stride`: per start m, the m+10 errors and the material carried after m point clouds
    profile = m_plus_10_profile(loaded, val_batch, [0, 2, 4], horizon=3)
    assert [r["m"] for r in profile] == [0, 2, 4] and all(r["m10_mse"] > 0 for r in profile)
    assert math.isnan(profile[0]["material_error"])  # no point cloud yet
    estimate = loaded.material_estimate(rollout(loaded.step, val_batch, EveryK(1), loaded.connectivity, steps=4)[1])
    assert profile[2]["material_error"] == pytest.approx((estimate - val_batch.material).abs().mean().item())
    assert "material_error" not in m_plus_10_profile(make(GGNS), val_batch, [1], horizon=3)[0]
    # the pooled score of those rollouts together: each m's pooled value weighed by its m + horizon steps
    preds = m_plus_10_rollouts(loaded.step, val_batch, loaded.connectivity, 3, [0, 2, 4])
    whole = [m_plus_10_pooled_mse({m: p[None] for m, p in preds.items()}, val_batch.positions[None], horizon=3)]
    assert pooled_over(profile, horizon=3) == pytest.approx(whole[0])
    with pytest.raises(ValueError, match="estimates the material from point clouds"):
        make(GGNSID, connectivity="plate_mgn", point_probability=0.0)


def test_ggns_id_estimator_noise_moves_only_the_estimators_mesh(val_batch, tiny_data_dir, tmp_path):
    """`estimator_noise` (a `TrainingNoise`): in training the estimator reads the sample's mesh moved by a smooth field (free
    nodes only, same point clouds, edges rebuilt); the dynamics' sample, validation and rollouts are as
    without it. Trains through Lightning and survives a checkpoint round trip."""
    model = make(GGNSID, statistics_batches=1, estimator_noise={"std": 0.0, "field_std": 0.05, "field_mixture": True})
    data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=4, generate_missing=False)
    trainer = quiet_trainer(tmp_path)
    trainer.fit(model, data)
    graph = first_graph(model, val_batch, True)
    moved = model.estimator_graph(graph, val_batch, 0)
    fixed = val_batch.fixed
    assert moved is not graph and torch.equal(moved["point"].pos, graph["point"].pos)
    assert torch.equal(moved["mesh"].pos[fixed], graph["mesh"].pos[fixed])
    shift = (moved["mesh"].pos - graph["mesh"].pos)[~fixed].norm(dim=1)
    assert shift.max() > 1e-3  # the free nodes moved
    # validation (train=False) reads the sample itself: the Gaussian NLL of the estimate on it
    mean, log_var, _ = model.estimate(graph)
    label = model.material_normalizer(val_batch.material[:, None])[:, 0]
    torch.testing.assert_close(model.auxiliary_loss(graph, val_batch, 0, train=False),
                               (0.5 * (log_var + (label - mean).square() * torch.exp(-log_var))).mean())
    torch.manual_seed(0)
    noisy = model.auxiliary_loss(graph, val_batch, 0, train=True)
    assert torch.isfinite(noisy) and not torch.allclose(noisy, model.auxiliary_loss(graph, val_batch, 0))
    assert make(GGNSID).estimator_graph(graph, val_batch, 0) is graph  # off by default
    trainer.save_checkpoint(tmp_path / "id.ckpt")
    loaded = GGNSID.load_from_checkpoint(tmp_path / "id.ckpt", weights_only=True).eval()
    assert loaded.estimator_noise == TrainingNoise(std=0.0, field_std=0.05, field_mixture=True)
    # a checkpoint of before the component (`estimator_noise_std`) loads as the noise it was: the model's
    # wavelength, mixed scales
    hparams = dict(torch.load(tmp_path / "id.ckpt", weights_only=True)["hyper_parameters"])
    hparams.pop("estimator_noise")
    assert TrainingNoise.of(upgrade_hparams({**hparams, "estimator_noise_std": 0.05})["estimator_noise"]) == \
        loaded.estimator_noise
    positions, _ = rollout(loaded.step, val_batch, EveryK(2), loaded.connectivity)
    assert torch.isfinite(positions).all()
    with pytest.raises(ValueError, match="field_std >= 0"):
        make(GGNSID, estimator_noise={"field_std": -0.1})


@pytest.mark.parametrize("cls", [GGNS, GGNSID, GGNSLSTM, MGNM])
def test_components_are_saved_as_plain_values_and_come_back(cls, tmp_path):
    """A model given its parts as objects (`TrainingNoise`, `LRSchedule`, as LightningCLI gives them) writes a
    checkpoint that reads as data (no class in it) and loads with the same parts and processor."""
    from ggns.checkpoints import read_checkpoint
    from conftest import save_untrained

    noise, schedule = TrainingNoise(std=0.02, field_std=0.01), LRSchedule(lr=1e-3, decay_rate=0.5, decay_steps=10)
    model = make(cls, noise=noise, lr_schedule=schedule, processor="per_type")
    checkpoint = read_checkpoint(save_untrained(model, tmp_path / "model.ckpt"))
    assert checkpoint["hyper_parameters"]["noise"] == dataclasses.asdict(noise)
    assert checkpoint["hyper_parameters"]["lr_schedule"] == dataclasses.asdict(schedule)
    loaded = load_simulator(tmp_path / "model.ckpt")
    assert (type(loaded), loaded.noise, loaded.lr_schedule, loaded.processor) == (cls, noise, schedule, "per_type")
