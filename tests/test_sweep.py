"""Multi-seed sweeps end to end on tiny generated data (the Lightning CLI's fits and tests run in this process
through `launch_in_process`; the real processes of a sweep are test_faults.py's and test_bad_input.py's):
each metric family tested with the checkpoint selected on it, resume (finished runs and test parts
skipped), the fallbacks of fits without per-family checkpoints, and the SLURM job-array script."""
from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch
import yaml

from ggns.config import CONF_DIR, preset_files
from ggns.baselines.scores import GENERATED_MESH_FILE
from ggns.sweeps.summary import baseline_spec, run_baselines, summarize
from ggns.sweeps.sweep import Run, load_sweep, prepare_datasets, run_sweep, runs_of, slurm_script
from conftest import TINY12, launch_in_process


def tiny_overrides(data_dir) -> dict:
    """The Lightning settings of a tiny fit on the plate_tiny data in `data_dir` (2 epochs of 2 batches)."""
    return {"data": {"dataset": str(data_dir / TINY12), "data_dir": str(data_dir), "generate_missing": False,
                     "batch_size": 8},
            "model": {"init_args": {"latent": 16, "blocks": 2}},
            "trainer": {"max_epochs": 2, "limit_train_batches": 2, "limit_val_batches": 1, "check_val_every_n_epoch": 1,
                        "enable_progress_bar": False, "enable_model_summary": False}}


def write_sweep(tmp_path, data_dir, seeds=(0, 1)) -> str:
    sweep = {"output": str(tmp_path / "sweep"), "seeds": list(seeds), "parallel": 2, "overrides": tiny_overrides(data_dir),
             "models": {"mgn": {"config": str(CONF_DIR / "plate" / "mgn.yaml")}},
             "baselines": {"dataset": str(data_dir / TINY12), "data_dir": str(data_dir), "alpha_shapes": True,
                           "static": True, "initial_mesh": ["mgn"]}}
    path = tmp_path / "sweep.yaml"
    path.write_text(yaml.safe_dump(sweep))
    return str(path)


def perturbed_copy(source: Path, target: Path, monitor: str, step: int) -> None:
    """`source` with its weights scaled by 1.01 and global step `step`, saved as `target` and
    recorded as the best checkpoint of the ModelCheckpoint monitoring `monitor`."""
    checkpoint = torch.load(source, weights_only=False)
    checkpoint["state_dict"] = {k: v * 1.01 if k.startswith("core.") and v.is_floating_point() else v
                                for k, v in checkpoint["state_dict"].items()}
    checkpoint["global_step"] = step
    (state,) = [v for k, v in checkpoint["callbacks"].items()
                if k.startswith("ModelCheckpoint") and v["monitor"] == monitor]
    state["best_model_path"] = str(target)
    torch.save(checkpoint, target)


