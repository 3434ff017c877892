"""Fault injection with real processes and real signals (docs/robustness.md; each `python -m ggns` command a process of
its own, forked from a server that imported ggns once, tests/forked.py): a generator killed with SIGKILL
at seeded points resumes, on the same command, to a split whose arrays are bit for bit those of an
uninterrupted run; what the killed run left (finished parts, a writer's temporary file, a part
truncated on disk) is reused when whole and removed otherwise, never read as complete."""
from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from ggns.config import load_config
from ggns.data.generate import generate, regenerate, split_path
from ggns.data.resume import SplitParts, remove_stale_partials
from ggns.data.schema import DatasetError, SplitReader, content_hash
import forked
from kill_points import HOOKS

ROOT = Path(__file__).resolve().parents[1]
COUNT = 6  # plate_tiny train trajectories of 8 steps: about 0.3 s each
# kill after this many finished trajectories (seeded; each point is one kill and one resume)
KILL_POINTS = sorted(random.Random(23).sample(range(2, COUNT), 2))


def _command(out: Path) -> list[str]:
    return [sys.executable, "-m", "ggns", "generate", "--config", "plate_tiny", "--output", str(out),
            "--split", "train", "--count", str(COUNT)]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("uninterrupted")
    config = load_config("plate_tiny", [f"output={out}", f"splits.train={COUNT}"])
    (path,) = generate(config, ["train"], progress=False)
    return content_hash(path)


def _parts(out: Path) -> list[Path]:
    directory = out / ".train.h5.parts"
    return sorted(directory.glob("[0-9]*.h5")) if directory.is_dir() else []


@pytest.mark.parametrize("after", KILL_POINTS)
def test_a_generator_killed_with_sigkill_resumes_to_identical_arrays(tmp_path, uninterrupted, after):
    out = tmp_path / "out"
    proc = forked.start(_command(out), tmp_path / "killed", cwd=ROOT)
    deadline = time.time() + 120
    while len(_parts(out)) < after and proc.poll() is None and time.time() < deadline:
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    kept = _parts(out)
    assert after <= len(kept) < COUNT, "the kill should land between two finished trajectories"
    assert not split_path(out, "train").exists()
    # what a crash can leave besides: a dead writer's temporary file and a part cut short on disk
    (out / ".train.h5.parts" / f".{COUNT - 1:06d}.h5.partial-{proc.pid}").write_bytes(b"half a trajectory")
    kept[0].write_bytes(kept[0].read_bytes()[:1000])
    rerun = forked.run(_command(out), tmp_path / "rerun", cwd=ROOT)
    assert rerun.returncode == 0, rerun.stderr
    assert f"resuming with {len(kept) - 1} of {COUNT}" in rerun.stdout + rerun.stderr
    assert "unreadable" in rerun.stdout + rerun.stderr  # the truncated part, made again
    assert content_hash(split_path(out, "train")) == uninterrupted
    assert not (out / ".train.h5.parts").exists() and not list(out.glob(".*partial*"))


def test_parts_of_another_configuration_or_seed_are_not_reused(tmp_path):
    config = load_config("plate_tiny", [f"output={tmp_path}", "splits.train=2"])
    other = load_config("plate_tiny", [f"output={tmp_path}", "splits.train=2", "scene.num_steps=5"])
    path = split_path(tmp_path, "train")
    jobs = [(0, 11), (1, 12)]

    SplitParts(path, other, scene="plate", split="train", dim=2).write(0, regenerate(other, 0, 11))  # another scene
    SplitParts(path, config, scene="plate", split="train", dim=2).write(1, regenerate(config, 1, 99))  # another seed
    messages = []
    fresh = SplitParts(path, config, scene="plate", split="train", dim=2, log=messages.append)
    assert fresh.done(jobs) == set()
    assert not _parts(tmp_path) and "another configuration" in messages[0] and "holds seed 99" in messages[0]
    with pytest.raises(DatasetError, match="parts \\[0, 1\\] are missing"):
        fresh.merge(2)
    assert not path.exists()


def test_a_live_writers_temporary_file_is_left_alone(tmp_path):
    live = tmp_path / f".train.h5.partial-{os.getpid()}"
    dead = tmp_path / ".train.h5.partial-999999999"
    live.write_bytes(b"x")
    dead.write_bytes(b"x")
    assert remove_stale_partials(tmp_path, log=lambda *_: None) == [dead]
    assert live.exists() and not dead.exists()
    with pytest.raises(DatasetError):
        SplitReader(live)


