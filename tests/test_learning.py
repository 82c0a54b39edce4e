"""A short CPU training run on a task whose future needs several modalities (fixed seeds)."""

import pytest
import torch

from mmf_rl import keys
from mmf_rl.models import ForecasterConfig, MultimodalForecaster
from mmf_rl.objectives import CombinedLoss, ELBOLoss, MissingModalityLoss
from tests.conftest import SYNTH_DT, SYNTH_MODALITIES

pytestmark = pytest.mark.slow  # two models trained for STEPS steps

# At 100 steps (200 before) the margins stay wide: the loss falls by 17-24 (> 5), the MSE is 0.07-0.09
# of constant velocity's (< 0.5), with L_mis 0.09-0.10 of the MSE without it (< 0.7).
STEPS = 100
BATCH = 128


def train(task, use_missing_modality_loss: bool):
    torch.manual_seed(0)
    config = ForecasterConfig(
        modalities=SYNTH_MODALITIES,
        history=8,
        horizon=8,
        target_dim=2,
        d_model=32,
        d_latent=4,
        num_heads=2,
        mlp_hidden=64,
        head_hidden=64,
    )
    model = MultimodalForecaster(config)
    losses = [ELBOLoss(model)] + ([MissingModalityLoss(model)] if use_missing_modality_loss else [])
    loss = CombinedLoss(*losses)
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    history = []
    for _ in range(STEPS):
        batch = task["train"][torch.randint(0, task["train"].shape[0], (BATCH,))]
        terms = loss(batch)
        total = sum(v for k, v in terms.items() if k.startswith("loss_"))
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
        history.append(terms["loss_nll"].item())
    return model.eval(), history


def forecast_mse(model, test, missing: str | None = None) -> float:
    td = test.clone()
    if missing is not None:
        td.set(keys.present_key(missing), torch.zeros(td.shape[0], dtype=torch.bool))
    with torch.no_grad():
        return float(((model(td).get(keys.FORECAST_LOC) - td.get(keys.TARGET)) ** 2).mean())


def constant_velocity_mse(test) -> float:
    past = test.get(keys.TARGET_PAST)
    velocity = (past[:, -1] - past[:, -2]) / SYNTH_DT
    steps = torch.arange(1, test.get(keys.TARGET).shape[1] + 1) * SYNTH_DT
    forecast = past[:, -1:] + velocity[:, None] * steps[None, :, None]
    return float(((forecast - test.get(keys.TARGET)) ** 2).mean())


@pytest.fixture(scope="module")
def trained(synthetic_task):
    return {use: train(synthetic_task, use) for use in (False, True)}


def test_loss_falls(trained):
    for _, history in trained.values():
        assert sum(history[-20:]) / 20 < sum(history[:20]) / 20 - 5.0


def test_forecasts_beat_constant_velocity(trained, synthetic_task):
    baseline = constant_velocity_mse(synthetic_task["test"])
    for model, _ in trained.values():
        assert forecast_mse(model, synthetic_task["test"]) < 0.5 * baseline


@pytest.mark.parametrize("missing", ["vel", "force"])
def test_missing_modality_loss_makes_forecasts_robust(trained, synthetic_task, missing):
    without_mis = forecast_mse(trained[False][0], synthetic_task["test"], missing)
    with_mis = forecast_mse(trained[True][0], synthetic_task["test"], missing)
    assert with_mis < 0.7 * without_mis