def test_two_seed_sweep_runs_skips_and_resumes(cli_data, tmp_path):
    sweep = load_sweep(write_sweep(tmp_path, cli_data))
    runs = runs_of(sweep)
    assert [(r.model, r.seed) for r in runs] == [("mgn", 0), ("mgn", 1)]
    messages = []
    run_sweep(sweep, log=messages.append, launch=launch_in_process)
    metrics = {r.seed: json.loads(r.metrics_path.read_text()) for r in runs}
    for run, m in zip(runs, metrics.values()):
        assert "rollout_mse_never" in m and m["rollout_mse_never"]["count"] == 2
        # each metric family was tested with the checkpoint selected on it (MGN: never, m10; one-step: never)
        (never,) = (run.fit_dir / "checkpoints").glob("best-never-step=*.ckpt")
        (m10,) = (run.fit_dir / "checkpoints").glob("best-m10-step=*.ckpt")
        chosen = m.pop("checkpoints")
        assert {f: c["name"] for f, c in chosen.items()} == {"never": never.name, "m10": m10.name,
                                                             "one_step": never.name}
        assert chosen["never"]["selected_on"] == "val/rollout_mse_never"
        assert chosen["m10"]["selected_on"] == "val/m10_mse"
        assert chosen["m10"]["metrics"] == ["m10_mse", "m10_pooled_mse"]
        assert sorted(chosen["never"]["metrics"]) == ["rollout_iou_never", "rollout_mse_never"]
        assert sorted(m) == ["m10_mse", "m10_pooled_mse", "one_step_mse", "rollout_iou_never", "rollout_mse_never"]
        # ... by one test per checkpoint, each computing only its families' metrics
        parts = {path.parent.name: data for path, data in
                 ((p, json.loads(p.read_text())) for p in run.test_dir.glob("*/test_metrics.json"))}
        assert sorted(parts) == sorted([never.stem, m10.stem])
        assert sorted(parts[m10.stem]) == ["checkpoint", "m10_mse", "m10_pooled_mse", "one_step_mse"]
        assert parts[m10.stem]["m10_mse"] == m["m10_mse"] and parts[never.stem]["one_step_mse"] == m["one_step_mse"]
        assert "| m10 | " + m10.name in (run.test_dir / "test_metrics.md").read_text()
    assert metrics[0]["rollout_mse_never"]["mean"] != metrics[1]["rollout_mse_never"]["mean"]  # seeds differ
    stamp = runs[1].metrics_path.stat().st_mtime_ns

    # resume: seed 1 is finished and skipped; seed 0 got a new best-m10 checkpoint (another step and
    # weights) and lost its merged metrics: neither its fit nor its finished never part runs again,
    # only a test of the new m10 checkpoint
    run = runs[0]
    directory = run.fit_dir / "checkpoints"
    (old,) = directory.glob("best-m10-step=*.ckpt")
    perturbed_copy(old, directory / "best-m10-step=1.ckpt", "val/m10_mse", 1)
    old.unlink()
    run.metrics_path.unlink()
    messages.clear()
    run_sweep(sweep, log=messages.append, launch=launch_in_process)
    assert any("skip mgn seed 1" in m for m in messages) and runs[1].metrics_path.stat().st_mtime_ns == stamp
    assert not any(m.startswith("fit") for m in messages)  # the fit ended before its tests began
    assert any(m.startswith("skip test mgn seed 0 best-never-step=") for m in messages)
    assert [m for m in messages if m.startswith("test")] == ["test (m10 with best-m10-step=1.ckpt) mgn seed 0"]
    merged = json.loads(run.metrics_path.read_text())
    m10 = merged["checkpoints"]["m10"]
    assert (m10["global_step"], m10["name"], m10["selected_on"]) == (1, "best-m10-step=1.ckpt", "val/m10_mse")
    assert merged["m10_mse"]["mean"] != metrics[0]["m10_mse"]["mean"]
    part = json.loads((run.test_dir / "best-m10-step=1" / "test_metrics.json").read_text())
    assert merged["m10_mse"] == part["m10_mse"]
    assert merged["rollout_mse_never"] == metrics[0]["rollout_mse_never"]

    written = run_baselines(sweep, log=messages.append)
    assert sorted(p.name for p in written) == [GENERATED_MESH_FILE] * 2 + ["test_metrics.json"] * 2
    static = json.loads((runs[0].output / "static" / "test_metrics.json").read_text())
    assert static["rollout_mse_never"]["count"] == 2 and static["rollout_mse_never"]["mean"] > 0
    assert 0.0 < static["rollout_iou_never"]["mean"] < 1.0  # the plate moves, so holding S_0 loses overlap
    assert static["one_step_mse"]["count"] == 2 and static["one_step_mse"]["mean"] > 0  # no motion, one step
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
    # per run and family: the tested checkpoint, its step / epoch and the scalar it was selected on
    assert "| mgn | 0 | m10 | best-m10-step=1.ckpt | 1 / " in summary
    (never,) = (runs[1].fit_dir / "checkpoints").glob("best-never-step=*.ckpt")
    step = torch.load(never, weights_only=False)["global_step"]
    assert f"| mgn | 1 | never | {never.name} | {step} / " in summary
    assert f"| mgn | 1 | one_step | {never.name} | {step} / " in summary
    assert summary.count("val/rollout_mse_never = ") == 4  # never and one_step of both runs
    # the targets, with the static row as the no-motion reference, and each run's learning curves
    assert "## The project's targets on this sweep" in summary and "(no motion: " in summary
    assert "## Learning curves of each run" in summary and "learning_curves.png" in summary
    assert (runs[0].output / "learning_curves.png").is_file()
    (row,) = [line for line in summary.splitlines() if line.startswith("| mgn seed 1 |")]
    assert int(row.split("|")[2]) == 4  # the fit's optimizer steps: 2 epochs x 2 batches
    csv_text = (runs[0].output / "summary.csv").read_text()
    assert "mgn,rollout_mse_never," in csv_text and "mgn,generated_mesh_iou_never," in csv_text
    assert "alpha_shapes,generated_mesh_iou_k1," in csv_text


