"""Degenerate batches for the forecaster and every baseline: empty, one sample, a modality in one row.

The rule (mmf_rl.keys): an empty batch is a clear error (a loss or metric over zero samples has
no value; the RL glue never calls a model on zero rows), never a reshape error from inside torch.
"""

import pytest
import torch

from mmf_rl import keys
from mmf_rl.models import build_loss
from mmf_rl.objectives import LossConfig
from tests.conftest import HORIZON, TARGET_DIM, make_batch
from tests.reliability.test_nonfinite_inputs import MODEL_CONFIGS, small_model

LOSS_CONFIG = LossConfig(kl_weight=1.0, kl_warmup_steps=0, missing_modality_weight=1.0)


@pytest.mark.parametrize("name", sorted(MODEL_CONFIGS))
def test_an_empty_batch_is_a_clear_error(name):
    model = small_model(name)
    for mode in ("train", "eval"):
        getattr(model, mode)()
        for call in (model, lambda td: model.sample(td, 3)):
            with pytest.raises(ValueError, match=r"empty batch \(batch size 0\).*skip empty batches"):
                call(make_batch(0))


@pytest.mark.parametrize("name", sorted(MODEL_CONFIGS))
def test_a_single_sample_trains_and_forecasts(name):
    model = small_model(name).train()
    loss = build_loss(name, model, LOSS_CONFIG)
    losses = loss(make_batch(1))
    total = sum(v for k, v in losses.items() if k.startswith("loss_"))
    assert torch.isfinite(total)
    total.backward()
    model.eval()
    with torch.no_grad():
        out = model(make_batch(1))
        samples = model.sample(make_batch(1), 3)
    assert out.get(keys.FORECAST_LOC).shape == (1, HORIZON, TARGET_DIM)
    assert samples.get(keys.FORECAST_SAMPLES).shape == (1, 3, HORIZON, TARGET_DIM)
    assert (
        torch.isfinite(out.get(keys.FORECAST_LOC)).all()
        and torch.isfinite(samples.get(keys.FORECAST_SAMPLES)).all()
    )


@pytest.mark.parametrize("name", sorted(MODEL_CONFIGS))
def test_a_modality_present_in_exactly_one_row(name):
    only_row = 2
    present = {"image": torch.arange(5) == only_row}
    model = small_model(name).train()
    loss = build_loss(name, model, LOSS_CONFIG)
    total = sum(v for k, v in loss(make_batch(5, present=present)).items() if k.startswith("loss_"))
    assert torch.isfinite(total)
    total.backward()
    model.eval()
    with torch.no_grad():
        out = model(make_batch(5, present=present))
        # Each row is forecast as it would be alone: batching rows of different presence changes nothing.
        alone = [model(make_batch(5, present=present)[i : i + 1]).get(keys.FORECAST_LOC) for i in range(5)]
    assert torch.isfinite(out.get(keys.FORECAST_LOC)).all()
    torch.testing.assert_close(out.get(keys.FORECAST_LOC), torch.cat(alone), rtol=1e-4, atol=1e-5)
