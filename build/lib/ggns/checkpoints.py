"""Checkpoint files are data, not code: the one place a `.ckpt` is read.

A Lightning checkpoint is a pickle, and a crafted pickle runs code when it is unpickled. Every
ggns loader reads checkpoints through `read_checkpoint`, i.e. `torch.load(weights_only=True)`:
torch's restricted unpickler, which rebuilds tensors, containers and plain Python values and
refuses any other global (a class, a function such as `os.system`) before calling it. Our
checkpoints need nothing else (their hyperparameters are plain values, the connectivity a plain
dict); a file that does is refused with `CheckpointError`, naming what it asked for.

`CHECKPOINT_FORMAT` is the version of what a simulator checkpoint holds and means (parameter
names and shapes, the normalizers' layout, the input features the graph builder makes): bump it
when a change makes older checkpoints load but compute something else. Checkpoints written before
the number existed are format 1 (the same layout).
"""
from __future__ import annotations

import hashlib
import pickle
from pathlib import Path

import torch

CHECKPOINT_FORMAT = 1
FORMAT_KEY = "ggns_format"


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: unreadable, not data-only, of another format, or not what it claims."""


def read_checkpoint(path: str | Path, map_location="cpu") -> dict:
    """The checkpoint at `path` as a dict, read without executing any code it may carry."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint file {path}")
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as error:
        reason = str(error).split("\n\n")[0].split("WeightsUnpickler error: ")[-1].strip()
        raise CheckpointError(f"{path} was refused: it holds more than tensors and plain values ({reason}); "
                              "ggns reads checkpoints as data and never runs code from them") from None
    except (RuntimeError, EOFError, OSError) as error:
        raise CheckpointError(f"{path} is not a readable checkpoint ({str(error).splitlines()[0]})") from None
    if not isinstance(checkpoint, dict):
        raise CheckpointError(f"{path} holds a {type(checkpoint).__name__}, not a checkpoint dict")
    return checkpoint


def check_format(checkpoint: dict, path: str | Path) -> None:
    """Refuse a checkpoint of another `CHECKPOINT_FORMAT` than this code's."""
    found = checkpoint.get(FORMAT_KEY, 1)
    if found != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is ggns checkpoint format {found!r}, this code reads format {CHECKPOINT_FORMAT}: "
                              "it was written by another version of ggns whose models compute something else; "
                              "use that version or retrain")


def sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