def test_checkpoint_fallbacks_of_older_and_unvalidated_fits(tmp_path):
    """A fit from before per-family selection (one best-epoch=N.ckpt) tests every family with that
    checkpoint and says so; a fit that never validated tests with last.ckpt."""
    import pytorch_lightning as pl

    from ggns.models.simulators import MGN

    trainer = pl.Trainer(logger=False, enable_checkpointing=False, accelerator="cpu")
    trainer.strategy.connect(MGN(latent=8, blocks=1))
    run = Run("mgn", 0, str(CONF_DIR / "plate" / "mgn.yaml"), (), tmp_path)
    directory = run.fit_dir / "checkpoints"
    directory.mkdir(parents=True)
    trainer.save_checkpoint(directory / "last.ckpt")
    selections = run.checkpoints()
    assert list(selections) == ["never", "m10", "one_step"]
    assert all(s.checkpoint.name == "last.ckpt" and "no validation ran" in s.note for s in selections.values())
    shutil.copy(directory / "last.ckpt", directory / "best-epoch=3.ckpt")
    selections = run.checkpoints()
    assert all(s.checkpoint.name == "best-epoch=3.ckpt" and "before per-family selection" in s.note
               for s in selections.values())
    (part,) = run.test_parts()
    assert (part.families, part.schedules, part.m_plus_10) == (("never", "m10", "one_step"), ("never",), True)
    assert part.test_dir == run.test_dir / "best-epoch=3"
    command = run.test_command(part)
    assert command[-6:] == ["--ckpt_path", str(directory / "best-epoch=3.ckpt"), "--evaluation.schedules",
                            '["never"]', "--evaluation.m_plus_10", "true"]
    # a run tested before per-family selection (its test_metrics.json names no checkpoints): the
    # summary shows the checkpoint it was tested with, and says so
    run.test_dir.mkdir()
    run.metrics_path.write_text(json.dumps({"rollout_mse_never": {"mean": 0.5, "std": 0.1, "count": 2}}))
    sweep = {"output": str(tmp_path), "seeds": [0], "models": {"mgn": {"config": run.config}}}
    summary = summarize(sweep, log=lambda message: None).read_text()
    assert ("| mgn | 0 | never | best-epoch=3.ckpt | 0 / 0 | - | tested before per-family selection (one checkpoint "
            "for every family) | - |") in summary
    assert "as GGNS" not in summary
    # a model named in findings_ggns is judged in GGNS's place: its rollout_mse_never is GGNS's "never"
    summary = summarize({**sweep, "findings_ggns": ["mgn"]}, log=lambda message: None).read_text()
    section = summary.split("## The paper's findings and the project's targets with `mgn` as GGNS")[1]
    assert "| GGNS rollout MSE: k=1 < k=2 < k=5 < k=10 < never | not checked | missing: k=1, k=2, k=5, k=10 |" in section
    # a family without its own best falls back to another family's, and says so
    shutil.copy(directory / "last.ckpt", directory / "best-never-step=5.ckpt")
    selections = run.checkpoints()
    assert selections["never"].checkpoint.name == "best-never-step=5.ckpt" and selections["never"].note == ""
    assert selections["m10"].checkpoint.name == "best-never-step=5.ckpt"
    assert selections["m10"].note == "no best-m10 checkpoint: never's"


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
    bad.write_text(yaml.safe_dump({"output": "x", "seeds": [0], "findings_ggns": ["ggns_id"],
                                   "models": {"mgn": {"config": str(CONF_DIR / "plate" / "mgn.yaml")}}}))
    with pytest.raises(ValueError, match=r"findings_ggns names \['ggns_id'\], which are not models"):
        load_sweep(bad)
    with pytest.raises(ValueError, match=r"initial_mesh names models \['ggns'\]"):
        baseline_spec({**sweep, "baselines": {"initial_mesh": ["ggns"]}})
    with pytest.raises(ValueError, match="unknown keys"):
        baseline_spec({**sweep, "baselines": {"alpha": True}})


