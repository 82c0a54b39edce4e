"""Fitting the per-presence-pattern scale factors (mmf_rl.eval.scale_fit), and `mmf-rl calibrate`
end to end on a recorded push dataset: train, calibrate, eval."""

import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from safetensors.torch import load_file
from scipy import stats
from tensordict.nn import TensorDictModuleBase

from mmf_rl import keys
from mmf_rl.checkpoint import LAST_POINTER, list_checkpoints, load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.eval.calibration import fallback_notes
from mmf_rl.eval.metrics import (
    evaluate_forecasts,
    forecast_crps,
    interval_coverage,
    level_curves,
    quantile_crps,
)
from mmf_rl.eval.scale_fit import (
    CALIBRATION_METHODS,
    HALF_WIDTH_90,
    LEVEL_90,
    calibration_header,
    calibration_in_use,
    calibration_record,
    coverage_factor,
    fit_scale_calibration,
    fit_table,
    fit_to_errors,
    level_curve,
    standardised_errors,
    temperature_factor,
    unfit_for_latent,
)
from mmf_rl.models import load_trained_model
from mmf_rl.models.scale_calibration import (
    LEVELS,
    PresenceScaleCalibration,
    family_half_widths,
    level_half_widths,
    pattern_name,
)
from mmf_rl.objectives import output_distribution, output_distribution_of
from tests.conftest import HORIZON, SMALL_MODALITIES, TARGET_DIM, make_batch

NAMES = [s.name for s in SMALL_MODALITIES]
FACTORS = "scale_calibration.factors"
STEP_FACTORS = "scale_calibration.step_factors"
LEVEL_FACTORS = "scale_calibration.level_factors"


class FixedGaussian(TensorDictModuleBase):
    """A model whose forecast is ``N(0, sigma_p²)`` for presence pattern ``p``: fitted on targets
    ``~ N(0, 1)``, pattern ``p``'s factor must come out as ``1 / sigma_p``."""

    def __init__(self, sigma: torch.Tensor):
        super().__init__()
        self.modalities = list(SMALL_MODALITIES)
        self.scale_calibration = PresenceScaleCalibration(len(self.modalities), HORIZON)
        self.sigma = sigma
        self.in_keys, self.out_keys = [], [keys.FORECAST_LOC, keys.FORECAST_SCALE]

    def forward(self, td):
        present = torch.stack([td.get(s.present_key) for s in self.modalities], 1)
        scale = self.sigma[self.scale_calibration.pattern_index(present)].view(-1, 1, 1)
        td.set(keys.FORECAST_LOC, torch.zeros(td.shape[0], HORIZON, TARGET_DIM))
        td.set(keys.FORECAST_SCALE, self.scale_calibration(scale.expand(-1, HORIZON, TARGET_DIM), present))
        return td


def batches(count: int, size: int = 50, without_image: bool = False, seed: int = 0):
    absent = {"image": torch.zeros(size, dtype=torch.bool)} if without_image else None
    return [make_batch(size, present=absent, seed=seed + i) for i in range(count)]


def heavy_tailed(data, outliers: float = 0.03, size: float = 15.0, seed: int = 0):
    """``data`` with targets ``N(0, 1)`` but for a share ``outliers`` of the values, ``size`` times
    larger: the few large errors of contact events or sensor glitches."""
    g = torch.Generator().manual_seed(seed)
    for batch in data:
        target = batch.get(keys.TARGET)
        jumps = torch.rand(target.shape, generator=g) < outliers
        batch.set(keys.TARGET, torch.where(jumps, size * target, target))
    return data


@pytest.mark.parametrize("method", sorted(CALIBRATION_METHODS))
def test_the_fit_recovers_a_known_miscalibration_per_pattern(method):
    sigma = torch.tensor([1.0, 0.5, 0.5, 2.0, 0.25, 1.0, 0.8, 0.5])  # pattern 0 (nothing) unused
    model = FixedGaussian(sigma)
    data = batches(4)  # 200 windows, every sensor present: each pattern once per window
    fits = fit_scale_calibration(model, data, min_windows=32, method=method)
    assert [fit.index for fit in fits] == list(range(1, 8))
    for fit in fits:
        assert fit.pattern == pattern_name(fit.index, NAMES) and fit.windows == 200 and fit.fitted
        # 2000 Gaussian values a pattern: either fit is within a few percent of the true factor.
        assert fit.factor == pytest.approx(1 / float(sigma[fit.index]), rel=0.06)
        assert fit.coverage_90_after == pytest.approx(0.9, abs=0.03)
        expected_before = torch.special.erf(torch.tensor(HALF_WIDTH_90 * float(sigma[fit.index]) / 2**0.5))
        assert fit.coverage_90_before == pytest.approx(float(expected_before), abs=0.04)
    assert torch.equal(model.scale_calibration.factors[1:], torch.tensor([f.factor for f in fits]))
    # A refit starts from the uncalibrated scale: the same factors, not their square.
    again = fit_scale_calibration(model, data, min_windows=32, method=method)
    assert [f.factor for f in again] == [f.factor for f in fits]


