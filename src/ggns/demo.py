"""The README's main job, for now: generate the small plate dataset and draw a few of its
trajectories with their point clouds."""
from __future__ import annotations

from pathlib import Path

from .config import load_config
from .data.generate import generate, split_path
from .data.schema import SplitReader
from .viz import plot_trajectories


def run_demo(output: str | Path = "lightning_logs/demo", preset: str = "plate_small") -> Path:
    config = load_config(preset)
    missing = [s for s in config["splits"] if not split_path(config["output"], s).exists()]
    for split in set(config["splits"]) - set(missing):
        print(f"{split_path(config['output'], split)} exists, reusing it (delete it to regenerate)")
    if missing:
        generate(config, missing)
    with SplitReader(split_path(config["output"], "train")) as reader:
        picked = [reader[i] for i in range(min(3, len(reader)))]
    picture = plot_trajectories(picked, Path(output) / "plate_trajectories.png")
    print(f"wrote {picture}")
    return picture
