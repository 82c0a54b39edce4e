"""The output distribution families (mmf_rl.objectives.distributions): each one's log-density, central
interval, CRPS, KL, standard deviation and NLL temperature, the Gaussian's identical to the Gaussian
terms the losses and metrics used before the families existed, and the losses reading the model's."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy import integrate, stats
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.keys import ModalitySpec
from mmf_rl.objectives import (
    OUTPUT_DISTRIBUTIONS,
    ELBOLoss,
    GaussianNLLLoss,
    LaplaceOutput,
    MissingModalityLoss,
    OutputDistribution,
    gaussian_kl,
    gaussian_nll,
    output_distribution,
    output_distribution_of,
    register_output_distribution,
)

# Each family and the scipy distribution it is (location 0, scale 1).
FAMILIES = {
    "normal": ({}, stats.norm()),
    "laplace": ({}, stats.laplace()),
    "student_t": ({"output_df": 4.0}, stats.t(4.0)),
    "student_t df 2.5": ({"output_df": 2.5}, stats.t(2.5)),
}


def family(key: str):
    settings, _ = FAMILIES[key]
    return output_distribution(key.split(" ")[0], **settings)


def scipy_member(key: str, loc: float, scale: float):
    settings, _ = FAMILIES[key]
    name = key.split(" ")[0]
    if name == "normal":
        return stats.norm(loc, scale)
    if name == "laplace":
        return stats.laplace(loc, scale)
    return stats.t(settings["output_df"], loc, scale)


def tensors(*values):
    return [torch.tensor([v], dtype=torch.float64) for v in values]


def test_the_registry_holds_the_three_families():
    assert {"normal", "laplace", "student_t"} <= set(OUTPUT_DISTRIBUTIONS)


@pytest.mark.parametrize("key", sorted(FAMILIES))
def test_log_prob_is_the_density_of_its_scipy_twin(key):
    value = torch.linspace(-6, 6, 25, dtype=torch.float64)
    loc, scale = torch.tensor(0.3, dtype=torch.float64), torch.tensor(1.7, dtype=torch.float64)
    expected = scipy_member(key, 0.3, 1.7).logpdf(value.numpy())
    torch.testing.assert_close(family(key).log_prob(value, loc, scale), torch.from_numpy(expected))
    torch.testing.assert_close(family(key).nll(value, loc, scale), -torch.from_numpy(expected))


@pytest.mark.parametrize("key", sorted(FAMILIES))
@pytest.mark.parametrize("level", [0.5, 0.9])
def test_the_central_interval_holds_its_level(key, level):
    half = family(key).half_width(level)
    _, standard = FAMILIES[key]
    assert standard.cdf(half) - standard.cdf(-half) == pytest.approx(level, abs=1e-6)


@pytest.mark.parametrize("key", sorted(FAMILIES))
@pytest.mark.parametrize("value, loc, scale", [(0.3, 0.0, 1.0), (2.0, -1.0, 0.5), (-5.0, 0.2, 2.0)])
def test_the_crps_is_the_integral_of_the_squared_cdf_error(key, value, loc, scale):
    """``CRPS(F, y) = ∫ (F(x) - 1{x >= y})² dx``, integrated numerically on either side of ``y``."""
    member = scipy_member(key, loc, scale)
    below = integrate.quad(lambda x: member.cdf(x) ** 2, -np.inf, value, limit=200)[0]
    above = integrate.quad(lambda x: member.sf(x) ** 2, value, np.inf, limit=200)[0]
    crps = family(key).crps(*tensors(value, loc, scale))
    assert float(crps) == pytest.approx(below + above, rel=1e-6, abs=1e-9)


@pytest.mark.parametrize("key", ["laplace", "student_t", "student_t df 2.5"])
@pytest.mark.parametrize(
    "p, q",
    [((0.0, 1.0), (0.5, 1.0)), ((0.0, 1.0), (3.0, 1.0)), ((0.0, 2.0), (0.0, 1.0)), ((1.0, 1.0), (0, 0.2))],
)
def test_the_kl_is_the_integral_of_the_log_density_ratio(key, p, q):
    """Laplace's in closed form (torch), Student-t's by quadrature: within 0.2% of adaptive quadrature."""
    settings, _ = FAMILIES[key]

    def log_density(x, loc, scale):  # written out: scipy's frozen calls are slow, and underflow far out
        if key == "laplace":
            return -math.log(2 * scale) - abs(x - loc) / scale
        df = settings["output_df"]
        norm = (
            math.lgamma((df + 1) / 2) - math.lgamma(df / 2) - 0.5 * math.log(df * math.pi) - math.log(scale)
        )
        return norm - (df + 1) / 2 * math.log1p(((x - loc) / scale) ** 2 / df)

    def integrand(x):
        log_p = log_density(x, *p)
        return math.exp(log_p) * (log_p - log_density(x, *q))

    # Split at the locations (Laplace's kinks); Student-t's tails past 1e4 scales weigh < 1e-9.
    edges = [p[0] - 1e4 * p[1], *sorted({p[0], q[0]}), p[0] + 1e4 * p[1]]
    expected = sum(
        integrate.quad(integrand, a, b, limit=500)[0] for a, b in zip(edges, edges[1:], strict=False)
    )
    assert float(family(key).kl(*tensors(*p, *q))) == pytest.approx(expected, rel=2e-3)


@pytest.mark.parametrize("key", sorted(FAMILIES))
def test_the_kl_of_a_member_to_itself_is_zero_and_its_gradient_flows(key):
    loc, scale = torch.randn(4, 3), torch.rand(4, 3) + 0.5
    torch.testing.assert_close(family(key).kl(loc, scale, loc, scale), torch.zeros(4, 3), atol=1e-5, rtol=0)
    student_loc = torch.zeros(4, 3, requires_grad=True)
    family(key).kl(loc, scale, student_loc, torch.ones(4, 3)).sum().backward()
    assert student_loc.grad.abs().sum() > 0


@pytest.mark.parametrize("key", sorted(FAMILIES))
def test_stddev_is_the_distributions(key):
    scale = torch.tensor([0.5, 2.0])
    torch.testing.assert_close(
        family(key).stddev(scale), family(key).distribution(torch.zeros(2), scale).stddev, rtol=1e-6, atol=0
    )


@pytest.mark.parametrize("key", sorted(FAMILIES))
def test_the_temperature_minimises_the_nll_of_the_standardised_errors(key):
    """Closed form (normal, laplace) or 1-D minimisation (student_t): either way the NLL's minimiser,
    the one the base class's numerical minimisation finds."""
    z = torch.from_numpy(stats.t(3).rvs(4000, random_state=0)).abs()
    factor = family(key).temperature(z)

    def mean_nll(f):
        return float(family(key).nll(z, torch.zeros(()), torch.tensor(f, dtype=torch.float64)).mean())

    assert mean_nll(factor) < min(mean_nll(factor * 0.99), mean_nll(factor * 1.01))
    generic = OutputDistribution.temperature(family(key), z)  # the numerical minimisation
    assert factor == pytest.approx(generic, rel=1e-5)