def test_a_cross_fit_calibrates_a_model_by_the_errors_of_others_on_data_none_trained_on():
    # Two models as wide as each other, the one fitted on the other's errors on wider data (a held-out
    # scene) and on a third's: its factors are theirs, not those of its own (narrower) val errors.
    sigma = torch.full((8,), 0.5)
    shifted = [batches(2, seed=10 * i) for i in (1, 2)]
    for data in shifted:
        for batch in data:
            batch.set(keys.TARGET, 2 * batch.get(keys.TARGET))  # errors twice the val ones
    first, second = (standardised_errors(FixedGaussian(sigma), data) for data in shifted)
    pooled = first.pooled(second)
    assert pooled.windows == {i: 200 for i in range(1, 8)}
    assert all(pooled.magnitudes[i].shape == (200, HORIZON, TARGET_DIM) for i in range(1, 8))
    model = FixedGaussian(sigma)
    fit_scale_calibration(model, batches(4), min_windows=32, method="levels")
    own = model.scale_calibration.factors.clone()
    fits = fit_to_errors(model, pooled, min_windows=32, method="levels")
    assert [f.windows for f in fits] == [200] * 7
    assert torch.allclose(model.scale_calibration.factors[1:], 2 * own[1:], rtol=0.08)
    # Pooling errors over other modalities, or of another horizon, is refused with what differs.
    other = SimpleNamespace(names=NAMES[::-1], windows={}, magnitudes={})
    with pytest.raises(ValueError, match="cannot be pooled"):
        first.pooled(other)
    longer = type(first)(NAMES, {1: 3}, {1: torch.ones(3, HORIZON + 1, TARGET_DIM)})
    with pytest.raises(ValueError, match=r"shapes .* cannot be pooled"):
        first.pooled(longer)
    with pytest.raises(ValueError, match="cannot calibrate a model of"):
        fit_to_errors(model, type(first)(NAMES[:1], first.windows, first.magnitudes))
    # Errors of another horizon than the model's, or none, are refused with what is wrong.
    with pytest.raises(ValueError, match=f"over {HORIZON + 1} horizon steps .* forecasting {HORIZON}"):
        fit_to_errors(model, longer)
    with pytest.raises(ValueError, match="the errors are empty"):
        fit_to_errors(model, type(first)(NAMES, {}, {}))
    # Errors carrying a graph leave the factors plain buffers.
    carrying = {i: m.clone().requires_grad_() for i, m in pooled.magnitudes.items()}
    fit_to_errors(model, type(first)(NAMES, pooled.windows, carrying), min_windows=32, method="levels")
    assert not any(b.requires_grad for b in model.scale_calibration.buffers())


def test_heavy_tailed_errors_the_coverage_fit_holds_90_percent_where_the_temperature_over_covers():
    def held_out_coverage(model):
        unseen = heavy_tailed(batches(8, seed=100), seed=1)
        covered = [
            interval_coverage(b.get(keys.TARGET), o.get(keys.FORECAST_LOC), o.get(keys.FORECAST_SCALE), 0.9)
            for b in unseen
            for o in [model(b.exclude(keys.TARGET))]
        ]
        return float(torch.cat(covered).mean())

    model = FixedGaussian(torch.ones(8))
    fitted_on = heavy_tailed(batches(4))  # 3% of the values 15 times larger
    by_method = {}
    for method in ("coverage", "temperature"):
        fits = fit_scale_calibration(model, fitted_on, min_windows=32, method=method)
        by_method[method] = (fits[-1], held_out_coverage(model))
    (coverage, coverage_unseen), (temperature, temperature_unseen) = by_method.values()
    # The outliers set the temperature: every interval widens ~2.6x and covers nearly everything.
    assert temperature.factor > 2 and temperature.coverage_90_after > 0.96 and temperature_unseen > 0.96
    # The coverage fit holds the nominal level on the windows it was fitted on and on unseen ones,
    # with intervals less than half as wide.
    assert coverage.coverage_90_after == pytest.approx(0.9, abs=0.01)
    assert coverage_unseen == pytest.approx(0.9, abs=0.03)
    assert coverage.factor < temperature.factor / 2


class FixedForecast(FixedGaussian):
    """`FixedGaussian` whose forecast is read with the output family its config names."""

    def __init__(self, sigma: torch.Tensor, family: str, **settings):
        super().__init__(sigma)
        self.config = SimpleNamespace(output_distribution=family, **settings)


def student_t_windows(df: float, seed: int, count: int = 4, size: int = 500) -> list:
    """``count`` batches of ``size`` windows, every sensor present, with targets Student-t with ``df``
    degrees of freedom (location 0, scale 1); no observations, which `FixedGaussian` never reads."""
    data = []
    for i, batch in enumerate(batches(count, size, seed=seed)):
        target = batch.get(keys.TARGET)
        noise = stats.t(df).rvs(target.numel(), random_state=seed + i)
        batch.set(keys.TARGET, torch.as_tensor(noise, dtype=target.dtype).view(target.shape))
        data.append(batch.exclude("obs", keys.TARGET_PAST))
    return data


# Errors of 2.2 degrees of freedom: heavier-tailed than a Gaussian, as the standardised errors of real
# arms are. With 3, the Gaussian fitted at 90% would cover 0.594 of them at 50% in expectation, not
# beyond 0.60; with 2.2, 0.63.
HEAVY_DF = 2.2


@pytest.mark.parametrize(
    "family, settings, covers_50",
    [
        ("normal", {}, (0.60, 1.0)),  # the wrong shape: one factor cannot hold both levels
        ("student_t", {"output_df": HEAVY_DF}, (0.40, 0.60)),  # the errors' own shape
        ("laplace", {}, (0.40, 0.60)),  # a 50% / 90% half-width ratio as small
    ],
)
def test_fitted_at_90_on_heavy_tailed_errors_the_50_percent_interval_holds_only_under_a_heavy_tailed_family(
    family, settings, covers_50
):
    """The coverage fit at 90% under the model's family (val windows), scored on unseen (test) windows by
    the evaluation's metrics under the same family: both hold 90%, but at 50% the Gaussian over-covers,
    its 50% half width (0.674) too large a share of its 90% one (1.645) for these errors."""
    model = FixedForecast(torch.ones(8), family, **settings)
    fits = fit_scale_calibration(
        model, student_t_windows(HEAVY_DF, seed=0), min_windows=32, method="coverage"
    )
    assert all(fit.coverage_90_after == pytest.approx(0.9, abs=0.005) for fit in fits)
    test = evaluate_forecasts(model, student_t_windows(HEAVY_DF, seed=100), lambda t: t)
    assert test["windows"] == 2000 and test["coverage_90"] == pytest.approx(0.9, abs=0.01)
    low, high = covers_50
    assert low <= test["coverage_50"] <= high, test["coverage_50"]


