"""Scenes: each module builds meshes, samples scene parameters and produces `Trajectory`s.

A scene module provides `DIM` (its spatial dimension), `check_config(config)` (refuses bad settings up front),
`num_combinations(scene_cfg)` (shape x material combinations that
balanced splits cycle through) and `make_trajectory(config, combination, seed, sensor)`.
"""
from . import cavity, plate, tissue

SCENES = {"plate": plate, "tissue": tissue, "cavity": cavity}
