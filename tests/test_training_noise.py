"""The smooth training-noise field: its standard deviation, its smoothness against the paper's
per-node noise, one independent draw per graph, and clear errors on bad arguments."""
import pytest
import torch

from ggns.models.training_noise import smooth_field


def test_field_has_the_asked_std_and_is_smooth():
    torch.manual_seed(0)
    rest = torch.rand(50, 2) * 2 - 1
    rest[1] = rest[0] + torch.tensor([0.05, 0.0])  # a neighbour 0.05 away (a fraction of a mesh edge)
    owner = torch.zeros(50, dtype=torch.long)
    draws = torch.stack([smooth_field(rest, owner, 1, 0.02, wavelength=4.0) for _ in range(4000)])
    assert draws.std().item() == pytest.approx(0.02, rel=0.05)
    # close nodes move together (per-node noise would give a correlation of 0)
    correlation = torch.corrcoef(torch.stack([draws[:, 0, 0], draws[:, 1, 0]]))[0, 1]
    assert correlation > 0.95
    # a shorter wavelength decorrelates them
    short = torch.stack([smooth_field(rest, owner, 1, 0.02, wavelength=0.05) for _ in range(4000)])
    assert torch.corrcoef(torch.stack([short[:, 0, 0], short[:, 1, 0]]))[0, 1] < 0.5


def test_one_draw_per_graph():
    torch.manual_seed(1)
    rest = torch.rand(10, 3)
    field = smooth_field(torch.cat([rest, rest]), torch.tensor([0] * 10 + [1] * 10), 2, 0.01, 4.0)
    assert field.shape == (20, 3) and torch.isfinite(field).all()
    assert not torch.allclose(field[:10], field[10:])  # same nodes, different graphs: different fields


@pytest.mark.parametrize("args", [dict(std=-1.0), dict(wavelength=0.0), dict(waves=0)])
def test_bad_arguments_are_refused(args):
    kwargs = dict(std=0.01, wavelength=4.0, waves=4) | args
    with pytest.raises(ValueError, match="std >= 0"):
        smooth_field(torch.zeros(3, 2), torch.zeros(3, dtype=torch.long), 1, **kwargs)


def test_owner_shape_is_checked():
    with pytest.raises(ValueError, match="owner must have shape"):
        smooth_field(torch.zeros(3, 2), torch.zeros(4, dtype=torch.long), 1, 0.01, 4.0)


def test_mixture_keeps_the_std_and_draws_small_fields_often():
    torch.manual_seed(2)
    rest = torch.rand(30, 2) * 2 - 1
    owner = torch.arange(2000).repeat_interleave(30)
    fixed = smooth_field(rest.repeat(2000, 1), owner, 2000, 0.02, 4.0).view(2000, 30, 2)
    mixed = smooth_field(rest.repeat(2000, 1), owner, 2000, 0.02, 4.0, mixture=True).view(2000, 30, 2)
    assert mixed.std().item() == pytest.approx(0.02, rel=0.08)
    per_graph = lambda f: f.square().mean(dim=(1, 2)).sqrt()
    # a fifth of the mixed graphs have an RMS offset below 0.2 std (about 1 in 70 without the mixture)
    assert (per_graph(mixed) < 0.004).float().mean() > 0.1 > (per_graph(fixed) < 0.004).float().mean()