def coverage_at(model, data, level: float) -> float:
    """The share of the values of ``data`` inside the model's central ``level`` intervals, as ``eval``
    counts them (under the pattern's level curve when the model has one)."""
    covered = []
    for batch in data:
        out = model(batch.exclude(keys.TARGET))
        loc, scale = out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_SCALE)
        curve = level_curves(model, out)
        family = output_distribution_of(model)
        covered.append(interval_coverage(batch.get(keys.TARGET), loc, scale, level, family, curve))
    return float(torch.cat(covered).mean())


def scale_mixture(data, seed: int = 0):
    """``data`` with targets ``N(0, 0.3²)`` for 60% of the values and ``N(0, 2²)`` for the others:
    errors more peaked and heavier-tailed than one Gaussian (a sensor precise most of the time, far off
    some of it)."""
    g = torch.Generator().manual_seed(seed)
    for batch in data:
        target = batch.get(keys.TARGET)
        precise = torch.rand(target.shape, generator=g) < 0.6
        batch.set(keys.TARGET, target * torch.where(precise, 0.3, 2.0))
    return data


@pytest.mark.parametrize("errors", ["student_t", "scale_mixture"])
def test_the_level_curve_holds_50_and_90_percent_where_one_factor_over_covers_at_50(errors):
    """Errors more peaked and heavier-tailed than the Gaussian family (Student-t with 2.2 degrees of
    freedom; a mixture of two Gaussians): the coverage fit at 90% over-covers
    the 50% intervals of unseen windows, the level curve holds both levels and every level of its grid,
    with the same 90% intervals and the same NLL (the family at the 90% scale), and a lower CRPS."""
    if errors == "student_t":
        fitted_on, unseen = student_t_windows(HEAVY_DF, seed=0), student_t_windows(HEAVY_DF, seed=100)
    else:
        fitted_on, unseen = scale_mixture(batches(40)), scale_mixture(batches(40, seed=100), seed=1)
    model = FixedGaussian(torch.ones(8))
    fit_scale_calibration(model, fitted_on, min_windows=32, method="coverage")
    one_factor = evaluate_forecasts(model, unseen, lambda t: t)
    assert one_factor["coverage_90"] == pytest.approx(0.9, abs=0.015)
    assert one_factor["coverage_50"] > 0.6
    assert not model.scale_calibration.has_level_curve()

    fits = fit_scale_calibration(model, fitted_on, min_windows=32, method="levels")
    calibration = model.scale_calibration
    assert calibration.has_level_curve() and [fit.index for fit in fits] == list(range(1, 8))
    for fit in fits:
        assert fit.fitted and fit.level_factors == calibration.level_factors[fit.index].tolist()
        # On the fitted windows: the corrected quantile's share of the values, at either level.
        assert fit.coverage_50_after == pytest.approx(0.5, abs=0.002)
        assert fit.coverage_90_after == pytest.approx(0.9, abs=0.002)
        # The curve is 1 at 90% (the factor holds it), under 1 in the body, nondecreasing half widths.
        assert fit.level_factors[LEVELS.index(0.9)] == pytest.approx(1.0, abs=1e-6)
        assert fit.level_factors[LEVELS.index(0.5)] < 0.9
        half_widths = torch.tensor(fit.level_factors) * family_half_widths(
            output_distribution("normal"), LEVELS
        )
        assert bool((half_widths.diff() >= 0).all())
    # Unseen windows: both levels hold, and every grid level within its tolerance.
    curve = evaluate_forecasts(model, unseen, lambda t: t)
    assert curve["coverage_50"] == pytest.approx(0.5, abs=0.015)
    assert curve["coverage_90"] == pytest.approx(0.9, abs=0.015)
    for level in LEVELS:
        assert coverage_at(model, unseen, level) == pytest.approx(level, abs=0.02), level
    # One scale for whatever reads one: the 90% intervals and the NLL are the coverage fit's.
    assert curve["width_90"] == pytest.approx(one_factor["width_90"], rel=1e-5)
    assert curve["nll"] == pytest.approx(one_factor["nll"], rel=1e-6)
    assert curve["crps"] < one_factor["crps"]


def test_patterns_with_too_few_windows_get_the_pooled_level_curve_and_the_table_says_so():
    model = FixedGaussian(torch.ones(8))
    # As in the pooled test below: the camera's patterns have 40 windows, the others 80.
    data = heavy_tailed(batches(1, 40) + batches(1, 40, without_image=True, seed=5))
    fits = fit_scale_calibration(model, data, min_windows=50, method="levels")
    curves = model.scale_calibration.level_factors
    pooled = [fit for fit in fits if "image" in fit.pattern]
    own = [fit for fit in fits if "image" not in fit.pattern]
    assert all(fit.pooled and fit.level_factors is not None for fit in pooled)
    assert all(torch.equal(curves[fit.index], curves[pooled[0].index]) for fit in pooled)
    assert all(fit.fitted and not torch.equal(curves[fit.index], curves[pooled[0].index]) for fit in own)
    table = fit_table(fits, "val")
    levels = ", ".join(f"{100 * level:g}" for level in LEVELS)
    assert table.splitlines()[0] == (
        f"| pattern | val windows | factor | level curve ({levels}%) | coverage 50% before -> after | "
        "coverage 90% before -> after |"
    )
    assert table.count("(pooled: too few windows) |") == 4 and table.count(" (pooled) |") == 4
    [note] = fallback_notes(fits, 50, "val")
    assert note.startswith("the pooled fit of every pattern and its level curve (fewer than min_windows=50")
    # Even every pattern together has too few windows: the family's own curve.
    fits = fit_scale_calibration(model, data, min_windows=1000, method="levels")
    assert model.scale_calibration.is_identity() and all(fit.level_factors is None for fit in fits)
    assert "level curve" not in fit_table(fits, "val")


