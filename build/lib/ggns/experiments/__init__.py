"""Experiments that orchestrate fits: multi-seed sweeps (sweep.py: runs, tests per metric family, the
baselines, the summary), their aggregation into the paper's tables (aggregate.py), the paper's findings
and the project's targets (findings.py), figures (figures.py), learning curves (curves.py) and
learning per CPU-second (learning.py)."""
from .aggregate import NoBenefitError, RunResult, aggregate, load_run, normalized_benefit, to_csv, to_markdown

__all__ = ["NoBenefitError", "RunResult", "aggregate", "load_run", "normalized_benefit", "to_csv", "to_markdown"]
