"""Splits read in pieces, for datasets beyond one machine's memory (the data module's `memory_budget`).

A `StreamedSplit` is a split's file, or its shard files (`generate --shard i/n`) as they are, seen as a
sequence of trajectories that are read from HDF5 (h5py, `SplitReader`) only when indexed: one whole
trajectory per read, in whichever process indexes it (DataLoader workers open their own handles).
Opening it reads metadata only, one file at a time: the files' roots (a truncated or foreign file is refused,
naming it), their generator configurations (refused when not the preset's, as `read_trajectories` does),
every trajectory's state count, array sizes and stored seed (for shards refused when not the preset's, as
`read_shards` does).

Training windows (`StreamingWindowDataset`) are those of the in-memory `WindowDataset`, with the same
indices; each window is cut from its trajectory, which a `ResidentCache` keeps while it fits: least
recently used trajectories are dropped so that the arrays kept stay within `budget` bytes (at least the
trajectory in use is kept, however large). The windows' order (`BlockSampler`) makes that cache
enough: epoch e permutes the trajectories with the seed + e, deals them to `lanes` lanes in turn
(one lane per DDP process by default), cuts each lane's trajectories into blocks of at most `block_bytes`
(the cache's budget), and permutes the windows within each block. A process therefore reads each of its
trajectories once per epoch, a block at a time, and never those of another process's lane. The order is a
function of (seed, epoch, rank, world, the block size and the trajectories' sizes) alone, so a fit resumed
in the middle of an epoch continues it exactly (`EpochSampler.resume`).

Memory model per reading process (the main one, or each DataLoader worker): the training cache's budget
(the data module gives each of `num_workers` workers budget / num_workers, so that all together keep at
most the budget), plus the one validation trajectory being cut into windows, plus the batches in flight,
plus what grows with the split's length: about 30 bytes a trajectory of metadata and the epoch's order of
windows (an int64 array, `BlockSampler`). Of the files it keeps at most one open, with HDF5's metadata
cache capped (`METADATA_CACHE`): left to HDF5's default, an open file's cache kept about 50 KB for every
trajectory visited, so a split's peak grew with its length (docs/streaming.md).
Workers get batches in turn, so each of them reads the trajectories of the current block: with w workers,
each trajectory is read w times per epoch.
"""
from __future__ import annotations

import bisect
import copy
import re
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from ..trajectory import Trajectory
from .generate import check_shard_seed, check_shard_sizes
from .sampling import EpochSampler, check_windows
from .schema import SplitReader, TrajectoryInfo, check_config, trajectory_nbytes

