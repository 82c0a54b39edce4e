import math
from types import SimpleNamespace

import pytest
import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.datasets import apply_presence_subset, presence_subsets
from mmf_rl.eval.metrics import (
    best_of_samples,
    constant_velocity,
    displacement_errors,
    evaluate_forecasts,
    evaluate_presence_subsets,
    gaussian_crps,
    interval_coverage,
)
from mmf_rl.eval.report import markdown_table
from mmf_rl.objectives import output_distribution

# The fake forecasters below read the future from here: the metrics hide "target" from the model.
ORACLE = "oracle"


class FixedForecaster(torch.nn.Module):
    """Forecasts target + offset; its K samples are target + k * spread (sample 0 is exact)."""

    def __init__(self, offset: float, spread: float = 1.0):
        super().__init__()
        self.offset, self.spread = offset, spread

    def forward(self, td):
        assert keys.TARGET not in td.keys(), "the model must not see the future it forecasts"
        td.set(keys.FORECAST_LOC, td.get(ORACLE) + self.offset)
        td.set(keys.FORECAST_SCALE, torch.ones_like(td.get(ORACLE)))
        return td

    def sample(self, td, num_samples):
        ks = torch.arange(num_samples, dtype=torch.float32).view(1, -1, 1, 1) * self.spread
        td.set(keys.FORECAST_SAMPLES, td.get(ORACLE)[:, None] + ks)
        return td


def batches(n=3, b=4, t=5):
    g = torch.Generator().manual_seed(0)
    out = []
    for _ in range(n):
        target = torch.randn(b, t, 2, generator=g)
        past = torch.cumsum(torch.ones(b, 3, 2), 1)  # moves +1 per step in both dims
        out.append(
            TensorDict({keys.TARGET: target, ORACLE: target.clone(), keys.TARGET_PAST: past}, batch_size=[b])
        )
    return out


def test_displacement_errors_are_euclidean():
    forecast = torch.zeros(1, 3, 2)
    target = torch.tensor([[[3.0, 4.0], [0.0, 0.0], [6.0, 8.0]]])
    ade, fde = displacement_errors(forecast, target)
    assert ade.item() == pytest.approx(5.0) and fde.item() == pytest.approx(10.0)


def test_constant_velocity_extrapolates_the_last_step():
    past = torch.tensor([[[0.0, 0.0], [1.0, 2.0]]])
    torch.testing.assert_close(
        constant_velocity(past, 3), torch.tensor([[[2.0, 4.0], [3.0, 6.0], [4.0, 8.0]]])
    )


def test_metrics_in_normalised_frame_and_units():
    scale = 10.0
    metrics = evaluate_forecasts(
        FixedForecaster(offset=0.3),
        batches(),
        denormalize=lambda t: t * scale,
        num_samples=4,
        with_baseline=True,
    )
    assert metrics["windows"] == 12
    assert metrics["mse"] == pytest.approx(0.09, rel=1e-5)
    assert metrics["mse_units"] == pytest.approx(9.0, rel=1e-5)
    assert metrics["ade"] == pytest.approx(0.3 * 2**0.5 * scale, rel=1e-5)
    assert metrics["min_ade_k"] == pytest.approx(0.0, abs=1e-5)  # sample 0 is exact
    assert metrics["min_fde_k"] == pytest.approx(0.0, abs=1e-5) and metrics["min_mse_k"] == pytest.approx(
        0.0, abs=1e-5
    )
    assert metrics["nll"] == pytest.approx(
        10 * (0.5 * 0.09 + 0.5 * torch.log(torch.tensor(2 * torch.pi)).item()), rel=1e-5
    )
    # |error| = 0.3 < 0.674 (the 50% half-width of N(0, 1)) everywhere: both intervals cover every value.
    assert metrics["coverage_50"] == 1.0 and metrics["coverage_90"] == 1.0
    # Scale 1 (normalised): the 90% intervals are 2 * 1.645 wide, in units 10 times that.
    assert metrics["width_90"] == pytest.approx(2 * 1.6449 * scale, rel=1e-4)
    assert metrics["crps"] == pytest.approx(float(gaussian_crps(*torch.tensor([[[0.3]], [[0.0]], [[1.0]]]))))
    assert metrics["cv_mse"] > 0


def test_gaussian_crps_is_the_integral_of_the_squared_cdf_error():
    target, loc, scale = (
        torch.tensor([0.3, -2.0, 5.0]),
        torch.tensor([0.0, 1.0, 5.0]),
        torch.tensor([1.0, 0.5, 2.0]),
    )
    grid = torch.linspace(-20, 20, 400_001, dtype=torch.float64)
    for y, mu, sigma in zip(target, loc, scale, strict=True):
        cdf = torch.distributions.Normal(mu.double(), sigma.double()).cdf(grid)
        integral = torch.trapezoid((cdf - (grid >= y).double()) ** 2, grid)
        assert float(gaussian_crps(y.view(1, 1, 1), mu.view(1, 1, 1), sigma.view(1, 1, 1))) == pytest.approx(
            float(integral), rel=1e-4
        )
    # Forecasts on target: the sharper scores better. As the scale vanishes: the absolute error.
    one = torch.ones(1, 1, 1)
    assert gaussian_crps(one, one, 0.5 * one) < gaussian_crps(one, one, 2 * one)
    assert float(gaussian_crps(0 * one, one, 1e-4 * one)) == pytest.approx(1.0, rel=1e-3)


