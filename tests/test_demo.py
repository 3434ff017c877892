"""The demo end to end on tiny sizes: the tiny registry's three simulators evaluated on generated
test trajectories, the pictures, GGNS trained from scratch through the Lightning CLI, the report."""
from __future__ import annotations

import json
import re
from pathlib import Path

from PIL import Image

import pytest

from ggns import pretrained
from ggns.config import CONF_DIR
from ggns.cli.demo import load_demo, run_demo

from conftest import TINY12


def test_the_shipped_demo_specs_name_shipped_simulators_and_parse():
    for task in ("plate", "tissue"):
        spec = load_demo(task)
        assert set(spec["pretrained"]) == {"ggns", "mgn", "mgn_m"}
        assert set(spec["pretrained"].values()) <= set(pretrained.names())


def test_the_demo_trains_with_its_profiles_and_overrides(tmp_path):
    """`train`: the model config, then the CPU profiles stacked after it, the demo's data and validation
    trajectories, then its overrides (the demo's faster lr schedule), the budget and a progress bar."""
    from ggns.cli import build_cli
    from ggns.cli.demo import train_arguments

    spec = load_demo("plate")
    args = train_arguments(spec, tmp_path, minutes=4)
    assert [Path(args[i + 1]).resolve() for i, a in enumerate(args) if a == "--config"][1:] == [
        CONF_DIR / "profiles" / "cpu.yaml", CONF_DIR / "profiles" / "cpu_model.yaml"]
    cli = build_cli(args, run=False)
    model, trainer = cli.model, cli.trainer
    assert (model.hparams.latent, model.hparams.blocks, model.lr_schedule.lr, model.lr_schedule.decay_steps) == (64, 3, 3e-3, 6000)
    assert (trainer.limit_val_batches, trainer.val_check_interval, trainer.check_val_every_n_epoch) == (4, 400, None)
    assert cli.datamodule.batch_size == 8 and cli.datamodule.hparams.max_eval_trajectories == 9  # the demo's, over cpu.yaml's 27


def test_a_demo_file_extends_a_shipped_one_and_refuses_the_former_args(tmp_path, monkeypatch):
    from ggns.config import load_layered

    (tmp_path / "mine.yaml").write_text("base: plate\ntrain: {minutes: 1}\n")
    spec = load_layered(tmp_path / "mine.yaml", "demo")
    assert spec["train"]["minutes"] == 1 and spec["train"]["config"] == "conf/plate/ggns.yaml"  # the rest: plate's
    assert spec["data"] == "plate_small"
    (tmp_path / "demo").mkdir()
    (tmp_path / "demo" / "plate.yaml").write_text(f"base: {CONF_DIR / 'demo' / 'plate.yaml'}\n"
                                                  "train: {args: ['--data.batch_size', '4']}\n")
    monkeypatch.setattr("ggns.config.CONF_DIR", tmp_path)
    monkeypatch.setattr("ggns.cli.demo.CONF_DIR", tmp_path)
    with pytest.raises(ValueError, match=r"train: `args`: a list of command-line strings .*\{data: \{batch_size: 4\}\}"):
        load_demo("plate")


def test_the_demo_runs_end_to_end_on_tiny_sizes(tiny_registry, cli_data, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(pretrained, "REGISTRY", tiny_registry[0])
    spec = {**load_demo("plate"), "data": str(cli_data / TINY12), "test_trajectories": 2,
            "pretrained": {"ggns": "tiny/ggns", "mgn": "tiny/mgn", "mgn_m": "tiny/mgn_m"}}
    spec["train"] = {**spec["train"], "val_trajectories": 2, "configs": [],
                     "overrides": {"data": {"batch_size": 8}, "model": {"init_args": {"latent": 8, "blocks": 1}},
                                   "trainer": {"max_epochs": 2, "check_val_every_n_epoch": 1,
                                               "enable_checkpointing": True}}}
    report = run_demo("plate", tmp_path, minutes=0.5, spec=spec)
    out = tmp_path / "plate"
    text = report.read_text()
    results = json.loads((out / "results.json").read_text())
    # the claim: MGN's full rollout over GGNS k=1 as computed from the results, each model's budget beside it
    ratio = results["ratio_mgn_over_ggns_k1"]
    mgn = results["results"]["mgn"]["rollout_mse_never"]["mean"]
    assert ratio == pytest.approx(mgn / results["results"]["ggns"]["rollout_mse_k1"]["mean"], rel=1e-12)
    relation = f"{ratio:.1f}x below MGN" if ratio >= 1 else f"{1 / ratio:.1f}x above MGN"
    claim = next(line for line in text.splitlines() if line.startswith("GGNS with a point cloud every step"))
    assert relation in claim, claim
    for key in ("ggns", "mgn", "mgn_m"):
        words = pretrained.budget_text(pretrained.manifest(f"tiny/{key}"))
        assert re.fullmatch(r"[\d,]+ steps.*", words) and f"trained {words}" in claim, (key, words, claim)
    assert "GGNS (paper)" in text and "`rollout_mse_k1`" in text and "## GGNS from scratch" in text
    assert set(results["results"]) == {"ggns", "mgn", "mgn_m"}
    assert results["results"]["ggns"]["rollout_mse_k1"]["count"] == 2
    for name in ("rollouts.png", "error_over_time.png", "learning.png"):
        assert (out / name).stat().st_size > 0
    with Image.open(out / "rollout.gif") as gif:
        assert gif.n_frames == 12
    printed = capsys.readouterr().out
    assert f"report:   {report}" in printed and "rollout.gif" in printed


def test_the_online_demo_tracks_a_test_trajectory_with_late_noisy_frames(tiny_registry, cli_data, tmp_path,
                                                                       monkeypatch):
    """`ggns demo --online` on tiny sizes: the tiny registry's GGNS stepped online through a test trajectory fed
    the virtual camera's noisy depth frames of every 2nd tick one tick late, beside the blind models; the
    error curves, the report and the JSON are written, and the frames changed GGNS's run."""
    from ggns.cli.demo import run_online

    monkeypatch.setattr(pretrained, "REGISTRY", tiny_registry[0])
    spec = {**load_demo("plate"), "data": str(cli_data / TINY12),
            "pretrained": {"ggns": "tiny/ggns", "mgn": "tiny/mgn", "mgn_m": "tiny/mgn_m"}}
    report = run_online("plate", tmp_path, spec, trajectory=1, every=2, latency=1, noise=1.0)
    out = json.loads((tmp_path / "plate" / "online.json").read_text())
    curves = out["per_tick_mse"]
    assert len(curves) == 5 and all(len(c) == 11 for c in curves.values())  # T = 12: ticks 1..11
    grounded, blind = curves["GGNS, a frame every 2 ticks, 1 late"], curves["GGNS blind"]
    assert grounded[0] == blind[0] and grounded != blind  # the frame of tick 0 arrives at tick 1: the first step is blind
    registered, mgn = curves["MGN + registration, the same frames"], curves["MGN (blind)"]
    assert registered[0] == mgn[0] and registered != mgn  # registered from the first frame on, as GGNS is grounded
    assert (tmp_path / "plate" / "online.png").stat().st_size > 0 and "tracking MSE" in report.read_text()
    with pytest.raises(ValueError, match="every >= 1"):
        run_online("plate", tmp_path, spec, every=0)
