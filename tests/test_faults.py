"""Fault injection with real processes and real signals (issue 23): a generator killed with SIGKILL
at seeded points resumes, on the same command, to a split whose arrays are bit for bit those of an
uninterrupted run; what the killed run left (finished parts, a writer's temporary file, a part
truncated on disk) is reused when whole and removed otherwise, never read as complete."""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ggns.config import load_config
from ggns.data.generate import generate, regenerate, split_path
from ggns.data.resume import SplitParts, remove_stale_partials
from ggns.data.schema import DatasetError, SplitReader, content_hash

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
    proc = subprocess.Popen(_command(out), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
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
    rerun = subprocess.run(_command(out), cwd=ROOT, capture_output=True, text=True)
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
