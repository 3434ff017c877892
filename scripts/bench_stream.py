"""In-memory against streamed splits (docs/streaming.md): peak resident memory and training speed.

Each case runs in a fresh process (`--case`), so that `resource.getrusage(RUSAGE_SELF).ru_maxrss` is that
case's peak alone: a Lightning fit of `--steps` steps of a small GGNS on the dataset's train split (batches of
32 one-step windows, one process, no DataLoader workers, no validation), through `SimulationDataModule` with
`memory_budget` None (every split in memory) or `--budget` (streamed: `ggns.data.stream`). Reported per case:
the peak RSS, the RSS before the fit (imports, model), training steps/s after `--warmup` steps, and for
the streamed reader the trajectories read and the most bytes its cache kept. Then, after the peak was
taken, the reading cost alone: training windows per second of a fresh train loader over `--steps`
batches (reads and collation, no model; epoch 1's order).

    python scripts/bench_stream.py --data data/plate_small --budget 4MB --steps 150 --repeats 3 \\
        --output docs/results/stream/plate_small

`--data` takes several dataset directories (e.g. the paper-size split and 10x it): every repeat runs
each directory with each of `--readers`, alternated, so that a slower period of the machine hits all.

writes <output>/raw.csv (one row per run), summary.json (medians per reader), command.txt (the command,
the git commit, the machine) and prints the summary.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import resource
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ["data", "reader", "repeat", "peak_rss_mb", "rss_before_fit_mb", "steps_per_s", "loader_windows_per_s", "steps",
          "split_mb_on_disk",
          "trajectories", "cache_reads", "cache_peak_mb", "budget_bytes"]


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kilobytes on Linux


def run_case(args) -> dict:
    """One fit in this process; returns its row (without reader and repeat)."""
    import pytorch_lightning as pl
    import torch

    from ggns.data.module import SimulationDataModule
    from ggns.models.simulators import GGNS

    torch.set_num_threads(1)
    pl.seed_everything(0, verbose=False)
    budget = None if args.case == "memory" else args.budget
    data = SimulationDataModule(args.dataset, data_dir=args.data, batch_size=32, train_window=1,
                                generate_missing=False, seed=0, memory_budget=budget)
    model = GGNS(latent=args.latent, blocks=args.blocks, statistics_batches=4)
    times: list[float] = []

    class Clock(pl.Callback):
        def on_train_batch_end(self, *_):
            times.append(time.perf_counter())

    trainer = pl.Trainer(max_steps=args.steps, limit_val_batches=0, num_sanity_val_steps=0, logger=False,
                         enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                         accelerator="cpu", callbacks=[Clock()])
    before = _rss_mb()
    trainer.fit(model, data)
    peak = _rss_mb()
    measured = times[args.warmup - 1:]
    cache = getattr(trainer.train_dataloader.dataset, "cache", None)
    files, _ = data.files("train")
    loader = data.train_dataloader()  # a fresh dataset: its cache starts empty
    loader.sampler.set_epoch(1)
    start, windows = time.perf_counter(), 0
    for i, batch in enumerate(loader):
        windows += batch.num_graphs
        if i + 1 == args.steps:
            break
    loader_rate = windows / (time.perf_counter() - start)
    return {"peak_rss_mb": round(peak, 1), "rss_before_fit_mb": round(before, 1),
            "steps_per_s": round((len(measured) - 1) / (measured[-1] - measured[0]), 3),
            "loader_windows_per_s": round(loader_rate, 1), "steps": len(times),
            "split_mb_on_disk": round(sum(f.stat().st_size for f in files) / 1e6, 1),
            "trajectories": len(data.trajectories("train")),
            "cache_reads": cache.reads if cache is not None else "",
            "cache_peak_mb": round(cache.peak_bytes / 1e6, 2) if cache is not None else "",
            "budget_bytes": data.memory_budget or ""}


def _git_commit() -> str:
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                           capture_output=True, text=True).stdout.strip()
    return head + (" (with uncommitted changes)" if dirty else "")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, nargs="+",
                        help="dataset directories (train.h5 or train shard files), each run with each reader")
    parser.add_argument("--readers", default="memory,stream", help="comma-separated: memory, stream")
    parser.add_argument("--dataset", default="plate_small", help="data preset the files were made with")
    parser.add_argument("--budget", default="4MB", help="memory_budget of the streamed reader")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--warmup", type=int, default=20, help="steps not timed")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--latent", type=int, default=32)
    parser.add_argument("--blocks", type=int, default=2)
    parser.add_argument("--output", help="folder for raw.csv, summary.json, command.txt")
    parser.add_argument("--case", choices=["memory", "stream"], help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.case:
        (args.data,) = args.data
        print(json.dumps(run_case(args)))
        return
    readers = [r.strip() for r in args.readers.split(",") if r.strip()]
    if not readers or set(readers) - {"memory", "stream"}:
        parser.error(f"--readers: memory and/or stream, got {args.readers!r}")
    rows = []
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT / "src")}
    given = list(argv if argv is not None else sys.argv[1:])  # a later --data replaces the given ones
    for repeat in range(args.repeats):
        for data in args.data:
            for reader in readers:  # alternated, so that a slower period of the machine hits every case
                done = subprocess.run([sys.executable, __file__, *given, "--data", data, "--case", reader], cwd=ROOT,
                                      env=env, capture_output=True, text=True)
                if done.returncode:
                    sys.exit(f"{data} {reader} run failed:\n{done.stderr[-3000:]}")
                row = {"data": data, "reader": reader, "repeat": repeat,
                       **json.loads(done.stdout.strip().splitlines()[-1])}
                print(row, flush=True)
                rows.append(row)
    summary = {f"{data} {reader}": {key: statistics.median(r[key] for r in rows if (r["data"], r["reader"]) == (data, reader))
                                    for key in ("peak_rss_mb", "rss_before_fit_mb", "steps_per_s", "loader_windows_per_s")}
               for data in args.data for reader in readers}
    print(json.dumps(summary, indent=2))
    if args.output:
        out = Path(args.output)
        out.mkdir(parents=True, exist_ok=True)
        with open(out / "raw.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, FIELDS)
            writer.writeheader()
            writer.writerows(rows)
        (out / "summary.json").write_text(json.dumps({"medians": summary, "runs": len(rows)}, indent=2) + "\n")
        command = "python " + " ".join(shlex.quote(a) for a in [os.path.relpath(__file__, ROOT), *sys.argv[1:]])
        (out / "command.txt").write_text(
            f"{command}\ngit commit: {_git_commit()}\nmachine: {platform.machine()}, {os.cpu_count()} cores "
            f"(shared), {platform.python_version()}, OMP_NUM_THREADS=1, niceness {os.nice(0)}\n"
            f"date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n")


if __name__ == "__main__":
    main()
