"""Training noise on the input mesh positions: the `TrainingNoise` component of the simulators.

`std` is the paper's: independent Gaussian noise per node and coordinate. A network can undo
most of it from the mesh alone (the true deformation is smooth, the noise is not), so it barely
teaches a grounded model to use its point clouds. The errors a rollout accumulates are smooth
instead: a mesh-only model cannot see them, the point cloud can. `smooth_field` draws such an
error, a random low-frequency displacement field over the rest (mesh-space) positions, one draw
per graph of the batch, to be added with the same target correction as the paper's noise.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from ..config import dataclass_of


@dataclass(frozen=True)
class TrainingNoise:
    """What a simulator adds to the free input mesh positions of its training samples (the target is
    corrected by the same amount, so the model learns to return to the true next state).

    Args:
        std: std of the paper's per-node Gaussian noise (task-space units; paper: 0.01).
        field_std: std of a smooth random displacement field added on top (`smooth_field`; 0, the
            default, is the paper's noise alone).
        field_wavelength: the field's wavelength in rest-space units.
        field_mixture: each graph's field scaled by u ~ U(0, sqrt 3) (`smooth_field`'s mixture).
        field_points_only: the field only on samples that get their point clouds (a blind step cannot
            see a smooth offset, so there it only adds unlearnable noise to the target).
        field_decay_steps: the field's std falls linearly to 0 over this many optimizer steps (0: constant).
    """

    std: float = 0.01
    field_std: float = 0.0
    field_wavelength: float = 4.0
    field_mixture: bool = False
    field_points_only: bool = False
    field_decay_steps: int = 0

    def __post_init__(self):
        if not (self.std >= 0 and self.field_std >= 0 and self.field_wavelength > 0):
            raise ValueError(f"training noise: need std >= 0, field_std >= 0 and field_wavelength > 0; got "
                             f"{self.std}, {self.field_std}, {self.field_wavelength}")
        if isinstance(self.field_decay_steps, bool) or not isinstance(self.field_decay_steps, int) \
                or self.field_decay_steps < 0:
            raise ValueError(f"training noise: field_decay_steps must be an integer >= 0, got {self.field_decay_steps!r}")

    @classmethod
    def of(cls, value: TrainingNoise | Mapping | None) -> TrainingNoise:
        """The part from itself, a mapping of its fields or None (the defaults); an unknown field is
        refused by name (`ggns.config.dataclass_of`)."""
        return dataclass_of(cls, value, "training noise")

    def field_std_at(self, step: int) -> float:
        """The smooth field's std at optimizer step `step` (`field_decay_steps`)."""
        if not self.field_decay_steps:
            return self.field_std
        return self.field_std * max(0.0, 1.0 - step / self.field_decay_steps)

    def perturb(self, pos: Tensor, free: Tensor, rest: Tensor, owner: Tensor, num_graphs: int, step: int,
                with_points: Tensor | bool) -> Tensor:
        """Noisy input positions [N, d] from `pos` [N, d]: noise on the nodes where `free` [N, 1] is true.
        rest [N, d], owner [N] (the graph of each node), num_graphs: for the field; step: the optimizer
        step (its decay); with_points: [num_graphs] bool, which graphs get their point clouds (or one bool)."""
        if self.std > 0:
            pos = pos + torch.randn_like(pos) * self.std * free
        field_std = self.field_std_at(step)
        if field_std > 0:
            field = smooth_field(rest, owner, num_graphs, field_std, self.field_wavelength, mixture=self.field_mixture)
            if self.field_points_only:
                if isinstance(with_points, bool):
                    field = field * float(with_points)
                else:
                    field = field * with_points.to(pos.device, non_blocking=True)[owner, None]
            pos = pos + field * free
        return pos


def smooth_field(rest: Tensor, owner: Tensor, num_graphs: int, std: float, wavelength: float,
                 waves: int = 4, mixture: bool = False) -> Tensor:
    """A random smooth displacement per node [N, d]: for every graph and output coordinate, a sum of
    `waves` sinusoids of the rest position with wave vectors ~ N(0, (2 pi / wavelength)^2 I), random
    phases and N(0, 2 / waves) amplitudes, so that each coordinate has standard deviation `std`
    over draws. mixture: each graph's field is scaled by u ~ U(0, sqrt 3) (same overall std), so that
    small offsets, which a rollout with frequent point clouds mostly has, are drawn often.
    rest [N, d]; owner [N] long, the graph of each node."""
    if std < 0 or wavelength <= 0 or waves < 1:
        raise ValueError(f"need std >= 0, wavelength > 0 and waves >= 1; got {std}, {wavelength}, {waves}")
    n, d = rest.shape
    if owner.shape != (n,):
        raise ValueError(f"owner must have shape [{n}], got {list(owner.shape)}")
    options = dict(device=rest.device, dtype=rest.dtype)
    omega = torch.randn(num_graphs, d, waves, d, **options) * (2 * math.pi / wavelength)  # [G, out d, wave, in d]
    phase = torch.rand(num_graphs, d, waves, **options) * (2 * math.pi)
    amplitude = torch.randn(num_graphs, d, waves, **options) * math.sqrt(2.0 / waves)
    angle = torch.einsum("nowi,ni->now", omega[owner], rest) + phase[owner]  # [N, out d, wave]
    field = std * (amplitude[owner] * torch.sin(angle)).sum(dim=-1)
    if mixture:
        field = field * (torch.rand(num_graphs, **options) * math.sqrt(3.0))[owner, None]
    return field
