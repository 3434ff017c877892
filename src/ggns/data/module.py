"""The LightningDataModule over a dataset's HDF5 splits (see `ggns.data.schema`).

Batches are `TrajectoryBatch`es (moved to the model's device by Lightning through their `.to`):
- train / val: windows of `train_window` + 1 consecutive states (window 1 = one next-step sample,
  the LSTM's windows of 5), drawn from every start step of every trajectory; the model turns
  them into graphs on its own device (imputation, noise), so the loaders do no graph work;
- test / predict: whole trajectories, `eval_batch_size` at a time, for batched rollouts.

The dataset is named by a data preset (conf/data/<name>.yaml or a YAML path): its `output`
directory holds <split>.h5. Missing splits are generated from the preset in `prepare_data`
when `generate_missing` is set; otherwise a FileNotFoundError says how to generate them. A
preset with an `importer` section (conf/data/reference_*.yaml) names imported data (the paper
authors' datasets, `ggns.data.reference`): it is never generated, and a missing split names the
import command. A split file generated with another scene, solver or sensor configuration than
the preset's is refused (`schema.read_trajectories`), never mixed in silently.
"""
from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl
from torch.utils.data import DataLoader, Dataset

from ..config import load_config
from ..batch import TrajectoryBatch
from .generate import generate, split_path
from .schema import read_trajectories
from ..trajectory import Trajectory

SPLITS = ("train", "val", "test")


class WindowDataset(Dataset):
    """Every window of `window` transitions (window + 1 states) of every trajectory."""

    def __init__(self, trajectories: list[Trajectory], window: int):
        if window < 1:
            raise ValueError(f"window must be >= 1 transitions, got {window}")
        unknown = [i for i, t in enumerate(trajectories) if not t.has_ground_truth]
        if unknown:
            raise ValueError(f"trajectories {unknown[:5]} have no ground truth (built without true_positions): "
                             f"nothing to train or validate on")
        short = [i for i, t in enumerate(trajectories) if t.num_steps < window + 1]
        if short:
            raise ValueError(f"trajectories {short[:5]} have fewer than window + 1 = {window + 1} states")
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
    """

    def __init__(self, dataset: str = "plate_small", data_dir: str | None = None, batch_size: int = 32,
                 train_window: int | None = None, eval_batch_size: int = 32, max_eval_trajectories: int | None = None,
                 num_workers: int = 0, generate_missing: bool = True):
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
        self.imported = "importer" in self.config  # the authors' data, imported: nothing to generate
        self._trajectories: dict[str, list[Trajectory]] = {}

    def path(self, split: str) -> Path:
        return split_path(self.data_dir, split)

    def prepare_data(self) -> None:
        missing = [s for s in SPLITS if not self.path(s).exists()]
        if missing and self.generate_missing and not self.imported:
            generate({**self.config, "output": str(self.data_dir)}, missing)

    def trajectories(self, split: str) -> list[Trajectory]:
        """The trajectories of a split (loaded once; val / test cut to max_eval_trajectories)."""
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
        if split not in self._trajectories:
            path = self.path(split)
            if not path.exists() and self.imported:
                raise FileNotFoundError(
                    f"{path}: split file missing; import it with `python -m ggns import-reference --config "
                    f"{self.hparams.dataset} --split {split} --output {self.data_dir} --input <the authors' pickle>`")
            if not path.exists():
                raise FileNotFoundError(
                    f"{path}: split file missing; generate it with `python -m ggns generate --config "
                    f"{self.hparams.dataset} --output {self.data_dir}` (or set data.generate_missing=true)")
            trajs = read_trajectories(path, expected_config=self.config)
            if split != "train" and self.max_eval_trajectories is not None:
                trajs = trajs[: self.max_eval_trajectories]
            if not trajs:
                raise ValueError(f"{path}: no trajectories")
            self._trajectories[split] = trajs
        return self._trajectories[split]

    @property
    def dim(self) -> int:
        return self.trajectories("train")[0].dim

    def _window(self) -> int:
        if self.train_window is not None:
            return self.train_window
        model = self.trainer.lightning_module if self.trainer is not None else None
        return getattr(model, "window", 1)

    def _loader(self, dataset: Dataset, batch_size: int, shuffle: bool) -> DataLoader:
        return DataLoader(dataset, batch_size=batch_size, shuffle=shuffle, collate_fn=collate,
                          num_workers=self.num_workers, persistent_workers=self.num_workers > 0)

    def train_dataloader(self) -> DataLoader:
        return self._loader(WindowDataset(self.trajectories("train"), self._window()), self.batch_size, True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(WindowDataset(self.trajectories("val"), self._window()), self.batch_size, False)

    def test_dataloader(self) -> DataLoader:
        return self._loader(TrajectoryDataset(self.trajectories("test")), self.eval_batch_size, False)

    def predict_dataloader(self) -> DataLoader:
        return self.test_dataloader()

    def eval_batch(self, split: str = "val", count: int | None = None, device=None) -> TrajectoryBatch:
        """The first `count` trajectories of a split as one batch (rollout callbacks)."""
        trajs = self.trajectories(split)
        return TrajectoryBatch.from_trajectories(trajs[:count] if count else trajs, device=device)

