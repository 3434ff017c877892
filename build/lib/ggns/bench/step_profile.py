"""`python -m ggns bench profile`: where the time of a training step and of a rollout step goes.

For one model on one device, three passes over the same prepared inputs:
1. timed: `steps` steps after `warmup`, the median wall time per step (the device synchronized around
   each step, so that it is the step's own time);
2. profiled (`torch.profiler`, with the hot path's named phases, `ggns.phases`): per phase (graph
   construction, encoder, processor, decoder, loss, backward, optimizer, checks, and the rest) its share
   of the step's wall time and its operator count; a leaf operator is what a GPU launches as a kernel
   (on a GPU the kernel launches themselves are counted); the share of operator time in matrix products
   (on the CPU of their self time, on a GPU of kernel time) and the matrix rate against the machine's
   GEMM rate (`bench.models.gemm_rate`);
3. counted: the host reads per step (`HostReads`: every call that returns a device value to Python or
   whose output shape depends on data, each a synchronization on a GPU; reads of host tensors marked by
   `phases.host_side` are not counted), by phase and call site, with the hot path's GPU code paths taken
   on the CPU too (`checks.gpu_code_paths`: on the CPU the checks read at once, where a read is free);
   on a GPU also the synchronizations CUDA itself reports (`torch.cuda.set_sync_debug_mode`).
Optionally (`fit_steps`) a Lightning fit of the same model, batch size and data, steps/s against the
bare loop of pass 1 (`lightning efficiency`: the loop's time per step / the fit's).
"""
from __future__ import annotations

import collections
import statistics
import time
import traceback
import warnings
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode

from .. import phases
from ..checks import gpu_code_paths
from ..batch import TrajectoryBatch
from ..data.module import SimulationDataModule
from ..evaluation.rollout import DEVICE_CHECK_EVERY, rollout
from ..evaluation.schedules import parse_schedule
from ..models.simulators import MODELS
from ..models.speed import compile_processor
from ..reports import write_json, write_text
from .models import MATMUL_OPS, train_batches_on, gemm_rate
from .timing import resolve_device, sync

# Calls that read a device value back to the host, or whose output shape depends on the data (the
# device must finish before the host knows it): each is a synchronization on a GPU.
READS = {"item", "tolist", "__bool__", "__int__", "__float__", "__index__", "numpy", "nonzero", "argwhere",
         "masked_select", "unique", "unique_consecutive", "bincount", "radius", "knn", "nonzero_static"}
GEMM_KERNELS = ("gemm", "cutlass", "xmma", "cublas", "matmul")
SOURCE = str(Path(__file__).resolve().parents[1])


def _is_reading_index(index) -> bool:
    """A boolean mask (its output size is data) or a 0-d integer tensor (read back as a Python int)."""
    items = index if isinstance(index, tuple) else (index,)
    return any(isinstance(i, torch.Tensor) and (i.dtype == torch.bool or (i.dim() == 0 and not i.is_floating_point()))
               for i in items)


class HostReads(TorchFunctionMode):
    """Counts host reads (module docstring) by (phase, call site in ggns, function) while active."""

    def __init__(self):
        super().__init__()
        self.counts: collections.Counter = collections.Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", str(func))
        read = name in READS or (name in ("__getitem__", "__setitem__") and len(args) > 1 and _is_reading_index(args[1])) \
            or (name == "repeat_interleave" and "output_size" not in kwargs and len(args) > 1
                and isinstance(args[1], torch.Tensor))
        if read and not (args and isinstance(args[0], torch.Tensor) and phases.is_host_side(args[0])):
            site = _call_site()
            if site is not None:
                self.counts[(phases.current(), site, name)] += 1
        return func(*args, **kwargs)


def _call_site() -> str | None:
    """file:line function of the innermost ggns frame that is not this module; None for a read inside
    torch.optim (the optimizers keep their step counts on the host unless made capturable)."""
    stack = traceback.extract_stack()[:-2]
    if stack and "torch/optim/" in stack[-1].filename:
        return None
    for frame in reversed(stack):
        if frame.filename.startswith(SOURCE) and not frame.filename.endswith("step_profile.py"):
            return f"{Path(frame.filename).relative_to(SOURCE)}:{frame.lineno} {frame.name}"
    return "outside ggns"


def _optimizer_step(model, batch, optimizer) -> None:
    loss = model.window_loss(batch, train=True)
    with phases.phase("backward"):
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
    with phases.phase("optimizer"):
        optimizer.step()