def test_per_step_factors_with_a_level_curve_hold_90_percent_at_every_step_and_50_overall():
    model = FixedGaussian(torch.ones(8))
    fitted_on = growing_with_the_horizon(student_t_windows(HEAVY_DF, seed=0))
    unseen = growing_with_the_horizon(student_t_windows(HEAVY_DF, seed=100))
    fits = fit_scale_calibration(model, fitted_on, min_windows=32, method="levels", per_step=True)
    assert all(fit.step_factors is not None and fit.level_factors is not None for fit in fits)
    assert all(fit.coverage_50_after == pytest.approx(0.5, abs=0.01) for fit in fits)
    # The curve describes the errors once each step's factor has matched their growth: 1 at 90%.
    assert all(fit.level_factors[LEVELS.index(0.9)] == pytest.approx(1.0, abs=0.02) for fit in fits)
    covered = []
    for batch in unseen:
        out = model(batch.exclude(keys.TARGET))
        half = level_half_widths(level_curves(model, out), [0.5, 0.9], output_distribution("normal"))
        error = (batch.get(keys.TARGET) - out.get(keys.FORECAST_LOC)).abs() / out.get(keys.FORECAST_SCALE)
        covered.append(error.unsqueeze(-1) <= half.view(-1, 1, 1, 2))
    by_step = torch.cat(covered).double().mean(dim=(0, 2))  # [T, 2]
    assert by_step[:, 1].tolist() == pytest.approx([0.9] * HORIZON, abs=0.03)
    assert float(by_step[:, 0].mean()) == pytest.approx(0.5, abs=0.02)


def test_the_level_curves_half_widths_are_monotone_and_the_familys_under_ones():
    normal = output_distribution("normal")
    fine = torch.linspace(0.001, 0.999, 999).tolist()
    assert torch.allclose(
        level_half_widths(torch.ones(len(LEVELS), dtype=torch.float64), fine, normal),
        family_half_widths(normal, tuple(fine)),
        rtol=1e-12,
    )
    # A curve whose half widths would fall between levels: the running maximum keeps them monotone.
    jagged = torch.tensor([[1.5, 0.4, 1.0, 0.3, 1.0, 1.0, 1.0, 0.5, 1.0, 2.0, 0.6]])
    assert bool((level_half_widths(jagged, fine, normal).diff() >= 0).all())
    # The fit's curve: the corrected quantiles at every level over the family's half widths.
    magnitudes = torch.arange(1.0, 1000.0, dtype=torch.float64)  # n = 999: rank 1000 L, halfway up
    expected = torch.tensor([round(1000 * level) + 0.5 for level in LEVELS], dtype=torch.float64)
    assert torch.allclose(level_curve(magnitudes, normal) * family_half_widths(normal, LEVELS), expected)


@pytest.mark.parametrize(
    "name, settings",
    [("normal", {}), ("laplace", {}), ("student_t", {"output_df": 4.0}), ("student_t", {"output_df": 2.5})],
)
def test_the_crps_of_the_quantile_function_is_the_closed_form_under_the_familys_own_curve(name, settings):
    family = output_distribution(name, **settings)
    g = torch.Generator().manual_seed(0)
    target = 3 * torch.randn(16, HORIZON, TARGET_DIM, generator=g)
    loc = torch.randn(16, HORIZON, TARGET_DIM, generator=g)
    scale = 0.2 + torch.rand(16, HORIZON, TARGET_DIM, generator=g)
    ones = torch.ones(16, len(LEVELS))
    closed = family.crps(target, loc, scale)
    assert torch.allclose(quantile_crps(target, loc, scale, ones, family), closed, rtol=5e-4)
    # eval takes the closed form where a window's curve is the family's.
    assert torch.equal(forecast_crps(target, loc, scale, family, ones), closed.flatten(1).mean(-1))


