"""`python -m ggns bench models`: training iterations and batched rollouts of the learned
simulators timed, against the reference figures and goals of conf/bench/models.yaml
(`bench_models`; docs/benchmarks.md).
"""
from __future__ import annotations

import os
import platform
import statistics
import time

import numpy as np
import torch

from ..batch import TrajectoryBatch
from ..config import load_config
from ..data.module import SimulationDataModule
from ..evaluation.schedules import EveryK, Never, effective_schedules
from ..graphs.state import ConstructionTimer, state_graph
from ..models.simulators import MODELS
from ..reports import write_csv
from .report import print_table
from .timing import median_ms, resolve_device, sync, time_rollout

MATMUL_OPS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm")


def load_goals(name: str = "models") -> dict:
    """The reference figures and goals (conf/bench/<name>.yaml or a path): {"reference": ..., "goals": ...}."""
    return load_config(name, kind="bench")


def gemm_rate(device: torch.device, m: int = 2048, k: int = 2048, n: int = 2048, repeats: int = 10) -> float:
    """The machine's fp32 matrix-multiply rate in GFLOP/s: median of `repeats` [m, k] @ [k, n]
    products after 3 warm-up ones (the default large square product measures the peak)."""
    a, b = torch.randn(m, k, device=device), torch.randn(k, n, device=device)
    times = []
    for i in range(repeats + 3):
        sync(device)
        start = time.perf_counter()
        a @ b
        sync(device)
        if i >= 3:
            times.append(time.perf_counter() - start)
    return 2.0 * m * k * n / statistics.median(times) / 1e9


def _iteration(model, batch, optimizer) -> None:
    """One optimizer iteration: graph construction, forward, backward, Adam step."""
    loss = model.window_loss(batch, train=True)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()


def _matrix_work(model, batch, optimizer) -> tuple[float, float]:
    """(matrix FLOPs of one training iteration, forward and backward, counted by torch's
    FlopCounterMode; share of the iteration's CPU time spent inside matrix products, from the
    profiler's self times of MATMUL_OPS)."""
    from torch.profiler import ProfilerActivity, profile
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        _iteration(model, batch, optimizer)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        _iteration(model, batch, optimizer)
    events = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in events)
    matmul = sum(e.self_cpu_time_total for e in events if e.key in MATMUL_OPS)
    return float(counter.get_total_flops()), matmul / total if total else float("nan")


def _graph_size(graph, num_graphs: int) -> tuple[float, float]:
    """Mean (nodes, edges) per graph of a batched graph; edges count every directed edge of every type."""
    nodes = sum(graph[t].num_nodes for t in graph.node_types)
    edges = sum(graph[t].edge_index.size(1) for t in graph.edge_types)
    return nodes / num_graphs, edges / num_graphs


def train_batches_on(datamodule, window: int, count: int, device: torch.device) -> list:
    """`count` training batches (windows of `window` transitions), cycling the shuffled loader if
    the split has fewer, collated and moved to the device before any timing."""
    datamodule.train_window = window
    batches = []
    while len(batches) < count:
        for batch in datamodule.train_dataloader():
            batches.append(batch.to(device))
            if len(batches) == count:
                break
    return batches


def _bench_training(name: str, model, datamodule, train_batches: int, device: torch.device,
                    statistics_batches: int = 2, warmup: int = 2) -> dict:
    batches = train_batches_on(datamodule, model.window, statistics_batches + warmup + train_batches, device)
    model.fit_normalizers(batches[:statistics_batches])
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=model.lr_schedule.lr)
    iteration, construction, graphs = [], [], []
    for i, batch in enumerate(batches[statistics_batches:]):
        with ConstructionTimer(device) as timer:
            sync(device)
            start = time.perf_counter()
            _iteration(model, batch, optimizer)
            sync(device)
            elapsed = time.perf_counter() - start
        if i >= warmup:
            iteration.append(elapsed)
            construction.append(timer.seconds)
            graphs.append(batch.num_graphs * (batch.num_steps - 1))
    # graph sizes: the timed batches' first states, with and without their point clouds
    sizes = {}
    with torch.no_grad():
        for use_points in ((True, False) if model.uses_points else (False,)):
            per_batch = [_graph_size(state_graph(b, 0, b.positions[0], use_points, model.connectivity, model.with_material),
                                     b.num_graphs) for b in batches[statistics_batches + warmup:]]
            sizes[use_points] = tuple(float(np.mean(v)) for v in zip(*per_batch))
    median = statistics.median(iteration)
    flops, matmul_share = _matrix_work(model, batches[-1], optimizer)  # after the timing: not timed
    row = {
        "model": name,
        "windows per batch": float(np.mean([b.num_graphs for b in batches[statistics_batches + warmup:]])),
        "window (transitions)": model.window,
        "graphs per batch": float(np.mean(graphs)),
        "iterations timed": len(iteration),
        "ms per iteration": 1e3 * median,
        "graphs/s": float(np.mean(graphs)) / median,
        "graph construction ms per batch": median_ms(construction),
        "graph construction share": statistics.median(construction) / median,
        "matrix GFLOP per iteration": flops / 1e9,
        "matrix GFLOP/s (per iteration time)": flops / 1e9 / median,
        "matmul share of CPU time (profiler)": matmul_share,
    }
    for use_points, (nodes, edges) in sizes.items():
        group = "with points" if use_points else "without points"
        row[f"nodes per graph ({group})"], row[f"edges per graph ({group})"] = nodes, edges
    reference = load_goals()["reference"]["train_graphs_per_s"].get(name)
    if reference:
        row["speed-up vs reference"] = row["graphs/s"] / reference
    return row


