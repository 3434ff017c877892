"""The CUDA paths: graphs, every simulator, training and the command line on a GPU give what they give on
the CPU. Skipped where torch sees no GPU (this project's CI); run on a GPU machine by scripts/gpu_check.sh,
which writes what it saw to docs/results/gpu_check/. Data: the `cli_data` fixture (plate_tiny, T = 12),
copied from GGNS_TEST_DATA where the machine has no open3d to raycast it.

Tolerances: message passing sums with atomic adds on a GPU (`index_add_`), in another order than the
CPU's, so float32 results agree to rounding, not bit for bit (docs/robustness.md); rollouts compound it."""
from __future__ import annotations

import copy
import json
import math
import sys

import pytest
import torch

from ggns.batch import TrajectoryBatch
from ggns.checkpoints import read_checkpoint
from ggns.config import CONF_DIR
from ggns.data.generate import split_path
from ggns.data.module import WindowDataset, collate
from ggns.data.schema import read_trajectories
from ggns.evaluation.schedules import EveryK, Never
from ggns.graphs.state import state_graph
from ggns.callbacks import TestEvaluation
from ggns.models.simulators import GGNS, GGNSID, GGNSLSTM, GGNSM, MGN, MGNM, MGNShared
from ggns.models.loading import load_simulator
from conftest import TINY12, eager_losses, make

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (scripts/gpu_check.sh)")

ALL_MODELS = (GGNS, GGNSLSTM, MGN, MGNM, MGNShared, GGNSM, GGNSID)
CUDA = torch.device("cuda")


@pytest.fixture(scope="module")
def splits(cli_data):
    return {split: read_trajectories(split_path(cli_data, split)) for split in ("train", "val", "test")}


def edges(graph) -> dict:
    """{edge type: sorted (source, target) pairs on the CPU}."""
    out = {}
    for edge_type in graph.edge_types:
        index = graph[edge_type].edge_index.cpu()
        order = torch.argsort(index[0] * (index.max() + 1) + index[1])
        out[edge_type] = index[:, order]
    return out


@pytest.mark.parametrize("cls", [GGNS, MGNM])
@pytest.mark.parametrize("use_points", [True, False])
def test_state_graphs_on_cuda_hold_the_cpu_edges_and_features(cls, use_points, splits):
    model = make(cls)
    cpu = TrajectoryBatch.from_trajectories(splits["val"])
    gpu = TrajectoryBatch.from_trajectories(splits["val"], device=CUDA)
    use = use_points and model.uses_points
    for t in range(cpu.num_steps - 1):
        a = state_graph(cpu, t, cpu.positions[t], use, model.connectivity, model.with_material)
        b = state_graph(gpu, t, gpu.positions[t], use, model.connectivity, model.with_material)
        assert a.node_types == b.node_types and a.edge_types == b.edge_types
        ea, eb = edges(a), edges(b)
        for edge_type in ea:  # radius search on the GPU: the same neighbours
            assert torch.equal(ea[edge_type], eb[edge_type]), (t, edge_type)
        for node_type in a.node_types:
            assert b[node_type].x.device.type == "cuda"
            torch.testing.assert_close(b[node_type].x.cpu(), a[node_type].x, atol=1e-6, rtol=0)


