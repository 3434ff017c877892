"""Non-learned baselines."""
