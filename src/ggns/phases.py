"""Named phases of the hot path (graph construction, encoder, processor, decoder, loss, checks), for
the step profile (`python -m ggns bench profile`): `with phase("processor"):` is a profiler range
(`torch.profiler.record_function`) while `recording` is on, and costs nothing otherwise.
`host_side(tensor)` marks a tensor that lives on the host in every run (the imputation draws), so that
the profile's count of host reads does not take a read of it for a device synchronization."""
from __future__ import annotations

import contextlib
import weakref

from torch import Tensor
from torch.profiler import record_function

# "check reads": the reads of the deferred checks at their intervals (`ggns.checks`), apart from the step
PHASES = ("graph construction", "encoder", "processor", "decoder", "loss", "backward", "optimizer", "checks",
          "check reads")
_recording = False
_open: list[str] = []  # the phases open now, innermost last (while recording)
HOST_TENSORS: "weakref.WeakValueDictionary[int, Tensor]" = weakref.WeakValueDictionary()  # id -> tensor


@contextlib.contextmanager
def recording():
    """Within the block, `phase` opens profiler ranges named `ggns::<phase>` and `host_side` marks tensors."""
    global _recording
    previous, _recording = _recording, True
    try:
        yield
    finally:
        _recording = previous


def phase(name: str):
    """A profiler range `ggns::<name>` while `recording`, else a no-op context."""
    if name not in PHASES:
        raise ValueError(f"unknown phase {name!r}; known: {PHASES}")
    return _range(name) if _recording else contextlib.nullcontext()


@contextlib.contextmanager
def _range(name: str):
    _open.append(name)
    try:
        with record_function(f"ggns::{name}"):
            yield
    finally:
        _open.pop()


def current() -> str:
    """The innermost open phase ("other" outside any)."""
    return _open[-1] if _open else "other"


def host_side(tensor: Tensor) -> Tensor:
    """`tensor`, marked as a host tensor while `recording` (a read of it is no device synchronization)."""
    if _recording:
        HOST_TENSORS[id(tensor)] = tensor
    return tensor


def is_host_side(tensor: Tensor) -> bool:
    return HOST_TENSORS.get(id(tensor)) is tensor
