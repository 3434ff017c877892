"""Aggregation of multi-seed experiment results into the paper's tables."""
from .aggregate import NoBenefitError, RunResult, aggregate, load_run, normalized_benefit, to_csv, to_markdown

__all__ = ["NoBenefitError", "RunResult", "aggregate", "load_run", "normalized_benefit", "to_csv", "to_markdown"]