def test_the_normal_family_is_the_gaussian_terms_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    value, loc = torch.randn(3, 5, 2, generator=g), torch.randn(3, 5, 2, generator=g)
    scale, other = torch.rand(3, 5, 2, generator=g) + 0.1, torch.rand(3, 5, 2, generator=g) + 0.1
    normal = output_distribution("normal")
    assert torch.equal(normal.nll(value, loc, scale), gaussian_nll(value, loc, scale))
    assert torch.equal(normal.kl(loc, scale, value, other), gaussian_kl(loc, scale, value, other))
    assert normal.stddev(scale) is scale
    # The CRPS and half width as mmf_rl.eval.metrics wrote them before the families existed.
    z = (value - loc) / scale
    standard = torch.distributions.Normal(0.0, 1.0)
    before = scale * (z * (2 * standard.cdf(z) - 1) + 2 * standard.log_prob(z).exp() - 1 / math.sqrt(math.pi))
    assert torch.equal(normal.crps(value, loc, scale), before)
    for level in (0.5, 0.9):
        assert normal.half_width(level) == standard.icdf(torch.tensor(0.5 + level / 2)).item()
    assert normal.temperature(z.abs()) == math.sqrt(float(z.abs().square().mean()))


def test_a_model_or_config_without_the_option_reads_as_normal():
    assert output_distribution_of(torch.nn.Linear(2, 2)).name == "normal"
    assert output_distribution_of(SimpleNamespace(config=SimpleNamespace(min_scale=1e-3))).name == "normal"
    chosen = SimpleNamespace(output_distribution="student_t", output_df=3.0)
    assert output_distribution_of(SimpleNamespace(config=chosen)).describe() == "student_t (df 3)"


