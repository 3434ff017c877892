"""The step that never waits, on the CPU: the static neighbour search against torch-cluster, the whole static
rollout step and training step against the eager ones, zero host reads, `fullgraph` compilation, capacity
growth, the checks' errors, and a Lightning fit and test with both static steps in one process."""
from __future__ import annotations

import copy
import warnings

import pytest
import pytorch_lightning as pl
import torch

from ggns import phases
from ggns.batch import TrajectoryBatch
from ggns.bench.step_profile import HostReads
from ggns.checks import gpu_code_paths
from ggns.data.module import SimulationDataModule, WindowDataset, collate
from ggns.evaluation.capture import StaticStep
from ggns.evaluation.rollout import RolloutError, one_step_predictions, rollout
from ggns.evaluation.schedules import EveryK, Never, parse_schedule
from ggns.graphs import search
from ggns.graphs.search import compact, static_knn, static_radius
from ggns.callbacks import TestEvaluation
from ggns.models.simulators import GGNS, GGNSID, GGNSLSTM, MGN, MGNM
from ggns.callbacks import StaticRollouts, StaticTraining
from ggns.models.static_training import StaticTrainStep, bucket, capturable_optimizer

from conftest import TINY12, eager_losses, make

torch_cluster = pytest.importorskip("torch_cluster")


def pairs(index: torch.Tensor) -> set:
    return set(map(tuple, index.T.tolist()))


def clouds(seed: int, dim: int = 3, graphs: int = 4):
    generator = torch.Generator().manual_seed(seed)
    nx = torch.randint(1, 40, (graphs,), generator=generator)
    ny = torch.randint(0, 30, (graphs,), generator=generator)
    bx = torch.repeat_interleave(torch.arange(graphs), nx)
    by = torch.repeat_interleave(torch.arange(graphs), ny)
    return torch.rand(len(bx), dim, generator=generator), torch.rand(len(by), dim, generator=generator), bx, by, nx


# ---- the static neighbour search -------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(6))
def test_the_static_radius_finds_torch_clusters_pairs_when_no_node_exceeds_the_cap(seed):
    x, y, bx, by, nx = clouds(seed, dim=2 + seed % 2)
    graphs, span = 4, int(nx.max())
    reference = torch_cluster.radius(x, y, 0.3, bx, by, max_num_neighbors=100)  # [query, source]
    found = static_radius(x, y, 0.3, bx, by, graphs, 100, span)
    assert found.index.shape == found.mask.shape == (len(y), min(100, span))
    edges, mask, needed = compact(found, 4096)
    assert int(needed) == reference.size(1) == int(mask.sum()) > 0
    assert pairs(edges[:, mask].flip(0)) == pairs(reference)
    assert torch.equal(found.count, torch.bincount(reference[0], minlength=len(y)))
    # the same graph against itself, without self loops, as radius_graph
    self_found = static_radius(x, x, 0.3, bx, bx, graphs, 100, span, exclude_self=True)
    edges, mask, _ = compact(self_found, 8192)
    assert pairs(edges[:, mask]) == pairs(torch_cluster.radius_graph(x, 0.3, bx, max_num_neighbors=100))
    # the dispatcher's static path gives the same as torch-cluster's
    assert pairs(search.radius(x, y, 0.3, bx, by, 100, graphs, search="static")) == pairs(reference)


def test_over_the_cap_the_nearest_are_kept_and_the_true_count_reported():
    x = torch.tensor([[0.0], [0.1], [0.2], [0.3], [0.45], [5.0]])
    y = torch.tensor([[0.0], [5.0]])
    zeros = (lambda n: torch.zeros(n, dtype=torch.long))
    found = static_radius(x, y, 0.5, zeros(6), zeros(2), 1, 2, 6)
    assert found.count.tolist() == [5, 1]  # 5 within 0.5 of the first query, more than the cap of 2
    assert found.index[0].tolist() == [0, 1] and found.mask[0].all()  # the two nearest, nearest first
    assert found.index[1, :1].tolist() == [5] and found.mask[1].tolist() == [True, False]
    edges, mask, needed = compact(found, 2)  # a capacity smaller than the pairs: needed says so
    assert int(needed) == 3 and mask.all() and edges.tolist() == [[0, 1], [0, 0]]