def test_the_quantile_crps_is_the_midpoint_rule_summed_level_by_level():
    """The closed-form sum over the levels equals the midpoint rule written out, one pinball loss per
    level (ties included: targets on a quantile), for any curve and an odd batch of windows."""
    family = output_distribution("laplace")
    g = torch.Generator().manual_seed(1)
    target = 3 * torch.randn(7, HORIZON, TARGET_DIM, generator=g, dtype=torch.float64)
    target[0] = 0.0  # on the median
    loc = torch.randn(7, HORIZON, TARGET_DIM, generator=g, dtype=torch.float64)
    scale = 0.2 + torch.rand(7, HORIZON, TARGET_DIM, generator=g, dtype=torch.float64)
    loc[0] = 0.0
    curve = 0.5 + torch.rand(7, len(LEVELS), generator=g, dtype=torch.float64)  # not monotone
    for quantiles in (2, 10, 400):
        tau = (torch.arange(quantiles, dtype=torch.float64) + 0.5) / quantiles
        upper = tau[quantiles // 2 :]
        half = level_half_widths(curve, (2 * upper - 1).tolist(), family)  # [B, pairs]
        q = torch.cat([-half.flip(-1), half], -1)[:, None, None, :]  # [B, 1, 1, quantiles]
        u = ((target - loc) / scale)[..., None] - q
        pinball = u * (tau - (u < 0).double())
        expected = 2 * pinball.mean(-1) * scale
        torch.testing.assert_close(
            quantile_crps(target, loc, scale, curve, family, quantiles), expected, rtol=1e-10, atol=1e-12
        )


def test_the_crps_under_a_curve_is_the_crps_of_the_distribution_it_describes():
    """A Gaussian forecast whose curve holds the Laplace's half widths at every grid level is, to the
    interpolation between them, the Laplace: its CRPS is the Laplace's closed form within 1%."""
    normal, laplace = output_distribution("normal"), output_distribution("laplace")
    curve = (family_half_widths(laplace, LEVELS) / family_half_widths(normal, LEVELS)).float()
    z = torch.linspace(-10, 10, 201).view(1, -1, 1)
    one = torch.ones(())
    crps = quantile_crps(z, 0 * one, one, curve.view(1, -1), normal)
    assert torch.allclose(crps, laplace.crps(z, 0 * one, one), rtol=0.01)


def test_a_factor_of_1_is_calibrated_at_90_percent_under_the_family():
    """Errors drawn from the family's own standard member: the coverage fit gives a factor near 1, and the
    temperature (the NLL's 1-D minimiser for the Student-t, its closed forms for the others) too."""
    for name, settings, draw in [
        ("normal", {}, stats.norm()),
        ("laplace", {}, stats.laplace()),
        ("student_t", {"output_df": 4.0}, stats.t(4.0)),
    ]:
        family = output_distribution(name, **settings)
        magnitudes = torch.from_numpy(abs(draw.rvs(50_000, random_state=0)))
        assert coverage_factor(magnitudes, family) == pytest.approx(1.0, abs=0.02), name
        assert temperature_factor(magnitudes, family) == pytest.approx(1.0, abs=0.02), name
    # The Gaussian's factor of Laplace errors is not 1: the family is what makes it 1.
    laplace_errors = torch.from_numpy(abs(stats.laplace().rvs(50_000, random_state=0)))
    assert coverage_factor(laplace_errors) == pytest.approx(2.3026 / 1.6449, rel=0.02)


# The std of the errors at each horizon step, where the forecast's scale is 1 at every step.
GROWTH = torch.linspace(0.4, 2.0, HORIZON)


def growing_with_the_horizon(data):
    """``data`` with targets ``N(0, GROWTH_t²)`` at step ``t``: errors growing with the horizon."""
    for batch in data:
        batch.set(keys.TARGET, batch.get(keys.TARGET) * GROWTH.view(1, -1, 1))
    return data


def step_coverage(model, data) -> torch.Tensor:
    """``[T]``: the share of the values of ``data`` inside the model's 90% intervals, at each step."""
    covered = [
        (b.get(keys.TARGET) - o.get(keys.FORECAST_LOC)).abs() <= HALF_WIDTH_90 * o.get(keys.FORECAST_SCALE)
        for b in data
        for o in [model(b.exclude(keys.TARGET))]
    ]
    return torch.cat(covered).double().mean(dim=(0, 2))


def test_errors_growing_with_the_horizon_per_step_factors_hold_90_percent_at_every_step():
    model = FixedGaussian(torch.ones(8))
    fitted_on = growing_with_the_horizon(batches(8))
    unseen = growing_with_the_horizon(batches(16, seed=100))
    fit_scale_calibration(model, fitted_on, min_windows=32)
    pooled = step_coverage(model, unseen)
    # One factor for every step covers 90% on average: too wide early, too narrow late.
    assert float(pooled.mean()) == pytest.approx(0.9, abs=0.02)
    assert pooled[0] > 0.97 and pooled[-1] < 0.8
    fits = fit_scale_calibration(model, fitted_on, min_windows=32, per_step=True)
    assert step_coverage(model, unseen).tolist() == pytest.approx([0.9] * HORIZON, abs=0.03)
    calibration = model.scale_calibration
    for fit in fits:
        assert fit.fitted and fit.coverage_90_after == pytest.approx(0.9, abs=0.01)
        # Each step's factor undoes its error's growth; the model applies the pattern's factor times
        # its step's, as the fit reports.
        assert fit.step_factors == pytest.approx(GROWTH.tolist(), rel=0.1)
        applied = calibration.factors[fit.index] * calibration.step_factors[fit.index]
        assert applied.tolist() == fit.step_factors
    # A refit without per_step starts from ones: the step factors are gone.
    fit_scale_calibration(model, fitted_on, min_windows=32)
    assert torch.equal(calibration.step_factors, torch.ones(8, HORIZON))


def test_per_step_patterns_with_too_few_windows_keep_the_pooled_factor_at_every_step():
    model = FixedGaussian(torch.ones(8))
    # As in the pooled test below: the camera's patterns have 40 windows, the others 80.
    data = growing_with_the_horizon(batches(1, 40) + batches(1, 40, without_image=True, seed=5))
    fits = fit_scale_calibration(model, data, min_windows=50, method="coverage", per_step=True)
    factors, steps = model.scale_calibration.factors, model.scale_calibration.step_factors
    for fit in fits:
        if "image" in fit.pattern:
            assert fit.pooled and fit.step_factors is None and factors[fit.index] == factors[1]
            assert torch.equal(steps[fit.index], torch.ones(HORIZON))
        else:
            assert fit.fitted and fit.step_factors == pytest.approx(GROWTH.tolist(), rel=0.15)
    table = fit_table(fits, "val")
    assert table.splitlines()[0] == (
        "| pattern | val windows | factor | factor per step | coverage 50% before -> after | "
        "coverage 90% before -> after |"
    )
    assert table.count("(pooled: too few windows) | as the factor |") == 4
    [note] = fallback_notes(fits, 50, "val", per_step=True)
    assert note.startswith("the pooled fit of every pattern, one factor at every horizon step (fewer than")
    assert note.endswith("image, image+force, image+proprio, image+force+proprio")


def test_the_coverage_fit_is_the_corrected_quantile_of_the_standardised_errors():
    # n = 9 values: rank ceil(10 * 0.9) = 9, the largest; the factor scales it to the 90% half width.
    magnitudes = torch.arange(1.0, 10.0, dtype=torch.float64)
    assert CALIBRATION_METHODS["coverage"](magnitudes) == pytest.approx(9 / HALF_WIDTH_90)
    # n = 99: rank 90, the 90th smallest (not the 89.1th an uncorrected quantile would take), halfway
    # to the 91st. Shuffled: the order of the values does not matter.
    shuffled = torch.arange(1.0, 100.0)[torch.randperm(99, generator=torch.Generator().manual_seed(0))]
    assert CALIBRATION_METHODS["coverage"](shuffled) == pytest.approx(90.5 / HALF_WIDTH_90)
    # Too few values for the correction (rank 5 of 4): the largest.
    assert CALIBRATION_METHODS["coverage"](torch.arange(1.0, 5.0)) == pytest.approx(4 / HALF_WIDTH_90)
    assert CALIBRATION_METHODS["temperature"](torch.tensor([3.0, 4.0])) == pytest.approx(12.5**0.5)


def test_patterns_with_too_few_windows_get_the_pooled_fit_and_each_window_counts_once():
    sigma = torch.full((8,), 0.5)
    sigma[[1, 3, 5, 7]] = 0.25  # the camera's patterns: their own fit would be 4, the others' 2
    model = FixedGaussian(sigma)
    # 40 windows with every sensor, 40 without the camera: the camera's patterns have 40 windows,
    # the others 80 (a camera-less window under "all" and under "without_image" is one window).
    data = batches(1, 40) + batches(1, 40, without_image=True, seed=5)
    fits = {fit.pattern: fit for fit in fit_scale_calibration(model, data, min_windows=50)}
    assert {name: fit.windows for name, fit in fits.items()} == {
        "image": 40,
        "force": 80,
        "image+force": 40,
        "proprio": 80,
        "image+proprio": 40,
        "force+proprio": 80,
        "image+force+proprio": 40,
    }
    factors = model.scale_calibration.factors
    pooled = factors[1]
    # The pooled fit mixes the camera's 160 (window, pattern) pairs at 4 with the 240 others at 2.
    assert 2.2 < pooled < 3.8 and factors[6] == pytest.approx(2.0, rel=0.1)
    for name, fit in fits.items():
        assert fit.fitted == ("image" not in name) and fit.pooled == ("image" in name)
        if "image" in name:
            assert fit.factor == pooled
    table = fit_table(list(fits.values()), "val")
    assert table.count(f"| {pooled:.3f} (pooled: too few windows) |") == 4
    # Even every pattern together has too few windows: nothing to pool, the factors stay 1.
    fits = fit_scale_calibration(model, data, min_windows=1000)
    assert not any(fit.fitted or fit.pooled for fit in fits) and model.scale_calibration.is_identity()
    assert all(fit.coverage_90_after == fit.coverage_90_before for fit in fits)
    assert "| 1 (kept: too few windows) |" in fit_table(fits, "val")


def test_bad_input_is_a_one_line_error():
    with pytest.raises(TypeError, match="has no per-presence-pattern scale factors"):
        fit_scale_calibration(torch.nn.Linear(2, 2), batches(1))
    model = FixedGaussian(torch.ones(8))
    with pytest.raises(ValueError, match="min_windows must be >= 1"):
        fit_scale_calibration(model, batches(1), min_windows=0)
    with pytest.raises(
        ValueError, match="unknown calibration method 'nll': choose among coverage, levels, temperature"
    ):
        fit_scale_calibration(model, batches(1), method="nll")
    with pytest.raises(ValueError, match="no window to fit"):
        fit_scale_calibration(model, [])
    without_presence = batches(1)[0].exclude(keys.present_key("force"))
    with pytest.raises(KeyError, match=r"lacks the presence flags \[\('present', 'force'\)\]"):
        fit_scale_calibration(model, [without_presence])


def test_the_results_header_says_whether_and_where_the_scale_was_recalibrated():
    model = FixedGaussian(torch.full((8,), 0.5))
    model.config = type("Config", (), {"eval_latent": "mean"})()
    assert calibration_in_use(model) is None and calibration_header(None) == ""
    fits = fit_scale_calibration(model, batches(1), min_windows=32, method="coverage")
    model.calibration = calibration_record(model, fits, "val", 32, "/data/push", "coverage")
    record = calibration_in_use(model)
    assert record["split"] == "val"
    assert "recalibrated per presence pattern on the val split" in calibration_header(record)
    assert "method=coverage;" in calibration_header(record)
    # A record written before the method was a choice was a temperature fit.
    older = {k: v for k, v in record.items() if k != "method"}
    assert "method=temperature;" in calibration_header(older)
    assert unfit_for_latent(model) is None
    # A record written before the step factors existed describes factors with step factors of ones.
    assert calibration_in_use(model) == record and record["per_step"] is False
    model.calibration = {k: v for k, v in record.items() if k not in ("step_factors", "per_step")}
    assert calibration_in_use(model) is model.calibration
    step_fits = fit_scale_calibration(model, batches(1), min_windows=32, method="coverage", per_step=True)
    model.calibration = calibration_record(model, step_fits, "val", 32, "/data/push", "coverage", True)
    assert "recalibrated per presence pattern and horizon step on the val split" in calibration_header(
        calibration_in_use(model)
    )
    model.scale_calibration.step_factors[3, 0] = 5.0  # step factors that the record does not describe
    unrecorded = calibration_in_use(model)
    assert unrecorded["split"] is None and unrecorded["step_factors"][3][0] == 5.0
    assert "per presence pattern and horizon step (the fit is not recorded" in calibration_header(unrecorded)
    # A record written before the level curves existed describes curves of ones.
    fits = fit_scale_calibration(model, batches(1), min_windows=32, method="coverage")
    record = calibration_record(model, fits, "val", 32, "/data/push", "coverage")
    model.calibration = {k: v for k, v in record.items() if k not in ("levels", "level_factors")}
    assert calibration_in_use(model) is model.calibration
    assert "level curve" not in calibration_header(model.calibration)
    level_fits = fit_scale_calibration(model, heavy_tailed(batches(1)), min_windows=32, method="levels")
    model.calibration = calibration_record(model, level_fits, "val", 32, "/data/push", "levels")
    assert calibration_in_use(model)["level_factors"] == model.scale_calibration.level_factors.tolist()
    assert (
        "method=levels; a level curve per pattern, read by the intervals and the CRPS;"
        in calibration_header(model.calibration)
    )
    model.scale_calibration.level_factors[3, 0] = 5.0  # a curve that the record does not describe
    unrecorded = calibration_in_use(model)
    assert unrecorded["split"] is None and unrecorded["level_curve"]
    assert "(the fit is not recorded with the model; a level curve per pattern" in calibration_header(
        unrecorded
    )
    fits = fit_scale_calibration(model, batches(1), min_windows=32, method="coverage")
    model.calibration = calibration_record(model, fits, "val", 32, "/data/push", "coverage")
    model.scale_calibration.factors[3] = 5.0  # factors that the record does not describe
    assert "fit is not recorded" in calibration_header(calibration_in_use(model))
    # Scored under another eval latent than the fit's: the factors describe another forecast.
    model.calibration = calibration_record(model, fits, "val", 32, "/data/push", "coverage")
    model.config.eval_latent = "predictive"
    assert "fitted with eval_latent=mean" in unfit_for_latent(model)
    assert calibration_in_use(model) is None and model.scale_calibration.is_identity()


# -- `mmf-rl calibrate` on a recorded push dataset -------------------------------------------------


@pytest.fixture(scope="module")
def push_run(push_forecaster_run, tmp_path_factory):
    """A copy of the session's tiny forecaster (`mmf-rl train` calibrated it: calibrate=true by
    default), which this module's tests recalibrate and evaluate into."""
    return Path(shutil.copytree(push_forecaster_run, tmp_path_factory.mktemp("calibrate") / "run"))


def stored_factors(run):
    checkpoint = load_checkpoint(run / "checkpoints", with_trainer_state=False)
    return checkpoint, load_file(run / "model" / "model.safetensors")[FACTORS]


def test_training_ends_with_a_calibration_on_val_stored_in_checkpoint_and_export(push_run):
    checkpoint, exported = stored_factors(push_run)
    record = checkpoint.meta["calibration"]
    assert record["split"] == "val" and record["min_windows"] == 32 and record["method"] == "levels"
    assert torch.equal(checkpoint.model_state[FACTORS], exported)
    assert exported.tolist() == record["factors"]
    assert json.loads((push_run / "model" / "calibration.json").read_text()) == record
    # The trainer state survives the re-save: the run can still be resumed.
    assert load_checkpoint(push_run / "checkpoints").trainer_state is not None


def test_calibrate_refits_writes_back_and_eval_scores_with_the_factors(push_run, capsys):
    last = (push_run / "checkpoints" / LAST_POINTER).read_text()
    steps = list_checkpoints(push_run / "checkpoints")
    assert cli(["calibrate", f"checkpoint={push_run}", "min_windows=4"]) == 0
    out = capsys.readouterr().out
    # The default method, levels: each pattern's level curve beside its factor.
    assert (
        "| pattern | val windows | factor | level curve (10, 20, 30, 40, 50, 60, 70, 80, 90, 95, 99%) |"
        in out
    )
    assert f"written: {steps[-1]}" in out and f"written: {push_run / 'model'}" in out
    assert (push_run / "checkpoints" / LAST_POINTER).read_text() == last
    assert list_checkpoints(push_run / "checkpoints") == steps
    assert not [p for p in (push_run / "checkpoints").iterdir() if p.name.startswith(".")]
    checkpoint, exported = stored_factors(push_run)
    record = checkpoint.meta["calibration"]
    assert record["min_windows"] == 4 and torch.equal(checkpoint.model_state[FACTORS], exported)
    fitted = {frozenset(p["pattern"].split("+")): p for p in record["patterns"]}
    assert all(p["fitted"] for p in fitted.values()) and len(fitted) == 7
    assert not torch.equal(exported, torch.ones_like(exported))
    # A refit starts from ones: calibrating again gives the same factors.
    assert cli(["calibrate", f"checkpoint={push_run / 'model'}", "min_windows=4"]) == 0
    capsys.readouterr()
    assert torch.equal(stored_factors(push_run)[1], exported)

    # `mmf-rl eval` scores the calibrated model, without a flag, and says so. On val (no sensor
    # fails in this recording: every subset is one pattern on every window) its 90% coverage per
    # subset is the calibration's "after".
    assert cli(["eval", f"checkpoint={push_run}", "split=val", "num_samples=0", "plots=false"]) == 0
    capsys.readouterr()
    results = json.loads((push_run / "eval" / "results.json").read_text())
    assert results["scale_calibration"]["split"] == "val"
    assert (
        "Forecast scale: recalibrated per presence pattern on the val split"
        in (push_run / "eval" / "results.md").read_text()
    )
    pattern = {
        "all": {"image", "force", "proprio"},
        "only_force": {"force"},
        "without_image": {"force", "proprio"},
    }
    for subset, name in pattern.items():
        name = frozenset(name)
        row = results["subsets"][subset]
        assert row["windows"] == fitted[name]["windows"]
        assert row["coverage_90"] == pytest.approx(fitted[name]["coverage_90_after"], abs=1e-6)
    model, _, _ = load_trained_model(push_run / "model")
    assert torch.equal(model.scale_calibration.factors, exported)


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["checkpoint=RUN", "split=test"], "split='test': the scale factors are fitted on val or train"),
        (["checkpoint=RUN", "method=nll"], "method='nll': choose among coverage, levels, temperature"),
        (["checkpoint=/nowhere/run"], "/nowhere/run does not exist"),
        ([], "checkpoint=PATH is required"),
    ],
)
def test_calibrate_names_bad_input_in_one_line(push_run, capsys, arguments, message):
    assert cli(["calibrate", *(a.replace("RUN", str(push_run)) for a in arguments)]) == 1
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_eval_and_calibrate_on_the_train_split_read_every_training_window(push_run, capsys):
    # The training loader shuffles and drops the tail that does not fill a batch: with a split smaller
    # than the batch, eval and calibrate would have read no window at all.
    trained = load_checkpoint(push_run / "checkpoints", with_trainer_state=False).meta["config"]["data"]
    windows = len(WindowDataset(DataConfig.from_dict(trained)).split_windows["train"])
    assert 0 < windows < 256
    args = [f"checkpoint={push_run}", "split=train", "num_samples=0", "plots=false", "batch_size=256"]
    assert cli(["eval", *args]) == 0
    results = json.loads((push_run / "eval" / "results.json").read_text())
    assert results["subsets"]["all"]["windows"] == windows
    assert cli(["calibrate", f"checkpoint={push_run}", "split=train", "min_windows=4", "batch_size=256"]) == 0
    capsys.readouterr()
    record = load_checkpoint(push_run / "checkpoints", with_trainer_state=False).meta["calibration"]
    assert record["split"] == "train"
    assert {p["windows"] for p in record["patterns"]} == {windows}  # no sensor fails in this recording


