"""`python -m ggns bench learning` (`ggns.sweeps.learning`): the curve summaries on hand-made
curves, and two tiny GGNS variants end to end (fits of the Lightning CLI in this process, `launch_in_process`, on
plate_tiny with T = 12, a budget of 4 optimizer steps): table, CSV and figures, the logged lr, resume."""
from __future__ import annotations

import csv
import json
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import TINY12, launch_in_process
from ggns.__main__ import main
from ggns.checkpoints import read_checkpoint
from ggns.config import CONF_DIR, preset_files
from ggns.sweeps.curves import CLOCK, COLUMNS, late_slope, read_scalars, steps_to_threshold, variant_row
from ggns.sweeps.learning import FINISHED, load_learning, run_learning, variant_runs
from ggns.models.lr_schedule import scheduled_lr


def curve(steps, values, wall=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    steps = np.asarray(steps, dtype=float)
    return steps, np.asarray(wall if wall is not None else steps, dtype=float), np.asarray(values, dtype=float)


def test_steps_to_threshold_and_late_slope():
    assert steps_to_threshold([10, 20, 30, 40], [0.9, 0.25, 0.2, 0.1], 0.2) == 30  # at the threshold counts
    assert steps_to_threshold([10, 20, 30], [0.9, 0.1, 0.5], 0.2) == 20  # the first time, even if it goes back up
    assert steps_to_threshold([10, 20], [0.9, 0.21], 0.2) is None and steps_to_threshold([], [], 0.2) is None
    steps = np.arange(0, 4001, 500)
    assert late_slope(steps, 10.0 ** (-steps / 1000)) == pytest.approx(-1.0)  # one decade per 1000 steps
    # only the second half counts: a fall before step 2000, flat after
    assert late_slope(steps, np.where(steps < 2000, 10.0 ** (-steps / 500), 1e-4)) == pytest.approx(0.0, abs=1e-12)
    assert late_slope([100, 200], [1.0, 0.5]) is not None and late_slope([200], [1.0]) is None
    # validations at 2000, 4000 and the fit's end 4001: the half [2000.5, 4001] spans one step, so 2000 joins
    # (was -81 decades per 1000 steps, read off one step's change in a sweep summary)
    assert late_slope([2000, 4000, 4001], [1e-4, 1e-5, 0.99e-5]) == pytest.approx(
        np.polyfit([2.0, 4.0, 4.001], np.log10([1e-4, 1e-5, 0.99e-5]), 1)[0])
    assert late_slope([4000, 4001], [1e-5, 0.99e-5]) is None  # one step apart and nothing earlier: no slope


def test_variant_row_on_hand_made_curves():
    """The clock maps steps to training seconds (validation excluded); the ratio first reaches 0.2 at
    step 200, i.e. after 40 training seconds."""
    scalars = {CLOCK: curve([100, 200, 300], [20.0, 40.0, 60.0]),
               "val/one_step_ratio": curve([100, 200, 300], [0.5, 0.2, 0.15]),
               "val/rollout_mse_never": curve([100, 200, 300], [1e-2, 1e-3, 1e-4]),
               "train/loss": curve([99, 199, 299], [1.0, 0.5, 0.4])}
    row = variant_row("a", ["--model.init_args.noise.std", "0.005"], scalars)
    assert list(row) == list(COLUMNS)
    assert row["change"] == "--model.init_args.noise.std 0.005" and row["steps"] == 300
    assert row["train_seconds"] == 60.0 and row["steps_per_second"] == 5.0
    assert (row["steps_to_ratio"], row["seconds_to_ratio"]) == (200, 40.0)
    assert (row["best_one_step_ratio"], row["last_one_step_ratio"]) == (0.15, 0.15)
    assert (row["rollout_mse_never_last"], row["rollout_mse_never_best"]) == (1e-4, 1e-4)
    assert row["slope_never"] == pytest.approx(-10.0)  # two decades over the last 100 steps (150..300: 200, 300)
    assert row["rollout_mse_k1_last"] is None and row["slope_k1"] is None  # no k=1 curve (MGN): n/a
    assert (row["validations"], row["last_val_step"]) == (3, 300)
    assert row["m10_mse_best"] is None and row["loss_points_late"] is None  # not logged: n/a
    # m+10 and the late training loss with / without point clouds (mean over the last 1000 steps)
    late = {"val/m10_mse": curve([100, 200, 300], [3e-3, 1e-3, 2e-3]),
            "train/loss_points": curve(np.arange(0, 3000, 500), [9.0, 9.0, 9.0, 9.0, 0.2, 0.4]),
            "train/loss_no_points": curve(np.arange(0, 3000, 500), [9.0, 9.0, 9.0, 9.0, 0.6, 0.6])}
    row = variant_row("a", [], {**scalars, **late})
    assert (row["m10_mse_last"], row["m10_mse_best"]) == (2e-3, 1e-3)
    assert row["slope_m10"] == pytest.approx(10 * np.log10(2))  # 1e-3 -> 2e-3 over steps 200..300
    assert row["loss_points_late"] == pytest.approx(0.3) and row["loss_no_points_late"] == pytest.approx(0.6)
    # without the clock: wall seconds, no steps/s
    wall = {k: curve(s, v, wall=s / 10 + 1000) for k, (s, _, v) in scalars.items() if k != CLOCK}
    row = variant_row("b", [], wall)
    assert row["change"] == "(base)" and row["steps_per_second"] is None and row["train_seconds"] == pytest.approx(20.1)


def write_learning(tmp_path, data_dir) -> str:
    (tmp_path / "tiny.yaml").write_text(  # a config file stacked after each variant's model config
        "model: {init_args: {latent: 16, blocks: 2}}\n"
        "trainer: {max_steps: 4, limit_val_batches: 1, log_every_n_steps: 1, enable_model_summary: false}\n")
    tiny = {"data": {"dataset": str(data_dir / TINY12), "data_dir": str(data_dir), "generate_missing": False,
                     "batch_size": 8},
            "trainer": {"enable_progress_bar": False}}
    spec = {"output": str(tmp_path / "learning"), "minutes": 5, "val_every": 2, "seed": 0, "parallel": 2,
            "run": {"config": str(CONF_DIR / "plate" / "ggns.yaml"), "configs": [str(tmp_path / "tiny.yaml")],
                    "overrides": tiny},
            # the second variant is another model (MGN, its own config) with the run's files and settings and its own
            "variants": {"paper": {}, "decay": {"config": str(CONF_DIR / "plate" / "mgn.yaml"),
                                                "overrides": {"model": {"init_args": {"lr_schedule": {
                                                    "decay_rate": 0.5, "decay_steps": 2}}}}}}}
    path = tmp_path / "learning.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return str(path)


def test_two_tiny_variants_end_to_end_and_resume(cli_data, tmp_path):
    spec = load_learning(write_learning(tmp_path, cli_data))
    runs = variant_runs(spec)
    assert [r.model for r in runs] == ["paper", "decay"]
    assert "00:00:05:00" in runs[0].args and runs[1].args[-1] == "2"  # the budget first, the variant last
    assert runs[0].config.endswith("ggns.yaml") and runs[1].config.endswith("mgn.yaml")
    assert str(cli_data) in runs[1].args  # the run's settings apply to a variant with its own config
    assert runs[1].configs == (str(tmp_path / "tiny.yaml"),)  # and so do its files
    messages = []
    report = run_learning(spec, log=messages.append, launch=launch_in_process)
    output = tmp_path / "learning"
    assert sorted(p.name for p in output.glob("*.png")) == ["curves_seconds.png", "curves_steps.png"]
    with open(output / "learning.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["variant"] for r in rows] == ["paper", "decay"] and list(rows[0]) == list(COLUMNS)
    for row in rows:
        assert int(row["steps"]) == 4 and float(row["steps_per_second"]) > 0
        assert 0 < float(row["train_seconds"]) < 300
        assert int(row["validations"]) == 2 and int(row["last_val_step"]) == 4  # after steps 2 and 4
        assert math.isfinite(float(row["rollout_mse_never_last"]))
    text = report.read_text()
    assert "Finished: 2 of 2 variants" in text and "| paper | `(base)` | 4 |" in text
    assert (f"| decay | `--config {CONF_DIR / 'plate' / 'mgn.yaml'} --model.init_args.lr_schedule.decay_rate 0.5 "
            "--model.init_args.lr_schedule.decay_steps 2` | 4 |") in text
    assert rows[0]["rollout_mse_k1_last"] and not rows[1]["rollout_mse_k1_last"]  # MGN has no point clouds
    # every validation, step by step: the CSV and the report's table
    with open(output / "learning_validations.csv") as f:
        validations = list(csv.DictReader(f))
    assert [(v["variant"], v["step"]) for v in validations] == [("paper", "2"), ("paper", "4"), ("decay", "2"), ("decay", "4")]
    assert all(float(v["rollout_mse_never"]) > 0 and 0 < float(v["train_seconds"]) < 300 for v in validations)
    assert [bool(v["rollout_mse_k1"]) for v in validations] == [True, True, False, False]
    assert float(validations[1]["rollout_mse_k1"]) == pytest.approx(float(rows[0]["rollout_mse_k1_last"]))
    table = text.split("## At each validation")[1]
    assert "| step | paper: rollout_mse_k1 |" in table and "decay: rollout_mse_never" in table
    assert "decay: rollout_mse_k1" not in table and len([l for l in table.splitlines() if l.startswith(("| 2 |", "| 4 |"))]) == 2
    hparams = [read_checkpoint(r.fit_dir / "checkpoints" / "last.ckpt")["hyper_parameters"] for r in runs]
    assert hparams[0]["point_probability"] > 0 and hparams[1]["point_probability"] == 0
    assert not any(key in h for h in hparams for key in ("eval_schedules", "test_m_plus_10", "test_iou"))  # the callback's
    # the LearningRateMonitor of the CLI logged the scheduled lr of each of the 4 steps
    steps, _, lrs = read_scalars(runs[1].fit_dir)["train/lr"]
    assert steps.tolist() == [1, 2, 3, 4]
    assert lrs.tolist() == pytest.approx([scheduled_lr(n - 1, 5e-4, 0.0, 0.5, 2) for n in range(1, 5)], rel=1e-6)
    assert read_scalars(runs[0].fit_dir)["train/lr"][2].tolist() == pytest.approx([5e-4] * 4)  # the paper's constant lr

    # resume: both finished variants are skipped, the report is rewritten
    stamps = [(r.fit_dir / FINISHED).stat().st_mtime_ns for r in runs]
    messages.clear()
    run_learning(spec, log=messages.append, launch=launch_in_process)
    assert sorted(m for m in messages if m.startswith(("skip", "fit"))) == [
        f"skip {r.model}: {r.fit_dir / FINISHED} exists" for r in sorted(runs, key=lambda r: r.model)]
    assert [(r.fit_dir / FINISHED).stat().st_mtime_ns for r in runs] == stamps
    # a finished variant whose arguments changed is an error, not a silent skip; so is a changed config file
    changed = load_learning(write_learning(tmp_path, cli_data), ["val_every=3"])
    with pytest.raises(ValueError, match="finished with other arguments .*trainer.val_check_interval: 2 then, 3 now"):
        run_learning(changed, only=["paper"])
    tiny_text = (tmp_path / "tiny.yaml").read_text()
    (tmp_path / "tiny.yaml").write_text(tiny_text.replace("blocks: 2", "blocks: 3"))
    with pytest.raises(ValueError, match="model.init_args.blocks: 2 then, 3 now"):
        run_learning(spec, only=["paper"])
    (tmp_path / "tiny.yaml").write_text(tiny_text)
    # a marker written before config files were stacked holds only the arguments: the same settings as
    # arguments alone (the file's keys among them) are the same fit
    marker = runs[0].fit_dir / FINISHED
    done = json.loads(marker.read_text())
    assert done["configs"] == [str(tmp_path / "tiny.yaml")] and done["settings"]["model.init_args.latent"] == 16
    inline = [part for key, value in done["settings"].items() for part in (f"--{key}", json.dumps(value).strip('"'))
              if not key.endswith("+")] + ["--trainer.callbacks+=ggns.callbacks.TrainingClock"]
    marker.write_text(json.dumps({"args": inline}))
    messages.clear()
    run_learning(spec, only=["paper"], log=messages.append)
    assert messages[0] == f"skip paper: {marker} exists"
    marker.write_text(json.dumps({**done, "args": list(runs[0].args)}))
    # the command line: the report alone
    (output / "learning.md").unlink()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, "argv", ["ggns"])
        main(["bench", "learning", "--config", str(tmp_path / "learning.yaml"), "--report-only"])
    assert (output / "learning.md").read_text() == text
    assert json.loads((runs[0].fit_dir / FINISHED).read_text())["args"] == list(runs[0].args)
    assert "Run: `--config " in text and f"--config {tmp_path / 'tiny.yaml'}` with `--data.dataset" in text


def test_bad_learning_files(tmp_path):
    path = tmp_path / "bad.yaml"
    mgn = str(CONF_DIR / "plate" / "mgn.yaml")
    good = {"output": "x", "minutes": 1, "val_every": 10, "run": {"config": mgn}, "variants": {"a": {}}}
    for change, message in ((dict(variants={}), "at least one"),
                            (dict(variants={"a": "--x"}), "variant 'a' must be a mapping"),
                            (dict(variants={"a": {"config": mgn, "arg": []}}), r"unknown keys: \['arg'\]"),
                            (dict(variants={"a": {"config": mgn, "model": {}}}), r"\['config', 'model'\]: .* \(not both\)"),
                            (dict(variants={"a": {"config": "gone.yaml"}}), "variant 'a': its config gone.yaml not found"),
                            (dict(variants={"a": {"configs": ["gone.yaml"]}}), "variant 'a': config gone.yaml not found"),
                            (dict(variants={"a": {"overrides": ["--x", "1"]}}), "variant 'a': `overrides`: a list"),
                            (dict(variants={"a": {"trainers": {"max_epochs": 1}}}), r"unknown keys: \['trainers'\]"),
                            (dict(minutes=0), "minutes"), (dict(val_every=0), "val_every"),
                            (dict(run={"config": "nope.yaml"}), "nope.yaml"),
                            (dict(run={"config": mgn, "overrides": {"model": 1}, "extra": 1}), r"unknown keys \['extra'\]")):
        path.write_text(yaml.safe_dump({**good, **change}))
        with pytest.raises((ValueError, FileNotFoundError), match=message):
            load_learning(path)
    path.write_text(yaml.safe_dump(good))
    with pytest.raises(ValueError, match=r"unknown variants \['b'\]"):
        run_learning(load_learning(path), only=["b"])


def test_the_former_forms_are_refused_naming_the_new_ones(tmp_path):
    """A variant as a list of command-line strings, `args:` in the run or a variant, `base: {config, args}` and
    `extends:`: each an error naming the file, the variant and what it is now."""
    path = tmp_path / "old.yaml"
    mgn = str(CONF_DIR / "plate" / "mgn.yaml")
    good = {"output": "x", "minutes": 1, "val_every": 10, "run": {"config": mgn}, "variants": {"a": {}}}
    for change, message in (
            (dict(variants={"noise": ["--model.init_args.noise.std", "0.005"]}),
             re.escape("variant 'noise': a list of command-line strings is the former form; Lightning settings are now "
                       "a mapping of their keys (noise: {model: {init_args: {noise: {std: 0.005}}}})")),
            (dict(variants={"b": {"config": mgn, "args": ["--data.batch_size", "4"]}}),
             re.escape("variant 'b': `args`: a list of command-line strings") + ".*"
             + re.escape("(overrides: {data: {batch_size: 4}})")),
            (dict(run={"config": mgn, "args": ["--data.batch_size", "4"]}),
             re.escape("`run`: `args`: a list of command-line strings") + ".*"
             + re.escape("(overrides: {data: {batch_size: 4}})")),
            (dict(run=None, base={"config": mgn, "args": []}),
             re.escape("`base:` names the one file this one extends") + ".*"
             + re.escape("now `run: {config, configs, overrides}`")),
            (dict(extends="plate_ggns"), re.escape("`extends:` is now `base:`"))):
        path.write_text(yaml.safe_dump({k: v for k, v in {**good, **change}.items() if v is not None}))
        with pytest.raises(ValueError, match=message) as error:
            load_learning(path)
        assert str(error.value).startswith(str(path)), error.value


def test_a_variant_in_either_form(tmp_path):
    """A variant is a mapping of Lightning settings over the run's, or {config, configs, overrides}: its own
    model config and files (after the run's) and settings; the files stack in order, the settings win."""
    from ggns.cli import build_cli

    (tmp_path / "small.yaml").write_text("model: {init_args: {latent: 16, blocks: 1}}\ndata: {batch_size: 4}\n")
    (tmp_path / "smaller.yaml").write_text("data: {batch_size: 2}\n")
    spec = {"output": str(tmp_path / "out"), "minutes": 1, "val_every": 10,
            "run": {"config": str(CONF_DIR / "plate" / "ggns.yaml"), "configs": [str(tmp_path / "small.yaml")],
                    "overrides": {"model": {"init_args": {"noise": {"std": 0.02}}}, "trainer": {"max_steps": 3}}},
            "variants": {"noise": {"model": {"init_args": {"noise": {"std": 0.005}}}, "trainer.max_steps": 5},
                         "mgn": {"config": str(CONF_DIR / "plate" / "mgn.yaml"), "configs": [str(tmp_path / "smaller.yaml")],
                                 "overrides": {"model": {"init_args": {"blocks": 2}}}}}}
    path = tmp_path / "learning.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    noise, mgn = variant_runs(load_learning(path))
    assert noise.configs == (str(tmp_path / "small.yaml"),) and noise.config == spec["run"]["config"]
    assert noise.args[-4:] == ("--model.init_args.noise.std", "0.005", "--trainer.max_steps", "5")
    assert mgn.configs == (str(tmp_path / "small.yaml"), str(tmp_path / "smaller.yaml"))
    assert mgn.args[-6:] == ("--model.init_args.noise.std", "0.02", "--model.init_args.blocks", "2",
                             "--trainer.max_steps", "3")
    for run, (kind, std, blocks, batch, steps) in zip((noise, mgn), (("GGNS", 0.005, 1, 4, 5), ("MGN", 0.02, 2, 2, 3))):
        cli = build_cli(run.fit_command()[4:], run=False)
        assert (type(cli.model).__name__, cli.model.noise.std, cli.model.hparams.blocks) == (kind, std, blocks)
        assert (cli.datamodule.batch_size, cli.trainer.max_steps, cli.model.hparams.latent) == (batch, steps, 16)


def test_a_learning_file_extends_another(tmp_path):
    """`base:`: the parent's keys with the child's on top (mappings merged key by key), the child's variants
    replacing the parent's; command-line overrides still win; a base by name is a learning preset; a file that
    extends itself through its parent, and a base that does not exist, are refused naming the file."""
    config = str(CONF_DIR / "plate" / "mgn.yaml")
    parent = {"output": "out", "minutes": 5, "val_every": 10, "seed": 0,
              "run": {"config": config, "overrides": {"data": {"batch_size": 4}}},
              "variants": {"x": {}, "y": {"model": {"init_args": {"blocks": 2}}}}}
    (tmp_path / "parent.yaml").write_text(yaml.safe_dump(parent))
    (tmp_path / "child.yaml").write_text(yaml.safe_dump(
        {"base": "parent.yaml", "seed": 1, "run": {"overrides": {"trainer": {"max_steps": 3}}},
         "variants": {"z": {"model": {"init_args": {"blocks": 3}}}}}))
    spec = load_learning(tmp_path / "child.yaml", ["minutes=7"])
    assert "base" not in spec and spec["seed"] == 1 and spec["minutes"] == 7 and spec["output"] == "out"
    assert spec["variants"] == {"z": {"model": {"init_args": {"blocks": 3}}}}
    assert spec["run"] == {"config": config, "overrides": {"data": {"batch_size": 4}, "trainer": {"max_steps": 3}}}
    (tmp_path / "keep.yaml").write_text(yaml.safe_dump({"base": str(tmp_path / "parent.yaml"), "seed": 2}))
    assert load_learning(tmp_path / "keep.yaml")["variants"] == parent["variants"]  # none of its own: the parent's
    (tmp_path / "named.yaml").write_text(yaml.safe_dump({"base": "plate_ggns", "output": "elsewhere"}))
    assert "lr_decay" in load_learning(tmp_path / "named.yaml")["variants"]  # conf/learning/plate_ggns.yaml's
    (tmp_path / "parent.yaml").write_text(yaml.safe_dump({**parent, "base": "child.yaml"}))
    with pytest.raises(ValueError, match="makes a cycle of bases"):
        load_learning(tmp_path / "child.yaml")
    (tmp_path / "lost.yaml").write_text(yaml.safe_dump({"base": "nowhere", "seed": 2}))
    with pytest.raises(ValueError, match=r"lost\.yaml: its base 'nowhere' is neither a file beside it nor a preset"):
        load_learning(tmp_path / "lost.yaml")


def test_the_cavity_depth_companion_runs_the_parents_blocks_8(tmp_path):
    """cavity_cpu_depth_mgn extends cavity_cpu_depth: its blocks_8 fit is the parent's, on seed 1."""
    parent = {r.model: r for r in variant_runs(load_learning("cavity_cpu_depth", ["seed=1"]))}
    child = {r.model: r for r in variant_runs(load_learning("cavity_cpu_depth_mgn"))}
    assert sorted(child) == ["blocks_8", "mgn_blocks_8"] and child["blocks_8"].seed == 1
    assert child["blocks_8"].fit_command() == parent["blocks_8"].fit_command()
    assert child["mgn_blocks_8"].config == "conf/cavity/mgn.yaml" and child["mgn_blocks_8"].args[-2:] == (
        "--model.init_args.blocks", "8")
    assert child["mgn_blocks_8"].configs == parent["blocks_8"].configs  # the run's files apply to a variant's config


def test_the_shipped_learning_file_parses(tmp_path):
    """Every variant of conf/learning/plate_ggns.yaml builds through the Lightning CLI (nothing is trained)."""
    from ggns.cli import build_cli

    spec = load_learning("plate_ggns", [f"output={tmp_path}"])
    wanted = {"paper", "lr_decay", "noise_0.005", "noise_0.02", "latent64_blocks3", "batch_4", "batch_16"}
    assert wanted <= set(spec["variants"])
    for run in variant_runs(spec):
        cli = build_cli(run.fit_command()[4:], run=False)
        assert cli.datamodule.hparams.dataset == "plate_small"
        if run.model == "lr_decay":
            assert cli.model.lr_schedule.decay_rate == 0.1
        if run.model == "batch_4":
            assert cli.datamodule.batch_size == 4 and cli.trainer.val_check_interval == 200


@pytest.mark.parametrize("name", sorted(p.stem for p in preset_files("learning") if p.stem.startswith(("tissue_", "cavity_"))))
def test_every_variant_of_the_tissue_learning_files_parses(name, tmp_path):
    """Each variant of each tissue and cavity learning file builds through the Lightning CLI with its arguments
    (option names, values, class switches such as GGNS(M)); nothing is trained."""
    task = name.split("_")[0]
    from ggns.cli import build_cli

    for run in variant_runs(load_learning(name, [f"output={tmp_path}"])):
        argv = run.fit_command()[4:]  # after `python -m ggns fit`: its config files and settings
        cli = build_cli(argv, run=False)
        graph = Path(str(cli.config["model"]["init_args"]["connectivity"])).stem  # the preset named
        assert cli.model.hparams.dim == 3 and graph.startswith(f"{task}_"), graph
        dataset = cli.datamodule.hparams.dataset  # the task's CPU data (tissue_cpu, tissue_cpu_60, cavity_tall_cpu)
        assert dataset.split("_")[0] == task and "cpu" in dataset.split("_"), dataset


@pytest.mark.parametrize("name", ["plate_cpu_reach", "plate_cpu_reach_mgn"])
def test_every_variant_of_the_plate_reach_learning_files_parses(name, tmp_path):
    """The point-cloud work's plate learning files: each variant builds through the Lightning CLI with its class
    switch (GGNSID, MGN(M)) and settings (per-type processor, blocks, latent, the field's decay)."""
    from ggns.cli import build_cli
    from ggns.models.simulators import GGNSID, MGNM

    for run in variant_runs(load_learning(name, [f"output={tmp_path}"])):
        argv = run.fit_command()[4:]  # after `python -m ggns fit`: its config files and settings
        cli = build_cli(argv, run=False)
        model = cli.model
        graph = Path(str(cli.config["model"]["init_args"]["connectivity"])).stem  # the preset named
        assert model.hparams.dim == 2 and graph.startswith("plate_"), graph
        assert isinstance(model, GGNSID) == ("id" in run.model.split("_"))
        assert isinstance(model, MGNM) == (run.model == "mgn_m")
        assert model.edge_partition == (run.model.startswith("partition") or run.model == "mgn_m")
        if "blocks_5" in run.model or "blocks_10" in run.model:
            assert model.hparams.blocks == int(run.model.rsplit("_", 1)[1])
        if run.model.endswith("field_decay"):
            assert model.noise.field_decay_steps == 8000


def test_every_variant_of_the_plate_lstm_learning_file_parses(tmp_path):
    """The point-cloud work's GGNS+LSTM budget file: each variant builds a per-type GGNS+LSTM with its window, batch
    and truncated backpropagation (nothing trained)."""
    from ggns.cli import build_cli
    from ggns.models.simulators import GGNSLSTM

    for run in variant_runs(load_learning("plate_cpu_lstm", [f"output={tmp_path}"])):
        argv = run.fit_command()[4:]  # after `python -m ggns fit`: its config files and settings
        cli = build_cli(argv, run=False)
        model = cli.model
        assert isinstance(model, GGNSLSTM) and model.edge_partition
        assert model.window == int(run.model.split("_")[1])
        assert cli.datamodule.batch_size == (int(run.model.split("batch_")[1][0]) if "batch" in run.model else 8)
        assert model.backprop_steps == (int(run.model.split("backprop_")[1]) if "backprop" in run.model else None)


def test_every_variant_of_the_plate_m10_learning_file_parses(tmp_path):
    """The point-cloud work's m+10 file: per-type GGNSID with the field on point-cloud samples only and other
    imputation probabilities (nothing trained)."""
    from ggns.cli import build_cli
    from ggns.models.simulators import GGNSID

    for run in variant_runs(load_learning("plate_cpu_m10", [f"output={tmp_path}"])):
        argv = run.fit_command()[4:]  # after `python -m ggns fit`: its config files and settings
        model = build_cli(argv, run=False).model
        assert isinstance(model, GGNSID) and model.edge_partition
        assert model.noise.field_points_only == run.model.startswith("field_points_only")
        probability = float(run.model.split("points_")[-1]) if "points_0" in run.model else 0.5
        assert model.hparams.point_probability == probability


def test_every_variant_of_the_estimator_learning_files_parses(tmp_path):
    """The point-cloud work's estimator files: the presets' GGNSIDs (plate: the points-only field) with and without
    the estimator's own noise (nothing trained)."""
    from ggns.cli import build_cli
    from ggns.models.simulators import GGNSID

    for preset in ("plate_cpu_estimator", "tissue_cpu_estimator"):
        for run in variant_runs(load_learning(preset, [f"output={tmp_path}"])):
            argv = run.fit_command()[4:]  # after `python -m ggns fit`: its config files and settings
            model = build_cli(argv, run=False).model
            assert isinstance(model, GGNSID) and model.edge_partition
            plate = preset.startswith("plate")
            assert model.noise.field_points_only == plate
            assert model.noise.field_decay_steps == (8000 if plate else 0)
            assert model.noise.field_wavelength == (4.0 if plate else 2.0)
            noise = float(run.model.split("noise_")[1]) if "estimator_noise" in run.model else 0.0
            assert model.estimator_noise.field_std == noise and model.estimator_noise.std == 0
            if noise:  # the smooth field of the model's own training noise, at mixed scales
                assert model.estimator_noise.field_wavelength == model.noise.field_wavelength
                assert model.estimator_noise.field_mixture