@pytest.mark.parametrize("cls", ALL_MODELS, ids=lambda c: c.__name__)
def test_every_simulator_trains_and_rolls_out_on_cuda_as_on_cpu(cls, splits):
    torch.manual_seed(0)
    model = make(cls, latent=32, blocks=2, noise=dict(field_std=0.01))  # the CPU presets' smooth field too
    windows = WindowDataset(splits["train"], model.window)
    batch = collate([windows[i] for i in range(min(8, len(windows)))])
    model.fit_normalizers([batch])
    gpu_model = copy.deepcopy(model).to(CUDA)
    gpu_batch = batch.to(CUDA)
    with torch.no_grad():  # the loss of the same window, without training noise
        cpu_loss, gpu_loss = model.window_loss(batch, train=False), gpu_model.window_loss(gpu_batch, train=False)
    assert math.isclose(gpu_loss.item(), cpu_loss.item(), rel_tol=1e-4), (cpu_loss, gpu_loss)

    # training on the GPU: noise (the field too, for the GGNS family), backward, Adam; all on the device
    # the parameters a training loss reaches on the CPU (a model of several node types may leave some unused)
    twin = copy.deepcopy(model)
    twin.window_loss(batch, train=True).backward()
    reached = {n for n, p in twin.named_parameters() if p.grad is not None}
    assert reached, "no gradient reached any parameter on the CPU"
    optimizer = gpu_model.configure_optimizers()["optimizer"]
    for _ in range(3):
        optimizer.zero_grad()
        loss = gpu_model.window_loss(gpu_batch, train=True)
        loss.backward()
        assert torch.isfinite(loss) and loss.device.type == "cuda"
        grads = {n: p.grad for n, p in gpu_model.named_parameters() if p.grad is not None}
        assert set(grads) == reached, set(grads) ^ reached
        assert all(g.device.type == "cuda" and torch.isfinite(g).all() for g in grads.values())
        optimizer.step()

    # the paper's metrics of the same weights on both devices
    trained = copy.deepcopy(gpu_model).cpu()
    val = TrajectoryBatch.from_trajectories(splits["val"])
    kwargs = dict(iou=False, m_plus_10_stride=5)
    with torch.no_grad():
        on_cpu = trained.evaluate(val, [EveryK(1), EveryK(5), Never()], **kwargs)
        on_gpu = gpu_model.evaluate(val.to(CUDA), [EveryK(1), EveryK(5), Never()], **kwargs)
    assert set(on_cpu) == set(on_gpu)
    for name, value in on_cpu.items():
        assert torch.isfinite(value).all(), name
        torch.testing.assert_close(on_gpu[name].cpu(), value, rtol=1e-3, atol=1e-9, msg=name)


def cli(config: str, data_dir, logs, version: str, *extra) -> list[str]:
    return ["--config", str(CONF_DIR / "plate" / f"{config}.yaml"), "--data.dataset", str(data_dir / TINY12),
            "--data.data_dir", str(data_dir), "--data.batch_size", "8", "--data.generate_missing", "false",
            "--trainer.logger.init_args.save_dir", str(logs), "--trainer.logger.init_args.version", version,
            "--model.init_args.latent", "16", "--model.init_args.blocks", "2",
            "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false", *extra]


@pytest.mark.parametrize("config", ["ggns", "mgn_m"])
def test_fit_on_the_gpu_and_test_on_both_devices(config, cli_data, tmp_path):
    """`fit` on the GPU (validation rollouts, checkpoints per metric family), then `test` of its last
    checkpoint on the GPU and on the CPU: the same paper metrics; the checkpoint is data a CPU reads."""
    from ggns.__main__ import main

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, "argv", ["ggns"])
        main(["fit", *cli(config, cli_data, tmp_path, "fit", "--trainer.accelerator", "gpu", "--trainer.devices", "1",
                          "--trainer.max_epochs", "2", "--trainer.limit_train_batches", "2",
                          "--trainer.check_val_every_n_epoch", "1", "--trainer.limit_val_batches", "1")])
        last = tmp_path / config / "fit" / "checkpoints" / "last.ckpt"
        checkpoint = read_checkpoint(last)  # weights_only, on the CPU
        assert checkpoint["global_step"] == 4
        assert all(t.device.type == "cpu" for t in checkpoint["state_dict"].values())
        metrics = {}
        for accelerator in ("gpu", "cpu"):
            main(["test", *cli(config, cli_data, tmp_path, f"test_{accelerator}", "--trainer.accelerator", accelerator,
                               "--trainer.devices", "1", "--ckpt_path", str(last))])
            text = (tmp_path / config / f"test_{accelerator}" / "test_metrics.json").read_text()
            metrics[accelerator] = {k: v["mean"] for k, v in json.loads(text).items()
                                    if isinstance(v, dict) and "mean" in v and "seconds" not in k}
    assert metrics["gpu"].keys() == metrics["cpu"].keys() and "rollout_mse_never" in metrics["cpu"]
    for name, value in metrics["cpu"].items():
        assert math.isclose(metrics["gpu"][name], value, rel_tol=1e-3, abs_tol=1e-9), (name, value, metrics["gpu"][name])
    model = load_simulator(last, map_location="cuda")
    assert next(model.parameters()).device.type == "cuda"