def _measure(kind: str, run, steps: int, warmup: int, device: torch.device, per_run: int = 1) -> dict:
    """The three passes of the module docstring for `run(i)` (one step, or `per_run` steps)."""
    for i in range(warmup):
        run(i)
    sync(device)
    times = []
    for i in range(steps):
        sync(device)
        start = time.perf_counter()
        run(i)
        sync(device)
        times.append((time.perf_counter() - start) / per_run)
    activities = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA]
                                                           if device.type == "cuda" else [])
    with phases.recording(), torch.profiler.profile(activities=activities) as prof:
        for i in range(steps):
            run(i)
        sync(device)
    reads, cuda_syncs = HostReads(), 0
    with phases.recording(), gpu_code_paths(), reads, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if device.type == "cuda":
            torch.cuda.set_sync_debug_mode("warn")
        try:
            for i in range(steps):
                run(i)
            sync(device)
        finally:
            if device.type == "cuda":
                torch.cuda.set_sync_debug_mode("default")
        cuda_syncs = sum("synchroniz" in str(w.message) for w in caught)
    count = steps * per_run
    row = {"step": kind, "ms per step": 1e3 * statistics.median(times)}
    row.update(_phase_table(prof, count, device))
    # matrix time (profiled pass) over the step's time (timed pass, no profiler)
    row["matrix share of step time"] = row.pop("matrix ms per step") / row["ms per step"]
    row["host reads per step"] = sum(reads.counts.values()) / count
    if device.type == "cuda":
        row["CUDA synchronizations per step"] = cuda_syncs / count
    row["host reads by site"] = {f"{p} | {site} | {name}": n / count for (p, site, name), n in
                                 sorted(reads.counts.items(), key=lambda kv: -kv[1])}
    return row


def _phase_table(prof, count: int, device: torch.device) -> dict:
    """Per phase: wall ms per step and operators (CPU) or kernel launches (CUDA) per step; matrix share."""
    events = list(prof.events())
    ranges = sorted(((e.time_range.start, e.time_range.end, e.name[len("ggns::"):]) for e in events
                     if e.name.startswith("ggns::")), key=lambda r: r[0])
    wall = collections.Counter()
    for start, end, name in ranges:
        wall[name] += (end - start) / 1e3 / count

    def phase_of(t: float) -> str:  # the innermost range holding time t (ranges nest at most once)
        found = "other"
        for start, end, name in ranges:
            if start > t:
                break
            if t <= end:
                found = name
        return found

    if device.type == "cuda":
        units = [e for e in events if "LaunchKernel" in e.name]
        kernels = [e for e in events if e.device_type == torch.autograd.DeviceType.CUDA]
        total = sum(e.time_range.elapsed_us() for e in kernels)
        matrix = sum(e.time_range.elapsed_us() for e in kernels if any(k in e.name.lower() for k in GEMM_KERNELS))
        unit_name = "kernel launches"
    else:
        units = [e for e in events if e.name.startswith("aten::") and not any(c.name.startswith("aten::")
                                                                               for c in e.cpu_children)]
        ops = [e for e in events if not e.name.startswith("ggns::")]
        total = sum(e.self_cpu_time_total for e in ops)
        matrix = sum(e.self_cpu_time_total for e in ops if e.name in MATMUL_OPS)
        unit_name = "operators"
    per_phase = collections.Counter(phase_of(e.time_range.start) for e in units)
    out = {f"{unit_name} per step": len(units) / count,
           "matrix share of operator time" if device.type == "cpu" else "matrix share of kernel time":
               matrix / total if total else float("nan"),
           "matrix ms per step": matrix / 1e3 / count}
    for name in [*phases.PHASES, "other"]:
        if name in wall or per_phase.get(name):
            out[f"{name}: ms"] = wall.get(name, float("nan"))
            out[f"{name}: {unit_name}"] = per_phase.get(name, 0) / count
    return out


def _lightning_fit(model_name: str, dataset: str, batch_size: int, kwargs: dict, steps: int, device) -> float:
    """Steps/s of a Lightning fit (no validation, no logger, no checkpoints) after 10 warm-up steps."""
    import pytorch_lightning as pl

    class Clock(pl.Callback):
        def on_train_batch_end(self, trainer, *args):
            if trainer.global_step == 10:
                self.start = time.perf_counter()
            self.end, self.steps = time.perf_counter(), trainer.global_step

    torch.manual_seed(0)
    data = SimulationDataModule(dataset, batch_size=batch_size, generate_missing=False)
    model = MODELS[model_name](dim=data.dim, **kwargs)
    clock = Clock()
    trainer = pl.Trainer(max_steps=steps + 10, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0, callbacks=[clock],
                         accelerator="gpu" if device.type == "cuda" else "cpu", devices=1)
    trainer.fit(model, datamodule=data)
    return (clock.steps - 10) / (clock.end - clock.start)


