"""Checks of the hot path that keep their verdict on the device until it is read (`DeferredCheck`).

A check in a training or rollout step (a non-finite loss, a node over the neighbour cap, a diverging
rollout) must not stop the device to ask the host whether it failed: on a GPU every such question is a
synchronization, and a step of them runs at the speed of the round trips, not of the arithmetic. A
`DeferredCheck` instead records, with tensor operations only, the first step at which its condition
held and what it saw there (`detail`, any tensor: a node index, a value, a mask); `failure()` reads it
back with one synchronization, at a logging interval, at the end of a rollout or before a checkpoint
is written, and the caller raises an error that names the step, the node and the quantity, as an
immediate check would have. On the CPU a read costs nothing, so callers may read every step there.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass

import torch
from torch import Tensor

from .phases import phase

_gpu_paths = False  # `gpu_code_paths`


def reads_cost(device: torch.device) -> bool:
    """Whether a read of a value on `device` costs a synchronization: on a GPU yes, on the CPU no (the hot
    path then takes cheaper CPU code), except inside `gpu_code_paths`."""
    return device.type != "cpu" or _gpu_paths


@contextlib.contextmanager
def gpu_code_paths():
    """Within the block the hot path takes its GPU code paths on the CPU too (the step profile's count of
    host reads and tests/test_hotpath.py use it to see what a GPU would synchronize on)."""
    global _gpu_paths
    previous, _gpu_paths = _gpu_paths, True
    try:
        yield
    finally:
        _gpu_paths = previous


@dataclass
class Failure:
    """What a `DeferredCheck` read back: the step of the first failure and its details (host values)."""

    step: int
    detail: list


class DeferredCheck:
    """The first failure of one condition over many steps, kept on the device.

    `record(failed, step, *detail)`: failed is a 0-d bool tensor (this step's verdict), step a host
    int, detail tensors of fixed shapes (the same at every call); only the first failing call's step
    and detail are kept. `failure()` returns them as a `Failure` (one device read) or None.
    """

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self._failed: Tensor | None = None
        self._step: Tensor | None = None
        self._detail: tuple[Tensor, ...] = ()
        self.pending = False  # host flag: something was recorded since the last read

    def record(self, failed: Tensor, step: int, *detail: Tensor) -> None:
        if not reads_cost(failed.device):  # a read costs nothing here: keep the first failure at once
            if self._failed is None or (not bool(self._failed) and bool(failed)):
                self._failed, self._step = failed.clone(), torch.tensor(step)
                self._detail = tuple(d.clone() for d in detail)
            self.pending = True
            return
        step_tensor = torch.full((), step, dtype=torch.long, device=failed.device)  # a fill, not a copy from the host
        if self._failed is None:
            self._failed, self._step, self._detail = failed.clone(), step_tensor, tuple(d.clone() for d in detail)
        else:
            keep = self._failed
            self._step = torch.where(keep, self._step, step_tensor)
            self._detail = tuple(torch.where(keep, old, new) for old, new in zip(self._detail, detail))
            self._failed = keep | failed
        self.pending = True

    def failure(self) -> Failure | None:
        """The first recorded failure, or None (reads the device once if anything was recorded)."""
        if self._failed is None:
            return None
        self.pending = False
        with phase("check reads"):
            if not bool(self._failed):
                return None
            return Failure(int(self._step), [d.tolist() for d in self._detail])
