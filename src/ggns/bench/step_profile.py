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
3. counted: the host reads per step (`HostReads`: every call that returns a device value to Python, copies
   it to the host or whose output shape depends on data, each a synchronization on a GPU; reads of host
   tensors marked by `phases.host_side` are not counted), by phase and call site, with the hot path's GPU
   code paths taken on the CPU too (`checks.gpu_code_paths`: on the CPU the checks read at once, where a
   read is free); on a GPU also the synchronizations CUDA itself reports (`torch.cuda.set_sync_debug_mode`).
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
# device must finish before the host knows it): each is a synchronization on a GPU. By name: the mode sees
# `torch.f(x)` and `x.f()` under the same name (`equal`, `nonzero`, `unique`, ...), a torch_cluster op too.
READS = frozenset({
    # a value to Python
    "item", "tolist", "__bool__", "__int__", "__float__", "__complex__", "__index__", "is_nonzero", "equal",
    "allclose", "__contains__", "__format__", "__repr__",
    # a copy to the host: on a GPU a device-to-host copy; a CPU tensor here stands for a device one, as it does
    # for every read above (host tensors marked by `phases.host_side` are exempt)
    "cpu", "numpy", "__array__",
    # an output size that is data
    "nonzero", "argwhere", "masked_select", "unique", "unique_consecutive", "bincount",  # bincount: its max
    # torch_cluster's neighbour searches (their edge counts are data)
    "radius", "knn",
})
# Reads only with some arguments (`_reads_by_arguments`):
# - `where` given the condition alone (= `nonzero`);
# - `to` the CPU (as `cpu`; `to(other)` only where other is on the CPU and the tensor is not), `copy_` into a
#   host tensor from a device one;
# - `__getitem__` and `__setitem__` by a boolean mask (its output size is data) or by a 0-d integer tensor
#   (read back as a Python int), `index_put(_)` by a boolean mask; but an assignment of one host value (a
#   Python number) through one mask is a `masked_fill_` in PyTorch, no read;
# - `repeat_interleave` by a tensor of repeats without `output_size` (the total is data);
# - `isin` where PyTorch takes its sorting path without `assume_unique` (two `unique`s): when the test elements
#   number at least 10 x (the elements)^0.145 (numpy's heuristic, which PyTorch copies).
# Not reads: `nonzero_static` (its size is given), `isclose`, `any`, `all` and other reductions to a 0-d tensor
# (until its `__bool__` or `item`), `__len__` (a shape).
READS_BY_ARGUMENTS = frozenset({"where", "to", "copy_", "__getitem__", "__setitem__", "index_put_", "index_put",
                                "repeat_interleave", "isin"})
GEMM_KERNELS = ("gemm", "cutlass", "xmma", "cublas", "matmul")
SOURCE = str(Path(__file__).resolve().parents[1])


def _index_items(index) -> tuple:
    return tuple(index) if isinstance(index, (tuple, list)) else (index,)


def _is_mask(item) -> bool:
    return isinstance(item, torch.Tensor) and item.dtype in (torch.bool, torch.uint8)


def _is_reading_index(index) -> bool:
    """A boolean mask (its output size is data) or a 0-d integer tensor (read back as a Python int)."""
    return any(_is_mask(i) or (isinstance(i, torch.Tensor) and i.dim() == 0 and not i.is_floating_point()
                               and not i.is_complex()) for i in _index_items(index))


def _is_masked_fill(target: torch.Tensor, index, value) -> bool:
    """An assignment that PyTorch turns into `masked_fill_` (no read): one mask as the only tensor index and one
    value from the host (a Python number, or a one-element tensor on the CPU while the target is not, or marked
    by `phases.host_side`)."""
    tensors = [i for i in _index_items(index) if isinstance(i, torch.Tensor)]
    if len(tensors) != 1 or not _is_mask(tensors[0]):
        return False
    if isinstance(value, (bool, int, float)):
        return True
    return isinstance(value, torch.Tensor) and value.numel() == 1 and value.device.type == "cpu" and (
        target.device.type != "cpu" or phases.is_host_side(value))


def _target_device(args, kwargs) -> torch.device | None:
    """The device of `Tensor.to(...)`'s arguments, None if it names none."""
    if "device" in kwargs and kwargs["device"] is not None:
        return torch.device(kwargs["device"])
    for arg in args[1:]:
        if isinstance(arg, (str, torch.device)):
            return torch.device(arg)
        if isinstance(arg, int) and not isinstance(arg, bool):
            return torch.device("cuda", arg)
    return None


