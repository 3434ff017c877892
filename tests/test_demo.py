"""The main job end to end on tiny sizes: the tiny registry's three simulators evaluated on generated
test trajectories, the pictures, GGNS trained from scratch through the Lightning CLI, the report."""
from __future__ import annotations

import json

from PIL import Image

from ggns import pretrained
from ggns.demo import load_demo, run_demo

from conftest import TINY12


def test_the_shipped_demo_specs_name_shipped_simulators_and_parse():
    for task in ("plate", "tissue"):
        spec = load_demo(task)
        assert set(spec["pretrained"]) == {"ggns", "mgn", "mgn_m"}
        assert set(spec["pretrained"].values()) <= set(pretrained.names())


def test_the_demo_runs_end_to_end_on_tiny_sizes(tiny_registry, cli_data, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(pretrained, "REGISTRY", tiny_registry[0])
    spec = {**load_demo("plate"), "data": str(cli_data / TINY12), "test_trajectories": 2,
            "pretrained": {"ggns": "tiny/ggns", "mgn": "tiny/mgn", "mgn_m": "tiny/mgn_m"}}
    spec["train"] = {**spec["train"], "val_trajectories": 2,
                     "args": ["--data.batch_size", "8", "--model.init_args.latent", "8", "--model.init_args.blocks", "1",
                              "--trainer.max_epochs", "2", "--trainer.check_val_every_n_epoch", "1",
                              "--trainer.enable_checkpointing", "true"]}
    report = run_demo("plate", tmp_path, minutes=0.5, spec=spec)
    out = tmp_path / "plate"
    text = report.read_text()
    assert "x below MGN" in text or "x above" in text
    assert "GGNS (paper)" in text and "`rollout_mse_k1`" in text and "## GGNS from scratch" in text
    results = json.loads((out / "results.json").read_text())
    assert set(results["results"]) == {"ggns", "mgn", "mgn_m"}
    assert results["results"]["ggns"]["rollout_mse_k1"]["count"] == 2
    for name in ("rollouts.png", "error_over_time.png", "learning.png"):
        assert (out / name).stat().st_size > 0
    with Image.open(out / "rollout.gif") as gif:
        assert gif.n_frames == 12
    printed = capsys.readouterr().out
    assert f"report:   {report}" in printed and "rollout.gif" in printed
