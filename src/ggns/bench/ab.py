"""`python -m ggns bench ab`: this checkout against a baseline commit, measured in one run on one
machine. Each probe (`bench.probe`: a training iteration, a rollout step, a Lightning fit) runs in a
fresh subprocess per source tree, the trees alternating within every round (A B, then B A) so that a
machine that speeds up or slows down during the run treats both alike; the report gives each tree's
median and the median of the per-round ratios (paired, the robust number on a noisy machine).
"""
from __future__ import annotations

import functools
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

from ..reports import write_csv, write_text

ROOT = Path(__file__).resolve().parents[3]  # the checkout (ab compares checkouts)
PROBE = Path(__file__).with_name("probe.py")
# (probe arguments, what to call it): the demo's from-scratch model and the paper-size models
DEFAULT_PROBES = (
    "fit ggns 64 3 8", "train ggns 64 3 8", "train ggns 128 5 32", "train mgn 128 5 32",
    "rollout ggns 128 5 1 every:1", "rollout ggns 128 5 32 every:1", "rollout mgn 128 5 1 never",
)


def source_tree(spec: str, scratch: Path) -> Path:
    """The `src` folder of `spec`: a path to a checkout, or a commit of this repository (checked out
    into a worktree under `scratch`)."""
    path = Path(spec)
    if (path / "src" / "ggns").is_dir():
        return (path / "src").resolve()
    target = scratch / f"tree_{spec}"
    if not target.exists():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(target), spec], check=True,
                       capture_output=True)
    return target / "src"


class ProbeFailed(ValueError):
    """A probe's subprocess that exited non-zero or printed no result: its exit status and stderr."""

    def __init__(self, message: str, returncode: int, stderr: str):
        super().__init__(message)
        self.returncode, self.stderr = returncode, stderr


class ProbesFailed(ValueError):
    """Raised by `bench_ab` at its end, after the report, when any probe run failed (the others ran)."""


def run_probe(tree: Path, probe: str, threads: int | None, device: str = "cpu", extra_env: dict | None = None) -> dict:
    """One probe in a subprocess importing ggns from `tree`, with `extra_env` set; its JSON line (ProbeFailed,
    a ValueError with its stderr, if it fails)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), *filter(None, [os.environ.get("PYTHONPATH")])]),
           "GGNS_PROBE_DEVICE": device, **(extra_env or {})}
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    done = subprocess.run([sys.executable, "-P", str(PROBE), *probe.split()], cwd=ROOT, env=env, capture_output=True,
                          text=True)
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode or not lines:
        raise ProbeFailed(f"probe {probe!r} on {tree} failed ({done.returncode}):\n{done.stderr[-2000:]}",
                          done.returncode, done.stderr)
    return json.loads(lines[-1])


def last_lines(error: BaseException, count: int = 5) -> str:
    """The last `count` non-blank lines of a failed probe's stderr (of the error's message for other errors)."""
    if isinstance(error, ProbeFailed):
        text = error.stderr if error.stderr.strip() else f"exit status {error.returncode}, no result line, no stderr"
    else:
        text = f"{type(error).__name__}: {error}"
    return "\n".join([line.rstrip() for line in text.splitlines() if line.strip()][-count:])


def failure_row(round_: int, probe: str, tree: str, error: BaseException) -> dict:
    """The raw row of a probe run that failed: no unit nor value, the error's last lines."""
    return {"round": round_, "probe": probe, "tree": tree, "unit": "", "value": None, "error": last_lines(error)}


def measure(round_: int, rounds: int, probe: str, name: str, run) -> dict:
    """One probe run (`run()`: its JSON result) as a raw row, printed as a log line; a failure (any exception
    but an interrupt) becomes a `failure_row`, printed with its last lines on stderr, so that the other
    probes still run."""
    head = f"bench ab: round {round_ + 1}/{rounds} {name:9s} {probe}:"
    try:
        result = run()
        value_key = next((k for k in ("steps/s", "ms", "ops") if k in result), None)
        if value_key is None:
            raise ValueError(f"probe {probe!r} printed no steps/s, ms or ops: {result}")
    except Exception as error:  # noqa: BLE001 - whatever a probe does, the others run
        row = failure_row(round_, probe, name, error)
        print(f"{head} FAILED ({row['error'].splitlines()[-1]})", flush=True)
        print(textwrap.indent(row["error"], "    "), file=sys.stderr, flush=True)
        return row
    print(f"{head} {result[value_key]:.2f} {value_key}", flush=True)
    return {"round": round_, "probe": probe, "tree": name, "unit": value_key, "value": result[value_key]}


def bench_ab(baseline: str, probes: tuple[str, ...] = DEFAULT_PROBES, rounds: int = 5, candidate: str = str(ROOT),
             output: str | None = None, threads: int | None = None, device: str = "cpu",
             baseline_env: dict | None = None, candidate_env: dict | None = None) -> list[dict]:
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    with tempfile.TemporaryDirectory() as scratch:
        trees = {"baseline": source_tree(baseline, Path(scratch)), "candidate": source_tree(candidate, Path(scratch))}
        raw = []
        try:
            for r in range(rounds):
                order = list(trees) if r % 2 == 0 else list(reversed(trees))
                for probe in probes:
                    for name in order:
                        env = baseline_env if name == "baseline" else candidate_env
                        raw.append(measure(r, rounds, probe, name,
                                           functools.partial(run_probe, trees[name], probe, threads, device, env)))
        finally:
            for name, tree in trees.items():
                if str(tree).startswith(scratch):
                    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree.parent)],
                                   capture_output=True)
    rows = report(raw, baseline, candidate, output, device, baseline_env, candidate_env)
    failed = [r for r in raw if r.get("error")]
    if failed:
        runs = "; ".join(f"{r['probe']!r} on {r['tree']} (round {r['round'] + 1})" for r in failed)
        raise ProbesFailed(f"{len(failed)} of {len(raw)} probe runs failed, the others measured and reported: {runs}")
    return rows