def _reads_by_arguments(name: str, args: tuple, kwargs: dict) -> bool:
    """Whether a call of READS_BY_ARGUMENTS reads (the comment above it)."""
    if name == "where":
        return len(args) + len(kwargs) == 1
    if name == "to":
        if len(args) > 1 and isinstance(args[1], torch.Tensor):  # to(other): other's device and dtype
            return args[1].device.type == "cpu" and args[0].device.type != "cpu"
        device = _target_device(args, kwargs)
        return device is not None and device.type == "cpu"
    if name == "copy_":  # host.copy_(device tensor)
        return len(args) > 1 and args[0].device.type == "cpu" and args[1].device.type != "cpu"
    if name == "__getitem__":
        return len(args) > 1 and _is_reading_index(args[1])
    if name == "__setitem__":
        return len(args) > 2 and _is_reading_index(args[1]) and not _is_masked_fill(args[0], args[1], args[2])
    if name in ("index_put_", "index_put"):
        indices = args[1] if len(args) > 1 else kwargs.get("indices", ())
        values = args[2] if len(args) > 2 else kwargs.get("values")
        accumulate = args[3] if len(args) > 3 else kwargs.get("accumulate", False)
        return any(_is_mask(i) for i in indices) and (accumulate or not _is_masked_fill(args[0], indices, values))
    if name == "repeat_interleave":
        output_size = args[3] if len(args) > 3 else kwargs.get("output_size")
        if output_size is not None:
            return False
        if len(args) == 1 and "repeats" not in kwargs:  # torch.repeat_interleave(repeats)
            return isinstance(args[0], torch.Tensor)
        repeats = args[1] if len(args) > 1 else kwargs.get("repeats")
        return isinstance(repeats, torch.Tensor)
    if name == "isin":
        elements = args[0] if args else kwargs.get("elements")
        test = args[1] if len(args) > 1 else kwargs.get("test_elements")
        if not (isinstance(elements, torch.Tensor) and isinstance(test, torch.Tensor)) or kwargs.get("assume_unique") \
                or elements.numel() == 0:
            return False
        return test.numel() >= int(10.0 * elements.numel() ** 0.145)
    return False


def is_read(func, args: tuple = (), kwargs: dict | None = None) -> bool:
    """Whether a call of `func` reads the device (READS, READS_BY_ARGUMENTS), ignoring `phases.host_side`."""
    name = getattr(func, "__name__", str(func))
    return name in READS or (name in READS_BY_ARGUMENTS and _reads_by_arguments(name, args, kwargs or {}))


class HostReads(TorchFunctionMode):
    """Counts host reads (module docstring; READS, READS_BY_ARGUMENTS) by (phase, call site in ggns, function)
    while active. The mode sees what the hot path calls, not what those calls call in turn (a read inside a
    torch function called from Python is counted as that function's, once)."""

    def __init__(self):
        super().__init__()
        self.counts: collections.Counter = collections.Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if is_read(func, args, kwargs) and not (args and isinstance(args[0], torch.Tensor)
                                                and phases.is_host_side(args[0])):
            site = _call_site()
            if site is not None:
                self.counts[(phases.current(), site, getattr(func, "__name__", str(func)))] += 1
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


def _optimizer_step(model, batch, optimizer, static: bool = False) -> None:
    if static:  # graphs, forward, backward and Adam in one static step (`models.static_training`)
        model.static_train_step().step(batch, optimizer)
        return
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
    checks = sum(n for (p, _, _), n in reads.counts.items() if p == "check reads")
    row["host reads per step"] = (sum(reads.counts.values()) - checks) / count
    row["deferred-check reads per step"] = checks / count  # the checks read at their interval, not every step
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
    (`models.speed.compile_processor`, timed after the warm-up compiled them); static: the whole training
    step and rollout step on static shapes (`models.static_training.StaticTrainStep`,
    `evaluation.capture.StaticStep`: one CUDA-graph replay each on a GPU, no host read)."""
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
    optimizer = simulator.configure_optimizers()["optimizer"]  # the fused Adam a fit uses
    training = batches[2:]
    report = {"model": model, "dataset": dataset, "device": str(device), "latent": latent, "blocks": blocks,
              "batch size": batch_size, "compiled processor": compile, "static steps": static,
              "machine": _machine(device), "GEMM GFLOP/s": gemm_rate(device)}
    print(f"bench profile: {model} training steps ...", flush=True)
    report["training"] = _measure("training", lambda i: _optimizer_step(simulator, training[i % len(training)],
                                                                         optimizer, static), steps, warmup, device)
    simulator.raise_if_checks_failed()
    report["training"]["matrix GFLOP per step"] = _matrix_flops(lambda: _optimizer_step(simulator, training[0],
                                                                                         optimizer, static)) / 1e9
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
    options = [name for name in ("compiled processor", "static steps") if report.get(name)]
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
