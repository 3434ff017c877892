"""Aggregation of multi-seed experiment results into the paper's tables."""
from .aggregate import RunResult, aggregate, load_run, normalized_benefit, to_csv, to_markdown

__all__ = ["RunResult", "aggregate", "load_run", "normalized_benefit", "to_csv", "to_markdown"]
