"""Multi-seed sweeps end to end on tiny generated data (real subprocess runs of the Lightning CLI),
resume after a run is deleted, and the SLURM job-array script."""
from __future__ import annotations

import json
import shutil

import pytest
import yaml

from ggns.config import CONF_DIR
from ggns.experiments.baselines import GENERATED_MESH_FILE, baseline_spec, run_baselines
from ggns.experiments.sweep import load_sweep, run_sweep, runs_of, slurm_script, summarize


def write_sweep(tmp_path, data_dir, seeds=(0, 1)) -> str:
    tiny = ["--data.dataset", "plate_tiny", "--data.data_dir", str(data_dir), "--data.generate_missing", "false",
            "--data.batch_size", "8", "--model.init_args.latent", "16", "--model.init_args.blocks", "2",
            "--trainer.max_epochs", "1", "--trainer.limit_train_batches", "2", "--trainer.limit_val_batches", "1",
            "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false"]
    sweep = {"output": str(tmp_path / "sweep"), "seeds": list(seeds), "parallel": 2, "args": tiny,
             "models": {"mgn": {"config": str(CONF_DIR / "plate" / "mgn.yaml")}},
             "baselines": {"dataset": "plate_tiny", "data_dir": str(data_dir), "alpha_shapes": True, "static": True,
                           "initial_mesh": ["mgn"]}}
    path = tmp_path / "sweep.yaml"
    path.write_text(yaml.safe_dump(sweep))
    return str(path)


def test_two_seed_sweep_runs_skips_and_resumes(tiny_data_dir, tmp_path):
    sweep = load_sweep(write_sweep(tmp_path, tiny_data_dir))
    runs = runs_of(sweep)
    assert [(r.model, r.seed) for r in runs] == [("mgn", 0), ("mgn", 1)]
    messages = []
    run_sweep(sweep, log=messages.append)
    metrics = {r.seed: json.loads(r.metrics_path.read_text()) for r in runs}
    for m in metrics.values():
        assert "rollout_mse_never" in m and m["rollout_mse_never"]["count"] == 2
    assert metrics[0]["rollout_mse_never"]["mean"] != metrics[1]["rollout_mse_never"]["mean"]  # seeds differ
    stamp = runs[0].metrics_path.stat().st_mtime_ns

    shutil.rmtree(runs[1].fit_dir)
    shutil.rmtree(runs[1].test_dir)
    messages.clear()
    run_sweep(sweep, log=messages.append)
    assert any("skip mgn seed 0" in m for m in messages)
    assert "fit mgn seed 1" in messages and "fit mgn seed 0" not in messages
    assert runs[0].metrics_path.stat().st_mtime_ns == stamp and runs[1].finished

    written = run_baselines(sweep, log=messages.append)
    assert sorted(p.name for p in written) == [GENERATED_MESH_FILE] * 2 + ["test_metrics.json"] * 2
    static = json.loads((runs[0].output / "static" / "test_metrics.json").read_text())
    assert static["rollout_mse_never"]["count"] == 2 and static["rollout_mse_never"]["mean"] > 0
    assert 0.0 < static["rollout_iou_never"]["mean"] < 1.0  # the plate moves, so holding S_0 loses overlap
    alpha = json.loads((runs[0].output / "alpha_shapes" / "test_metrics.json").read_text())
    generated = json.loads((runs[0].test_dir / GENERATED_MESH_FILE).read_text())
    for metrics in (alpha, generated):
        (name,) = [n for n in metrics if n.startswith("generated_mesh_iou_")]
        assert metrics[name]["count"] == 2 and 0.3 < metrics[name]["mean"] <= 1.0
    assert run_baselines(sweep, log=messages.append) == []  # computed once, then kept

    summary = summarize(sweep, log=messages.append).read_text()
    assert "2 of 2 runs finished" in summary and "| mgn |" in summary
    assert "## Rollout IoU from a mesh generated from the first point cloud" in summary
    assert "| alpha_shapes |" in summary and "| static |" in summary and "generated_mesh_iou.png" in summary
    assert "| mgn | 1 | last.ckpt | 2 / 0 | 0 |" in summary  # no validation ran: last.ckpt, 2 steps in epoch 0
    csv_text = (runs[0].output / "summary.csv").read_text()
    assert "mgn,rollout_mse_never," in csv_text and "mgn,generated_mesh_iou_never," in csv_text
    assert "alpha_shapes,generated_mesh_iou_k1," in csv_text


def test_a_single_array_task_and_bad_sweeps(tiny_data_dir, tmp_path):
    sweep = load_sweep(write_sweep(tmp_path, tiny_data_dir))
    with pytest.raises(IndexError, match="task 2 outside"):
        run_sweep(sweep, task=2)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"output": "x", "seeds": [0, 0], "models": {"mgn": {"config": str(CONF_DIR / "plate" / "mgn.yaml")}}}))
    with pytest.raises(ValueError, match="repeated seeds"):
        load_sweep(bad)
    bad.write_text(yaml.safe_dump({"output": "x", "seeds": [0], "models": {"mgn": {"config": "nope.yaml"}}}))
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        load_sweep(bad)
    with pytest.raises(ValueError, match=r"initial_mesh names models \['ggns'\]"):
        baseline_spec({**sweep, "baselines": {"initial_mesh": ["ggns"]}})
    with pytest.raises(ValueError, match="unknown keys"):
        baseline_spec({**sweep, "baselines": {"alpha": True}})


def test_slurm_script_has_one_task_per_run(tmp_path):
    sweep = load_sweep("plate", ["seeds=[0,1,2]"])
    script = slurm_script(sweep, "conf/sweeps/plate.yaml", partition="gpu")
    assert script.startswith("#!/bin/bash\n")
    assert "#SBATCH --array=0-11" in script  # 4 models x 3 seeds
    assert "#SBATCH --partition=gpu" in script and "#SBATCH --gres=gpu:1" in script
    assert "#SBATCH --signal=SIGUSR1@90" in script
    assert "python -m ggns sweep --config conf/sweeps/plate.yaml --task $SLURM_ARRAY_TASK_ID" in script


@pytest.mark.parametrize("preset", sorted(p.stem for p in (CONF_DIR / "sweeps").glob("*.yaml")))
def test_every_run_of_every_sweep_preset_parses(preset, tmp_path):
    """Each model of each shipped sweep builds through the Lightning CLI with its arguments
    (catches typos in option names and values; nothing is trained)."""
    from ggns.cli import build_cli

    sweep = load_sweep(preset, [f"output={tmp_path}"])
    baseline_spec(sweep)  # its baselines section, if any, is valid
    for run in {r.model: r for r in runs_of(sweep)}.values():
        argv = ["--config", run.config, "--seed_everything", str(run.seed),
                "--trainer.logger.init_args.save_dir", str(tmp_path), *run.args]
        cli = build_cli(argv, run=False)
        assert cli.model.hparams.connectivity.startswith("plate_")
