"""The notebooks in notebooks/ run top to bottom on tiny data: their code cells are executed in
order in one namespace (what a kernel does), with parameters given by environment variables."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl

from ggns.config import CONF_DIR
from ggns.data.module import SimulationDataModule
from ggns.data.predictions import read_predictions
from ggns.data.schema import SplitReader
from ggns.models.simulators import GGNS, MGN

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"


def run_notebook(name: str) -> dict:
    book = json.loads((NOTEBOOKS / name).read_text())
    assert book["nbformat"] == 4
    namespace: dict = {"__name__": "__main__"}
    for i, cell in enumerate(book["cells"]):
        if cell["cell_type"] == "code":
            exec(compile("".join(cell["source"]), f"{name}[cell {i}]", "exec"), namespace)
    return namespace


@pytest.fixture(scope="module")
def tiny_checkpoints(tiny_data_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("notebook_ckpts")
    paths = {}
    for name, cls in (("GGNS", GGNS), ("MGN", MGN)):
        model = cls(latent=8, blocks=1)
        data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=8, generate_missing=False)
        trainer = pl.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                             enable_model_summary=False, limit_val_batches=0)
        trainer.fit(model, datamodule=data)
        paths[name] = out / f"{name}.ckpt"
        trainer.save_checkpoint(paths[name])
    return paths


def test_rollout_animation_notebook(tiny_checkpoints, tiny_data_dir, tmp_path, monkeypatch):
    monkeypatch.setenv("GGNS_CHECKPOINTS", ",".join(f"{k}={v}" for k, v in tiny_checkpoints.items()))
    monkeypatch.setenv("GGNS_DATASET", "plate_tiny")
    monkeypatch.setenv("GGNS_DATA_DIR", str(tiny_data_dir))
    monkeypatch.setenv("GGNS_SCHEDULE", "every:2")
    monkeypatch.setenv("GGNS_OUTPUT", str(tmp_path))
    ns = run_notebook("rollout_animation.ipynb")
    assert set(ns["rollouts"]) == {"GGNS (every:2)", "MGN (never)"}
    gif = tmp_path / "rollout_test0.gif"
    assert gif.read_bytes()[:6] in (b"GIF87a", b"GIF89a")
    assert all(v > 0 for v in ns["errors"].values())


def test_own_data_notebook(tiny_checkpoints, tmp_path, monkeypatch):
    monkeypatch.setenv("GGNS_CHECKPOINT", str(tiny_checkpoints["GGNS"]))
    monkeypatch.setenv("GGNS_DATA_PRESET", "plate_tiny")
    monkeypatch.setenv("GGNS_SCHEDULE", "every:2")
    monkeypatch.setenv("GGNS_OUTPUT", str(tmp_path))
    ns = run_notebook("own_data.ipynb")
    assert not ns["observed"].has_ground_truth and ns["known"].has_ground_truth
    assert ns["predicted"].shape == ns["simulated"].positions.shape and ns["label"] == "GGNS (every:2)"
    assert ns["metrics"]["rollout_mse_k2"][0] > 0
    assert (tmp_path / "own_data.png").read_bytes()[:4] == b"\x89PNG"
    assert [p.name for p in ns["pvd"]] == ["GGNS.pvd", "points.pvd"] and not (tmp_path / "paraview" / "truth").exists()
    back = read_predictions(tmp_path / "predictions.h5")
    assert np.array_equal(back.positions[0], ns["predicted"]) and back.schedule == "every:2"
    assert len(SplitReader(tmp_path / "own.h5")) == 1


def test_sweep_tables_notebook(tmp_path, monkeypatch):
    import yaml

    output = tmp_path / "sweep"
    config = {"output": str(output), "seeds": [0, 1], "models": {
        "ggns": {"config": str(CONF_DIR / "plate" / "ggns.yaml")}, "mgn": {"config": str(CONF_DIR / "plate" / "mgn.yaml")}}}
    (tmp_path / "sweep.yaml").write_text(yaml.safe_dump(config))
    values = {"ggns": {f"rollout_mse_k{k}": 1e-3 * k for k in (1, 2, 5, 10)} | {"rollout_mse_never": 0.02, "m10_mse": 0.003},
              "mgn": {"rollout_mse_never": 0.02, "m10_mse": 0.01}}
    for model, metrics in values.items():
        for seed in (0, 1):
            d = output / model / f"seed_{seed}_test"
            d.mkdir(parents=True)
            summary = {m: {"mean": v * (1 + 0.1 * seed), "std": 0.0, "count": 2} for m, v in metrics.items()}
            (d / "test_metrics.json").write_text(json.dumps(summary))
    monkeypatch.setenv("GGNS_SWEEP", str(tmp_path / "sweep.yaml"))
    ns = run_notebook("sweep_tables.ipynb")
    assert ns["table"]["ggns"]["rollout_mse_k1"]["seeds"] == 2
    assert {p.name for p in ns["figures"]} >= {"rollout_mse.png", "m_plus_10.png", "normalized_benefit.png"}
