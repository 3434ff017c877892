"""Benchmarks (commands, not tests): `python -m ggns bench sim` and `python -m ggns bench models`.

`bench sim` times the ground-truth simulator and the depth sensor trajectory by trajectory on
one thread (as a generation worker runs), and optionally the generation of all the config's
splits with its worker count. `bench models` times training iterations and batched rollouts of
the learned simulators (`bench_models`). Both print medians; nothing here asserts a time.
"""
from __future__ import annotations

import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from .config import load_config
from .data.generate import generate, trajectory_seed
from .scenes import SCENES
from .sensors.camera import DepthSensor, SensorConfig


def _median_ms(values: list[float]) -> float:
    return 1e3 * statistics.median(values)


def bench_sim(preset: str = "plate", trajectories: int = 9, generate_splits: bool = False) -> dict:
    config = load_config(preset)
    scene_module = SCENES[config["scene"]["name"]]
    torch.set_num_threads(1)
    sensor = DepthSensor(SensorConfig.from_dict(config["sensor"]))
    combos = scene_module.num_combinations(config["scene"])
    sim_step, sensor_step, whole, newton = [], [], [], []
    for i in range(trajectories):
        start = time.perf_counter()
        traj = scene_module.make_trajectory(config, (i * 7) % combos, trajectory_seed(config["seed"], "train", i), sensor)
        whole.append(time.perf_counter() - start)
        # observe the recorded states again to split the time between sensor and simulator
        start = time.perf_counter()
        for t in range(traj.num_steps):
            sensor.observe(traj.positions[t], traj.cells, traj.collider_positions[t], traj.collider_faces)
        observe = time.perf_counter() - start
        sensor_step.append(observe / traj.num_steps)
        sim_step.append((whole[-1] - observe) / (traj.num_steps - 1))
        newton.append(traj.diagnostics["newton_iterations"][1:].mean())
    result = {
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} torch thread(s)",
        "simulator ms/step (median, incl. scene set-up)": _median_ms(sim_step),
        "sensor ms/step (median)": _median_ms(sensor_step),
        "trajectory s (median, simulate + observe)": statistics.median(whole),
        "Newton iterations/step (mean)": float(np.mean(newton)),
        "trajectories timed": trajectories,
    }
    if generate_splits:
        total = sum(config["splits"].values())
        with tempfile.TemporaryDirectory() as out:
            start = time.perf_counter()
            generate(dict(config, output=out), progress=True)
            elapsed = time.perf_counter() - start
        result[f"generate all splits ({total} trajectories, {config['workers']} workers) s"] = elapsed
    print(f"bench sim: preset {preset!r}, {config['scene']['num_steps']} steps per trajectory")
    for key, value in result.items():
        print(f"  {key:58s} {value:.3f}" if isinstance(value, float) else f"  {key:58s} {value}")
    return result


# ---- bench models -----------------------------------------------------------------------------

# The authors' public code on this machine class (2 CPU cores), from the issue: training
# graphs/s per model family and rollout ms per step of one trajectory, with / without points.
REFERENCE_TRAIN_GRAPHS_PER_S = {"ggns": 13.0, "ggns_lstm": 13.0, "mgn": 40.0, "mgn_m": 40.0}
REFERENCE_ROLLOUT_MS = {True: 40.0, False: 11.0}  # per trajectory step, with / without point clouds
TRAIN_SPEEDUP_GOAL = 3.0  # >= 3x the reference training throughput
ROLLOUT_SPEEDUP_GOAL = 10.0  # <= reference / 10 ms per trajectory step in the batched rollout
GRAPH_SHARE_GOAL = 0.20  # graph construction under 20 % of a rollout step
BATCHING_GOAL = 10.0  # 32 trajectories at once >= 10x the throughput of one at a time
GEMM_SHARE_GOAL = 0.50  # the model's matrix FLOPs per training second >= 50 % of the machine's fp32 GEMM rate
MATMUL_OPS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm")


def gemm_rate(device: torch.device, m: int = 2048, k: int = 2048, n: int = 2048, repeats: int = 10) -> float:
    """The machine's fp32 matrix-multiply rate in GFLOP/s: median of `repeats` [m, k] @ [k, n]
    products after 3 warm-up ones (the default large square product measures the peak)."""
    a, b = torch.randn(m, k, device=device), torch.randn(k, n, device=device)
    times = []
    for i in range(repeats + 3):
        _sync(device)
        start = time.perf_counter()
        a @ b
        _sync(device)
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