# ---- fit: SIGKILL at seeded points of a `python -m ggns fit` process (forked: tests/forked.py), then the same
# command resumes ---------------------------------------------------------------------------------------------
FIT_STEPS = 15  # 3 epochs x 5 batches (33 windows of cli_data in batches of 8: the last batch holds 1)
# (hook, global step) of each kill: seeded, one per hook; checkpoints every 3 steps, so most kills lose steps
FIT_KILLS = list(zip(HOOKS, random.Random(230).sample(range(1, FIT_STEPS - 1), len(HOOKS))))


def _fit_config(directory: Path) -> Path:
    """conf/plate/ggns.yaml with its last.ckpt written every 3 steps instead of at epoch ends, so that
    kills land in the middle of an epoch, between two checkpoints."""
    import yaml

    from ggns.config import CONF_DIR

    # plate/ggns.yaml extends trainer_points.yaml, which extends trainer.yaml: their callbacks in that order
    callbacks = (yaml.safe_load((CONF_DIR / "trainer.yaml").read_text())["trainer"]["callbacks"] +
                 yaml.safe_load((CONF_DIR / "trainer_points.yaml").read_text())["trainer"]["callbacks+"])
    assert yaml.safe_load((CONF_DIR / "plate" / "ggns.yaml").read_text())["base"] == "trainer_points"
    (last,) = [c for c in callbacks if c.get("init_args", {}).get("filename") == "last"]
    last["init_args"] = {"filename": "last", "every_n_train_steps": 3}
    path = directory / "ggns_last_every_3_steps.yaml"  # extends the shipped config, its callbacks replaced
    path.write_text(yaml.safe_dump({"base": "plate/ggns", "trainer": {"callbacks": callbacks}}))
    return path


def _fit_command(data, logs, version: str, resume: Path | None = None, extra: tuple[str, ...] = ()) -> list[str]:
    from conftest import TINY12

    return [sys.executable, "-m", "ggns", "fit", "--config", str(_fit_config(logs)),
            "--data.dataset", str(data / TINY12), "--data.data_dir", str(data), "--data.batch_size", "8",
            "--data.generate_missing", "false", "--seed_everything", "0",
            "--model.init_args.latent", "16", "--model.init_args.blocks", "2",
            "--trainer.logger.init_args.save_dir", str(logs), "--trainer.logger.init_args.version", version,
            "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
            "--trainer.max_epochs", "3", "--trainer.log_every_n_steps", "1",
            "--trainer.check_val_every_n_epoch", "1", "--trainer.limit_val_batches", "1",
            "--trainer.callbacks+=kill_points.KillAt", *extra,
            *(["--ckpt_path", str(resume)] if resume is not None else [])]


def _fit(command: list[str], output: Path, kill: tuple[str, int] | None = None,
         env: dict | None = None) -> subprocess.CompletedProcess:
    """`command` as a process of its own, forked from the preloaded server (tests/forked.py), its stdout and
    stderr kept in the fresh directory `output`; kill: GGNS_KILL_AT's (hook, step)."""
    env = {**os.environ, **(env or {}), "OMP_NUM_THREADS": "1"}
    env.pop("GGNS_KILL_AT", None)
    if kill is not None:
        env["GGNS_KILL_AT"] = f"{kill[0]}:{kill[1]}"
    return forked.run(command, output, env=env, cwd=ROOT, timeout=300)