def test_slurm_script_has_one_task_per_run(tmp_path):
    sweep = load_sweep("plate", ["seeds=[0,1,2]"])
    script = slurm_script(sweep, "conf/sweeps/plate.yaml", partition="gpu")
    assert script.startswith("#!/bin/bash\n")
    assert "#SBATCH --array=0-14" in script  # 5 models (the four and mgn_shared) x 3 seeds
    assert "#SBATCH --partition=gpu" in script and "#SBATCH --gres=gpu:1" in script
    assert "#SBATCH --signal=SIGUSR1@90" in script
    assert "python -m ggns sweep --config conf/sweeps/plate.yaml --task $SLURM_ARRAY_TASK_ID" in script


@pytest.mark.parametrize("preset", sorted(p.stem for p in preset_files("sweeps")))
def test_every_run_of_every_sweep_preset_parses(preset, tmp_path):
    """Each model of each sweep preset (shipped, and the experiments' of this checkout) builds through the Lightning CLI with its arguments
    (catches typos in option names and values; nothing is trained)."""
    from ggns.cli import build_cli

    sweep = load_sweep(preset, [f"output={tmp_path}"])
    baseline_spec(sweep)  # its baselines section, if any, is valid
    for run in {r.model: r for r in runs_of(sweep)}.values():
        argv = run.fit_command()[4:]  # after `python -m ggns fit`; the logger's save_dir: the output, tmp_path
        cli = build_cli(argv, run=False)
        scene = cli.datamodule.hparams.dataset.split("_")[0]  # plate_small -> plate, tissue_cpu -> tissue
        graph = cli.config["model"]["init_args"]["connectivity"]  # the preset named; the model keeps its values
        assert Path(str(graph)).stem.startswith(f"{scene}_"), graph  # the model's graph is the data's scene's
        assert cli.model.hparams.connectivity == dataclasses.asdict(cli.model.connectivity)


def _last(args: tuple, option: str) -> str | None:
    values = [args[i + 1] for i, a in enumerate(args) if a == option]
    return values[-1] if values else None


EQUAL_STEP_PRESETS = sorted([p.stem for p in (CONF_DIR / "sweeps").glob("*.yaml")] + ["plate_equal_steps"])


@pytest.mark.parametrize("preset", EQUAL_STEP_PRESETS)
def test_a_shipped_sweep_gives_every_model_the_same_optimizer_steps(preset, tmp_path):
    """The shipped presets and the plate's equal-step study budget every model in optimizer steps (or, the
    paper-scale ones, in epochs of the same data and batch), never in wall time: a comparison between their
    models is one at equal training."""
    runs = {r.model: r.fit_command() for r in runs_of(load_sweep(preset, [f"output={tmp_path}"]))}
    assert len(runs) >= 3
    budgets = {model: (_last(args, "--trainer.max_steps"), _last(args, "--trainer.max_epochs"),
                       _last(args, "--data.batch_size")) for model, args in runs.items()}
    assert len(set(budgets.values())) == 1, budgets
    for model, args in runs.items():
        assert _last(args, "--trainer.max_time") in (None, "null"), (preset, model)
    steps, epochs, _ = next(iter(budgets.values()))
    assert steps is not None or preset in ("plate", "tissue", "cavity"), preset  # the GPU presets: epochs