def test_padding_rows_excluded_pairs_and_knn():
    x, y, bx, by, nx = clouds(7)
    padded_x = torch.cat([x, torch.zeros(5, 3)])
    padded_bx = torch.cat([bx, torch.full((5,), 4)])  # rows of graph B = 4: padding
    padded_y = torch.cat([y, torch.zeros(3, 3)])
    padded_by = torch.cat([by, torch.full((3,), 4)])
    found = static_radius(padded_x, padded_y, 0.3, padded_bx, padded_by, 4, 64, int(nx.max()))
    edges, mask, _ = compact(found, 4096)
    reference = torch_cluster.radius(x, y, 0.3, bx, by, max_num_neighbors=64)
    assert pairs(edges[:, mask].flip(0)) == pairs(reference)
    excluded = reference[:, ::2].flip(0)  # (source, query) pairs to leave out
    kept = static_radius(x, y, 0.3, bx, by, 4, 64, int(nx.max()), exclude=excluded)
    edges, mask, _ = compact(kept, 4096)
    assert pairs(edges[:, mask]) == pairs(reference.flip(0)) - pairs(excluded)
    assert torch.equal(kept.count, found.count[:len(y)])  # excluded pairs still count toward the cap
    nearest = static_knn(x, y, 3, bx, by, 4, int(nx.max()))
    edges, mask, _ = compact(nearest, 4096)
    assert pairs(edges[:, mask].flip(0)) == pairs(torch_cluster.knn(x, y, 3, bx, by))
    assert pairs(search.knn(x, y, 3, bx, by, search="static")) == pairs(torch_cluster.knn(x, y, 3, bx, by))