# ---- the hot path on the GPU (tests/test_hotpath.py on the CPU) ------------------------------------------
def _fitted(cls, splits, **kwargs):
    torch.manual_seed(0)
    model = make(cls, latent=32, blocks=2, **kwargs)
    model.fit_normalizers([collate([splits["train"][0].steps(0, 2), splits["train"][1].steps(3, 5)])])
    return model.to(CUDA)


@pytest.mark.parametrize("cls", [GGNS, MGNM, GGNSLSTM], ids=lambda c: c.__name__)
def test_the_captured_whole_step_replays_the_eager_rollouts_without_a_synchronization(cls, splits):
    """The whole rollout step (graph, model, integration, checks) as one CUDA graph: the eager rollouts, one
    recording, no synchronization inside the steps (the checks are read once at the end)."""
    from ggns.evaluation.capture import StaticStep
    from ggns.evaluation.rollout import rollout

    model = _fitted(cls, splits).eval()
    val = TrajectoryBatch.from_trajectories(splits["val"], device=CUDA)
    step = StaticStep(model)
    assert step.capture
    for schedule in ([EveryK(1), EveryK(3), Never()] if model.uses_points else [Never()]):
        eager, _ = rollout(model.step, val, schedule, model.connectivity, model.with_material)
        replayed, _ = rollout(step, val, schedule, model.connectivity, model.with_material)
        torch.testing.assert_close(replayed, eager, rtol=1e-4, atol=1e-6)
    assert step.recordings <= 2  # once, and again only if a rollout outgrew the capacities measured on the truth
    step.buffers.t.fill_(0)
    assert _syncs(lambda: [step._run() for _ in range(5)]) == 0


def test_the_recorded_step_survives_weight_updates_reloads_moves_and_autocast(splits):
    """Replays read the live weights (an update between replays shows), a reload or a move drops the
    recording (the normalizers' masks are made anew), autocast records anew with its cache off."""
    from ggns.evaluation.capture import StaticStep
    from ggns.evaluation.rollout import rollout

    model = _fitted(GGNS, splits).eval()
    model.static_rollouts = True
    val = TrajectoryBatch.from_trajectories(splits["val"], device=CUDA)
    step = model.rollout_step()
    rollout(step, val, EveryK(1), model.connectivity)
    with torch.no_grad():
        model.core.decoder[-1].bias.add_(0.01)
    eager, _ = rollout(model.step, val, EveryK(1), model.connectivity)
    torch.testing.assert_close(rollout(step, val, EveryK(1), model.connectivity)[0], eager, rtol=1e-4, atol=1e-6)
    model.load_state_dict(copy.deepcopy(model.state_dict()))
    reloaded = model.rollout_step()
    assert reloaded is not step
    torch.testing.assert_close(rollout(reloaded, val, EveryK(1), model.connectivity)[0], eager, rtol=1e-4, atol=1e-6)
    with torch.autocast("cuda", dtype=torch.bfloat16):
        cast, _ = rollout(reloaded, val, EveryK(1), model.connectivity)
        again, _ = rollout(reloaded, val, EveryK(1), model.connectivity)
    assert reloaded.recordings == 2  # float32, then bf16: recorded anew
    torch.testing.assert_close(again, cast, rtol=1e-3, atol=1e-5)  # the second replays read no freed cache
    torch.testing.assert_close(cast, eager, rtol=0.1, atol=1e-3)


