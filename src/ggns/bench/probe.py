"""One timed measurement of whichever `ggns` is first on sys.path, as a script: `bench ab` runs it by
path in subprocesses with PYTHONPATH set to each source tree in turn (this checkout and a baseline
commit), so it imports nothing of its own tree and uses only the API both trees share (data module,
models, `window_loss`, the rollout engine, a Lightning fit). Prints one JSON line.

    python probe.py train  MODEL LATENT BLOCKS BATCH [ITERATIONS] [static]  ms per optimizer iteration
    python probe.py rollout MODEL LATENT BLOCKS TRAJECTORIES SCHEDULE [static]   ms per rollout step
    python probe.py fit    MODEL LATENT BLOCKS BATCH [STEPS]          Lightning fit steps/s
    python probe.py ops    train|rollout MODEL LATENT BLOCKS SIZE [SCHEDULE]  operators per step (torch.profiler)
    python probe.py import MODULE                                    ms to import MODULE in this fresh process

`static`: roll out with the model's static step where its tree has one (`GraphSimulator.rollout_step`),
else its plain step; train with its static training step where its tree has one
(`GraphSimulator.static_train_step`), else its plain step. The device is GGNS_PROBE_DEVICE (default cpu). Data: plate_small (generated
beforehand); weights random (speed does not depend on them), seeded.
"""
from __future__ import annotations

import itertools
import json
import os
import statistics
import sys
import time
import warnings

DEVICE = os.environ.get("GGNS_PROBE_DEVICE", "cpu")


def _sync():
    import torch

    if DEVICE.startswith("cuda"):
        torch.cuda.synchronize()


def _setup(model_name: str, latent: int, blocks: int, batch_size: int):
    import torch
    from ggns.data.module import SimulationDataModule
    from ggns.models.simulators import MODELS

    warnings.filterwarnings("ignore")
    torch.manual_seed(0)
    data = SimulationDataModule("plate_small", batch_size=batch_size, generate_missing=False)
    model = MODELS[model_name](dim=data.dim, latent=latent, blocks=blocks).to(DEVICE)
    data.train_window = model.window
    return torch, data, model


def _batches(data, count: int) -> list:
    batches = []
    while len(batches) < count:
        batches += list(itertools.islice(iter(data.train_dataloader()), count - len(batches)))
    return [b.to(DEVICE) for b in batches]


def train(model_name: str, latent: int, blocks: int, batch_size: int, iterations: int | str = 30,
          mode: str = "eager") -> dict:
    if iterations == "static":  # train MODEL LATENT BLOCKS BATCH static
        iterations, mode = 30, "static"
    torch, data, model = _setup(model_name, latent, blocks, batch_size)
    batches = _batches(data, iterations + 10)
    model.fit_normalizers(batches[:5])
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4, fused=True)  # a captured step needs it
    static = model.static_train_step() if mode == "static" and hasattr(model, "static_train_step") else None
    times = []
    for i, batch in enumerate(batches[5:]):
        _sync()
        start = time.perf_counter()
        if static is not None:
            static.step(batch, optimizer)
        else:
            loss = model.window_loss(batch, train=True)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        _sync()
        if i >= 5:
            times.append(time.perf_counter() - start)
    return {"ms": 1e3 * statistics.median(times), "iterations": len(times)}


def rollout(model_name: str, latent: int, blocks: int, trajectories: int, schedule: str, mode: str = "eager",
            steps: int = 20) -> dict:
    torch, data, model = _setup(model_name, latent, blocks, 8)
    from ggns.batch import TrajectoryBatch
    from ggns.evaluation.rollout import rollout as run
    from ggns.evaluation.schedules import parse_schedule

    model.fit_normalizers(_batches(data, 4))
    model.eval()
    tests = data.trajectories("test")
    batch = TrajectoryBatch.from_trajectories([tests[i % len(tests)] for i in range(trajectories)], device=DEVICE)
    plan = parse_schedule(schedule)
    step = model.step
    if mode == "static" and hasattr(model, "rollout_step"):
        model.static_rollouts = True
        step = model.rollout_step()
    times = []
    with torch.no_grad():
        for i in range(6):
            _sync()
            start = time.perf_counter()
            run(step, batch, plan, model.connectivity, model.with_material, steps=steps)
            _sync()
            if i >= 1:
                times.append((time.perf_counter() - start) / steps)
    return {"ms": 1e3 * statistics.median(times), "rollouts": len(times)}


def fit(model_name: str, latent: int, blocks: int, batch_size: int, steps: int = 200) -> dict:
    torch, data, model = _setup(model_name, latent, blocks, batch_size)
    import pytorch_lightning as pl

    class Clock(pl.Callback):
        def on_train_batch_end(self, trainer, *args):
            if trainer.global_step == 20:
                self.start = time.perf_counter()
            self.end, self.steps = time.perf_counter(), trainer.global_step

    clock = Clock()
    trainer = pl.Trainer(max_steps=steps, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0,
                         callbacks=[clock], log_every_n_steps=50,
                         accelerator="gpu" if DEVICE.startswith("cuda") else "cpu", devices=1)
    trainer.fit(model, datamodule=data)
    return {"steps/s": (clock.steps - 20) / (clock.end - clock.start), "steps": clock.steps - 20}


def ops(step: str, model_name: str, latent: int, blocks: int, size: int, schedule: str = "every:1") -> dict:
    """Operators (leaf aten ops, what a GPU launches as kernels) per training iteration (batch `size`) or per
    rollout step (`size` trajectories), counted by torch's profiler over 3 iterations or 10 steps."""
    torch, data, model = _setup(model_name, latent, blocks, size if step == "train" else 8)
    from torch.profiler import profile

    batches = _batches(data, 8)
    model.fit_normalizers(batches[:3])
    if step == "train":
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)

        def run():
            for batch in batches[3:6]:
                loss = model.window_loss(batch, train=True)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
        count = 3
    else:
        from ggns.batch import TrajectoryBatch
        from ggns.evaluation.rollout import rollout as roll
        from ggns.evaluation.schedules import parse_schedule

        model.eval()
        tests = data.trajectories("test")
        batch = TrajectoryBatch.from_trajectories([tests[i % len(tests)] for i in range(size)], device=DEVICE)

        def run():
            with torch.no_grad():
                roll(model.step, batch, parse_schedule(schedule), model.connectivity, model.with_material, steps=10)
        count = 10
    run()
    with profile() as prof:
        run()
    leaves = [e for e in prof.events() if e.name.startswith("aten::")
              and not any(c.name.startswith("aten::") for c in e.cpu_children)]
    return {"ops": len(leaves) / count}


def import_module(module: str) -> dict:
    """Milliseconds to import `module` (with all it imports) in this process, which has imported nothing of
    ggns, torch or Lightning before: the part of a command's start-up that a source tree decides (the
    process's own start, the same for both trees, is not counted)."""
    import importlib

    start = time.perf_counter()
    importlib.import_module(module)
    return {"ms": (time.perf_counter() - start) * 1e3}


def main(argv: list[str]) -> None:
    kind, *rest = argv
    numbers = [int(v) if v.isdigit() else v for v in rest]
    result = {"train": train, "rollout": rollout, "fit": fit, "ops": ops, "import": import_module}[kind](*numbers)
    print(json.dumps({"probe": " ".join(argv), **result}))


if __name__ == "__main__":
    main(sys.argv[1:])