def report(raw: list[dict], baseline: str, candidate: str, output: str | None = None, device: str = "cpu",
           baseline_env: dict | None = None, candidate_env: dict | None = None, note: str = "") -> list[dict]:
    """Summarize raw rows (printed; with `output`, ab_raw.csv and ab_summary.md written there)."""
    rows = summarize(raw)
    rounds = len({r["round"] for r in raw})
    label = (lambda tree, env: tree + (" with " + " ".join(f"{k}={v}" for k, v in env.items()) if env else ""))
    text = summary_markdown(rows, label(baseline, baseline_env), label(candidate, candidate_env), rounds, device)
    text += failures_markdown(raw)
    text += f"\n{note}\n" if note else ""
    print("\n" + text)
    if output is not None:
        out = Path(output)
        write_csv(out / "ab_raw.csv", raw, list(dict.fromkeys(k for r in raw for k in r)))
        write_text(out / "ab_summary.md", text)
        print(f"wrote {out / 'ab_raw.csv'} and {out / 'ab_summary.md'}")
    return rows


def summarize(raw: list[dict]) -> list[dict]:
    """Per probe: each tree's median and the median per-round speed-up of the candidate (baseline ms /
    candidate ms, or candidate steps/s / baseline steps/s; for operator counts the reduction), over the
    rounds in which it ran on both trees (a probe that never did has no row)."""
    rows = []
    for probe in dict.fromkeys(r["probe"] for r in raw):
        mine = [r for r in raw if r["probe"] == probe and not r.get("error")]  # failed runs: failures_markdown
        value = {(r["round"], r["tree"]): r["value"] for r in mine}
        # rounds measured on both trees, with values a ratio can take (a log's 2 decimals may round one to 0)
        rounds = sorted(k for k in {r["round"] for r in mine} if value.get((k, "baseline")) and value.get((k, "candidate")))
        if not rounds:
            continue
        unit = mine[0]["unit"]
        speedups = [(value[k, "candidate"] / value[k, "baseline"]) if unit == "steps/s" else
                    (value[k, "baseline"] / value[k, "candidate"]) for k in rounds]
        rows.append({"probe": probe, "unit": unit,
                     "baseline": statistics.median(value[k, "baseline"] for k in rounds),
                     "candidate": statistics.median(value[k, "candidate"] for k in rounds),
                     "speed-up (median of rounds)": statistics.median(speedups),
                     "speed-up range": (min(speedups), max(speedups))})
    return rows


LOG_LINE = re.compile(r"^bench ab: round (\d+)/(\d+) (baseline|candidate)\s+(.+): ([0-9.eE+-]+) (steps/s|ms|ops)$")
FAILED_LINE = re.compile(r"^bench ab: round (\d+)/(\d+) (baseline|candidate)\s+(.+): FAILED \((.*)\)$")


def raw_from_log(text: str) -> list[dict]:
    """The raw rows of a `bench ab` run from its printed log (what an interrupted run leaves): only the
    rounds in which every probe ran on both trees (a failed run, its error's last line kept, counts as run)."""
    raw = []
    for line in text.splitlines():
        if m := LOG_LINE.match(line):
            raw.append({"round": int(m[1]) - 1, "probe": m[4], "tree": m[3], "unit": m[6], "value": float(m[5])})
        elif m := FAILED_LINE.match(line):
            raw.append({"round": int(m[1]) - 1, "probe": m[4], "tree": m[3], "unit": "", "value": None, "error": m[5]})
    if not raw:
        raise ValueError("no `bench ab: round ...` lines in the log")
    probes = dict.fromkeys(r["probe"] for r in raw)
    complete = {k for k in {r["round"] for r in raw}
                if len({(r["probe"], r["tree"]) for r in raw if r["round"] == k}) == 2 * len(probes)}
    if not complete:
        raise ValueError("the log has no complete round (every probe on both trees)")
    return [r for r in raw if r["round"] in complete]


def summary_markdown(rows: list[dict], baseline: str, candidate: str, rounds: int, device: str = "cpu") -> str:
    lines = [f"bench ab on {device}: candidate {candidate} against baseline {baseline}, {rounds} rounds, trees alternating",
             "", "| probe | unit | baseline (median) | candidate (median) | speed-up (median of rounds) | range |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        low, high = r["speed-up range"]
        lines.append(f"| `{r['probe']}` | {r['unit']} | {r['baseline']:.2f} | {r['candidate']:.2f} | "
                     f"{r['speed-up (median of rounds)']:.2f}x | {low:.2f}-{high:.2f}x |")
    return "\n".join(lines) + "\n"


def failures_markdown(raw: list[dict]) -> str:
    """The summary's section on failed probe runs (empty when none failed): each run's probe, tree, round
    and its error's last lines."""
    failed = [r for r in raw if r.get("error")]
    if not failed:
        return ""
    lines = ["", f"Failed: {len(failed)} of {len(raw)} probe runs (left out of the table; a probe's medians cover "
                 "the rounds in which it ran on both trees)", ""]
    for r in failed:
        lines += [f"- `{r['probe']}` on {r['tree']}, round {r['round'] + 1}:", "", "  ```",
                  *(f"  {line}" for line in str(r["error"]).splitlines()), "  ```"]
    return "\n".join(lines) + "\n"
