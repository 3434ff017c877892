"""`python -m ggns bench precision`: what the reduced-precision options do to the shipped simulators' test
metrics (and their rollout time): float32 (the reference), bf16 autocast (`torch.autocast`, what Lightning's
`--trainer.precision bf16-mixed` applies in test) and, on a GPU, TF32 matrix products
(`torch.set_float32_matmul_precision("high")`, the `MatmulPrecision` callback). Each mode evaluates the same
test trajectories with the model's own `evaluate` (full rollouts per schedule, one-step error); the report
gives each metric's mean and its ratio to float32's.
"""
from __future__ import annotations

import contextlib
import time
from pathlib import Path

import torch

from ..batch import TrajectoryBatch
from ..data.module import SimulationDataModule
from ..evaluation.schedules import effective_schedules, parse_schedule
from ..pretrained import load_model
from ..reports import write_csv, write_text
from .timing import resolve_device, sync

MODES = ("float32", "bf16", "tf32")


@contextlib.contextmanager
def precision_mode(mode: str, device: torch.device):
    """Within the block, the model runs in `mode` (module docstring)."""
    if mode == "float32":
        yield
    elif mode == "bf16":
        with torch.autocast(device.type, dtype=torch.bfloat16):
            yield
    elif mode == "tf32":
        if device.type != "cuda":
            raise ValueError("tf32 needs a CUDA device (TF32 is an NVIDIA tensor-core format)")
        previous = torch.get_float32_matmul_precision()
        torch.set_float32_matmul_precision("high")
        try:
            yield
        finally:
            torch.set_float32_matmul_precision(previous)
    else:
        raise ValueError(f"unknown precision mode {mode!r}; known: {MODES}")


def bench_precision(checkpoints: dict[str, str], dataset: str = "plate_small", trajectories: int = 9,
                    schedules: tuple[str, ...] = ("every:1", "every:5", "never"), modes: tuple[str, ...] = MODES,
                    device: str = "cpu", output_dir: str | None = None) -> list[dict]:
    device = resolve_device(device)
    modes = tuple(m for m in modes if m != "tf32" or device.type == "cuda")
    if "float32" not in modes:
        modes = ("float32",) + modes
    data = SimulationDataModule(dataset, generate_missing=False)
    batch = TrajectoryBatch.from_trajectories(data.trajectories("test")[:trajectories], device=device)
    rows = []
    for name, spec in checkpoints.items():
        model = load_model(spec, map_location="cpu").to(device).eval()
        plans = effective_schedules([parse_schedule(s) for s in schedules], model.uses_points)
        reference = None
        for mode in modes:
            print(f"bench precision: {name} {mode} ...", flush=True)
            with precision_mode(mode, device):
                sync(device)
                start = time.perf_counter()
                metrics = model.evaluate(batch, schedules=plans, m_plus_10=False, iou=False)
                sync(device)
                seconds = time.perf_counter() - start
            means = {k: float(v.double().mean()) for k, v in metrics.items() if "mse" in k}
            reference = means if mode == "float32" else reference
            for key, value in means.items():
                rows.append({"model": name, "mode": mode, "metric": key, "mean": value,
                             "ratio to float32": value / reference[key] if reference[key] else float("nan"),
                             "evaluation seconds": seconds})
    text = precision_markdown(rows, dataset, trajectories, device)
    print("\n" + text)
    if output_dir is not None:
        write_csv(Path(output_dir) / "precision.csv", rows, list(rows[0]))
        write_text(Path(output_dir) / "precision.md", text)
    return rows


def precision_markdown(rows: list[dict], dataset: str, trajectories: int, device) -> str:
    lines = [f"bench precision on {trajectories} test trajectories of {dataset}, {device}:", "",
             "| model | metric | mode | mean | ratio to float32 | evaluation s |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['model']} | {r['metric']} | {r['mode']} | {r['mean']:.4g} | {r['ratio to float32']:.4f} | "
                     f"{r['evaluation seconds']:.1f} |")
    return "\n".join(lines) + "\n"
