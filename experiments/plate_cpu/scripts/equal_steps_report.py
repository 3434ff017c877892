"""The learning curves of an equal-step sweep's runs, finished or still running, and the grounding ratio at
equal steps: each run's validations read from its TensorBoard logs, and at every step where GGNS and a
blind baseline both validated, the baseline's full rollout MSE over GGNS's k=1 (the grounding ratio):

    python experiments/plate_cpu/scripts/equal_steps_report.py --sweep lightning_logs/sweeps/plate_equal_steps \
        --output docs/results/plate_equal_steps [--ggns ggns] [--baselines mgn mgn_m] [--seed 0]

Writes validations.csv (one row per run and validation step), ratios.csv (step, baseline, ratio), status.csv
(per run: optimizer steps reached, training seconds, steps per training second, wall minutes from first to
last event, whether the run's fit finished), report.md (the tables) and curves_steps.png. Runs partway
through are reported as far as they went, and status.csv says so. A run whose logs are gone (e.g. it ran on
another machine) is kept from an earlier report's raw files with --earlier DIR: its rows of DIR/validations.csv
and DIR/status.csv, used only for models that have no logs under --sweep.

Also: tests.csv, each tested run's test metrics (the sweep's <model>/seed_<seed>_test/test_metrics.json) and
the test grounding ratios; fit.csv, a power law fitted to GGNS's validation k=1 curve from --fit-from on
(least squares of log MSE on log step) and the step at which that law reaches --target (the paper's plate
GGNS k=1 test MSE, 1.86e-5, by default): an extrapolation of the fitted law, not a measurement."""
from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import numpy as np


REPORTED = ("rollout_mse_k1", "rollout_mse_never", "one_step_mse", "m10_mse")  # the test metrics report.md shows


def read_runs(sweep: Path, models: list[str], seed: int) -> dict[str, dict]:
    """{model: read_scalars of <sweep>/<model>/seed_<seed>} for the runs that have logged anything."""
    from ggns.sweeps.curves import read_scalars

    found = {}
    for model in models:
        directory = sweep / model / f"seed_{seed}"
        if directory.is_dir() and any(directory.glob("events.out.tfevents.*")):
            found[model] = read_scalars(directory)
    return found


def grounding_ratios(rows: list[dict], ggns: str, baselines: list[str]) -> list[dict]:
    """At each step where `ggns` logged k=1 and a baseline its full rollout: baseline never / GGNS k=1."""
    k1 = {r["step"]: r["rollout_mse_k1"] for r in rows if r["variant"] == ggns and r["rollout_mse_k1"] is not None}
    out = []
    for baseline in baselines:
        never = {r["step"]: r["rollout_mse_never"] for r in rows
                 if r["variant"] == baseline and r["rollout_mse_never"] is not None}
        out += [{"step": s, "baseline": baseline, "ggns_k1": k1[s], "baseline_never": never[s],
                 "ratio": never[s] / k1[s]} for s in sorted(set(k1) & set(never))]
    return out


def run_status(sweep: Path, model: str, seed: int, scalars: dict, max_steps: int | None) -> dict:
    from ggns.sweeps.curves import training_seconds

    steps = max(int(s.max()) for s, _, _ in scalars.values())
    seconds, clocked = training_seconds(scalars, np.array([float(steps)]))
    walls = [w for _, wall, _ in scalars.values() for w in wall]
    tested = (sweep / model / f"seed_{seed}_test" / "test_metrics.json").is_file()  # the sweep's mark of a finished run
    finished = tested or (max_steps is not None and steps >= max_steps)
    return {"model": model, "optimizer_steps": steps, "train_seconds": round(float(seconds[0]), 1) if clocked else None,
            "steps_per_train_second": round(steps / float(seconds[0]), 2) if clocked and seconds[0] > 0 else None,
            "wall_minutes": round((max(walls) - min(walls)) / 60, 1), "budget_steps": max_steps,
            "finished": bool(finished), "tested": tested}


def _value(text: str):
    """A cell of a csv this script wrote: None for an empty cell, else an int, a float or the text."""
    if text == "":
        return None
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {"True": True, "False": False}.get(text, text)


def read_earlier(directory: Path, models: list[str]) -> tuple[list[dict], list[dict]]:
    """The validation rows and status rows of `models` in an earlier report's validations.csv and status.csv."""
    def rows(name: str) -> list[dict]:
        path = directory / name
        if not path.is_file():
            sys.exit(f"--earlier {directory}: no {name} there")
        with path.open(newline="") as f:
            return [{k: _value(v) for k, v in row.items()} for row in csv.DictReader(f)]
    return ([r for r in rows("validations.csv") if r["variant"] in models],
            [r for r in rows("status.csv") if r["model"] in models])