# bytes of HDF5 metadata cache per open file of a streamed split (SplitReader.metadata_cache): HDF5's
# adaptive default kept about 50 KB per trajectory visited; a quarter MiB reads as fast (docs/streaming.md)
METADATA_CACHE = 2**18
_UNITS = {"": 1, "b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12,
          "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40}


def parse_bytes(value: str | int) -> int:
    """A memory size: bytes as an int, or a string such as "512MB", "2GB" (powers of 1000) or "4GiB"
    (powers of 1024). Raises ValueError for anything else, or a size below 1 byte."""
    if isinstance(value, bool):
        raise ValueError(f"memory size must be bytes or a string like '2GB', got {value!r}")
    if isinstance(value, int):
        size = value
    else:
        match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([kmgt]i?b|b)?\s*", str(value), flags=re.IGNORECASE)
        if not match:
            raise ValueError(f"memory size must be bytes or a string like '512MB', '2GB', '4GiB'; got {value!r}")
        size = int(float(match.group(1)) * _UNITS[(match.group(2) or "").lower()])
    if size < 1:
        raise ValueError(f"memory size must be at least 1 byte, got {value!r}")
    return size


class StreamedSplit(Sequence):
    """A split's trajectories, read from its file(s) when indexed (see the module docstring).

    Args:
        files: the split file, or its n shard files in shard order (`shard_files`).
        config: the data preset; files generated with another scene, solver or sensor are refused, and
            so are shard trajectories whose seed is not the preset's (None: no check).
        split: the split's name (the shards' seed check).
        shards: whether `files` are shards: trajectory j is trajectory j // n of shard j mod n.

    Opening it reads each file's metadata once, a file at a time (closed after it), and keeps of each
    trajectory only its `TrajectoryInfo` in arrays (about 30 bytes a trajectory, with its index). `split[i]` reads and
    returns trajectory i (validated, `SplitReader`), with at most one of the files open in this process
    (another is closed first) and HDF5's metadata cache of an open file capped at `METADATA_CACHE`
    bytes, so that what this process keeps of the files does not grow with the split's length. A slice
    is a StreamedSplit over those trajectories that reads nothing. `reads` counts the trajectories this
    process read through this split and its slices.
    """

    def __init__(self, files: list[Path], config: dict | None = None, split: str = "train", shards: bool = False):
        self.files = [Path(f) for f in files]
        if not self.files or (len(self.files) > 1 and not shards):
            raise ValueError(f"StreamedSplit needs one split file or its shard files, got {self.files}")
        # refuses a missing, truncated or foreign file by name
        self.readers = [SplitReader(f, metadata_cache=METADATA_CACHE) for f in self.files]
        sizes = [len(r) for r in self.readers]
        if shards:
            check_shard_sizes(sizes)
        total, n = sum(sizes), len(self.readers)
        self._steps, self._nbytes = np.empty(total, np.int32), np.empty(total, np.int64)
        self._truth, self._seeds = np.empty(total, np.bool_), np.empty(total, np.int64)
        for f, reader in enumerate(self.readers):
            try:
                if config is not None:
                    check_config(reader, config)
                for k in range(len(reader)):
                    j = k * n + f
                    info = reader.info(k)
                    if shards and config is not None:
                        check_shard_seed(self.files, config, split, j, info.seed)
                    self._steps[j], self._nbytes[j], self._truth[j], self._seeds[j] = info
            finally:
                reader.close()
        self._index = np.arange(total)
        self._reads = [0]  # shared with slices

    @property
    def reads(self) -> int:
        return self._reads[0]

    @property
    def dim(self) -> int:
        """The spatial dimension (a root attribute: nothing is read)."""
        return self.readers[0].dim

    def info(self, i: int) -> TrajectoryInfo:
        """Trajectory i's state count, size in memory, ground-truth flag and seed (read when the split was opened)."""
        j = self._index[i]
        return TrajectoryInfo(int(self._steps[j]), int(self._nbytes[j]), bool(self._truth[j]), int(self._seeds[j]))

    def __len__(self) -> int:
        return len(self._index)

    def __getitem__(self, i):
        if isinstance(i, slice):
            part = copy.copy(self)
            part._index = self._index[i]
            return part
        j = int(self._index[i])
        n = len(self.readers)
        reader = self.readers[j % n]
        for other in self.readers:
            if other is not reader and other.is_open:
                other.close()
        self._reads[0] += 1
        return reader[j // n]

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def __repr__(self) -> str:
        return f"StreamedSplit({len(self)} trajectories in {[f.name for f in self.files]})"


class ResidentCache:
    """Trajectories of a `StreamedSplit` kept in memory within `budget` bytes, least recently used out first.

    Args:
        split: where trajectories are read from.
        budget: bytes of trajectory arrays kept; at least the trajectory last asked for is kept.

    `reads` counts the trajectories read, `peak_count` / `peak_bytes` the most kept at once (this process).
    """

    def __init__(self, split: StreamedSplit, budget: int):
        self.split, self.budget = split, budget
        self._kept: OrderedDict[int, tuple[Trajectory, int]] = OrderedDict()
        self.resident = self.reads = self.peak_count = self.peak_bytes = 0

    def get(self, i: int) -> Trajectory:
        """Trajectory i, read if it is not kept; evicts the least recently used to stay within the budget."""
        if i in self._kept:
            self._kept.move_to_end(i)
            return self._kept[i][0]
        trajectory = self.split[i]
        size = trajectory_nbytes(trajectory)
        self.reads += 1
        while self._kept and self.resident + size > self.budget:
            _, (_, dropped) = self._kept.popitem(last=False)
            self.resident -= dropped
        self._kept[i] = (trajectory, size)
        self.resident += size
        self.peak_count, self.peak_bytes = max(self.peak_count, len(self._kept)), max(self.peak_bytes, self.resident)
        return trajectory

    def __len__(self) -> int:
        return len(self._kept)

    def __getstate__(self) -> dict:  # a DataLoader worker starts with an empty cache, not the parent's arrays
        return {**self.__dict__, "_kept": OrderedDict(), "resident": 0}


class StreamingWindowDataset(Dataset):
    """Every window of `window` transitions of every trajectory of a `StreamedSplit`, with the indices
    of the in-memory `WindowDataset` (trajectory by trajectory, start by start); trajectories are read
    through a `ResidentCache` of `cache_bytes`.

    Args:
        split: the trajectories.
        window: transitions per window (window + 1 states).
        cache_bytes: the cache's budget (0: only the trajectory in use, enough for windows in index order).
    """

    def __init__(self, split: StreamedSplit, window: int, cache_bytes: int):
        infos = [split.info(i) for i in range(len(split))]
        check_windows(infos, window)
        self.split, self.window = split, window
        self.nbytes = [t.nbytes for t in infos]
        self.offsets = [0]
        for t in infos:
            self.offsets.append(self.offsets[-1] + t.num_steps - window)
        self.cache = ResidentCache(split, cache_bytes)

    def __len__(self) -> int:
        return self.offsets[-1]

    def locate(self, i: int) -> tuple[int, int]:
        """(trajectory, start step) of window i."""
        if not 0 <= i < len(self):
            raise IndexError(f"window {i} out of range for {len(self)} windows")
        traj = bisect.bisect_right(self.offsets, i) - 1
        return traj, i - self.offsets[traj]

    def windows(self, traj: int) -> range:
        """The indices of trajectory traj's windows."""
        return range(self.offsets[traj], self.offsets[traj + 1])

    def __getitem__(self, i: int) -> Trajectory:
        traj, start = self.locate(i)
        return self.cache.get(traj).steps(start, start + self.window + 1)


class BlockSampler(EpochSampler):
    """The streamed training windows' order (see the module docstring): epoch e's trajectory permutation
    (torch.Generator seeded with seed + e) dealt to `lanes` lanes, each lane cut into blocks of at most
    `block_bytes`, windows permuted within each block. Position p of the epoch belongs to lane p mod lanes;
    process `rank` of `num_replicas` takes every num_replicas-th position from its rank (as EpochSampler),
    so it reads only the trajectories of its lanes. Every lane is padded to the same length (the most
    windows any lane could hold) by repeating its last block's windows, so each process has the same
    number of windows in every epoch. `resume` and `set_epoch` as EpochSampler's.

    Args:
        dataset: the windows.
        seed: of the order.
        block_bytes: most trajectory bytes in a block (the cache's budget; a block holds at least one).
        num_replicas: the DDP world size.
        rank: this process's rank.
        lanes: a multiple of num_replicas (None: num_replicas). With one lane an epoch holds every window
            exactly once, as EpochSampler's.
    """

    def __init__(self, dataset: StreamingWindowDataset, seed: int, block_bytes: int, num_replicas: int = 1,
                 rank: int = 0, lanes: int | None = None):
        super().__init__(dataset, seed, num_replicas=num_replicas, rank=rank)
        self.lanes = num_replicas if lanes is None else lanes
        if self.lanes < 1 or self.lanes % num_replicas:
            raise ValueError(f"lanes must be a positive multiple of the {num_replicas} processes, got {lanes}")
        trajectories = len(dataset.offsets) - 1
        if trajectories < self.lanes:
            raise ValueError(f"{trajectories} training trajectories cannot be shared among {self.lanes} processes "
                             f"(lanes): use at least one per process")
        self.block_bytes = block_bytes
        counts = sorted((len(dataset.windows(j)) for j in range(trajectories)), reverse=True)
        # the most windows a lane can be dealt: ceil(n / lanes) trajectories, the longest ones
        self.lane_length = sum(counts[: -(-trajectories // self.lanes)])
        self.total_size = self.lane_length * self.lanes
        self.num_samples = self.total_size // num_replicas

    def lane(self, trajectories: list[int], generator: torch.Generator) -> np.ndarray:
        """A lane's windows: its trajectories (in order) in blocks of at most block_bytes, each block's
        windows permuted; padded to lane_length with its last block's windows."""
        offsets, parts, block, size = self.dataset.offsets, [], [], 0
        for j in trajectories + [None]:
            if block and (j is None or size + self.dataset.nbytes[j] > self.block_bytes):
                ids = np.concatenate([np.arange(offsets[t], offsets[t + 1]) for t in block])
                parts.append(ids[torch.randperm(len(ids), generator=generator).numpy()])
                block, size = [], 0
            if j is not None:
                block.append(j)
                size += self.dataset.nbytes[j]
        windows = np.concatenate(parts) if parts else np.empty(0, np.int64)
        pad = self.lane_length - len(windows)
        return np.concatenate([windows, np.resize(parts[-1], pad)]) if pad > 0 else windows

    def epoch_indices(self) -> np.ndarray:
        """This rank's indices of the current epoch (an int64 array: 8 bytes a window)."""
        generator = torch.Generator()
        generator.manual_seed(self.seed + self.epoch)
        order = torch.randperm(len(self.dataset.offsets) - 1, generator=generator).tolist()
        lanes = np.stack([self.lane(order[k::self.lanes], generator) for k in range(self.lanes)])
        # position p of the epoch is window p // lanes of lane p mod lanes
        return lanes.T.reshape(-1)[self.rank:self.total_size:self.num_replicas]
