import pytest
import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.eval.metrics import constant_velocity, displacement_errors, evaluate_forecasts
from mmf_rl.eval.report import markdown_table


class FixedForecaster(torch.nn.Module):
    """Forecasts target + offset; its K samples are target + k * spread (sample 0 is exact)."""

    def __init__(self, offset: float, spread: float = 1.0):
        super().__init__()
        self.offset, self.spread = offset, spread

    def forward(self, td):
        td.set(keys.FORECAST_LOC, td.get(keys.TARGET) + self.offset)
        td.set(keys.FORECAST_SCALE, torch.ones_like(td.get(keys.TARGET)))
        return td

    def sample(self, td, num_samples):
        ks = torch.arange(num_samples, dtype=torch.float32).view(1, -1, 1, 1) * self.spread
        td.set(keys.FORECAST_SAMPLES, td.get(keys.TARGET)[:, None] + ks)
        return td


def batches(n=3, b=4, t=5):
    g = torch.Generator().manual_seed(0)
    out = []
    for _ in range(n):
        target = torch.randn(b, t, 2, generator=g)
        past = torch.cumsum(torch.ones(b, 3, 2), 1)  # moves +1 per step in both dims
        out.append(TensorDict({keys.TARGET: target, keys.TARGET_PAST: past}, batch_size=[b]))
    return out


def test_displacement_errors_are_euclidean():
    forecast = torch.zeros(1, 3, 2)
    target = torch.tensor([[[3.0, 4.0], [0.0, 0.0], [6.0, 8.0]]])
    ade, fde = displacement_errors(forecast, target)
    assert ade.item() == pytest.approx(5.0) and fde.item() == pytest.approx(10.0)


def test_constant_velocity_extrapolates_the_last_step():
    past = torch.tensor([[[0.0, 0.0], [1.0, 2.0]]])
    torch.testing.assert_close(constant_velocity(past, 3), torch.tensor([[[2.0, 4.0], [3.0, 6.0], [4.0, 8.0]]]))


def test_metrics_in_normalised_frame_and_units():
    scale = 10.0
    metrics = evaluate_forecasts(FixedForecaster(offset=0.3), batches(), denormalize=lambda t: t * scale,
                                 num_samples=4, with_baseline=True)
    assert metrics["windows"] == 12
    assert metrics["mse"] == pytest.approx(0.09, rel=1e-5)
    assert metrics["mse_units"] == pytest.approx(9.0, rel=1e-5)
    assert metrics["ade"] == pytest.approx(0.3 * 2**0.5 * scale, rel=1e-5)
    assert metrics["ade_best_of_k"] == pytest.approx(0.0, abs=1e-5)  # sample 0 is exact
    assert metrics["nll"] == pytest.approx(10 * (0.5 * 0.09 + 0.5 * torch.log(torch.tensor(2 * torch.pi)).item()), rel=1e-5)
    assert metrics["cv_mse"] > 0


def test_baseline_needs_target_past():
    data = [b.exclude(keys.TARGET_PAST) for b in batches()]
    with pytest.raises(KeyError, match="include_target_past"):
        evaluate_forecasts(FixedForecaster(0.0), data, denormalize=lambda t: t, with_baseline=True)


def test_no_windows_gives_no_metrics():
    assert evaluate_forecasts(FixedForecaster(0.0), [], denormalize=lambda t: t) == {}


def test_markdown_table_rows_and_degradation():
    results = {"all": {"windows": 10, "mse": 0.1, "degradation": 0.0}, "without_image": {"windows": 10, "mse": 0.15, "degradation": 0.5}}
    table = markdown_table(results, {"windows": 10, "mse": 0.4}, units="metres")
    lines = table.splitlines()
    assert lines[0] == "| subset | windows | MSE (norm.) | MSE vs all |"
    assert lines[3] == "| without_image | 10 | 0.1500 | +50.0% |"
    assert lines[4] == "| constant velocity | 10 | 0.4000 |  |"