def curves_from_rows(rows: list[dict]) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """`read_scalars`-shaped validation curves of one run rebuilt from its validation rows (wall times unknown)."""
    from ggns.sweeps.curves import VALIDATIONS

    curves = {}
    for tag in VALIDATIONS:
        points = [(r["step"], r[tag.removeprefix("val/")]) for r in rows if r[tag.removeprefix("val/")] is not None]
        if points:
            steps, values = map(np.array, zip(*sorted(points)))
            curves[tag] = (steps.astype(float), np.full(len(steps), np.nan), values.astype(float))
    return curves


def test_rows(sweep: Path, models: list[str], seed: int) -> list[dict]:
    """One row per tested run and test metric: {model, metric, mean, std, count} from its test_metrics.json."""
    import json

    rows = []
    for model in models:
        path = sweep / model / f"seed_{seed}_test" / "test_metrics.json"
        if path.is_file():
            metrics = json.loads(path.read_text())
            rows += [{"model": model, "metric": name, "mean": value["mean"], "std": value.get("std"),
                      "count": value.get("count")} for name, value in metrics.items()
                     if isinstance(value, dict) and "mean" in value]
    return rows


def test_ratios(tests: list[dict], ggns: str, baselines: list[str]) -> list[dict]:
    """Each tested baseline's test rollout_mse_never over GGNS's test rollout_mse_k1."""
    mean = {(r["model"], r["metric"]): r["mean"] for r in tests}
    k1 = mean.get((ggns, "rollout_mse_k1"))
    return [] if k1 is None else [
        {"baseline": b, "ggns_k1": k1, "baseline_never": mean[(b, "rollout_mse_never")],
         "ratio": mean[(b, "rollout_mse_never")] / k1} for b in baselines if (b, "rollout_mse_never") in mean]


def power_law(rows: list[dict], ggns: str, fit_from: int, target: float) -> dict | None:
    """log(k1) = a + b log(step) fitted to `ggns`'s validation k=1 at steps >= fit_from (least squares): the
    exponent b, the points used, the law's value at the last of them and the step where it reaches `target`
    (None when it does not fall). None with fewer than 3 points."""
    points = sorted((r["step"], r["rollout_mse_k1"]) for r in rows
                    if r["variant"] == ggns and r["rollout_mse_k1"] is not None and r["step"] >= fit_from)
    if len(points) < 3:
        return None
    steps, values = (np.array(v, dtype=float) for v in zip(*points))
    b, a = np.polyfit(np.log(steps), np.log(values), 1)
    reach = float(np.exp((math.log(target) - a) / b)) if b < 0 else None
    return {"fit_from": fit_from, "fit_to": int(steps[-1]), "points": len(points), "exponent": float(b),
            "law_at_last_step": float(np.exp(a + b * math.log(steps[-1]))), "target": target,
            "steps_to_target": None if reach is None else round(reach)}


