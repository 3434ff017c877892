"""The hot path (issue: fast where users train): checks that stay on the device until read and still name
the step, node and quantity; no host reads in a training or rollout step but the neighbour search's own;
static-shape graphs and the static step equal to the dynamic ones; the step profile on tiny data."""
from __future__ import annotations

import contextlib
import dataclasses

import pytest
import pytorch_lightning as pl
import torch

from ggns.batch import TrajectoryBatch
from ggns.bench.step_profile import HostReads, profile
from ggns.checks import DeferredCheck, gpu_code_paths
from ggns.data.module import SimulationDataModule, collate
from ggns.evaluation.capture import StaticStep
from ggns.evaluation.rollout import RolloutError, rollout
from ggns.evaluation.schedules import EveryK, Never, parse_schedule
from ggns.graphs.state import state_graph
from ggns.graphs.static import StaticGraph, unmasked
from ggns.models.simulators import GGNS, GGNSLSTM, MGN, MGNM
from ggns import phases

from conftest import TINY12, make


@pytest.mark.parametrize("gpu_paths", [False, True], ids=["cpu path", "gpu path"])
def test_a_deferred_check_keeps_the_first_failure_until_read(gpu_paths):
    with gpu_code_paths() if gpu_paths else contextlib.nullcontext():
        check = DeferredCheck()
        assert check.failure() is None
        for step, value in enumerate([1.0, float("nan"), 2.0, float("inf")]):
            x = torch.tensor(value)
            check.record(~torch.isfinite(x), step, x, torch.tensor([step, 7]))
        failure = check.failure()
        assert failure.step == 1 and failure.detail[1] == [1, 7] and failure.detail[0] != failure.detail[0]  # nan
        check.reset()
        check.record(torch.tensor(False), 5, torch.tensor(0.0))
        assert check.failure() is None


def test_a_non_finite_loss_in_a_fit_raises_naming_step_node_and_quantity(cli_data, tmp_path):
    """NaN weights from step 3 on: the fit reads its checks every log_every_n_steps (2) and raises at step 4
    naming step 3, the first non-finite mesh node and its trajectory; no checkpoint is written after it."""
    class Poison(pl.Callback):
        def on_train_batch_start(self, trainer, module, batch, batch_idx):
            if trainer.global_step == 3:
                with torch.no_grad():
                    module.core.decoder[-1].bias.fill_(float("nan"))

    model = make(GGNS, statistics_batches=1)
    data = SimulationDataModule(str(cli_data / TINY12), batch_size=2, generate_missing=False)
    seen = []

    class Steps(pl.Callback):
        def on_train_batch_end(self, trainer, *args):
            seen.append(trainer.global_step)

    trainer = pl.Trainer(max_steps=8, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, log_every_n_steps=2,
                         callbacks=[Poison(), Steps()], accelerator="cpu")
    with pytest.raises(FloatingPointError, match=r"non-finite training loss nan at global step 3 \(transition 0 .*"
                                                 r"mesh node \d+ of trajectory \d+ of the batch"):
        trainer.fit(model, data)
    assert seen == [1, 2, 3, 4]  # global step after each batch: the poisoned batch (step 3) was the last


def test_the_neighbour_cap_is_read_later_and_names_the_step(val_batch, trajs):
    """A rollout reading its checks every 4 steps: the cap was exceeded from step 0 on, the error names
    step 0 and the node; a training fit names the global step."""
    model = make(GGNS).eval()
    tight = dataclasses.replace(model.connectivity, max_num_neighbors=2)
    with pytest.raises(ValueError, match=r"edge type .* at step 0: \w+ node \d+ has more than max_num_neighbors=2 "
                                         r"neighbours .*set a larger max_num_neighbors"):
        rollout(model.step, val_batch, EveryK(1), tight, check_every=4)
    model.connectivity = tight
    model.neighbour_check = type(model.neighbour_check)(tight, what="training")
    model.window_loss(collate([t.steps(0, 2) for t in trajs["val"]]))  # recorded, not raised
    with pytest.raises(ValueError, match=r"at step 0: .*more than max_num_neighbors=2"):
        model.raise_if_checks_failed()


