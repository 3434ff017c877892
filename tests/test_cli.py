"""`python -m ggns fit / test / predict` end to end (ggns.cli) on plate_tiny with T = 12 (the
`cli_data` fixture): real Lightning, real TensorBoard logs, checkpoints per metric family, resuming,
the refusals of mismatched checkpoints and arguments. Runs single-threaded (conftest `single_thread`)."""
from __future__ import annotations

import json
import math
import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch

from ggns.__main__ import main
from ggns.batch import TrajectoryBatch
from ggns.checkpoints import sha256
from ggns.config import CONF_DIR
from ggns.data.generate import split_path
from ggns.data.predictions import read_predictions
from ggns.data.schema import read_trajectories
from ggns.callbacks import RolloutEvaluation
from ggns.evaluation.evaluate import zero_motion_one_step_mse
from ggns.evaluation.schedules import EveryK, Never
from ggns.evaluation.selection import val_metric
from ggns.models.simulators import GGNS, MGN
from ggns.models.loading import load_simulator
from conftest import TINY12, make, normalizer_buffers

pytestmark = pytest.mark.usefixtures("single_thread")


# ---- 4. the command line end to end (data: the `cli_data` fixture, T = 12) ---------------------------------------
def run_cli(args: list[str]) -> None:
    """`python -m ggns <args>` in this process (sys.argv emptied: LightningCLI warns when it also has one)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, "argv", ["ggns"])
        main(args)


def cli_args(config: str, data_dir, logs, version: str, *extra) -> list[str]:
    return ["--config", str(CONF_DIR / "plate" / f"{config}.yaml"), "--data.dataset", str(data_dir / TINY12),
            "--data.data_dir", str(data_dir), "--data.batch_size", "8", "--data.generate_missing", "false",
            "--trainer.logger.init_args.save_dir", str(logs), "--trainer.logger.init_args.version", version,
            "--model.init_args.latent", "16", "--model.init_args.blocks", "2",
            "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
            "--trainer.limit_train_batches", "2", "--trainer.log_every_n_steps", "1", *extra]


def events(log_dir: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (event_file,) = log_dir.glob("events.out.tfevents.*")
    acc = EventAccumulator(str(event_file), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    return acc


def family_states(ckpt: dict) -> dict:
    """{monitored scalar: state} of the ModelCheckpoints that keep a best checkpoint per metric family."""
    return {v["monitor"]: v for k, v in ckpt["callbacks"].items() if k.startswith("ModelCheckpoint") and v["monitor"]}


@pytest.fixture(scope="module")
def ggns_fit(cli_data, tmp_path_factory):
    logs = tmp_path_factory.mktemp("logs")
    run_cli(["fit", *cli_args("ggns", cli_data, logs, "fit", "--trainer.max_epochs", "2",
                           "--trainer.check_val_every_n_epoch", "1", "--trainer.limit_val_batches", "1")])
    return logs


def test_a_fit_starts_from_a_trained_checkpoints_weights(ggns_fit, cli_data, tmp_path, capsys):
    """`InitialWeights`: one optimizer step from the trained fit's weights and statistics (each weight within
    Adam's first step, lr 1e-3, of its trained value; a fresh fit is nowhere near); a checkpoint of other
    parameter shapes or of another class is refused naming the difference, before any step."""
    import json

    trained = ggns_fit / "ggns" / "fit" / "checkpoints" / "last.ckpt"
    start = json.dumps({"class_path": "ggns.callbacks.InitialWeights", "init_args": {"checkpoint": str(trained)}})
    one_step = ("--trainer.max_steps", "1", "--trainer.limit_val_batches", "0", "--seed_everything", "1")  # another init
    run_cli(["fit", *cli_args("ggns", cli_data, tmp_path, "tuned", *one_step, f"--trainer.callbacks+={start}")])
    run_cli(["fit", *cli_args("ggns", cli_data, tmp_path, "fresh", *one_step)])
    source = torch.load(trained, weights_only=True)["state_dict"]
    tuned, fresh = (torch.load(tmp_path / "ggns" / v / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
                    for v in ("tuned", "fresh"))
    floats = [k for k, v in source.items() if v.is_floating_point() and "normalizer" not in k]
    assert floats and max(float((tuned[k] - source[k]).abs().max()) for k in floats) <= 1.5e-3
    assert max(float((fresh[k] - source[k]).abs().max()) for k in floats) > 0.05
    normalizers = [k for k in source if "normalizer" in k]
    assert normalizers and all(torch.equal(tuned[k], source[k]) for k in normalizers)
    for config, version, extra, message in (("ggns", "wider", ("--model.init_args.latent", "8"), "in the fit's model"),
                                            ("mgn", "other", (), "a GGNS, the fit's model is a MGN")):
        capsys.readouterr()
        with pytest.raises(SystemExit) as stop:
            run_cli(["fit", *cli_args(config, cli_data, tmp_path, version, *one_step, f"--trainer.callbacks+={start}",
                                      *extra)])
        last = capsys.readouterr().err.strip().splitlines()[-1]
        assert stop.value.code == 2 and last.startswith(f"error: initial weights {trained}") and message in last, last
        assert not (tmp_path / config / version / "checkpoints").exists()  # refused before any step


def test_cli_fit_logs_and_checkpoints(ggns_fit, cli_data):
    run = ggns_fit / "ggns" / "fit"
    last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    assert (run / "config.yaml").is_file()
    assert last["epoch"] == 1 and last["global_step"] == 4  # 2 epochs x limit_train_batches 2
    assert last["hyper_parameters"]["latent"] == 16 and last["hyper_parameters"]["blocks"] == 2

    acc = events(run)
    scalars = acc.Tags()["scalars"]
    for tag in ("train/loss", "train/loss_points", "train/loss_no_points", "val/loss", "val/rollout_mse",
                "val/rollout_mse_k1", "val/rollout_mse_never", "val/m10_mse", "val/one_step_mse",
                "val/one_step_mse_zero_motion", "val/one_step_ratio", "val/evaluation_seconds"):
        assert tag in scalars, tag
    values = {tag: [e.value for e in acc.Scalars(tag)] for tag in scalars if tag.startswith("val/")}
    for tag, v in values.items():  # one per epoch, no sanity check
        assert len(v) == 2 and all(math.isfinite(x) and x > 0 for x in v), tag
    assert values["val/rollout_mse"] == values["val/rollout_mse_k1"]  # the alias of GGNS's primary family

    # one best checkpoint per family, selected on the family's own scalar
    states = family_states(last)
    assert sorted(states) == ["val/m10_mse", "val/rollout_mse_k1", "val/rollout_mse_never"]
    for family in ("k1", "never", "m10"):
        (path,) = (run / "checkpoints").glob(f"best-{family}-step=*.ckpt")
        state = states[val_metric(family)]
        assert Path(state["best_model_path"]) == path
        assert math.isclose(float(state["best_model_score"]), min(values[val_metric(family)]), rel_tol=1e-6)
        assert torch.load(path, weights_only=False)["global_step"] == int(path.stem.split("=")[1])

    # the second validation's scalars are last.ckpt's metrics on the 2 validation trajectories
    model = GGNS.load_from_checkpoint(run / "checkpoints" / "last.ckpt")
    val = TrajectoryBatch.from_trajectories(read_trajectories(split_path(cli_data, "val")))
    direct = model.evaluate(val, [EveryK(1), Never()], iou=False, m_plus_10_stride=10)
    for name in ("one_step_mse", "rollout_mse_k1", "rollout_mse_never", "m10_mse"):
        assert math.isclose(values[f"val/{name}"][1], direct[name].mean().item(), rel_tol=1e-5), name
    zero = values["val/one_step_mse_zero_motion"]
    assert zero[0] == zero[1] and math.isclose(zero[0], zero_motion_one_step_mse(val).mean().item(), rel_tol=1e-6)
    for one, ratio in zip(values["val/one_step_mse"], values["val/one_step_ratio"]):
        assert math.isclose(ratio, one / zero[0], rel_tol=1e-5)
    assert "rollout/val_0" in acc.Tags()["images"]
    image = acc.Images("rollout/val_0")
    assert len(image) == 2 and image[0].width > 100 and image[0].height > 100


def test_cli_test_writes_paper_metrics_of_the_best_checkpoint(ggns_fit, cli_data, capsys):
    (best,) = (ggns_fit / "ggns" / "fit" / "checkpoints").glob("best-k1-step=*.ckpt")
    run_cli(["test", *cli_args("ggns", cli_data, ggns_fit, "test", "--ckpt_path", str(best))])
    run = ggns_fit / "ggns" / "test"
    summary = json.loads((run / "test_metrics.json").read_text())
    # the tested checkpoint is named: path, step, epoch and the scalar it was selected on
    saved = torch.load(best, weights_only=False)
    info = summary.pop("checkpoint")
    assert info["path"] == str(best) and (info["global_step"], info["epoch"]) == (saved["global_step"], saved["epoch"])
    assert info["selected_on"] == "val/rollout_mse_k1"
    assert info["score"] == float(family_states(saved)["val/rollout_mse_k1"]["best_model_score"])
    line = (f"tested checkpoint: {best.name} (global step {saved['global_step']}, epoch {saved['epoch']}; "
            f"best val/rollout_mse_k1 = ")
    assert line in capsys.readouterr().out and line in (run / "test_metrics.md").read_text()

    keys = ["one_step_mse", "m10_mse", "m10_pooled_mse"] + [f"rollout_{m}_{s}" for m in ("mse", "iou")
                                          for s in ("k1", "k2", "k5", "k10", "never")]
    assert sorted(summary) == sorted(keys)
    for name, s in summary.items():
        assert s["count"] == 2 and math.isfinite(s["mean"]) and math.isfinite(s["std"]), name
        if name.startswith("rollout_iou"):
            assert 0 < s["mean"] <= 1
    table = (run / "test_metrics.md").read_text()
    assert all(f"| {k} |" in table for k in keys)
    # the numbers are the best checkpoint's, on the whole 12-state test split
    model = GGNS.load_from_checkpoint(best)
    batch = TrajectoryBatch.from_trajectories(read_trajectories(split_path(cli_data, "test")))
    assert batch.num_steps == 12
    direct = model.evaluate(batch)
    for name, s in summary.items():
        assert math.isclose(direct[name].mean().item(), s["mean"], rel_tol=1e-5, abs_tol=1e-12), name


def test_rollout_evaluation_refuses_what_it_cannot_log(tiny_data_dir, tmp_path, capsys):
    """val/m10_mse on trajectories of T <= 10 states, or a primary family the model does not evaluate:
    an error at the start of fit naming the setting, not a ModelCheckpoint failing after training."""
    with pytest.raises(SystemExit) as exit_info:
        run_cli(["fit", *cli_args("mgn", tiny_data_dir, tmp_path, "fit", "--data.dataset", "plate_tiny")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "Traceback" not in err
    assert ("error: RolloutEvaluation: val/m10_mse needs val trajectories of more than 10 states, these have 8; "
            "set m_plus_10: false") in err
    assert not list(tmp_path.rglob("*.ckpt"))
    with pytest.raises(ValueError, match=r"primary 'k1' is not evaluated for MGN; choose one of \['never', 'm10'\]"):
        RolloutEvaluation(primary="k1").primary_family(make(MGN))
    assert RolloutEvaluation(primary="m10").primary_family(make(GGNS)) == "m10"
    assert [str(s) for s in RolloutEvaluation(schedules=["every:5", "every:1"]).schedules(make(GGNS))] == [
        "every:1", "never", "every:5"]
    assert [str(s) for s in RolloutEvaluation(schedules=["every:5"]).schedules(make(MGN))] == ["never"]


def test_cli_resume_continues_without_new_statistics(ggns_fit, cli_data):
    last_path = ggns_fit / "ggns" / "fit" / "checkpoints" / "last.ckpt"
    before = torch.load(last_path, weights_only=False)
    run_cli(["fit", *cli_args("ggns", cli_data, ggns_fit, "resume", "--trainer.max_epochs", "3",
                           "--trainer.check_val_every_n_epoch", "1", "--trainer.limit_val_batches", "1",
                           "--ckpt_path", str(last_path))])
    after = torch.load(ggns_fit / "ggns" / "resume" / "checkpoints" / "last.ckpt", weights_only=False)
    assert (before["epoch"], after["epoch"]) == (1, 2)
    assert after["global_step"] == before["global_step"] + 2  # one more epoch of 2 batches
    old, new = normalizer_buffers(before["state_dict"]), normalizer_buffers(after["state_dict"])
    assert old.keys() == new.keys() and old
    for name in old:
        assert torch.equal(new[name], old[name]), name
    changed = [k for k in before["state_dict"] if k not in old and not torch.equal(before["state_dict"][k],
                                                                                     after["state_dict"][k])]
    assert changed  # the weights did train
    assert len(events(ggns_fit / "ggns" / "resume").Scalars("val/rollout_mse")) == 1  # epoch 2 only


def test_last_checkpoint_is_the_newest_state_between_validations(cli_data, tmp_path):
    """Validation every 2nd epoch of 3: the best checkpoints are epoch 1's, while last.ckpt must hold
    the end of epoch 2, which no validation followed (a resume continues from there). Lightning's
    own save_last only copies a newly saved best checkpoint and would stop at epoch 1."""
    run_cli(["fit", *cli_args("mgn", cli_data, tmp_path, "fit", "--trainer.max_epochs", "3",
                           "--trainer.check_val_every_n_epoch", "2", "--trainer.limit_val_batches", "1")])
    checkpoints = tmp_path / "mgn" / "fit" / "checkpoints"
    assert sorted(p.name for p in checkpoints.glob("best-*.ckpt")) == ["best-m10-step=4.ckpt", "best-never-step=4.ckpt"]
    last = torch.load(checkpoints / "last.ckpt", weights_only=False)
    assert (last["epoch"], last["global_step"]) == (2, 6)  # 3 epochs x 2 batches


def test_cli_mgn_fit_and_test(cli_data, tmp_path, capsys):
    run_cli(["fit", *cli_args("mgn", cli_data, tmp_path, "fit", "--trainer.max_epochs", "1",
                           "--trainer.check_val_every_n_epoch", "1", "--trainer.limit_val_batches", "1")])
    run = tmp_path / "mgn" / "fit"
    (best,) = (run / "checkpoints").glob("best-never-step=2.ckpt")
    assert (run / "checkpoints" / "last.ckpt").is_file()
    acc = events(run)
    scalars = acc.Tags()["scalars"]
    assert "rollout/val_0" in acc.Tags()["images"]
    assert "train/loss_no_points" in scalars and "train/loss_points" not in scalars  # MGN never sees points
    assert "val/rollout_mse_k1" not in scalars and "val/m10_mse" in scalars
    assert [e.value for e in acc.Scalars("val/rollout_mse")] == [e.value for e in acc.Scalars("val/rollout_mse_never")]
    run_cli(["test", *cli_args("mgn", cli_data, tmp_path, "test", "--ckpt_path", str(best))])
    summary = json.loads((tmp_path / "mgn" / "test" / "test_metrics.json").read_text())
    assert summary.pop("checkpoint")["selected_on"] == "val/rollout_mse_never"
    assert sorted(summary) == ["m10_mse", "m10_pooled_mse", "one_step_mse", "rollout_iou_never", "rollout_mse_never"]
    assert all(math.isfinite(s["mean"]) and s["count"] == 2 for s in summary.values())
    # predict: the RolloutWriter of the config writes the rollouts of the test trajectories as a predictions
    # file, the format `python -m ggns rollout` writes (tests/test_own_data.py)
    run_cli(["predict", *cli_args("mgn", cli_data, tmp_path, "predict", "--ckpt_path", str(best))])
    predictions = read_predictions(tmp_path / "mgn" / "predict" / "predictions.h5")
    tests = read_trajectories(split_path(cli_data, "test"))
    assert (predictions.model_class, predictions.schedule, predictions.scene) == ("MGN", "never", "plate")
    assert predictions.checkpoint == str(best) and predictions.checkpoint_sha256 == sha256(best)
    assert predictions.input_file == str(split_path(cli_data, "test").resolve()) and predictions.input_indices == [0, 1]
    model = load_simulator(best, map_location="cpu")
    batch = TrajectoryBatch.from_trajectories(tests)
    direct = model.rollout(batch, "never")
    for b, (x, traj) in enumerate(zip(predictions.positions, predictions.inputs)):
        assert np.array_equal(traj.positions, tests[b].positions)
        assert np.array_equal(x, direct[:, batch.node_offsets[b]:batch.node_offsets[b + 1]].numpy())
    # never silently another model: a checkpoint of another class than the config's is refused, and so
    # is a model argument on the command line that the checkpoint would replace; nothing is logged
    for config, extra, message in (("ggns", [], "holds a ggns.models.simulators.MGN, but the config asks for "
                                                 "ggns.models.simulators.GGNS"),
                                   ("mgn", ["--model.init_args.latent", "32"], "latent: given 32, checkpoint 16"),
                                   ("mgn", ["--model.init_args.noise.std=0.5"], "noise: given")):
        with pytest.raises(SystemExit) as exit_info:
            run_cli(["test", *cli_args(config, cli_data, tmp_path, "refused", "--ckpt_path", str(best), *extra)])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err
        assert not list(tmp_path.glob("*/refused"))
    # evaluation settings may change at test time, and are applied (they are the `evaluation` group's; the old
    # model argument is refused naming its new place)
    with pytest.raises(SystemExit) as exit_info:
        run_cli(["test", *cli_args("mgn", cli_data, tmp_path, "old", "--ckpt_path", str(best),
                                   "--model.init_args.test_m_plus_10", "false")])
    assert "test_m_plus_10 is now --evaluation.m_plus_10" in capsys.readouterr().err
    run_cli(["test", *cli_args("mgn", cli_data, tmp_path, "no_m10", "--ckpt_path", str(best),
                               "--evaluation.m_plus_10", "false")])
    no_m10 = json.loads((tmp_path / "mgn" / "no_m10" / "test_metrics.json").read_text())
    assert "m10_mse" not in no_m10
    # a checkpoint of before the components (flat noise_std, lr, lr_decay_rate, type_partition, as the
    # shipped simulators are) and with the evaluation settings among its hyperparameters tests through the CLI
    # with its hyperparameters converted: the same numbers
    checkpoint = torch.load(best, weights_only=True)
    hparams = checkpoint["hyper_parameters"]
    noise, schedule = hparams.pop("noise"), hparams.pop("lr_schedule")
    hparams.update(noise_std=noise["std"], noise_field_std=noise["field_std"], lr=schedule["lr"],
                   lr_decay_rate=schedule["decay_rate"], type_partition=None, eval_schedules=["every:1", "never"],
                   test_m_plus_10=True, test_iou=True)
    torch.save(checkpoint, tmp_path / "flat.ckpt")
    run_cli(["test", *cli_args("mgn", cli_data, tmp_path, "flat", "--ckpt_path", str(tmp_path / "flat.ckpt"),
                               "--evaluation.m_plus_10", "false")])
    flat = json.loads((tmp_path / "mgn" / "flat" / "test_metrics.json").read_text())
    assert {k: v for k, v in flat.items() if k != "checkpoint"} == {k: v for k, v in no_m10.items() if k != "checkpoint"}
    # the run's saved config is the whole merged config (its `base` cleared) and parses to the same config
    saved = tmp_path / "mgn" / "fit" / "config.yaml"
    assert "base: null" in saved.read_text() and "RolloutEvaluation" in saved.read_text()


def test_configs_extend_their_base(tmp_path):
    """`base:` in a Lightning config: the shipped model configs extend conf/trainer_points.yaml or
    trainer_mesh.yaml (their _3d versions for the tissue and the cavity), which extend conf/trainer.yaml (its
    checkpoints first, then their `callbacks+:`); a config of one's own extends a file beside it or a shipped
    config by name; a missing base or a cycle is refused naming the config."""
    from ggns.cli import build_cli, config_bases

    assert config_bases(CONF_DIR / "plate" / "ggns.yaml") == [CONF_DIR / "trainer.yaml", CONF_DIR / "trainer_points.yaml"]
    for task, model, tail in (("plate", "mgn_shared", "trainer_mesh"), ("tissue", "ggns_lstm", "trainer_points_3d"),
                              ("cavity", "mgn_m", "trainer_mesh_3d")):
        assert config_bases(CONF_DIR / task / f"{model}.yaml") == [CONF_DIR / "trainer.yaml", CONF_DIR / f"{tail}.yaml"]
    cli = build_cli(["--config", "plate/ggns", "--trainer.logger", "false"], run=False)
    names = [type(c).__name__ + (f":{c.filename}" if type(c).__name__ == "ModelCheckpoint" else "")
             for c in cli.trainer.callbacks]
    for wanted in ("RolloutWriter", "TestEvaluation", "ModelCheckpoint:best-never-{step}", "ModelCheckpoint:last",
                   "RolloutEvaluation", "ModelCheckpoint:best-k1-{step}", "RandomState"):
        assert sum(n == wanted for n in names) == 1, (wanted, names)
    (tmp_path / "mine.yaml").write_text("base: plate/mgn\ntrainer:\n  max_epochs: 3\n")
    (tmp_path / "two.yaml").write_text("base: mine.yaml\ndata:\n  batch_size: 4\n")
    assert config_bases(tmp_path / "two.yaml") == [CONF_DIR / "trainer.yaml", CONF_DIR / "trainer_mesh.yaml",
                                                   CONF_DIR / "plate" / "mgn.yaml", tmp_path / "mine.yaml"]
    cli = build_cli(["--config", str(tmp_path / "two.yaml"), "--trainer.logger", "false"], run=False)
    assert (cli.trainer.max_epochs, cli.datamodule.batch_size, type(cli.model).__name__) == (3, 4, "MGN")
    (tmp_path / "gone.yaml").write_text("base: nowhere.yaml\n")
    with pytest.raises(ValueError, match="gone.yaml: its base 'nowhere.yaml' is neither"):
        config_bases(tmp_path / "gone.yaml")
    (tmp_path / "a.yaml").write_text("base: b.yaml\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\n")
    with pytest.raises(ValueError, match="cycle"):
        config_bases(tmp_path / "a.yaml")


def test_arguments_of_before_the_components_are_refused_with_their_new_names():
    from ggns.cli import build_cli

    with pytest.raises(ValueError, match=r"noise_std is now noise\.std; type_partition is now processor"):
        build_cli(["--config", "plate/ggns", "--model.init_args.noise_std", "0.02",
                   "--model.init_args.type_partition=true"], run=False)


def test_a_run_without_logger_writes_no_config_into_its_root(cli_data, tmp_path):
    """Lightning's SaveConfigCallback would drop config.yaml into default_root_dir (the working
    directory by default) when a run has no logger of its own."""
    run_cli(["fit", *cli_args("mgn", cli_data, tmp_path, "fit", "--trainer.logger", "false", "--trainer.max_epochs", "1",
                           "--trainer.limit_val_batches", "0", "--trainer.default_root_dir", str(tmp_path))])
    assert (tmp_path / "checkpoints" / "last.ckpt").is_file()  # the fit ran, in that root
    assert not (tmp_path / "config.yaml").exists()




class SigtermOnFirstBatch(pl.Callback):
    """Sends this process a SIGTERM after the first training batch, as a cluster's scheduler would."""

    def on_train_batch_end(self, trainer, *args) -> None:
        if trainer.global_step == 1:
            os.kill(os.getpid(), signal.SIGTERM)


