"""Feature normalization: running mean and std of model inputs and targets.

Statistics are exact over everything passed to `update` (Chan's parallel merge of count,
mean and sum of squared deviations, accumulated in float64), so the order and size of the
batches do not matter. A `Normalizer` is filled by a statistics pass over the training data,
then frozen; all its state is in buffers, so it is saved and restored with the checkpoint.
"""
from __future__ import annotations

from typing import Mapping, Union

import torch
from torch import Tensor, nn
from torch_geometric.nn.module_dict import ModuleDict

NodeOrEdgeType = Union[str, tuple[str, str, str]]

# Well above the float32 resolution of task-space quantities (~1e-7 in [-1, 1]): a feature whose
# std in the training data is below it (float32 rounding noise around a constant, as the plate's
# collider velocity) counts as constant and is not an input (`Normalizer.varies`).
DEFAULT_STD_FLOOR = 1e-5


def type_key(t: NodeOrEdgeType) -> str:
    """Module-dict key of a node type ("mesh") or edge type ("collider__near__mesh")."""
    return t if isinstance(t, str) else "__".join(t)


class TypeModuleDict(ModuleDict):
    """PyG's ModuleDict keyed by node types ("mesh") and edge types (("collider", "near", "mesh")),
    storing each under its `type_key`, so state dicts keep the parameter names that checkpoints
    written before it have ("edge_mlp.collider__near__mesh.0.weight")."""

    @classmethod
    def to_internal_key(cls, key: NodeOrEdgeType) -> str:
        return type_key(key)

    @classmethod
    def to_external_key(cls, key: str) -> NodeOrEdgeType:
        parts = key.split("__")
        return tuple(parts) if len(parts) == 3 else key