def test_capacity_buckets_pad_at_most_an_eighth():
    sizes = range(1, 5000)
    assert all(n <= bucket(n) <= max(8, n * 9 // 8 + 1) for n in sizes)
    assert len({bucket(n) for n in range(513, 1025)}) == 8  # 576, 640, ..., 1024


# ---- the whole static rollout step -----------------------------------------------------------------------
def fitted(cls, trajs, **kwargs):
    model = make(cls, **kwargs)
    model.fit_normalizers([collate([trajs["train"][0].steps(0, 2), trajs["train"][1].steps(2, 4)])])
    return model


@pytest.mark.parametrize("cls", [GGNS, MGNM, GGNSLSTM], ids=lambda c: c.__name__)  # MGNM: world edges, material
def test_the_static_rollout_equals_the_eager_one(cls, trajs, val_batch):
    model = fitted(cls, trajs).eval()
    step = StaticStep(model, capture=False)
    for schedule in ({GGNS: ["every:1", "every:3", "never"], GGNSLSTM: ["every:3"]}.get(cls, ["never"])):
        plan = parse_schedule(schedule)
        eager, eager_state = rollout(model.step, val_batch, plan, model.connectivity, model.with_material)
        static, static_state = rollout(step, val_batch, plan, model.connectivity, model.with_material)
        torch.testing.assert_close(static, eager, rtol=1e-5, atol=1e-6)
        if cls is GGNSLSTM:
            torch.testing.assert_close(static_state[0], eager_state[0], rtol=1e-5, atol=1e-6)
    assert step.recordings == 1  # capacities measured on the batch's true states held every rollout here
    torch.testing.assert_close(one_step_predictions(step, val_batch, EveryK(1), model.connectivity, model.with_material),
                               one_step_predictions(model.step, val_batch, EveryK(1), model.connectivity,
                                                    model.with_material), rtol=1e-5, atol=1e-6)


def test_the_static_step_keeps_its_most_recently_used_shapes(trajs, monkeypatch):
    """With room for two batch shapes, shapes used A, B, A, C keep A and C (least recently used dropped), not B
    and C (the oldest dropped), and a kept shape's buffers are used again."""
    from ggns.evaluation import capture

    monkeypatch.setattr(capture, "SLOTS", 2)
    model = fitted(MGN, trajs).eval()
    step = StaticStep(model, capture=False)
    shapes = [TrajectoryBatch.from_trajectories(trajs["val"][:1]), TrajectoryBatch.from_trajectories(trajs["val"][:2]),
              TrajectoryBatch.from_trajectories(trajs["train"][:3])]

    def use(batch):
        rollout(step, batch, Never(), model.connectivity, steps=2)
        return step._slot

    a, b = use(shapes[0]), use(shapes[1])
    assert a is not b and use(shapes[0]) is a
    c = use(shapes[2])
    kept = list(step._slots.values())
    assert len(kept) == 2 and any(s is a for s in kept) and any(s is c for s in kept) and not any(s is b for s in kept)


def test_a_static_rollout_from_a_later_start_with_state_equals_the_eager_one(trajs, val_batch):
    model = fitted(GGNSLSTM, trajs).eval()
    step = StaticStep(model, capture=False)
    _, state = rollout(model.step, val_batch, EveryK(1), model.connectivity, steps=2)
    start = val_batch.positions[2] + 0.001
    eager, _ = rollout(model.step, val_batch, Never(), model.connectivity, start_positions=start, start=2, steps=4,
                       state=state)
    static, _ = rollout(step, val_batch, Never(), model.connectivity, start_positions=start, start=2, steps=4,
                        state=state)
    torch.testing.assert_close(static, eager, rtol=1e-5, atol=1e-6)


def test_evaluation_with_static_rollouts_gives_the_eager_metrics(trajs, cli_data):
    from ggns.data.schema import read_trajectories

    val_batch = TrajectoryBatch.from_trajectories(read_trajectories(cli_data / "val.h5"))  # T = 12: m+10 defined
    model = fitted(GGNS, trajs).eval()
    model.static_rollouts = True
    assert isinstance(model.rollout_step(), StaticStep) and model.rollout_step() is model.rollout_step()
    static = model.evaluate(val_batch, ["every:2", "never"], iou=False, m_plus_10_stride=2)
    model.static_rollouts = False
    eager = model.evaluate(val_batch, ["every:2", "never"], iou=False, m_plus_10_stride=2)
    assert "m10_mse" in eager and eager.keys() == static.keys()
    for key, value in eager.items():
        torch.testing.assert_close(static[key], value, rtol=1e-4, atol=1e-9, msg=key)


def test_capacities_that_are_too_small_grow_and_the_steps_are_taken_again(trajs, val_batch):
    model = fitted(GGNS, trajs).eval()
    eager, _ = rollout(model.step, val_batch, EveryK(1), model.connectivity)
    step = StaticStep(model, capture=False)
    rollout(step, val_batch, EveryK(1), model.connectivity)
    step.set_capacities({t: 8 for t in step.layout.edges})
    before = step.recordings
    static, _ = rollout(step, val_batch, EveryK(1), model.connectivity, check_every=3)
    torch.testing.assert_close(static, eager, rtol=1e-5, atol=1e-6)
    assert step.recordings > before and all(c > 8 for c in step.layout.edges.values())


def test_the_static_step_reads_nothing_and_a_read_added_to_it_is_seen(trajs, val_batch):
    model = fitted(GGNS, trajs).eval()
    step = StaticStep(model, capture=False)
    rollout(step, val_batch, EveryK(1), model.connectivity)  # prepared: buffers for this batch

    def count(function) -> dict:
        reads = HostReads()
        step.buffers.t.fill_(0)
        with phases.recording(), gpu_code_paths(), reads, torch.no_grad():
            for _ in range(3):
                function(step.buffers)
        return {name: n for (_, _, name), n in reads.counts.items()}

    assert count(step.step_function) == {}

    def with_a_read(buffers):
        step.step_function(buffers)
        if buffers.pos.abs().max() > 1e9:  # a read a careless edit might add
            raise AssertionError

    assert count(with_a_read) == {"__bool__": 3}
    # the eager step of the same model reads in every radius query: the counter sees them too
    reads = HostReads()
    with phases.recording(), gpu_code_paths(), reads, torch.no_grad():
        rollout(model.step, val_batch, EveryK(1), model.connectivity, steps=1, check_every=10)
    assert sum(n for (_, _, name), n in reads.counts.items() if name == "radius") == 5


def test_the_whole_static_rollout_step_compiles_as_one_graph(trajs, val_batch):
    """fullgraph=True fails on any graph break, dynamic=False on any data-dependent shape; the eager backend
    traces what inductor would compile without its compile time. MGN(M): world edges, the per-type processor."""
    model = fitted(MGNM, trajs).eval()
    plan = EveryK(1) if model.uses_points else Never()
    eager, _ = rollout(model.step, val_batch, plan, model.connectivity, model.with_material)
    step = StaticStep(model, compile=True, compile_options={"backend": "eager"})
    compiled, _ = rollout(step, val_batch, plan, model.connectivity, model.with_material)
    torch.testing.assert_close(compiled, eager, rtol=1e-5, atol=1e-6)


def test_the_static_step_errors_name_the_step_as_the_eager_ones(trajs, val_batch):
    model = fitted(GGNS, trajs).eval()
    step = StaticStep(model, capture=False)
    tight = copy.deepcopy(model)
    tight.connectivity = type(model.connectivity)(**{**vars(model.connectivity), "max_num_neighbors": 2})
    with pytest.raises(ValueError, match=r"at step 0: \w+ node \d+ has more than max_num_neighbors=2"):
        rollout(StaticStep(tight, capture=False), val_batch, EveryK(1), tight.connectivity, check_every=4)
    with torch.no_grad():
        model.core.decoder[-1].bias.fill_(float("nan"))
    with pytest.raises(RolloutError, match=r"diverged at prediction step 0 .*non-finite positions"):
        rollout(step, val_batch, EveryK(1), model.connectivity, check_every=4)


def test_a_static_rollout_in_inference_mode_leaves_buffers_a_later_rollout_can_use(trajs, val_batch):
    """Lightning tests in inference mode; a later evaluation of the same model outside it updates the same
    buffers (inference tensors would refuse that)."""
    model = fitted(GGNS, trajs).eval()
    step = StaticStep(model, capture=False)
    with torch.inference_mode():
        inside, _ = rollout(step, val_batch, EveryK(2), model.connectivity)
    outside, _ = rollout(step, val_batch, EveryK(2), model.connectivity)
    torch.testing.assert_close(outside, inside)


def test_the_recorded_step_is_dropped_on_reload_move_and_cast(trajs):
    model = fitted(GGNS, trajs).eval()
    model.static_rollouts = True
    first = model.rollout_step()
    model.load_state_dict(model.state_dict())
    second = model.rollout_step()
    assert second is not first
    model.to("cpu")
    assert model.rollout_step() is not second
    with pytest.raises(ValueError, match="GGNSID.*static step"):
        StaticStep(make(GGNSID))
    with pytest.raises(ValueError, match="capture needs the model on a CUDA device"):
        StaticStep(make(GGNS), capture=True)


def test_autocast_and_matmul_precision_are_part_of_the_recording(trajs, val_batch):
    model = fitted(GGNS, trajs).eval()
    step = StaticStep(model, capture=False)
    rollout(step, val_batch, Never(), model.connectivity, steps=2)
    recorded = step.recordings
    with torch.autocast("cpu", dtype=torch.bfloat16):
        rollout(step, val_batch, Never(), model.connectivity, steps=2)
    assert step.recordings == recorded + 1
    rollout(step, val_batch, Never(), model.connectivity, steps=2)
    assert step.recordings == recorded + 2


# ---- the whole static training step ----------------------------------------------------------------------
def windows(trajs, model, count: int) -> list[TrajectoryBatch]:
    data = WindowDataset(trajs["train"], model.window)
    return [collate([data[(3 * i + j) % len(data)] for j in range(2 + i % 2)]) for i in range(count)]


@pytest.mark.parametrize("cls, optimizer, steps", [(GGNS, "adam", 50), (GGNSLSTM, "adam", 6), (MGNM, "sgd", 30)],
                         ids=["GGNS", "GGNSLSTM", "MGNM"])
def test_fifty_static_training_steps_equal_the_eager_ones(cls, optimizer, steps, trajs):
    """Losses and weights of 50 steps (GGNS+LSTM: 6 windows of 5 transitions; MGN(M): 30), batches of two sizes (two
    layouts), no noise (the eager step draws it on fewer rows). MGN's per-type MLPs of an edge type absent from a batch get no gradient in the eager step
    and a zero one in the static step, which Adam's momentum still moves: compared under SGD."""
    model = make(cls, noise={"std": 0.0})
    batches = windows(trajs, model, steps)
    model.fit_normalizers(batches[:1])
    twin = copy.deepcopy(model)
    make_optimizer = (lambda m: m.configure_optimizers()["optimizer"]) if optimizer == "adam" else \
        (lambda m: torch.optim.SGD(m.parameters(), lr=1e-3))
    eager_optimizer, static_optimizer = make_optimizer(model), make_optimizer(twin)
    step = StaticTrainStep(twin, margin=4.0)
    eager = eager_losses(model, eager_optimizer, batches)
    torch.manual_seed(1)
    static = []
    for batch in batches:
        static.append(step.step(batch, static_optimizer).item())
        step.read_capacities()
    assert step.skipped == 0
    torch.testing.assert_close(torch.tensor(static), torch.tensor(eager), rtol=1e-5, atol=1e-7)
    for (name, a), b in zip(model.named_parameters(), twin.parameters()):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-6, msg=name)


def test_a_decaying_lr_reaches_the_static_step_through_the_tensor_the_recording_reads(trajs):
    """The optimizer a recorded step needs (capturable, lr a tensor on the device) under a schedule that decays
    every 3 steps: the schedule updates that one tensor in place (a recording reads it, a float would be frozen
    into it), its values are the schedule's, and the losses equal the eager steps' under the same schedule."""
    schedule = {"lr": 1e-3, "decay_rate": 0.1, "decay_steps": 3, "final": 1e-5}
    model = make(GGNS, noise={"std": 0.0}, lr_schedule=schedule)
    batches = windows(trajs, model, 12)
    model.fit_normalizers(batches[:1])
    twin = copy.deepcopy(model)
    eager_config, static_config = model.configure_optimizers(), twin.configure_optimizers()
    eager_optimizer, eager_scheduler = eager_config["optimizer"], eager_config["lr_scheduler"]["scheduler"]
    static_optimizer, static_scheduler = static_config["optimizer"], static_config["lr_scheduler"]["scheduler"]
    capturable_optimizer(static_optimizer, torch.device("cpu"))
    lr = static_optimizer.param_groups[0]["lr"]
    assert isinstance(lr, torch.Tensor) and float(lr) == pytest.approx(1e-3)
    torch.manual_seed(1)
    eager = []
    for batch in batches:
        eager_optimizer.zero_grad()
        loss = model.window_loss(batch)
        loss.backward()
        eager_optimizer.step()
        eager_scheduler.step()
        eager.append(loss.item())
    step = StaticTrainStep(twin, margin=4.0)
    torch.manual_seed(1)
    static = []
    for n, batch in enumerate(batches):
        static.append(step.step(batch, static_optimizer).item())
        step.read_capacities()
        static_scheduler.step()
        assert static_optimizer.param_groups[0]["lr"] is lr  # updated in place, not replaced
        assert float(lr) == pytest.approx(twin.lr_schedule.at(n + 1), rel=1e-6)
    assert float(lr) < 1e-4  # it did decay (to the floor's neighbourhood)
    assert float(lr) == pytest.approx(eager_optimizer.param_groups[0]["lr"], rel=1e-6)
    assert step.skipped == 0
    torch.testing.assert_close(torch.tensor(static), torch.tensor(eager), rtol=1e-5, atol=1e-7)


def test_the_static_training_step_reads_nothing_and_compiles_with_its_backward(trajs):
    model = make(GGNS, latent=8, blocks=1)  # the smallest program that has every part (compile time grows with it)
    batches = windows(trajs, model, 3)
    model.fit_normalizers(batches[:1])
    optimizer = model.configure_optimizers()["optimizer"]
    step = StaticTrainStep(model, margin=4.0)
    step.step(batches[0], optimizer)  # the layout of this batch size
    reads = HostReads()
    with phases.recording(), gpu_code_paths(), reads:
        step.step(batches[2], optimizer)  # the same size: prepare, forward, backward, Adam, the checks recorded
    assert dict(reads.counts) == {}
    eager = HostReads()  # the counter, in the same harness, sees the eager step's reads
    with phases.recording(), gpu_code_paths(), eager:
        model.window_loss(batches[2]).backward()
    assert {name for _, _, name in eager.counts} == {"radius"}
    buffers = step.prepare(batches[2])
    expected = step.loss_function(buffers, train=False)
    compiled = torch.compile(step.loss_function, fullgraph=True, dynamic=False, backend="aot_eager")
    loss = compiled(buffers, train=False)
    loss.backward()  # the backward graph is traced too (aot_eager)
    torch.testing.assert_close(loss, expected, rtol=1e-5, atol=1e-7)


def test_a_step_that_needed_more_edges_is_skipped_and_reported(trajs):
    model = make(GGNS, point_probability=1.0)  # every window with its points: the same pairs at every try
    batches = windows(trajs, model, 3)
    model.fit_normalizers(batches[:1])
    optimizer = model.configure_optimizers()["optimizer"]
    step = StaticTrainStep(model)
    step.step(batches[0], optimizer)
    step.read_capacities()
    step.set_capacities({t: 8 for t in step.layout.edges})
    before = [p.detach().clone() for p in model.parameters()]
    step.step(batches[2], optimizer)
    assert all(torch.equal(a, b) for a, b in zip(before, model.parameters()))  # skipped by the fused Adam
    with pytest.warns(UserWarning, match=r"1 step\(s\) since the last read needed more edges"):
        step.read_capacities()
    assert step.skipped == 1 and all(c > 8 for c in step.layout.edges.values())
    step.step(batches[2], optimizer)
    assert not all(torch.equal(a, b) for a, b in zip(before, model.parameters()))


def test_a_fit_then_a_test_in_one_process_with_static_steps_workers_and_bf16(cli_data, tmp_path):
    """Lightning stays the loop: the static training step under manual optimization (steps counted,
    checkpoints, the lr schedule), then a test with static rollouts, data-loader workers, bf16 autocast."""
    data = SimulationDataModule(str(cli_data / TINY12), batch_size=2, generate_missing=False, num_workers=1,
                                eval_batch_size=2)
    # the statistics pass over every training batch: the static step's edge capacities start from its graphs
    model = make(GGNS)
    evaluation = TestEvaluation(schedules=("every:1", "never"), iou=False, m_plus_10=False)
    trainer = pl.Trainer(max_steps=4, logger=False, enable_progress_bar=False, enable_model_summary=False,
                         limit_val_batches=0, log_every_n_steps=2, accelerator="cpu", precision="bf16-mixed",
                         callbacks=[StaticTraining(), StaticRollouts(), evaluation], default_root_dir=tmp_path)
    used = []

    class Used(pl.Callback):
        def on_train_batch_end(self, trainer, module, *args):
            used.append(module._static_train is not None and module._static_train.buffers is not None)

    trainer.callbacks.append(Used())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trainer.fit(model, data)
        assert trainer.global_step == 4 and used == [True] * 4
        assert model.lr_schedulers().last_epoch == 4
        optimizer = model.optimizers().optimizer
        assert all(int(state["step"]) == 4 for state in optimizer.state.values())  # 4 Adam steps, none skipped
        trainer.test(model, data)
    assert isinstance(model.rollout_step(), StaticStep)
    assert set(evaluation.results) >= {"rollout_mse_k1", "rollout_mse_never"}
    assert all(torch.isfinite(torch.tensor(s["mean"])) for s in evaluation.results.values())


def test_the_eager_builder_works_without_torch_cluster(trajs, val_batch, monkeypatch):
    """The connectivity's search: "static" gives torch-cluster's graphs; "auto" takes it where torch-cluster
    is not installed (PyG 2.8 no longer needs it), and "cluster" then names what is missing."""
    import dataclasses

    from ggns.graphs.state import state_graph

    model = fitted(MGNM, trajs).eval()
    static = dataclasses.replace(model.connectivity, search="static")
    for t in (0, 4):
        reference = state_graph(val_batch, t, val_batch.positions[t], False, model.connectivity, True)
        graph = state_graph(val_batch, t, val_batch.positions[t], False, static, True)
        assert set(graph.edge_types) == set(reference.edge_types)
        for edge_type in reference.edge_types:
            assert pairs(graph[edge_type].edge_index) == pairs(reference[edge_type].edge_index), edge_type
    eager, _ = rollout(model.step, val_batch, Never(), model.connectivity, True)
    monkeypatch.setattr(search, "torch_cluster", None)
    without, _ = rollout(model.step, val_batch, Never(), model.connectivity, True)
    torch.testing.assert_close(without, eager, rtol=1e-5, atol=1e-6)
    with pytest.raises(ImportError, match="needs torch-cluster, which is not installed"):
        rollout(model.step, val_batch, Never(), dataclasses.replace(model.connectivity, search="cluster"), True)
    with pytest.raises(ValueError, match="search must be one of"):
        dataclasses.replace(model.connectivity, search="fast")