def test_missing_datasets_are_generated_once_before_parallel_runs(cli_data, tmp_path):
    """`prepare_datasets` generates the split files the runs need into the directory they name, once
    for runs sharing a dataset; a second call finds them and generates nothing."""
    empty = tmp_path / "data"
    args = ("--data.dataset", str(cli_data / TINY12), "--data.data_dir", str(empty))
    runs = [Run("mgn", seed, str(CONF_DIR / "plate" / "mgn.yaml"), args, tmp_path / "sweep") for seed in (0, 1)]
    messages = []
    assert prepare_datasets(runs, messages.append) == [str(cli_data / TINY12)]
    assert len(messages) == 1 and "generate" in messages[0]
    assert all((empty / f"{split}.h5").is_file() for split in ("train", "val", "test"))
    messages.clear()
    prepare_datasets(runs, messages.append)
    assert messages == []


def test_a_run_stacks_its_config_files_and_flattens_its_overrides(cli_data, tmp_path):
    """A run's fit: its model's config, the sweep's `configs`, the model's `configs` (a later file wins key by
    key), then the sweep's `overrides` merged with the model's (the model's win) as `--dotted.key value`
    arguments, which win over every file; `Run.setting` reads the stack (prepare_datasets' dataset)."""
    from ggns.cli import build_cli

    (tmp_path / "first.yaml").write_text(f"data: {{dataset: {cli_data / TINY12}, batch_size: 4}}\n"
                                        "trainer: {max_epochs: 5}\n")
    (tmp_path / "second.yaml").write_text("data: {batch_size: 2}\nmodel: {init_args: {lr_schedule: {lr: 1.0e-3}}}\n")
    mgn = str(CONF_DIR / "plate" / "mgn.yaml")
    sweep = {"output": str(tmp_path / "out"), "seeds": [3], "configs": [str(tmp_path / "first.yaml")],
             "overrides": {"trainer": {"max_epochs": 6, "check_val_every_n_epoch": None},
                           "model": {"init_args": {"latent": 16, "noise": {"std": 0.0}}}},
             "models": {"mgn": {"config": mgn, "configs": [str(tmp_path / "second.yaml")],
                                "overrides": {"trainer.max_epochs": 7, "model": {"init_args": {"blocks": 1}},
                                              "data": {"data_dir": str(cli_data)}}}}}
    path = tmp_path / "sweep.yaml"
    path.write_text(yaml.safe_dump(sweep, sort_keys=False))
    (run,) = runs_of(load_sweep(path))
    assert run.configs == (str(tmp_path / "first.yaml"), str(tmp_path / "second.yaml"))
    assert list(run.args) == ["--trainer.max_epochs", "7", "--trainer.check_val_every_n_epoch", "null",
                              "--model.init_args.latent", "16", "--model.init_args.noise.std", "0.0",
                              "--model.init_args.blocks", "1", "--data.data_dir", str(cli_data)]
    command = run.fit_command()
    assert command[3:9] == ["fit", "--config", mgn, "--config", str(tmp_path / "first.yaml"), "--config"]
    assert command[command.index("--seed_everything") + 1] == "3" and command[-len(run.args):] == list(run.args)
    cli = build_cli(command[4:], run=False)
    assert cli.datamodule.batch_size == 2  # second.yaml over first.yaml
    assert cli.trainer.max_epochs == 7 and cli.trainer.check_val_every_n_epoch is None  # the arguments over the files
    assert (cli.model.hparams.latent, cli.model.hparams.blocks, cli.model.lr_schedule.lr) == (16, 1, 1e-3)
    assert run.setting("data.dataset") == str(cli_data / TINY12) and run.setting("data.batch_size") == 2
    assert run.setting("trainer.max_epochs") == 7 and run.setting("data.data_dir") == str(cli_data)
    assert prepare_datasets([run], lambda message: None) == [str(cli_data / TINY12)]  # found, nothing generated


