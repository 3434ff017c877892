"""Named phases of the hot path (graph construction, encoder, processor, decoder, loss, checks), for
the step profile (`python -m ggns bench profile`): `with phase("processor"):` is a profiler range
(`torch.profiler.record_function`) while `recording` is on, and costs nothing otherwise."""
from __future__ import annotations

import contextlib

from torch.profiler import record_function

PHASES = ("graph construction", "encoder", "processor", "decoder", "loss", "backward", "optimizer", "checks")
_recording = False


@contextlib.contextmanager
def recording():
    """Within the block, `phase` opens profiler ranges named `ggns::<phase>`."""
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
    return record_function(f"ggns::{name}") if _recording else contextlib.nullcontext()
