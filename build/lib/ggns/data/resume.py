"""Resumable split generation: every finished trajectory is kept as its own file until the split
file is whole, so a generator killed at any point (SIGKILL, a dead node, a full disk) loses at most
the trajectories it was simulating, and running the same command again continues.

While `generate` makes `<output>/<split>.h5` it writes trajectory i, as soon as it is finished, to
`<output>/.<split>.h5.parts/<i:06d>.h5`: a complete one-trajectory split file, written atomically
(`AtomicHDF5`: a hidden temporary file renamed into place after its last write, so a part either
exists whole or not at all). When every trajectory of the split has its part, the parts are copied
in order into the split file (itself written atomically) and the directory is removed.

On a rerun, a part is reused only if it is readable, marked complete, holds one trajectory, was made
with the same scene, solver and sensor (the defining sections, `schema.config_differences`) and the
same trajectory seed as the job at its index; any other part is removed with a message, never read
as complete. Temporary files left by killed writers (`.<name>.partial-<pid>` of a process that no
longer runs) are removed too. Trajectory i's seed depends only on (seed, split, i), so the resumed
split's arrays are bit for bit those of an uninterrupted run (tests/test_faults.py). Code changes
between the killed run and the rerun are not detected: the parts record the configuration, not the
code (`generate --overwrite` after `rm -r <output>/.<split>.h5.parts` starts from scratch).
"""
from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

from .schema import DatasetError, SplitReader, SplitWriter, config_differences

_PARTIAL = re.compile(r"^\.(?P<name>.+)\.partial-(?P<pid>\d+)$")


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def remove_stale_partials(directory: str | os.PathLike, log=print) -> list[Path]:
    """Remove the temporary files (`.<name>.partial-<pid>`) in `directory` whose writer process no
    longer runs; returns their paths."""
    directory = Path(directory)
    removed = []
    if not directory.is_dir():
        return removed
    for entry in directory.iterdir():
        match = _PARTIAL.match(entry.name)
        if match and entry.is_file() and not _running(int(match["pid"])):
            entry.unlink(missing_ok=True)
            removed.append(entry)
    if removed:
        log(f"removed {len(removed)} temporary file(s) of killed writers in {directory}")
    return removed


class SplitParts:
    """The finished trajectories of one split being generated (module docstring)."""

    def __init__(self, path: str | os.PathLike, config: dict, *, scene: str, split: str, dim: int, log=print):
        self.path = Path(path)
        self.directory = self.path.with_name(f".{self.path.name}.parts")
        self.config, self.scene, self.split, self.dim, self.log = config, scene, split, dim, log

    def part(self, index: int) -> Path:
        return self.directory / f"{index:06d}.h5"

    def _usable(self, part: Path, seed: int) -> str | None:
        """None if `part` holds trajectory `seed` of this configuration, else why not."""
        try:
            with SplitReader(part) as reader:
                if len(reader) != 1:
                    return f"holds {len(reader)} trajectories"
                differ = config_differences(reader.generator_config, self.config)
                if differ:
                    return f"made with another configuration ({', '.join(differ[:4])})"
                if reader.scene != self.scene or reader.split != self.split:
                    return f"made for {reader.scene}/{reader.split}"
                stored = reader.seed(0)
        except (DatasetError, OSError, KeyError, ValueError) as error:
            return f"unreadable ({error})"
        return None if stored == seed else f"holds seed {stored}, the job has {seed}"

    def done(self, jobs: list[tuple[int, int]]) -> set[int]:
        """Indices of `jobs` (combination, seed) whose part can be reused; every other file in the
        directory (stale, foreign, beyond the jobs, a killed writer's temporary) is removed."""
        if not self.directory.is_dir():
            return set()
        remove_stale_partials(self.directory, self.log)
        done, dropped = set(), []
        for entry in sorted(self.directory.iterdir()):
            if _PARTIAL.match(entry.name):  # a live writer's temporary file: not ours to judge
                continue
            index = int(entry.stem) if entry.suffix == ".h5" and entry.stem.isdigit() else None
            why = "not a part" if index is None else (
                "beyond the split's size" if index >= len(jobs) else self._usable(entry, jobs[index][1]))
            if why is None:
                done.add(index)
            else:
                dropped.append(f"{entry.name}: {why}")
                if entry.is_dir():
                    shutil.rmtree(entry)
                else:
                    entry.unlink(missing_ok=True)
        if dropped:
            self.log(f"{self.directory}: removed {len(dropped)} unusable file(s): {'; '.join(dropped[:3])}"
                     f"{' ...' if len(dropped) > 3 else ''}")
        if done:
            self.log(f"{self.path}: resuming with {len(done)} of {len(jobs)} trajectories already made")
        return done

    def write(self, index: int, trajectory) -> None:
        """Keep trajectory `index` as its part (atomically)."""
        self.directory.mkdir(parents=True, exist_ok=True)
        with SplitWriter(self.part(index), scene=self.scene, split=self.split, dim=self.dim,
                         generator_config=self.config, overwrite=True) as writer:
            writer.append(trajectory)

    def merge(self, count: int, overwrite: bool = False, indices: list[int] | None = None) -> Path:
        """Write the split file from parts 0..count-1 (or those at `indices`, in that order: a shard)
        atomically, then remove the parts."""
        indices = list(range(count)) if indices is None else indices
        missing = [i for i in indices if not self.part(i).exists()]
        if missing:
            raise DatasetError(f"{self.directory}: parts {missing[:10]} are missing; cannot write {self.path}")
        with SplitWriter(self.path, scene=self.scene, split=self.split, dim=self.dim,
                         generator_config=self.config, overwrite=overwrite) as writer:
            for i in indices:
                with SplitReader(self.part(i)) as reader:
                    writer.append(reader[0])
        shutil.rmtree(self.directory)
        return self.path
