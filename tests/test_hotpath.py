"""The hot path: checks that stay on the device until read and still name the step, node and quantity; a
host-read counter that sees every kind of read; no host reads in an eager training or rollout step but the
neighbour search's own; the step profile on tiny data (the static steps: tests/test_static_step.py)."""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import operator

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
import torch_cluster

from ggns.batch import TrajectoryBatch
from ggns.bench.step_profile import READS, READS_BY_ARGUMENTS, HostReads, is_read, profile
from ggns.checks import DeferredCheck, gpu_code_paths
from ggns.data.module import SimulationDataModule, collate
from ggns.evaluation.rollout import RolloutError, rollout
from ggns.evaluation.schedules import EveryK, Never, parse_schedule
from ggns.graphs.state import state_graph
from ggns.graphs.types import MESH_EDGE
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
    counts = collections.Counter()
    for (_, _, name), n in reads.counts.items():
        counts[name] += n
    return dict(counts)


def _tensors() -> dict:
    x = torch.randn(6, 3, generator=torch.Generator().manual_seed(0))
    mask = torch.tensor([True, False, True, True, False, False])
    return dict(x=x, mask=mask, values=torch.ones(3, 3), index=torch.tensor([0, 2, 2, 5]), scalar=torch.tensor(0.5),
                zero_d=torch.tensor(2), repeats=torch.tensor([1, 0, 2, 1, 1, 0]),
                batch=torch.zeros(6, dtype=torch.long), many=torch.arange(20))


def _set_by_mask(t):
    y = t["x"].clone()
    y[t["mask"]] = t["values"]  # a device tensor of values: its rows are matched to the mask's count


def _set_by_0d_index(t):
    y = t["x"].clone()
    y[t["zero_d"]] = 1.0


def _fill_by_mask(t):
    y = t["x"].clone()
    y[t["mask"]] = 0.0  # one Python number through one mask: PyTorch's masked_fill_