def _resolve_device(device: str) -> torch.device:
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {device} requested but CUDA is not available "
                         f"(torch {torch.__version__}, built with CUDA: {torch.version.cuda or 'no'})")
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be cpu or cuda, got {device}")
    return device


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class _GraphTimer:
    """Context manager: wraps a batch's `graph` method (set on the instance, removed on exit) and
    sums the time spent in it, synchronizing the device around each call so that the time is
    the construction's own."""

    def __init__(self, batch, device: torch.device):
        self.batch, self.device, self.seconds, self.calls = batch, device, 0.0, 0
        self.build = batch.graph

    def __enter__(self) -> _GraphTimer:
        self.batch.graph = self
        return self

    def __exit__(self, *exc) -> None:
        del self.batch.graph  # the instance attribute; the class's method shows through again

    def __call__(self, *args, **kwargs):
        _sync(self.device)
        start = time.perf_counter()
        graph = self.build(*args, **kwargs)
        _sync(self.device)
        self.seconds += time.perf_counter() - start
        self.calls += 1
        return graph

    def reset(self) -> None:
        self.seconds, self.calls = 0.0, 0


def _graph_size(graph, num_graphs: int) -> tuple[float, float]:
    """Mean (nodes, edges) per graph of a batched graph; edges count every directed edge of every type."""
    nodes = sum(graph[t].num_nodes for t in graph.node_types)
    edges = sum(graph[t].edge_index.size(1) for t in graph.edge_types)
    return nodes / num_graphs, edges / num_graphs