@pytest.mark.parametrize(
    "name, settings, message",
    [
        (
            "cauchy",
            {},
            r"unknown output distribution 'cauchy'; expected one of \['laplace', 'normal', 'student_t'",
        ),
        ("student_t", {"output_df": 2.0}, r"output_df must be a number > 2"),
        ("student_t", {"output_df": "four"}, r"output_df must be a number > 2"),
    ],
)
def test_an_unknown_family_or_a_bad_df_is_refused(name, settings, message):
    with pytest.raises(ValueError, match=message):
        output_distribution(name, **settings)


def test_a_new_family_is_one_class_and_one_registration():
    @register_output_distribution("wide_laplace_for_test")
    class WideLaplace(LaplaceOutput):
        def distribution(self, loc, scale):
            return super().distribution(loc, 2 * scale)

        def standard_quantile(self, probability):
            return 2 * super().standard_quantile(probability)

    try:
        config = SimpleNamespace(output_distribution="wide_laplace_for_test")
        found = output_distribution_of(config)
        assert isinstance(found, WideLaplace) and found.half_width(0.5) == pytest.approx(2 * math.log(2))
        with pytest.raises(ValueError, match="already registered"):
            register_output_distribution("wide_laplace_for_test")(LaplaceOutput)
        with pytest.raises(TypeError, match="decorates an OutputDistribution subclass"):
            register_output_distribution("not_a_family")(dict)
    finally:
        OUTPUT_DISTRIBUTIONS.pop("wide_laplace_for_test")


class FixedForecast(torch.nn.Module):
    """Writes a given forecast (and a degraded one, and a posterior) under a chosen output family."""

    def __init__(self, loc, scale, name, **settings):
        super().__init__()
        self.loc, self.scale = loc, scale
        self.config = SimpleNamespace(output_distribution=name, **settings)
        self.modalities = [ModalitySpec("x", "vector", (2,))]

    def forward(self, td):
        td.set(keys.FORECAST_LOC, self.loc)
        td.set(keys.FORECAST_SCALE, self.scale)
        td.set(keys.FORECAST_DROPPED_LOC, self.loc + 1.0)
        td.set(keys.FORECAST_DROPPED_SCALE, 2 * self.scale)
        td.set(keys.POSTERIOR_LOC, torch.zeros(td.shape[0], 3))
        td.set(keys.POSTERIOR_SCALE, torch.ones(td.shape[0], 3))
        return td


@pytest.mark.parametrize("key", sorted(FAMILIES))
def test_every_likelihood_loss_reads_the_models_family(key):
    g = torch.Generator().manual_seed(1)
    target, loc = torch.randn(4, 5, 2, generator=g), torch.randn(4, 5, 2, generator=g)
    scale = torch.rand(4, 5, 2, generator=g) + 0.2
    settings, _ = FAMILIES[key]
    model = FixedForecast(loc, scale, key.split(" ")[0], **settings)
    batch = TensorDict({keys.TARGET: target}, batch_size=[4])
    expected = family(key).nll(target, loc, scale).sum((1, 2)).mean()
    torch.testing.assert_close(GaussianNLLLoss(model)(batch)["loss_nll"], expected)
    torch.testing.assert_close(ELBOLoss(model)(batch)["loss_nll"], expected)
    mis = MissingModalityLoss(model, dropped_nll_weight=1.0)
    out = mis.loss_from_outputs(
        model(batch.clone().update({keys.drop_key("x"): torch.ones(4, dtype=torch.bool)}))
    )
    teacher_to_student = family(key).kl(loc, scale, loc + 1.0, 2 * scale).sum((1, 2)).mean()
    torch.testing.assert_close(out["loss_mis"], teacher_to_student)
    torch.testing.assert_close(
        out["loss_mis_nll"], family(key).nll(target, loc + 1.0, 2 * scale).sum((1, 2)).mean()
    )