def bench_models(dataset: str = "plate_small", models: tuple[str, ...] = ("ggns", "ggns_lstm", "mgn", "mgn_m"),
                 train_batches: int = 10, rollout_steps: int | None = None, device: str = "cpu",
                 output: str | None = None, batch_size: int = 32, rollout_trajectories: int = 32, repeats: int = 3,
                 latent: int = 128, blocks: int = 5, seed: int = 0) -> list[dict]:
    """Training and rollout throughput of the learned simulators (random weights: speed does not
    depend on them), printed as tables; one CSV row per model x measurement if `output` is given.

    Training: after `fit_normalizers` on 2 batches and 2 warm-up iterations, `train_batches` full
    optimizer iterations (graph construction + forward + backward + Adam step) on batches of
    `batch_size` windows; a window of the LSTM holds 5 transitions, i.e. 5 graphs, so its batch
    counts windows x 5 graphs. Rollout: whole rollouts of `rollout_steps` steps (default: all)
    of 1 test trajectory and of `rollout_trajectories` at once (test trajectories repeated if
    the split has fewer), `repeats` times, median ms per step; the graph construction share is the
    time inside `graphs.state.state_graph` within the same rollouts (`ConstructionTimer`).
    """
    device = resolve_device(device)
    figures = load_goals()
    reference_ms = figures["reference"]["rollout_ms_per_step"]
    unknown = [m for m in models if m not in MODELS]
    if unknown or not models:
        raise ValueError(f"unknown model(s) {unknown}; choose from {sorted(MODELS)}")
    if train_batches < 1 or repeats < 1 or rollout_trajectories < 1 or (rollout_steps is not None and rollout_steps < 1):
        raise ValueError("train_batches, repeats, rollout_trajectories and rollout_steps must be >= 1")
    datamodule = SimulationDataModule(dataset=dataset, batch_size=batch_size)
    datamodule.prepare_data()
    dim = datamodule.dim
    tests = datamodule.trajectories("test")
    single = TrajectoryBatch.from_trajectories(tests[:1], device=device)
    many = TrajectoryBatch.from_trajectories([tests[i % len(tests)] for i in range(rollout_trajectories)], device=device)
    steps = single.num_steps - 1 if rollout_steps is None else min(rollout_steps, single.num_steps - 1)

    peak = gemm_rate(device)
    train_rows, rollout_rows = [], []
    for name in models:
        torch.manual_seed(seed)
        model = MODELS[name](dim=dim, latent=latent, blocks=blocks).to(device)
        print(f"bench models: {name} training ...", flush=True)
        train_rows.append(_bench_training(name, model, datamodule, train_batches, device))
        train_rows[-1]["share of the GEMM rate"] = train_rows[-1]["matrix GFLOP/s (per iteration time)"] / peak
        for schedule in effective_schedules((EveryK(1), Never()), model.uses_points):
            print(f"bench models: {name} rollout {schedule} ...", flush=True)
            one = time_rollout(model, single, schedule, steps, repeats, device)
            batched = time_rollout(model, many, schedule, steps, repeats, device)
            per_trajectory = batched["ms per step"] / rollout_trajectories
            with_points = model.uses_points and schedule.uses_points(0)
            target = reference_ms["with_points" if with_points else "without_points"] / figures["goals"]["rollout_speedup"]
            rollout_rows.append({
                "model": name, "schedule": str(schedule), "steps": steps,
                "ms/step (1 traj.)": one["ms per step"], f"ms/step ({rollout_trajectories} traj.)": batched["ms per step"],
                "ms per trajectory-step (batched)": per_trajectory, "target ms per trajectory-step": target,
                "throughput ratio": rollout_trajectories * one["ms per step"] / batched["ms per step"],
                "graph share (1 traj.)": one["graph construction share"],
                f"graph share ({rollout_trajectories} traj.)": batched["graph construction share"],
            })
        del model

    threads = torch.get_num_threads()
    machine = (torch.cuda.get_device_name(device) if device.type == "cuda"
               else f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, {threads} torch threads")
    print(f"\nbench models: dataset {dataset!r} ({dim}D), device {device} ({machine}); random weights, "
          f"latent {latent}, {blocks} blocks; fp32 GEMM rate {peak:.0f} GFLOP/s (2048^3 product, median)")
    print(f"\ntraining: {batch_size} windows per batch (ggns_lstm: windows of 5 transitions = 5 graphs each), "
          f"median over {train_batches} iterations after 2 warm-up")
    print_table(train_rows, transpose=True, label_keys=("model", "schedule"))
    print(f"\nrollout: {steps} steps, median of {repeats} whole rollouts; 1 vs {rollout_trajectories} trajectories")
    print_table(rollout_rows, transpose=True, label_keys=("model", "schedule"))
    goals = _goals(train_rows, rollout_rows, rollout_trajectories, figures)
    train_rows[0]["GEMM rate GFLOP/s"] = peak  # into the CSV (once)
    print("\ngoals:")
    for line in goals:
        print(f"  {line}")
    rows = _csv_rows(train_rows, rollout_rows, dataset, device, machine)
    if output is not None:
        write_csv(output, rows, list(rows[0]))
        print(f"\nwrote {len(rows)} rows to {output}")
    return rows


def _goals(train_rows: list[dict], rollout_rows: list[dict], trajectories: int, figures: dict) -> list[str]:
    def met(ok: bool) -> str:
        return "met" if ok else "NOT met"

    goals = figures["goals"]
    train_speedup, gemm_share, graph_share, batching = (goals[k] for k in ("train_speedup", "gemm_share",
                                                                          "graph_share", "batching"))

    lines = []
    for row in train_rows:
        reference = figures["reference"]["train_graphs_per_s"].get(row["model"])
        if reference:
            lines.append(f"training {row['model']}: {row['graphs/s']:.1f} graphs/s vs >= {train_speedup * reference:.0f} "
                         f"({train_speedup:g}x the reference {reference:.0f}): {met(row['graphs/s'] >= train_speedup * reference)}")
        share = row["share of the GEMM rate"]
        lines.append(f"training {row['model']}: matrix work at {share:.0%} of the GEMM rate vs >= {gemm_share:.0%}: "
                     f"{met(share >= gemm_share)}")
    for row in rollout_rows:
        label = f"rollout {row['model']} {row['schedule']}"
        share = row[f"graph share ({trajectories} traj.)"]
        share_one = row["graph share (1 traj.)"]
        lines.append(f"{label}: graph construction {share_one:.0%} (1 traj.) / {share:.0%} ({trajectories} traj.) "
                     f"of a step vs < {graph_share:.0%}: {met(max(share, share_one) < graph_share)}")
        lines.append(f"{label}: batched throughput {row['throughput ratio']:.1f}x one at a time vs >= {batching:.0f}x: "
                     f"{met(row['throughput ratio'] >= batching)}")
        per, target = row["ms per trajectory-step (batched)"], row["target ms per trajectory-step"]
        lines.append(f"{label}: {per:.2f} ms per trajectory-step (batched) vs <= {target:.2f}: {met(per <= target)}")
    return lines


def _csv_rows(train_rows: list[dict], rollout_rows: list[dict], dataset: str, device, machine: str) -> list[dict]:
    rows = []
    for phase, source in (("train", train_rows), ("rollout", rollout_rows)):
        for row in source:
            for key, value in row.items():
                if key in ("model", "schedule"):
                    continue
                rows.append({"dataset": dataset, "device": str(device), "machine": machine, "model": row["model"],
                             "phase": phase, "schedule": row.get("schedule", ""), "measurement": key, "value": value})
    return rows