class Normalizer(nn.Module):
    """Standardizes a feature vector of width `size`: forward(x) = (x - mean) / std.

    `std` is the population std floored at `std_floor`. A feature that did not vary in the
    training data (a one-hot column, a fixed-node flag, the plate's collider velocity, which is the
    same in every training trajectory) maps to 0 whatever its value: its value carries nothing the
    model could have learned, and standardized by the floor a change of it became an input of
    order 1e3-1e5 (a plate collider that stops after its push made every shipped plate simulator
    explode within one step; docs/results.md, "Stability at the extremes"). Before any `update`
    the normalizer is the identity (mean 0, std 1), e.g. for a type absent from training data.
    """

    def __init__(self, size: int, std_floor: float = DEFAULT_STD_FLOOR):
        super().__init__()
        self.size = size
        self.std_floor = std_floor
        self.register_buffer("count", torch.zeros((), dtype=torch.int64))
        self.register_buffer("acc_mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("acc_m2", torch.zeros(size, dtype=torch.float64))  # sum of squared deviations
        self.register_buffer("mean", torch.zeros(size))  # [F], derived from the accumulators
        self.register_buffer("std", torch.ones(size))  # [F]
        self.register_buffer("is_frozen", torch.zeros((), dtype=torch.bool))
        self._mask: Tensor | None = None  # varies() as 0/1, cached: `_varies_as`

    @property
    def cached_mask(self) -> Tensor | None:
        """The cached `varies()` mask (None until a forward made it): a recorded step reads it by address."""
        return self._mask

    @property
    def frozen(self) -> bool:
        return bool(self.is_frozen)

    def freeze(self) -> None:
        """End the statistics pass; later `update` calls are refused."""
        self.is_frozen.fill_(True)

    @torch.no_grad()
    def update(self, x: Tensor) -> None:
        """Adds the rows of x [M, F] to the statistics."""
        if self.frozen:
            raise RuntimeError("Normalizer is frozen; its statistics can no longer change")
        if x.ndim != 2 or x.shape[1] != self.size:
            raise ValueError(f"Normalizer of width {self.size} got shape {tuple(x.shape)}, expected [M, {self.size}]")
        if not torch.isfinite(x).all():
            raise ValueError("Normalizer.update got NaN or infinite values")
        n = x.shape[0]
        if n == 0:
            return
        x = x.to(torch.float64)
        batch_mean = x.mean(0)
        batch_m2 = (x - batch_mean).square().sum(0)
        count = self.count.to(torch.float64)
        total = count + n
        delta = batch_mean - self.acc_mean
        self.acc_mean.add_(delta * (n / total))
        self.acc_m2.add_(batch_m2 + delta.square() * (count * n / total))
        self.count.add_(n)
        self.mean.copy_(self.acc_mean)
        self.std.copy_((self.acc_m2 / total).sqrt().clamp(min=self.std_floor))
        self._mask = None

    @torch.no_grad()
    def merge(self, counts: Tensor, means: Tensor, m2s: Tensor) -> None:
        """Replace the statistics by the merge of several parts' (count [P], mean [P, F], sum of squared
        deviations [P, F]), in their order: the same result on every process that merges the same parts."""
        if self.frozen:
            raise RuntimeError("Normalizer is frozen; its statistics can no longer change")
        count, mean, m2 = 0.0, torch.zeros_like(self.acc_mean), torch.zeros_like(self.acc_m2)
        for n, part_mean, part_m2 in zip(counts.tolist(), means.to(mean), m2s.to(m2)):
            if n == 0:
                continue
            total = count + n
            delta = part_mean - mean
            mean = mean + delta * (n / total)
            m2 = m2 + part_m2 + delta.square() * (count * n / total)
            count = total
        self.count.fill_(int(count))
        self.acc_mean.copy_(mean)
        self.acc_m2.copy_(m2)
        self.mean.copy_(mean)
        self.std.copy_((m2 / max(count, 1.0)).sqrt().clamp(min=self.std_floor) if count else torch.ones_like(self.std))
        self._mask = None

    def varies(self) -> Tensor:
        """[F] bool: the features whose std over the statistics exceeds `std_floor` (all of them before
        any statistics)."""
        return (self.acc_m2 > self.std_floor ** 2 * self.count) | (self.count == 0)

    def forward(self, x: Tensor) -> Tensor:
        """[..., F] -> [..., F] standardized; a feature that did not vary in the statistics maps to 0
        whatever its value (class docstring)."""
        if x.shape[-1] != self.size:
            raise ValueError(f"Normalizer of width {self.size} got shape {tuple(x.shape)}")
        return (x - self.mean) / self.std * self._varies_as(x.dtype)

    def _varies_as(self, dtype: torch.dtype) -> Tensor:
        """`varies()` as 0/1 of `dtype`, kept until the statistics change: update, merge, load_state_dict
        and moves or casts (`_apply`) drop it, so a frozen normalizer does not recompute it in every step
        (not benchmarked by a repo command; a one-off timeit put it at about half a call's time)."""
        if self._mask is None or self._mask.dtype != dtype:
            self._mask = self.varies().to(dtype)
        return self._mask

    def _apply(self, fn, *args, **kwargs):
        self._mask = None
        return super()._apply(fn, *args, **kwargs)

    def _load_from_state_dict(self, *args, **kwargs) -> None:
        self._mask = None
        super()._load_from_state_dict(*args, **kwargs)

    def inverse(self, y: Tensor) -> Tensor:
        """[..., F] standardized -> [..., F] in data units."""
        return y * self.std + self.mean

    def extra_repr(self) -> str:
        return f"size={self.size}, std_floor={self.std_floor}"


def merge_across(normalizers: list[Normalizer], all_gather) -> None:
    """Merge each normalizer's statistics over the processes of a distributed run: `all_gather`
    (LightningModule.all_gather) stacks a tensor of every rank on a new first axis. Every rank must
    call it with the same normalizers in the same order."""
    for normalizer in normalizers:
        counts, means, m2s = (all_gather(t) for t in (normalizer.count, normalizer.acc_mean, normalizer.acc_m2))
        normalizer.merge(counts.reshape(-1), means.reshape(-1, normalizer.size), m2s.reshape(-1, normalizer.size))


class NormalizerDict(nn.Module):
    """One `Normalizer` per node or edge type, used with dicts {type: features [M, F]}."""

    def __init__(self, sizes: Mapping[NodeOrEdgeType, int], std_floor: float = DEFAULT_STD_FLOOR):
        super().__init__()
        self.normalizers = TypeModuleDict({t: Normalizer(f, std_floor) for t, f in sizes.items()})

    def __getitem__(self, t: NodeOrEdgeType) -> Normalizer:
        if t not in self.normalizers:
            raise KeyError(f"no normalizer for type {t!r}; known: {list(self.normalizers.keys())}")
        return self.normalizers[t]

    def update(self, features: Mapping[NodeOrEdgeType, Tensor]) -> None:
        for t, x in features.items():
            self[t].update(x)

    def freeze(self) -> None:
        for normalizer in self.normalizers.values():
            normalizer.freeze()

    def forward(self, features: Mapping[NodeOrEdgeType, Tensor]) -> dict[NodeOrEdgeType, Tensor]:
        return {t: self[t](x) for t, x in features.items()}