@pytest.mark.parametrize("cls", [GGNS, GGNSLSTM], ids=lambda c: c.__name__)
def test_the_captured_training_step_equals_the_eager_one(cls, splits):
    """Forward, backward and the fused Adam as one CUDA graph: 20 steps give the eager step's losses and
    weights (no noise: the eager step draws it on fewer rows), without a synchronization per step."""
    from ggns.models.static_training import StaticTrainStep

    model = _fitted(cls, splits, noise={"std": 0.0})
    data = WindowDataset(splits["train"], model.window)
    batches = [collate([data[(3 * i + j) % len(data)] for j in range(2)]).to(CUDA) for i in range(20)]
    twin = copy.deepcopy(model)
    eager_optimizer = model.configure_optimizers()["optimizer"]
    static_optimizer = twin.configure_optimizers()["optimizer"]
    step = StaticTrainStep(twin, margin=4.0)
    assert step.capture
    eager = eager_losses(model, eager_optimizer, batches)
    torch.manual_seed(1)
    static = [step.step(batch, static_optimizer).item() for batch in batches]
    step.read_capacities()
    assert step.skipped == 0 and step.recordings <= 3  # one per batch shape (bucketed point clouds may differ)
    assert all(int(state["step"]) == len(batches) for state in static_optimizer.state.values())  # no warm-up step
    torch.testing.assert_close(torch.tensor(static), torch.tensor(eager), rtol=1e-4, atol=1e-6)
    for (name, a), b in zip(model.named_parameters(), twin.parameters()):
        torch.testing.assert_close(b, a, rtol=1e-3, atol=1e-5, msg=name)
    assert _syncs(lambda: step.step(batches[0], static_optimizer)) == 0


def test_a_fit_with_static_steps_then_a_test_in_one_process_with_workers_and_bf16(cli_data, tmp_path):
    import pytorch_lightning as pl

    from ggns.data.module import SimulationDataModule
    from ggns.callbacks import StaticRollouts, StaticTraining

    data = SimulationDataModule(str(cli_data / TINY12), batch_size=2, generate_missing=False, num_workers=2,
                                eval_batch_size=2)
    model = make(GGNS)  # capacities from every batch's graphs
    evaluation = TestEvaluation(schedules=("every:1", "never"), iou=False)
    trainer = pl.Trainer(max_steps=6, logger=False, enable_progress_bar=False, enable_model_summary=False,
                         limit_val_batches=0, log_every_n_steps=2, accelerator="gpu", devices=1,
                         precision="bf16-mixed", callbacks=[StaticTraining(), StaticRollouts(), evaluation],
                         default_root_dir=tmp_path)
    trainer.fit(model, data)
    assert trainer.global_step == 6
    optimizer = model.optimizers().optimizer
    assert all(int(state["step"]) == 6 for state in optimizer.state.values())  # the recording's warm-up applied none
    assert math.isclose(float(optimizer.param_groups[0]["lr"]), model.lr_schedule.at(6), rel_tol=1e-6)
    trainer.test(model, data)
    assert all(math.isfinite(s["mean"]) for s in evaluation.results.values())


def _sync_warnings(caught) -> int:
    return sum("synchroniz" in str(w.message) for w in caught)


def _syncs(run) -> int:
    """The synchronizations CUDA's sync debug mode reports inside run(). A known one after it (one `.item()`)
    must be reported too, else the mode saw nothing and a count of 0 would mean nothing. The closing
    `torch.cuda.synchronize()` (asynchronous errors surface there) is not counted: it runs after the mode is
    reset, and PyTorch's device-wide synchronize does not report to the mode anyway."""
    import warnings

    probe = torch.zeros((), device=CUDA)
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            run()
            inside = _sync_warnings(caught)
            probe.item()
            probed = _sync_warnings(caught) - inside
        finally:
            torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()
    assert probed == 1, f"CUDA's sync debug mode reported {probed} synchronizations for one .item()"
    return inside


