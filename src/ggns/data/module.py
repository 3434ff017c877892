"""The LightningDataModule over a dataset's HDF5 splits (see `ggns.data.schema`).

Batches are `TrajectoryBatch`es (moved to the model's device by Lightning through their `.to`):
- train / val: windows of `train_window` + 1 consecutive states (window 1 = one next-step sample,
  the LSTM's windows of 5), drawn from every start step of every trajectory; the model turns
  them into graphs on its own device (imputation, noise), so the loaders do no graph work;
- test / predict: whole trajectories, `eval_batch_size` at a time, for batched rollouts.

The training order is a function of the seed, the epoch and the process's rank alone (`EpochSampler`):
each of `world_size` processes (Lightning DDP) takes every world_size-th window of the epoch's
permutation, and a fit resumed from a checkpoint saved in the middle of an epoch (a cluster's
pre-emption, a SIGKILL) starts that epoch's permutation after the batches its `global_step` says
were already trained on, so the resumed fit sees the windows the uninterrupted one would have. No
loader draws from torch's global random generator (each has its own), so the training noise and the
imputation draws, which do, are the same sequence however the loaders are created (that generator's
state is kept in a fit's checkpoints by the `callbacks.RandomState` callback).

The dataset is named by a data preset (conf/data/<name>.yaml or a YAML path): its `output`
directory holds <split>.h5, or the split's shard files made by a job array (`generate --shard i/n`),
read in the split's order. Missing splits are generated from the preset in `prepare_data`
when `generate_missing` is set; otherwise a FileNotFoundError says how to generate them. A
preset with an `importer` section (conf/data/reference_*.yaml) names imported data (the paper
authors' datasets, `ggns.data.reference`): it is never generated, and a missing split names the
import command. A split file generated with another scene, solver or sensor configuration than
the preset's is refused (`schema.read_trajectories`), never mixed in silently.

With a `memory_budget`, a split whose files are larger than it is not loaded: it is read in pieces
(`ggns.data.stream`, docs/streaming.md), trajectories read when a window or a rollout needs them, the
training windows in a block order (`stream.BlockSampler`) that keeps the reads within the budget, as
seeded and resumable as `EpochSampler`'s.
"""
from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset

from ..config import load_config
from ..batch import TrajectoryBatch
from .generate import generate, read_shards, shard_files, split_path
from .sampling import EpochSampler, check_windows
from .schema import read_trajectories
from .stream import BlockSampler, StreamedSplit, StreamingWindowDataset, parse_bytes
from ..trajectory import Trajectory

from . import DEFAULT_DATASET, SPLITS  # noqa: F401 (SPLITS: importable from here as before)


class WindowDataset(Dataset):
    """Every window of `window` transitions (window + 1 states) of every trajectory."""

    def __init__(self, trajectories: list[Trajectory], window: int):
        check_windows(trajectories, window)
        self.trajectories = trajectories
        self.index = [(i, s) for i, t in enumerate(trajectories) for s in range(t.num_steps - window)]
        self.window = window

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> Trajectory:
        traj, start = self.index[i]
        return self.trajectories[traj].steps(start, start + self.window + 1)


class TrajectoryDataset(Dataset):
    """Whole trajectories."""

    def __init__(self, trajectories: list[Trajectory]):
        self.trajectories = trajectories

    def __len__(self) -> int:
        return len(self.trajectories)

    def __getitem__(self, i: int) -> Trajectory:
        return self.trajectories[i]


# Lightning warns that a fit resumed in the middle of an epoch is unreliable unless its loader has a
# state_dict; ours resumes from the trainer's global step instead (`EpochSampler.resume`), tested in
# tests/test_faults.py
warnings.filterwarnings("ignore", message="You're resuming from a checkpoint that ended before the epoch ended")


def collate(trajectories: list[Trajectory]) -> TrajectoryBatch:
    return TrajectoryBatch.from_trajectories(trajectories)


