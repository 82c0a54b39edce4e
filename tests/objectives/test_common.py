import torch
from torch.distributions import Independent, Normal, kl_divergence

from mmf_rl.objectives import gaussian_kl, gaussian_kl_to_standard, gaussian_nll


def random_gaussian(shape, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(shape, generator=g), torch.rand(shape, generator=g) * 2 + 0.05


def test_gaussian_kl_matches_torch_distributions():
    (loc_p, scale_p), (loc_q, scale_q) = random_gaussian((16, 5, 2), 0), random_gaussian((16, 5, 2), 1)
    expected = kl_divergence(Independent(Normal(loc_p, scale_p), 2), Independent(Normal(loc_q, scale_q), 2))
    torch.testing.assert_close(gaussian_kl(loc_p, scale_p, loc_q, scale_q).sum((-2, -1)), expected)


def test_kl_to_standard_matches_torch_distributions():
    loc, scale = random_gaussian((16, 8), 2)
    expected = kl_divergence(Normal(loc, scale), Normal(torch.zeros(8), torch.ones(8)))
    torch.testing.assert_close(gaussian_kl_to_standard(loc, scale), expected)


def test_nll_matches_log_prob():
    loc, scale = random_gaussian((16, 5, 2), 3)
    value = torch.randn(16, 5, 2)
    torch.testing.assert_close(gaussian_nll(value, loc, scale), -Normal(loc, scale).log_prob(value))


def test_kl_of_identical_gaussians_is_zero():
    loc, scale = random_gaussian((4, 3), 4)
    assert torch.equal(gaussian_kl(loc, scale, loc, scale), torch.zeros(4, 3))