def _losses(run: Path) -> dict[int, float]:
    """{step: train/loss} of a run's TensorBoard files, the newest file's value where two logged a step."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    losses = {}
    for path in sorted(run.glob("events.out.tfevents.*"), key=lambda p: p.stat().st_mtime):
        acc = EventAccumulator(str(path), size_guidance={"scalars": 0})
        acc.Reload()
        if "train/loss" in acc.Tags()["scalars"]:
            losses.update({e.step: e.value for e in acc.Scalars("train/loss")})
    return losses


@pytest.fixture(scope="module")
def uninterrupted_fit(cli_data, tmp_path_factory):
    """The fit uninterrupted, in this test process (a process start-up fewer; the kills are real processes)."""
    from conftest import launch_in_process

    logs = tmp_path_factory.mktemp("fit_logs")
    assert "GGNS_KILL_AT" not in os.environ
    with open(logs / "fit.log", "w") as out:
        status = launch_in_process(_fit_command(cli_data, logs, "whole"), out, {"OMP_NUM_THREADS": "1"})
    assert status == 0, (logs / "fit.log").read_text()[-3000:]
    run = logs / "ggns" / "whole"
    last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)
    assert last["global_step"] == FIT_STEPS
    return last["state_dict"], _losses(run)


def test_a_fit_killed_with_sigkill_at_each_hook_resumes_to_the_same_weights_and_losses(cli_data, tmp_path,
                                                                                       uninterrupted_fit):
    """Killed at each of FIT_KILLS in turn (a real SIGKILL at each hook, the steps in increasing order), the
    fit is rerun every time with --ckpt_path of the last.ckpt it left (a fresh start if none): each resumed
    fit trains on the windows, with the noise and imputation draws, the uninterrupted one did (the data
    order and torch's generator state resume from the checkpoint), so after the last rerun its losses and
    final weights equal the uninterrupted run's; we ask for float equality within 1e-6 relative (on the
    CPU they come out bit for bit). One chain of kills instead of one fit per kill: fewer process start-ups,
    and resuming a resumed fit is tested too."""
    weights, losses = uninterrupted_fit
    last = tmp_path / "ggns" / "run" / "checkpoints" / "last.ckpt"
    for kill in sorted(FIT_KILLS, key=lambda k: k[1]):
        resume = last if last.is_file() else None
        killed = _fit(_fit_command(cli_data, tmp_path, "run", resume=resume), tmp_path / f"killed_{kill[1]}", kill=kill)
        assert killed.returncode == -signal.SIGKILL, (kill, killed.stderr[-3000:])
        resumed_from = torch.load(last, weights_only=True)["global_step"] if last.is_file() else 0
        assert resumed_from <= kill[1], kill
    rerun = _fit(_fit_command(cli_data, tmp_path, "run", resume=last if last.is_file() else None), tmp_path / "rerun")
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    final = torch.load(last, weights_only=True)
    assert final["global_step"] == FIT_STEPS
    assert final["state_dict"].keys() == weights.keys()
    for name, value in weights.items():
        torch.testing.assert_close(final["state_dict"][name], value, rtol=1e-6, atol=1e-9, msg=name)
    again = _losses(tmp_path / "ggns" / "run")
    assert sorted(again) == sorted(losses) and len(losses) == FIT_STEPS
    for step in losses:
        assert again[step] == pytest.approx(losses[step], rel=1e-6), step


def test_a_fit_stopped_by_a_slurm_time_limit_requeues_and_resumes_from_the_hpc_checkpoint(cli_data, tmp_path,
                                                                                         uninterrupted_fit):
    """SLURM's environment (one task) and a stand-in `scontrol` on the PATH (there is no SLURM here: it
    records its arguments): SIGUSR1 at a seeded mid-epoch step, then SIGKILL (kill_points.REQUEUE).
    Lightning's handler saved hpc_ckpt_1.ckpt in --trainer.default_root_dir and asked to requeue this
    job; the requeued job, the same command without --ckpt_path, resumes from it (Lightning loads it
    on SLURM) and ends with the uninterrupted fit's weights and losses (but one, below): our generator
    states and data order ride in every checkpoint Lightning writes, the hpc one too."""
    from kill_points import REQUEUE

    weights, losses = uninterrupted_fit
    bin_dir, root = tmp_path / "bin", tmp_path / "root"
    bin_dir.mkdir()
    scontrol = bin_dir / "scontrol"
    scontrol.write_text(f'#!/bin/sh\necho "$@" >> {tmp_path / "scontrol.calls"}\n')
    scontrol.chmod(0o755)
    slurm = {"SLURM_JOB_ID": "4242", "SLURM_JOB_NAME": "ggns-fit", "SLURM_NTASKS": "1", "SLURM_NTASKS_PER_NODE": "1",
             "SLURM_NNODES": "1", "SLURM_PROCID": "0", "SLURM_LOCALID": "0", "SLURM_NODEID": "0",
             "SLURM_NODELIST": "localhost", "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    step = random.Random(2310).randrange(1, FIT_STEPS - 1)
    command = _fit_command(cli_data, tmp_path, "run", extra=("--trainer.default_root_dir", str(root)))
    killed = _fit(command, tmp_path / "killed", kill=(REQUEUE, step), env=slurm)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    assert (tmp_path / "scontrol.calls").read_text().split() == ["requeue", "4242"]
    hpc = torch.load(root / "hpc_ckpt_1.ckpt", weights_only=True)
    assert hpc["global_step"] == step and "ggns_rng_states" in hpc
    rerun = _fit(command, tmp_path / "requeued", env=slurm)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert "hpc_ckpt_1.ckpt" in rerun.stdout + rerun.stderr  # Lightning says what it restored
    final = torch.load(tmp_path / "ggns" / "run" / "checkpoints" / "last.ckpt", weights_only=True)
    assert final["global_step"] == FIT_STEPS
    for name, value in weights.items():
        torch.testing.assert_close(final["state_dict"][name], value, rtol=1e-6, atol=1e-9, msg=name)
    again = _losses(tmp_path / "ggns" / "run")
    # the loss of the batch the signal ended was computed but not yet handed to the logger (Lightning logs
    # after the batch-end callbacks), and the hpc checkpoint is after that batch: that one point is missing
    assert set(losses) - set(again) == {step - 1} and set(again) <= set(losses)
    for s in again:
        assert again[s] == pytest.approx(losses[s], rel=1e-6), s


# ---- sharded generation (a SLURM array): shards made apart, merged, equal to one machine's split ---------------
def test_shards_made_apart_merge_to_the_split_one_machine_makes(tmp_path, uninterrupted, capsys):
    from ggns.__main__ import main

    out = tmp_path / "out"
    common = ["--config", "plate_tiny", "--output", str(out), "--split", "train", "--count", str(COUNT)]
    for i in range(3):  # 6 trajectories in 4 shards: 2, 2, 1, 1
        main(["generate", *common, "--shard", f"{i}/4", "--workers", "1"])
    # the last as a SLURM array task would make it, through the job script
    task = subprocess.run(["bash", "scripts/slurm/generate_shards.sh", "plate_tiny", "4", "--output", str(out),
                           "--split", "train", "--count", str(COUNT)], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "SLURM_ARRAY_TASK_ID": "3", "SLURM_CPUS_PER_TASK": "1"})
    assert task.returncode == 0, task.stderr[-2000:]
    shards = [split_path(out, "train").with_name(f"train.shard-{i}-of-4.h5") for i in range(4)]
    assert [len(SplitReader(s)) for s in shards] == [2, 2, 1, 1] and not split_path(out, "train").exists()
    # the data module reads the shards as they are, in the split's order
    from ggns.config import CONF_DIR
    from ggns.data.module import SimulationDataModule

    config = tmp_path / "tiny6.yaml"
    config.write_text(f"base: {CONF_DIR / 'data' / 'plate_tiny.yaml'}\noutput: {out}\nsplits: {{train: {COUNT}}}\n")
    read = SimulationDataModule(str(config), generate_missing=False).trajectories("train")
    main(["generate", *common, "--merge-shards", "4"])
    assert content_hash(split_path(out, "train")) == uninterrupted
    merged = SplitReader(split_path(out, "train"))
    assert [t.seed for t in read] == [merged.seed(j) for j in range(COUNT)]
    assert all((a.positions == merged[j].positions).all() for j, a in enumerate(read))
    assert all(s.exists() for s in shards)  # kept
    # refused, with the output left as it was: an existing split, a missing shard, a shard of another seed
    capsys.readouterr()
    before = split_path(out, "train").read_bytes()
    with pytest.raises(SystemExit):
        main(["generate", *common, "--merge-shards", "4"])
    assert "already exists" in capsys.readouterr().err
    shards[3].rename(tmp_path / "away.h5")
    with pytest.raises(SystemExit):
        main(["generate", *common, "--merge-shards", "4", "--overwrite"])
    assert "train.shard-3-of-4.h5" in capsys.readouterr().err
    main(["generate", *common, "--shard", "3/4", "--workers", "1", "--seed", "7", "--output", str(tmp_path / "other")])
    (tmp_path / "other" / shards[3].name).rename(shards[3])
    with pytest.raises(SystemExit):
        main(["generate", *common, "--merge-shards", "4", "--overwrite"])
    assert "another configuration" in capsys.readouterr().err
    assert split_path(out, "train").read_bytes() == before
    for bad in ("4/4", "1", "a/b"):
        with pytest.raises(SystemExit):
            main(["generate", *common, "--shard", bad])
        assert "--shard" in capsys.readouterr().err


# ---- sweep: its whole process group SIGKILLed mid-fit, then mid-test; the same command finishes it -----------
def _sweep_file(tmp_path: Path, data: Path) -> Path:
    import yaml

    from conftest import TINY12
    from ggns.config import CONF_DIR

    tiny = {"data": {"dataset": str(data / TINY12), "data_dir": str(data), "generate_missing": False, "batch_size": 8,
                     "max_eval_trajectories": 2},
            "model": {"init_args": {"latent": 16, "blocks": 2}},
            "trainer": {"max_epochs": 2, "limit_train_batches": 2, "limit_val_batches": 1, "check_val_every_n_epoch": 2,
                        "enable_progress_bar": False, "enable_model_summary": False},
            "evaluation": {"m_plus_10": False}}  # one test part (never), one process fewer per test
    sweep = {"output": str(tmp_path / "sweep"), "seeds": [0], "parallel": 1, "overrides": tiny,
             "models": {"mgn": {"config": str(CONF_DIR / "plate" / "mgn.yaml")}}}
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "sweep.yaml"
    path.write_text(yaml.safe_dump(sweep))
    return path


def _sweep(path: Path, output: Path, kill_when=None) -> int:
    """`python -m ggns sweep --config path` in a session of its own, forked with its fits and tests
    (tests/forked.py), its stdout and stderr in `output`; SIGKILL to the whole group (the sweep and the fit
    or test it runs, as a cluster does to a job) once kill_when() holds. Returns the status."""
    child = forked.start([sys.executable, "-m", "ggns", "sweep", "--config", str(path)], output,
                         env={**os.environ, "OMP_NUM_THREADS": "1"}, cwd=ROOT, session=True)
    deadline = time.time() + 300
    while kill_when is not None and child.poll() is None and time.time() < deadline:
        if kill_when():
            os.killpg(child.pid, signal.SIGKILL)
            break
        time.sleep(0.05)
    return child.wait(timeout=300)


def test_a_sweep_killed_mid_fit_and_mid_test_finishes_with_the_uninterrupted_metrics(cli_data, tmp_path):
    """Kill points (events, not times): the fit's first last.ckpt (end of epoch 0 of 2), then the first
    test part's output directory. Each rerun of the same command resumes: the fit from last.ckpt, the
    tests from the parts that finished; the merged test metrics equal an uninterrupted sweep's."""
    from conftest import launch_in_process
    from ggns.sweeps.sweep import load_sweep, run_sweep

    # the uninterrupted reference: the same sweep, its fit and test in this process (two start-ups fewer)
    run_sweep(load_sweep(_sweep_file(tmp_path / "whole", cli_data)), log=lambda message: None, launch=launch_in_process)
    expected = json.loads((tmp_path / "whole" / "sweep" / "mgn" / "seed_0_test" / "test_metrics.json").read_text())

    path = _sweep_file(tmp_path / "killed", cli_data)
    run = tmp_path / "killed" / "sweep" / "mgn"
    last = run / "seed_0" / "checkpoints" / "last.ckpt"
    assert _sweep(path, tmp_path / "sweep_1", kill_when=last.is_file) == -signal.SIGKILL
    assert torch.load(last, weights_only=True)["global_step"] < 4  # killed before the fit's end
    tests = run / "seed_0_test"
    in_tests = lambda: tests.is_dir() and any(tests.iterdir())  # noqa: E731
    assert _sweep(path, tmp_path / "sweep_2", kill_when=in_tests) == -signal.SIGKILL
    assert not (tests / "test_metrics.json").exists()
    assert _sweep(path, tmp_path / "sweep_3") == 0, (tmp_path / "sweep_3" / "stderr").read_text()[-3000:]
    # the fit ran twice (killed, resumed); the rerun after the kill in the tests did not start it again
    assert (run / "seed_0" / "fit_ended").is_file() and len(list((run / "seed_0").glob("events.out.*"))) == 2
    metrics = json.loads((tests / "test_metrics.json").read_text())
    checkpoints, expected_checkpoints = metrics.pop("checkpoints"), expected.pop("checkpoints")
    assert {f: c["name"] for f, c in checkpoints.items()} == {f: c["name"] for f, c in expected_checkpoints.items()}
    assert sorted(metrics) == sorted(expected)
    for name in expected:
        assert metrics[name]["mean"] == pytest.approx(expected[name]["mean"], rel=1e-6), name
