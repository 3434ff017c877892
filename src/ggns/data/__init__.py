"""Datasets: the HDF5 schema, generation, the Lightning data module, predictions files, your own arrays.

The split names, the default dataset and where a split's file lies live here, importable without torch
(a sweep's orchestration checks its datasets' files without importing the data module)."""

from pathlib import Path

SPLITS = ("train", "val", "test")
DEFAULT_DATASET = "plate_small"  # the data module's default preset


def split_path(output: str | Path, split: str) -> Path:
    """The file of `split` in a dataset directory."""
    return Path(output) / f"{split}.h5"