def test_calibrate_method_temperature_stores_the_nll_fit(push_run, capsys):
    assert cli(["calibrate", f"checkpoint={push_run}", "min_windows=4", "method=temperature"]) == 0
    assert "(method=temperature)" in capsys.readouterr().out
    record = load_checkpoint(push_run / "checkpoints", with_trainer_state=False).meta["calibration"]
    assert record["method"] == "temperature"
    assert "method=temperature;" in calibration_header(record)


def recalibrated(push_run, capsys, *arguments):
    """`mmf-rl calibrate` the run with ``arguments``: what it printed, the checkpoint, the exported
    factors and the recorded fit."""
    assert cli(["calibrate", f"checkpoint={push_run}", "min_windows=4", *arguments]) == 0
    out = capsys.readouterr().out
    checkpoint, exported = stored_factors(push_run)
    return out, checkpoint, exported, checkpoint.meta["calibration"]


def test_calibrate_method_levels_stores_the_curves_and_eval_scores_both_levels_with_them(push_run, capsys):
    out, checkpoint, _, record = recalibrated(push_run, capsys, "method=levels")
    assert "(method=levels)" in out and "| level curve (10, 20, 30, 40, 50, 60, 70, 80, 90, 95, 99%) |" in out
    curves = checkpoint.model_state[LEVEL_FACTORS]
    assert record["method"] == "levels" and record["levels"] == list(LEVELS)
    assert curves.tolist() == record["level_factors"] and not torch.equal(curves, torch.ones_like(curves))
    assert torch.equal(load_file(push_run / "model" / "model.safetensors")[LEVEL_FACTORS], curves)
    model, _, _ = load_trained_model(push_run / "model")
    assert torch.equal(model.scale_calibration.level_factors, curves)
    fitted = {frozenset(p["pattern"].split("+")): p for p in record["patterns"]}
    assert all(p["level_factors"] == curves[p["index"]].tolist() for p in fitted.values())

    # On val (every subset one pattern on every window, as above) eval's 50% and 90% coverage are the
    # fit's "after", read through the level curve, and its header says so.
    assert cli(["eval", f"checkpoint={push_run}", "split=val", "num_samples=0", "plots=false"]) == 0
    capsys.readouterr()
    results = json.loads((push_run / "eval" / "results.json").read_text())
    assert results["scale_calibration"]["method"] == "levels"
    assert "method=levels; a level curve per pattern" in (push_run / "eval" / "results.md").read_text()
    for subset, name in {"all": {"image", "force", "proprio"}, "only_force": {"force"}}.items():
        row, fit = results["subsets"][subset], fitted[frozenset(name)]
        assert row["coverage_50"] == pytest.approx(fit["coverage_50_after"], abs=1e-6)
        assert row["coverage_90"] == pytest.approx(fit["coverage_90_after"], abs=1e-6)