def test_a_fit_stopped_by_sigterm_exits_nonzero(cli_data, tmp_path, capsys):
    """Lightning ends a SIGTERM'd fit with a bare SystemExit (status 0); the sweep and the learning
    command read the status to decide whether a fit finished, so the CLI must turn it into 143. The
    state at the stop is in last.ckpt (no epoch ended, so only the SIGTERM hook can have written it)."""
    with pytest.raises(SystemExit) as exit_info:
        run_cli(["fit", *cli_args("mgn", cli_data, tmp_path, "fit", "--trainer.max_epochs", "3",
                                  "--trainer.limit_val_batches", "0",
                                  f"--trainer.callbacks+={__name__}.SigtermOnFirstBatch")])
    assert exit_info.value.code == 143 and "stopped by SIGTERM" in capsys.readouterr().err
    last = torch.load(tmp_path / "mgn" / "fit" / "checkpoints" / "last.ckpt", weights_only=False)
    assert (last["epoch"], last["global_step"]) == (0, 1)  # stopped after batch 1 of 3 epochs x 2 batches


def _seeded_fit_and_test(cli_data, logs: Path, name: str, loader_workers: int) -> tuple[dict, dict]:
    """A fit (one epoch) and a test with seed 0: (last.ckpt's weights, the test metrics)."""
    run_cli(["fit", *cli_args("ggns", cli_data, logs, name, "--trainer.max_epochs", "1", "--seed_everything", "0",
                              "--trainer.limit_val_batches", "0", "--data.num_workers", str(loader_workers))])
    (last,) = (logs / "ggns" / name / "checkpoints").glob("last.ckpt")
    run_cli(["test", *cli_args("ggns", cli_data, logs, f"{name}_test", "--ckpt_path", str(last),
                               "--seed_everything", "0", "--data.num_workers", str(loader_workers))])
    metrics = json.loads((logs / "ggns" / f"{name}_test" / "test_metrics.json").read_text())
    metrics.pop("checkpoint")
    return torch.load(last, weights_only=True)["state_dict"], metrics


