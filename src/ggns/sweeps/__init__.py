"""Sweeps: many fits and their tests, run and summarized. Multi-seed sweeps of model configs (sweep.py: runs,
tests per metric family), their summary and the non-learned baselines beside it (summary.py), aggregation into
the paper's tables (aggregate.py), the paper's findings and the project's targets (findings.py), figures
(figures.py), learning curves (curves.py), learning per CPU-second (learning.py: a sweep of variants within
one budget) and the runs the shipped simulators are cut from (pretrain.py). ("Experiments" are the project's
own questions: experiments/ and their pages in docs/experiments/.)"""
from .aggregate import NoBenefitError, RunResult, aggregate, load_run, normalized_benefit, to_csv, to_markdown

__all__ = ["NoBenefitError", "RunResult", "aggregate", "load_run", "normalized_benefit", "to_csv", "to_markdown"]