@pytest.mark.parametrize("every", [1, 3, 100])
def test_a_diverging_rollout_names_its_first_bad_step_whenever_it_is_read(val_batch, every):
    node = int(torch.nonzero(~val_batch.fixed & (val_batch.mesh_batch == 1))[0])
    calls = []

    def step_fn(graph, state):
        calls.append(len(calls))
        out = torch.zeros_like(graph["mesh"].pos)
        if len(calls) - 1 == 2:
            out[node, 0] = float("nan")
        return out, state

    with pytest.raises(RolloutError, match=r"step 2 \(state 2 -> 3\): non-finite positions in trajectory index\(es\) "
                                           r"\[1\]"):
        rollout(step_fn, val_batch, Never(), make(MGN).connectivity, check_every=every)
    last = val_batch.num_steps - 2
    assert calls[-1] == min(every * (2 // every + 1) - 1, last)  # ran on to the read after step 2, no further


def _reads(run) -> dict:
    reads = HostReads()
    with phases.recording(), gpu_code_paths(), reads:
        run()
    return {name: n for (_, _, name), n in reads.counts.items()}


@pytest.mark.parametrize("cls", [GGNS, MGNM])
def test_training_and_rollout_steps_read_the_host_only_in_the_neighbour_search(cls, trajs, val_batch):
    """Every host read left in a training step (window loss, backward, Adam) and a rollout step is a radius
    query (its edge count is data) or, for MGN's world edges, the filter of the mesh pairs."""
    model = make(cls, statistics_batches=1)
    batch = collate([trajs["train"][0].steps(2, 4), trajs["train"][1].steps(0, 2)])
    model.fit_normalizers([batch])
    optimizer = torch.optim.Adam(model.parameters())

    def train():
        loss = model.window_loss(batch)
        loss.backward()
        optimizer.step()

    allowed = {"radius"} | ({"__getitem__"} if cls is MGNM else set())  # drop_mesh_pairs' boolean mask
    assert set(_reads(train)) <= allowed
    model.eval()
    schedule = EveryK(1) if model.uses_points else Never()
    reads = _reads(lambda: rollout(model.step, val_batch, schedule, model.connectivity, model.with_material,
                                   check_every=val_batch.num_steps))
    assert set(reads) - allowed <= {"__bool__"} and reads.get("__bool__", 0) <= 2  # the one read at the end


@pytest.mark.parametrize("cls", [GGNS, MGN, MGNM])
def test_static_graphs_equal_the_dynamic_ones_after_masking(cls, val_batch):
    model = make(cls).eval()
    static = StaticGraph(*model.input_dims(model.connectivity, 2, model.with_material), "cpu", multiple=8)
    caps = []
    for t in range(val_batch.num_steps - 1):
        for use_points in ((True, False) if model.uses_points else (False,)):
            graph = state_graph(val_batch, t, val_batch.positions[t], use_points, model.connectivity,
                                model.with_material)
            padded, _ = static.fill(graph)
            caps.append(static.capacities())
            assert set(padded.edge_types) >= set(graph.edge_types) and set(padded.node_types) >= set(graph.node_types)
            for edge_type in padded.edge_types:
                kept = unmasked(padded[edge_type])
                expected = graph[edge_type].edge_index if edge_type in graph.edge_types else kept[:, :0]
                assert torch.equal(kept, expected), edge_type
                n = expected.size(1)
                if n:
                    assert torch.equal(padded[edge_type].edge_attr[:n], graph[edge_type].edge_attr)
            with torch.no_grad():
                torch.testing.assert_close(model.step(padded)[0], model.step(graph)[0], rtol=1e-5, atol=1e-7)
    assert all(c[t] >= 8 for c in caps for t in c)


@pytest.mark.parametrize("cls", [GGNS, MGNM])
def test_the_static_step_rolls_out_as_the_eager_one(cls, val_batch, trajs):
    """The padded, buffered step (what a GPU captures) gives the eager rollouts and the same losses."""
    model = make(cls).eval()
    model.fit_normalizers([collate([trajs["train"][0].steps(0, 2)])])
    step = StaticStep(model, capture=False)
    for schedule in (["every:1", "every:3", "never"] if model.uses_points else ["never"]):
        plan = parse_schedule(schedule)
        eager, _ = rollout(model.step, val_batch, plan, model.connectivity, model.with_material)
        static, _ = rollout(step, val_batch, plan, model.connectivity, model.with_material)
        torch.testing.assert_close(static, eager, rtol=1e-5, atol=1e-6)
    model.static_rollouts = True
    assert isinstance(model.rollout_step(), StaticStep)
    static_metrics = model.evaluate(val_batch, m_plus_10=False, iou=False)
    model.static_rollouts = False
    eager_metrics = model.evaluate(val_batch, m_plus_10=False, iou=False)
    for key, value in eager_metrics.items():
        torch.testing.assert_close(static_metrics[key], value, rtol=1e-4, atol=1e-9)


def test_the_static_step_refuses_what_it_cannot_replay():
    with pytest.raises(ValueError, match="GGNSLSTM.*static step"):
        StaticStep(make(GGNSLSTM))
    with pytest.raises(ValueError, match="capture needs the model on a CUDA device"):
        StaticStep(make(GGNS), capture=True)


def test_the_step_profile_runs_on_tiny_data(cli_data, tmp_path):
    report = profile("ggns", str(cli_data / TINY12), latent=8, blocks=2, batch_size=2, steps=2, warmup=1,
                     fit_steps=3, output=str(tmp_path))
    for key in ("training", "rollout"):
        row = report[key]
        assert row["ms per step"] > 0 and row["operators per step"] > 0
        assert row["processor: operators"] > 0 and row["graph construction: ms"] > 0
        assert set(name.rsplit(" | ", 1)[1] for name in row["host reads by site"]) <= {"radius", "__bool__"}
    assert "backward: ms" in report["training"] and report["lightning fit"]["fit steps/s"] > 0
    assert (tmp_path / "profile.json").is_file() and "### training step" in (tmp_path / "profile.md").read_text()


def test_the_compiled_processor_equals_the_eager_one(trajs, val_batch):
    """torch.compile of the blocks (dynamic shapes; the aot_eager backend traces what inductor would compile,
    in a fraction of its compile time) gives the eager losses, gradients and rollouts on the CPU."""
    from ggns.models.speed import compile_processor

    torch._dynamo.reset()
    eager = make(GGNS, statistics_batches=1)
    batch = collate([trajs["train"][0].steps(0, 2), trajs["train"][1].steps(3, 5)])
    eager.fit_normalizers([batch])
    compiled = make(GGNS, statistics_batches=1)
    compiled.load_state_dict(eager.state_dict())
    compile_processor(compiled, backend="aot_eager")
    for model in (eager, compiled):
        torch.manual_seed(1)
        model.window_loss(batch).backward()
    for (name, a), b in zip(eager.named_parameters(), compiled.parameters()):
        torch.testing.assert_close(b.grad, a.grad, rtol=1e-5, atol=1e-7, msg=name)
    with torch.no_grad():
        torch.testing.assert_close(compiled.rollout(val_batch, "every:2"), eager.rollout(val_batch, "every:2"))
    assert set(compiled.state_dict()) == set(eager.state_dict())  # checkpoints keep their names


def test_an_interrupted_ab_run_is_summarized_from_its_complete_rounds():
    from ggns.bench.ab import raw_from_log, summarize

    log = "\n".join([
        "bench ab: round 1/3 baseline  train ggns 64 3 8: 100.00 ms",
        "bench ab: round 1/3 candidate train ggns 64 3 8: 50.00 ms",
        "bench ab: round 2/3 candidate train ggns 64 3 8: 40.00 ms",
        "bench ab: round 2/3 baseline  train ggns 64 3 8: 120.00 ms",
        "bench ab: round 3/3 baseline  train ggns 64 3 8: 90.00 ms",  # the run was killed here
    ])
    raw = raw_from_log(log)
    assert sorted({r["round"] for r in raw}) == [0, 1]
    (row,) = summarize(raw)
    assert row["baseline"] == 110.0 and row["candidate"] == 45.0
    assert row["speed-up (median of rounds)"] == pytest.approx((2.0 + 3.0) / 2)
    with pytest.raises(ValueError, match="no complete round"):
        raw_from_log(log.splitlines()[-1])


def test_the_import_probe_times_a_fresh_import_and_the_sweep_processes_import_no_torch():
    """`bench ab --probe "import MODULE"` times an import in a fresh process; a sweep's and bench learning's
    own processes (which only start fits and tests) import neither torch nor Lightning, nor does reading
    a sweep's results without baselines, nor writing a run's merged test metrics."""
    import subprocess
    import sys
    from pathlib import Path

    from ggns.bench.ab import run_probe

    src = Path(__file__).resolve().parents[1] / "src"
    result = run_probe(src, "import ggns.experiments.sweep", threads=1)
    assert result["probe"] == "import ggns.experiments.sweep" and result["ms"] > 0
    check = ("import sys, ggns.experiments.sweep, ggns.experiments.learning, ggns.baselines, ggns.commands; "
             "from ggns.reports import metrics_markdown; "  # what a sweep writes a run's merged metrics with
             "assert 'e-01' in metrics_markdown({'mse': {'mean': 0.5, 'std': float('nan'), 'count': 2}}); "
             "heavy = sorted(m for m in ('torch', 'pytorch_lightning', 'torch_geometric') if m in sys.modules); "
             "print(heavy); assert not heavy")
    done = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