class SimulationDataModule(pl.LightningDataModule):
    """Args:
        dataset: data preset name (conf/data/<name>.yaml) or YAML path; its `output` is the data directory.
        data_dir: overrides the preset's output directory.
        batch_size: training windows per batch (paper: 32).
        train_window: transitions per train / val sample; None takes the model's `window` (LSTM 5, others 1).
        eval_batch_size: trajectories rolled out at once in test / predict.
        max_eval_trajectories: use only the first n val / test trajectories (None: all).
        num_workers: DataLoader worker processes.
        generate_missing: generate absent split files from the preset in `prepare_data`.
        seed: of the training order (`EpochSampler`); None takes the fit's `seed_everything` (Lightning's
            PL_GLOBAL_SEED), else 0.
        memory_budget: bytes, or a size such as "512MB" / "2GB" (`stream.parse_bytes`). A split whose files
            are larger is read in pieces (`ggns.data.stream`, docs/streaming.md): trajectories read when
            needed, at most this many bytes of them kept for training (shared among the `num_workers`
            workers), the training order in blocks that fit (`stream.BlockSampler`). None (default): every
            split is loaded into memory.
        stream_lanes: lanes of the streamed training order, a multiple of the processes (None: one per
            process, each reading only its own trajectories). Equal lanes give equal windows per step
            however many processes share them (1 process with batches of 2B trains as 2 with B).
    """

    def __init__(self, dataset: str = DEFAULT_DATASET, data_dir: str | None = None, batch_size: int = 32,
                 train_window: int | None = None, eval_batch_size: int = 32, max_eval_trajectories: int | None = None,
                 num_workers: int = 0, generate_missing: bool = True, seed: int | None = None,
                 memory_budget: str | int | None = None, stream_lanes: int | None = None):
        super().__init__()
        for name, value in (("batch_size", batch_size), ("eval_batch_size", eval_batch_size)):
            if value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        self.save_hyperparameters()
        self.config = load_config(dataset)
        self.data_dir = Path(data_dir if data_dir is not None else self.config["output"])
        self.batch_size, self.eval_batch_size = batch_size, eval_batch_size
        self.train_window, self.num_workers = train_window, num_workers
        self.max_eval_trajectories = max_eval_trajectories
        self.generate_missing = generate_missing
        self.seed = seed

        self.memory_budget = None if memory_budget is None else parse_bytes(memory_budget)
        self.stream_lanes = stream_lanes
        self.imported = "importer" in self.config  # the authors' data, imported: nothing to generate
        self._trajectories: dict[str, Sequence[Trajectory]] = {}

    def path(self, split: str) -> Path:
        return split_path(self.data_dir, split)

    def prepare_data(self) -> None:
        missing = [s for s in SPLITS if not self.path(s).exists() and not shard_files(self.data_dir, s)]
        if missing and self.generate_missing and not self.imported:
            generate({**self.config, "output": str(self.data_dir)}, missing)

    def files(self, split: str) -> tuple[list[Path], bool]:
        """The split's files and whether they are shards: [<split>.h5], or else its shard files made by a
        job array (`generate --shard i/n`, read as they are, in the split's order); a FileNotFoundError
        that names the command making the file when there are neither."""
        path = self.path(split)
        shards = shard_files(self.data_dir, split) if not path.exists() else []
        if shards:
            return shards, True
        if not path.exists() and self.imported:
            raise FileNotFoundError(
                f"{path}: split file missing; import it with `python -m ggns import-reference --config "
                f"{self.hparams.dataset} --split {split} --output {self.data_dir} --input <the authors' pickle>`")
        if not path.exists():
            raise FileNotFoundError(
                f"{path}: split file missing; generate it with `python -m ggns generate --config "
                f"{self.hparams.dataset} --output {self.data_dir}` (or set data.generate_missing=true)")
        return [path], False

    def streams(self, split: str) -> bool:
        """Whether the split is read in pieces: a memory_budget is set and the split's files are larger."""
        return self.memory_budget is not None and sum(f.stat().st_size for f in self.files(split)[0]) > self.memory_budget

    def trajectories(self, split: str) -> Sequence[Trajectory]:
        """The trajectories of a split (opened once; val / test cut to max_eval_trajectories): a list in
        memory, or a `stream.StreamedSplit` that reads each when indexed (`streams`)."""
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
        if split not in self._trajectories:
            files, shards = self.files(split)
            if self.streams(split):

                trajs = StreamedSplit(files, self.config, split, shards=shards)
            elif shards:
                trajs = read_shards(files, self.config, split)
            else:
                trajs = read_trajectories(files[0], expected_config=self.config)
            return self._keep(split, trajs, self.path(split))
        return self._trajectories[split]

    def _keep(self, split: str, trajs: Sequence[Trajectory], path: Path) -> Sequence[Trajectory]:
        if split != "train" and self.max_eval_trajectories is not None:
            trajs = trajs[: self.max_eval_trajectories]
        if not trajs:
            raise ValueError(f"{path}: no trajectories")
        self._trajectories[split] = trajs
        return trajs

    @property
    def dim(self) -> int:
        trajs = self.trajectories("train")
        return trajs[0].dim if isinstance(trajs, list) else trajs.dim  # a StreamedSplit reads no trajectory

    def _window(self) -> int:
        if self.train_window is not None:
            return self.train_window
        model = self.trainer.lightning_module if self.trainer is not None else None
        return getattr(model, "window", 1)

    def _seed(self) -> int:
        return self.seed if self.seed is not None else int(os.environ.get("PL_GLOBAL_SEED", 0))

    def _on_gpu(self) -> bool:
        device = getattr(getattr(self.trainer, "strategy", None), "root_device", None)
        return device is not None and device.type == "cuda"

    def _loader(self, dataset: Dataset, batch_size: int, sampler=None) -> DataLoader:
        # its own generator: creating an iterator (every epoch, every validation) draws the workers' base
        # seed from it, which would otherwise shift torch's global generator, i.e. the training noise.
        # On a GPU the batches are pinned, so that their move to the device does not wait (transfer_batch_to_device)
        return DataLoader(dataset, batch_size=batch_size, sampler=sampler, collate_fn=collate,
                          num_workers=self.num_workers, persistent_workers=self.num_workers > 0,
                          generator=torch.Generator().manual_seed(self._seed()), pin_memory=self._on_gpu())

    def transfer_batch_to_device(self, batch, device: torch.device, dataloader_idx: int):
        """TrajectoryBatches move without the host waiting for the copies on a GPU (`TrajectoryBatch.to`)."""
        if isinstance(batch, TrajectoryBatch):
            return batch.to(device, non_blocking=device.type == "cuda")
        return super().transfer_batch_to_device(batch, device, dataloader_idx)

    def reader_budget(self) -> int:
        """The training cache's bytes in each reading process (the budget shared among the workers; 0 without one)."""
        return (self.memory_budget or 0) // max(1, self.num_workers)

    def _windows(self, split: str, cache_bytes: int = 0) -> Dataset:
        trajs = self.trajectories(split)
        if isinstance(trajs, list):
            return WindowDataset(trajs, self._window())

        return StreamingWindowDataset(trajs, self._window(), cache_bytes)

    def train_dataloader(self) -> DataLoader:
        """Windows in `EpochSampler` order (`stream.BlockSampler` when streamed): this process's share (a
        rank of the trainer's world), from the batch after the trainer's `global_step` (a resumed fit)."""
        trainer = self.trainer
        world, rank = getattr(trainer, "world_size", 1), getattr(trainer, "global_rank", 0)
        dataset = self._windows("train", self.reader_budget())
        if isinstance(dataset, WindowDataset):
            sampler = EpochSampler(dataset, self._seed(), num_replicas=world, rank=rank)
        else:

            sampler = BlockSampler(dataset, self._seed(), self.reader_budget(), num_replicas=world, rank=rank,
                                   lanes=self.stream_lanes)
        if getattr(trainer, "global_step", 0) > 0:
            batches = math.ceil(len(sampler) / self.batch_size)
            limit = trainer.limit_train_batches
            batches = min(batches, limit) if isinstance(limit, int) else int(batches * limit)
            sampler.resume(trainer.global_step * trainer.accumulate_grad_batches, self.batch_size, batches)
        return self._loader(dataset, self.batch_size, sampler)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self._windows("val"), self.batch_size)  # streamed: in order, one trajectory kept

    def test_dataloader(self) -> DataLoader:
        return self._loader(TrajectoryDataset(self.trajectories("test")), self.eval_batch_size)

    def predict_dataloader(self) -> DataLoader:
        return self.test_dataloader()

    def eval_batch(self, split: str = "val", count: int | None = None, device=None, rank: int = 0,
                   world: int = 1) -> TrajectoryBatch | None:
        """The first `count` trajectories of a split as one batch (rollout callbacks); of those, process
        `rank` of `world` takes every `world`-th from its rank (None when that leaves it none)."""
        trajs = self.trajectories(split)
        mine = list((trajs[:count] if count else trajs)[rank::world])  # streamed: reads only these
        return TrajectoryBatch.from_trajectories(mine, device=device) if mine else None

