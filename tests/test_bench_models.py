"""`python -m ggns bench models` on tiny data: it runs end to end and reports the matrix work of a
training iteration (FLOPs counted by torch, share of the GEMM rate). Speeds are not asserted."""
import math

import torch

from ggns.bench.models import bench_models, gemm_rate
from ggns.config import CONF_DIR


def test_gemm_rate_is_a_rate():
    rate = gemm_rate(torch.device("cpu"), 256, 256, 256, repeats=3)
    assert math.isfinite(rate) and rate > 0


def test_bench_models_reports_matrix_work(tiny_data_dir, tmp_path):
    preset = tmp_path / "tiny.yaml"
    preset.write_text(f"base: {CONF_DIR / 'data' / 'plate_tiny.yaml'}\noutput: {tiny_data_dir}\n")
    rows = bench_models(str(preset), ("ggns", "mgn"), train_batches=1, rollout_steps=2, batch_size=2,
                        rollout_trajectories=2, repeats=1, latent=16, blocks=2, output=str(tmp_path / "b.csv"))
    train = {(r["model"], r["measurement"]): r["value"] for r in rows if r["phase"] == "train"}
    for model in ("ggns", "mgn"):
        flops = train[model, "matrix GFLOP per iteration"]
        assert flops > 0
        assert 0 < train[model, "matmul share of CPU time (profiler)"] <= 1
        assert train[model, "share of the GEMM rate"] > 0
    # GGNS graphs carry points in about half the windows, MGN never: per graph, their matrix work differs
    assert train["ggns", "matrix GFLOP per iteration"] != train["mgn", "matrix GFLOP per iteration"]
    assert (tmp_path / "b.csv").read_text().count("\n") == len(rows) + 1
