"""Datasets: the HDF5 schema, generation, the Lightning data module, predictions files, your own arrays.

The split names and the default dataset live here, importable without torch (a sweep's orchestration
checks its datasets' files without importing the data module)."""

SPLITS = ("train", "val", "test")
DEFAULT_DATASET = "plate_small"  # the data module's default preset
