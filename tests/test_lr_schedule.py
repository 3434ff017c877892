"""The simulators' learning-rate schedule (`ggns.models.lr_schedule`): the formula, argument
checks, the lr Lightning actually uses in a tiny real fit, and checkpoints written before the
schedule existed."""
from __future__ import annotations

import math

import pytest
import pytorch_lightning as pl
import torch

from ggns.data.module import SimulationDataModule
from ggns.models.lr_schedule import LRSchedule, scheduled_lr
from ggns.models.simulators import GGNS, MGN
from ggns.models.loading import load_simulator

SCHEDULE = dict(lr_schedule=LRSchedule(lr=1e-3, final=1e-4, decay_rate=0.5, decay_steps=2, warmup_steps=2))


def test_formula():
    assert scheduled_lr(0, 5e-4) == scheduled_lr(10**6, 5e-4) == 5e-4  # the default: constant
    assert math.isclose(scheduled_lr(2, 1e-3, 1e-4, 0.5, 2), 1e-4 + 9e-4 * 0.5)
    assert math.isclose(scheduled_lr(5, 1e-3, 1e-4, 0.5, 2), 1e-4 + 9e-4 * 0.5 ** 2.5)
    assert math.isclose(scheduled_lr(0, 1e-3, 1e-4, 0.5, 2, warmup_steps=4), 1e-3 / 4)  # warm-up: (step + 1) / 4
    assert math.isclose(scheduled_lr(10**4, 1e-3, 1e-4, 0.5, 2), 1e-4)  # floor


@pytest.mark.parametrize("kwargs, name", [
    (dict(lr=0.0), "lr_schedule.lr must"), (dict(final=1e-3), "lr_schedule.final"),
    (dict(final=-1e-6), "lr_schedule.final"), (dict(decay_rate=0.0), "lr_schedule.decay_rate"),
    (dict(decay_rate=1.5), "lr_schedule.decay_rate"), (dict(decay_steps=0), "lr_schedule.decay_steps"),
    (dict(decay_steps=2.5), "lr_schedule.decay_steps"), (dict(warmup_steps=-1), "lr_schedule.warmup_steps"),
    (dict(decay=0.5), r"lr_schedule: unknown fields \['decay'\]")])
def test_bad_schedule_arguments_raise_naming_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        MGN(latent=8, blocks=1, lr_schedule=kwargs)


class LrRecorder(pl.Callback):
    def __init__(self):
        self.lrs = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.lrs.append(trainer.optimizers[0].param_groups[0]["lr"])


def tiny_fit(tiny_data_dir, root, model, steps: int, ckpt_path=None) -> tuple[pl.Trainer, LrRecorder]:
    """`steps` optimizer steps on plate_tiny in one thread (threads slow such tiny graphs down)."""
    data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=4, generate_missing=False)
    recorder = LrRecorder()
    trainer = pl.Trainer(max_steps=steps, limit_val_batches=0, logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, default_root_dir=root,
                         accelerator="cpu", callbacks=[recorder])
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        trainer.fit(model, data, ckpt_path=ckpt_path)
    finally:
        torch.set_num_threads(threads)
    return trainer, recorder


def test_a_real_fit_follows_the_schedule_per_optimizer_step(tiny_data_dir, tmp_path):
    """8 optimizer steps over two epochs (6 batches of 4 windows each), then resumed for 3 more:
    the lr of step k is scheduled_lr(k), also across the resume."""
    torch.manual_seed(0)
    model = GGNS(latent=16, blocks=2, statistics_batches=1, **SCHEDULE)
    trainer, recorder = tiny_fit(tiny_data_dir, tmp_path, model, 8)
    expected = [scheduled_lr(k, 1e-3, 1e-4, 0.5, 2, 2) for k in range(11)]
    assert trainer.global_step == 8
    assert recorder.lrs == pytest.approx(expected[:8], rel=1e-12)
    assert trainer.optimizers[0].param_groups[0]["lr"] == pytest.approx(expected[8], rel=1e-12)
    trainer.save_checkpoint(tmp_path / "model.ckpt")
    _, resumed = tiny_fit(tiny_data_dir, tmp_path, GGNS(latent=16, blocks=2, **SCHEDULE), 11, tmp_path / "model.ckpt")
    assert resumed.lrs == pytest.approx(expected[8:], rel=1e-12)


def test_checkpoints_from_before_the_schedule_load_and_resume(tiny_data_dir, tmp_path):
    """A checkpoint without the schedule's hyperparameters and without scheduler state (as written
    before the schedule existed, with the flat `lr` and `noise_std` of before the components) loads with
    the constant paper lr, and a fit resumes from it."""
    torch.manual_seed(0)
    trainer, _ = tiny_fit(tiny_data_dir, tmp_path, MGN(latent=16, blocks=2, statistics_batches=1), 2)
    trainer.save_checkpoint(tmp_path / "new.ckpt")
    checkpoint = torch.load(tmp_path / "new.ckpt", weights_only=False)
    hparams = checkpoint["hyper_parameters"]
    del hparams["lr_schedule"], hparams["noise"]
    hparams.update(lr=5e-4, noise_std=0.01)
    checkpoint["lr_schedulers"] = []
    torch.save(checkpoint, tmp_path / "old.ckpt")
    model = load_simulator(tmp_path / "old.ckpt")
    assert model.lr_schedule == LRSchedule(lr=5e-4) and model.noise.std == 0.01
    trainer, recorder = tiny_fit(tiny_data_dir, tmp_path, MGN(latent=16, blocks=2), 4, tmp_path / "old.ckpt")
    assert trainer.global_step == 4 and recorder.lrs == [5e-4, 5e-4]


def test_cli_trainers_with_a_logger_log_the_lr(tmp_path):
    """`ggns.cli` adds one LearningRateMonitor to a trainer with a logger (the monitor raises without one)."""
    from pytorch_lightning.callbacks import LearningRateMonitor

    from ggns.cli import build_cli
    from ggns.config import CONF_DIR

    args = ["--config", str(CONF_DIR / "plate" / "mgn.yaml"), "--trainer.logger.init_args.save_dir", str(tmp_path)]
    for extra, count in (([], 1), (["--trainer.logger", "false"], 0)):
        trainer = build_cli(args + extra, run=False).trainer
        assert sum(isinstance(c, LearningRateMonitor) for c in trainer.callbacks) == count