def profile(model: str = "ggns", dataset: str = "plate_small", latent: int = 128, blocks: int = 5,
            batch_size: int = 32, rollout_trajectories: int = 1, schedule: str = "every:1", device: str = "cpu",
            steps: int = 10, warmup: int = 3, fit_steps: int = 0, output: str | None = None,
            compile: bool = False, static: bool = False) -> dict:
    """The step profile (module docstring); returns {"training": row, "rollout": row, ...} and writes it
    as JSON and markdown to `output` (a folder) if given. compile: the processor's blocks compiled
    (`models.speed.compile_processor`, timed after the warm-up compiled them); static: rollouts on
    static-shape graphs (`GraphSimulator.static_rollouts`: CUDA-graph replays on a GPU)."""
    device = resolve_device(device)
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; choose from {sorted(MODELS)}")
    if steps < 1 or warmup < 0:
        raise ValueError(f"need steps >= 1 and warmup >= 0, got {steps}, {warmup}")
    torch.manual_seed(0)
    data = SimulationDataModule(dataset, batch_size=batch_size, generate_missing=False)
    kwargs = dict(latent=latent, blocks=blocks)
    simulator = MODELS[model](dim=data.dim, **kwargs).to(device)
    if compile:
        compile_processor(simulator)
    simulator.static_rollouts = static
    batches = train_batches_on(data, simulator.window, 2 + warmup + steps, device)
    simulator.fit_normalizers(batches[:2])
    simulator.train()
    optimizer = torch.optim.Adam(simulator.parameters(), lr=1e-4)
    training = batches[2:]
    report = {"model": model, "dataset": dataset, "device": str(device), "latent": latent, "blocks": blocks,
              "batch size": batch_size, "compiled processor": compile, "static rollouts": static, "machine": _machine(device), "GEMM GFLOP/s": gemm_rate(device)}
    print(f"bench profile: {model} training steps ...", flush=True)
    report["training"] = _measure("training", lambda i: _optimizer_step(simulator, training[i % len(training)],
                                                                         optimizer), steps, warmup, device)
    simulator.raise_if_checks_failed()
    report["training"]["matrix GFLOP per step"] = _matrix_flops(lambda: _optimizer_step(simulator, training[0],
                                                                                         optimizer)) / 1e9
    simulator.eval()
    tests = data.trajectories("test")
    trajectories = TrajectoryBatch.from_trajectories([tests[i % len(tests)] for i in range(rollout_trajectories)],
                                                     device=device)
    plan, per_run = parse_schedule(schedule), min(DEVICE_CHECK_EVERY, trajectories.num_steps - 1)

    def rollout_steps(i):  # the checks read as on a GPU, every DEVICE_CHECK_EVERY steps, whatever the device
        with torch.no_grad():
            rollout(simulator.rollout_step(), trajectories, plan, simulator.connectivity, simulator.with_material, steps=per_run,
                    check_every=DEVICE_CHECK_EVERY)

    print(f"bench profile: {model} rollout steps ({rollout_trajectories} trajectories, {schedule}) ...", flush=True)
    report["rollout"] = _measure(f"rollout ({rollout_trajectories} traj., {schedule})", rollout_steps,
                                 max(1, steps // 2), min(warmup, 1), device, per_run=per_run)
    with torch.no_grad():
        report["rollout"]["matrix GFLOP per step"] = _matrix_flops(rollout_steps) / 1e9 / per_run
    for key in ("training", "rollout"):
        row = report[key]
        rate = row["matrix GFLOP per step"] / (row["ms per step"] / 1e3)
        row["matrix GFLOP/s"], row["share of the GEMM rate"] = rate, rate / report["GEMM GFLOP/s"]
    if fit_steps:
        print(f"bench profile: {model} Lightning fit, {fit_steps} steps ...", flush=True)
        fit = _lightning_fit(model, dataset, batch_size, kwargs, fit_steps, device)
        loop = 1e3 / report["training"]["ms per step"]
        report["lightning fit"] = {"fit steps/s": fit, "bare loop steps/s": loop, "lightning efficiency": fit / loop}
    text = profile_markdown(report)
    print("\n" + text)
    if output is not None:
        write_json(Path(output) / "profile.json", report)
        write_text(Path(output) / "profile.md", text)
        print(f"wrote {Path(output) / 'profile.json'} and {Path(output) / 'profile.md'}")
    return report


def _matrix_flops(run) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        run(0) if run.__code__.co_argcount else run()
    return float(counter.get_total_flops())


def _machine(device: torch.device) -> str:
    import os
    import platform

    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, {torch.get_num_threads()} torch threads"


def profile_markdown(report: dict) -> str:
    options = [name for name in ("compiled processor", "static rollouts") if report.get(name)]
    head = (f"bench profile: {report['model']} (latent {report['latent']}, {report['blocks']} blocks) on "
            f"{report['dataset']}, batch {report['batch size']}, {report['device']} ({report['machine']}), "
            f"GEMM rate {report['GEMM GFLOP/s']:.0f} GFLOP/s" + (f"; {', '.join(options)}" if options else ""))
    lines = [head, ""]
    for key in ("training", "rollout"):
        row = report[key]
        lines += [f"### {row['step']} step", "", "| quantity | value |", "|---|---|"]
        for name, value in row.items():
            if name in ("step", "host reads by site"):
                continue
            text = f"{value:.1%}" if "share" in name else (f"{value:.3g}" if isinstance(value, float) else str(value))
            lines.append(f"| {name} | {text} |")
        lines += ["", "host reads per step by phase, call site and function:", ""]
        lines += [f"- {site}: {n:g}" for site, n in row["host reads by site"].items()] or ["- none"]
        lines.append("")
    if "lightning fit" in report:
        fit = report["lightning fit"]
        lines.append(f"Lightning fit: {fit['fit steps/s']:.2f} steps/s against the bare loop's "
                     f"{fit['bare loop steps/s']:.2f} ({fit['lightning efficiency']:.0%})")
    return "\n".join(lines) + "\n"