def test_calibrate_per_step_on_the_recording_holds_90_percent_at_every_step_and_travels(push_run, capsys):
    out, checkpoint, exported, record = recalibrated(push_run, capsys, "per_step=true")
    assert "(method=levels, per horizon step)" in out and "| factor per step |" in out
    steps = checkpoint.model_state[STEP_FACTORS]
    assert record["per_step"] and steps.tolist() == record["step_factors"]
    assert torch.equal(load_file(push_run / "model" / "model.safetensors")[STEP_FACTORS], steps)
    assert torch.equal(exported, checkpoint.model_state[FACTORS])
    assert not torch.equal(steps, torch.ones_like(steps))
    model, _, data_config = load_trained_model(push_run / "model")
    assert torch.equal(model.scale_calibration.step_factors, steps)

    # On the val windows it was fitted on (no sensor fails in this recording: every sensor present is
    # one pattern), each step's 90% intervals hold the corrected quantile's share of the step's values.
    data = WindowDataset(DataConfig.from_dict(data_config))
    val = list(data.loader("val", 256, shuffle=False))
    every = {spec.name for spec in model.modalities}
    every_sensor = next(p for p in record["patterns"] if set(p["pattern"].split("+")) == every)
    values = every_sensor["windows"] * val[0].get(keys.TARGET).shape[-1]
    assert values == sum(b.shape[0] for b in val) * val[0].get(keys.TARGET).shape[-1]
    rank = min(math.ceil((values + 1) * LEVEL_90), values)
    assert step_coverage(model, val).tolist() == pytest.approx([rank / values] * steps.shape[1], abs=1e-9)

    assert cli(["eval", f"checkpoint={push_run}", "split=val", "num_samples=0", "plots=false"]) == 0
    capsys.readouterr()
    assert (
        "Forecast scale: recalibrated per presence pattern and horizon step on the val split"
        in (push_run / "eval" / "results.md").read_text()
    )