# (the name HostReads counts it under, a call that reads exactly once, its id)
READ_KINDS = [
    ("item", lambda t: t["scalar"].item(), "item"),
    ("tolist", lambda t: t["x"].tolist(), "tolist"),
    ("__bool__", lambda t: bool(t["mask"].any()), "bool of any"),
    ("__int__", lambda t: int(t["index"].max()), "int of max"),
    ("__float__", lambda t: float(t["scalar"]), "float"),
    ("__complex__", lambda t: complex(t["scalar"]), "complex"),
    ("__index__", lambda t: operator.index(t["zero_d"]), "index"),
    ("is_nonzero", lambda t: torch.is_nonzero(t["scalar"]), "is_nonzero"),
    ("equal", lambda t: torch.equal(t["x"], t["x"]), "torch.equal"),
    ("equal", lambda t: t["x"].equal(t["x"]), "Tensor.equal"),
    ("allclose", lambda t: torch.allclose(t["x"], t["x"]), "torch.allclose"),
    ("allclose", lambda t: t["x"].allclose(t["x"]), "Tensor.allclose"),
    ("__contains__", lambda t: 0.5 in t["x"], "in"),
    ("__format__", lambda t: f"{t['scalar']:.3f}", "format"),
    ("__repr__", lambda t: repr(t["x"]), "repr"),
    ("__repr__", lambda t: str(t["x"]), "str"),
    ("cpu", lambda t: t["x"].cpu(), "cpu"),
    ("numpy", lambda t: t["x"].numpy(), "numpy"),
    ("__array__", lambda t: np.asarray(t["x"]), "numpy asarray"),
    ("nonzero", lambda t: torch.nonzero(t["mask"]), "torch.nonzero"),
    ("nonzero", lambda t: t["mask"].nonzero(as_tuple=True), "Tensor.nonzero as tuple"),
    ("argwhere", lambda t: torch.argwhere(t["mask"]), "argwhere"),
    ("masked_select", lambda t: torch.masked_select(t["x"], t["mask"][:, None]), "torch.masked_select"),
    ("masked_select", lambda t: t["x"].masked_select(t["mask"][:, None]), "Tensor.masked_select"),
    ("unique", lambda t: torch.unique(t["index"]), "torch.unique"),
    ("unique", lambda t: t["index"].unique(return_counts=True), "Tensor.unique"),
    ("unique_consecutive", lambda t: torch.unique_consecutive(t["index"]), "unique_consecutive"),
    ("bincount", lambda t: torch.bincount(t["index"], minlength=6), "bincount"),  # its size is max(index, 5) + 1
    ("radius", lambda t: torch_cluster.radius(t["x"], t["x"], 1.0, t["batch"], t["batch"], batch_size=1), "radius"),
    ("knn", lambda t: torch_cluster.knn(t["x"], t["x"], 2, t["batch"], t["batch"], batch_size=1), "knn"),
    ("where", lambda t: torch.where(t["mask"]), "where of a condition"),
    ("to", lambda t: t["x"].to("cpu"), "to cpu"),
    ("to", lambda t: t["x"].to(device="cpu"), "to device=cpu"),
    ("to", lambda t: t["x"].to(torch.device("cpu"), torch.float64), "to cpu and float64"),
    ("__getitem__", lambda t: t["x"][t["mask"]], "getitem by a mask"),
    ("__getitem__", lambda t: t["x"][t["mask"], 1:], "getitem by a mask and a slice"),
    ("__getitem__", lambda t: t["x"][t["zero_d"]], "getitem by a 0-d index"),
    ("__setitem__", _set_by_mask, "setitem by a mask"),
    ("__setitem__", _set_by_0d_index, "setitem by a 0-d index"),
    ("index_put_", lambda t: t["x"].clone().index_put_((t["mask"],), t["values"]), "index_put_ by a mask"),
    ("index_put", lambda t: torch.index_put(t["x"], (t["mask"],), t["values"]), "index_put by a mask"),
    ("repeat_interleave", lambda t: t["x"].repeat_interleave(t["repeats"], dim=0), "Tensor.repeat_interleave"),
    ("repeat_interleave", lambda t: torch.repeat_interleave(t["repeats"]), "repeat_interleave of repeats"),
    ("isin", lambda t: torch.isin(t["index"], t["many"]), "isin, sorting path"),  # 20 >= 10 x 4^0.145
]
NO_READS = [
    (lambda t: torch.index_select(t["x"], 0, t["index"]), "index_select"),
    (lambda t: t["x"][t["index"]], "getitem by an index tensor"),
    (lambda t: t["x"][0, 1:], "getitem by numbers and slices"),
    (lambda t: torch.zeros(6, 3).scatter_(0, t["index"][:, None].expand(-1, 3), t["x"][:4]), "scatter_"),
    (lambda t: torch.zeros(6, 3).index_add_(0, t["index"], t["x"][:4]), "index_add_"),
    (lambda t: torch.where(t["mask"][:, None], t["x"], 0.0), "torch.where(cond, a, b)"),
    (lambda t: t["x"].where(t["mask"][:, None], 0.0), "Tensor.where(cond, b)"),
    (lambda t: torch.topk(t["x"][:, 0], 2), "topk"),
    (lambda t: torch.cumsum(t["mask"], 0), "cumsum"),
    (lambda t: torch.sort(t["x"][:, 0]), "sort"),
    (lambda t: t["x"].max(dim=0), "max(dim)"),
    (lambda t: (t["x"].max(), t["x"].min()), "max() and min() to 0-d tensors"),
    (lambda t: (t["mask"].any(), t["mask"].all()), "any and all"),
    (lambda t: torch.arange(6), "arange"),
    (lambda t: torch.searchsorted(t["index"], t["repeats"]), "searchsorted"),
    (lambda t: torch.nonzero_static(t["mask"], size=6), "nonzero_static"),
    (lambda t: t["x"].masked_fill(t["mask"][:, None], 0.0), "masked_fill"),
    (_fill_by_mask, "setitem of a number by a mask"),
    (lambda t: torch.gather(t["x"], 0, t["index"][:, None].expand(-1, 3)), "gather"),
    (lambda t: torch.isclose(t["x"], t["x"]), "isclose"),
    (lambda t: torch.isin(t["many"], t["index"]), "isin, brute-force path"),  # 4 < 10 x 20^0.145
    (lambda t: t["x"].repeat_interleave(2, dim=0), "repeat_interleave by a number"),
    (lambda t: torch.repeat_interleave(t["repeats"], output_size=5), "repeat_interleave with output_size"),
    (lambda t: len(t["x"]), "len"),
    (lambda t: (t["x"].to(torch.float64), t["x"].to(t["x"])), "to a dtype, to a tensor on the same device"),
    (lambda t: torch.empty(6, 3).copy_(t["x"]), "copy_ on one device"),
    (lambda t: phases.host_side(torch.tensor([1.5])).item(), "item of a host tensor"),
]