@pytest.fixture(scope="module")
def first_seeded_run(cli_data, tmp_path_factory):
    return _seeded_fit_and_test(cli_data, tmp_path_factory.mktemp("seeded"), "first", 0)


@pytest.mark.parametrize("workers", [0, 2])
def test_the_same_seed_gives_bit_identical_weights_and_test_metrics(cli_data, tmp_path, workers, first_seeded_run):
    """Determinism on the CPU (docs/robustness.md): a fit + test with seed 0 twice (the first shared by both cases),
    the second with `workers` data-loader processes, gives the same checkpoint weights and test metrics
    bit for bit (the sampler and the training noise run in the main process; workers only read windows)."""
    (first_weights, first_metrics) = first_seeded_run
    weights, metrics = _seeded_fit_and_test(cli_data, tmp_path, "again", workers)
    assert first_weights.keys() == weights.keys()
    assert all(torch.equal(first_weights[k], weights[k]) for k in weights)
    assert metrics == first_metrics and all(math.isfinite(m["mean"]) for m in metrics.values())


def test_a_callback_named_by_its_former_module_is_refused_naming_its_place(tmp_path):
    """Every callback lives in `ggns.callbacks`: a config or an argument that names one by the module it was in
    before (`ggns.evaluation.callbacks`, `ggns.models.speed`, ...) is refused with its path now."""
    from ggns.cli.lightning import build_cli

    (tmp_path / "old.yaml").write_text("base: plate/mgn\ntrainer:\n  callbacks+:\n"
                                       "    - class_path: ggns.evaluation.callbacks.RolloutPictures\n")
    with pytest.raises(ValueError, match=r"old.yaml: ggns.evaluation.callbacks.RolloutPictures is now "
                                         r"ggns.callbacks.RolloutPictures"):
        build_cli(["--config", str(tmp_path / "old.yaml"), "--trainer.logger", "false"], run=False)
    with pytest.raises(ValueError, match="the command line: ggns.models.speed.StaticRollouts is now ggns.callbacks"):
        build_cli(["--config", "plate/mgn", "--trainer.callbacks+=ggns.models.speed.StaticRollouts"], run=False)
    cli = build_cli(["--config", "plate/mgn", "--trainer.logger", "false",
                     "--trainer.callbacks+=ggns.callbacks.StaticRollouts"], run=False)
    assert sum(type(c).__name__ == "StaticRollouts" for c in cli.trainer.callbacks) == 1
