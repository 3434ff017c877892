"""Beyond one process (docs/robustness.md): Lightning DDP on the CPU (gloo, 2 real processes launched by
`python -m ggns fit --trainer.strategy ddp --trainer.devices 2`). Each rank trains on its own share of
every batch of windows (`EpochSampler`), the normalizer's statistics are merged across the ranks,
and the logged loss is the ranks' mean, so 2 processes with batches of B train as 1 process with
batches of 2B: the same windows per step, the same statistics, the same gradient (DDP averages the
ranks' gradients; plate meshes have the same node count, so the mean of the two halves' node means
is the mean over all nodes). MGN without training noise, so that no random draw differs between them."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torch.utils.data import TensorDataset

from ggns.config import CONF_DIR
from ggns.data.module import EpochSampler
from ggns.models.normalization import Normalizer, merge_across
from test_faults import _losses
from conftest import TINY12, launch_in_process

ROOT = Path(__file__).resolve().parents[1]
STEPS = 8  # 2 epochs of 4 batches


def _fit(data, logs, version: str, processes: int, batch_size: int,
         strategy: str = "ddp_find_unused_parameters_true", validate: bool = False,
         command: str = "fit", extra: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "ggns", command, "--config", str(CONF_DIR / "plate" / "mgn.yaml"),
               "--data.dataset", str(data / TINY12), "--data.data_dir", str(data),
               "--data.batch_size", str(batch_size), "--data.generate_missing", "false", "--seed_everything", "0",
               "--model.init_args.latent", "16", "--model.init_args.blocks", "2", "--model.init_args.noise.std", "0",
               "--model.init_args.statistics_batches", "4",
               "--trainer.logger.init_args.save_dir", str(logs), "--trainer.logger.init_args.version", version,
               "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
               "--trainer.max_epochs", "2", "--trainer.limit_train_batches", "4",
               "--trainer.limit_val_batches", "1" if validate else "0", "--trainer.check_val_every_n_epoch", "1",
               "--trainer.log_every_n_steps", "1", "--trainer.accelerator", "cpu",
               "--trainer.devices", str(processes), "--trainer.strategy", strategy, *extra]
    if processes == 1:  # the one-process reference in this test process (a start-up fewer); DDP's are real
        log = Path(logs) / f"{version}.log"
        Path(logs).mkdir(parents=True, exist_ok=True)
        with open(log, "w") as out:
            status = launch_in_process(command, out, {"OMP_NUM_THREADS": "1"})
        return subprocess.CompletedProcess(command, status, "", log.read_text())
    # SIGKILL on timeout: a rank stuck in a collective ignores the SIGTERM that subprocess.run would send
    with subprocess.Popen(command, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True, start_new_session=True) as proc:
        try:
            out, err = proc.communicate(timeout=300)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            raise
    return subprocess.CompletedProcess(command, proc.returncode, out, err)


def _scalars(run: Path, prefix: str) -> dict[str, dict[int, float]]:
    """{tag: {step: value}} of a run's TensorBoard scalars whose tag starts with `prefix`."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out: dict[str, dict[int, float]] = {}
    for path in sorted(run.glob("events.out.tfevents.*"), key=lambda p: p.stat().st_mtime):
        acc = EventAccumulator(str(path), size_guidance={"scalars": 0})
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            if tag.startswith(prefix):
                out.setdefault(tag, {}).update({e.step: e.value for e in acc.Scalars(tag)})
    return out


def _one_process_against_two(cli_data, tmp_path, **fit_options) -> tuple[Path, Path, dict]:
    """Fits of 1 process with batches of 8 and 2 DDP processes with 4 each: (run folder of one, of two, the
    two-process last.ckpt), after checking that both ran STEPS steps to the same weights (statistics, merged
    in float64, and weights differ by float summation order only: 1.5e-7 relative here)."""
    for version, processes, batch_size in (("one", 1, 8), ("two", 2, 4)):
        done = _fit(cli_data, tmp_path, version, processes=processes, batch_size=batch_size,
                    strategy="ddp_find_unused_parameters_true" if processes > 1 else "auto", **fit_options)
        assert done.returncode == 0, done.stderr[-3000:]
    one, two = tmp_path / "mgn" / "one", tmp_path / "mgn" / "two"
    first, second = (torch.load(run / "checkpoints" / "last.ckpt", weights_only=True) for run in (one, two))
    assert first["global_step"] == second["global_step"] == STEPS
    for name, value in first["state_dict"].items():
        torch.testing.assert_close(second["state_dict"][name], value, rtol=1e-4, atol=1e-6, msg=name)
    return one, two, second


