"""Every ratio the README's prose states is a claim recomputed here from the committed raw file a command
wrote, and its paragraph gives the training budgets of the models it compares (the numbers of the budgets
checked against their raw files where one records them). A ratio written into the README without a claim
below, a claim whose raw file says otherwise, or a comparison without its budgets fails."""
from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest
import yaml

from ggns import pretrained
from ggns.sweeps.paper import paper_figures, read_summary

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
RATIO = re.compile(r"(?<![\w.-])\d+(?:\.\d+)?(?:-\d+(?:\.\d+)?)?x\b")


def prose_paragraphs(text: str) -> list[str]:
    """The README's paragraphs of prose (no code blocks, tables or comments), whitespace collapsed."""
    paragraphs, current, fenced = [], [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
            continue
        if fenced or line.startswith(("|", "<!--")) or not line.strip():
            if current:
                paragraphs.append(" ".join(current))
            current = []
            continue
        current.append(line.strip())
    if current:
        paragraphs.append(" ".join(current))
    return paragraphs


def _mean(summary: str | list, model: str, metric: str) -> float:
    paths = [RESULTS / p for p in ([summary] if isinstance(summary, str) else summary)]
    return read_summary(paths)[model][metric][0]


def _paper(task: str, model: str, metric: str) -> float:
    return paper_figures(task)[metric][model]


def _steps(name: str) -> int:
    return pretrained.training_budget(pretrained.manifest(name))["optimizer_steps"]


def _demo_ratio() -> float:
    return json.loads((RESULTS / "demo_plate" / "results.json").read_text())["ratio_mgn_over_ggns_k1"]


def _demo_scratch() -> tuple[int, float]:
    """(optimizer steps, the shipped MGN's validation MSE over the from-scratch GGNS's best k=1) of the
    demo's report."""
    text = (RESULTS / "demo_plate" / "report.md").read_text()
    found = re.search(r"(\d+) optimizer steps in .*?MGN's full rollout MSE is (\d\.\d+e[+-]\d+); the from-scratch "
                      r"GGNS's best k=1 is (\d\.\d+e[+-]\d+)", text)
    return int(found.group(1)), float(found.group(2)) / float(found.group(3))


def _long_cavity() -> list[tuple[int, float]]:
    """[(step, MGN / GGNS k=1)] at each validation step both ran, then at their last validations."""
    rows = list(csv.DictReader((RESULTS / "cavity_diagnosis" / "learning_ggns_mgn_long" /
                                "learning_validations.csv").open()))
    ggns = {int(r["step"]): float(r["rollout_mse_k1"]) for r in rows if r["variant"] == "ggns_per_type"}
    mgn = {int(r["step"]): float(r["rollout_mse_never"]) for r in rows if r["variant"] == "mgn"}
    pairs = [(s, mgn[s] / ggns[s]) for s in sorted(set(ggns) & set(mgn))]
    return pairs + [(max(mgn), mgn[max(mgn)] / ggns[max(ggns)])]


def _long_cavity_range() -> str:
    ratios = [r for s, r in _long_cavity() if s >= 4000]
    return f"{min(ratios):.1f}-{max(ratios):.1f}"


def _long_cavity_steps() -> str:
    rows = list(csv.DictReader((RESULTS / "cavity_diagnosis" / "learning_ggns_mgn_long" /
                                "learning_validations.csv").open()))
    last = {v: max(int(r["step"]) for r in rows if r["variant"] == v) for v in ("ggns_per_type", "mgn")}
    return f"GGNS {last['ggns_per_type']:,} steps, MGN {last['mgn']:,}"


def _test_mean(path: str, metric: str) -> float:
    return json.loads((RESULTS / path).read_text())[metric]["mean"]


def _learning_steps(path: str, variant: str) -> int:
    rows = csv.DictReader((RESULTS / path).open())
    return next(int(r["steps"]) for r in rows if r["variant"] == variant)


def _tall_ratio() -> float:
    """The tall cavity's MGN / GGNS k=1: the ratio of the seed means."""
    sweep = RESULTS / "cavity_mesh" / "sweep_tall_10min"

    def seed_mean(model: str, metric: str) -> float:
        values = [json.loads(p.read_text())[metric]["mean"] for p in sorted((sweep / model).glob("seed_*_test_metrics.json"))]
        assert len(values) == 3, (model, values)
        return sum(values) / len(values)
    return seed_mean("mgn", "rollout_mse_never") / seed_mean("ggns_partition", "rollout_mse_k1")


def _tall_budgets() -> str:
    sweep = yaml.safe_load((ROOT / "experiments" / "cavity_mesh" / "sweeps" / "cavity_mesh_tall.yaml").read_text())
    steps = {m: sweep["models"][m]["overrides"]["trainer"]["max_steps"] for m in ("ggns_partition", "mgn")}
    return f"GGNS {steps['ggns_partition']:,} steps, MGN {steps['mgn']:,}"


def _equal_registration(column: str) -> float:
    """GGNS over a registered baseline (`column` of the summary), the tissue's realistic sensor every tick one
    tick late, with every tissue file at GGNS's optimizer steps."""
    rows = csv.DictReader((RESULTS / "online_registration" / "tissue_realistic_late1_equal_summary.csv").open())
    row = next(r for r in rows if r["sensor"] == "realistic")
    return float(row["GGNS"]) / float(row[column])


def _equal_study_budget() -> str:
    """The tissue files' optimizer steps as `pretrained list` printed them for the equal-step study, when equal."""
    listed = (RESULTS / "online_registration" / "pretrained_list_equal.txt").read_text()
    steps = {m.group(2) for m in re.finditer(r"^tissue/(\w+) .* trained +([\d,]+) steps", listed, re.M)}
    assert len(steps) == 1, steps
    return f"each trained {steps.pop()} optimizer steps"


def _equal_plate(model: str) -> float:
    """A plate equal-step run's test MSE: GGNS's k=1, a baseline's full rollout (tests.csv of its report)."""
    metric = "rollout_mse_k1" if model == "ggns" else "rollout_mse_never"
    rows = csv.DictReader((RESULTS / "plate_equal_steps" / "tests.csv").open())
    return next(float(r["mean"]) for r in rows if (r["model"], r["metric"]) == (model, metric))


def _equal_plate_budget() -> str:
    """The optimizer steps every plate equal-step run reached (status.csv), when they are one number."""
    steps = {int(r["optimizer_steps"]) for r in csv.DictReader((RESULTS / "plate_equal_steps" / "status.csv").open())}
    assert len(steps) == 1, steps
    return f"At {steps.pop():,} optimizer steps each"


CAVITY = ["cavity_cpu/summary.csv", "cavity_cpu_seed1/summary.csv", "cavity_cpu_seed2/summary.csv"]
TISSUE_ID = "tissue_cpu_id_partition/summary.csv"


@dataclass(frozen=True)
class Claim:
    """`text` as the README writes it (whitespace collapsed), with `stated` the number in it that `value`
    recomputes (formatted as `stated` is: `digits` decimals); `budgets`: phrases the paragraph must hold,
    each a string or a function of the raw files giving it."""
    text: str
    stated: str
    value: Callable[[], float | str]
    budgets: tuple = ()
    digits: int = 1

    def recomputed(self) -> str:
        value = self.value()
        return value if isinstance(value, str) else f"{value:.{self.digits}f}"


CLAIMS = [
    Claim("a point cloud every step 103.5x below MGN", "103.5", _demo_ratio,
          (lambda: f"GGNS trained {_steps('plate/ggns'):,} optimizer steps, MGN {_steps('plate/mgn'):,}",)),
    Claim("from scratch 8.9x below that MGN after 4,324 steps", "8.9", lambda: _demo_scratch()[1],
          (lambda: f"after {_demo_scratch()[0]:,} steps of its own",
           lambda: f"MGN {_steps('plate/mgn'):,}")),
    Claim("GGNS k=1 62x below MGN", "62", lambda: _mean("plate_cpu_partition/summary.csv", "mgn", "rollout_mse_never") /
          _mean("plate_cpu_partition/summary.csv", "ggns", "rollout_mse_k1"),
          ("GGNS 40 minutes of training", "MGN and MGN(M) 12 minutes"), 0),
    Claim("1.9x below MGN(M)", "1.9", lambda: _mean("plate_cpu_partition/summary.csv", "mgn_m", "rollout_mse_never") /
          _mean("plate_cpu_partition/summary.csv", "ggns", "rollout_mse_k1"),
          ("GGNS 40 minutes of training", "MGN and MGN(M) 12 minutes")),
    Claim("the paper's 297x", "297", lambda: _paper("plate", "mgn", "rollout_mse_never") /
          _paper("plate", "ggns", "rollout_mse_k1"), ("about 1M steps",), 0),
    Claim("104x below MGN", "104", lambda: _equal_plate("mgn") / _equal_plate("ggns"), (_equal_plate_budget,), 0),
    Claim("1.4x above MGN(M)", "1.4", lambda: _equal_plate("ggns") / _equal_plate("mgn_m"), (_equal_plate_budget,)),
    Claim("GGNSID k=1 2.0x below the MGN(M) trained beside it", "2.0",
          lambda: _mean(TISSUE_ID, "mgn_m", "rollout_mse_never") / _mean(TISSUE_ID, "ggns_id_partition", "rollout_mse_k1"),
          ("GGNSID 30 minutes of training, MGN(M) 15",)),
    Claim("1.3x below the `tissue_cpu` MGN(M)", "1.3",
          lambda: _mean("tissue_cpu/summary.csv", "mgn_m", "rollout_mse_never") /
          _mean(TISSUE_ID, "ggns_id_partition", "rollout_mse_k1"), ("GGNSID 30 minutes of training, MGN(M) 15",)),
    Claim("MGN(M) is 4x below the paper's", "4",
          lambda: _paper("tissue", "mgn_m", "rollout_mse_never") / _mean(TISSUE_ID, "mgn_m", "rollout_mse_never"),
          ("ours 15 minutes of training, the paper's about 1.5M steps",), 0),
    Claim("the per-type GGNS k=1 2.7x below MGN", "2.7",
          lambda: _mean(CAVITY, "mgn", "rollout_mse_never") / _mean(CAVITY, "ggns_partition", "rollout_mse_k1"),
          ("GGNS 30 minutes of training", "MGN 15 minutes")),
    Claim("the paper has 18x", "18", lambda: _paper("cavity", "mgn", "rollout_mse_never") /
          _paper("cavity", "ggns", "rollout_mse_k1"), ("about 740K steps each",), 0),
    Claim("1.5x there at equal training time", "1.5", _tall_ratio, (_tall_budgets,)),
    Claim("GGNS k=1 3.0-8.8x below MGN at each validation from step 4,000 on", "3.0-8.8", _long_cavity_range,
          (_long_cavity_steps,)),
    Claim("0.8x at step 3,000", "0.8", lambda: dict(_long_cavity())[3000], (_long_cavity_steps,)),
    Claim("GGNS tracks the tissue 0.73x a blind MGN registered to each frame", "0.73",
          lambda: _equal_registration("MGN + reg"), (_equal_study_budget,), 2),
    Claim("1.5x above MGN(M) registered so", "1.5", lambda: _equal_registration("MGN(M) + reg"), (_equal_study_budget,)),
    Claim("3.2x (seed 1, 27 test trajectories)", "3.2",
          lambda: _test_mean("cavity_diagnosis/learning_depth_seed1/test_mgn_blocks_8/test_metrics.json", "rollout_mse_never") /
          _test_mean("cavity_diagnosis/learning_depth_seed1/test_blocks_8/test_metrics.json", "rollout_mse_k1"),
          (lambda: f"GGNS {_learning_steps('cavity_diagnosis/learning_depth_seed1/learning.csv', 'blocks_8'):,} steps",)),
]


def _paragraph(claim: Claim) -> str:
    found = [p for p in prose_paragraphs((ROOT / "README.md").read_text()) if claim.text in p]
    assert len(found) == 1, f"README's prose has {len(found)} paragraphs with {claim.text!r}"
    return found[0]


def test_every_ratio_in_the_readme_prose_is_a_claim_checked_here():
    covered = []
    for paragraph in prose_paragraphs((ROOT / "README.md").read_text()):
        spans = [(m.start(), m.end()) for c in CLAIMS for m in re.finditer(re.escape(c.text), paragraph)]
        for match in RATIO.finditer(paragraph):
            assert any(a <= match.start() and match.end() <= b for a, b in spans), \
                f"README states {match.group()!r} with no claim in tests/test_claims.py: {paragraph[:120]}..."
            covered.append(match.group())
    assert len(covered) >= len(CLAIMS)  # every claim's ratio was found in the prose


@pytest.mark.parametrize("claim", CLAIMS, ids=lambda c: c.text[:40])
def test_each_claim_is_its_raw_files_number_and_states_the_budgets(claim):
    paragraph = _paragraph(claim)
    assert claim.stated in claim.text
    assert claim.recomputed() == claim.stated, (claim.text, claim.recomputed())
    for budget in claim.budgets:
        phrase = budget() if callable(budget) else budget
        assert phrase in paragraph, f"{claim.text!r}: its paragraph does not state {phrase!r}"


def test_a_ratio_without_a_claim_is_caught():
    paragraph = "GGNS is 7.5x below MGN here."
    assert [m.group() for m in RATIO.finditer(paragraph)] == ["7.5x"]
    assert [m.group() for m in RATIO.finditer("3.0-8.8x, 62x and 0.8x; not 2x2 or v1.2x")] == ["3.0-8.8x", "62x", "0.8x"]
