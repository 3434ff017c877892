"""Reading a simulator from a checkpoint (`load_simulator`: any class of `simulators.py`, read as data
only) and converting the hyperparameters of checkpoints written by older versions (`upgrade_hparams`;
`RENAMED_ARGS` names where an old command-line argument went).
"""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING

from ..checkpoints import CheckpointError, check_format, read_checkpoint
from .training_noise import TrainingNoise

if TYPE_CHECKING:
    from .graph_simulator import GraphSimulator

# init arguments of the simulators before the parts: old flat name -> the part's field
_FLAT_NOISE = {"noise_std": "std", "noise_field_std": "field_std", "noise_field_wavelength": "field_wavelength",
               "noise_field_mixture": "field_mixture", "noise_field_points_only": "field_points_only",
               "noise_field_decay_steps": "field_decay_steps"}
_FLAT_LR = {"lr": "lr", "lr_final": "final", "lr_decay_rate": "decay_rate", "lr_decay_steps": "decay_steps",
            "lr_warmup_steps": "warmup_steps"}
# evaluation settings that were model arguments: old name -> the `TestEvaluation` callback's (the CLI's
# `evaluation:` group); checkpoints that hold them load without them
_EVALUATION = {"eval_schedules": "schedules", "test_m_plus_10": "m_plus_10", "test_iou": "iou"}
RENAMED_ARGS = {**{k: f"noise.{v}" for k, v in _FLAT_NOISE.items()},
                **{k: f"lr_schedule.{v}" for k, v in _FLAT_LR.items()},
                "type_partition": "processor (\"per_type\" for true, \"shared\" for false)",
                "estimator_noise_std": "estimator_noise (a TrainingNoise: {std: 0, field_std: <x>, field_mixture: true})",
                **{k: f"--evaluation.{v} (the TestEvaluation callback's, not a model argument)"
                   for k, v in _EVALUATION.items()}}


def upgrade_hparams(hparams: dict) -> dict:
    """A simulator's hyperparameters as this version's init arguments: the flat training-noise,
    lr-schedule and `type_partition` arguments of checkpoints written before the components
    (`TrainingNoise`, `LRSchedule`, `processor`) moved into them, and without the evaluation settings
    (`eval_schedules`, `test_m_plus_10`, `test_iou`) that were model arguments before they moved to the
    `TestEvaluation` callback; GGNSID's `estimator_noise_std` as the `estimator_noise` it was (a smooth
    field of that std, the model's wavelength, mixed scales); anything else is kept as it is."""
    out = {k: v for k, v in hparams.items()
           if k not in _FLAT_NOISE and k not in _FLAT_LR and k != "type_partition" and k not in _EVALUATION}
    noise = {field: hparams[old] for old, field in _FLAT_NOISE.items() if old in hparams}
    schedule = {field: hparams[old] for old, field in _FLAT_LR.items() if old in hparams}
    if noise:
        out["noise"] = {**dict(out.get("noise") or {}), **noise}
    if schedule:
        out["lr_schedule"] = {**dict(out.get("lr_schedule") or {}), **schedule}
    if hparams.get("type_partition") is not None:
        out["processor"] = "per_type" if hparams["type_partition"] else "shared"
    if "estimator_noise_std" in hparams:  # GGNSID's smooth field on the estimator's samples, now a TrainingNoise
        out.pop("estimator_noise_std")
        wavelength = dict(out.get("noise") or {}).get("field_wavelength", TrainingNoise.field_wavelength)
        out["estimator_noise"] = {"std": 0.0, "field_std": float(hparams["estimator_noise_std"]),
                                  "field_wavelength": wavelength, "field_mixture": True}
    return out


def load_simulator(path: str | Path, map_location=None) -> GraphSimulator:
    """Any of the simulators from a Lightning checkpoint written by this library, in eval mode, read
    as data only (`ggns.checkpoints`: a file that would run code is refused with CheckpointError, and
    so is one of another checkpoint format). The class is stored in the checkpoint
    ("simulator_class"); for checkpoints without it the class whose parameters load strictly is used
    (their parameter sets differ). Hyperparameters of checkpoints written before the components are
    converted (`upgrade_hparams`)."""
    checkpoint = read_checkpoint(path, map_location="cpu")
    check_format(checkpoint, path)
    if "hyper_parameters" not in checkpoint or "state_dict" not in checkpoint:
        raise CheckpointError(f"{path}: not a Lightning checkpoint of a ggns simulator")
    from .simulators import MODELS

    classes = {cls.__name__: cls for cls in MODELS.values()}
    name = checkpoint.get("simulator_class")
    if name is not None:
        if name not in classes:
            raise CheckpointError(f"{path}: unknown simulator_class {name!r} (known: {sorted(classes)})")
        return from_checkpoint(classes[name], checkpoint, map_location)
    errors = []
    for cls in classes.values():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return from_checkpoint(cls, checkpoint, map_location)
        except (RuntimeError, KeyError, TypeError, ValueError) as error:
            errors.append(f"{cls.__name__}: {str(error).splitlines()[0][:120]}")
    raise CheckpointError(f"{path}: no simulator class loads this checkpoint ({'; '.join(errors)})")


def from_checkpoint(cls: type[GraphSimulator], checkpoint: dict, map_location=None) -> GraphSimulator:
    """A `cls` built from a checkpoint dict's (upgraded) hyperparameters with its weights loaded strictly,
    in eval mode."""
    hparams = {k: v for k, v in upgrade_hparams(checkpoint["hyper_parameters"]).items() if not k.startswith("_")}
    if checkpoint.get("connectivity") is not None:  # the radii the checkpoint was trained with: no preset file needed
        hparams["connectivity"] = {"search": "auto", **checkpoint["connectivity"]}
    model = cls(**hparams)
    model.on_load_checkpoint(checkpoint)
    model.load_state_dict(checkpoint["state_dict"], strict=True)
    return (model.to(map_location) if map_location is not None else model).eval()