@pytest.mark.parametrize("name, run", [pytest.param(name, run, id=label) for name, run, label in READ_KINDS])
def test_the_host_read_counter_sees_every_kind_of_read(name, run):
    t = _tensors()
    assert _reads(lambda: run(t)) == {name: 1}


def test_every_kind_of_read_the_counter_knows_is_tested():
    assert {name for name, _, _ in READ_KINDS} | {"copy_"} == READS | READS_BY_ARGUMENTS


def test_the_host_read_counter_sees_copies_from_another_device():
    """A copy to the host from another device (a meta tensor here) reads; one to another device does not."""
    host, other = torch.zeros(3), torch.zeros(3, device="meta")
    assert is_read(torch.Tensor.copy_, (host, other)) and not is_read(torch.Tensor.copy_, (other, host))
    assert is_read(torch.Tensor.to, (other, host)) and not is_read(torch.Tensor.to, (host, other))
    assert is_read(torch.Tensor.to, (other, "cpu")) and not is_read(torch.Tensor.to, (host, "meta"))


@pytest.mark.parametrize("run", [pytest.param(run, id=label) for run, label in NO_READS])
def test_static_shape_operations_are_no_host_reads(run):
    t = _tensors()
    assert _reads(lambda: run(t)) == {}


def _radius_queries(connectivity, node_types) -> int:
    """The radius queries of one graph build with these node types: one per edge family with a radius > 0
    whose node types the graph has (a cross family, e.g. mesh-point, one query for both directions, as long
    as it finds pairs; else the builder queries the reverse direction again)."""
    return len({(tuple(sorted((src, dst))), relation) for (src, relation, dst), r in connectivity.radii().items()
                if r > 0 and src in node_types and dst in node_types})


def _graph_reads(model, graphs) -> dict:
    """The reads of building `graphs`: the radius queries, and where world edges are queried on a graph with
    mesh edges the filter of the mesh pairs (`drop_mesh_pairs`: its boolean mask and its `isin`, which sorts
    and so reads when the mesh edges number at least 10 x (candidate pairs)^0.145, at most n^2 pairs)."""
    reads = {"radius": sum(_radius_queries(model.connectivity, graph.node_types) for graph in graphs)}
    filtered = [graph for graph in graphs if model.connectivity.world > 0 and MESH_EDGE in graph.edge_types]
    for graph in filtered:
        assert graph[MESH_EDGE].edge_index.size(1) >= 10 * (graph["mesh"].num_nodes ** 2) ** 0.145
    if filtered:
        reads.update(isin=len(filtered), __getitem__=len(filtered))
    return reads


@pytest.mark.parametrize("cls", [GGNS, MGNM])
def test_training_and_rollout_steps_read_the_host_only_in_the_neighbour_search(cls, trajs, val_batch):
    """Every host read left in a training step (window loss, backward, Adam) and a rollout step is a radius
    query (its edge count is data) or, for MGN's world edges, the filter of the mesh pairs; a rollout reads
    its two deferred checks (divergence, neighbour caps) once each at its end."""
    points = dict(point_probability=1.0) if make(cls).uses_points else {}  # every training graph with its points
    model = make(cls, statistics_batches=1, **points)
    batch = collate([trajs["train"][0].steps(2, 4), trajs["train"][1].steps(0, 2)])  # one transition each
    model.fit_normalizers([batch])
    optimizer = torch.optim.Adam(model.parameters())

    def train():
        loss = model.window_loss(batch)
        loss.backward()
        optimizer.step()

    graphs = [graph for graph, _ in model.training_graphs(batch, train=False)]  # the node types of training's
    assert len(graphs) == batch.num_steps - 1 == 1 and all("collider" in g.node_types for g in graphs)
    expected = _graph_reads(model, graphs)
    assert expected["radius"] > 0 and _reads(train) == expected
    model.eval()
    schedule = EveryK(1) if model.uses_points else Never()
    graphs = [state_graph(val_batch, t, val_batch.positions[t], schedule.uses_points(t), model.connectivity,
                          model.with_material) for t in range(val_batch.num_steps - 1)]
    reads = _reads(lambda: rollout(model.step, val_batch, schedule, model.connectivity, model.with_material,
                                   check_every=val_batch.num_steps))
    assert reads == {**_graph_reads(model, graphs), "__bool__": 2}