def write_csv(path: Path, rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        if rows:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


def main(argv: list[str] | None = None) -> Path:
    from ggns.reports import markdown_table
    from ggns.sweeps.curves import plot_curves, validation_markdown, validation_rows

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sweep", required=True, type=Path)
    parser.add_argument("--output", required=True, type=Path)
    parser.add_argument("--ggns", default="ggns")
    parser.add_argument("--baselines", nargs="+", default=["mgn", "mgn_m"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-steps", type=int, default=None, help="the budget every run was given")
    parser.add_argument("--earlier", type=Path, default=None,
                        help="an earlier report's folder: runs with no logs under --sweep are kept from its raw files")
    parser.add_argument("--fit-from", type=int, default=20000, help="the first step of GGNS's k=1 power-law fit")
    parser.add_argument("--target", type=float, default=1.86e-5, help="the k=1 MSE the fitted law is followed to")
    args = parser.parse_args(argv)
    models = [args.ggns, *args.baselines]
    runs = read_runs(args.sweep, models, args.seed)
    kept_rows, kept_status = read_earlier(args.earlier, [m for m in models if m not in runs]) if args.earlier else ([], [])
    if not runs and not kept_rows:
        sys.exit(f"no run of {models} with logs under {args.sweep}")
    args.output.mkdir(parents=True, exist_ok=True)
    kept = {m: [r for r in kept_rows if r["variant"] == m] for m in models if m not in runs}
    kept = {m: r for m, r in kept.items() if r}
    rows = [row for m in models for row in (validation_rows(m, runs[m]) if m in runs else kept.get(m, []))]
    ratios = grounding_ratios(rows, args.ggns, args.baselines)
    status = {m: run_status(args.sweep, m, args.seed, s, args.max_steps) for m, s in runs.items()}
    status.update({s["model"]: s for s in kept_status})
    status = [status[m] for m in models if m in status]
    curves = {m: runs[m] if m in runs else curves_from_rows(kept[m]) for m in models if m in runs or m in kept}
    write_csv(args.output / "validations.csv", rows)
    write_csv(args.output / "ratios.csv", ratios)
    write_csv(args.output / "status.csv", status)
    tests = test_rows(args.sweep, models, args.seed)
    test_ratio = test_ratios(tests, args.ggns, args.baselines)
    write_csv(args.output / "tests.csv", tests + [{"model": r["baseline"], "metric": f"ratio_never_to_{args.ggns}_k1",
                                                   "mean": r["ratio"], "std": None, "count": None} for r in test_ratio])
    fit = power_law(rows, args.ggns, args.fit_from, args.target)
    write_csv(args.output / "fit.csv", [fit] if fit else [])
    plot_curves(curves, args.output / "curves_steps.png", "steps", title="model")
    ratio_lines = [[str(r["step"]), r["baseline"], f"{r['ggns_k1']:.3g}", f"{r['baseline_never']:.3g}", f"{r['ratio']:.2f}"]
                   for r in ratios]
    status_lines = [[s["model"], f"{s['optimizer_steps']:,}", "-" if s["budget_steps"] is None else f"{s['budget_steps']:,}",
                     "-" if s["train_seconds"] is None else f"{s['train_seconds'] / 60:.1f}",
                     "-" if s["steps_per_train_second"] is None else str(s["steps_per_train_second"]),
                     f"{s['wall_minutes']:.1f}", "yes" if s["finished"] else "no (running or stopped)",
                     "yes" if s["tested"] else "no"] for s in status]
    from_earlier = list(kept)
    text = "\n".join([
        f"# Equal-step curves: {args.sweep.name}, seed {args.seed}", "",
        f"`python experiments/plate_cpu/scripts/equal_steps_report.py --sweep {args.sweep} --output {args.output}"
        + (f" --max-steps {args.max_steps}" if args.max_steps else "")
        + (f" --earlier {args.earlier}" if args.earlier else "") + "`", "",
        *([f"Kept from the earlier report's raw files (no logs under the sweep): {', '.join(from_earlier)}.", ""]
          if from_earlier else []),
        "## Runs", "",
        markdown_table(["model", "optimizer steps reached", "budget", "training minutes", "steps per training second",
                        "wall minutes (first to last event)", "fit finished", "tested"], status_lines), "",
        "## The grounding ratio at equal steps", "",
        "Each baseline's validation full-rollout MSE over GGNS's validation k=1 rollout MSE at the same optimizer step.", "",
        markdown_table(["step", "baseline", "GGNS k=1", "baseline never", "ratio"], ratio_lines) if ratio_lines else "(none yet)",
        "", "## Tests", "",
        "Each run's test metrics (its sweep test: the checkpoint of each family selected on validation), and each "
        "baseline's test full-rollout MSE over GGNS's test k=1.", "",
        markdown_table(["model", "metric", "mean", "std over trajectories", "trajectories"],
                       [[r["model"], r["metric"], f"{r['mean']:.4g}", "-" if r["std"] is None else f"{r['std']:.3g}",
                         str(r["count"])] for r in tests if r["metric"] in REPORTED]) if tests else "(no run tested yet)", "",
        *([markdown_table(["baseline", "GGNS k=1", "baseline never", "ratio"],
                          [[r["baseline"], f"{r['ggns_k1']:.4g}", f"{r['baseline_never']:.4g}", f"{r['ratio']:.2f}"]
                           for r in test_ratio]), ""] if test_ratio else []),
        "## GGNS's k=1 curve as a power law", "",
        ("(fewer than 3 validations from the fit's first step)" if fit is None else
         f"Fitted to the {fit['points']} validations from step {fit['fit_from']:,} to {fit['fit_to']:,}: MSE ~ step^"
         f"{fit['exponent']:.2f}, {fit['law_at_last_step']:.3g} at step {fit['fit_to']:,}; "
         + ("it does not fall." if fit["steps_to_target"] is None else
            f"followed on, it reaches {fit['target']:.3g} at step {fit['steps_to_target']:,} (an extrapolation).")), "",
        "## Validations", "", validation_markdown(rows), "", "![curves](curves_steps.png)", ""])
    report = args.output / "report.md"
    report.write_text(text)
    print(f"wrote {report}")
    return report


if __name__ == "__main__":
    main()
