import math

import pytest
import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.objectives import GaussianNLLLoss


class FixedForecast(torch.nn.Module):
    """Writes a given forecast, to test the loss in isolation."""

    def __init__(self, loc, scale):
        super().__init__()
        self.loc, self.scale = loc, scale

    def forward(self, td):
        td.set(keys.FORECAST_LOC, self.loc)
        td.set(keys.FORECAST_SCALE, self.scale)
        return td


def batch(target):
    return TensorDict({keys.TARGET: target}, batch_size=[target.shape[0]])


def test_value_matches_torch_distributions():
    g = torch.Generator().manual_seed(0)
    target, loc = torch.randn(3, 4, 2, generator=g), torch.randn(3, 4, 2, generator=g)
    scale = torch.rand(3, 4, 2, generator=g) + 0.1
    out = GaussianNLLLoss(FixedForecast(loc, scale))(batch(target))
    expected = -torch.distributions.Normal(loc, scale).log_prob(target).sum((1, 2)).mean()
    torch.testing.assert_close(out["loss_nll"], expected)
    assert list(out.keys()) == ["loss_nll"]


def test_unit_gaussian_at_its_mean():
    zeros = torch.zeros(2, 5, 2)
    out = GaussianNLLLoss(FixedForecast(zeros, torch.ones_like(zeros)))(batch(zeros))
    torch.testing.assert_close(out["loss_nll"], torch.tensor(10 * 0.5 * math.log(2 * math.pi)))


@pytest.mark.parametrize("reduction,shape", [("none", (3,)), ("sum", ()), ("mean", ())])
def test_reductions(reduction, shape):
    target = torch.randn(3, 2, 2)
    loss = GaussianNLLLoss(
        FixedForecast(torch.zeros_like(target), torch.ones_like(target)), reduction=reduction
    )
    assert loss(batch(target))["loss_nll"].shape == shape


def test_set_keys_reads_renamed_entries():
    target = torch.randn(2, 3, 2)

    class Renamed(torch.nn.Module):
        def forward(self, td):
            td.set(("pred", "mu"), target)
            td.set(("pred", "sigma"), torch.ones_like(target))
            return td

    loss = GaussianNLLLoss(Renamed())
    loss.set_keys(target="future", forecast_loc=("pred", "mu"), forecast_scale=("pred", "sigma"))
    assert loss.in_keys == ["future", ("pred", "mu"), ("pred", "sigma")]
    out = loss(TensorDict({"future": target}, batch_size=[2]))
    torch.testing.assert_close(out["loss_nll"], torch.tensor(6 * 0.5 * math.log(2 * math.pi)))


def test_set_keys_none_restores_the_default():
    loss = GaussianNLLLoss(torch.nn.Identity())
    loss.set_keys(target="future")
    loss.set_keys(target=None)
    assert loss.tensor_keys.target == keys.TARGET


def test_missing_forecast_is_a_clear_error():
    loss = GaussianNLLLoss(torch.nn.Identity())
    with pytest.raises(KeyError, match="not found in the forecaster's outputs"):
        loss(batch(torch.zeros(2, 3, 2)))


def test_gradient_reaches_loc_and_scale():
    target = torch.randn(2, 3, 2)
    loc = torch.zeros_like(target, requires_grad=True)
    scale = torch.ones_like(target, requires_grad=True)
    GaussianNLLLoss(FixedForecast(loc, scale))(batch(target))["loss_nll"].backward()
    assert loc.grad is not None and scale.grad is not None and bool(loc.grad.abs().sum() > 0)
