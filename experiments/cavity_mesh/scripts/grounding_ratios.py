"""The grounding gain of a sweep, seed by seed: each seed's MGN full-rollout MSE (and MGN(M)'s) over the
same seed's GGNS k=1 rollout MSE, on the test split, from the sweep's per-seed test metrics:
python experiments/cavity_mesh/scripts/grounding_ratios.py --sweep lightning_logs/sweeps/cavity_mesh_tall_10min
    [--ggns ggns_partition] [--output docs/results/cavity_mesh/sweep_tall_10min/ratios.md]

Writes a table per seed (the metrics and the two ratios), the mean of the per-seed ratios and the ratio of
the seed means (not the same number). A diagnostic for docs/experiments/cavity_mesh.md."""
from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
from pathlib import Path


def seed_metrics(sweep: Path, model: str) -> dict[int, dict[str, float]]:
    """{seed: {metric: mean over the test trajectories}} of one model's finished test runs."""
    found = {}
    for path in sorted(sweep.glob(f"{model}/seed_*_test/test_metrics.json")):
        seed = int(path.parent.name.split("_")[1])
        data = json.loads(path.read_text())
        found[seed] = {k: v["mean"] for k, v in data.items() if isinstance(v, dict) and "mean" in v}
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sweep", required=True)
    parser.add_argument("--ggns", default="ggns_partition")
    parser.add_argument("--output", default=None)
    args = parser.parse_args()
    sweep = Path(args.sweep)
    ggns, mgn, mgn_m = (seed_metrics(sweep, m) for m in (args.ggns, "mgn", "mgn_m"))
    seeds = sorted(set(ggns) & set(mgn))
    if not seeds:
        sys.exit(f"no seed of {sweep} has finished test metrics for both {args.ggns} and mgn")
    rows, over_mgn, over_mgn_m = [], [], []
    for s in seeds:
        k1 = ggns[s]["rollout_mse_k1"]
        r = mgn[s]["rollout_mse_never"] / k1
        over_mgn.append(r)
        rm = mgn_m[s]["rollout_mse_never"] / k1 if s in mgn_m else None
        if rm is not None:
            over_mgn_m.append(rm)
        rows.append(f"| {s} | {k1:.3e} | {ggns[s]['rollout_mse_never']:.3e} | {mgn[s]['rollout_mse_never']:.3e} | "
                    + (f"{mgn_m[s]['rollout_mse_never']:.3e}" if s in mgn_m else "-") + f" | {r:.2f} | "
                    + (f"{rm:.2f}" if rm is not None else "-") + " |")
    mean = lambda xs: statistics.fmean(xs) if xs else float("nan")  # noqa: E731
    lines = [f"`{shlex.join(['python', 'experiments/cavity_mesh/scripts/grounding_ratios.py', *sys.argv[1:]])}`", "",
             f"Test rollout MSE per seed (mean over the test trajectories) of {args.ggns} (k=1 and never), MGN and MGN(M) "
             "(never), and the ratios MGN / GGNS k=1 and MGN(M) / GGNS k=1.", "",
             "| seed | GGNS k=1 | GGNS never | MGN | MGN(M) | MGN / GGNS k=1 | MGN(M) / GGNS k=1 |", "|---|---|---|---|---|---|---|",
             *rows, "",
             f"Mean of the per-seed ratios: MGN / GGNS k=1 {mean(over_mgn):.2f} ({len(over_mgn)} seeds, range "
             f"{min(over_mgn):.2f}-{max(over_mgn):.2f})"
             + (f"; MGN(M) / GGNS k=1 {mean(over_mgn_m):.2f} ({len(over_mgn_m)} seeds, range {min(over_mgn_m):.2f}-{max(over_mgn_m):.2f})"
                if over_mgn_m else "") + ".",
             f"Ratio of the seed means: MGN / GGNS k=1 {mean([mgn[s]['rollout_mse_never'] for s in seeds]) / mean([ggns[s]['rollout_mse_k1'] for s in seeds]):.2f}"
             + (f"; MGN(M) / GGNS k=1 {mean([mgn_m[s]['rollout_mse_never'] for s in sorted(mgn_m) if s in ggns]) / mean([ggns[s]['rollout_mse_k1'] for s in sorted(mgn_m) if s in ggns]):.2f}"
                if over_mgn_m else "") + "."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.output:
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        Path(args.output).write_text(text)


if __name__ == "__main__":
    main()
