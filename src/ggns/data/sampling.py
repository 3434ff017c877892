"""The training windows' order (`EpochSampler`): seeded per epoch, shared among DDP processes, resumable
from a global step. The in-memory data module uses it as it is; the streamed reader's `BlockSampler`
(`ggns.data.stream`) orders the same windows in blocks that fit a memory budget on top of it."""
from __future__ import annotations

from collections.abc import Sequence

from torch.utils.data import Dataset, DistributedSampler


def check_windows(trajectories: Sequence, window: int) -> None:
    """Refuse what windows of `window` transitions cannot be cut from: a window below 1, trajectories without
    ground truth, trajectories of fewer than window + 1 states (each item has `has_ground_truth` and
    `num_steps`: a `Trajectory`, or a streamed split's `TrajectoryInfo`). ValueError naming the first ones."""
    if window < 1:
        raise ValueError(f"window must be >= 1 transitions, got {window}")
    unknown = [i for i, t in enumerate(trajectories) if not t.has_ground_truth]
    if unknown:
        raise ValueError(f"trajectories {unknown[:5]} have no ground truth (built without true_positions): "
                         f"nothing to train or validate on")
    short = [i for i, t in enumerate(trajectories) if t.num_steps < window + 1]
    if short:
        raise ValueError(f"trajectories {short[:5]} have fewer than window + 1 = {window + 1} states")


class EpochSampler(DistributedSampler):
    """The training windows' order: epoch e's permutation comes from torch.Generator seeded with
    seed + e (torch's DistributedSampler), of which rank r of `num_replicas` takes every
    num_replicas-th index (the epoch padded by repeating its first indices to a multiple of
    num_replicas, as DistributedSampler does). `start`: indices of this rank to skip in the next
    iteration only (a fit resumed in the middle of an epoch), `resume` sets it from a global step."""

    def __init__(self, dataset: Dataset, seed: int, num_replicas: int = 1, rank: int = 0):
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=True, seed=seed, drop_last=False)
        self.start = 0

    def resume(self, batches_done: int, batch_size: int, batches_per_epoch: int) -> None:
        """Position at the start of the batch after the first `batches_done` of the fit (all epochs)."""
        if batches_per_epoch < 1:
            return
        epoch, done = divmod(batches_done, batches_per_epoch)
        self.set_epoch(epoch)
        self.start = done * batch_size

    def epoch_indices(self) -> list[int]:
        """This rank's indices of the current epoch, all of them."""
        return list(super().__iter__())

    def __iter__(self):
        indices = self.epoch_indices()  # a list, or an array (BlockSampler's)
        start, self.start = self.start, 0
        return map(int, indices[start:])