def test_two_ddp_processes_train_as_one_with_twice_the_batch(cli_data, tmp_path):
    """... and validate as one: the rollout callback's metrics (each process rolls out one of the 2
    validation trajectories, sums and counts added across processes) and val/loss (synced) equal one
    process's, so every process selects the same best-* checkpoints."""
    one, two, second = _one_process_against_two(cli_data, tmp_path, validate=True)
    assert second["ggns_rng_states"]["cpu"].shape[0] == 2  # every rank's generator, for an exact resume
    losses, ddp = _losses(one), _losses(two)
    assert sorted(losses) == sorted(ddp) and len(losses) == STEPS
    for step in losses:
        assert ddp[step] == pytest.approx(losses[step], rel=1e-4), step
    val, val_ddp = _scalars(one, "val/"), _scalars(two, "val/")
    assert {"val/loss", "val/rollout_mse_never", "val/m10_mse", "val/one_step_ratio"} <= set(val)
    assert sorted(val) == sorted(val_ddp)
    for tag, values in val.items():
        assert sorted(values) == sorted(val_ddp[tag]) and len(values) == 2, tag  # after each of the 2 epochs
        if tag != "val/evaluation_seconds":
            for step, value in values.items():
                assert val_ddp[tag][step] == pytest.approx(value, rel=1e-4), (tag, step)
    assert sorted(p.name for p in (one / "checkpoints").iterdir()) == sorted(p.name for p in (two / "checkpoints").iterdir())


def test_streamed_two_ddp_processes_train_as_one_with_twice_the_batch(cli_data, tmp_path):
    """The same through the streaming reader (every split streamed: a budget of 1 byte) with 2 lanes
    in both runs: each process reads only its lane's trajectories, and the 2 processes' batches together are
    the one process's, so the weights and losses are again those of one process."""
    streamed = ("--data.memory_budget", "1", "--data.stream_lanes", "2")
    one, two, _ = _one_process_against_two(cli_data, tmp_path, extra=streamed)
    losses, ddp = _losses(one), _losses(two)
    assert sorted(losses) == sorted(ddp) and len(losses) == STEPS
    for step in losses:
        assert ddp[step] == pytest.approx(losses[step], rel=1e-4), step


def _refused(capsys, data, logs, version: str, command: str, strategy: str) -> str:
    """`python -m ggns <command>` with 2 CPU processes, in this process: the CLI refuses before
    Lightning's DDP launcher starts the second one. Returns the error line."""
    from test_cli import run_cli

    with pytest.raises(SystemExit) as exit_:
        run_cli([command, "--config", str(CONF_DIR / "plate" / "mgn.yaml"), "--data.dataset", str(data / TINY12),
                 "--data.data_dir", str(data), "--data.generate_missing", "false",
                 "--model.init_args.latent", "16", "--model.init_args.blocks", "2",
                 "--trainer.logger.init_args.save_dir", str(logs), "--trainer.logger.init_args.version", version,
                 "--trainer.enable_progress_bar", "false", "--trainer.accelerator", "cpu", "--trainer.devices", "2",
                 "--trainer.strategy", strategy])
    assert exit_.value.code == 2
    return capsys.readouterr().err


def test_test_and_predict_refuse_more_than_one_process(cli_data, tmp_path, capsys):
    """Lightning's distributed sampler would hand each process part of the split: the metrics and
    predictions written would be one process's part. Refused before a process starts, nothing written."""
    for command in ("test", "predict"):
        err = _refused(capsys, cli_data, tmp_path, command, command, "ddp_find_unused_parameters_true")
        assert f"error: {command} runs in one process" in err and "this run has 2 processes" in err, err
    assert not list((tmp_path / "mgn").rglob("test_metrics*")) and not list((tmp_path / "mgn").rglob("*.h5"))