def test_the_step_profile_runs_on_tiny_data(cli_data, tmp_path):
    report = profile("ggns", str(cli_data / TINY12), latent=8, blocks=2, batch_size=2, steps=2, warmup=1,
                     fit_steps=3, output=str(tmp_path))
    for key in ("training", "rollout"):
        row = report[key]
        assert row["ms per step"] > 0 and row["operators per step"] > 0
        assert row["processor: operators"] > 0 and row["graph construction: ms"] > 0
        # the radius queries; a rollout also reads its two deferred checks at the end of each run of steps
        names = {name.rsplit(" | ", 1)[1] for name in row["host reads by site"]}
        assert names == ({"radius"} if key == "training" else {"radius", "__bool__"}), names
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
    result = run_probe(src, "import ggns.sweeps.sweep", threads=1)
    assert result["probe"] == "import ggns.sweeps.sweep" and result["ms"] > 0
    check = ("import sys, ggns.sweeps.sweep, ggns.sweeps.learning, ggns.baselines, ggns.cli.commands; "
             "from ggns.reports import metrics_markdown; "  # what a sweep writes a run's merged metrics with
             "assert 'e-01' in metrics_markdown({'mse': {'mean': 0.5, 'std': float('nan'), 'count': 2}}); "
             "heavy = sorted(m for m in ('torch', 'pytorch_lightning', 'torch_geometric') if m in sys.modules); "
             "print(heavy); assert not heavy")
    done = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_eager_search_takes_torch_cluster_wherever_it_runs(monkeypatch):
    """`search: auto` routes one way on every device: torch-cluster where its build runs on the tensors'
    device (a CPU build on the CPU, a CUDA build on a GPU), else the static search; `cluster` where it
    cannot run says why. The GPU's routing is decided by the build, which the CPU can stand in for."""
    from ggns.graphs import search

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert search._use_cluster("auto", cpu) and search._use_cluster("cluster", cpu)
    assert not search._use_cluster("static", cpu) and not search._use_cluster("static", cuda)
    assert search._cluster_has_cuda() == (int(torch.ops.torch_cluster.cuda_version()) != -1)
    monkeypatch.setattr(search, "_cluster_has_cuda", lambda: True)  # as a CUDA build answers
    assert search._use_cluster("auto", cuda) and search._use_cluster("cluster", cuda)
    monkeypatch.setattr(search, "_cluster_has_cuda", lambda: False)  # as a CPU-only build answers
    assert not search._use_cluster("auto", cuda)
    with pytest.raises(RuntimeError, match="built without CUDA"):
        search._use_cluster("cluster", cuda)
    monkeypatch.setattr(search, "torch_cluster", None)
    assert not search._use_cluster("auto", cpu)
    with pytest.raises(ImportError, match="not installed"):
        search._use_cluster("cluster", cpu)


def test_the_static_eager_search_reads_twice_per_radius_query(trajs):
    """Without a torch-cluster for the device the eager builder's radius query is the static search, read
    twice (the largest graph's node count, the found pairs' count)."""
    import dataclasses

    model = make(GGNS, statistics_batches=1, point_probability=1.0)
    model.connectivity = dataclasses.replace(model.connectivity, search="static")
    batch = collate([trajs["train"][0].steps(2, 4), trajs["train"][1].steps(0, 2)])
    model.fit_normalizers([batch])
    graphs = [graph for graph, _ in model.training_graphs(batch, train=False)]
    reads = _reads(lambda: model.window_loss(batch).backward())
    queries = sum(_radius_queries(model.connectivity, graph.node_types) for graph in graphs)
    assert queries > 0 and reads == {"__int__": 2 * queries}, (reads, queries)