def _train_batches(datamodule, window: int, count: int, device: torch.device) -> list:
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
    batches = _train_batches(datamodule, model.window, statistics_batches + warmup + train_batches, device)
    model.fit_normalizers(batches[:statistics_batches])
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=model.hparams.lr)
    iteration, construction, graphs = [], [], []
    for i, batch in enumerate(batches[statistics_batches:]):
        with _GraphTimer(batch, device) as timer:
            _sync(device)
            start = time.perf_counter()
            _iteration(model, batch, optimizer)
            _sync(device)
            elapsed = time.perf_counter() - start
        if i >= warmup:
            iteration.append(elapsed)
            construction.append(timer.seconds)
            graphs.append(batch.num_graphs * (batch.num_steps - 1))
    # graph sizes: the timed batches' first states, with and without their point clouds
    sizes = {}
    with torch.no_grad():
        for use_points in ((True, False) if model.uses_points else (False,)):
            per_batch = [_graph_size(b.graph(0, b.positions[0], use_points, model.connectivity, model.with_material),
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
        "graph construction ms per batch": _median_ms(construction),
        "graph construction share": statistics.median(construction) / median,
        "matrix GFLOP per iteration": flops / 1e9,
        "matrix GFLOP/s (per iteration time)": flops / 1e9 / median,
        "matmul share of CPU time (profiler)": matmul_share,
    }
    for use_points, (nodes, edges) in sizes.items():
        group = "with points" if use_points else "without points"
        row[f"nodes per graph ({group})"], row[f"edges per graph ({group})"] = nodes, edges
    reference = REFERENCE_TRAIN_GRAPHS_PER_S.get(name)
    if reference:
        row["speed-up vs reference"] = row["graphs/s"] / reference
    return row


def _bench_rollout(model, batch, schedule, steps: int, repeats: int, device: torch.device) -> dict:
    from .evaluation.rollout import rollout

    model.eval()
    with torch.no_grad(), _GraphTimer(batch, device) as timer:
        rollout(model.step, batch, schedule, model.connectivity, model.with_material, steps=1)  # warm-up
        times, shares = [], []
        for _ in range(repeats):
            timer.reset()
            _sync(device)
            start = time.perf_counter()
            rollout(model.step, batch, schedule, model.connectivity, model.with_material, steps=steps)
            _sync(device)
            elapsed = time.perf_counter() - start
            times.append(elapsed / steps)
            shares.append(timer.seconds / elapsed)
    return {"ms per step": _median_ms(times), "graph construction share": statistics.median(shares)}


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
    time inside `TrajectoryBatch.graph` within the same rollouts.
    """
    from .data.module import SimulationDataModule
    from .evaluation.schedules import EveryK, Never
    from .graphs.state import TrajectoryBatch
    from .models.simulators import MODELS

    device = _resolve_device(device)
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
        for schedule in ((EveryK(1), Never()) if model.uses_points else (Never(),)):
            print(f"bench models: {name} rollout {schedule} ...", flush=True)
            one = _bench_rollout(model, single, schedule, steps, repeats, device)
            batched = _bench_rollout(model, many, schedule, steps, repeats, device)
            per_trajectory = batched["ms per step"] / rollout_trajectories
            target = REFERENCE_ROLLOUT_MS[model.uses_points and schedule.uses_points(0)] / ROLLOUT_SPEEDUP_GOAL
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
    _print_table(train_rows)
    print(f"\nrollout: {steps} steps, median of {repeats} whole rollouts; 1 vs {rollout_trajectories} trajectories")
    _print_table(rollout_rows)
    goals = _goals(train_rows, rollout_rows, rollout_trajectories)
    train_rows[0]["GEMM rate GFLOP/s"] = peak  # into the CSV (once)
    print("\ngoals:")
    for line in goals:
        print(f"  {line}")
    rows = _csv_rows(train_rows, rollout_rows, dataset, device, machine)
    if output is not None:
        import csv

        Path(output).parent.mkdir(parents=True, exist_ok=True)
        with open(output, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        print(f"\nwrote {len(rows)} rows to {output}")
    return rows


def _print_table(rows: list[dict]) -> None:
    keys = list(dict.fromkeys(k for row in rows for k in row))
    cells = [[_fmt(k, row.get(k, "")) for k in keys] for row in rows]
    # one row per quantity, one column per model / measurement: the keys are long, the values short
    header = ["quantity"] + [" ".join(str(row[k]) for k in ("model", "schedule") if k in row) for row in rows]
    table = [[k] + [c[i] for c in cells] for i, k in enumerate(keys) if k not in ("model", "schedule")]
    widths = [max(len(r[j]) for r in [header] + table) for j in range(len(header))]
    for r in [header] + table:
        print("  " + "  ".join(v.ljust(w) if j == 0 else v.rjust(w) for j, (v, w) in enumerate(zip(r, widths))))


def _fmt(key: str, value) -> str:
    if isinstance(value, float):
        if "share" in key:
            return f"{value:.0%}"
        return f"{value:.3g}" if abs(value) < 100 else f"{value:.0f}"
    return str(value)


def _goals(train_rows: list[dict], rollout_rows: list[dict], trajectories: int) -> list[str]:
    def met(ok: bool) -> str:
        return "met" if ok else "NOT met"

    lines = []
    for row in train_rows:
        reference = REFERENCE_TRAIN_GRAPHS_PER_S.get(row["model"])
        if reference:
            lines.append(f"training {row['model']}: {row['graphs/s']:.1f} graphs/s vs >= {TRAIN_SPEEDUP_GOAL * reference:.0f} "
                         f"(3x the reference {reference:.0f}): {met(row['graphs/s'] >= TRAIN_SPEEDUP_GOAL * reference)}")
        share = row["share of the GEMM rate"]
        lines.append(f"training {row['model']}: matrix work at {share:.0%} of the GEMM rate vs >= {GEMM_SHARE_GOAL:.0%}: "
                     f"{met(share >= GEMM_SHARE_GOAL)}")
    for row in rollout_rows:
        label = f"rollout {row['model']} {row['schedule']}"
        share = row[f"graph share ({trajectories} traj.)"]
        share_one = row["graph share (1 traj.)"]
        lines.append(f"{label}: graph construction {share_one:.0%} (1 traj.) / {share:.0%} ({trajectories} traj.) "
                     f"of a step vs < {GRAPH_SHARE_GOAL:.0%}: {met(max(share, share_one) < GRAPH_SHARE_GOAL)}")
        lines.append(f"{label}: batched throughput {row['throughput ratio']:.1f}x one at a time vs >= {BATCHING_GOAL:.0f}x: "
                     f"{met(row['throughput ratio'] >= BATCHING_GOAL)}")
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
