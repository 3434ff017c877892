"""Milliseconds per frame of the registration alone (`ggns.online.registration.register`, the task's settings of
conf/online/registration.yaml) on one thread: each tick of a task's first test trajectory, the shipped MGN's blind
prediction of that tick registered to the tick's stored flawless cloud, after a warm-up of 5 frames:

    python experiments/online_registration/scripts/registration_speed.py --task tissue --data-dir data/tissue_cpu \
        --output docs/results/online_registration/speed_tissue.csv

Writes one row per frame (tick, points, milliseconds) and prints the median and quartiles."""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
import torch


def main(argv: list[str] | None = None) -> None:
    from ggns.batch import TrajectoryBatch
    from ggns.bench.online import DATA_PRESETS, first_test_trajectories
    from ggns.bench.online_study import registration_settings
    from ggns.online.registration import ObjectGeometry, register
    from ggns.pretrained import load

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=sorted(DATA_PRESETS), required=True)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model = load(f"{args.task}/mgn").eval()
    _, (world,) = first_test_trajectories(DATA_PRESETS[args.task], 1, args.data_dir, f"{args.task}/mgn")
    predicted = model.rollout(TrajectoryBatch.from_trajectories([world]), "never")
    settings = registration_settings(args.task)
    geometry = ObjectGeometry(world.cells, world.dim, world.fixed, torch.device("cpu"))
    rows = []
    for t in range(world.num_steps):
        cloud = torch.as_tensor(world.point_cloud(t))
        start = time.perf_counter()
        register(settings, geometry, predicted[t], cloud)
        rows.append({"tick": t, "points": len(cloud), "ms": 1e3 * (time.perf_counter() - start)})
    timed = [r["ms"] for r in rows[5:]]
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with args.output.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    q1, median, q3 = np.percentile(timed, [25, 50, 75])
    print(f"{args.task}: registration of {len(timed)} frames ({np.mean([r['points'] for r in rows]):.0f} points, "
          f"{len(world.rest_positions)} nodes): median {median:.1f} ms (quartiles {q1:.1f}-{q3:.1f}), 1 thread")


if __name__ == "__main__":
    main()
