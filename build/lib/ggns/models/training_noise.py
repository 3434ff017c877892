"""Training noise on the input mesh positions.

`noise_std` is the paper's: independent Gaussian noise per node and coordinate. A network can undo
most of it from the mesh alone (the true deformation is smooth, the noise is not), so it barely
teaches a grounded model to use its point clouds. The errors a rollout accumulates are smooth
instead: a mesh-only model cannot see them, the point cloud can. `smooth_field` draws such an
error, a random low-frequency displacement field over the rest (mesh-space) positions, one draw
per graph of the batch, to be added with the same target correction as the paper's noise.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor


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