def test_plain_ddp_is_refused_before_it_can_hang(cli_data, tmp_path, capsys):
    """Without find_unused_parameters, DDP waits forever for the gradient of an edge MLP that a batch
    without contact did not use (it hung on the plate): refused before the processes start, with the fix."""
    err = _refused(capsys, cli_data, tmp_path, "plain", "fit", "ddp")
    assert "use --trainer.strategy ddp_find_unused_parameters_true" in err, err
    assert not (tmp_path / "mgn" / "plain" / "checkpoints").exists()


def test_each_rank_refuses_too_when_the_trainer_is_built_in_python():
    """A Trainer built in Python reaches the model's setup on every rank without the CLI: the same refusals
    there (a real DDP Trainer of 2 CPU processes, constructed, not launched)."""
    from pytorch_lightning import Trainer

    from ggns.models.simulators import MGN

    model = MGN(latent=8, blocks=1)
    for strategy, stage, message in (("ddp", "fit", "find_unused_parameters"),
                                     ("ddp_find_unused_parameters_true", "test", "test runs in one process"),
                                     ("ddp_find_unused_parameters_true", "predict", "predict runs in one process")):
        model.trainer = Trainer(accelerator="cpu", devices=2, strategy=strategy, logger=False,
                                enable_checkpointing=False, enable_progress_bar=False)
        with pytest.raises(ValueError, match=message):
            model.setup(stage)
    model.setup("fit")  # with find_unused_parameters, a fit goes on


def test_the_ranks_share_the_epoch_and_a_resumed_epoch_skips_what_was_trained():
    data = TensorDataset(torch.arange(10))
    whole = list(EpochSampler(data, seed=3))
    ranks = [list(EpochSampler(data, seed=3, num_replicas=2, rank=r)) for r in range(2)]
    assert sorted(whole) == list(range(10)) and ranks[0] + ranks[1] != whole
    assert [i for pair in zip(*ranks) for i in pair] == whole  # rank r takes every 2nd, from r
    later = EpochSampler(data, seed=3)
    later.set_epoch(1)
    second_epoch = list(later)
    assert second_epoch != whole and sorted(second_epoch) == list(range(10))
    resumed = EpochSampler(data, seed=3)
    resumed.resume(batches_done=4 + 1, batch_size=3, batches_per_epoch=4)  # 5 batches of 3: 1 into epoch 1
    assert list(resumed) == second_epoch[3:]
    assert list(resumed) == second_epoch  # only the first iteration after a resume is cut


def test_normalizer_statistics_merged_across_processes_equal_one_pass_over_all():
    torch.manual_seed(0)
    parts = [torch.randn(n, 3, dtype=torch.float64) * 2 + 1 for n in (5, 0, 9)]
    whole = Normalizer(3)
    whole.update(torch.cat(parts))
    ranks = []
    for part in parts:
        normalizer = Normalizer(3)
        normalizer.update(part)
        ranks.append(normalizer)
    # what all_gather returns on every rank: each buffer of every rank, stacked
    stacked = {name: torch.stack([dict(r.named_buffers())[name] for r in ranks]) for name in ("count", "acc_mean", "acc_m2")}
    for normalizer in ranks:  # every rank merges the same parts in the same order: the same statistics
        merge_across([normalizer], lambda t, n=normalizer: stacked[_name(n, t)].clone())
        assert int(normalizer.count) == 14
        torch.testing.assert_close(normalizer.acc_mean, whole.acc_mean)
        torch.testing.assert_close(normalizer.acc_m2, whole.acc_m2)
        torch.testing.assert_close(normalizer.std, whole.std)


def _name(normalizer: Normalizer, tensor) -> str:
    """The buffer name of `tensor` in `normalizer`."""
    (name,) = [k for k, v in normalizer.named_buffers() if v is tensor]
    return name
