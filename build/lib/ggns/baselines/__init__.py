"""Non-learned baselines of the paper and their scores: Alpha Shapes on every point cloud
(alpha_shapes.py), initial-mesh generation from the first point cloud (initial_mesh.py), and the
scoring of both and of the static reference in the runs' metric format (scores.py)."""