def test_baseline_needs_target_past():
    data = [b.exclude(keys.TARGET_PAST) for b in batches()]
    with pytest.raises(KeyError, match="include_target_past"):
        evaluate_forecasts(FixedForecaster(0.0), data, denormalize=lambda t: t, with_baseline=True)


def test_no_windows_gives_no_metrics():
    assert evaluate_forecasts(FixedForecaster(0.0), [], denormalize=lambda t: t) == {}


def test_markdown_table_rows_and_degradation():
    results = {
        "all": {"windows": 10, "windows_available": 12, "mse": 0.1, "coverage_90": 0.875, "degradation": 0.0},
        "without_image": {
            "windows": 10,
            "windows_available": 12,
            "mse": 0.15,
            "coverage_90": 0.5,
            "degradation": 0.5,
        },
    }
    table = markdown_table(results, {"windows": 10, "mse": 0.4}, units="metres", num_samples=20)
    lines = table.splitlines()
    assert lines[0] == "| subset | windows | available | MSE (norm.) | cover 90% | MSE vs all |"
    assert lines[3] == "| without_image | 10 | 12 | 0.1500 | 0.50 | +50.0% |"
    assert lines[4] == "| constant velocity | 10 |  | 0.4000 |  |  |"
    assert "K = 20" in table


def test_interval_coverage_counts_values_inside_the_central_interval():
    # N(0, 1): the central 50% interval is +-0.674, the 90% one +-1.645.
    target = torch.tensor([[[0.0], [0.5], [-0.7], [1.0], [2.0]]])
    loc, scale = torch.zeros_like(target), torch.ones_like(target)
    assert interval_coverage(target, loc, scale, 0.5).tolist() == [pytest.approx(2 / 5)]
    assert interval_coverage(target, loc, scale, 0.9).tolist() == [pytest.approx(4 / 5)]
    # The scale sets the width: doubled, -0.7 and 1.0 fall inside the 50% interval too.
    assert interval_coverage(target, loc, 2 * scale, 0.5).tolist() == [pytest.approx(4 / 5)]
    # Calibrated Gaussian forecasts cover about the nominal share.
    g = torch.Generator().manual_seed(0)
    draws = torch.randn(200, 10, 2, generator=g) * 3.0 + 1.0
    loc, scale = torch.ones_like(draws), torch.full_like(draws, 3.0)
    assert abs(float(interval_coverage(draws, loc, scale, 0.9).mean()) - 0.9) < 0.02


def test_min_over_samples_takes_each_minimum_on_its_own():
    target = torch.zeros(1, 2, 2)
    # Sample 0: small error at step 0, large at the last step; sample 1: the other way round.
    samples = torch.tensor([[[[0.0, 0.0], [4.0, 0.0]], [[2.0, 0.0], [1.0, 0.0]]]])
    best = best_of_samples(samples, target, samples * 10, target * 10)
    assert best["min_ade_k"].item() == pytest.approx(10 * 1.5)  # sample 1: (20 + 10) / 2 < sample 0's 20
    assert best["min_fde_k"].item() == pytest.approx(10 * 1.0)  # sample 1's final error
    assert best["min_mse_k"].item() == pytest.approx(5 / 4)  # sample 1: (4 + 1) / 4 < sample 0's 16 / 4
    samples[0, 0, 1, 0] = 0.5  # now sample 0 has the best FDE, sample 1 still the best ADE
    best = best_of_samples(samples, target, samples, target)
    assert best["min_fde_k"].item() == pytest.approx(0.5) and best["min_ade_k"].item() == pytest.approx(0.25)


class PresenceForecaster(torch.nn.Module):
    """Forecast error = the window's own difficulty + 1 for each absent modality (a, b, c)."""

    def forward(self, td):
        absent = sum((~td.get(keys.present_key(m))).float() for m in ("a", "b", "c"))
        error = td.get("difficulty") + absent
        td.set(keys.FORECAST_LOC, td.get(ORACLE) + error[:, None, None])
        td.set(keys.FORECAST_SCALE, torch.ones_like(td.get(ORACLE)))
        return td


def presence_batch(a, b, c, difficulty):
    n = len(difficulty)
    target = torch.zeros(n, 1, 1)
    return TensorDict(
        {
            keys.present_key("a"): torch.tensor(a, dtype=torch.bool),
            keys.present_key("b"): torch.tensor(b, dtype=torch.bool),
            keys.present_key("c"): torch.tensor(c, dtype=torch.bool),
            "difficulty": torch.tensor(difficulty),
            keys.TARGET: target,
            ORACLE: target.clone(),
        },
        batch_size=[n],
    )


