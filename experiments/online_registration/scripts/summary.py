"""The registration comparison's table from `bench online-study` raw files: per setting (sensor, frames every r
ticks, latency) the mean tracking error over the trajectories of the grounded GGNS, each registered variant and
the blind baselines, which run is lowest (blind ones included), GGNS over MGN + registration (the ratio of the means) and on how many
trajectories GGNS is below it, and the milliseconds per tick:

    python experiments/online_registration/scripts/summary.py docs/results/online_registration/tissue/online_study_raw.csv \
        [more raw files of the same task] --output docs/results/online_registration/tissue_summary.md

Writes the markdown table (and a CSV beside it, the same name with .csv)."""
from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

import numpy as np

SHORT = {"ggns": "GGNS", "mgn + registration": "MGN + reg", "mgn_m + registration": "MGN(M) + reg",
         "static + registration": "static + reg", "ggns + registration": "GGNS + reg"}


def short(model: str) -> str:
    """'tissue/mgn + registration' -> 'MGN + reg'; blind models keep their shipped name."""
    name = model.split("/", 1)[-1]
    return SHORT.get(name, model)


def read(paths: list[Path]) -> list[dict]:
    rows = []
    for path in paths:
        with path.open() as f:
            rows += list(csv.DictReader(f))
    return rows


def summarize(rows: list[dict]) -> list[dict]:
    """One row per setting: {sensor, every, latency, trajectories, <run>: mean MSE, <run> ms: mean ms per tick,
    lowest, ggns_over_registered_mgn, ggns_below_registered_mgn}; blind runs as columns of every setting."""
    blind = defaultdict(dict)  # model -> trajectory -> mse
    settings = defaultdict(lambda: defaultdict(dict))  # (sensor, every, latency) -> run -> trajectory -> (mse, ms)
    for r in rows:
        mse, ms = float(r["tracking mse"]), float(r["ms per tick"]) if r.get("ms per tick") else float("nan")
        if r["every"] == "never":
            name = r["model"].split("/", 1)[-1]
            blind[{"ggns": "GGNS", "mgn": "MGN", "mgn_m": "MGN(M)"}.get(name, name) + " blind"][int(r["trajectory"])] = (mse, ms)
        else:
            settings[(r["sensor"], int(r["every"]), int(r["latency"]))][short(r["model"])][int(r["trajectory"])] = (mse, ms)
    out = []
    for (sensor, every, latency), runs in sorted(settings.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][2])):
        trajectories = sorted(set.intersection(*(set(v) for v in runs.values())))
        row = {"sensor": sensor, "every": every, "latency": latency, "trajectories": len(trajectories)}
        for run, values in list(runs.items()) + [(k, v) for k, v in blind.items() if not k.startswith("GGNS")]:
            row[run] = float(np.mean([values[t][0] for t in trajectories]))
            row[f"{run} ms"] = float(np.mean([values[t][1] for t in trajectories]))
        row["lowest"] = min([*runs, *(k for k in blind if not k.startswith("GGNS"))], key=lambda k: row[k])
        if "GGNS" in runs and "MGN + reg" in runs:
            row["ggns_over_registered_mgn"] = row["GGNS"] / row["MGN + reg"]
            row["ggns_below_registered_mgn"] = sum(runs["GGNS"][t][0] < runs["MGN + reg"][t][0] for t in trajectories)
        out.append(row)
    return out


def markdown(summary: list[dict]) -> str:
    runs = [k for k in ("GGNS", "MGN + reg", "MGN(M) + reg", "static + reg", "GGNS + reg", "MGN blind", "MGN(M) blind")
            if any(k in r for r in summary)]
    head = ["sensor", "every r", "latency", "trajectories", *runs, "lowest", "GGNS / MGN + reg (GGNS below on)",
            "ms per tick: GGNS / MGN + reg"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in summary:
        cells = [r["sensor"], str(r["every"]), str(r["latency"]), str(r["trajectories"]),
                 *(f"{r[k]:.2e}" if k in r else "-" for k in runs), r["lowest"],
                 f"{r['ggns_over_registered_mgn']:.2f} ({r['ggns_below_registered_mgn']} of {r['trajectories']})"
                 if "ggns_over_registered_mgn" in r else "-",
                 f"{r.get('GGNS ms', float('nan')):.0f} / {r.get('MGN + reg ms', float('nan')):.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("raw", nargs="+", type=Path)
    parser.add_argument("--output", required=True, type=Path)
    args = parser.parse_args(argv)
    summary = summarize(read(args.raw))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(markdown(summary))
    keys = list(dict.fromkeys(k for r in summary for k in r))
    with args.output.with_suffix(".csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(summary)
    print(args.output.read_text())
    return args.output


if __name__ == "__main__":
    main()