def _radius_queries(connectivity, node_types) -> int:
    """The radius queries of one graph build with these node types (tests/test_hotpath.py)."""
    return len({(tuple(sorted((src, dst))), relation) for (src, relation, dst), r in connectivity.radii().items()
                if r > 0 and src in node_types and dst in node_types})


def test_a_training_step_synchronizes_only_in_its_radius_queries(splits):
    """GGNS's training step on the GPU synchronizes in its radius queries only (their edge counts are data),
    not in checks, losses, masks or the optimizer. A torch_cluster radius call synchronizes twice on a GPU:
    its CUDA kernel fills max_num_neighbors slots per query node and the pairs found are cut out by two
    masked_selects (rows, columns), each a nonzero; its Python wrapper reads each batch vector's maximum too
    (`int(batch.max())`) unless given batch_size, which the graph builder gives."""
    import torch_cluster

    from ggns import phases
    from ggns.bench.step_profile import HostReads
    from ggns.graphs.search import cluster_runs_on

    # the eager step's search on a GPU is torch-cluster only where it was built with CUDA (gpu_check.sh does)
    assert cluster_runs_on(CUDA), "torch-cluster here was built without CUDA: build it as scripts/gpu_check.sh does"

    pos = torch.rand(50, 3, device=CUDA)
    graph_of = torch.arange(2, device=CUDA).repeat_interleave(25)
    torch_cluster.radius(pos, pos, 0.3, graph_of, graph_of, batch_size=2)  # warm-up
    assert _syncs(lambda: torch_cluster.radius(pos, pos, 0.3, graph_of, graph_of, batch_size=2)) == 2
    assert _syncs(lambda: torch_cluster.radius(pos, pos, 0.3, graph_of, graph_of)) == 2 + 2

    model = _fitted(GGNS, splits, point_probability=1.0)  # every graph with its points: a fixed set of queries
    batch = collate([splits["train"][0].steps(0, 2), splits["train"][1].steps(3, 5)]).to(CUDA)
    optimizer = torch.optim.Adam(model.parameters())

    def train():
        loss = model.window_loss(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    train()  # warm-up (first calls may initialize lazily)
    reads = HostReads()
    with phases.recording(), reads:
        train()
    assert {name for _, _, name in reads.counts} == {"radius"}, reads.counts
    calls = sum(reads.counts.values())
    graphs = [graph for graph, _ in model.training_graphs(batch, train=False)]
    assert calls == sum(_radius_queries(model.connectivity, graph.node_types) for graph in graphs) > 0
    # 2 per radius call if nothing else synchronizes (the exact count is checked on one call above)
    syncs = _syncs(train)
    assert 0 < syncs <= 2 * calls, (syncs, calls)
    with torch.no_grad():
        model.core.decoder[-1].bias.fill_(float("nan"))
    model.window_loss(batch)  # recorded on the device, not raised
    with pytest.raises(FloatingPointError, match="non-finite training loss nan at global step 0"):
        model.raise_if_checks_failed()


def test_the_step_profile_runs_on_the_gpu(cli_data, tmp_path):
    from ggns.bench.step_profile import profile

    report = profile("ggns", str(cli_data / TINY12), latent=8, blocks=2, batch_size=2, steps=2, warmup=1,
                     device="cuda", fit_steps=3, output=str(tmp_path))
    for key in ("training", "rollout"):
        assert report[key]["kernel launches per step"] > 0 and "CUDA synchronizations per step" in report[key]
    static = profile("ggns", str(cli_data / TINY12), latent=8, blocks=2, batch_size=2, steps=2, warmup=1,
                     device="cuda", static=True, output=str(tmp_path / "static"))
    assert static["training"]["host reads per step"] == static["rollout"]["host reads per step"] == 0
    assert static["training"]["CUDA synchronizations per step"] == 0
    # a rollout synchronizes only where it reads its deferred checks (once per run of steps)
    assert static["rollout"]["CUDA synchronizations per step"] <= static["rollout"]["deferred-check reads per step"]