def test_a_sweep_file_extends_another(tmp_path):
    """`base:`: the base's keys with the file's on top (mappings merged key by key), `models` replaced whole;
    a base by name is a sweep preset; a missing base and a cycle are refused naming the file."""
    mgn, ggns = str(CONF_DIR / "plate" / "mgn.yaml"), str(CONF_DIR / "plate" / "ggns.yaml")
    (tmp_path / "parent.yaml").write_text(yaml.safe_dump(
        {"output": "out", "seeds": [0], "parallel": 2, "overrides": {"data": {"dataset": "plate_small", "batch_size": 8}},
         "models": {"mgn": {"config": mgn}, "ggns": {"config": ggns}}}))
    (tmp_path / "child.yaml").write_text(yaml.safe_dump(
        {"base": "parent.yaml", "seeds": [1, 2], "overrides": {"data": {"batch_size": 4}},
         "models": {"ggns": {"config": ggns}}}))
    sweep = load_sweep(tmp_path / "child.yaml")
    assert "base" not in sweep and sweep["seeds"] == [1, 2] and sweep["parallel"] == 2
    assert sweep["overrides"] == {"data": {"dataset": "plate_small", "batch_size": 4}} and list(sweep["models"]) == ["ggns"]
    (tmp_path / "named.yaml").write_text(yaml.safe_dump({"base": "plate", "output": str(tmp_path / "o")}))
    assert [r.model for r in runs_of(load_sweep(tmp_path / "named.yaml"))][:1] == ["ggns"]  # conf/sweeps/plate.yaml's
    (tmp_path / "lost.yaml").write_text("base: nowhere\n")
    with pytest.raises(ValueError, match=r"lost\.yaml: its base 'nowhere' is neither a file beside it nor a preset of conf/sweeps/"):
        load_sweep(tmp_path / "lost.yaml")
    (tmp_path / "parent.yaml").write_text(yaml.safe_dump({"base": "child.yaml", "output": "out"}))
    with pytest.raises(ValueError, match=r"child\.yaml: its base 'parent\.yaml' makes a cycle|parent\.yaml: its base 'child\.yaml' makes a cycle"):
        load_sweep(tmp_path / "child.yaml")


def test_lists_of_command_line_strings_are_refused_naming_the_mapping(tmp_path):
    """The former form (`args: ["--trainer.max_time", ...]`, in a sweep or a model) is an error naming the file,
    the place and the mapping that says the same; so is `overrides` with a key Lightning does not have."""
    mgn = str(CONF_DIR / "plate" / "mgn.yaml")
    path = tmp_path / "old.yaml"
    for spec, where in (({"args": ["--trainer.max_time", "00:00:12:00", "--model.init_args.latent", "64"],
                          "models": {"mgn": {"config": mgn}}}, "`args`"),
                        ({"models": {"mgn": {"config": mgn, "args": ["--trainer.max_time", "00:00:12:00",
                                                                     "--model.init_args.latent", "64"]}}},
                         "model 'mgn': `args`")):
        path.write_text(yaml.safe_dump({"output": "out", "seeds": [0], **spec}))
        with pytest.raises(ValueError) as error:
            load_sweep(path)
        message = str(error.value)
        assert message.startswith(f"{path}: {where}: a list of command-line strings is the former form"), message
        assert "{trainer: {max_time: '00:00:12:00'}, model: {init_args: {latent: 64}}}" in message
    path.write_text(yaml.safe_dump({"output": "out", "seeds": [0], "overrides": {"trainers": {"max_epochs": 1}},
                                    "models": {"mgn": {"config": mgn}}}))
    with pytest.raises(ValueError, match=r"`overrides` has keys \['trainers'\], which are not Lightning's"):
        load_sweep(path)
    path.write_text(yaml.safe_dump({"output": "out", "seeds": [0], "configs": ["gone.yaml"],
                                    "models": {"mgn": {"config": mgn}}}))
    with pytest.raises(FileNotFoundError, match="config gone.yaml not found"):
        load_sweep(path)
