"""Non-learned baselines of the paper and their scores: Alpha Shapes on every point cloud
(alpha_shapes.py), initial-mesh generation from the first point cloud (initial_mesh.py), and the
scoring of both and of the static reference in the runs' metric format (scores.py)."""

# The names of the baselines' results, here so that reading a sweep's results imports no torch
ALPHA_SHAPES = "alpha_shapes"
STATIC = "static"
ROWS = (ALPHA_SHAPES, STATIC)  # baseline rows of their own, <output>/<row>/test_metrics.json
GENERATED_MESH_FILE = "generated_mesh_metrics.json"