def test_presence_subsets_are_scored_on_the_windows_they_share():
    # Windows 0-2 have a and b; window 3 lacks a (and is hard); c exists nowhere.
    batches = [
        presence_batch([1, 1], [1, 1], [0, 0], [0.0, 1.0]),
        presence_batch([1, 0], [1, 1], [0, 0], [2.0, 10.0]),
    ]
    subsets = list(presence_subsets(["a", "b", "c"]))
    results, _ = evaluate_presence_subsets(PresenceForecaster(), batches, subsets, denormalize=lambda t: t)
    # only_c has no window; every other row keeps a present modality on windows 0-2 only.
    assert set(results) == {"all", "without_a", "without_b", "without_c", "only_a", "only_b"}
    assert {row["windows"] for row in results.values()} == {3.0}
    assert results["all"]["windows_available"] == 4 and results["only_a"]["windows_available"] == 3
    # On windows 0-2 (difficulty 0, 1, 2) "all" lacks c only: errors 1, 2, 3.
    assert results["all"]["mse"] == pytest.approx((1 + 4 + 9) / 3)
    assert results["without_a"]["mse"] == pytest.approx((4 + 9 + 16) / 3)  # a and c absent
    assert (
        results["without_a"]["degradation"] == pytest.approx(29 / 14 - 1)
        and results["all"]["degradation"] == 0
    )
    # Unpaired, each row would average its own windows: "all" also window 3 (a and c absent: error 12),
    # which only_a cannot score, so removing b and c would look like an improvement.
    unpaired_all = evaluate_forecasts(PresenceForecaster(), batches, denormalize=lambda t: t)["mse"]
    only_a = dict(subsets)["only_a"]
    unpaired_only_a = evaluate_forecasts(
        PresenceForecaster(), [apply_presence_subset(b, only_a) for b in batches], denormalize=lambda t: t
    )["mse"]
    assert unpaired_all == pytest.approx((1 + 4 + 9 + 144) / 4) and unpaired_only_a < unpaired_all
    assert results["only_a"]["mse"] == pytest.approx(unpaired_only_a) and results["only_a"]["degradation"] > 0


def test_subsets_sharing_no_window_are_a_clear_error():
    batches = [presence_batch([1, 0], [0, 1], [0, 0], [0.0, 0.0])]
    with pytest.raises(ValueError, match="no window can be scored in every presence subset"):
        evaluate_presence_subsets(
            PresenceForecaster(), batches, list(presence_subsets(["a", "b", "c"])), denormalize=lambda t: t
        )
    assert evaluate_presence_subsets(
        PresenceForecaster(), [], list(presence_subsets(["a"])), denormalize=lambda t: t
    ) == ({}, None)


def test_paired_baseline_row_uses_the_shared_windows():
    batch = presence_batch([1, 0], [1, 1], [1, 1], [0.0, 0.0])
    batch.set(keys.TARGET_PAST, torch.tensor([[[0.0], [1.0]], [[0.0], [3.0]]]))  # cv forecasts 2 and 6
    _, baseline = evaluate_presence_subsets(
        PresenceForecaster(),
        [batch],
        list(presence_subsets(["a", "b", "c"])),
        denormalize=lambda t: t,
        with_baseline=True,
    )
    assert baseline["windows"] == 1 and baseline["mse"] == pytest.approx(4.0)
    assert not math.isnan(baseline["ade"])


class FamilyForecaster(FixedForecaster):
    """`FixedForecaster` whose forecast is read with the output family its config names."""

    def __init__(self, offset: float, family: str, **settings):
        super().__init__(offset)
        self.config = SimpleNamespace(output_distribution=family, **settings)


@pytest.mark.parametrize("family, settings", [("laplace", {}), ("student_t", {"output_df": 3.0})])
def test_the_nll_intervals_and_crps_are_the_models_output_familys(family, settings):
    """Errors 0.3 or -1.5, scale 1 (normalised), 10 units a normalised unit."""
    model = FamilyForecaster(0.0, family, **settings)
    data = batches()
    errors = torch.tensor([0.3, -1.5]).repeat(3, 4, 5, 1)
    for i, batch in enumerate(data):
        batch.set(ORACLE, batch.get(keys.TARGET) + errors[i])
    metrics = evaluate_forecasts(model, data, denormalize=lambda t: t * 10.0)
    found = output_distribution(family, **settings)
    values, loc, scale = torch.tensor([0.3, -1.5]), torch.zeros(2), torch.ones(2)
    assert metrics["nll"] == pytest.approx(5 * float(found.nll(values, loc, scale).sum()), rel=1e-5)
    assert metrics["crps"] == pytest.approx(float(found.crps(values, loc, scale).mean()), rel=1e-5)
    # |0.3| is inside every central 50% interval of these families, |-1.5| outside; both inside the 90% ones.
    assert found.half_width(0.5) > 0.3 and found.half_width(0.5) < 1.5 < found.half_width(0.9)
    assert metrics["coverage_50"] == 0.5 and metrics["coverage_90"] == 1.0
    assert metrics["width_90"] == pytest.approx(2 * found.half_width(0.9) * 10.0, rel=1e-5)
    assert found.half_width(0.9) != pytest.approx(1.6449, rel=1e-2)  # not the Gaussian's
